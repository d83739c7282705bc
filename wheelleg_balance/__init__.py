"""
Balance control of a two-wheeled wheel-legged robot (ROS 2 Jazzy, Python).

Layout: ``core`` is the math (model, controllers, estimators, kinematics, CAN codecs) and imports
neither rclpy nor python-can; ``nodes`` are thin ROS 2 shells; ``sim`` is the MuJoCo robot;
``validation`` checks them apart from the product: ``paper`` (the paper's experiments,
``experiments`` and ``main_job``), ``faults`` (``fault_report``), ``bench`` (``benchmark``).
"""
