"""
Fuzzing balance_node and teleop_node with hypothesis: 10,000 generated cases per input.

Messages (Imu, JointState, TwistStamped) and parameter values go straight into balance_node's
subscription callbacks, ``set_parameters`` and one control tick (``fault_suite.Bench``: the
node with its control thread stopped, no DDS round trip, about 40 us per tick); Joy samples go
into teleop_node's callback and timer tick. Every case asserts that no exception escapes, that
every torque frame sent decodes (MitProtocol, as the motor firmware does) to a finite torque
within max_wheel_torque, and the reaction where one is required (a non-finite pitch, pitch rate,
wheel velocity or leg angle: FAULT and zero torque at that very tick).

Marked ``slow`` (about a minute for the file on 2 cores); nothing deselects it, so it runs in
``colcon test``.
"""
import math
import os

from hypothesis import given, HealthCheck, settings, strategies as st
import pytest
from rclpy.exceptions import ParameterNotDeclaredException
from rclpy.parameter import Parameter
from sensor_msgs.msg import Joy

from wheelleg_balance.core.estimation import pitch_from_quaternion
from wheelleg_balance.core.protocols.mit import MitCommand
from wheelleg_balance.nodes.params import SPECS
from wheelleg_balance.nodes.teleop_node import TeleopNode
from wheelleg_balance.tools import fault_suite as fs

pytestmark = [pytest.mark.ros, pytest.mark.slow]

# WHEELLEG_FUZZ_EXAMPLES lowers the count for a quick local run; the default is the real one.
FUZZ = settings(max_examples=int(os.environ.get('WHEELLEG_FUZZ_EXAMPLES', 10_000)),
                deadline=None, database=None, suppress_health_check=list(HealthCheck))
MAX_TORQUE = 12.0   # max_wheel_torque default [N m]
NAN = math.nan

any_float = st.floats(allow_nan=True, allow_infinity=True)
# Mostly near the nominal range, often anything at all: both the normal paths and the guards.
small = st.floats(-2.0, 2.0)


# ``context`` (and ROS isolation) comes from conftest.py.
@pytest.fixture(scope='module')
def bench(context):
    with fs.Bench(context) as b:
        yield b


@pytest.fixture(scope='module')
def leg_bench(context):
    with fs.Bench(context, **fs.LEG_PARAMS) as b:
        yield b


def check_frames(frames, limit=MAX_TORQUE):
    """Every frame a well-formed MIT frame; torques finite and within ``limit``."""
    for motor_id, frame in frames:
        assert motor_id in fs.MOTOR_IDS
        assert frame in ('enter', 'exit') or isinstance(frame, MitCommand), frame
        if isinstance(frame, MitCommand):
            assert frame.kp == 0.0 and frame.kd == 0.0, frame
            assert math.isfinite(frame.torque) and abs(frame.torque) <= limit + fs.TORQUE_LSB


def check_state(b, limit=MAX_TORQUE):
    for tau in b.wheel_torques():
        assert math.isfinite(tau) and abs(tau) <= limit


def assert_fault_now(b, frames):
    assert b.mode == fs.MODE['FAULT']
    assert frames and all(fs.is_zero_torque(f) for _, f in frames), frames


NOMINAL_IMU = fs.make_imu(0.0)
NOMINAL_JOINTS = fs.make_joints()
NOMINAL_LEG_JOINTS = fs.make_joints(legs=fs.NOMINAL_LEGS)


def balancing(b, legs=False):
    """
    Make sure the node balances: re-arm only after a case ended in FAULT.

    Cases otherwise follow each other on one running node, as samples do on the robot (and a
    fresh arm per case would double the time per case).
    """
    if b.mode != fs.MODE['BALANCING']:
        b.feed(NOMINAL_IMU, NOMINAL_LEG_JOINTS if legs else NOMINAL_JOINTS)
        b.rearm()


# ------------------------------------------------------------------------------------ Imu

# Strategies are built once: building them inside a composite costs more than the node's tick.
IMU_EDITS = st.dictionaries(st.sampled_from(fs.IMU_FIELDS), any_float, max_size=6)
PITCH = st.floats(-1.6, 1.6)


@st.composite
def imu_messages(draw):
    """Draw a pitch anywhere, then set up to six fields to anything at all."""
    msg = fs.make_imu(draw(PITCH), draw(small))
    for path, value in draw(IMU_EDITS).items():
        fs.set_field(msg, path, value)
    return msg


@FUZZ
@given(msg=imu_messages())
def test_fuzz_imu(bench, msg):
    balancing(bench)
    bench.node._on_imu(msg)
    bench.node._on_joint_states(NOMINAL_JOINTS)
    frames = bench.tick()
    check_frames(frames)
    check_state(bench)
    o = msg.orientation
    bad = (msg.orientation_covariance[0] == -1.0
           or not math.isfinite(pitch_from_quaternion(o.x, o.y, o.z, o.w))
           or not math.isfinite(msg.angular_velocity.y))
    if bad:
        assert_fault_now(bench, frames)


# ----------------------------------------------------------------------------- JointState

NAMES = list(fs.WHEEL_JOINTS) + list(fs.LEG_JOINTS) + ['caster_joint', '']


JOINT_NAMES = st.one_of(st.just(NAMES[:6]), st.permutations(NAMES[:6]),
                        st.lists(st.sampled_from(NAMES), max_size=8))
# Lists of exactly k values, for k = 0..9 (the length follows the names, sometimes one short).
POSITIONS = [st.lists(st.one_of(small, any_float), min_size=k, max_size=k) for k in range(10)]
ANY_VALUES = [st.lists(any_float, min_size=k, max_size=k) for k in range(10)]
SHORT = st.booleans()


@st.composite
def joint_messages(draw):
    """Our six joints in order, shuffled, or any list of names (repeats, strangers, missing)."""
    names = draw(JOINT_NAMES)
    n = len(names)

    def size():
        return max(0, n - 1) if draw(SHORT) else n
    return fs.JointState(name=list(names), position=draw(POSITIONS[size()]),
                         velocity=draw(ANY_VALUES[size()]), effort=draw(ANY_VALUES[size()]))


def _first(names, values, joint):
    """Return the value at the joint's first occurrence (what the node reads), or None."""
    if joint not in names:
        return None
    i = names.index(joint)
    return values[i] if i < len(values) else None


@FUZZ
@given(msg=joint_messages())
def test_fuzz_joint_states(leg_bench, msg):
    b = leg_bench
    balancing(b, legs=True)
    b.node._on_imu(NOMINAL_IMU)
    b.node._on_joint_states(msg)
    frames = b.tick()
    check_frames(frames)
    check_state(b)
    names = list(msg.name)
    wheels = [_first(names, msg.velocity, j) for j in fs.WHEEL_JOINTS]
    legs = [_first(names, msg.position, j) for j in fs.LEG_JOINTS]
    if None not in wheels and not all(math.isfinite(w) for w in wheels):
        assert_fault_now(b, frames)
    if None not in legs and not all(math.isfinite(q) for q in legs):
        assert_fault_now(b, frames)


# --------------------------------------------------------------------------- TwistStamped

@st.composite
def cmd_messages(draw):
    msg = fs.TwistStamped()
    msg.header.stamp.sec = draw(st.integers(-2 ** 31, 2 ** 31 - 1))
    msg.header.stamp.nanosec = draw(st.integers(0, 2 ** 32 - 1))
    for path in fs.CMD_FIELDS:
        used = path in ('twist.linear.x', 'twist.angular.z')
        fs.set_field(msg, path, draw(st.one_of(small, any_float) if used else any_float))
    return msg


@FUZZ
@given(msg=cmd_messages())
def test_fuzz_cmd_vel(bench, msg):
    balancing(bench)
    rejected = bench.node.rejected_cmd_vel   # what diagnostics report as rejected_cmd_vel
    bench.feed(NOMINAL_IMU, NOMINAL_JOINTS)
    bench.node._on_cmd_vel(msg)
    frames = bench.tick()
    check_frames(frames)
    check_state(bench)
    assert bench.mode == fs.MODE['BALANCING']
    shaper = bench.node.shaper
    # reference.max_velocity 1 m/s, reference.max_yaw_rate 3 rad/s (defaults).
    assert math.isfinite(shaper.x_dot_ref) and abs(shaper.x_dot_ref) <= 1.0
    assert math.isfinite(shaper.yaw_rate_ref) and abs(shaper.yaw_rate_ref) <= 3.0
    dropped = not (math.isfinite(msg.twist.linear.x) and math.isfinite(msg.twist.angular.z))
    assert bench.node.rejected_cmd_vel - rejected == int(dropped)


# ------------------------------------------------------------------------------------ Joy

@pytest.fixture(scope='module')
def teleop(context):
    node = TeleopNode(context=context, namespace=fs.unique_namespace())
    node._pub = fs.Captured()   # capture cmd_vel instead of publishing it
    yield node
    node.destroy_node()


@FUZZ
@given(axes=st.lists(st.one_of(small, any_float), max_size=8),
       buttons=st.lists(st.one_of(st.integers(0, 1), st.integers(-2 ** 31, 2 ** 31 - 1)),
                        max_size=12))
def test_fuzz_joy(teleop, axes, buttons):
    joy = Joy()
    joy.axes = axes
    joy.buttons = buttons
    del teleop._pub.msgs[:]
    teleop._on_joy(joy)
    teleop._tick()
    cfg = teleop._teleop.cfg
    x_max = max(abs(cfg.scale_linear_x), abs(cfg.scale_linear_turbo_x))
    w_max = max(abs(cfg.scale_angular_yaw), abs(cfg.scale_angular_turbo_yaw))
    for msg in teleop._pub.msgs:
        x, w = msg.twist.linear.x, msg.twist.angular.z
        assert math.isfinite(x) and abs(x) <= x_max
        assert math.isfinite(w) and abs(w) <= w_max


# ----------------------------------------------------------------------------- parameters

PARAM_NAMES = [s.name for s in SPECS]
param_values = st.one_of(
    any_float, small, st.integers(-2 ** 63, 2 ** 63 - 1), st.integers(-3, 3), st.booleans(),
    st.text(max_size=6), st.sampled_from(['ida_pbc', 'output_regulation', 'lqr', 'mit']),
    st.lists(any_float, min_size=1, max_size=6), st.lists(st.integers(-2, 2), min_size=1,
                                                          max_size=6))


@FUZZ
@given(name=st.one_of(st.sampled_from(PARAM_NAMES), st.just('no_such_parameter')),
       value=param_values)
def test_fuzz_parameters(bench, name, value):
    node = bench.node
    balancing(bench)
    try:
        before = node.get_parameter(name).value
    except ParameterNotDeclaredException:
        before = None
    try:
        (result,) = node.set_parameters([Parameter(name, value=value)])
    except ParameterNotDeclaredException:
        assert before is None   # rclpy refuses undeclared names: nothing to check in the node
        return
    if not result.successful:
        assert result.reason
        assert node.get_parameter(name).value == before
        return
    try:
        limit = node.get_parameter('max_wheel_torque').value
        frames = bench.tick()   # the change is applied here
        check_frames(frames, limit)
        check_state(bench, limit)
        # No accepted value switches the guards off: a NaN pitch and a fall still fault.
        bench.feed(fs.make_imu(NAN))
        assert_fault_now(bench, bench.tick())
        fall = node.get_parameter('fall_angle').value + 0.05
        if fall < 0.5 * math.pi - 0.01:
            balancing(bench)
            bench.feed(fs.make_imu(fall))
            assert_fault_now(bench, bench.tick())
    finally:
        (restored,) = node.set_parameters([Parameter(name, value=before)])
        assert restored.successful, restored.reason
        bench.tick()
