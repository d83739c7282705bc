"""ROS 2 nodes: thin shells around wheelleg_balance.core."""
