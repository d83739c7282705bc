"""
The control tick of balance_node as one object (no rclpy, no python-can).

``BalanceLoop.tick(now, inputs)`` takes the time and everything that arrived since the last tick
(IMU and joint samples, the motors' CAN replies, the newest cmd_vel and cmd_height, an arm or
disarm request, parameter changes) and returns the CAN frames to send and the state to publish.
The node is a shell around it: it collects the inputs, calls ``tick`` every 2 ms, sends the
frames, reports the send's outcome back (``report_send``) and publishes. Given the same inputs
the tick does the same thing, so a fault test, a fuzz case, a benchmark and an offline run drive
this very object with a fake clock.

One tick, in order (docs/architecture.md draws it):

1. parameter changes (validated by the caller against core/config.py) take effect;
2. samples: ``ImuReader`` (roll and theta~ from the whole orientation, the IMU's mounting
   applied; a frozen driver dropped), the motors' replies (``MotorSet``: liveness, feedback),
   from which the wheel speeds (core/wheel_state.py, ``wheel_state_source: can``) and the legs'
   joint angles and height l (core/legs.py); or the wheels and legs from another driver's
   joint states (``wheel_state_source: joint_states``);
3. the wheel odometry (core/estimation.py) advances while not balancing (``BalanceCore`` moves
   it while balancing: one odometry, one odom pose);
4. an arm or disarm request, or the one-time ``auto_arm``, is decided by the safety supervisor
   (core/safety.py): arming homes the legs first where their angles are not known, and arms
   only from a plausible pose; a disarm while balancing starts the sit-down sequence;
5. the supervisor's checks: a commanded mode goes to FAULT on any condition, and on a command
   frame to our motors that this node did not send (another sender on the bus, decided by the
   protocol: ``command_motor_ids``; arming waits until none came for FOREIGN_COMMAND_HOLD);
6. per mode: HOMING (the legs before balancing): zero wheel torque, the hips' homing ramp where
   their angles are not known yet, then the legs raised on the tail to height_min, the start
   of the paper's start-up (Sec. V-B 1); BALANCING: the reference shaping (core/reference.py)
   of cmd_vel, ``BalanceCore.step`` (observer (8), the controller, the torque split of
   Sec. V-A), one torque frame per wheel motor through its ID and direction, and the hips'
   impedance commands for the shaped height and the roll levelling; SITTING: the same, with
   the sit-down's lean and brake (core/sit_down.py), then DISARMED; FAULT: zero wheel torque
   every tick, the hips damping (the body is lowered, not dropped); DISARMED: nothing but,
   every few ticks, exit frames that keep the motors' replies (and so their liveness and the
   wheel and hip readings) coming while they rest.
"""
import math
from typing import Any, Dict, List, Mapping, Optional, Tuple

import numpy as np

from .config import BalanceConfig
from .estimation import WheelOdometry
from .kinematics import FiveBarLeg
from .legs import (HeightShaper, HipHoming, HipMotors, HomingConfig, LEFT_LEG, LegController,
                   LegGains, LegState, RIGHT_LEG, RollLeveller, split_heights)
from .lift import FREE_FALL, LiftDetector
from .motor_health import derate, error_reason
from .motors import MotorSet
from .pipeline import BalanceCore, CONTROLLER_NAMES, CoreConfig, Measurement, Reference
from .protocols import make_protocol
from .protocols.base import Frame, MotorProtocol
from .protocols.mit import MitProtocol
from .reference import ReferenceShaper
from .response import MAX_PITCH as RESPONSE_PITCH, ResponseCheck
from .safety import COMMANDING, IMU_STALE, INPUT_CONFLICT, LEGS, LIFTED, LOOP_STALL, Mode, \
    MOTOR_ERROR, MOTOR_REBOOTED, OVER_TEMPERATURE, SafetyLimits, SafetySupervisor, SensorSnapshot
from .safety import ENCODER_MISMATCH, RESPONSE
from .schema import with_changes
from .sensors import ImuReader, JointSample, JointStateReader
from .sit_down import BRAKE, DONE, FOLD, SitDown, SitDownConfig
# The tick's inputs and outputs (imported from here by older callers too).
from .tick_io import CmdHeight, CmdVel, LoopState, Odom, STATE_FIELDS, TickInputs, \
    TickResult  # noqa: F401
from .wheel_state import WheelState

LEFT_WHEEL = 'left_wheel'
RIGHT_WHEEL = 'right_wheel'
WHEELS = (LEFT_WHEEL, RIGHT_WHEEL)
HIPS = ('left_front_hip', 'left_rear_hip', 'right_front_hip', 'right_rear_hip')
#: Ticks between the exit frames that keep resting motors answering (DISARMED): 20 ms.
POLL_TICKS = 10
#: |theta~ - d_hat| [rad] below which, for RISE_TIME [s], the robot counts as risen (the legs
#: then go to the commanded height).
RISEN_ANGLE = math.radians(5.0)
RISE_TIME = 0.5
#: The legs count as raised to height_min on the tail within this [m] for this long [s].
RAISED_TOLERANCE = 0.005
RAISED_TIME = 0.3
#: How far above the folded height the sit-down folds the legs before the motors rest [m].
FOLD_MARGIN = 0.005
#: The share of the body's weight the legs carry while the robot rests on its tail, and the
#: integral gain [1/s] and limit [m] that correct the height for the rest.
TAIL_LOAD = 0.5
RAISE_KI = 3.0
RAISE_LIMIT = 0.04


#: auto_arm waits until the ticks have come without a gap beyond the sensor timeouts for this
#: long [s]. In lockstep (clock_source imu_stamp) the first samples can come as a burst of old
#: stamps: a tick armed on one of them and the next, 0.38 s of stamps later, faulted the motors
#: as silent since the arm (sim-files test, 2026-12-02).
AUTO_ARM_STEADY = 0.05
#: The inputs whose conflicts are about the sensors (TickInputs.conflicts): FAULT, no arming.
SENSOR_INPUTS = ('imu', 'joint_states')
#: Arming is refused until no command frame from another sender has come for this long [s]:
#: a script or a second node that commands now and then is still there between its frames.
FOREIGN_COMMAND_HOLD = 1.0
#: What a command frame this node did not send most likely is, for a fault or refusal reason.
ANOTHER_SENDER = ('another sender on the bus (another balance_node, a test script, a second '
                  'computer?)')


def build_protocol(cfg: BalanceConfig) -> MotorProtocol:
    """Build the wheel motors' CAN codec named by ``can.protocol`` (the motor model's ranges)."""
    can = cfg.can
    if can.protocol == 'mit':
        return make_protocol('mit', **can.mit.codec_ranges())
    return make_protocol(can.protocol, torque_constant=can.dji.torque_constant,
                         gear_ratio=can.dji.gear_ratio, current_limit=can.dji.current_limit)


def all_stop_frames(cfg: BalanceConfig) -> Tuple[List[Frame], List[Frame]]:
    """
    Return zero torque + exit motor mode for every motor of ``cfg``: (the wheels', the hips').

    What the loop sends at start-up and shutdown (BalanceLoop.stop_frames), built from the
    configuration alone for the watchdog (nodes/watchdog.py), which has no loop.
    """
    # Directions do not matter for zero torque and exit: MotorSet.stop_frames is the recipe.
    wheels = MotorSet(build_protocol(cfg), ((LEFT_WHEEL, cfg.can.left_motor_id, 1),
                                            (RIGHT_WHEEL, cfg.can.right_motor_id, 1)))
    if not cfg.legs.driven:
        return wheels.stop_frames(), []
    hips = MotorSet(MitProtocol(**cfg.legs.mit.codec_ranges()),
                    [(name, i, 1) for name, i in zip(HIPS, cfg.legs.motor_ids)])
    return wheels.stop_frames(), hips.stop_frames()


def core_config(cfg: BalanceConfig) -> CoreConfig:
    """Return the control core's tuning from the configuration (the tick's, the margins')."""
    c = cfg.control
    return CoreConfig(controller=c.controller, ida_pbc=cfg.ida_pbc,
                      compensate_offset=c.compensate_offset, d_hat0=c.d_hat0,
                      yaw_rate_gain=c.yaw_rate_gain, yaw_rate_ki=c.yaw_rate_ki,
                      yaw_rate_ff=c.yaw_rate_ff, yaw_integral_limit=c.yaw_integral_limit,
                      yaw_rate_source=c.yaw_rate_source,
                      max_wheel_torque=cfg.safety.max_wheel_torque,
                      switch_blend_time=c.switch_blend_time,
                      lqr_Q=np.diag(cfg.output_regulation.q_diag),
                      lqr_R=cfg.output_regulation.r,
                      linear_gain_source=cfg.output_regulation.gain_source, auto=cfg.auto,
                      hold=cfg.output_regulation)


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


def five_bar(cfg: BalanceConfig) -> FiveBarLeg:
    """Return the leg's kinematics from the configured geometry."""
    g = cfg.leg
    return FiveBarLeg(thigh=g.thigh, shank=g.shank, hip_spacing=g.hip_spacing,
                      com_height=g.com_height, com_x=g.com_x)


def joint_state_reader(cfg: BalanceConfig) -> JointStateReader:
    """How a JointState message is matched to the wheels and hips of ``cfg``."""
    j = cfg.joints
    names, dirs, offs = j.leg_names, j.leg_joint_directions, j.leg_joint_offsets
    legs = [(names[k], names[k + 1], dirs[k], dirs[k + 1], offs[k], offs[k + 1])
            for k in (0, 2) if names[k] and names[k + 1]]
    return JointStateReader((j.left_wheel_joint, j.right_wheel_joint),
                            (j.left_wheel_direction, j.right_wheel_direction), legs,
                            five_bar(cfg))


def joint_states_used(cfg: BalanceConfig) -> bool:
    """Tell whether the tick reads joint_states_in: wheels from another driver, or hip angles."""
    return cfg.wheel_state.wheel_state_source == 'joint_states' \
        or bool(joint_state_reader(cfg).legs)


def joint_names(cfg: BalanceConfig) -> List[str]:
    """Return the joints balance_node publishes: wheels, and with driven legs hips and knees."""
    j = cfg.joints
    names = [j.left_wheel_joint, j.right_wheel_joint]
    if cfg.legs.driven:
        names += list(cfg.legs.joint_names) + list(cfg.legs.knee_names)
    return names


class Legs:
    """The driven legs of the tick: hip motors, state, height shaping, levelling, homing."""

    def __init__(self, cfg: BalanceConfig):
        lc, p = cfg.legs, cfg.model
        self.protocol = MitProtocol(**lc.mit.codec_ranges())
        self.motors = MotorSet(self.protocol, [(name, i, 1) for name, i in
                                               zip(HIPS, lc.motor_ids)])
        self.controller = LegController(
            five_bar(cfg), HipMotors(tuple(lc.motor_ids), tuple(lc.directions),
                                     tuple(lc.offsets)),
            LegGains(lc.kp, lc.kd, lc.damping_kd, lc.damping_gravity),
            weight_share=0.5 * p.body_mass * p.gravity)
        if lc.homing == 'set_zero':
            self.controller.set_offsets(lc.offsets)
        self.homing_config = HomingConfig(
            stop_angles=tuple(lc.stop_angles), speed=lc.homing_speed,
            torque_threshold=lc.homing_torque,
            max_torque=max(2.0 * lc.homing_torque, lc.homing_torque + 1.0))
        self.homing: Optional[HipHoming] = None
        self.shaper = HeightShaper(p.height_min, p.height_max, lc.max_height_rate,
                                   lc.max_height_accel)
        self.leveller = RollLeveller(lc.roll_kp, lc.roll_ki, lc.roll_kd, lc.max_roll_dl)
        self.levelling = lc.roll_kp > 0.0 or lc.roll_ki > 0.0
        self.divider = lc.command_divider
        self._phases = ((LEFT_LEG, 0), (RIGHT_LEG, self.divider // 2))
        self.height_min, self.height_max = p.height_min, p.height_max
        self.state: Optional[LegState] = None
        self.raised_since: Optional[float] = None
        self.raise_integral = 0.0
        self.hold_height: Optional[float] = None
        leg = self.controller.leg
        #: The height with the hips at their lower stops (the rest after power-up) [m].
        self.folded_height = leg.height(leg.q_min, leg.q_min)

    def replies(self):
        """Return the hips' (position, velocity, torque) in the motor frame (None: no reply)."""
        return [None if m.feedback is None else m.feedback[1:4] for m in self.motors.motors]

    def read(self) -> LegState:
        """Update and return the legs' state from the newest replies."""
        self.state = self.controller.state(self.replies())
        return self.state

    def load(self) -> float:
        """Return the legs' mean load f_l [N] from the hip torques (NaN: not known)."""
        st = self.state
        if st is None or not st.valid:
            return math.nan
        leg, dirs = self.controller.leg, self.controller.motors.directions
        tau = [d * m.feedback.torque if m.feedback is not None else math.nan
               for d, m in zip(dirs, self.motors.motors)]
        return 0.5 * (leg.leg_force(st.q[0], st.q[1], tau[0], tau[1])[1]
                      + leg.leg_force(st.q[2], st.q[3], tau[2], tau[3])[1])

    def reply_time(self) -> Optional[float]:
        """Return the oldest of the hips' newest reply times (None until each replied)."""
        times = [m.last_reply for m in self.motors.motors]
        return None if any(t is None for t in times) else min(times)

    def due(self, tick: int) -> Tuple[int, ...]:
        """
        Return the legs whose hips are commanded in this tick while balancing.

        Each leg every ``legs.command_divider``-th tick; with a divider of 2 or more the two
        legs take turns, so every tick carries the same number of frames (the right leg half a
        cycle after the left: 2 hip frames per tick at 250 Hz, not 4 and 0).
        """
        phase = tick % self.divider
        return tuple(leg for leg, at in self._phases if at == phase)

    def frames(self, commands) -> List[Frame]:
        """MIT frames of impedance commands."""
        cf = self.protocol.command_frame
        return [cf(c.motor_id, c.position, c.velocity, c.kp, c.kd, c.torque) for c in commands]


def _motor_name(m) -> str:
    """Name a motor in a problem's text: 'motor 3 (left_front)'."""
    return 'motor %d (%s)' % (m.motor_id, m.name)


class BalanceLoop:
    """The control tick (see the module docstring)."""

    def __init__(self, cfg: BalanceConfig):
        self.cfg = cfg
        self.period = cfg.loop.control_period
        self.p = cfg.model
        self.odometry = WheelOdometry(self.p)
        self.core = BalanceCore(self.p, core_config(cfg), dt=self.period,
                                odometry=self.odometry)
        self.protocol = build_protocol(cfg)
        self.motors = MotorSet(self.protocol, (
            (LEFT_WHEEL, cfg.can.left_motor_id, cfg.can.left_direction),
            (RIGHT_WHEEL, cfg.can.right_motor_id, cfg.can.right_direction)))
        self.legs = Legs(cfg) if cfg.legs.driven else None
        ids = self.motors.ids + (self.legs.motors.ids if self.legs else ())
        self.supervisor = SafetySupervisor(safety_limits(cfg), ids)
        self.shaper = ReferenceShaper()
        self.imu = ImuReader(cfg.imu.imu_mounting_rpy, self.p.gravity,
                             cfg.safety.stamp_tolerance)
        self.from_can = cfg.wheel_state.wheel_state_source == 'can'
        ws = cfg.wheel_state
        self.wheel_states = [WheelState(m.direction, self.protocol if self.from_can else None,
                                        ws.wheel_speed_time_constant, wrap=ws.position_wraps)
                             for m in self.motors.motors] if self.from_can else []
        self._wheel_state_of = {m.motor_id: w for m, w in zip(self.motors.motors,
                                                              self.wheel_states)}
        self.has_leg_joints = bool(joint_state_reader(cfg).legs)
        self.sit_down_config = SitDownConfig(tail_pitch=cfg.safety.tail_pitch)
        self.sit: Optional[SitDown] = None
        self.last_sit_down: Optional[SitDown] = None   # the newest finished one (its figures)
        self._sit_d_hat: Optional[float] = None
        self._wheels: Optional[JointSample] = None   # newest sample with the wheels
        self._legs_js: Optional[JointSample] = None  # newest sample with the hips
        self._cmd: Optional[CmdVel] = None
        self.rejected_cmd_vel = 0
        self.rejected_cmd_height = 0
        #: Why inputs are refused for their publishers (TickInputs.conflicts), '' for none.
        self.input_conflicts = ''
        self._snapshot = SensorSnapshot()
        self._result = TickResult()
        self._pending_reply: Optional[Tuple[str, bool, str]] = None
        self._auto_arm = cfg.safety.auto_arm
        self._last_now: Optional[float] = None
        #: The tick since which no gap beyond the sensor timeouts came [s] (AUTO_ARM_STEADY).
        self._steady_since: Optional[float] = None
        self._ticks = 0
        self._x = 0.0
        self._d_hat = 0.0
        self._x_dot_prev = 0.0
        self._accel = 0.0   # forward acceleration estimate [m/s^2] (gravity fallback)
        self._risen_since: Optional[float] = None
        self._rising = False
        self._height_target = cfg.control.height
        self.joint_names = joint_names(cfg)
        sc = cfg.safety
        self.lift = LiftDetector(sc.lift_wheel_inertia, sc.lift_window, sc.lift_min_dv,
                                 sc.lift_ratio, sc.lift_free_time,
                                 wheel_radius=self.p.wheel_radius, gravity=self.p.gravity)
        self.response = ResponseCheck(self.p, sc.response_window, sc.response_min_effect,
                                      sc.response_gain, sc.response_time)
        self._lift_hold: Optional[Tuple[float, float]] = None   # the legs' heights when lifted
        self._lifted = False   # since the lifted fault, until an arm on the ground
        # Motor health (core/motor_health.py): each motor set with its model's figures.
        wheel_model = cfg.can.mit if cfg.can.protocol == 'mit' else cfg.can.dji
        self._health = [(self.motors, wheel_model)] + (
            [(self.legs.motors, cfg.legs.mit)] if self.legs is not None else [])
        wrap = 65536.0 / 65535.0 if cfg.wheel_state.position_wraps else math.inf
        for motors, model in self._health:
            if isinstance(motors.protocol, MitProtocol):
                motors.jump_limit = model.position_jump
                motors.span = (motors.protocol.p_max - motors.protocol.p_min) * wrap
                motors.speed_limit = 0.9 * min(-motors.protocol.v_min, motors.protocol.v_max)
        #: Why the motors are not fit to arm (errors, reboots, heat), from the newest tick.
        self.motor_problems: List[str] = []
        #: Command frames to our motors that this node did not send (a second commander): how
        #: many, the newest's receipt time [s], the motors it addressed, one since the check.
        self.foreign_commands = 0
        self._foreign_last: Optional[float] = None
        self._foreign_motors = ''
        self._foreign_new = False
        #: Wheels whose encoder_mismatch was announced (one warn event per wheel and run).
        self._mismatch_warned: set = set()
        self._configure_live(cfg)

    # ----------------------------------------------------------------------- configuration

    def _configure_live(self, cfg: BalanceConfig) -> None:
        """Give every component the live-changeable settings of ``cfg``."""
        core = self.core.config
        core.d_hat0 = cfg.control.d_hat0
        core.yaw_rate_gain = cfg.control.yaw_rate_gain
        core.yaw_rate_ki = cfg.control.yaw_rate_ki
        core.yaw_rate_ff = cfg.control.yaw_rate_ff
        core.yaw_integral_limit = cfg.control.yaw_integral_limit
        core.yaw_rate_source = cfg.control.yaw_rate_source
        core.max_wheel_torque = cfg.safety.max_wheel_torque
        core.switch_blend_time = cfg.control.switch_blend_time
        self.core.set_auto_rules(cfg.auto)
        self.supervisor.limits = safety_limits(cfg)
        sh, ref = self.shaper, cfg.reference
        sh.max_velocity, sh.max_acceleration = ref.max_velocity, ref.max_acceleration
        sh.max_yaw_rate, sh.max_yaw_acceleration = ref.max_yaw_rate, ref.max_yaw_acceleration
        sh.cmd_vel_timeout = cfg.safety.cmd_vel_timeout
        self.imu.stamp_tolerance = cfg.safety.stamp_tolerance
        lift, sc = self.lift, cfg.safety
        lift.window, lift.min_dv, lift.ratio = sc.lift_window, sc.lift_min_dv, sc.lift_ratio
        lift.free_time = sc.lift_free_time
        lift.min_load = sc.lift_min_load * 0.5 * self.p.body_mass * self.p.gravity \
            if self.legs is not None else -math.inf
        lift.unloaded_time = sc.lift_unloaded_time
        lift.still_window, lift.still_min_dv = sc.lift_still_window, sc.lift_still_min_dv
        lift.still_ratio = sc.lift_still_ratio
        resp = self.response
        resp.window, resp.min_effect = sc.response_window, sc.response_min_effect
        resp.gain, resp.hold = sc.response_gain, sc.response_time
        self._height = cfg.control.height
        legs = self.legs
        if legs is not None:
            lc = cfg.legs
            legs.controller.gains = LegGains(lc.kp, lc.kd, lc.damping_kd, lc.damping_gravity)
            legs.shaper.max_rate, legs.shaper.max_accel = lc.max_height_rate, \
                lc.max_height_accel
            lv = legs.leveller
            lv.kp, lv.ki, lv.kd, lv.max_dl = lc.roll_kp, lc.roll_ki, lc.roll_kd, lc.max_roll_dl
            legs.levelling = lc.roll_kp > 0.0 or lc.roll_ki > 0.0

    def apply_parameters(self, changes: Mapping[str, Any]) -> None:
        """Apply validated parameter changes {name: value} (at the start of a tick)."""
        old, new = self.cfg, with_changes(self.cfg, changes)
        self.cfg = new
        if new.control.controller != old.control.controller:
            self.core.select(new.control.controller)
        if new.ida_pbc != old.ida_pbc:
            self.core.set_ida_pbc_gains(new.ida_pbc)
        if new.output_regulation != old.output_regulation:
            self.core.set_hold_shape(new.output_regulation)
        if new.control.height != old.control.height:
            self._height_target = new.control.height
        self._configure_live(new)

    # ---------------------------------------------------------------------------- the tick

    @property
    def mode(self) -> Mode:
        """Return the supervisor's mode."""
        return self.supervisor.mode

    @property
    def last_result(self) -> TickResult:
        """Return what the newest tick produced (the object is reused by the next tick)."""
        return self._result

    def tick(self, now: float, inputs: TickInputs) -> TickResult:
        """Run one control tick at monotonic time ``now`` [s] (see the module docstring)."""
        r = self._result
        r.frames, r.leg_frames, r.arm_reply, r.events = [], [], None, []
        dt = self.period if self._last_now is None else now - self._last_now
        self._last_now = now
        self._ticks += 1
        if inputs.params:
            self.apply_parameters(inputs.params)
        stall_limit = self._stall_limit()   # the timeouts as this tick's parameters set them
        if self._steady_since is None or dt > stall_limit:
            self._steady_since = now
        self._take(inputs)
        s = self._read_samples(now)
        sup = self.supervisor
        commanded = sup.mode in COMMANDING   # since the previous tick (before any arming now)
        if sup.mode not in (Mode.BALANCING, Mode.SITTING) and s.imu_time is not None \
                and s.joint_time is not None and sup.limits.plausible(s):
            self.odometry.update(s.wheel_vel_left, s.wheel_vel_right, s.theta_dot, dt)
        self._estimate_acceleration(dt)
        self._check_motors(now)
        conflicts = inputs.conflicts
        sensor_conflict = '; '.join(conflicts[k] for k in SENSOR_INPUTS
                                    if k in conflicts) if conflicts else ''
        self.input_conflicts = '; '.join(conflicts.values()) if conflicts else ''
        if inputs.estop:
            self._auto_arm = False
            was = sup.mode
            self._stop(disarm_reply=False)
            if was in COMMANDING:
                r.events.append(('warn', 'emergency stop: zero torque, motors to rest'))
        elif inputs.arm is not None:
            self._auto_arm = False  # the operator decides from now on
            if inputs.arm and not inputs.guarded:
                self._pending_reply = ('refused', False, 'arming refused: the watchdog is not '
                                       'watching the control loop yet')
            elif inputs.arm and sensor_conflict:
                self._pending_reply = ('refused', False, 'arming refused: ' + sensor_conflict)
            else:
                self._handle_arm(inputs.arm, now, s)
            self._lifted = self._lifted and sup.mode not in COMMANDING
        elif self._auto_arm and inputs.guarded and not sensor_conflict \
                and sup.mode is Mode.DISARMED and now - self._steady_since >= AUTO_ARM_STEADY \
                and self._can_arm(now, s):
            self._auto_arm = False  # at most once per start, whatever the outcome
            self._handle_arm(True, now, s)
            r.events.append(('info', 'auto_arm: %s' % self._pending_reply[2]))
        before = sup.mode
        sup.update(now, s, self._reply_times())
        if self._foreign_new:   # another sender commands our motors: two masters
            self._foreign_new = False
            sup.report_fault(now, INPUT_CONFLICT, 'command frames to %s that this node did not '
                             'send: %s' % (self._foreign_motors, ANOTHER_SENDER))
        if sensor_conflict:   # samples from two sources cannot be trusted
            sup.report_fault(now, INPUT_CONFLICT, sensor_conflict)
        if inputs.imu_silent:
            sup.report_fault(now, IMU_STALE, inputs.imu_silent)
        if commanded:   # a gap before arming held no torque of ours
            self._check_stall(now, dt, stall_limit)
        if not self._check_response(now, s, dt):
            self._check_lift(now, s, dt)
        mode = sup.mode
        if mode is Mode.FAULT and before in COMMANDING:
            self._auto_arm = False
            r.events.append(('error', 'FAULT: ' + '; '.join(f.message for f in sup.faults)))
        self._command(mode, now, s, dt)
        self._publish(s)
        return r

    def _reply_times(self) -> Dict[int, Optional[float]]:
        if self.legs is None:
            return self.motors.reply_times
        return {**self.motors.reply_times, **self.legs.motors.reply_times}

    def _take(self, inputs: TickInputs) -> None:
        for sample in inputs.imu:
            self.imu.take(sample, self._accel)
        for sample in inputs.joints:
            if sample.has_wheels:
                self._wheels = sample
            if sample.has_legs:
                self._legs_js = sample
        legs = self.legs
        for t, frame in inputs.frames:
            motor = self.motors.on_frame(t, frame)
            if motor is None:
                if legs is None or legs.motors.on_frame(t, frame) is None:
                    self._note_foreign(t, frame)
            elif self.from_can:
                fb = motor.feedback
                wheel = self._wheel_state_of[motor.motor_id]
                wheel.update(fb.position, fb.velocity, t)
                if wheel.mismatch and motor.motor_id not in self._mismatch_warned:
                    self._warn_mismatch(motor, wheel)
        cmd = inputs.cmd_vel
        conflicts = inputs.conflicts
        if cmd is not None:
            if 'cmd_vel' not in conflicts and math.isfinite(cmd.x_dot) \
                    and math.isfinite(cmd.yaw_rate):
                self._cmd = cmd
            else:
                self.rejected_cmd_vel += 1
        if inputs.cmd_height is not None:
            h = inputs.cmd_height.height
            if 'cmd_height' not in conflicts and isinstance(h, (int, float)) \
                    and math.isfinite(h):
                self._height_target = min(max(float(h), self.p.height_min), self.p.height_max)
            else:
                self.rejected_cmd_height += 1

    def _note_foreign(self, t: float, frame: Frame) -> None:
        """Count a frame that commands one of our motors but is none of ours (not a reply)."""
        for motors, _ in self._health:
            hit = motors.commanded_motors(frame)
            if hit:
                self.foreign_commands += 1
                self._foreign_last = t
                self._foreign_motors = ', '.join(_motor_name(m) for m in hit)
                self._foreign_new = True
                return

    def _foreign_reason(self, now: float) -> str:
        """Return why arming is refused for another sender's commands ('' for none lately)."""
        last = self._foreign_last
        if last is None or now - last > FOREIGN_COMMAND_HOLD:
            return ''
        return ('%s got command frames this node did not send: %s; %d so far, the newest '
                '%.3f s ago (arming waits until none came for %.1f s)' % (
                    self._foreign_motors, ANOTHER_SENDER, self.foreign_commands, now - last,
                    FOREIGN_COMMAND_HOLD))

    def _warn_mismatch(self, motor, wheel: WheelState) -> None:
        """Announce once per wheel that its replies contradict its speed (encoder_mismatch)."""
        self._mismatch_warned.add(motor.motor_id)
        if motor.rebooted is not None:
            return   # a reboot's jump: motor_rebooted names it (core/motors.py)
        self._result.events.append(('warn', '%s: %s: %s; %s' % (
            ENCODER_MISMATCH, _motor_name(motor), wheel.mismatch_reason,
            self._mismatch_advice())))

    def _mismatch_advice(self) -> str:
        """Return the likely cause of an encoder_mismatch and its fix, for this configuration."""
        if self.cfg.wheel_state.position_wraps:
            return ('likely firmware that saturates the position at +-%g rad instead of '
                    'wrapping it: set can.mit.wrap: false. The wheel angle is dead-reckoned '
                    'from the reported speed until the position agrees with it again'
                    % self.protocol.p_max)
        return ('with can.mit.wrap: false already: an encoder or reply fault? Check the motor '
                'and can.mit.p_min / p_max. The wheel angle is dead-reckoned from the reported '
                'speed until the position agrees with it again')

    def _warnings(self) -> List[Tuple[str, str]]:
        """Return the warnings (WARNING_CODES) for /diagnostics as (code, message) pairs."""
        out = []
        for m, w in zip(self.motors.motors, self.wheel_states):
            if w.mismatches and m.rebooted is None:   # a reboot's jump: motor_rebooted
                out.append((ENCODER_MISMATCH, '%s: %s%s' % (
                    _motor_name(m), w.mismatch_reason,
                    '; the wheel angle is dead-reckoned from the reported speed' if w.mismatch
                    else '; %d times since the start, the position agrees with the speed again'
                    % w.mismatches)))
        return out

    def _read_samples(self, now: float) -> SensorSnapshot:
        s, imu = self._snapshot, self.imu
        s.imu_time, s.theta, s.theta_dot, s.roll = imu.time, imu.theta, imu.theta_dot, imu.roll
        if self.from_can:
            times = self.motors.reply_times.values()
            s.joint_time = None if None in times else min(times)
            readings = [w.reading(now) for w in self.wheel_states]
            s.wheel_vel_left, s.wheel_vel_right = readings[0].speed, readings[1].speed
        elif self._wheels is None:
            s.joint_time, s.wheel_vel_left, s.wheel_vel_right = None, math.nan, math.nan
        else:
            s.joint_time = self._wheels.t
            s.wheel_vel_left, s.wheel_vel_right = self._wheels.w_left, self._wheels.w_right
        if self.legs is not None:
            state = self.legs.read()
            if self.legs.controller.homed:
                s.l = state.l   # NaN for a leg out of reach or a hip that never replied
            else:
                # Before homing the hip angles are known only modulo a rotor turn: l is not
                # known, and not needed (nothing balances); the lowest height stands in.
                s.l = self.p.height_min
        elif self.has_leg_joints:
            legs = self._legs_js
            if legs is None:
                s.joint_time, s.l = None, math.nan
            else:
                s.l = legs.l
                if s.joint_time is not None:
                    s.joint_time = min(s.joint_time, legs.t)
        else:
            s.l = self._height
        return s

    def _stall_limit(self) -> float:
        """Return the longest gap between two ticks [s] that is no stall: the sensor timeouts."""
        lim = self.supervisor.limits
        return min(lim.imu_timeout, lim.joint_state_timeout)

    def _check_stall(self, now: float, dt: float, limit: float) -> None:
        """Fault when the loop was late beyond ``limit``, the sensor timeouts (it was blind)."""
        if dt > limit and self.supervisor.mode in COMMANDING:
            self.supervisor.report_fault(now, LOOP_STALL, 'control loop stalled %.1f ms (longer '
                                         'than the sensor timeouts, %.0f ms)'
                                         % (1e3 * dt, 1e3 * limit))

    def _check_lift(self, now: float, s: SensorSnapshot, dt: float) -> None:
        """Fault when the wheels spin free (core/lift.py): lifted; the legs then hold."""
        lift = self.lift
        if not self.supervisor.torque_allowed:
            lift.reset()
            return
        st = self._result.state   # still the torques of the last tick: applied since
        # The wheels' rotation in the world (the encoders read it relative to the leg): a
        # free wheel's follows the torque alone, whatever the body does.
        legs = self.legs
        # Rising from the tail or sitting down onto it, the tail carries part of the weight,
        # and a body tipping over (a push, a fall) unloads the legs too: their load tells
        # only while balancing near upright.
        near_upright = abs(s.theta - self._d_hat) <= self.supervisor.limits.upright_pitch
        load = legs.load() if legs is not None and not self._rising and near_upright \
            and self.supervisor.mode is Mode.BALANCING else math.nan
        # The still-body rule needs model (1): near upright, the tail off the ground.
        reason = lift.update(now, (st.tau_left, st.tau_right),
                             (s.wheel_vel_left + s.theta_dot, s.wheel_vel_right + s.theta_dot),
                             dt, load, s.theta_dot if near_upright else math.nan, s.l,
                             self.imu.specific_force)
        if reason is not None:
            state = legs.state if legs is not None else None
            self._lift_hold = tuple(state.heights) if state is not None and state.valid \
                else None
            self.supervisor.report_fault(now, LIFTED, reason)
            self._lifted = True

    def _check_response(self, now: float, s: SensorSnapshot, dt: float) -> bool:
        """
        Fault when the pitch answers the wheel torque with the wrong sign (core/response.py).

        Judged where model (1) holds: the wheels commanded, near upright (the tail off the
        ground), not in free fall. Returns True when it faulted.
        """
        check = self.response
        theta = s.theta - self._d_hat
        falling = self.lift.accel_seen and \
            self.imu.specific_force < FREE_FALL * self.p.gravity   # False for NaN
        if not self.supervisor.torque_allowed:
            check.reset()
            return False
        st = self._result.state   # still the torques of the last tick: applied since
        u = (st.tau_left + st.tau_right) / self.p.wheel_radius
        reason = check.update(now, theta, s.theta_dot, u, s.l, dt,
                              judge=abs(theta) <= RESPONSE_PITCH and not falling,
                              sample=s.imu_time)
        if reason is None:
            return False
        self.supervisor.report_fault(now, RESPONSE, reason)
        return True

    def _estimate_acceleration(self, dt: float) -> None:
        # The robot's own forward acceleration, low-passed (50 ms), for the gravity fallback.
        x_dot = self.odometry.x_dot
        if math.isfinite(x_dot) and dt > 0.0:
            a = (x_dot - self._x_dot_prev) / dt
            self._accel += min(1.0, dt / 0.05) * (a - self._accel)
            self._x_dot_prev = x_dot
        if not math.isfinite(self._accel):
            self._accel = 0.0

    def _measurement(self, s: SensorSnapshot) -> Measurement:
        return Measurement(s.theta, s.theta_dot, s.wheel_vel_left, s.wheel_vel_right, s.l,
                           self.imu.yaw_rate)

    # ------------------------------------------------------------------------------ modes

    def _command(self, mode: Mode, now: float, s: SensorSnapshot, dt: float) -> None:
        r, state = self._result, self._result.state
        wheels_commanded = False
        if mode is Mode.BALANCING or mode is Mode.SITTING:
            wheels_commanded = self._balance(mode, now, s, dt)
        if not wheels_commanded:
            if mode is Mode.FAULT or mode is Mode.HOMING:
                r.frames += self.motors.zero_torque_frames()
            elif mode is Mode.DISARMED and self._ticks % POLL_TICKS == 0 and (
                    self.from_can or self.legs is not None) and not r.frames:
                # Resting motors answer every frame: exit frames keep them resting and their
                # replies (liveness, wheel and hip readings) coming.
                r.frames += self.motors.protocol.disable_frames(self.motors.ids) \
                    if self.from_can else []
                if self.legs is not None:
                    r.leg_frames += self.legs.protocol.disable_frames(self.legs.motors.ids)
            state.x, state.x_dot = self._x, self.odometry.x_dot
            state.yaw_rate = self.odometry.yaw_rate
            state.u = state.tau_left = state.tau_right = 0.0
            state.x_dot_ref = state.yaw_rate_ref = 0.0
        if self.legs is not None:
            self._command_legs(mode, now, s, dt)
        if self.sit is not None and self.sit.phase == DONE and mode is Mode.SITTING:
            self._finish_sit_down()

    def _balance(self, mode: Mode, now: float, s: SensorSnapshot, dt: float) -> bool:
        """Run the balance controller (or the sit-down's lean); return True: wheels sent."""
        r, state = self._result, self._result.state
        cmd = self._cmd
        sitting = mode is Mode.SITTING and self.sit is not None
        if cmd is None or sitting:
            x_ref, w_ref = self.shaper.update(now, None, 0.0, 0.0, dt)
        else:
            x_ref, w_ref = self.shaper.update(now, cmd.t, cmd.x_dot, cmd.yaw_rate, dt)
        out = self.core.step(self._measurement(s), Reference(x_ref, w_ref), dt)
        tau_l, tau_r, u = out.tau_left, out.tau_right, out.u
        if sitting:
            self.sit.lowered(now, self._l_ref(), s.l)
            if self.sit.phase != 'lower':
                # The offset estimate of the moment the lean starts: while the body leans far
                # from upright the observer holds d_hat, and it is fed the controller's force.
                if self._sit_d_hat is None:
                    self._sit_d_hat = out.d_hat
                u = self.sit.force(now, s.theta - self._sit_d_hat, s.theta_dot, out.x_dot,
                                   s.l)
                lim = self.core.config.max_wheel_torque   # derated when hot
                tau_l = tau_r = min(max(0.5 * self.p.wheel_radius * u, -lim), lim)
                u = (tau_l + tau_r) / self.p.wheel_radius
        r.frames += self.motors.torque_frames({LEFT_WHEEL: tau_l, RIGHT_WHEEL: tau_r})
        self._x, self._d_hat = out.x, out.d_hat
        state.x, state.x_dot, state.yaw_rate = out.x, out.x_dot, out.yaw_rate
        state.u, state.tau_left, state.tau_right = u, tau_l, tau_r
        state.x_dot_ref, state.yaw_rate_ref = x_ref, w_ref
        if self._rising:
            if abs(s.theta - out.d_hat) < RISEN_ANGLE:
                self._risen_since = now if self._risen_since is None else self._risen_since
                if now - self._risen_since >= RISE_TIME:
                    self._rising = False
                    r.events.append(('info', 'risen: the legs go to %.3f m'
                                     % self._height_target))
            else:
                self._risen_since = None
        return True

    def _prepare_legs(self, now: float, s: SensorSnapshot, dt: float) -> None:
        """HOMING: home the hips where needed, then raise the legs on the tail to height_min."""
        legs, r = self.legs, self._result
        homing = legs.homing
        if homing is not None and homing.status == 'running':
            r.leg_frames += legs.frames(homing.step(legs.replies(), now))
            if homing.status == 'done':
                legs.controller.set_offsets(homing.offsets)
                r.events.append(('info', 'legs homed: offsets %s rad' % ', '.join(
                    '%.4f' % o for o in homing.offsets)))
                state = legs.read()
                legs.shaper.reset(state.l if state.valid else self.p.height_min)
            elif homing.status == 'failed':
                self.supervisor.report_fault(now, LEGS, 'homing failed: %s' % homing.reason)
            return
        state = legs.state
        if not state.valid:
            self.supervisor.report_fault(now, LEGS, 'legs: ' + '; '.join(state.problems))
            return
        sh = legs.shaper
        sh.command(self.p.height_min)
        l_ref, l_dot = sh.step(dt)
        theta = s.theta - self._d_hat
        l_cmd = self._tail_height(l_ref, state, dt)
        r.leg_frames += legs.frames(legs.controller.commands(l_cmd, l_cmd, l_dot, l_dot,
                                                             pitch=theta, load=TAIL_LOAD))
        if l_ref == self.p.height_min and abs(state.l - l_ref) < RAISED_TOLERANCE:
            legs.raised_since = now if legs.raised_since is None else legs.raised_since
            if now - legs.raised_since >= RAISED_TIME:
                self._start_balancing(now, s, reply_needed=False)
        else:
            legs.raised_since = None

    def _fold_legs(self, now: float, s: SensorSnapshot, dt: float) -> None:
        """Sit-down's last phase: fold the legs down to their stops, resting on the tail."""
        legs, r = self.legs, self._result
        sh, state = legs.shaper, legs.state
        if legs.hold_height is not None:   # from holding at contact to folding
            sh.reset(legs.hold_height)
            legs.hold_height = None
            legs.raise_integral = 0.0
        folded = legs.folded_height + FOLD_MARGIN
        sh.height_min = min(sh.height_min, folded)   # the shaper may go below height_min now
        sh.command(folded)
        l_ref, l_dot = sh.step(dt)
        l_cmd = self._tail_height(l_ref, state, dt)
        r.leg_frames += legs.frames(legs.controller.commands(
            l_cmd, l_cmd, l_dot, l_dot, pitch=s.theta - self._d_hat, load=TAIL_LOAD))
        if state.valid and l_ref == folded and state.l <= folded + RAISED_TOLERANCE:
            self.sit.folded()

    def _tail_height(self, l_ref: float, state: LegState, dt: float) -> float:
        """
        Return the legs' commanded height for l_ref [m] while the robot rests on its tail.

        The tail carries part of the weight: feeding the whole share forward pushed the legs
        4 cm past the reference and tipped the robot over the tail. How much the tail carries
        changes with the pitch: an integral on the height error takes the rest (it left
        1.4 cm without).
        """
        legs = self.legs
        if state.valid:
            legs.raise_integral += RAISE_KI * (l_ref - state.l) * dt
            legs.raise_integral = min(max(legs.raise_integral, -RAISE_LIMIT), RAISE_LIMIT)
        return l_ref + legs.raise_integral

    def _l_ref(self) -> float:
        return self.legs.shaper.l_ref if self.legs is not None else self._height

    def _command_legs(self, mode: Mode, now: float, s: SensorSnapshot, dt: float) -> None:
        legs, r = self.legs, self._result
        if mode is Mode.HOMING:
            self._prepare_legs(now, s, dt)
            return
        if mode is Mode.SITTING and self.sit is not None and self.sit.phase in (FOLD, DONE):
            self._fold_legs(now, s, dt)
            return
        if mode is Mode.BALANCING or mode is Mode.SITTING:
            sh = legs.shaper
            if mode is Mode.SITTING:
                sh.command(self.p.height_min)
            elif not self._rising:
                sh.command(self._height_target)
            l_ref, l_dot = sh.step(dt)
            if self.sit is not None and self.sit.phase == BRAKE:
                # On the tail: the legs hold the length they had at contact, so the tail stops
                # the body's rotation (legs that give way, or push with the whole weight's
                # share, let the body roll on over the tail), carrying what the tail leaves.
                # The weight's share goes over with the brake: dropped at once, it lets the
                # body fall onto the tail.
                if legs.hold_height is None:
                    legs.hold_height = legs.state.l if legs.state.valid else l_ref
                load = 1.0 - (1.0 - TAIL_LOAD) * self.sit.brake_blend(now)
                r.leg_frames += legs.frames(legs.controller.commands(
                    legs.hold_height, legs.hold_height, pitch=s.theta - self._d_hat,
                    load=load))
                return
            dl = legs.leveller.update(s.roll, self.imu.gyro[0], dt) \
                if legs.levelling else 0.0
            l_left, l_right = split_heights(l_ref, dl, self.p.height_min,
                                            self.p.height_max)
            due = legs.due(self._ticks)
            if due:
                theta = s.theta - self._d_hat
                r.leg_frames += legs.frames(legs.controller.commands(
                    l_left, l_right, l_dot, l_dot, pitch=theta, legs=due))
            if not legs.state.valid:
                self.supervisor.report_fault(now, LEGS, 'legs: ' + '; '.join(
                    legs.state.problems))
        elif mode is Mode.FAULT:
            hold = self._lift_hold
            if hold is not None and any(f.code == LIFTED for f in self.supervisor.faults):
                # Lifted: the legs keep their length, without the weight's share (the weight
                # is on the hand), so they neither drop nor push out.
                r.leg_frames += legs.frames(legs.controller.commands(*hold, load=0.0))
            else:
                r.leg_frames += legs.frames(legs.controller.damping_commands(legs.state))

    # ------------------------------------------------------------------ arming and sending

    def _handle_arm(self, arm: bool, now: float, s: SensorSnapshot) -> None:
        r, sup = self._result, self.supervisor
        if not arm:
            if sup.mode is Mode.BALANCING and self.sit_down_possible():
                self._start_sit_down()
                self._pending_reply = ('sit', True, 'sitting down: lowering, leaning onto the '
                                       'tail, then zero torque')
                return
            self._stop(disarm_reply=True)
        elif sup.mode is Mode.BALANCING or sup.mode is Mode.SITTING:
            self._pending_reply = ('noop', True, 'already balancing')
        elif self._silent_motor(now) is not None:
            self._pending_reply = ('refused', False, 'arming refused: %s'
                                   % self._silent_motor(now))
        elif self._foreign_reason(now):
            self._pending_reply = ('refused', False, 'arming refused: %s'
                                   % self._foreign_reason(now))
        elif self.motor_problems:
            self._pending_reply = ('refused', False, 'arming refused: %s'
                                   % '; '.join(self.motor_problems))
        elif self._lifted and not self._on_ground(s):
            self._pending_reply = ('refused', False, 'arming refused: lifted, and not back on '
                                   'the ground (the legs carry no weight and it is not on its '
                                   'tail)')
        elif self.legs is not None and not self._legs_ready(s):
            ok, reason = sup.start_homing(now, s, self._reply_times())
            if ok:
                legs = self.legs
                homed = legs.controller.homed
                legs.homing = None if homed else HipHoming(legs.controller.motors,
                                                           legs.homing_config)
                legs.raised_since = None
                legs.raise_integral = 0.0
                legs.shaper.height_min = self.p.height_min   # a sit-down folded below it
                if homed:
                    state = legs.read()
                    legs.shaper.reset(state.l if state.valid else self.p.height_min)
                r.frames += self.motors.enable_frames()
                r.leg_frames += legs.motors.enable_frames()
                self._pending_reply = ('arm', True, '%sraising the legs to %.2f m, then '
                                       'balancing' % ('' if homed else 'homing the legs, ',
                                                      self.p.height_min))
            else:
                self._pending_reply = ('refused', False, reason)
        else:
            self._start_balancing(now, s, reply_needed=True)

    def _on_ground(self, s: SensorSnapshot) -> bool:
        """Return True when the robot rests on its tail or its legs carry weight."""
        lim = self.supervisor.limits
        if abs(s.theta - lim.tail_pitch) <= lim.tail_tolerance:
            return True
        return self.legs is None or self.legs.load() >= self.lift.min_load

    def _start_sit_down(self) -> None:
        self.supervisor.sit_down()
        self.sit = SitDown(self.p, self.sit_down_config, lower=self.legs is not None)
        self._sit_d_hat = None
        if self.legs is not None:
            self.legs.raise_integral = 0.0
            self.legs.hold_height = None

    def _check_motors(self, now: float) -> None:
        """
        Motor health (core/motor_health.py) from the newest replies.

        An error code or a reboot: FAULT. Heat: the wheels' torque limit derated; at temp_max
        balancing ends with the sit-down (FAULT where it cannot run). Every problem refuses
        arming (``motor_problems``).
        """
        sup, problems, hot = self.supervisor, [], None
        scale = 1.0
        for motors, model in self._health:
            for m in motors.motors:
                fb = m.feedback
                if fb is None:
                    continue
                code, m.error = m.error, 0
                if code:
                    text = '%s error %d: %s' % (_motor_name(m), code, error_reason(code))
                    problems.append(text)
                    sup.report_fault(now, MOTOR_ERROR, text)
                if m.rebooted is not None:
                    text = '%s %s' % (_motor_name(m), m.rebooted)
                    problems.append(text)
                    sup.report_fault(now, MOTOR_REBOOTED, text)
                t = fb.temperature
                if motors is self.motors:
                    scale = min(scale, derate(t, model.temp_derate, model.temp_max))
                if t is not None and t >= model.temp_max:
                    hot = '%s at %.0f deg C, temp_max %.0f deg C' % (
                        _motor_name(m), t, model.temp_max)
                    problems.append(hot)
        self.core.config.max_wheel_torque = self.cfg.safety.max_wheel_torque * scale
        self.motor_problems = problems
        if hot is None:
            return
        if sup.mode is Mode.BALANCING and self.sit_down_possible():
            self._start_sit_down()
            self._result.events.append(('warn', 'over-temperature, sitting down: ' + hot))
        elif sup.mode is Mode.HOMING:
            sup.report_fault(now, OVER_TEMPERATURE, hot)

    def _can_arm(self, now: float, s: SensorSnapshot) -> bool:
        """Return True when an arm request would be accepted now (for auto_arm)."""
        sup = self.supervisor
        return not sup.check(now, s, self._reply_times()) and sup.pose_problem(s) is None \
            and self._silent_motor(now) is None and not self.motor_problems \
            and not self._foreign_reason(now)

    def _silent_motor(self, now: float) -> Optional[str]:
        """Return why a motor is not ready to arm (it must be answering), else None."""
        limit = self.supervisor.limits.motor_timeout
        if not self.from_can and self.legs is None:
            return None   # the motors answer only once commanded: judged after arming
        sets = ([self.motors] if self.from_can else []) + \
            ([self.legs.motors] if self.legs is not None else [])
        for motors in sets:
            for m in motors.motors:
                if m.last_reply is None or now - m.last_reply > limit:
                    return ('motor %d (%s) does not answer: powered, in MIT mode, on this bus, '
                            'with this CAN ID?' % (m.motor_id, m.name))
        return None

    def _legs_ready(self, s: SensorSnapshot) -> bool:
        """Return True when the legs are homed and at height_min or above (ready to balance)."""
        st = self.legs.state
        return self.legs.controller.homed and st is not None and st.valid and \
            st.l >= self.p.height_min - RAISED_TOLERANCE

    def sit_down_possible(self) -> bool:
        """Return True when the sensors allow the controlled sit-down (else: cut at once)."""
        return not self.supervisor.conditions

    def _start_balancing(self, now: float, s: SensorSnapshot, reply_needed: bool) -> None:
        r, sup = self._result, self.supervisor
        from_homing = sup.mode is Mode.HOMING
        ok, reason = sup.arm(now, s, self._reply_times())
        if ok:
            self.core.reset(self._measurement(s))
            self.shaper.reset()
            self._rising = True
            self._risen_since = None
            if not from_homing:
                r.frames += self.motors.enable_frames()
                if self.legs is not None:
                    r.leg_frames += self.legs.motors.enable_frames()
            if self.legs is not None:
                state = self.legs.read()
                self.legs.shaper.height_min = self.p.height_min
                self.legs.shaper.reset(state.l if state.valid else self.p.height_min)
                self.legs.leveller.reset()
            if reply_needed:
                self._pending_reply = ('arm', True, reason)
        elif reply_needed:
            self._pending_reply = ('refused', False, reason)
        else:
            sup.report_fault(now, LEGS, 'homed, but %s' % reason)

    def _finish_sit_down(self) -> None:
        sit = self.sit
        self.last_sit_down = sit
        self._result.events.append(('info', 'sat down: tail contact at %.2f rad/s, peak force '
                                    '%.0f N' % (sit.contact_rate or math.nan, sit.max_force)))
        self._stop(disarm_reply=False)

    def _stop(self, disarm_reply: bool) -> None:
        """Disarm: zero torque and exit motor mode for every motor."""
        r = self._result
        self.supervisor.disarm()
        self.sit = None
        r.frames += self.motors.stop_frames()
        if self.legs is not None:
            r.leg_frames += self.legs.motors.stop_frames()
        if disarm_reply:
            self._pending_reply = ('disarm', True, 'disarmed')

    def report_send(self, now: float, error: Optional[str]) -> None:
        """
        Tell the loop how sending this tick's frames went (None: all sent, else the error).

        A failed send while commanding is a fault; it completes a pending arm/disarm reply.
        """
        r = self._result
        if r.frames or r.leg_frames or error is not None:
            before = self.supervisor.mode
            self.supervisor.report_send(now, error is None, error or '')
            if error is not None and before in COMMANDING:
                r.events.append(('error', 'FAULT: CAN send failed: %s' % error))
        pending, self._pending_reply = self._pending_reply, None
        if pending is None:
            return
        kind, ok, message = pending
        if error is not None and kind == 'arm':
            ok, message = False, 'enter motor mode failed: %s' % error
        elif error is not None and kind == 'disarm':
            ok, message = False, 'disarmed, but %s' % error
        r.arm_reply = (ok, message)

    def report_internal_error(self, now: float,
                              message: str) -> Optional[Tuple[bool, str]]:
        """
        Report an exception that escaped a tick (a bug): a commanded mode goes to FAULT.

        Returns the failed reply of an arm/disarm request the tick was handling, else None.
        """
        self.supervisor.report_internal_error(now, message)
        pending, self._pending_reply = self._pending_reply, None
        if pending is None:
            return None
        self._result.arm_reply = (False, 'internal error: %s' % message)
        return self._result.arm_reply

    def stop_frames(self) -> Tuple[List[Frame], List[Frame]]:
        """
        Disarm; return zero torque + exit motor mode for every motor (start, shutdown).

        (the wheels' frames, the hips' frames): the hips may be on a bus of their own.
        """
        self.supervisor.disarm()
        self.sit = None
        return all_stop_frames(self.cfg)

    # ------------------------------------------------------------------------- publishing

    def _publish(self, s: SensorSnapshot) -> None:
        r, state = self._result, self._result.state
        state.theta, state.theta_dot, state.d_hat, state.l = s.theta, s.theta_dot, \
            self._d_hat, s.l
        state.roll = s.roll
        state.l_ref = self._l_ref()
        state.l_target = self._height_target if self.legs is not None else self._height
        state.controller = CONTROLLER_NAMES.index(self.core.active_controller)
        state.mode = int(self.supervisor.mode)
        odom, o = r.odom, self.odometry
        odom.x, odom.y, odom.yaw = o.pose
        odom.x_dot = o.x_dot if math.isfinite(o.x_dot) else 0.0
        odom.yaw_rate = o.yaw_rate if math.isfinite(o.yaw_rate) else 0.0

    def joint_values(self, now: float) -> Tuple[List[float], List[float], List[float]]:
        """
        Return (position, velocity, effort) of ``joint_names``, each in its joint's convention.

        Wheels: forward positive, relative to the leg (angle unwrapped from the replies, or the
        joint states' velocity); hips: the FiveBarLeg angles; knees: the passive angles of the
        five-bar kinematics (position only). NaN where unknown.
        """
        nan = math.nan
        pos, vel, eff = [], [], []
        for k, m in enumerate(self.motors.motors):
            if self.from_can:
                reading = self.wheel_states[k].reading(now)
                pos.append(reading.angle)
                vel.append(reading.speed)
            else:
                pos.append(nan)
                vel.append(self._snapshot.wheel_vel_left if k == 0
                           else self._snapshot.wheel_vel_right)
            eff.append(m.torque())
        legs = self.legs
        if legs is not None:
            st = legs.state
            dirs = legs.controller.motors.directions
            if st is None:
                st = legs.read()
            pos += list(st.q)
            vel += list(st.q_dot)
            eff += [d * (m.feedback.torque if m.feedback is not None else nan)
                    for d, m in zip(dirs, legs.motors.motors)]
            pos += list(st.knees)
            vel += [nan] * 4
            eff += [nan] * 4
        return pos, vel, eff

    # ---------------------------------------------------------------------------- status

    def status(self, now: float) -> Dict[str, Any]:
        """
        Everything /diagnostics shows about the tick, as plain values (picklable).

        mode, faults and conditions as (code, message) pairs, the controller, the references,
        input counters, per motor: alive, reply age [s], replies and the last feedback; the
        newest samples; the legs (homed, height, problems).
        """
        sup, snap = self.supervisor, self._snapshot
        motors = {}
        all_motors = self.motors.motors + (self.legs.motors.motors if self.legs else [])
        for m in all_motors:
            age = math.inf if m.last_reply is None else now - m.last_reply
            fb = m.feedback
            motors[m.motor_id] = {
                'name': m.name, 'alive': age <= sup.limits.motor_timeout, 'reply_age_s': age,
                'replies': m.replies,
                'feedback': None if fb is None else tuple(fb)}
        out = {
            'mode': sup.mode.name, 'mode_index': int(sup.mode),
            'faults': [(f.code, f.message) for f in sup.faults],
            'conditions': [(f.code, f.message) for f in sup.conditions],
            'controller': self.core.active_controller,
            'controller_parameter': self.cfg.control.controller,
            'x_dot_ref': self.shaper.x_dot_ref, 'yaw_rate_ref': self.shaper.yaw_rate_ref,
            'cmd_vel_timed_out': self.shaper.timed_out,
            'rejected_cmd_vel': self.rejected_cmd_vel,
            'rejected_cmd_height': self.rejected_cmd_height,
            'input_conflicts': self.input_conflicts,
            'foreign_commands': self.foreign_commands,
            'foreign_command_reason': self._foreign_reason(now),
            'warnings': self._warnings(),
            'frozen_imu_samples': self.imu.frozen,
            'refused_imu_stamps': self.imu.refused_stamps,
            'refused_imu_reason': self.imu.refused_reason,
            'protocol': self.protocol.name, 'rx_replies': self.motors.rx_replies,
            'motors': motors,
            'sensors': {
                'imu_age_s': _age(now, snap.imu_time), 'joint_age_s': _age(now, snap.joint_time),
                'theta': snap.theta, 'theta_dot': snap.theta_dot, 'roll': snap.roll,
                'attitude_source': self.imu.source,
                'wheel_vel_left': snap.wheel_vel_left, 'wheel_vel_right': snap.wheel_vel_right,
                'wheel_state_source': self.cfg.wheel_state.wheel_state_source,
                'l': snap.l},
        }
        if self.legs is not None:
            st = self.legs.state
            out['legs'] = {'homed': self.legs.controller.homed,
                           'homing': None if self.legs.homing is None
                           else self.legs.homing.status,
                           'l_ref': self.legs.shaper.l_ref, 'target': self._height_target,
                           'problems': list(st.problems) if st is not None else ['no state']}
        if self.sit is not None:
            out['sit_down'] = self.sit.phase
        return out


def _age(now: float, t: Optional[float]) -> float:
    return math.inf if t is None else now - t
