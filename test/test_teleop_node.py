"""
teleop_node end to end: real rclpy and DDS on localhost; plus its config files and launch file.

In-process tests run teleop_node and a tester node (Joy publisher, cmd_vel subscriber, parameter
service client) in a MultiThreadedExecutor on a background thread, each test with its own
context. The signal tests run the node as its own process (`python -m
wheelleg_balance.nodes.teleop_node`).
"""
import ast
import math
import os
import pathlib
import py_compile
import signal
import subprocess
import sys
import threading
import time

from geometry_msgs.msg import Twist, TwistStamped
import pytest
from rcl_interfaces.srv import SetParameters
import rclpy
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import Joy
from std_msgs.msg import Float64
from std_srvs.srv import SetBool

from wheelleg_balance.core.schema import from_flat, spec_by_name
from wheelleg_balance.nodes.teleop_node import TeleopNode, TeleopNodeConfig
# The polling helper of all the ROS tests (test/conftest.py says why it lives there).
from wheelleg_balance.validation.faults.rig import wait_for
import yaml  # after wheelleg_balance: google order sorts it as third party

REPO = pathlib.Path(__file__).resolve().parents[1]
CONFIGS = ('teleop_xbox.yaml', 'teleop_ps4.yaml')
ENABLE, TURBO = 9, 10   # the node's defaults (SDL LEFTSHOULDER, RIGHTSHOULDER)
AX_X, AX_YAW = 1, 2


def joy_msg(x=0.0, yaw=0.0, enable=False, turbo=False, held=()):
    msg = Joy()
    axes = [0.0] * 6
    axes[AX_X], axes[AX_YAW] = x, yaw
    buttons = [0] * 15
    buttons[ENABLE], buttons[TURBO] = int(enable), int(turbo)
    for b in held:
        buttons[b] = 1
    msg.axes, msg.buttons = axes, buttons
    return msg


class Operator(Node):
    """
    Publishes Joy at 20 Hz (a joystick driver's autorepeat), records cmd_vel and cmd_height.

    It also stands in for balance_node's ~/arm service and records the requests.
    """

    def __init__(self, context, stamped=True):
        super().__init__('teleop_tester', context=context)
        self.joy = None            # the sample to repeat; None: the joystick is silent
        self.joy_sent = []         # monotonic send times
        self.received = []         # (monotonic receipt time, linear.x, angular.z, msg)
        self._lock = threading.Lock()
        self.pub = self.create_publisher(Joy, 'joy', 10)
        self.create_subscription(TwistStamped if stamped else Twist, 'cmd_vel', self._on_cmd, 50)
        self.heights = []          # (monotonic receipt time, cmd_height [m])
        self.arm_requests = []     # (monotonic time, data)
        self.create_subscription(Float64, 'cmd_height', lambda m: self.heights.append(
            (time.monotonic(), m.data)), 10)
        self.create_service(SetBool, 'balance_node/arm', self._on_arm)
        self.create_timer(0.05, self._repeat)
        self.set_params = self.create_client(SetParameters, '/teleop_node/set_parameters')

    def _on_arm(self, request, response):
        self.arm_requests.append((time.monotonic(), request.data))
        response.success, response.message = True, 'ok'
        return response

    def _repeat(self):
        msg = self.joy
        if msg is not None:
            self.pub.publish(msg)
            self.joy_sent.append(time.monotonic())

    def _on_cmd(self, msg):
        twist = msg.twist if isinstance(msg, TwistStamped) else msg
        with self._lock:
            self.received.append((time.monotonic(), twist.linear.x, twist.angular.z, msg))

    def cmds(self, since=0.0):
        with self._lock:
            return [r for r in self.received if r[0] >= since]

    def set_parameter(self, name, value):
        """Call SetParameters as `ros2 param set` does; return the SetParametersResult."""
        assert self.set_params.wait_for_service(timeout_sec=5.0)
        msg = Parameter(name, value=value).to_parameter_msg()
        request = SetParameters.Request(parameters=[msg])
        future = self.set_params.call_async(request)
        assert wait_for(future.done, 5.0), 'no answer from /teleop_node/set_parameters'
        return future.result().results[0]


class Ros:
    """A context, teleop_node, the tester and a MultiThreadedExecutor spinning in a thread."""

    def __init__(self, overrides=None, stamped=True):
        self.context = Context()
        rclpy.init(context=self.context)
        params = dict(overrides or {})
        params.setdefault('publish_stamped_twist', stamped)
        self.teleop = TeleopNode(context=self.context, parameter_overrides=[
            Parameter(k, value=v) for k, v in params.items()])
        self.tester = Operator(self.context, stamped=stamped)
        self.executor = MultiThreadedExecutor(num_threads=3, context=self.context)
        self.executor.add_node(self.teleop)
        self.executor.add_node(self.tester)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        assert wait_for(lambda: self.tester.pub.get_subscription_count() > 0
                        and self.tester.count_publishers('cmd_vel') > 0, 10.0), 'no discovery'

    def close(self):
        self.executor.shutdown(timeout_sec=2.0)
        self.thread.join(timeout=2.0)
        self.teleop.destroy_node()
        self.tester.destroy_node()
        rclpy.shutdown(context=self.context)
        assert not self.thread.is_alive()


@pytest.fixture
def make_ros():
    """Start a Ros(**kwargs) for the test; always closed at teardown."""
    envs = []

    def make(**kwargs):
        envs.append(Ros(**kwargs))
        return envs[-1]
    yield make
    for env in envs:
        env.close()


def moving_then_released(tester, settle, release_wait=0.6):
    """Release the enable button; return (cmds before the zero, the zero, cmds after it)."""
    tester.joy = joy_msg(x=1.0, yaw=0.5)
    t_release = time.monotonic()
    assert wait_for(lambda: any(c[1] == 0.0 and c[2] == 0.0 for c in tester.cmds(t_release)),
                    2.0), 'no zero command after the release'
    time.sleep(release_wait)
    after = tester.cmds(settle)
    k = next(i for i, c in enumerate(after) if c[1] == 0.0 and c[2] == 0.0)
    return after[:k], after[k], after[k + 1:]


pytestmark = pytest.mark.ros


def test_enable_button_ramps_cmd_vel_at_the_publish_rate_then_one_zero(make_ros):
    tester = make_ros(overrides={'frame': 'test_base', 'max_linear_accel': 2.0,
                                 'max_angular_accel': 10.0, 'joy_timeout': 2.0}).tester
    tester.joy = joy_msg(x=1.0, yaw=0.5)                  # stick held, no button: no motion
    time.sleep(0.3)
    assert all(c[1] == 0.0 and c[2] == 0.0 for c in tester.cmds()), 'moved without enable'
    t0 = time.monotonic()
    tester.joy = joy_msg(x=1.0, yaw=0.5, enable=True)
    # scale_linear.x 0.5 m/s at 2 m/s^2: 0.25 s of ramp; scale_angular.yaw 1.5 * 0.5 rad/s.
    assert wait_for(lambda: any(c[1] == 0.5 for c in tester.cmds(t0)), 3.0)
    time.sleep(1.0)
    moving, zero, after = moving_then_released(tester, t0)
    xs = [c[1] for c in moving if c[1] > 0.0]
    stamps = [c[3].header.stamp.sec + 1e-9 * c[3].header.stamp.nanosec for c in moving
              if c[1] > 0.0]
    assert all(c[3].header.frame_id == 'test_base' for c in moving + [zero])
    assert stamps[0] > 1e9 and all(b > a for a, b in zip(stamps, stamps[1:]))
    # A ramp, not a step: each increment within 2 m/s^2 times the stamp interval (+ 1 tick of
    # scheduling slack), never above the scale.
    assert xs[0] < 0.5 and max(xs) == 0.5
    for (x0, s0), (x1, s1) in zip(zip(xs, stamps), zip(xs[1:], stamps[1:])):
        assert 0.0 <= x1 - x0 <= 2.0 * (s1 - s0) + 2.0 * 0.02 + 1e-9
    # Yaw: half deflection through the default 0.1 deadzone (rescaled), scale 1.5 rad/s.
    assert [c[2] for c in moving][-1] == pytest.approx(1.5 * (0.5 - 0.1) / (1.0 - 0.1))
    # 50 Hz while enabled.
    rate = (len(stamps) - 1) / (stamps[-1] - stamps[0])
    assert 35.0 <= rate <= 60.0, rate
    # Exactly one zero, then silence while released.
    assert after == []


def test_silent_joystick_gives_one_zero_after_the_timeout(make_ros):
    tester = make_ros(overrides={'joy_timeout': 0.3}).tester
    tester.joy = joy_msg(x=1.0, enable=True)
    assert wait_for(lambda: any(c[1] > 0.0 for c in tester.cmds()), 3.0)
    time.sleep(0.3)
    tester.joy = None                                      # the link drops
    time.sleep(0.06)
    t_last_joy = tester.joy_sent[-1]
    assert wait_for(lambda: any(c[1] == 0.0 for c in tester.cmds(t_last_joy)), 2.0)
    time.sleep(0.5)
    after = tester.cmds(t_last_joy)
    zeros = [c for c in after if c[1] == 0.0 and c[2] == 0.0]
    assert len(zeros) == 1 and zeros[0] is after[-1]
    # The zero comes joy_timeout after the last sample (plus delivery and one tick).
    assert 0.25 <= zeros[0][0] - t_last_joy <= 0.3 + 0.25


def test_parameters_through_the_set_parameters_service(make_ros):
    ros = make_ros()
    tester, teleop = ros.tester, ros.teleop
    ok = tester.set_parameter('scale_linear.x', 0.8)
    assert ok.successful, ok.reason
    assert teleop.get_parameter('scale_linear.x').value == 0.8
    tester.joy = joy_msg(x=1.0, enable=True)
    assert wait_for(lambda: any(c[1] == 0.8 for c in tester.cmds()), 3.0), 'change not applied'
    # Refused, each with a reason, and nothing changes.
    refused = {
        'deadzone': 1.5,                 # out of the descriptor's range
        'enable_turbo_button': ENABLE,   # same as the enable button: turbo always on
        'joy_timeout': -1.0,
        'publish_rate': 10.0,            # read-only
        'scale_angular.yaw': 'fast',     # wrong type
    }
    for name, value in refused.items():
        before = teleop.get_parameter(name).value
        result = tester.set_parameter(name, value)
        assert not result.successful, name
        assert result.reason.strip(), name
        assert teleop.get_parameter(name).value == before, name
    assert 'turbo' in tester.set_parameter('enable_turbo_button', ENABLE).reason
    assert teleop.teleop.cfg.enable_turbo_button == TURBO


def test_plain_twist_when_not_stamped(make_ros):
    tester = make_ros(stamped=False).tester
    tester.joy = joy_msg(yaw=-1.0, turbo=True)
    # Turbo yaw scale: -2.88 rad/s (right turn), reached at 6 rad/s^2 in about 0.5 s.
    assert wait_for(lambda: any(c[2] == pytest.approx(-2.88) for c in tester.cmds()), 3.0)
    assert all(isinstance(c[3], Twist) for c in tester.cmds())


def test_pad_sets_the_height_and_arms_and_disarms_with_the_deadman(make_ros):
    tester = make_ros().tester
    # The Xbox layout (the defaults): Y (3) 0.70 m, X (2) 0.52 m; START (6) arms, BACK (4)
    # disarms, each with LB (9) held for 0.5 s.
    tester.joy = joy_msg(held=(3, 6))                   # no deadman: nothing
    time.sleep(1.0)
    assert tester.heights == [] and tester.arm_requests == []
    tester.joy = joy_msg(enable=True)
    time.sleep(0.2)
    tester.joy = joy_msg(enable=True, held=(3,))
    assert wait_for(lambda: tester.heights, 3.0), 'no cmd_height'
    time.sleep(0.3)
    assert [h for _, h in tester.heights] == [0.70]     # once per press
    tester.joy = joy_msg(enable=True, held=(6,))
    t0 = time.monotonic()
    assert wait_for(lambda: tester.arm_requests, 3.0), 'no arm request'
    assert tester.arm_requests[0][0] - t0 >= 0.45        # held 0.5 s first
    time.sleep(0.8)
    tester.joy = joy_msg(enable=True, held=(4,))
    assert wait_for(lambda: len(tester.arm_requests) > 1, 3.0), 'no disarm request'
    time.sleep(0.8)
    assert [d for _, d in tester.arm_requests] == [True, False]
    # Releasing the deadman while driving still stops cmd_vel with one zero.
    tester.joy = joy_msg(x=1.0, enable=True)
    assert wait_for(lambda: any(c[1] > 0.0 for c in tester.cmds()), 3.0)
    t_release = time.monotonic()
    tester.joy = joy_msg(x=1.0)
    assert wait_for(lambda: any(c[1] == 0.0 for c in tester.cmds(t_release)), 2.0)


# --- the process: SIGINT / SIGTERM ---------------------------------------------------------

@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_signal_stops_the_robot_and_exits_cleanly(sig):
    context = Context()
    rclpy.init(context=context)
    tester = Operator(context)
    executor = MultiThreadedExecutor(num_threads=2, context=context)
    executor.add_node(tester)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO)] + sys.path))
    proc = subprocess.Popen([sys.executable, '-m', 'wheelleg_balance.nodes.teleop_node'],
                            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        tester.joy = joy_msg(x=1.0, enable=True)
        assert wait_for(lambda: any(c[1] > 0.0 for c in tester.cmds()), 15.0), 'no cmd_vel'
        tester.joy = joy_msg(x=1.0, enable=True)
        t_sig = time.monotonic()
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=10.0)
        assert proc.returncode == 0, err
        assert 'Traceback' not in err, err
        # The last word is the one zero command (teleop_twist_joy does the same on exit).
        assert wait_for(lambda: any(c[1] == 0.0 for c in tester.cmds(t_sig)), 2.0), err
        assert tester.cmds()[-1][1:3] == (0.0, 0.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        executor.shutdown(timeout_sec=2.0)
        thread.join(timeout=2.0)
        tester.destroy_node()
        rclpy.shutdown(context=context)


# --- config files and launch file ----------------------------------------------------------

@pytest.mark.parametrize('name', CONFIGS)
def test_config_file_is_accepted_by_the_node(name):
    doc = yaml.safe_load((REPO / 'config' / name).read_text())
    values = doc['teleop_node']['ros__parameters']
    # Every key is a parameter of the node (a typo would be silently ignored by rclpy) ...
    context = Context()
    rclpy.init(context=context)
    try:
        node = TeleopNode(context=context, parameter_overrides=[
            Parameter(k, value=v) for k, v in values.items()])
        try:
            declared = set(spec_by_name(TeleopNodeConfig))
            assert set(values) <= declared, set(values) - declared
            assert all(node.has_parameter(name) for name in declared)
            # ... and its type and range are accepted (the constructor raises otherwise).
            assert node.teleop.cfg == from_flat(TeleopNodeConfig, values).teleop
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
    # The paper's figures: top speed 1 m/s, rotation at 165 deg/s with turbo.
    assert abs(values['scale_linear_turbo.x']) <= 1.0
    assert values['scale_angular_turbo.yaw'] == pytest.approx(math.radians(165.0), abs=0.01)
    # The driver must repeat a held stick faster than the teleop timeout.
    driver = doc['game_controller_node']['ros__parameters']
    assert driver['autorepeat_rate'] > 1.0 / values['joy_timeout']


def test_launch_file_compiles_and_references_installed_files():
    path = REPO / 'launch' / 'robot.launch.py'
    py_compile.compile(str(path), doraise=True)
    tree = ast.parse(path.read_text())
    strings = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant)
               and isinstance(n.value, str)}
    assert 'generate_launch_description' in {n.name for n in ast.walk(tree)
                                             if isinstance(n, ast.FunctionDef)}
    # Config files: balance.yaml by name, teleop_<joystick>.yaml for every choice.
    assert 'balance.yaml' in strings and (REPO / 'config' / 'balance.yaml').is_file()
    choices = next(ast.literal_eval(n.value) for n in ast.walk(tree)
                   if isinstance(n, ast.Assign) and n.targets[0].id == 'JOYSTICKS')
    assert set(choices) == {'xbox', 'ps4'}
    for joystick in choices:
        assert (REPO / 'config' / ('teleop_%s.yaml' % joystick)).is_file()
    # Executables: ours are console scripts of setup.py; the driver is joy's SDL mapping one.
    setup = (REPO / 'setup.py').read_text()
    for exe in ('teleop_node', 'balance_node'):
        assert exe in strings and "'%s = " % exe in setup
    assert {'joy', 'game_controller_node', 'wheelleg_balance'} <= strings
    # Files are installed: setup.py ships config/*.yaml and launch/*.launch.py to share/.
    assert "glob('config/*.yaml')" in setup and "glob('launch/*.launch.py')" in setup
    _check_discovery_stays_on_the_robot(tree)


def _check_discovery_stays_on_the_robot(tree):
    """robot.launch.py: ROS_AUTOMATIC_DISCOVERY_RANGE LOCALHOST unless told, static peers."""
    def name(call):
        return getattr(call.func, 'id', getattr(call.func, 'attr', ''))

    def literal(node):
        return ast.literal_eval(node) if isinstance(node, ast.Constant) else None

    actions = next(n.args[0].elts for n in ast.walk(tree) if isinstance(n, ast.Call)
                   and name(n) == 'LaunchDescription')
    calls = [a for a in actions if isinstance(a, ast.Call)]
    arguments = {literal(c.args[0]): c for c in calls if name(c) == 'DeclareLaunchArgument'}
    settings = {literal(c.args[0]): c.args[1] for c in calls
                if name(c) == 'SetEnvironmentVariable'}
    first_node = min(i for i, c in enumerate(calls) if name(c) == 'Node')
    ranges = next(ast.literal_eval(n.value) for n in ast.walk(tree)
                  if isinstance(n, ast.Assign) and n.targets[0].id == 'DISCOVERY_RANGES')
    assert set(ranges) == {'LOCALHOST', 'SUBNET', 'SYSTEM_DEFAULT', 'OFF'}   # rcl, Jazzy
    for variable, argument, default in (('ROS_AUTOMATIC_DISCOVERY_RANGE', 'discovery_range',
                                         'LOCALHOST'),
                                        ('ROS_STATIC_PEERS', 'static_peers', '')):
        # The variable is the launch argument's value, set before any node starts ...
        value = settings[variable]
        assert name(value) == 'LaunchConfiguration' and literal(value.args[0]) == argument
        assert calls.index(arguments[argument]) < first_node
        assert max(i for i, c in enumerate(calls) if name(c) == 'SetEnvironmentVariable' and
                   literal(c.args[0]) == variable) < first_node
        # ... whose default is the caller's variable, else the robot's default.
        kwargs = {k.arg: k.value for k in arguments[argument].keywords}
        env = kwargs['default_value']
        assert name(env) == 'EnvironmentVariable' and literal(env.args[0]) == variable
        assert {k.arg: literal(k.value) for k in env.keywords} == {'default_value': default}
    choices = {k.arg: k.value for k in arguments['discovery_range'].keywords}['choices']
    assert ast.unparse(choices) == 'list(DISCOVERY_RANGES)'
