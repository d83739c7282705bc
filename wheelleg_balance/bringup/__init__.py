"""
bringup: the checks of a robot on a stand before its first arm (docs/robot_setup.md).

The ``bringup`` command (cli.py) checks the CAN interface (iplink.py), finds every configured
motor and names the likely cause of one that does not answer, asks the builder to turn each
wheel forward and to move each leg to its stop and checks the directions and zero offsets
(motor_checks.py), checks the IMU against the tail rest and its mounting (imu_check.py), and
writes a filled balance_node config (robot_config.py). session.py runs the procedure on
python-can buses; every judgement is in the pure modules, tested on recorded data. It refuses
to run while a balance_node drives the bus. ``bringup --sim`` runs the same against sim_node,
whose hand (sim/hand.py) does what the builder's hands do (sim.py).
"""
