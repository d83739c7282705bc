"""
Field matrices: one bad value in one field of one message at a time, into the control tick.

Every numeric field of the messages balance_node takes gets non-finite and absurd values; each
case runs on a LoopBench (deterministic) and its reaction is compared with the same sequence
run with the clean message: FAULT where the field feeds the controller, no change where the
node does not use the field; cmd_vel's non-finite commands dropped and counted. Joy samples go
through teleop's core the way teleop_node hands them over.
"""
from array import array
from dataclasses import replace
import math
from typing import Dict, List, Optional

from geometry_msgs.msg import TwistStamped
from sensor_msgs.msg import Joy

from .bench import is_zero_torque, LEG_PARAMS, LoopBench, make_imu, make_joints, MODE
from .outcome import Outcome
from ...core.teleop import Teleop, TeleopConfig


def set_field(msg, path: str, value) -> None:
    """Set a numeric field by path, e.g. 'orientation.x', 'velocity[0]', 'twist.linear.x'."""
    if path.endswith(']'):
        name, index = path[:-1].split('[')
        getattr(msg, name)[int(index)] = value
        return
    *parents, leaf = path.split('.')
    obj = msg
    for p in parents:
        obj = getattr(obj, p)
    setattr(obj, leaf, value)


def _vector(prefix: str) -> List[str]:
    return ['%s.%s' % (prefix, axis) for axis in 'xyz']


def _matrix(name: str) -> List[str]:
    return ['%s[%d]' % (name, i) for i in range(9)]


#: Every numeric field of the messages balance_node takes (header stamps are integers).
IMU_FIELDS = (['orientation.%s' % a for a in 'xyzw'] + _matrix('orientation_covariance')
              + _vector('angular_velocity') + _matrix('angular_velocity_covariance')
              + _vector('linear_acceleration') + _matrix('linear_acceleration_covariance'))
JOINT_FIELDS = ['%s[%d]' % (a, i) for a in ('position', 'velocity', 'effort') for i in (0, 1)]
LEG_FIELDS = ['position[%d]' % i for i in range(2, 6)]
CMD_FIELDS = _vector('twist.linear') + _vector('twist.angular')
NON_FINITE = (math.nan, math.inf, -math.inf)
#: Finite but physically impossible for any field the node uses.
ABSURD = (1.0e6, 1.0e300, -1.0e300)


def expected_reaction(kind: str, path: str, value: float) -> str:
    """
    Return the required reaction of balance_node to ``value`` in field ``path`` of a message.

    'fault': FAULT with zero torque at the next tick (the field feeds theta~, theta_dot, a wheel
    velocity or l); 'ignored': the torques are exactly those of the clean message (a field the
    node does not use); 'used': still balancing, on other torques (the gravity fallback).
    cmd_vel: 'rejected' (dropped and counted) for a non-finite x_dot* or yaw rate*, else
    'accepted' (the shaped references stay finite and within their limits).
    """
    if kind == 'imu':
        if path.startswith('orientation.'):
            # A broken quaternion is a broken sample (core/attitude.py: body_attitude).
            return 'fault'
        if path == 'orientation_covariance[0]' and value == -1.0:
            # sensor_msgs/Imu's "no orientation estimate": roll and pitch come from gravity.
            return 'used'
        if path.startswith('angular_velocity.') and not math.isfinite(value):
            return 'fault'    # a broken gyro: the mounting rotation mixes every axis
        if path == 'angular_velocity.y':
            return 'fault'    # the pitch rate itself: an absurd one is implausible
        return 'ignored'
    if kind == 'joints':
        return 'fault' if path.startswith('velocity') else 'ignored'
    if kind == 'legs':
        return 'fault'
    if path in ('twist.linear.x', 'twist.angular.z') and not math.isfinite(value):
        return 'rejected'
    return 'accepted'


class FieldMatrix:
    """
    One bad value in one field at a time, into a Bench on virtual time (deterministic).

    Each case: re-arm, three clean ticks, then the message with the bad field and one tick; its
    reaction is compared with the same sequence run with the clean message.
    """

    def __init__(self, bench: LoopBench):
        self.bench = bench
        self.legs = bench.has_legs
        self._reference: Dict[str, tuple] = {}

    def _messages(self):
        legs = (0.25, 0.25, 0.25, 0.25) if self.legs else None
        cmd = TwistStamped()
        cmd.twist.linear.x, cmd.twist.angular.z = 0.2, 0.1
        return make_imu(0.02), make_joints(legs=legs), cmd

    def _run(self, kind: Optional[str], path: str = '', value: float = 0.0):
        bench = self.bench
        imu, joints, cmd = self._messages()
        bench.feed(imu, joints)
        bench.feed_cmd_vel(cmd)   # the newest command must not be the last case's
        bench.rearm()
        for _ in range(3):
            bench.feed(imu, joints)
            bench.feed_cmd_vel(cmd)
            bench.tick()
        target = {'imu': imu, 'joints': joints, 'legs': joints, 'cmd': cmd}.get(kind)
        if target is not None:
            set_field(target, path, value)
        rejected = bench.rejected_cmd_vel
        bench.feed(imu, joints)
        bench.feed_cmd_vel(cmd)
        frames = tuple(bench.tick())
        shaper = bench.loop.shaper
        return (frames, bench.mode, bench.rejected_cmd_vel - rejected,
                shaper.x_dot_ref, shaper.yaw_rate_ref)

    def reaction(self, kind: str, path: str, value: float) -> str:
        """Run one case; return 'fault', 'ignored', 'used', 'rejected', 'accepted' or other."""
        if 'clean' not in self._reference:
            self._reference['clean'] = self._run(None)
        ref = self._reference['clean']
        frames, mode, rejected, x_ref, w_ref = self._run(kind, path, value)
        if mode == MODE['FAULT'] and frames and all(is_zero_torque(f) for _, f in frames):
            return 'fault'
        if mode != MODE['BALANCING']:
            return 'mode %d' % mode
        if kind == 'cmd':
            if rejected:
                return 'rejected'
            limited = math.isfinite(x_ref) and math.isfinite(w_ref) and abs(x_ref) <= 1.0 \
                and abs(w_ref) <= 3.0
            return 'accepted' if limited else 'references out of limits'
        return 'ignored' if frames == ref[0] else 'used'

    def outcome(self, name: str, kind: str, cases) -> Outcome:
        """Every (field, value) of ``cases``; one check per case."""
        cases = list(cases)
        out = Outcome(name, '%s: %d bad values in %d fields' % (
            kind, len(cases), len({p for p, _ in cases})),
            'FAULT where the field feeds the controller, else ignored '
            '(cmd_vel: non-finite dropped, the rest within the reference limits)')
        for path, value in cases:
            want = expected_reaction(kind, path, value)
            got = self.reaction(kind, path, value)
            out.check('%s %s = %r: %s (got %s)' % (kind, path, value, want, got), got == want)
        return out


def field_cases(fields_, values):
    """Every field with every value: [(path, value)]."""
    return [(path, value) for path in fields_ for value in values]


def matrix_scenario(name, kind, cases, params):
    def run(context) -> Outcome:
        return FieldMatrix(LoopBench(**params)).outcome(name, kind, cases)
    return run


def _float32(value: float) -> float:
    """Return ``value`` as sensor_msgs/Joy stores it (float32: 1e300 becomes inf)."""
    return array('f', [value])[0]


def scenario_joy_fields(context) -> Outcome:
    """
    Bad values in every Joy axis and in the enable buttons, into teleop_node (in-process).

    teleop_node's rate limits are switched off (0 = unlimited) so that each sample's command
    shows at once. Required: cmd_vel finite and within the scales; a non-finite axis reads as
    centred (0), a finite one beyond +-1 as full deflection (core/teleop.py); a button reads as
    pressed when non-zero.
    """
    out = Outcome('joy_fields', 'Joy with NaN / +-inf / 1e6 / +-1e300 in each of 8 axes and '
                  'odd button values (teleop_node)', 'non-finite axis = centred, finite axis '
                  'clamped to +-1: cmd_vel finite, within the scales')
    cfg = replace(TeleopConfig(), max_linear_accel=0.0, max_angular_accel=0.0)
    teleop = Teleop(cfg)
    used = {cfg.axis_linear_x: cfg.scale_linear_x, cfg.axis_angular_yaw: cfg.scale_angular_yaw}
    clock = [0.0]

    def command(axes, buttons):
        joy = Joy()   # the message's own storage: float32 axes, int32 buttons
        joy.axes, joy.buttons = axes, buttons
        clock[0] += 0.02
        teleop.on_joy(joy.axes, joy.buttons, clock[0])   # what teleop_node's callback does
        return teleop.tick(clock[0])                      # what its timer publishes, or None
    pressed = [0] * 12
    pressed[cfg.enable_button] = 1
    for axis in range(8):
        for value in NON_FINITE + ABSURD:
            axes = [0.0] * 8
            axes[axis] = value
            v = _float32(value)
            want = 0.0 if not math.isfinite(v) else math.copysign(used.get(axis, 0.0), v)
            got = command(axes, pressed)
            index = 0 if axis == cfg.axis_linear_x else 1
            ok = got is not None and all(math.isfinite(c) for c in got) and \
                got[index] == want and (axis in used or got == (0.0, 0.0))
            out.check('axis %d = %r: command %s (got %s)' % (
                axis, value, want, got), ok)
    for value in (-1, 2 ** 31 - 1, -2 ** 31):
        buttons = [0] * 12
        buttons[cfg.enable_button] = value
        axes = [0.0] * 8
        axes[cfg.axis_linear_x] = 1.0
        got = command(axes, buttons)
        out.check('enable button = %d counts as pressed (got %s)' % (value, got),
                  got is not None and got[0] == cfg.scale_linear_x)
    return out


#: The field-matrix scenarios: name -> (message kind, cases, leg joints configured).
#: Wheels (and hips) from another driver's joint states, the joint fields' subject.
JOINT_STATES = {'wheel_state_source': 'joint_states'}
MATRICES = {
    'imu_fields_non_finite': ('imu', field_cases(IMU_FIELDS, NON_FINITE)
                              + [('orientation_covariance[0]', -1.0)], {}),
    'imu_fields_absurd': ('imu', field_cases(IMU_FIELDS, ABSURD), {}),
    'joint_fields_non_finite': ('joints', field_cases(JOINT_FIELDS, NON_FINITE), JOINT_STATES),
    'joint_fields_absurd': ('joints', field_cases(JOINT_FIELDS, ABSURD), JOINT_STATES),
    'leg_fields': ('legs', field_cases(LEG_FIELDS, NON_FINITE + ABSURD),
                   dict(JOINT_STATES, **LEG_PARAMS)),
    'cmd_vel_fields': ('cmd', field_cases(CMD_FIELDS, NON_FINITE + ABSURD), {}),
}
