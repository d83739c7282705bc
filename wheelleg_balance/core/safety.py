"""
Safety supervisor of balance_node: the mode machine and the fault checks of every tick.

``SafetySupervisor`` is a state machine (no rclpy, no python-can: the tick feeds it monotonic
times and the newest samples every control tick):

- ``DISARMED``: motors in rest mode, no torque. Fault conditions are evaluated and reported, but
  they do not change the mode; ``arm`` is refused with a reason while one is present.
- ``BALANCING``: the controller's torques go to the wheels. Any fault condition moves to FAULT.
- ``FAULT``: zero torque, latched reasons. FAULT is never left by itself: only an explicit
  ``arm`` (re-arm, refused while a condition is still present) or ``disarm``.
- ``HOMING``: the hip motors are driven to their stops before the first arm (core/legs.py);
  the wheels get zero torque; any condition is a FAULT, like BALANCING.
- ``SITTING``: the sit-down sequence (core/balance_loop.py): still balancing while the legs go
  down and the body leans onto its tail, then DISARMED; any condition is a FAULT.
- ``EXCITING``: an identification phase with the wheels' scripted torques, from DISARMED
  (core/excitation.py: stand, tail); any condition is a FAULT; it ends in DISARMED.

Fault conditions (checked every tick): stale IMU (``imu_timeout``), stale wheel states
(``joint_state_timeout``), a non-finite measurement, |theta~| > ``fall_angle``, |roll| >
``fall_roll_angle`` (lying on a side; a robot on its side reads pitch 0), a motor that has not
answered within ``motor_timeout`` while it is being commanded, and a failed CAN send. An
exception inside the control tick (a bug) is reported as ``internal_error`` and treated alike.
Arming needs a plausible pose on top (``pose``): resting on the tail (about +36 deg, inside
``fall_angle``: the paper's start-up, Sec. V-B 1) or upright and still.

A stale cmd_vel is *not* a fault: the reference shaping (core/reference.py) brings x_dot* and
yaw rate* to zero while the robot keeps balancing.
"""
from dataclasses import dataclass
import enum
import math
from math import isfinite
from typing import Dict, Iterable, Mapping, NamedTuple, Optional, Sequence, Tuple

IMU_STALE = 'imu_stale'
JOINT_STATES_STALE = 'joint_states_stale'
NON_FINITE = 'non_finite'
IMPLAUSIBLE = 'implausible'
FALL = 'fall'
MOTOR_SILENT = 'motor_silent'
CAN_SEND = 'can_send'
INTERNAL = 'internal_error'
ROLL = 'roll'
POSE = 'pose'
LOOP_STALL = 'loop_stall'
LEGS = 'legs'
LIFTED = 'lifted'
MOTOR_ERROR = 'motor_error'
MOTOR_REBOOTED = 'motor_rebooted'
OVER_TEMPERATURE = 'over_temperature'
INPUT_CONFLICT = 'input_conflict'
RESPONSE = 'response'
#: Not a fault: a wheel's position replies contradict its reported speed (an encoder that
#: saturates instead of wrapping); the wheel angle is dead-reckoned from the speed, a warning.
ENCODER_MISMATCH = 'encoder_mismatch'

#: Every fault code, in the order the checks run.
FAULT_CODES = (IMU_STALE, JOINT_STATES_STALE, NON_FINITE, IMPLAUSIBLE, FALL, ROLL,
               MOTOR_SILENT, CAN_SEND, INTERNAL, LOOP_STALL, LEGS, LIFTED, MOTOR_ERROR,
               MOTOR_REBOOTED, OVER_TEMPERATURE, INPUT_CONFLICT, RESPONSE, POSE)
#: Codes of conditions that warn without a FAULT.
WARNING_CODES = (ENCODER_MISMATCH,)


class Reaction(NamedTuple):
    """One row of the safety table: when a check fires, what the node does, how to get out."""

    detected: str
    reaction: str
    recovery: str


_FAULT = 'FAULT: zero wheel torque every tick, driven hips damping, diagnostics ERROR'
_REARM = 'fix the cause, then `~/arm true` (refused while the condition is present)'

#: {code: Reaction} for every code of FAULT_CODES and WARNING_CODES (docs/balance_node.md's
#: "Safety reactions" table is written from it: validation/interface_doc.py).
SAFETY_TABLE: Dict[str, Reaction] = {
    IMU_STALE: Reaction(
        'the newest IMU sample (receipt time) is older than `imu_timeout`; samples stamped '
        'ahead of the clock by more than `stamp_tolerance`, running backwards or repeating a '
        'stamp do not count as new. In lockstep (`clock_source: imu_stamp`): no sample for '
        '`lockstep_wall_timeout` of wall time',
        _FAULT, 'restore the IMU stream, then `~/arm true`'),
    JOINT_STATES_STALE: Reaction(
        'no reply of a wheel motor (`wheel_state_source: can`), or no wheel joint state on '
        '`joint_states_in` (`joint_states`), for `joint_state_timeout`',
        _FAULT, 'restore the replies or the joint states, then `~/arm true`'),
    NON_FINITE: Reaction(
        'theta~, theta_dot, a wheel speed or l is NaN or infinite (an orientation that is not '
        'a unit quaternion; hip angles out of the five-bar reach)', _FAULT, _REARM),
    IMPLAUSIBLE: Reaction(
        '|theta_dot| > `max_pitch_rate` or a wheel speed beyond `max_wheel_velocity`: a '
        'broken sample, never used', _FAULT, _REARM),
    FALL: Reaction('|theta~| > `fall_angle`', _FAULT + ': the body drops onto its tail',
                   'put it on its tail or upright, then `~/arm true`'),
    ROLL: Reaction('|roll| > `fall_roll_angle` (lying on a side)', _FAULT,
                   'stand it up, then `~/arm true`'),
    MOTOR_SILENT: Reaction(
        'a commanded motor has not replied for `motor_timeout`', _FAULT,
        'power, wiring, ID; re-arm once it answers the zero-torque frames again'),
    CAN_SEND: Reaction(
        'a CAN send failed (a full TX queue past `can.send_timeout`, bus-off, an OSError)',
        _FAULT + '; the zero torque is sent again every tick',
        're-arm once a send succeeds again'),
    INTERNAL: Reaction('an exception inside the control tick (a bug)',
                       _FAULT + '; logged; the loop keeps running',
                       'report it; `~/arm true`'),
    LOOP_STALL: Reaction(
        'a tick came later than the sensor timeouts (`imu_timeout`, `joint_state_timeout`) '
        'after the one before, while commanding: the loop was blind that long', _FAULT,
        '`~/arm true`; see `balance_node: control loop` in diagnostics'),
    LEGS: Reaction(
        "hip homing failed, the legs' state is invalid (a hip without replies, out of reach) "
        'or the legs homed but the robot may not arm', _FAULT,
        'fix the hips (docs/legs.md), then `~/arm true`'),
    LIFTED: Reaction(
        'balancing: both wheels speed up as free wheels would from the torque commanded '
        '(`lift_window`, `lift_min_dv`, `lift_ratio`, `lift_free_time`; one wheel: three '
        'times as long); or, within 20 deg of upright, they do so by as little as '
        '`lift_still_min_dv` while the body holds still, its pitch rate changing by less than '
        "`lift_still_ratio` of what model (1) gives the wheels' acceleration on the ground "
        '(`lift_still_window`); or the driven legs carry less than `lift_min_load` for '
        '`lift_unloaded_time`. Not in free fall (specific force below 0.5 g: a hop)',
        'FAULT: zero wheel torque; driven legs hold their length',
        '`~/arm true` once on the ground (on the tail, or the driven legs carry weight)'),
    MOTOR_ERROR: Reaction('a motor reply carries an error code (decoded in the reason)',
                          _FAULT, 're-arm once the drive clears the code'),
    MOTOR_REBOOTED: Reaction(
        "a motor's position jumped by more than `position_jump` (a reboot: its angle is known "
        'only modulo a rotor turn), or a motor whose replies carry its state (DaMiao, '
        'CyberGear) answered disabled after enabled while commanded', _FAULT + '; latched',
        'restart balance_node'),
    OVER_TEMPERATURE: Reaction(
        'a motor at `temp_max` (from `temp_derate` on the wheel torque limit is derated)',
        'balancing: the sit-down; homing: FAULT', 'arming refused until it cools'),
    INPUT_CONFLICT: Reaction(
        'a second publisher on `imu` or `joint_states_in` (the ROS graph, every 0.5 s), or '
        'command frames to our motors that this node did not send (another commander on the '
        'bus)', _FAULT + '; arming refused while it lasts',
        'stop the other publisher or sender, then `~/arm true`'),
    RESPONSE: Reaction(
        'within 15 deg of upright, the measured change of the pitch rate follows the torque '
        'term of model (1) with a gain below `response_gain` (a least-squares fit over '
        '`response_window`) for `response_time`: the pitch answers the wheel torque with the '
        'wrong sign, a wrong `imu_mounting_rpy` or wheel directions', _FAULT,
        'fix `imu_mounting_rpy`, `can.left_direction`, `can.right_direction`, then `~/arm true`'),
    POSE: Reaction('arming from a pose neither on the tail nor upright and still',
                   'arming refused (not a FAULT)', 'put it on its tail or hold it upright'),
    ENCODER_MISMATCH: Reaction(
        "a wheel's position replies contradict its reported speed (an encoder that saturates "
        'instead of wrapping)', 'warning: the wheel angle is dead-reckoned from the speed',
        'set `can.mit.wrap: false` for saturating firmware'),
}

#: Reactions without a fault code of their own (docs/balance_node.md's table, after the codes).
OTHER_REACTIONS: Dict[str, Reaction] = {
    'cmd_vel timeout': Reaction(
        'the newest cmd_vel is older than `cmd_vel_timeout`',
        'x_dot* and yaw rate* ramp to zero; still balancing', 'send cmd_vel again'),
    'second commander on cmd_vel / cmd_height': Reaction(
        'a second publisher on a command topic', 'that command is dropped (WARN), then times '
        'out; still balancing', 'stop the other publisher'),
    'control loop stalled or died': Reaction(
        "the watchdog process: the loop's heartbeat older than `watchdog_timeout` (in "
        'lockstep `lockstep_wall_timeout` + `watchdog_timeout`) while commanding, or the '
        'control process gone',
        'kills the control process; zero torque, then exit motor mode to every motor',
        'restart balance_node'),
    'balance_node ends or is killed': Reaction(
        'SIGINT, SIGTERM, SIGHUP, SIGQUIT; SIGKILL of the node (its children see the parent '
        'die)', 'zero torque, then exit motor mode to every motor', 'start balance_node'),
    'disarm': Reaction('`~/arm false`', 'balancing: the sit-down (lower, lean onto the tail), '
                       'then zero torque and exit motor mode', '`~/arm true`'),
    'emergency stop': Reaction('`~/stop`', 'zero torque and exit motor mode at once',
                               '`~/arm true`'),
}


class Mode(enum.IntEnum):
    """Operating mode; the integer is what the state topic publishes."""

    DISARMED = 0
    BALANCING = 1
    FAULT = 2
    HOMING = 3
    SITTING = 4
    EXCITING = 5


#: The modes by plain names for the tick's hot path: ``Mode.BALANCING`` looks the member up
#: through the enum's class on every use, some ten times slower than a module name.
DISARMED, BALANCING, FAULT, HOMING, SITTING, EXCITING = (
    Mode.DISARMED, Mode.BALANCING, Mode.FAULT, Mode.HOMING, Mode.SITTING, Mode.EXCITING)
#: Modes in which the motors are commanded (and must answer).
COMMANDING = (BALANCING, HOMING, SITTING, EXCITING)


@dataclass
class SafetyLimits:
    """
    Thresholds of the fault checks (SI units).

    fall_angle: |theta~| beyond which the robot has fallen [rad] (45 deg; the tail rest is 36 deg).
    imu_timeout / joint_state_timeout: age of the newest sample that counts as stale [s].
    motor_timeout: time a commanded motor may stay without a reply [s].
    max_pitch_rate: |theta_dot| no balancing robot reaches: beyond it the IMU sample is broken
    [rad/s] (35 rad/s = 2000 deg/s, the full scale of common MEMS gyros).
    max_wheel_velocity: |wheel velocity| no drive of this robot reaches [rad/s] (200 rad/s:
    20 m/s on 0.1 m wheels; unloaded wheels in a simulated tumble reached 103 rad/s).
    fall_roll_angle: |roll| beyond which the robot lies on a side [rad].
    tail_pitch, tail_tolerance: the tail rest pitch and the window around it that counts as
    resting on the tail for arming [rad]; upright_pitch: |theta~| of the upright window for
    arming [rad]; still_rate: |theta_dot| [rad/s] below which upright counts as still.
    """

    fall_angle: float = math.radians(45.0)
    imu_timeout: float = 0.05
    joint_state_timeout: float = 0.05
    motor_timeout: float = 0.05
    max_pitch_rate: float = 35.0
    max_wheel_velocity: float = 200.0
    fall_roll_angle: float = math.radians(30.0)
    tail_pitch: float = math.radians(36.0)
    tail_tolerance: float = math.radians(10.0)
    upright_pitch: float = math.radians(20.0)
    still_rate: float = 0.3

    def plausible(self, s: 'SensorSnapshot') -> bool:
        """Return True when the rates in ``s`` are within what the robot can do (False for NaN)."""
        return (abs(s.theta_dot) <= self.max_pitch_rate
                and abs(s.wheel_vel_left) <= self.max_wheel_velocity
                and abs(s.wheel_vel_right) <= self.max_wheel_velocity)


@dataclass(frozen=True)
class Fault:
    """One fault condition: a code of FAULT_CODES, a readable reason, when it was seen [s]."""

    code: str
    message: str
    time: float


@dataclass
class SensorSnapshot:
    """
    The newest samples the control tick uses (the node reuses one instance).

    imu_time / joint_time: monotonic receipt time of the newest IMU / joint-state sample [s],
    None when none arrived yet. theta: IMU pitch theta~ [rad]; theta_dot [rad/s];
    wheel_vel_left / wheel_vel_right [rad/s]; l: height [m]; roll: body roll [rad] (0 when the
    caller does not know it).
    """

    imu_time: Optional[float] = None
    joint_time: Optional[float] = None
    theta: float = math.nan
    theta_dot: float = math.nan
    wheel_vel_left: float = math.nan
    wheel_vel_right: float = math.nan
    l: float = math.nan
    roll: float = 0.0

    def finite(self) -> bool:
        """Return True when every measured value is finite."""
        return (math.isfinite(self.theta) and math.isfinite(self.theta_dot)
                and math.isfinite(self.wheel_vel_left) and math.isfinite(self.wheel_vel_right)
                and math.isfinite(self.l))


_NO_FAULTS: Tuple[Fault, ...] = ()
#: The motors' reply times as ``_check`` reads them: groups of (motor ID, time [s] or None).
ReplyTimes = Sequence[Iterable[Tuple[int, Optional[float]]]]


class SafetySupervisor:
    """
    The DISARMED / BALANCING / FAULT state machine (see the module docstring).

    Call ``update`` once per control tick, ``report_send`` after every CAN send, and ``arm`` /
    ``disarm`` on operator request. Times are monotonic seconds.
    """

    def __init__(self, limits: Optional[SafetyLimits] = None, motor_ids=(1, 2)):
        self.limits = limits if limits is not None else SafetyLimits()
        self.motor_ids = tuple(motor_ids)
        self._mode = Mode.DISARMED
        self._faults: Tuple[Fault, ...] = _NO_FAULTS
        self._conditions: Tuple[Fault, ...] = _NO_FAULTS
        # Motors are expected to answer from the moment we start commanding them (arm) on.
        self._commanding_since: Optional[float] = None
        self._send_error: Optional[str] = None

    @property
    def mode(self) -> Mode:
        """Return the current mode."""
        return self._mode

    @property
    def torque_allowed(self) -> bool:
        """Return True while the controller's wheel torques go out (BALANCING, SITTING)."""
        mode = self._mode
        return mode is BALANCING or mode is SITTING

    @property
    def faults(self) -> Tuple[Fault, ...]:
        """Return the latched reasons of the current FAULT (empty in the other modes)."""
        return self._faults

    @property
    def conditions(self) -> Tuple[Fault, ...]:
        """Return the fault conditions present at the last ``update`` or ``arm``."""
        return self._conditions

    def check(self, now: float, s: SensorSnapshot,
              motor_reply_times: Mapping[int, Optional[float]]) -> Tuple[Fault, ...]:
        """Return the fault conditions present at time ``now`` [s] (empty tuple: none)."""
        return self._check(now, s, self._replies(motor_reply_times))

    def _replies(self, motor_reply_times: Mapping[int, Optional[float]]) -> ReplyTimes:
        """Return ``motor_reply_times`` as ``_check`` takes them (nothing while not commanding)."""
        if self._commanding_since is None:
            return ()
        get = motor_reply_times.get
        return ([(i, get(i)) for i in self.motor_ids],)

    def _check(self, now: float, s: SensorSnapshot, replies: ReplyTimes) -> Tuple[Fault, ...]:
        """``check`` with the reply times as ``update_replies`` takes them."""
        lim = self.limits
        found = None
        imu_time, joint_time = s.imu_time, s.joint_time
        if imu_time is None or now - imu_time > lim.imu_timeout:
            found = [Fault(IMU_STALE, 'no IMU sample yet' if imu_time is None else
                           'IMU silent for %.3f s (imu_timeout %.3f s)'
                           % (now - imu_time, lim.imu_timeout), now)]
        if joint_time is None or now - joint_time > lim.joint_state_timeout:
            found = found or []
            found.append(Fault(JOINT_STATES_STALE, 'no joint state yet' if joint_time is None
                               else 'joint states silent for %.3f s (joint_state_timeout %.3f s)'
                               % (now - joint_time, lim.joint_state_timeout), now))
        theta, theta_dot, roll = s.theta, s.theta_dot, s.roll
        if imu_time is None or joint_time is None:
            pass  # nothing measured yet: reported as stale above
        else:
            w_l, w_r = s.wheel_vel_left, s.wheel_vel_right
            max_rate, max_w = lim.max_pitch_rate, lim.max_wheel_velocity
            # s.finite() and lim.plausible(s) without the calls
            if not (isfinite(theta) and isfinite(theta_dot) and isfinite(w_l) and isfinite(w_r)
                    and isfinite(s.l)):
                found = found or []
                found.append(Fault(NON_FINITE, 'non-finite measurement: theta %r theta_dot %r '
                                   'wheel_vel %r %r l %r' % (theta, theta_dot, w_l, w_r, s.l),
                                   now))
            elif not (abs(theta_dot) <= max_rate and abs(w_l) <= max_w and abs(w_r) <= max_w):
                # Finite but impossible: one such sample would throw odometry and the
                # observer off.
                found = found or []
                found.append(Fault(IMPLAUSIBLE, 'implausible measurement: theta_dot %.4g rad/s '
                                   '(max %.4g), wheel_vel %.4g %.4g rad/s (max %.4g)'
                                   % (theta_dot, max_rate, w_l, w_r, max_w), now))
        if imu_time is not None:
            fall = lim.fall_angle
            if abs(theta) > fall:  # False for NaN
                found = found or []
                found.append(Fault(FALL, '|theta| %.1f deg > fall_angle %.1f deg'
                                   % (math.degrees(abs(theta)), math.degrees(fall)), now))
            fall = lim.fall_roll_angle
            if abs(roll) > fall:
                found = found or []
                found.append(Fault(ROLL, '|roll| %.1f deg > fall_roll_angle %.1f deg (lying on '
                                   'a side?)' % (math.degrees(abs(roll)), math.degrees(fall)),
                                   now))
        commanding_since = self._commanding_since
        if commanding_since is not None:
            timeout = lim.motor_timeout
            for motors in replies:
                for motor_id, last in motors:
                    if last is not None and now - last <= timeout:
                        continue   # answered lately: since >= last is within the timeout too
                    since = commanding_since if last is None else max(last, commanding_since)
                    if now - since > timeout:
                        found = found or []
                        found.append(Fault(MOTOR_SILENT, 'motor %d silent for %.3f s '
                                           '(motor_timeout %.3f s)' % (motor_id, now - since,
                                                                       timeout), now))
            if self._send_error is not None:
                found = found or []
                found.append(Fault(CAN_SEND, 'CAN send failed: %s' % self._send_error, now))
        return _NO_FAULTS if found is None else tuple(found)

    def update(self, now: float, s: SensorSnapshot,
               motor_reply_times: Mapping[int, Optional[float]]) -> Mode:
        """Run the checks of one control tick; a commanding mode goes to FAULT on any."""
        return self.update_replies(now, s, self._replies(motor_reply_times))

    def update_replies(self, now: float, s: SensorSnapshot, replies: ReplyTimes) -> Mode:
        """
        ``update`` with the reply times as groups of (motor ID, time [s] or None) pairs.

        The groups' pairs in turn are every motor of ``motor_ids``, in order: the tick passes
        its motor sets' live ``reply_times.items()`` (no merged map, no lookups per tick).
        """
        self._conditions = conditions = self._check(now, s, replies)
        if conditions and self._mode in COMMANDING:
            self._enter_fault(conditions)
        return self._mode

    def pose_problem(self, s: SensorSnapshot) -> Optional[str]:
        """Return why the pose is no place to arm from (None: on the tail, or upright, still)."""
        lim = self.limits
        on_tail = abs(s.theta - lim.tail_pitch) <= lim.tail_tolerance
        upright = abs(s.theta) <= lim.upright_pitch and abs(s.theta_dot) <= lim.still_rate
        if (on_tail or upright) and abs(s.roll) <= lim.tail_tolerance:
            return None
        return ('pose: pitch %.1f deg, roll %.1f deg, pitch rate %.2f rad/s is neither resting '
                'on the tail (%.0f +- %.0f deg) nor upright and still' % (
                    math.degrees(s.theta), math.degrees(s.roll), s.theta_dot,
                    math.degrees(lim.tail_pitch), math.degrees(lim.tail_tolerance)))

    def report_fault(self, now: float, code: str, message: str) -> Mode:
        """Report a fault found outside the checks (a loop stall, the legs): FAULT if commanded."""
        if self._mode in COMMANDING:
            self._enter_fault((Fault(code, message, now),))
        elif self._mode is Mode.FAULT and all(f.code != code for f in self._faults):
            self._faults = self._faults + (Fault(code, message, now),)
        return self._mode

    def report_send(self, now: float, ok: bool, message: str = '') -> Mode:
        """Record the outcome of a CAN send; a failure while BALANCING is a fault."""
        if ok:
            self._send_error = None
            return self._mode
        self._send_error = message or 'unknown error'
        fault = Fault(CAN_SEND, 'CAN send failed: %s' % self._send_error, now)
        if self._mode in COMMANDING:
            self._enter_fault((fault,))
        elif self._mode is Mode.FAULT and all(f.code != CAN_SEND for f in self._faults):
            self._faults = self._faults + (fault,)
        return self._mode

    def report_internal_error(self, now: float, message: str) -> Mode:
        """Report an exception in the control tick: BALANCING goes to FAULT (the node lives on)."""
        if self._mode is not Mode.DISARMED:
            fault = Fault(INTERNAL, 'internal error: %s' % message, now)
            if self._mode in COMMANDING:
                self._enter_fault((fault,))
            elif all(f.code != INTERNAL for f in self._faults):
                self._faults = self._faults + (fault,)
        return self._mode

    def arm(self, now: float, s: SensorSnapshot,
            motor_reply_times: Mapping[int, Optional[float]]) -> Tuple[bool, str]:
        """
        Request BALANCING (from DISARMED or, as the explicit re-arm, from FAULT).

        Returns (accepted, reason). Refused while any fault condition is present, and from a
        pose that is neither resting on the tail nor upright and still. From DISARMED the
        motors have not been commanded, so their replies and the CAN sends are judged from
        ``now`` on (the node sends the enter-motor-mode frames right after). From HOMING (the
        legs are done) it goes on balancing with the motors already commanded.
        """
        if self._mode is Mode.BALANCING or self._mode is Mode.SITTING:
            return True, 'already balancing'
        return self._start(now, s, motor_reply_times, Mode.BALANCING, 'balancing')

    def start_homing(self, now: float, s: SensorSnapshot,
                     motor_reply_times: Mapping[int, Optional[float]]) -> Tuple[bool, str]:
        """Request HOMING (the legs before the first arm), with arm's checks and pose rule."""
        return self._start(now, s, motor_reply_times, Mode.HOMING, 'homing the legs')

    def start_exciting(self, now: float, s: SensorSnapshot,
                       motor_reply_times: Mapping[int, Optional[float]]) -> Tuple[bool, str]:
        """Request EXCITING (an identification phase) from DISARMED, with arm's checks."""
        if self._mode is not Mode.DISARMED:
            return False, 'not disarmed (mode %s)' % self._mode.name
        return self._start(now, s, motor_reply_times, Mode.EXCITING, 'exciting')

    def _start(self, now, s, motor_reply_times, mode: Mode, what: str) -> Tuple[bool, str]:
        self._conditions = self.check(now, s, motor_reply_times)
        if self._conditions:
            return False, 'arming refused: ' + '; '.join(f.message for f in self._conditions)
        pose = self.pose_problem(s)
        if pose is not None:
            self._conditions = (Fault(POSE, pose, now),)
            return False, 'arming refused: ' + pose
        if self._mode not in COMMANDING:
            self._commanding_since = now
            self._send_error = None  # judged again by the enter-motor-mode frames that follow
        self._mode = mode
        self._faults = _NO_FAULTS
        return True, what

    def sit_down(self) -> bool:
        """Go from BALANCING to SITTING (the sit-down sequence); False from any other mode."""
        if self._mode is not Mode.BALANCING:
            return False
        self._mode = Mode.SITTING
        return True

    def disarm(self) -> None:
        """Go to DISARMED (from any mode): the node sends zero torque, then exit motor mode."""
        self._mode = Mode.DISARMED
        self._faults = _NO_FAULTS
        self._commanding_since = None

    def _enter_fault(self, faults: Tuple[Fault, ...]) -> None:
        self._mode = Mode.FAULT
        self._faults = faults
