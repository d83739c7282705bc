"""
What the simulated robot is made of, without MuJoCo: its joints, leg modes, actuator limits.

robot.xml's names and ranges that code outside the simulator needs (sim/config.py checks
sim_node's parameters against them; robot_sim.py, which loads the model, re-exports them), so
that a configuration can be checked where MuJoCo is not installed.
"""

#: Torque range of the wheel motors' actuators [N m] (the MIT limit of the AK80-9 class).
WHEEL_TORQUE_LIMIT = 18.0
#: Torque range of the hip motors' actuators [N m] (AK80-9 class too; docs/legs.md).
HIP_TORQUE_LIMIT = 18.0
#: Leg modes of RobotSim: hip torque motors, or the transitional position servos.
LEG_MODES = ('motors', 'servo')
#: Hip joints, in the order of ``leg_angles()``: left front, left rear, right front, right rear.
LEG_JOINTS = ('left_leg_front_joint', 'left_leg_rear_joint',
              'right_leg_front_joint', 'right_leg_rear_joint')
WHEEL_JOINTS = ('left_wheel_joint', 'right_wheel_joint')
