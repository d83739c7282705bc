r"""
The legs: height command, roll levelling, hip impedance commands, homing, damping (pure).

The four hip (body) motors are MIT-mode motors (core/protocols/mit.py) driving two five-bar
legs (core/kinematics.py). Order everywhere: left front, left rear, right front, right rear.
A hip motor's position p [rad] maps to the leg's joint angle q (FiveBarLeg convention) as

    q = direction p + offset          (direction +1 or -1; offset: q at the motor's zero)

and torques and speeds through the direction alone.

Per tick the pieces are (docs/legs.md has the figures):

- ``HeightShaper``: the commanded height l* [m], clamped to [height_min, height_max], rate- and
  acceleration-limited; NaN or infinite commands are refused (the last good one stays);
- ``RollLeveller``: a PID on the body roll [rad] giving the differential leg length
  dl = l_left - l_right [m] (roll > 0 is left side up, REP 103, so dl < 0 shortens the left
  leg); ``split_heights`` turns (l, dl) into the two legs' heights within the legs' range;
- ``LegController.commands``: per hip an impedance command (p, v, kp, kd, tau_ff): p from the
  five-bar inverse kinematics of each leg's height, v from the height rate through the leg
  Jacobian, tau_ff the static torque J^T f that carries the body's weight share f = m g / 2 per
  leg (rotated into the body frame by the pitch), all mapped into each motor's frame;
- ``LegController.state``: from the four hip replies the joint angles, each leg's height l
  (FiveBarLeg.forward), their mean, l_dot and the passive knee angles; a reply that is missing
  or out of the five-bar's reach makes the state invalid with a reason (never an exception);
- ``LegController.damping_commands``: kp = 0, kd > 0 (and optionally part of the weight's
  static torque while the state is valid): the body sinks slowly instead of dropping, for a
  disarm or a fault;
- homing: at the hard stops (core/homing.py ``HipHoming``), or ``LegController.home_known_pose``
  where the legs are known to be at given angles (after the motors' set-zero in a documented
  pose, or held in a jig). Arming is refused until one of the two has run.
"""
from dataclasses import dataclass
import math
from typing import List, NamedTuple, Optional, Sequence, Tuple

from .kinematics import FiveBarLeg, force_at, Jacobian
from .protocols.mit import MitCommand
from .rate_limiter import limit_rate

#: Hip order of every 4-sequence here.
HIP_NAMES = ('left_front', 'left_rear', 'right_front', 'right_rear')
#: The legs, by the index of their front hip in HIP_NAMES.
LEFT_LEG, RIGHT_LEG = 0, 2
BOTH_LEGS = (LEFT_LEG, RIGHT_LEG)
#: A reply as the legs need it: (position [rad], velocity [rad/s], torque [N m]), motor frame.
Reply = Optional[Tuple[float, float, float]]


def _finite(x: float) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


# On the hot paths a value is tested with isfinite itself, its TypeError (not a number) caught:
# a call of it costs less than ``type(x) is float`` and ``x - x == 0.0`` (callgrind, Python
# 3.11); tuple.__new__ builds a NamedTuple without its Python __new__.
_INF = math.inf
isfinite = math.isfinite
_new = tuple.__new__


# ---- height command ------------------------------------------------------------------------


class HeightShaper:
    """
    Shapes the commanded height l* [m] into a reference l_ref with its rate l_dot_ref [m/s].

    The target is clamped to [height_min, height_max]; the reference moves towards it at most
    at max_rate [m/s] and changes its rate at most by max_accel [m/s^2] (a trapezoidal profile
    that brakes in time: the rate is also bounded by sqrt(2 max_accel distance)).
    """

    def __init__(self, height_min: float = 0.37, height_max: float = 0.70,
                 max_rate: float = 0.1, max_accel: float = 0.2):
        if not (height_min < height_max and max_rate > 0.0 and max_accel > 0.0):
            raise ValueError('need height_min < height_max, max_rate > 0, max_accel > 0')
        self.height_min = float(height_min)
        self.height_max = float(height_max)
        self.max_rate = float(max_rate)
        self.max_accel = float(max_accel)
        self.target = self.height_min
        self.l_ref = self.height_min
        self.l_dot_ref = 0.0
        self.refused = 0          # commands refused (NaN, inf, not a number)
        self.clamped = False      # the last accepted command was out of range

    def reset(self, l: float) -> None:
        """Start at height l [m] at rest (e.g. the measured height on arm), target l clamped."""
        if _finite(l):
            self.l_ref = float(l)
        self.l_dot_ref = 0.0
        self.target = min(max(self.l_ref, self.height_min), self.height_max)

    def command(self, l: float) -> bool:
        """Take a new commanded height l* [m]; False if refused (not finite)."""
        try:
            ok = isfinite(l)
        except TypeError:
            ok = False
        if not ok:
            self.refused += 1
            return False
        target = l if type(l) is float else float(l)
        lo, hi = self.height_min, self.height_max
        if lo > target:   # min(max(l, lo), hi)
            target = lo
        if hi < target:
            target = hi
        self.clamped = target != l
        self.target = target
        return True

    def step(self, dt: float) -> Tuple[float, float]:
        """Advance dt [s]; return (l_ref [m], l_dot_ref [m/s])."""
        try:
            ok = isfinite(dt) and dt > 0.0
        except TypeError:
            ok = False
        if not ok:
            return self.l_ref, self.l_dot_ref
        error = self.target - self.l_ref
        if error == 0.0 and self.l_dot_ref == 0.0:
            # At the target at rest: the step below would land on it again (its rate stays
            # within max_accel dt of 0), so it is skipped.
            self.l_dot_ref = 0.0
            return self.l_ref, 0.0
        # The fastest rate from which steps of max_accel dt still stop at the target:
        # v^2 / (2 a) + v dt / 2 = |error|.
        a = self.max_accel
        brake = a * (math.sqrt(0.25 * dt * dt + 2.0 * abs(error) / a) - 0.5 * dt)
        wanted = math.copysign(min(self.max_rate, brake), error)
        rate = limit_rate(wanted, self.l_dot_ref, a, dt)
        l_next = self.l_ref + rate * dt
        if (self.target - l_next) * error <= 0.0 and abs(rate) <= a * dt:
            l_next, rate = self.target, 0.0   # arrived: no creeping around the target
        self.l_ref, self.l_dot_ref = l_next, rate
        return self.l_ref, self.l_dot_ref


# ---- roll levelling ------------------------------------------------------------------------


class RollLeveller:
    """
    Differential leg length dl = l_left - l_right [m] that levels the body's roll.

    dl = -(kp roll + ki integral(roll) + kd roll_rate), limited to +-max_dl; the integral stops
    growing while the output is at its limit (anti-windup). Gains: kp [m/rad], ki [m/(rad s)],
    kd [m s/rad]. A body roll phi needs about dl = d_w tan(phi) (0.47 m per rad for d_w =
    0.47 m). Non-finite inputs hold the last output.
    """

    def __init__(self, kp: float = 0.5, ki: float = 2.0, kd: float = 0.0,
                 max_dl: float = 0.2):
        if min(kp, ki, kd) < 0.0 or not max_dl >= 0.0:
            raise ValueError('levelling gains and max_dl must be >= 0')
        self.kp, self.ki, self.kd, self.max_dl = float(kp), float(ki), float(kd), float(max_dl)
        self.reset()

    def reset(self) -> None:
        """Start level: no integral, no output."""
        self.integral = 0.0
        self.dl = 0.0

    def update(self, roll: float, roll_rate: float, dt: float) -> float:
        """Advance dt [s] with the body roll [rad] and roll rate [rad/s]; return dl [m]."""
        try:
            ok = isfinite(roll) and isfinite(roll_rate) and isfinite(dt) and dt > 0.0
        except TypeError:
            ok = False
        if not ok:
            return self.dl
        integral = self.integral + roll * dt
        raw = -(self.kp * roll + self.ki * integral + self.kd * roll_rate)
        dl, max_dl = raw, self.max_dl   # min(max(raw, -max_dl), max_dl)
        if -max_dl > dl:
            dl = -max_dl
        if max_dl < dl:
            dl = max_dl
        if dl == raw or (raw > dl) == (roll > 0.0):   # unsaturated, or unwinding
            self.integral = integral
        self.dl = dl
        return dl


def split_heights(l: float, dl: float, lo: float, hi: float) -> Tuple[float, float]:
    """
    (l_left, l_right) [m] = l +- dl / 2, both within the legs' range [lo, hi].

    Levelling comes first: dl is limited to the range's width, then the mean l moves as far as
    needed to fit both legs (on a slope at the lowest height the body rises by |dl| / 2).
    """
    # min(max(x, a), b) as comparisons (called every tick)
    a, b = lo - hi, hi - lo
    if a > dl:
        dl = a
    if b < dl:
        dl = b
    half = 0.5 * abs(dl)
    a, b = lo + half, hi - half
    if a > l:
        l = a
    if b < l:
        l = b
    return l + 0.5 * dl, l - 0.5 * dl


# ---- motors and state ----------------------------------------------------------------------


@dataclass(frozen=True)
class HipMotors:
    """
    The four hip motors (HIP_NAMES order): CAN IDs, directions (+1 or -1), offsets [rad].

    q = direction p + offset maps a motor position p to the FiveBarLeg joint angle q.
    """

    motor_ids: Tuple[int, int, int, int] = (3, 4, 5, 6)
    directions: Tuple[int, int, int, int] = (1, 1, 1, 1)
    offsets: Tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)

    def __post_init__(self):
        """Check the four entries of each field."""
        if not (len(self.motor_ids) == len(self.directions) == len(self.offsets) == 4):
            raise ValueError('four hip motors: motor_ids, directions, offsets of 4 entries')
        if any(d not in (1, -1) for d in self.directions):
            raise ValueError('hip directions must be 1 or -1')
        if len(set(self.motor_ids)) != 4:
            raise ValueError('the hip motors need four different CAN IDs')
        if not all(_finite(o) for o in self.offsets):
            raise ValueError('hip offsets must be finite')

    def joint_angle(self, i: int, p: float) -> float:
        """Return the joint angle q [rad] of hip i for a motor position p [rad]."""
        return self.directions[i] * p + self.offsets[i]

    def motor_position(self, i: int, q: float) -> float:
        """Return the motor position p [rad] of hip i for a joint angle q [rad]."""
        return self.directions[i] * (q - self.offsets[i])


@dataclass(frozen=True)
class LegGains:
    """
    Impedance gains of each hip (motor frame): kp [N m/rad], kd [N m s/rad].

    damping_kd: kd of the damping mode [N m s/rad]; damping_gravity: the share (0..1) of the
    weight's static torque kept in the damping mode while the leg state is valid (0: pure
    damping, the body sinks at about f / (kd sum (dq/dl)^2), docs/legs.md).
    """

    kp: float = 60.0
    kd: float = 3.0
    damping_kd: float = 5.0
    damping_gravity: float = 0.6

    def __post_init__(self):
        """Check the ranges."""
        if min(self.kp, self.kd, self.damping_kd) < 0.0 or not self.damping_kd > 0.0:
            raise ValueError('leg gains must be >= 0 and damping_kd > 0')
        if not 0.0 <= self.damping_gravity <= 1.0:
            raise ValueError('damping_gravity must be in [0, 1]')


class LegState(NamedTuple):
    """
    The legs from the four hip replies.

    q, q_dot: joint angles [rad] and rates [rad/s] (HIP_NAMES order, nan where no reply);
    heights: (l_left, l_right) [m] (nan for a leg out of reach); l: their mean [m] (nan unless
    both are valid); l_dot: mean height rate [m/s]; knees: passive knee angles [rad] (left
    front, left rear, right front, right rear; FiveBarLeg.knee_angles); valid: both legs
    measured and in reach; problems: why not, one text per problem.
    """

    q: Tuple[float, ...]
    q_dot: Tuple[float, ...]
    heights: Tuple[float, float]
    l: float
    l_dot: float
    knees: Tuple[float, ...]
    valid: bool
    problems: Tuple[str, ...]


class _OneLeg(NamedTuple):
    """
    One leg's part of a LegState: its two hips' q, q_dot; its height l, l_dot; knees.

    And the Jacobian at q (None: out of reach, singular or not measured), for the load.
    """

    q: Tuple[float, float]
    q_dot: Tuple[float, float]
    l: float
    l_dot: float
    knees: Tuple[float, float]
    problems: Tuple[str, ...]
    j: Optional[Jacobian]


class LegController:
    """
    Hip motor commands from leg heights, and leg state from hip replies (see module docstring).

    leg: the five-bar geometry; motors: the hip motors (their offsets are replaced by homing);
    gains: LegGains; weight_share: the force each leg carries [N] (body mass g / 2).
    """

    def __init__(self, leg: Optional[FiveBarLeg] = None, motors: HipMotors = HipMotors(),
                 gains: LegGains = LegGains(), weight_share: float = 11.0 * 9.81 / 2.0):
        self.leg = leg if leg is not None else FiveBarLeg()
        self.motors = motors
        self.gains = gains
        self.weight_share = float(weight_share)
        self.homed = False
        #: Per leg: (the HipMotors, its two hips' replies, _leg_state's result), left and right;
        #: the LegState built from the two.
        self._memo = [(None, None, None, None), (None, None, None, None)]
        self._state: Optional[LegState] = None
        lo, hi = self.leg.height(self.leg.q_min, self.leg.q_min), \
            self.leg.height(self.leg.q_max, self.leg.q_max)
        #: The height range [m] the legs can be commanded to (their reach, symmetric stance).
        self.reach = (lo, hi)

    # ---- homing -----------------------------------------------------------------------------

    def set_offsets(self, offsets: Sequence[float]) -> None:
        """Use these offsets [rad] (q = direction p + offset) and count the legs as homed."""
        m = self.motors
        self.motors = HipMotors(m.motor_ids, m.directions, tuple(float(o) for o in offsets))
        self.homed = True

    def home_known_pose(self, replies: Sequence[Reply], q_known: Sequence[float]) -> bool:
        """
        Home from a known pose: the hips are at joint angles q_known [rad] now.

        For a set-zero in a documented pose (the motors read 0 there: offset = q_known) or a
        jig. False (nothing changes) if a reply is missing or not finite.
        """
        if len(replies) != 4 or len(q_known) != 4:
            return False
        offsets = []
        for i, (r, q) in enumerate(zip(replies, q_known)):
            if r is None or not (_finite(r[0]) and _finite(q)):
                return False
            offsets.append(q - self.motors.directions[i] * r[0])
        self.set_offsets(offsets)
        return True

    def arm_refusal(self, state: Optional[LegState]) -> Optional[str]:
        """Return why the legs cannot be armed (None when they can)."""
        if not self.homed:
            return 'legs not homed'
        if state is None or not state.valid:
            return 'leg state invalid: ' + ('; '.join(state.problems) if state else 'no replies')
        return None

    # ---- state ------------------------------------------------------------------------------

    def state(self, replies: Sequence[Reply]) -> LegState:
        """
        Return the LegState from the four hip replies (None for a missing one); never raises.

        Only a reply's position and velocity count: a reply (p, v, tau) equal to the previous
        one in those two may be passed again as it was (Legs.read does).
        """
        n = len(replies)
        if n >= 4:
            r0, r1, r2, r3 = replies[0], replies[1], replies[2], replies[3]
        else:
            r0, r1, r2, r3 = (tuple(replies) + (None,) * 4)[:4]
        # Each leg's part is kept while its hips' replies and the offsets stay the same: with
        # the legs commanded in turns, one leg's hips have not replied since the previous tick.
        # The whole state is kept while neither leg's part changed.
        m = self.motors
        left, right = self._memo
        kept = True
        if not (left[0] is m and (left[1] is r0 or left[1] == r0)
                and (left[2] is r1 or left[2] == r1)):
            left = self._memo[0] = (m, r0, r1, self._leg_state(LEFT_LEG, r0, r1))
            kept = False
        if not (right[0] is m and (right[1] is r2 or right[1] == r2)
                and (right[2] is r3 or right[2] == r3)):
            right = self._memo[1] = (m, r2, r3, self._leg_state(RIGHT_LEG, r2, r3))
            kept = False
        if kept:
            return self._state
        left, right = left[3], right[3]
        problems = left[5] + right[5]
        valid = not problems
        self._state = _new(LegState, (
            left[0] + right[0], left[1] + right[1], (left[2], right[2]),
            0.5 * (left[2] + right[2]) if valid else math.nan,
            0.5 * (left[3] + right[3]) if valid else math.nan,
            left[4] + right[4], valid, problems))
        return self._state

    def _leg_state(self, side: int, r_front: Reply, r_rear: Reply) -> _OneLeg:
        """One leg's part of the LegState from its hips' replies."""
        m = self.motors
        nan = math.nan
        problems = ()
        q, q_dot = [nan, nan], [nan, nan]
        for k, r in ((0, r_front), (1, r_rear)):
            if r is not None:
                p, v = r[0], r[1]
                try:
                    ok = isfinite(p) and isfinite(v)
                except TypeError:
                    ok = False
                if ok:
                    d = m.directions[side + k]
                    q[k] = d * p + m.offsets[side + k]   # HipMotors.joint_angle
                    q_dot[k] = d * v
                    continue
            problems += ('no reply from hip %s' % HIP_NAMES[side + k],)
        qf, qr = q
        if qf == qf and qr == qr:
            _, j, l, knees = self.leg.measure(qf, qr)
            if l != l:
                problems += ('%s leg out of reach (q = %.3f, %.3f rad)'
                             % ('left' if side == LEFT_LEG else 'right', qf, qr),)
            l_dot = nan if j is None else j[1][0] * q_dot[0] + j[1][1] * q_dot[1]
        else:
            l = l_dot = nan
            knees, j = (nan, nan), None
        return _new(_OneLeg, ((qf, qr), (q_dot[0], q_dot[1]), l, l_dot, knees, problems, j))

    def load(self, torques: Sequence[float]) -> float:
        """
        Return the legs' mean load f_l [N] that the hips' torques [N m] hold at the state's pose.

        torques: the four hips' (motor frame, HIP_NAMES order, NaN where unknown); the pose:
        the newest state's (NaN unless it is valid). f_l > 0: the legs carry the body
        (FiveBarLeg.leg_force).
        """
        st = self._state
        if st is None or not st.valid:
            return math.nan
        d = self.motors.directions
        return 0.5 * (force_at(self._memo[0][3].j, d[0] * torques[0], d[1] * torques[1])[1]
                      + force_at(self._memo[1][3].j, d[2] * torques[2], d[3] * torques[3])[1])

    # ---- commands ---------------------------------------------------------------------------

    def commands(self, l_left: float, l_right: float, l_dot_left: float = 0.0,
                 l_dot_right: float = 0.0, pitch: float = 0.0, load: float = 1.0,
                 legs: Sequence[int] = BOTH_LEGS) -> List[MitCommand]:
        """
        Impedance commands of the hips for the legs' heights [m] and rates [m/s].

        Heights are clamped to the legs' reach; pitch [rad] (theta, forward lean positive)
        turns the weight share into the body frame: f_l = f cos(theta), f_x = f sin(theta).
        load: the share of the body's weight the legs carry (1 balancing; less resting on the
        tail, which carries the rest). A non-finite input falls back to the damping mode for
        that leg. legs: which legs to command (LEFT_LEG, RIGHT_LEG), two commands each.
        """
        g, m = self.gains, self.motors
        f = self.weight_share * load
        try:
            if not isfinite(pitch):
                pitch = 0.0
        except TypeError:
            pitch = 0.0
        f_l, f_x = f * math.cos(pitch), f * math.sin(pitch)
        lo, hi = self.reach
        out: List[MitCommand] = []
        for side in legs:
            l, l_dot = (l_left, l_dot_left) if side == LEFT_LEG else (l_right, l_dot_right)
            try:
                ok = isfinite(l) and isfinite(l_dot)
            except TypeError:
                ok = False
            if not ok:
                out.extend(self._damping(side))
                continue
            if lo > l:   # min(max(l, lo), hi)
                l = lo
            if hi < l:
                l = hi
            qf, qr, rf, rr, tf, tr = v = self.leg.hip_command(l, l_dot, f_l, f_x)
            # A finite float sum means six finite floats; otherwise each is checked.
            total = qf + qr + rf + rr + tf + tr
            if not (type(total) is float and total - total == 0.0) \
                    and not all(_finite(x) for x in v):
                out.extend(self._damping(side))
                continue
            ids, dirs, offsets = m.motor_ids, m.directions, m.offsets
            d = dirs[side]   # q -> motor frame: HipMotors.motor_position, directions
            out.append(_new(MitCommand, (ids[side], d * (qf - offsets[side]), d * rf, g.kp,
                                         g.kd, d * tf)))
            d = dirs[side + 1]
            out.append(_new(MitCommand, (ids[side + 1], d * (qr - offsets[side + 1]), d * rr,
                                         g.kp, g.kd, d * tr)))
        return out

    def damping_commands(self, state: Optional[LegState] = None,
                         load: float = 1.0) -> List[MitCommand]:
        """
        Damping mode of the four hips: kp = 0, kd = damping_kd, v = 0.

        With a valid state, tau_ff keeps damping_gravity of the weight's static torque at the
        measured pose, so the body sinks slower; without one, pure damping. load: the share of
        the weight on the legs (less when the tail carries the rest: a full share would push
        the legs out).
        """
        out: List[MitCommand] = []
        for side in (0, 2):
            out.extend(self._damping(side, state, load))
        return out

    def _damping(self, side: int, state: Optional[LegState] = None,
                 load: float = 1.0) -> List[MitCommand]:
        g, m = self.gains, self.motors
        tau = (0.0, 0.0)
        if state is not None and state.valid and g.damping_gravity > 0.0:
            ff = self.leg.static_torques(state.q[side], state.q[side + 1],
                                         g.damping_gravity * load * self.weight_share)
            if all(_finite(v) for v in ff):
                tau = ff
        return [MitCommand(m.motor_ids[side + k], 0.0, 0.0, 0.0, g.damping_kd,
                           m.directions[side + k] * tau[k]) for k in (0, 1)]
