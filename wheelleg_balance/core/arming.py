"""
The arming and health supervisor of the tick: every reason to refuse or to fault.

Beside core/safety.py (the mode machine and the sensor checks, ``SafetySupervisor``), this part
decides what the tick may do (no rclpy, no CAN): an arm or a disarm request, the one-time
``auto_arm``, an emergency stop; and it judges what only the whole robot tells: the motors'
health (error codes, reboots, heat: core/motor_health.py), another commander on the bus, a
conflict on a sensor input, a loop that stalled, the pitch answering the torque with the wrong
sign (core/response.py) and a robot picked up (core/lift.py).

``request`` returns what the tick must carry out, an ``Action``: STOP (zero torque, exit motor
mode), SIT (the sit-down), HOME (homing and raising the legs), BALANCE (balancing begins); the
reply to the operator is kept until ``reply`` hands it over once the frames went out.
"""
import math
from typing import Any, Dict, List, NamedTuple, Optional, Tuple

from .config import BalanceConfig
from .lift import FREE_FALL, FreeWheelNotice, LiftDetector
from .motor_health import judge_motors
from .response import MAX_PITCH as RESPONSE_PITCH, ResponseCheck
from .safety import BALANCING, COMMANDING, DISARMED, EXCITING, FAULT, HOMING, IMU_STALE, \
    INPUT_CONFLICT, LEGS, LIFTED, LOOP_STALL, Mode, OVER_TEMPERATURE, RESPONSE, SafetyLimits, \
    SafetySupervisor, SensorSnapshot, SITTING
from .sensing import motor_name

#: auto_arm waits until the ticks have come without a gap beyond the sensor timeouts for this
#: long [s]. In lockstep (clock_source imu_stamp) the first samples can come as a burst of old
#: stamps: a tick armed on one of them and the next, 0.38 s of stamps later, faulted the motors
#: as silent since the arm (sim-files test, 2026-12-02).
AUTO_ARM_STEADY = 0.05
#: The inputs whose conflicts are about the sensors (TickInputs.conflicts): FAULT, no arming.
SENSOR_INPUTS = ('imu', 'joint_states')
#: -MAX_PITCH of the response check: |theta| <= MAX_PITCH as two comparisons.
_RESPONSE_PITCH_LOW = -RESPONSE_PITCH
#: What the tick carries out for a decision (``Action.kind``).
STOP, SIT, HOME, BALANCE = 'stop', 'sit', 'home', 'balance'


class Action(NamedTuple):
    """A decision for the tick: its kind, and for BALANCE whether the motors were enabled."""

    kind: str
    enabled: bool = False


def safety_limits(cfg: BalanceConfig) -> SafetyLimits:
    """Return the supervisor's thresholds from the configuration."""
    s = cfg.safety
    return SafetyLimits(fall_angle=s.fall_angle, imu_timeout=s.imu_timeout,
                        joint_state_timeout=s.joint_state_timeout,
                        motor_timeout=s.motor_timeout, max_pitch_rate=s.max_pitch_rate,
                        max_wheel_velocity=s.max_wheel_velocity,
                        fall_roll_angle=s.fall_roll_angle, tail_pitch=s.tail_pitch,
                        tail_tolerance=s.arm_pose_tolerance, upright_pitch=s.arm_upright_pitch,
                        still_rate=s.arm_still_rate)


class ArmingSupervisor:
    """The arming and health supervisor (see the module docstring)."""

    def __init__(self, cfg: BalanceConfig, sensing, legs):
        """Build it over the tick's sensing (core/sensing.py) and leg task (core/leg_task.py)."""
        self.sensing, self.legs = sensing, legs
        self.p = cfg.model
        self.safety = SafetySupervisor(safety_limits(cfg), [m.motor_id
                                                            for m in sensing.all_motors])
        self.motion = MotionChecks(cfg, sensing, legs)
        self.lift, self.response = self.motion.lift, self.motion.response
        self.lifted = False   # since the lifted fault, until an arm on the ground
        self.auto_arm = cfg.safety.auto_arm
        #: The tick since which no gap beyond the sensor timeouts came [s] (AUTO_ARM_STEADY).
        self.steady_since: Optional[float] = None
        #: Why the motors are not fit to arm (errors, reboots, heat), from the newest tick.
        self.motor_problems: List[str] = []
        #: Why inputs are refused for their publishers (TickInputs.conflicts), '' for none.
        self.input_conflicts = ''
        self.sensor_conflict = ''
        self._pending: Optional[Tuple[str, bool, str]] = None
        # The safety checks' reply times: the motor sets' own maps, live (core/motors.py
        # updates them in place), where they hold the supervisor's motors in its order, instead
        # of the map sensing.reply_times() merges anew (None: that one, IDs shared by a set).
        wheels = sensing.motors.reply_times
        hips = sensing.hips.reply_times if sensing.hips is not None else {}
        # (The maps, not their items() views: a loop is deep-copied, views cannot be.)
        self._replies = (wheels, hips) if not wheels.keys() & hips.keys() \
            and list(wheels) + list(hips) == list(self.safety.motor_ids) else None
        self.configure(cfg)

    def configure(self, cfg: BalanceConfig) -> None:
        """Take the live settings of ``cfg`` (at build and on every parameter change)."""
        self.safety.limits = safety_limits(cfg)
        self.motion.configure(cfg)

    @property
    def mode(self) -> Mode:
        """Return the mode."""
        return self.safety._mode

    def begin(self, now: float, dt: float) -> float:
        """Start a tick ``dt`` [s] after the last; return the longest gap that is no stall."""
        lim = self.safety.limits
        imu, joints = lim.imu_timeout, lim.joint_state_timeout
        stall_limit = joints if joints < imu else imu   # min(imu, joints)
        if self.steady_since is None or dt > stall_limit:
            self.steady_since = now
        return stall_limit

    # --------------------------------------------------------------------- motor health

    def motor_health(self, now: float) -> Tuple[float, Optional[str]]:
        """
        Judge the motors' newest replies; return (the wheels' torque scale, why too hot).

        An error code or a reboot: FAULT. Heat: the wheels' torque limit derated; at temp_max
        balancing ends with the sit-down (the caller's, ``hot``) or, homing, a FAULT. Every
        problem refuses arming (``motor_problems``).
        """
        sensing = self.sensing
        scale, hot, problems = judge_motors(sensing.health, sensing.motors, motor_name,
                                            self.safety._mode in COMMANDING)
        if problems:
            for code, text in problems:
                if code:
                    self.safety.report_fault(now, code, text)
            self.motor_problems = [text for _, text in problems]
        else:
            self.motor_problems = []
        if hot is not None and self.safety._mode is HOMING:
            self.safety.report_fault(now, OVER_TEMPERATURE, hot)
        return scale, hot

    def sit_down_possible(self) -> bool:
        """Return True when the sensors allow the controlled sit-down (else: cut at once)."""
        return not self.safety.conditions

    def sit_down(self) -> bool:
        """Go from BALANCING to SITTING where the sit-down can run; False where it cannot."""
        return self.sit_down_possible() and self.safety.sit_down()

    # ------------------------------------------------------------------------- requests

    def request(self, now: float, inputs, s: SensorSnapshot, events: list) -> Optional[Action]:
        """Decide an emergency stop, an arm or disarm request, or auto_arm (module docstring)."""
        conflicts = inputs.conflicts
        if conflicts:
            self.sensor_conflict = '; '.join(conflicts[k] for k in SENSOR_INPUTS
                                             if k in conflicts)
            self.input_conflicts = '; '.join(conflicts.values())
        else:
            self.sensor_conflict = self.input_conflicts = ''
        sup = self.safety
        if inputs.estop:
            self.auto_arm = False
            if sup._mode in COMMANDING:
                events.append(('warn', 'emergency stop: zero torque, motors to rest'))
            return self._stop(False)
        if inputs.arm is not None:
            self.auto_arm = False  # the operator decides from now on
            action = None
            if inputs.arm and not inputs.guarded:
                self._pending = ('refused', False, 'arming refused: the watchdog is not '
                                 'watching the control loop yet')
            elif inputs.arm and self.sensor_conflict:
                self._pending = ('refused', False, 'arming refused: ' + self.sensor_conflict)
            else:
                action = self._arm(inputs.arm, now, s)
            self.lifted = self.lifted and sup._mode not in COMMANDING
            return action
        if self.auto_arm and inputs.guarded and not self.sensor_conflict \
                and sup._mode is DISARMED and now - self.steady_since >= AUTO_ARM_STEADY \
                and self._can_arm(now, s):
            self.auto_arm = False  # at most once per start, whatever the outcome
            action = self._arm(True, now, s)
            events.append(('info', 'auto_arm: %s' % self._pending[2]))
            return action
        return None

    def _arm(self, arm: bool, now: float, s: SensorSnapshot) -> Optional[Action]:
        sup = self.safety
        if not arm:
            if sup._mode is BALANCING and self.sit_down():
                self._pending = ('sit', True, 'sitting down: lowering, leaning onto the tail, '
                                 'then zero torque')
                return Action(SIT)
            return self._stop(True)
        reason = self._refusal(now, s)
        if sup._mode is BALANCING or sup._mode is SITTING:
            self._pending = ('noop', True, 'already balancing')
        elif sup._mode is EXCITING:
            self._pending = ('refused', False, 'arming refused: an excitation phase runs '
                             '(~/stop or ~/arm false ends it)')
        elif reason:
            self._pending = ('refused', False, 'arming refused: %s' % reason)
        elif not self.legs.ready():
            plan = self.legs.homing_plan()
            ok, reason = sup.start_homing(now, s, self.sensing.reply_times())
            self._pending = ('arm', True, plan) if ok else ('refused', False, reason)
            return Action(HOME) if ok else None
        else:
            return self.start_balancing(now, s, reply_needed=True)
        return None

    def _refusal(self, now: float, s: SensorSnapshot) -> str:
        """Return why the motors or the robot are not fit to arm ('' when they are)."""
        sensing = self.sensing
        silent = sensing.silent_motor(now, self.safety.limits.motor_timeout)
        if silent is not None:
            return silent
        if self.motor_problems:
            return '; '.join(self.motor_problems)
        foreign = sensing.foreign_reason(now)
        if foreign:
            return foreign
        if self.lifted and not self._on_ground(s):
            return ('lifted, and not back on the ground (the legs carry no weight and it is '
                    'not on its tail)')
        return ''

    def start_balancing(self, now: float, s: SensorSnapshot,
                        reply_needed: bool) -> Optional[Action]:
        """Go to BALANCING (an arm, or the legs raised after HOMING): the BALANCE action."""
        sup = self.safety
        from_homing = sup._mode is HOMING
        ok, reason = sup.arm(now, s, self.sensing.reply_times())
        if ok:
            if reply_needed:
                self._pending = ('arm', True, reason)
            return Action(BALANCE, enabled=from_homing)
        if reply_needed:
            self._pending = ('refused', False, reason)
        else:
            sup.report_fault(now, LEGS, 'homed, but %s' % reason)
        return None

    def start_exciting(self, now: float, s: SensorSnapshot, guarded: bool) -> str:
        """
        Go from DISARMED to EXCITING (core/excitation.py's stand, tail) with arming's checks.

        guarded: TickInputs.guarded. Returns '' when it did, else why not.
        """
        if not guarded:
            return 'the watchdog is not watching the control loop yet'
        reason = self.sensor_conflict or self._refusal(now, s)
        if reason:
            return reason
        ok, reason = self.safety.start_exciting(now, s, self.sensing.reply_times())
        return '' if ok else reason.replace('arming refused: ', '', 1)   # the caller's words

    def answer(self, ok: bool, message: str) -> None:
        """Hand the operator's pending request (an excitation's) its reply with this tick's."""
        self._pending = ('excite', ok, message)

    def disarm(self) -> Action:
        """Disarm (the sit-down ended): the STOP action."""
        return self._stop(False)

    def _stop(self, reply: bool) -> Action:
        self.safety.disarm()
        if reply:
            self._pending = ('disarm', True, 'disarmed')
        return Action(STOP)

    def _on_ground(self, s: SensorSnapshot) -> bool:
        """Return True when the robot rests on its tail or its legs carry weight."""
        lim = self.safety.limits
        if abs(s.theta - lim.tail_pitch) <= lim.tail_tolerance:
            return True
        return not self.legs.driven or self.legs.load() >= self.lift.min_load

    def _can_arm(self, now: float, s: SensorSnapshot) -> bool:
        """Return True when an arm request would be accepted now (for auto_arm)."""
        sup, sensing = self.safety, self.sensing
        return not sup.check(now, s, sensing.reply_times()) and sup.pose_problem(s) is None \
            and sensing.silent_motor(now, sup.limits.motor_timeout) is None \
            and not self.motor_problems and not sensing.foreign_reason(now)

    # --------------------------------------------------------------------------- checks

    def check(self, now: float, s: SensorSnapshot, dt: float, stall_limit: float,
              commanded: bool, imu_silent: str, tau_left: float, tau_right: float,
              d_hat: float, rising: bool, events: list) -> Mode:
        """
        Run the checks of a tick; a commanding mode goes to FAULT on any. Return the mode.

        commanded: the motors were commanded since the previous tick (a gap before an arm
        held no torque of ours); imu_silent: TickInputs.imu_silent; tau_left, tau_right: the
        wheel torques of the last tick [N m] (applied since); d_hat [rad]; rising: from the
        tail. (The supervisor's ``_mode`` is read directly: the property costs a call a use.)
        """
        sup = self.safety
        before = sup._mode
        if self._replies is not None:
            wheels, hips = self._replies
            sup.update_replies(now, s, (wheels.items(), hips.items()))
        else:
            sup.update(now, s, self.sensing.reply_times())
        foreign = self.sensing.new_foreign_command()
        if foreign:   # another sender commands our motors: two masters
            sup.report_fault(now, INPUT_CONFLICT, foreign)
        if self.sensor_conflict:   # samples from two sources cannot be trusted
            sup.report_fault(now, INPUT_CONFLICT, self.sensor_conflict)
        if imu_silent:
            sup.report_fault(now, IMU_STALE, imu_silent)
        if commanded and dt > stall_limit and sup._mode in COMMANDING:
            sup.report_fault(now, LOOP_STALL, 'control loop stalled %.1f ms (longer than the '
                             'sensor timeouts, %.0f ms)' % (1e3 * dt, 1e3 * stall_limit))
        if self.motion.check(now, s, dt, tau_left, tau_right, d_hat, rising, sup):
            self.lifted = True
        mode = sup._mode
        if mode is FAULT and before in COMMANDING:
            self.auto_arm = False
            events.append(('error', 'FAULT: ' + '; '.join(f.message for f in sup.faults)))
        return mode

    # ---------------------------------------------------------------------- the reply

    def reply(self, now: float, sent: bool, error: Optional[str],
              events: list) -> Optional[Tuple[bool, str]]:
        """
        Record how this tick's sends went; return the pending arm/disarm reply, if any.

        sent: the tick sent frames; error: None when all went out, else why not. A failed send
        while commanding is a fault (its line goes to ``events``).
        """
        if sent or error is not None:
            before = self.safety._mode
            self.safety.report_send(now, error is None, error or '')
            if error is not None and before in COMMANDING:
                events.append(('error', 'FAULT: CAN send failed: %s' % error))
        pending, self._pending = self._pending, None
        if pending is None:
            return None
        kind, ok, message = pending
        if error is not None and kind == 'arm':
            ok, message = False, 'enter motor mode failed: %s' % error
        elif error is not None and kind == 'disarm':
            ok, message = False, 'disarmed, but %s' % error
        return ok, message

    def internal_error(self, now: float, message: str) -> Optional[Tuple[bool, str]]:
        """Report an exception that escaped a tick; return a failed pending reply, if any."""
        self.safety.report_internal_error(now, message)
        pending, self._pending = self._pending, None
        return None if pending is None else (False, 'internal error: %s' % message)

    def status(self) -> Dict[str, Any]:
        """Return the supervisor's part of /diagnostics."""
        sup = self.safety
        return {'mode': sup.mode.name, 'mode_index': int(sup.mode),
                'faults': [(f.code, f.message) for f in sup.faults],
                'conditions': [(f.code, f.message) for f in sup.conditions],
                'input_conflicts': self.input_conflicts}


class MotionChecks:
    """
    What the body's motion tells: a robot picked up, a pitch of the wrong sign.

    Picked up: core/lift.py; the pitch answering the torque with the wrong sign:
    core/response.py. Both judge the torques of the last tick against what the wheels and the
    IMU did since.
    """

    def __init__(self, cfg: BalanceConfig, sensing, legs):
        self.sensing, self.legs, self.p = sensing, legs, cfg.model
        sc = cfg.safety
        self.lift = LiftDetector(sc.lift_wheel_inertia, sc.lift_window, sc.lift_min_dv,
                                 sc.lift_ratio, sc.lift_free_time,
                                 wheel_radius=self.p.wheel_radius, gravity=self.p.gravity)
        self.response = ResponseCheck(self.p, sc.response_window, sc.response_min_effect,
                                      sc.response_gain, sc.response_time)
        #: Planned free wheels (the stand phase, a flight): neither check judges meanwhile.
        self.free_wheels = FreeWheelNotice()
        self.configure(cfg)

    def configure(self, cfg: BalanceConfig) -> None:
        """Take the live settings of ``cfg`` (at build and on every parameter change)."""
        lift, sc = self.lift, cfg.safety
        lift.window, lift.min_dv, lift.ratio = sc.lift_window, sc.lift_min_dv, sc.lift_ratio
        lift.free_time = sc.lift_free_time
        lift.min_load = sc.lift_min_load * 0.5 * self.p.body_mass * self.p.gravity \
            if self.legs.driven else -math.inf
        lift.unloaded_time = sc.lift_unloaded_time
        lift.still_window, lift.still_min_dv = sc.lift_still_window, sc.lift_still_min_dv
        lift.still_ratio = sc.lift_still_ratio
        resp = self.response
        resp.window, resp.min_effect = sc.response_window, sc.response_min_effect
        resp.gain, resp.hold = sc.response_gain, sc.response_time

    def check(self, now: float, s: SensorSnapshot, dt: float, tau_left: float,
              tau_right: float, d_hat: float, rising: bool, sup: SafetySupervisor) -> bool:
        """
        Run both checks on ``sup`` (the response first); return True when lifted.

        The response (core/response.py): a fault when the pitch answers the wheel torque with
        the wrong sign, judged where model (1) holds: the wheels commanded, near upright (the
        tail off the ground), not in free fall. The lift (core/lift.py): a fault when the
        wheels spin free; the legs then hold. Both see the torques of the last tick [N m].
        Neither judges while ``free_wheels`` (a planned free-wheel window: the stand phase, a
        flight) covers the tick.
        """
        mode = sup._mode
        if not (mode is BALANCING or mode is SITTING or mode is EXCITING) \
                or now < self.free_wheels.until:   # free_wheels.covers(now)
            self.response.reset()
            self.lift.reset()
            return False
        p, lift = self.p, self.lift
        specific_force = self.sensing.imu.specific_force
        theta = s.theta - d_hat
        falling = lift.accel_seen and specific_force < FREE_FALL * p.gravity  # False for NaN
        u = (tau_left + tau_right) / p.wheel_radius
        reason = self.response.update(now, theta, s.theta_dot, u, s.l, dt,
                                      _RESPONSE_PITCH_LOW <= theta <= RESPONSE_PITCH
                                      and not falling, s.imu_time)
        if reason is not None:
            sup.report_fault(now, RESPONSE, reason)
            return False
        # Rising from the tail or sitting down onto it, the tail carries part of the weight,
        # and a body tipping over (a push, a fall) unloads the legs too: their load tells
        # only while balancing near upright.
        near_upright = abs(theta) <= sup.limits.upright_pitch
        load = self.legs.load() if not rising and near_upright and mode is BALANCING \
            else math.nan
        # The wheels' rotation in the world (the encoders read it relative to the leg): a
        # free wheel's follows the torque alone, whatever the body does. The still-body rule
        # needs model (1): near upright, the tail off the ground.
        theta_dot = s.theta_dot
        reason = lift.step(now, tau_left, tau_right, s.wheel_vel_left + theta_dot,
                           s.wheel_vel_right + theta_dot, dt, load,
                           theta_dot if near_upright else math.nan, s.l, specific_force)
        if reason is None:
            return False
        self.legs.lifted()
        sup.report_fault(now, LIFTED, reason)
        return True
