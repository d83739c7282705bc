"""
Balance control of a two-wheeled wheel-legged robot (ROS 2 Jazzy, Python).

Layout: ``core`` is the math (model, controllers, estimators, kinematics, CAN codecs) and imports
neither rclpy nor python-can; ``nodes`` are thin ROS 2 shells; ``tools`` are commands
(experiments, benchmark, main job, fault report); ``sim`` is the MuJoCo robot.
"""
