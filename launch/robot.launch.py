"""
Bring up the real robot: joystick driver, teleop_node and balance_node.

    ros2 launch wheelleg_balance robot.launch.py joystick:=ps4 params_file:=$HOME/robot.yaml

- ``game_controller_node`` (package joy): the pad through SDL2's game controller mapping, so
  the button and axis indices of config/teleop_<joystick>.yaml hold for any Xbox, PS4 or PS5 pad
  (the plain ``joy_node`` uses SDL's raw joystick API, whose order depends on pad and driver);
- ``teleop_node``: joy -> cmd_vel (TwistStamped), config/teleop_<joystick>.yaml;
- ``balance_node``: the balance loop, with ``params_file`` (default config/balance.yaml; the
  robot's own file is the one ``bringup`` writes, docs/robot_setup.md). It starts disarmed
  unless the file sets auto_arm:
  ``ros2 service call /balance_node/arm std_srvs/srv/SetBool "{data: true}"``;
- ``robot_state_publisher``: the TF of the robot's links from urdf/wheelleg_balance.urdf and the
  joint_states balance_node publishes (hips, wheels and the legs' passive knees).

DDS discovery stays on the robot: ``discovery_range`` (ROS_AUTOMATIC_DISCOVERY_RANGE of every
node started here) is the caller's ROS_AUTOMATIC_DISCOVERY_RANGE if set, else LOCALHOST;
``static_peers`` (ROS_STATIC_PEERS, ``;``-separated) is the caller's ROS_STATIC_PEERS, the
operator's station that may reach the robot all the same. Both are launch arguments:
``discovery_range:=SUBNET`` opens it again. SROS2 (docs/robot_setup.md, "SROS2") comes from the
environment the launch inherits (ROS_SECURITY_*), not from arguments.

All files come from share/wheelleg_balance of the installed package. The launch packages are
imported inside generate_launch_description, so the module imports (and its helpers run) where
they are not installed, as in the test suite's environment.
"""
import os

JOYSTICKS = ('xbox', 'ps4')
#: The values of ROS_AUTOMATIC_DISCOVERY_RANGE (Jazzy's rcl); this launch's default: LOCALHOST.
DISCOVERY_RANGES = ('LOCALHOST', 'SUBNET', 'SYSTEM_DEFAULT', 'OFF')
URDF_FILE = os.path.join('urdf', 'wheelleg_balance.urdf')


def robot_description(share):
    """Return the URDF text robot_state_publisher takes as robot_description."""
    with open(os.path.join(share, URDF_FILE)) as f:
        return f.read()


def generate_launch_description():
    from ament_index_python.packages import get_package_share_directory
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument, SetEnvironmentVariable
    from launch.substitutions import EnvironmentVariable, LaunchConfiguration
    from launch_ros.actions import Node

    share = get_package_share_directory('wheelleg_balance')
    config = os.path.join(share, 'config')
    joystick = LaunchConfiguration('joystick')
    # One file per pad holds the parameters of both the joystick driver and teleop_node. A list
    # of text and substitutions is concatenated by launch into one path.
    teleop_yaml = [os.path.join(config, 'teleop_'), joystick, '.yaml']
    return LaunchDescription([
        # Before any node: the environment is read when a process starts.
        DeclareLaunchArgument('discovery_range', default_value=EnvironmentVariable(
            'ROS_AUTOMATIC_DISCOVERY_RANGE', default_value='LOCALHOST'),
            choices=list(DISCOVERY_RANGES),
            description='ROS_AUTOMATIC_DISCOVERY_RANGE of the nodes (default: the '
                        "caller's, else LOCALHOST: discovery stays on the robot)"),
        SetEnvironmentVariable('ROS_AUTOMATIC_DISCOVERY_RANGE',
                               LaunchConfiguration('discovery_range')),
        DeclareLaunchArgument('static_peers', default_value=EnvironmentVariable(
            'ROS_STATIC_PEERS', default_value=''),
            description="ROS_STATIC_PEERS of the nodes: the operator's station, "
                        "';'-separated addresses (default: the caller's)"),
        SetEnvironmentVariable('ROS_STATIC_PEERS', LaunchConfiguration('static_peers')),
        DeclareLaunchArgument('joystick', default_value='xbox', choices=list(JOYSTICKS),
                              description='pad layout: config/teleop_<joystick>.yaml '
                                          '(ps4 also covers PS5 pads)'),
        Node(package='joy', executable='game_controller_node', name='game_controller_node',
             parameters=[teleop_yaml], output='screen'),
        Node(package='wheelleg_balance', executable='teleop_node', name='teleop_node',
             parameters=[teleop_yaml], output='screen'),
        DeclareLaunchArgument('params_file', default_value=os.path.join(config, 'balance.yaml'),
                              description="balance_node's parameters (the robot's file, as "
                                          '`bringup` writes it)'),
        Node(package='wheelleg_balance', executable='balance_node', name='balance_node',
             parameters=[LaunchConfiguration('params_file')], output='screen'),
        Node(package='robot_state_publisher', executable='robot_state_publisher',
             name='robot_state_publisher',
             parameters=[{'robot_description': robot_description(share)}], output='screen'),
    ])
