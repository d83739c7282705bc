"""
Bring up the real robot: joystick driver, teleop_node and balance_node.

    ros2 launch wheelleg_balance robot.launch.py joystick:=ps4

- ``game_controller_node`` (package joy): the pad through SDL2's game controller mapping, so
  the button and axis indices of config/teleop_<joystick>.yaml hold for any Xbox, PS4 or PS5 pad
  (the plain ``joy_node`` uses SDL's raw joystick API, whose order depends on pad and driver);
- ``teleop_node``: joy -> cmd_vel (TwistStamped), config/teleop_<joystick>.yaml;
- ``balance_node``: the balance loop, config/balance.yaml. It starts disarmed unless the file
  sets auto_arm: ``ros2 service call /balance_node/arm std_srvs/srv/SetBool "{data: true}"``.

All files come from share/wheelleg_balance/config of the installed package.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

JOYSTICKS = ('xbox', 'ps4')


def generate_launch_description():
    config = os.path.join(get_package_share_directory('wheelleg_balance'), 'config')
    joystick = LaunchConfiguration('joystick')
    # One file per pad holds the parameters of both the joystick driver and teleop_node. A list
    # of text and substitutions is concatenated by launch into one path.
    teleop_yaml = [os.path.join(config, 'teleop_'), joystick, '.yaml']
    return LaunchDescription([
        DeclareLaunchArgument('joystick', default_value='xbox', choices=list(JOYSTICKS),
                              description='pad layout: config/teleop_<joystick>.yaml '
                                          '(ps4 also covers PS5 pads)'),
        Node(package='joy', executable='game_controller_node', name='game_controller_node',
             parameters=[teleop_yaml], output='screen'),
        Node(package='wheelleg_balance', executable='teleop_node', name='teleop_node',
             parameters=[teleop_yaml], output='screen'),
        Node(package='wheelleg_balance', executable='balance_node', name='balance_node',
             parameters=[os.path.join(config, 'balance.yaml')], output='screen'),
    ])
