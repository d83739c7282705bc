"""
Fuzzing balance_node and teleop_node with hypothesis: 10,000 generated cases per input.

Messages (Imu, JointState, TwistStamped) go through balance_node's own reductions into the
control tick (``LoopBench``: core/balance_loop.py on a virtual clock, no DDS round trip); parameter
values go through rclpy's parameter machinery and balance_node's ParameterGuard on a node that
declares balance_node's parameters, then into the tick; Joy samples go through teleop's core as
teleop_node hands them over. Every case asserts that no exception escapes, that
every torque frame sent decodes (MitProtocol, as the motor firmware does) to a finite torque
within max_wheel_torque, and the reaction where one is required (a non-finite pitch, pitch rate,
wheel velocity or leg angle: FAULT and zero torque at that very tick).

Marked ``slow`` (about a minute for the file on 2 cores); nothing deselects it, so it runs in
``colcon test``.
"""
import math
import os

from geometry_msgs.msg import TwistStamped
from hypothesis import example, given, HealthCheck, settings, strategies as st
import pytest
from rclpy.exceptions import ParameterNotDeclaredException
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState, Joy

from wheelleg_balance.core.attitude import GRAVITY_NORM_TOLERANCE, QUATERNION_NORM_TOLERANCE
from wheelleg_balance.core.config import BalanceConfig
from wheelleg_balance.core.protocols.base import Frame
from wheelleg_balance.core.protocols.mit import MitCommand
from wheelleg_balance.core.schema import specs
from wheelleg_balance.core.teleop import Teleop, TeleopConfig
from wheelleg_balance.nodes.sensor_intake import imu_sample
from wheelleg_balance.validation.faults import bench as fb
from wheelleg_balance.validation.faults.doubles import MOTOR_IDS
from wheelleg_balance.validation.faults.matrices import CMD_FIELDS, IMU_FIELDS, set_field

pytestmark = [pytest.mark.ros, pytest.mark.slow]

# WHEELLEG_FUZZ_EXAMPLES lowers the count for a quick local run; the default is the real one.
FUZZ = settings(max_examples=int(os.environ.get('WHEELLEG_FUZZ_EXAMPLES', 10_000)),
                deadline=None, database=None, suppress_health_check=list(HealthCheck))
MAX_TORQUE = 12.0   # max_wheel_torque default [N m]
NAN = math.nan

any_float = st.floats(allow_nan=True, allow_infinity=True)
# Mostly near the nominal range, often anything at all: both the normal paths and the guards.
small = st.floats(-2.0, 2.0)


@pytest.fixture(scope='module')
def bench():
    return fb.LoopBench()


@pytest.fixture(scope='module')
def leg_bench():
    """Wheels and hips from another driver's joint states (what test_fuzz_joint_states feeds)."""
    return fb.LoopBench(wheel_state_source='joint_states', **fb.LEG_PARAMS)


def check_frames(frames, limit=MAX_TORQUE):
    """Every frame a well-formed MIT frame; torques finite and within ``limit``."""
    for motor_id, frame in frames:
        assert motor_id in MOTOR_IDS
        assert frame in ('enter', 'exit') or isinstance(frame, MitCommand), frame
        if isinstance(frame, MitCommand):
            assert frame.kp == 0.0 and frame.kd == 0.0, frame
            assert math.isfinite(frame.torque) and abs(frame.torque) <= limit + fb.TORQUE_LSB


def check_state(b, limit=MAX_TORQUE):
    for tau in b.wheel_torques():
        assert math.isfinite(tau) and abs(tau) <= limit


def assert_fault_now(b, frames):
    assert b.mode == fb.MODE['FAULT']
    assert frames and all(fb.is_zero_torque(f) for _, f in frames), frames


NOMINAL_IMU = fb.make_imu(0.0)
NOMINAL_JOINTS = fb.make_joints()
NOMINAL_LEG_JOINTS = fb.make_joints(legs=fb.NOMINAL_LEGS)


def balancing(b, legs=False):
    """
    Make sure the node balances: re-arm only after a case ended in FAULT.

    Cases otherwise follow each other on one running node, as samples do on the robot (and a
    fresh arm per case would double the time per case).
    """
    if b.mode != fb.MODE['BALANCING']:
        # Upright at pitch 0: inside every accepted arm_upright_pitch (0.01 rad at least).
        joints = NOMINAL_LEG_JOINTS if legs else NOMINAL_JOINTS
        b.feed(NOMINAL_IMU, joints)
        b.rearm(NOMINAL_IMU, joints)


# ------------------------------------------------------------------------------------ Imu

# Strategies are built once: building them inside a composite costs more than the node's tick.
IMU_EDITS = st.dictionaries(st.sampled_from(IMU_FIELDS), any_float, max_size=6)
PITCH = st.floats(-1.6, 1.6)


@st.composite
def imu_messages(draw):
    """Draw a pitch anywhere, then set up to six fields to anything at all."""
    msg = fb.make_imu(draw(PITCH), draw(small))
    for path, value in draw(IMU_EDITS).items():
        set_field(msg, path, value)
    return msg


@FUZZ
@given(msg=imu_messages())
def test_fuzz_imu(bench, msg):
    balancing(bench)
    bench.feed_imu(msg)
    bench.feed_joints(NOMINAL_JOINTS)
    frames = bench.tick()
    check_frames(frames)
    check_state(bench)
    o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
    # Attitude from the orientation, else from gravity (core/attitude.py); a broken gyro axis
    # mixes into the others (the mounting rotation), so any non-finite one is a broken sample.
    norm = math.sqrt(o.x * o.x + o.y * o.y + o.z * o.z + o.w * o.w)   # inf, not OverflowError
    absent = msg.orientation_covariance[0] == -1.0 or norm == 0.0
    orientation = not absent and math.isfinite(norm) and \
        abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE
    g = math.sqrt(a.x * a.x + a.y * a.y + a.z * a.z)
    gravity_bad = not math.isfinite(g) or abs(g - 9.81) > GRAVITY_NORM_TOLERANCE * 9.81 * 1.1
    gyro = all(math.isfinite(v) for v in (w.x, w.y, w.z))
    # A broken (not absent) orientation is a broken sample; an absent one needs gravity.
    if not gyro or (not orientation and (not absent or gravity_bad)):
        assert_fault_now(bench, frames)


# ----------------------------------------------------------------------------- JointState

NAMES = list(fb.WHEEL_JOINTS) + list(fb.LEG_JOINTS) + ['caster_joint', '']


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
    return JointState(name=list(names), position=draw(POSITIONS[size()]),
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
    b.feed_imu(NOMINAL_IMU)
    b.feed_joints(msg)
    frames = b.tick()
    check_frames(frames)
    check_state(b)
    names = list(msg.name)
    wheels = [_first(names, msg.velocity, j) for j in fb.WHEEL_JOINTS]
    legs = [_first(names, msg.position, j) for j in fb.LEG_JOINTS]
    if None not in wheels and not all(math.isfinite(w) for w in wheels):
        assert_fault_now(b, frames)
    if None not in legs and not all(math.isfinite(q) for q in legs):
        assert_fault_now(b, frames)


# --------------------------------------------------------------------------- TwistStamped

@st.composite
def cmd_messages(draw):
    msg = TwistStamped()
    msg.header.stamp.sec = draw(st.integers(-2 ** 31, 2 ** 31 - 1))
    msg.header.stamp.nanosec = draw(st.integers(0, 2 ** 32 - 1))
    for path in CMD_FIELDS:
        used = path in ('twist.linear.x', 'twist.angular.z')
        set_field(msg, path, draw(st.one_of(small, any_float) if used else any_float))
    return msg


@FUZZ
@given(msg=cmd_messages())
def test_fuzz_cmd_vel(bench, msg):
    balancing(bench)
    rejected = bench.rejected_cmd_vel   # what diagnostics report as rejected_cmd_vel
    bench.feed(NOMINAL_IMU, NOMINAL_JOINTS)
    bench.feed_cmd_vel(msg)
    frames = bench.tick()
    check_frames(frames)
    check_state(bench)
    assert bench.mode == fb.MODE['BALANCING']
    shaper = bench.loop.shaper
    # reference.max_velocity 1 m/s, reference.max_yaw_rate 3 rad/s (defaults).
    assert math.isfinite(shaper.x_dot_ref) and abs(shaper.x_dot_ref) <= 1.0
    assert math.isfinite(shaper.yaw_rate_ref) and abs(shaper.yaw_rate_ref) <= 3.0
    dropped = not (math.isfinite(msg.twist.linear.x) and math.isfinite(msg.twist.angular.z))
    assert bench.rejected_cmd_vel - rejected == int(dropped)


# ------------------------------------------------------------------------------------ Joy

@pytest.fixture(scope='module')
def teleop():
    return Teleop(TeleopConfig())


@FUZZ
@given(axes=st.lists(st.one_of(small, any_float), max_size=8),
       buttons=st.lists(st.one_of(st.integers(0, 1), st.integers(-2 ** 31, 2 ** 31 - 1)),
                        max_size=12))
def test_fuzz_joy(teleop, axes, buttons):
    joy = Joy()   # the message's storage: float32 axes, int32 buttons, as teleop_node gets them
    joy.axes = axes
    joy.buttons = buttons
    teleop.on_joy(joy.axes, joy.buttons, 0.0)   # teleop_node's callback and timer tick
    cmd = teleop.tick(0.02)
    cfg = teleop.cfg
    x_max = max(abs(cfg.scale_linear_x), abs(cfg.scale_linear_turbo_x))
    w_max = max(abs(cfg.scale_angular_yaw), abs(cfg.scale_angular_turbo_yaw))
    if cmd is not None:
        x, w = cmd
        assert math.isfinite(x) and abs(x) <= x_max
        assert math.isfinite(w) and abs(w) <= w_max


# ----------------------------------------------------------------------------- parameters

PARAM_NAMES = [s.name for s in specs(BalanceConfig)]
param_values = st.one_of(
    any_float, small, st.integers(-2 ** 63, 2 ** 63 - 1), st.integers(-3, 3), st.booleans(),
    st.text(max_size=6), st.sampled_from(['ida_pbc', 'output_regulation', 'lqr', 'mit']),
    st.lists(any_float, min_size=1, max_size=6), st.lists(st.integers(-2, 2), min_size=1,
                                                          max_size=6))


@pytest.fixture(scope='module')
def param_node(context, bench):
    """balance_node's parameters with its ParameterGuard, forwarding to ``bench``'s tick."""
    node = fb.ParameterFront(context, bench)
    yield node
    node.destroy_node()


@FUZZ
@given(name=st.one_of(st.sampled_from(PARAM_NAMES), st.just('no_such_parameter')),
       value=param_values)
@example(name='arm_upright_pitch', value=0.015625)   # CI 2026-12-02: narrower than the rig's pose
def test_fuzz_parameters(bench, param_node, name, value):
    node = param_node
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
        # No accepted value switches the guards off: a NaN pitch rate and a fall still fault.
        bench.feed(fb.make_imu(0.0, NAN))
        assert_fault_now(bench, bench.tick())
        fall = node.get_parameter('fall_angle').value + 0.05
        if fall < 0.5 * math.pi - 0.01:
            balancing(bench)
            bench.feed(fb.make_imu(fall))
            assert_fault_now(bench, bench.tick())
    finally:
        (restored,) = node.set_parameters([Parameter(name, value=before)])
        assert restored.successful, restored.reason
        bench.tick()


# --------------------------------------------------------------- motor replies (issue 11)

REPLY_BYTES = st.one_of(st.binary(min_size=6, max_size=6), st.binary(min_size=8, max_size=8),
                        st.binary(max_size=8))


@pytest.fixture(scope='module')
def reply_bench():
    """Return a bench of its own: bad replies latch a reboot, cleared by hand here."""
    return fb.LoopBench()


@FUZZ
@given(motor=st.sampled_from(MOTOR_IDS), data=REPLY_BYTES, error=st.integers(0, 255))
def test_fuzz_motor_replies(reply_bench, motor, data, error):
    """Any reply bytes from a wheel motor (6 or 8 bytes: temperature, error code), any error."""
    bench = reply_bench
    if bench.mode != fb.MODE['BALANCING']:
        for m in bench.loop.motors.motors:
            m.rebooted = None   # a reboot latches until a restart: this is one
        for _ in range(100):    # the wheel speed estimate forgets the bad reply (0.1 s)
            bench.feed(NOMINAL_IMU, NOMINAL_JOINTS)
            bench.tick()
        balancing(bench)
    if len(data) == 8:
        data = data[:7] + bytes([error])
    data = bytes([motor]) + data[1:] if data else data
    reply = Frame(bench.loop.protocol.master_id, data)
    bench.inputs.frames.append((bench.t + bench.period, reply))
    bench.feed(NOMINAL_IMU, NOMINAL_JOINTS)
    frames = bench.tick()
    check_frames(frames)
    check_state(bench)
    if len(data) == 8 and error:
        assert_fault_now(bench, frames)
        assert any(f.code == 'motor_error' for f in bench.loop.supervisor.faults)


# ----------------------------------------------------------------- IMU stamps (issue 11)

@FUZZ
@given(sec=st.integers(-2 ** 31, 2 ** 31 - 1), nanosec=st.integers(0, 2 ** 32 - 1),
       clock=st.one_of(any_float, st.floats(1.6e9, 1.8e9)))
def test_fuzz_imu_stamps(bench, sec, nanosec, clock):
    """Any header stamp, any node clock: no exception; a stamp far ahead is refused."""
    balancing(bench)
    msg = fb.make_imu(0.0)
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec % 1_000_000_000
    imu = bench.loop.imu
    refused, previous = imu.refused_stamps, imu._stamp
    bench.inputs.imu.append(imu_sample(msg, bench.t + bench.period, clock))
    bench.feed_joints(NOMINAL_JOINTS)
    frames = bench.tick()
    check_frames(frames)
    check_state(bench)
    stamp = sec + 1e-9 * (nanosec % 1_000_000_000)
    new = (sec, nanosec % 1_000_000_000)
    if new != (0, 0) and new != previous and math.isfinite(clock) \
            and stamp - clock > imu.stamp_tolerance + 1e-6:
        assert imu.refused_stamps == refused + 1
