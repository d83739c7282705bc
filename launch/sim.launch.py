"""
Bring up the simulated robot: sim_node (MuJoCo), balance_node, and the pad through teleop_node.

    ros2 launch wheelleg_balance sim.launch.py joystick:=ps4

- ``sim_node``: the robot of config/sim.yaml, folded on its tail as after power-up, six MIT
  motors on a udp_multicast CAN bus of this machine;
- ``balance_node``: config/balance_sim.yaml, the same bus and wiring, the hips driven and
  ``auto_arm`` on: it homes the hips, raises the legs on the tail, stands up and balances;
- ``game_controller_node`` (package joy) and ``teleop_node`` with config/teleop_<joystick>.yaml:
  hold the deadman (LB / L1) to drive with the sticks, set the height with the face buttons
  (Y / triangle 0.70 m, X / square 0.52 m, A / cross 0.37 m) or the right stick's vertical
  axis, deadman + START / OPTIONS arms, deadman + BACK / SHARE disarms (the robot sits down).

DDS discovery stays on this machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) unless the caller
set it. All files come from share/wheelleg_balance of the installed package. The launch packages
are imported inside generate_launch_description, so the module imports where they are not
installed, as in the test suite's environment.
"""
import os

JOYSTICKS = ('xbox', 'ps4')


def generate_launch_description():
    from ament_index_python.packages import get_package_share_directory
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument, SetEnvironmentVariable
    from launch.substitutions import EnvironmentVariable, LaunchConfiguration
    from launch_ros.actions import Node

    config = os.path.join(get_package_share_directory('wheelleg_balance'), 'config')
    joystick = LaunchConfiguration('joystick')
    # One file per pad holds the parameters of both the joystick driver and teleop_node. A list
    # of text and substitutions is concatenated by launch into one path.
    teleop_yaml = [os.path.join(config, 'teleop_'), joystick, '.yaml']
    return LaunchDescription([
        DeclareLaunchArgument('joystick', default_value='xbox', choices=list(JOYSTICKS),
                              description='pad layout: config/teleop_<joystick>.yaml '
                                          '(ps4 also covers PS5 pads)'),
        SetEnvironmentVariable('ROS_AUTOMATIC_DISCOVERY_RANGE', EnvironmentVariable(
            'ROS_AUTOMATIC_DISCOVERY_RANGE', default_value='LOCALHOST')),
        Node(package='wheelleg_balance', executable='sim_node', name='sim_node',
             parameters=[os.path.join(config, 'sim.yaml')], output='screen'),
        Node(package='wheelleg_balance', executable='balance_node', name='balance_node',
             parameters=[os.path.join(config, 'balance_sim.yaml')], output='screen'),
        Node(package='joy', executable='game_controller_node', name='game_controller_node',
             parameters=[teleop_yaml], output='screen'),
        Node(package='wheelleg_balance', executable='teleop_node', name='teleop_node',
             parameters=[teleop_yaml], output='screen'),
    ])
