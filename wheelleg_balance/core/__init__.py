"""The math core: no rclpy, no python-can. See docs/architecture.md for the map to the paper."""
