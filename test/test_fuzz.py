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

Issue 11 ("safe on the real robot") adds the robot's other inputs, on a bench with the four hips
driven (``SixMotorBench``: the tick's hip frames go to four emulated MIT hips, IDs 3..6, as its
wheel frames go to the wheels): one reply of any bytes from any of the six motors, cmd_height of
any float, attitudes over the whole of SO(3) (balancing and arming), and IMU header stamps of any
integers. There every hip command is also checked as the tick made it, before the MIT codec
clamps it or sends a NaN as 0: finite, kp, kd, torque and velocity within the hip motor model's
ranges, a stiff command's position within the joints' range.

Marked ``slow`` (about a minute for the file on 2 cores); nothing deselects it, so it runs in
``colcon test``.
"""
import functools
import math
import os

from geometry_msgs.msg import TwistStamped
from hypothesis import event, example, given, HealthCheck, settings, strategies as st
import pytest
from rclpy.exceptions import ParameterNotDeclaredException
from rclpy.parameter import Parameter
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import Imu, JointState, Joy
from std_msgs.msg import Float64

from wheelleg_balance.core.attitude import GRAVITY_NORM_TOLERANCE, QUATERNION_NORM_TOLERANCE
from wheelleg_balance.core.balance_loop import CmdHeight
from wheelleg_balance.core.config import BalanceConfig, DEFAULTS
from wheelleg_balance.core.protocols.base import Frame
from wheelleg_balance.core.protocols.mit import MitCommand
from wheelleg_balance.core.schema import specs
from wheelleg_balance.core.teleop import Teleop, TeleopConfig
from wheelleg_balance.nodes.sensor_intake import imu_sample
from wheelleg_balance.sim.motor_emulator import MitMotorBank
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
            # A drive's error stays until a reply clears it; the bench's motors answer in 6
            # bytes (no error field), so the fuzzed 8-byte reply's code is cleared here.
            m.drive_error = 0
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


# ------------------------------------------------- six motors: driven legs (issue 11)

NOMINAL_SAMPLE = imu_sample(NOMINAL_IMU, 0.0)
MODE_NAMES = {v: k for k, v in fb.MODE.items()}


class SixMotorBench(fb.LoopBench):
    """
    LoopBench with ``legs.driven``: the four hips (MIT, IDs 3..6) answer as the wheels do.

    The hips' frames (``leg_frames``, one bus) go to emulated MIT motors as well, with 8-byte
    replies (temperature 25 deg C, error 0) from all six. The hips' offsets are the configured
    ones (``legs.homing: set_zero``: homed at once), their joints at NOMINAL_LEGS (l = 0.37 m,
    height_min); ``follow``: each hip's joint goes to its newest stiff command (an ideal leg),
    so the measured height follows the commanded one. ``hip_commands``: the hips' commands of
    the newest tick as the tick made them, before the MIT codec clamps them (or sends a NaN as
    0). ``tick(inject=...)``: one more frame among the replies (see ``tick``).
    """

    def __init__(self, follow=False, **params):
        super().__init__(**dict({'legs.driven': True}, **params))
        loop = self.loop
        hips = loop.legs.controller.motors
        self.hip_ids = tuple(hips.motor_ids)
        self.ids = loop.motors.ids + self.hip_ids
        directions = {m.motor_id: m.direction for m in loop.motors.motors}
        directions.update(zip(self.hip_ids, hips.directions))
        self.motors = MitMotorBank(self.ids, directions, loop.protocol, reply_temperature=True)
        for i, q, offset, d in zip(self.hip_ids, fb.NOMINAL_LEGS, hips.offsets, hips.directions):
            self.motors.joints[i] = (q, 0.0)
            e = self.motors.motor(i)
            e.protocol = loop.legs.protocol   # the hip motor model's ranges
            e.zero = d * offset               # motor position d (q - offset)
        self.follow = follow
        self.hip_commands = []
        legs, encode = loop.legs, loop.legs.frames

        def frames(commands):
            commands = list(commands)
            self.hip_commands += commands
            return encode(commands)
        legs.frames = frames

    def tick(self, replies=True, inject=None, where='after'):
        """
        Run one tick as LoopBench.tick does, the hips' frames sent after the wheels'.

        inject: (motor ID, Frame) received in this tick with the motors' replies: 'before' or
        'after' them, or in place of that motor's own reply ('replace': a corrupted reply).
        """
        self.hip_commands = []
        self.t += self.period
        frames = list(self._replies) if replies else []
        if inject is not None:
            motor, frame = inject
            if where == 'replace':
                frames = [f for f in frames if f.data[0] != motor]
            frames = [frame] + frames if where == 'before' else frames + [frame]
        self.inputs.frames.extend((self.t, f) for f in frames)
        result = self.loop.tick(self.t, self.inputs)
        self.inputs.clear()
        self.sent = [] if self.fail_with is not None else \
            list(result.frames) + list(result.leg_frames)
        # Each frame decoded as its motor's firmware decodes it (the emulator's decoding).
        self._replies, out = [], []
        for f in self.sent:
            e = self.motors.emulators.get(f.arbitration_id)
            if e is not None:
                e.last_decoded = None
            self._replies += self.motors.handle(f, self.t)
            out.append((f.arbitration_id, None if e is None else e.last_decoded))
        self.after_tick(result)
        if self.follow:
            for motor_id, cmd in out:
                if isinstance(cmd, MitCommand) and cmd.kp > 0.0 and motor_id in self.hip_ids:
                    e = self.motors.motor(motor_id)
                    self.motors.joints[motor_id] = (e.direction * (cmd.position + e.zero), 0.0)
        return out

    def feed_nominal(self, sample=None):
        """Hand one IMU sample (upright, still, unstamped by default) to the next tick."""
        self.inputs.imu.append((NOMINAL_SAMPLE if sample is None else sample)._replace(t=self.t))

    def balancing(self):
        """
        Re-arm after a case that did not end BALANCING (upright, still): a fresh start.

        A reboot latches until a restart and the wheel speed estimate keeps a bad reply for
        0.1 s: a restart clears both, so does this (as test_fuzz_motor_replies does).
        """
        if self.mode == fb.MODE['BALANCING']:
            return
        self.estop()
        self.feed_nominal()
        self.tick()   # stop frames to all six motors: their own replies come next tick
        for m in self.loop.motors.motors + self.loop.legs.motors.motors:
            # A restart knows no reply before those (the legs took turns: a hip's newest can
            # still be a case's injected one, which the next reply must not be judged by).
            m.rebooted = None
            m.feedback = None
        for w in self.loop.wheel_states:
            w.reset()
        self.loop.sensing.foreign_last = None   # nor another sender's commands before it
        self.feed_nominal()
        req = self.request(True)
        self.tick()
        assert req.success, req.message


def six_bench(follow=False, **params):
    """Return a SixMotorBench balancing upright, risen (the legs take the commanded height)."""
    b = SixMotorBench(follow, **params)
    b.feed_nominal()
    b.tick()
    b.balancing()
    for _ in range(int(0.6 / b.period)):   # RISE_TIME 0.5 s upright: risen
        b.feed_nominal()
        b.tick()
    assert b.mode == fb.MODE['BALANCING'] and not b.loop.balancing.rising
    return b


def check_six(b, frames, wheel_limit=MAX_TORQUE):
    """
    Check every frame of a SixMotorBench tick and the hips' commands before encoding.

    Wheels: torque-only MIT commands, finite, within ``wheel_limit``. Hips: MIT commands or
    enter / exit (never a set-zero), every field of every command finite, kp and kd within the
    hip motor model's MIT ranges, |torque| within its t_max, |velocity| within its v_max, and a
    stiff command's position (kp > 0) inside the joints' range [q_min, q_max].
    """
    cfg = b.loop.cfg
    wheels = b.loop.motors.ids
    for motor_id, cmd in frames:
        assert motor_id in b.ids, (motor_id, cmd)
        assert cmd in ('enter', 'exit') or isinstance(cmd, MitCommand), (motor_id, cmd)
        if motor_id in wheels and isinstance(cmd, MitCommand):
            assert cmd.kp == 0.0 and cmd.kd == 0.0, cmd
            assert math.isfinite(cmd.torque) and abs(cmd.torque) <= wheel_limit + fb.TORQUE_LSB
    hip, legs = cfg.legs.mit, b.loop.legs.controller
    for c in b.hip_commands:
        assert c.motor_id in b.hip_ids, c
        assert all(math.isfinite(v) for v in c[1:]), c
        assert 0.0 <= c.kp <= hip.kp_max and 0.0 <= c.kd <= hip.kd_max, c
        assert abs(c.torque) <= hip.t_max and abs(c.velocity) <= hip.v_max, c
        if c.kp > 0.0:
            i = b.hip_ids.index(c.motor_id)
            q = legs.motors.joint_angle(i, c.position)
            assert legs.leg.q_min - 1e-9 <= q <= legs.leg.q_max + 1e-9, (c, q)
    for tau in b.wheel_torques():
        assert math.isfinite(tau) and abs(tau) <= wheel_limit


def wheel_frames(b, frames):
    return [(i, f) for i, f in frames if i in b.loop.motors.ids]


def assert_wheels_zero_now(b, frames):
    """FAULT at this tick: the wheels' frames all zero torque (the hips damp)."""
    assert b.mode == fb.MODE['FAULT'], b.loop.supervisor.conditions
    wheels = wheel_frames(b, frames)
    assert wheels and all(fb.is_zero_torque(f) for _, f in wheels), wheels


# ----------------------------------------------------- motor replies of all six motors

#: A reply from any of the six motors: raw bytes (6, 8 or 0..8), or a well-formed reply whose
#: position lies near the motor's true one (within or beyond the reboot limit), any velocity,
#: torque, temperature and error code.
SIX_IDS = (1, 2, 3, 4, 5, 6)
PLACES = ('replace', 'after', 'before')
ARBITRATION = st.one_of(st.just('master'), st.just('master'), st.just('own'),
                        st.integers(0, 0x7FF))
FIELD = st.floats(-1.0, 1.0)


@st.composite
def six_replies(draw):
    """
    Return (motor, data, arbitration, where) of one reply frame from any of the six motors.

    data: bytes, or (dp, velocity share, torque share, temperature, error) of a well-formed
    8-byte reply at the motor's true position + dp [rad] (``reply_frame`` encodes it).
    """
    motor = draw(st.sampled_from(SIX_IDS))
    if draw(st.booleans()):
        data = draw(REPLY_BYTES)
        if len(data) == 8 and draw(st.booleans()):
            data = data[:7] + b'\x00'   # clean replies too: their temperatures, jumps, values
        data = bytes([motor]) + data[1:] if data else data
    else:
        data = (draw(st.floats(-0.6, 0.6)), draw(FIELD), draw(FIELD),
                draw(st.one_of(st.integers(-128, 127), st.integers(60, 95))),
                draw(st.one_of(st.just(0), st.integers(0, 255))))
    return motor, data, draw(ARBITRATION), draw(st.sampled_from(PLACES))


def reply_frame(b, motor, data, arbitration):
    """Return the Frame of a drawn reply (six_replies) on the bench ``b``."""
    mit = b.motors.motor(motor).protocol
    if not isinstance(data, bytes):
        dp, v, tau, temperature, error = data
        e = b.motors.motor(motor)
        data = bytes(mit.encode_reply(motor, e.position(b.motors.joints[motor][0]) + dp,
                                      v * mit.v_max, tau * mit.t_max, temperature, error).data)
    arbitration = {'master': mit.master_id, 'own': motor}.get(arbitration, arbitration)
    return Frame(arbitration, data)


def jump(mit, p_prev, v_prev, t_prev, p, v, t):
    """
    Return how far [rad] a reply's position is off the previous reply's extrapolation.

    docs/faults.md, core/motor_health.py: the trapezoid of the two speeds over the gap, modulo
    the position field's span (it wraps, can.mit.wrap: 65536 codes of (p_max - p_min) / 65535),
    less what 2000 rad/s^2 over the gap and 12 ms of receipt jitter explain.
    """
    span = (mit.p_max - mit.p_min) * 65536.0 / 65535.0
    gap = t - t_prev
    d = p - (p_prev + 0.5 * (v_prev + v) * gap)
    d = (d + 0.5 * span) % span - 0.5 * span
    return abs(d) - 1000.0 * gap * gap - 0.006 * abs(v_prev + v)


def derate_share(temperature, cold=70.0, hot=85.0):
    """Share of the wheel torque limit at ``temperature`` (can.mit temp_derate, temp_max)."""
    if temperature <= cold:
        return 1.0
    return 0.5 if temperature >= hot else 1.0 - 0.5 * (temperature - cold) / (hot - cold)


#: The reply bench's wheel torque limit [N m]: a lean of 0.3 rad asks for 3.4 N m, so the
#: torque saturates and a derated limit shows.
REPLY_TORQUE = 2.0


@pytest.fixture(scope='module')
def six_reply_bench():
    return six_bench(max_wheel_torque=REPLY_TORQUE)


def leaning(theta):
    """Return an IMU sample of pitch theta [rad] (unstamped, still)."""
    return NOMINAL_SAMPLE._replace(qy=math.sin(0.5 * theta), qw=math.cos(0.5 * theta))


@FUZZ
@given(reply=six_replies(), theta=st.floats(-0.3, 0.3))
def test_fuzz_hip_motor_replies(six_reply_bench, reply, theta):
    """
    Any one reply from any of the six motors, before, after or in place of the motor's own.

    The hips (IDs 3..6) driven, the robot balancing, leaning up to 0.3 rad. Every frame and
    hip command within its limits; while balancing, nothing it balances on non-finite or
    implausible; and the reaction where one is required: an error code, a position jump beyond
    can.mit / legs.mit position_jump (a reboot), a hip angle beyond the joints' range: FAULT at
    this tick, zero wheel torque; temp_max reached: no longer balancing (sit-down or FAULT); a
    hot wheel: its torque limit derated at this tick.
    """
    b = six_reply_bench
    b.balancing()
    motor, data, arbitration, where = reply
    frame = reply_frame(b, motor, data, arbitration)
    wheel = motor in b.loop.motors.ids
    mit = b.loop.protocol if wheel else b.loop.legs.protocol   # the motor model's ranges
    raw = bytes(frame.data)
    accepted = len(raw) in (6, 8) and frame.arbitration_id in (mit.master_id, raw[0])
    model = b.loop.cfg.can.mit if wheel else b.loop.cfg.legs.mit
    m = b.loop.motors.by_id[motor] if wheel else b.loop.legs.motors.by_id[motor]
    # The reply the injected one follows: the motor's own of this tick ('after'), else its
    # newest before this tick (a hip whose leg was not commanded last tick has none now: the
    # legs take turns, legs.command_divider).
    own = next((mit.decode_feedback(f) for f in b._replies if f.data[0] == motor), None)
    prev, t_prev = (own, b.t + b.period) if where == 'after' and own is not None \
        else (m.feedback, m.last_reply)
    b.feed_nominal(leaning(theta))
    frames = b.tick(inject=(motor, frame), where=where)
    reply = mit.decode_feedback(frame) if accepted else None
    newest = accepted and where != 'before'   # what the tick goes by
    hot = reply.temperature if newest and len(raw) == 8 else None
    limit = REPLY_TORQUE
    if hot is not None and wheel:
        limit *= derate_share(hot, model.temp_derate, model.temp_max)
    check_six(b, frames, limit)
    if b.mode == fb.MODE['BALANCING']:   # nothing it balances on is non-finite or implausible
        snap, lim = b.loop.sensing.snapshot, b.loop.cfg.safety
        assert snap.finite() and b.loop.legs.state.valid
        assert abs(snap.wheel_vel_left) <= lim.max_wheel_velocity and \
            abs(snap.wheel_vel_right) <= lim.max_wheel_velocity
    event('%s %s' % ('wheel' if wheel else 'hip', MODE_NAMES[b.mode]))
    if not accepted and frame.arbitration_id in SIX_IDS and len(raw) == 8:
        # 8 bytes on a motor's ID, not its reply (byte 0 is not the ID): that motor takes it
        # for a command, so it is another sender's (issue 29): FAULT input_conflict.
        event('command of another sender')
        assert_wheels_zero_now(b, frames)
        assert 'input_conflict' in [f.code for f in b.loop.supervisor.faults]
    if not accepted:
        event('not a reply')
        return
    faults = [f.code for f in b.loop.supervisor.faults]
    if len(raw) == 8 and raw[7]:
        event('error code')
        assert_wheels_zero_now(b, frames)
        assert 'motor_error' in faults
    fast = 0.9 * min(-mit.v_min, mit.v_max) - 0.1   # speeds the reboot check judges
    if abs(prev.velocity) < fast and abs(reply.velocity) < fast and model.position_jump + 0.01 \
            < jump(mit, prev.position, prev.velocity, t_prev, reply.position, reply.velocity, b.t):
        event('position jump')
        assert_wheels_zero_now(b, frames)
        assert 'motor_rebooted' in faults, faults
    if hot is not None and hot >= model.temp_max:
        event('temp_max')
        assert b.mode != fb.MODE['BALANCING']
    elif limit < REPLY_TORQUE:
        event('derated')
    if newest and not wheel:
        legs = b.loop.legs.controller
        q = legs.motors.joint_angle(b.hip_ids.index(motor), reply.position)
        if not legs.leg.q_min - 0.05 <= q <= legs.leg.q_max + 0.05:
            event('hip angle out of range')
            assert_wheels_zero_now(b, frames)


# ---------------------------------------------------------------- cmd_height (issue 11)

#: Any float; heights around and inside the range; the tiniest ones.
HEIGHTS = st.one_of(any_float, st.floats(0.2, 0.9), st.floats(-1e-300, 1e-300),
                    st.sampled_from([0.37, 0.70, 0.0, -0.0, 5e-324, -5e-324, 1e308]))


@pytest.fixture(scope='module')
def height_bench():
    return six_bench(follow=True)


def commanded_heights(b):
    """Return the heights [m] of the legs' stiff commands of the newest tick (five-bar)."""
    legs = b.loop.legs.controller
    q = {}
    for c in b.hip_commands:
        if c.kp > 0.0:
            i = b.hip_ids.index(c.motor_id)
            q[i] = legs.motors.joint_angle(i, c.position)
    return [legs.leg.height(q[k], q[k + 1]) for k in (0, 2) if k in q and k + 1 in q]


@FUZZ
@given(height=HEIGHTS, t=any_float)
def test_fuzz_cmd_height(height_bench, height, t):
    """
    Any float as cmd_height (std_msgs/Float64), any receipt time, to a balancing robot.

    The legs follow their commands (an ideal leg). The target (~/state l_target) is the value
    clamped to [height_min, height_max] (model.height_min / height_max), or, for NaN and +-inf,
    unchanged and the command counted as rejected; the height reference and the heights of the
    hips' stiff commands stay in the range; every frame and hip command within its limits; it
    keeps balancing.
    """
    b = height_bench
    b.balancing()
    model = b.loop.cfg.model
    lo, hi = model.height_min, model.height_max
    before, rejected = b.loop.last_result.state.l_target, b.loop.balancing.rejected_cmd_height
    b.feed_nominal()
    b.inputs.cmd_height = CmdHeight(t, Float64(data=height).data)   # as balance_node takes it
    frames = b.tick()
    check_six(b, frames)
    assert b.mode == fb.MODE['BALANCING'], b.loop.supervisor.faults
    state = b.loop.last_result.state
    if math.isfinite(height):
        assert state.l_target == min(max(height, lo), hi)
        assert b.loop.balancing.rejected_cmd_height == rejected
    else:
        assert state.l_target == before and b.loop.balancing.rejected_cmd_height == rejected + 1
    assert lo <= state.l_target <= hi and lo <= b.loop.legs.shaper.target <= hi
    # The reference starts at the height measured at arming: height_min within the arming
    # tolerance (RAISED_TOLERANCE, 5 mm); the legs' commands are in the range from the start.
    assert lo - 0.005 <= state.l_ref <= hi
    heights = commanded_heights(b)
    assert heights, b.hip_commands
    for l in heights:
        assert lo - 1e-6 <= l <= hi + 1e-6, heights


# ------------------------------------------------- quaternions of any attitude (issue 11)

UNIFORM = st.floats(0.0, 1.0, exclude_min=True)
SIGN = st.sampled_from((-1.0, 1.0))
NEAR = st.floats(-0.01, 0.01)


@st.composite
def attitudes(draw):
    """
    Return a unit quaternion (x, y, z, w) of any attitude, in three ways.

    Four normal floats (Box-Muller) normalised: uniform over SO(3); roll, pitch, yaw over their
    whole ranges; or roll and pitch within 0.01 rad of a threshold of the supervisor (fall_angle,
    fall_roll_angle, the arming windows of the default configuration), yaw any.
    """
    kind = draw(st.sampled_from(('uniform', 'euler', 'edge')))
    if kind == 'uniform':
        n = []
        for _ in range(2):
            radius = math.sqrt(-2.0 * math.log(draw(UNIFORM)))
            phase = 2.0 * math.pi * draw(UNIFORM)
            n += [radius * math.cos(phase), radius * math.sin(phase)]
        norm = math.sqrt(sum(v * v for v in n))
        return tuple(v / norm for v in n) if norm > 1e-6 else (0.0, 0.0, 0.0, 1.0)
    if kind == 'euler':
        rpy = (draw(st.floats(-math.pi, math.pi)), draw(st.floats(-0.5 * math.pi, 0.5 * math.pi)),
               draw(st.floats(-math.pi, math.pi)))
    else:
        s = DEFAULTS.safety
        pitches = (s.fall_angle, s.tail_pitch - s.arm_pose_tolerance,
                   s.tail_pitch + s.arm_pose_tolerance, s.arm_upright_pitch, 0.0)
        rolls = (s.fall_roll_angle, s.arm_pose_tolerance, 0.0)
        rpy = (draw(SIGN) * draw(st.sampled_from(rolls)) + draw(NEAR),
               draw(SIGN) * draw(st.sampled_from(pitches)) + draw(NEAR),
               draw(st.floats(-math.pi, math.pi)))
    return tuple(Rotation.from_euler('ZYX', rpy[::-1]).as_quat())   # (x, y, z, w)


GYRO = st.one_of(st.just((0.0, 0.0, 0.0)), st.tuples(*[st.floats(-0.4, 0.4)] * 3),
                 st.tuples(*[st.floats(-3.0, 3.0)] * 3))


@functools.lru_cache()
def mounting(rpy):
    """Return R_bi, the IMU frame's orientation in base_link, of imu_mounting_rpy [rad]."""
    return Rotation.from_euler('ZYX', rpy[::-1])


def reference_attitude(b, q, gyro):
    """
    Return the body's (roll, pitch, pitch rate) by scipy, the IMU's mounting applied.

    Body orientation R_wb = R_wi R_bi^-1 (R_bi from imu_mounting_rpy, a URDF rpy), its z-y'-x''
    Euler angles; the Euler pitch rate omega_y cos(roll) - omega_z sin(roll) of the body-frame
    gyro R_bi omega_i.
    """
    r_bi = mounting(tuple(b.loop.cfg.imu.imu_mounting_rpy))
    _, pitch, roll = (Rotation.from_quat(q) * r_bi.inv()).as_euler('ZYX')
    w = r_bi.apply(gyro)
    return roll, pitch, w[1] * math.cos(roll) - w[2] * math.sin(roll)


def attitude_imu(q, gyro, gravity=9.81):
    """Return an Imu of orientation q, the gyro (IMU frame) and gravity's specific force."""
    msg = Imu()
    o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
    o.x, o.y, o.z, o.w = (float(v) for v in q)
    w.x, w.y, w.z = (float(v) for v in gyro)
    a.x, a.y, a.z = (float(v) for v in Rotation.from_quat(q).inv().apply((0.0, 0.0, gravity)))
    return msg


@pytest.fixture(scope='module')
def attitude_bench():
    return six_bench()


@FUZZ
@given(q=attitudes(), gyro=GYRO, arm=st.booleans())
@pytest.mark.filterwarnings('ignore:Gimbal lock detected')
def test_fuzz_quaternions_of_any_attitude(attitude_bench, q, gyro, arm):
    """
    Any attitude (a unit quaternion) with a plausible gyro and gravity, hips driven.

    Balancing: beyond fall_roll_angle or fall_angle (roll and pitch by scipy): FAULT at this
    tick, zero wheel torque; inside both: still balancing; frames within limits either way.
    Arming (from DISARMED, or the re-arm from FAULT): accepted only from a plausible pose,
    accepted from every one inside fall_angle: on the tail (|pitch - tail_pitch| within
    arm_pose_tolerance) or upright (|pitch| within arm_upright_pitch) and still (|pitch rate|
    within arm_still_rate), |roll| within arm_pose_tolerance.
    """
    b = attitude_bench
    s = b.loop.cfg.safety
    roll, pitch, pitch_rate = reference_attitude(b, q, gyro)
    eps = 1e-9   # scipy's angles and the node's differ in the last bits

    def pose(margin):
        on_tail = abs(pitch - s.tail_pitch) <= s.arm_pose_tolerance + margin
        upright = abs(pitch) <= s.arm_upright_pitch + margin and \
            abs(pitch_rate) <= s.arm_still_rate + margin
        return (on_tail or upright) and abs(roll) <= s.arm_pose_tolerance + margin
    if arm:
        if b.mode != fb.MODE['FAULT']:   # the explicit re-arm from FAULT, else from DISARMED
            b.estop()
            b.feed_nominal()
            b.tick()
        b.feed_imu(attitude_imu(q, gyro))
        req = b.request(True)
        frames = b.tick()
        check_six(b, frames)
        event('arm %s' % ('accepted' if req.success else 'refused'))
        if req.success:
            assert pose(eps), (roll, pitch, pitch_rate)
            assert b.mode == fb.MODE['BALANCING']
        elif pose(-eps) and abs(pitch) < s.fall_angle - eps:
            raise AssertionError('refused from a plausible pose: %s' % req.message)
        return
    b.balancing()
    b.feed_imu(attitude_imu(q, gyro))
    frames = b.tick()
    check_six(b, frames)
    if abs(roll) > s.fall_roll_angle + eps or abs(pitch) > s.fall_angle + eps:
        event('fallen')
        assert_wheels_zero_now(b, frames)
    elif abs(roll) < s.fall_roll_angle - eps and abs(pitch) < s.fall_angle - eps:
        event('inside')
        assert b.mode == fb.MODE['BALANCING'], b.loop.supervisor.faults


# ----------------------------------------------- IMU stamps of any integers (issue 11)

INT64 = st.integers(-2 ** 63, 2 ** 63 - 1)


@pytest.fixture(scope='module')
def stamp_bench():
    return fb.LoopBench()


@FUZZ
@given(sec=st.one_of(st.integers(-2 ** 31, 2 ** 31 - 1), INT64),
       nanosec=st.one_of(st.integers(0, 2 ** 32 - 1), INT64),
       clock=st.one_of(any_float, st.floats(1.6e9, 1.8e9)))
def test_fuzz_imu_stamps_any_integers(stamp_bench, sec, nanosec, clock):
    """
    Any header stamp: int32 sec, uint32 nanosec (also >= 1e9), or any int64 pair.

    An Imu's stamp through the intake, or any int64 pair as the control link carries it
    (negative nanosec, sums beyond int32), any receipt clock: no exception; frames as above; a
    sample the reader refuses is not used; a new stamp more than stamp_tolerance ahead of a
    finite clock is refused, as is one before the previous one (compared in ns: a pair with
    nanosec >= 1e9 once passed as forward when it was 0.5 s backwards).
    """
    b = stamp_bench
    balancing(b)
    imu = b.loop.imu
    refused, previous, time_before = imu.refused_stamps, imu.stamp_ns, imu.time
    receipt = b.t + b.period
    if -2 ** 31 <= sec < 2 ** 31 and 0 <= nanosec < 2 ** 32:
        msg = fb.make_imu(0.0)
        msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
        sample = imu_sample(msg, receipt, clock)
    else:
        sample = imu_sample(fb.make_imu(0.0), receipt, clock)
        sample = sample._replace(stamp_sec=sec, stamp_nanosec=nanosec)
    b.inputs.imu.append(sample)
    b.feed_joints(NOMINAL_JOINTS)
    frames = b.tick()
    check_frames(frames)
    check_state(b)
    new = sec * 1_000_000_000 + nanosec   # the stamp [ns], whatever the split
    if imu.refused_stamps != refused or (new == previous and new != 0):
        assert imu.time == time_before   # refused or frozen: not used, it goes stale
    else:
        assert imu.time == receipt
    stamp = 1e-9 * new
    if new != 0 and new != previous and math.isfinite(clock) and \
            stamp - clock > b.loop.cfg.safety.stamp_tolerance + 1e-6 * max(1.0, abs(stamp)):
        assert imu.refused_stamps == refused + 1
    if new != 0 and previous not in (None, 0) and new < previous:
        event('backwards')
        assert imu.refused_stamps == refused + 1
