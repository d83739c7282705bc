"""
Safety supervisor of balance_node and the shaping of the operator's reference.

``SafetySupervisor`` is a three-mode state machine (no rclpy, no python-can: the node feeds it
monotonic times and the newest samples every control tick):

- ``DISARMED``: motors in rest mode, no torque. Fault conditions are evaluated and reported, but
  they do not change the mode; ``arm`` is refused with a reason while one is present.
- ``BALANCING``: the controller's torques go to the wheels. Any fault condition moves to FAULT.
- ``FAULT``: zero torque, latched reasons. FAULT is never left by itself: only an explicit
  ``arm`` (re-arm, refused while a condition is still present) or ``disarm``.

Fault conditions (checked every tick): stale IMU (``imu_timeout``), stale joint states
(``joint_state_timeout``), a non-finite measurement, |theta~| > ``fall_angle``, a motor that has
not answered within ``motor_timeout`` while it is being commanded, and a failed CAN send. An
exception inside the control tick (a bug) is reported as ``internal_error`` and treated alike.
The robot rests on its tail at about +36 deg, inside ``fall_angle`` (45 deg): arming there is the
paper's start-up experiment (Sec. V-B 1), so it is allowed.

A stale cmd_vel is *not* a fault: ``ReferenceShaper`` brings x_dot* and yaw rate* to zero through
acceleration then velocity limits (as ros2_controllers' diff_drive_controller speed limiter)
while the robot keeps balancing.
"""
from dataclasses import dataclass
import enum
import math
from typing import Mapping, Optional, Tuple

IMU_STALE = 'imu_stale'
JOINT_STATES_STALE = 'joint_states_stale'
NON_FINITE = 'non_finite'
IMPLAUSIBLE = 'implausible'
FALL = 'fall'
MOTOR_SILENT = 'motor_silent'
CAN_SEND = 'can_send'
INTERNAL = 'internal_error'

#: Every fault code, in the order the checks run.
FAULT_CODES = (IMU_STALE, JOINT_STATES_STALE, NON_FINITE, IMPLAUSIBLE, FALL, MOTOR_SILENT,
               CAN_SEND, INTERNAL)


class Mode(enum.IntEnum):
    """Operating mode; the integer is what the state topic publishes."""

    DISARMED = 0
    BALANCING = 1
    FAULT = 2


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
    """

    fall_angle: float = math.radians(45.0)
    imu_timeout: float = 0.05
    joint_state_timeout: float = 0.05
    motor_timeout: float = 0.05
    max_pitch_rate: float = 35.0
    max_wheel_velocity: float = 200.0

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
    wheel_vel_left / wheel_vel_right [rad/s]; l: height [m].
    """

    imu_time: Optional[float] = None
    joint_time: Optional[float] = None
    theta: float = math.nan
    theta_dot: float = math.nan
    wheel_vel_left: float = math.nan
    wheel_vel_right: float = math.nan
    l: float = math.nan

    def finite(self) -> bool:
        """Return True when every measured value is finite."""
        return (math.isfinite(self.theta) and math.isfinite(self.theta_dot)
                and math.isfinite(self.wheel_vel_left) and math.isfinite(self.wheel_vel_right)
                and math.isfinite(self.l))


_NO_FAULTS: Tuple[Fault, ...] = ()


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
        """Return True only while BALANCING: other modes send zero torque or nothing."""
        return self._mode is Mode.BALANCING

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
        lim = self.limits
        found = None
        if s.imu_time is None or now - s.imu_time > lim.imu_timeout:
            found = [Fault(IMU_STALE, 'no IMU sample yet' if s.imu_time is None else
                           'IMU silent for %.3f s (imu_timeout %.3f s)'
                           % (now - s.imu_time, lim.imu_timeout), now)]
        if s.joint_time is None or now - s.joint_time > lim.joint_state_timeout:
            found = found or []
            found.append(Fault(JOINT_STATES_STALE, 'no joint state yet' if s.joint_time is None
                               else 'joint states silent for %.3f s (joint_state_timeout %.3f s)'
                               % (now - s.joint_time, lim.joint_state_timeout), now))
        if s.imu_time is None or s.joint_time is None:
            pass  # nothing measured yet: reported as stale above
        elif not s.finite():
            found = found or []
            found.append(Fault(NON_FINITE, 'non-finite measurement: theta %r theta_dot %r '
                               'wheel_vel %r %r l %r' % (s.theta, s.theta_dot, s.wheel_vel_left,
                                                         s.wheel_vel_right, s.l), now))
        elif not lim.plausible(s):
            # Finite but impossible: one such sample would throw odometry and the observer off.
            found = found or []
            found.append(Fault(IMPLAUSIBLE, 'implausible measurement: theta_dot %.4g rad/s '
                               '(max %.4g), wheel_vel %.4g %.4g rad/s (max %.4g)'
                               % (s.theta_dot, lim.max_pitch_rate, s.wheel_vel_left,
                                  s.wheel_vel_right, lim.max_wheel_velocity), now))
        if s.imu_time is not None and abs(s.theta) > lim.fall_angle:  # False for NaN
            found = found or []
            found.append(Fault(FALL, '|theta| %.1f deg > fall_angle %.1f deg'
                               % (math.degrees(abs(s.theta)), math.degrees(lim.fall_angle)), now))
        if self._commanding_since is not None:
            for motor_id in self.motor_ids:
                last = motor_reply_times.get(motor_id)
                since = self._commanding_since if last is None else max(last,
                                                                        self._commanding_since)
                if now - since > lim.motor_timeout:
                    found = found or []
                    found.append(Fault(MOTOR_SILENT, 'motor %d silent for %.3f s '
                                       '(motor_timeout %.3f s)' % (motor_id, now - since,
                                                                   lim.motor_timeout), now))
        if self._send_error is not None and self._commanding_since is not None:
            found = found or []
            found.append(Fault(CAN_SEND, 'CAN send failed: %s' % self._send_error, now))
        return _NO_FAULTS if found is None else tuple(found)

    def update(self, now: float, s: SensorSnapshot,
               motor_reply_times: Mapping[int, Optional[float]]) -> Mode:
        """Run the checks of one control tick; BALANCING goes to FAULT on any condition."""
        self._conditions = self.check(now, s, motor_reply_times)
        if self._conditions and self._mode is Mode.BALANCING:
            self._enter_fault(self._conditions)
        return self._mode

    def report_send(self, now: float, ok: bool, message: str = '') -> Mode:
        """Record the outcome of a CAN send; a failure while BALANCING is a fault."""
        if ok:
            self._send_error = None
            return self._mode
        self._send_error = message or 'unknown error'
        fault = Fault(CAN_SEND, 'CAN send failed: %s' % self._send_error, now)
        if self._mode is Mode.BALANCING:
            self._enter_fault((fault,))
        elif self._mode is Mode.FAULT and all(f.code != CAN_SEND for f in self._faults):
            self._faults = self._faults + (fault,)
        return self._mode

    def report_internal_error(self, now: float, message: str) -> Mode:
        """Report an exception in the control tick: BALANCING goes to FAULT (the node lives on)."""
        if self._mode is not Mode.DISARMED:
            fault = Fault(INTERNAL, 'internal error: %s' % message, now)
            if self._mode is Mode.BALANCING:
                self._enter_fault((fault,))
            elif all(f.code != INTERNAL for f in self._faults):
                self._faults = self._faults + (fault,)
        return self._mode

    def arm(self, now: float, s: SensorSnapshot,
            motor_reply_times: Mapping[int, Optional[float]]) -> Tuple[bool, str]:
        """
        Request BALANCING (from DISARMED or, as the explicit re-arm, from FAULT).

        Returns (accepted, reason). Refused while any fault condition is present. From DISARMED
        the motors have not been commanded, so their replies and the CAN sends are judged from
        ``now`` on (the node sends the enter-motor-mode frames right after).
        """
        if self._mode is Mode.BALANCING:
            return True, 'already balancing'
        self._conditions = self.check(now, s, motor_reply_times)
        if self._conditions:
            return False, 'arming refused: ' + '; '.join(f.message for f in self._conditions)
        if self._mode is Mode.DISARMED:
            self._commanding_since = now
            self._send_error = None  # judged again by the enter-motor-mode frames that follow
        self._mode = Mode.BALANCING
        self._faults = _NO_FAULTS
        return True, 'balancing'

    def disarm(self) -> None:
        """Go to DISARMED (from any mode): the node sends zero torque, then exit motor mode."""
        self._mode = Mode.DISARMED
        self._faults = _NO_FAULTS
        self._commanding_since = None

    def _enter_fault(self, faults: Tuple[Fault, ...]) -> None:
        self._mode = Mode.FAULT
        self._faults = faults


def limit_rate(target: float, previous: float, max_rate: float, dt: float) -> float:
    """Move from ``previous`` towards ``target`` by at most ``max_rate * dt``."""
    step = max_rate * dt
    return min(max(target, previous - step), previous + step)


class ReferenceShaper:
    """
    Shapes cmd_vel into the references x_dot* [m/s] and yaw rate* [rad/s].

    Per axis, as diff_drive_controller's SpeedLimiter: first the acceleration limit (relative to
    the previous reference), then the velocity limit. A command older than ``cmd_vel_timeout``
    [s] counts as zero, so the references ramp down to zero at the acceleration limits.
    """

    def __init__(self, max_velocity: float = 1.0, max_acceleration: float = 1.0,
                 max_yaw_rate: float = 3.0, max_yaw_acceleration: float = 6.0,
                 cmd_vel_timeout: float = 0.5):
        self.max_velocity = max_velocity
        self.max_acceleration = max_acceleration
        self.max_yaw_rate = max_yaw_rate
        self.max_yaw_acceleration = max_yaw_acceleration
        self.cmd_vel_timeout = cmd_vel_timeout
        self.x_dot_ref = 0.0
        self.yaw_rate_ref = 0.0
        self.timed_out = True

    def reset(self) -> None:
        """Start from rest (on arm)."""
        self.x_dot_ref = 0.0
        self.yaw_rate_ref = 0.0

    def update(self, now: float, cmd_time: Optional[float], x_dot_cmd: float,
               yaw_rate_cmd: float, dt: float) -> Tuple[float, float]:
        """
        Advance one tick of ``dt`` [s] towards the newest command.

        cmd_time is the monotonic receipt time of the command [s] (None: none yet).
        Returns (x_dot*, yaw rate*).
        """
        self.timed_out = cmd_time is None or now - cmd_time > self.cmd_vel_timeout
        if self.timed_out:
            x_dot_cmd = yaw_rate_cmd = 0.0
        x = limit_rate(x_dot_cmd, self.x_dot_ref, self.max_acceleration, dt)
        self.x_dot_ref = min(max(x, -self.max_velocity), self.max_velocity)
        w = limit_rate(yaw_rate_cmd, self.yaw_rate_ref, self.max_yaw_acceleration, dt)
        self.yaw_rate_ref = min(max(w, -self.max_yaw_rate), self.max_yaw_rate)
        return self.x_dot_ref, self.yaw_rate_ref
