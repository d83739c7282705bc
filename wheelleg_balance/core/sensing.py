"""
Sensing, the first part of the tick: the IMU and the motors' replies into one snapshot.

``Sensing`` owns what the robot tells the tick (no rclpy, no CAN): the IMU reader (roll and
theta~ from the whole orientation, core/sensors.py), the wheel motors and, with driven legs,
the hip motors (core/motors.py ``MotorSet``: liveness and the newest feedback of each), each
wheel's angle and speed from its replies (core/wheel_state.py, ``wheel_state_source: can``) or
another driver's joint states (``joint_states``). Per tick it takes what arrived
(``take``) and gives the ``SensorSnapshot`` the checks and the controllers read (``read``).

Two things it notices on the way, for the supervisor (core/arming.py) to judge: command frames
to our motors that this node did not send (another commander on the bus: the protocol decides
what is a command, ``commanded_motors``), and wheel replies whose position contradicts their
speed (``encoder_mismatch``, a warning).
"""
import math
from typing import Any, Dict, List, Optional, Tuple

from .config import BalanceConfig
from .kinematics import FiveBarLeg
from .motors import MotorSet
from .protocols import protocol_for
from .protocols.base import Frame, MotorProtocol
from .safety import ENCODER_MISMATCH, SensorSnapshot
from .sensors import ImuReader, JointSample, JointStateReader
from .wheel_state import WheelState

LEFT_WHEEL = 'left_wheel'
RIGHT_WHEEL = 'right_wheel'
WHEELS = (LEFT_WHEEL, RIGHT_WHEEL)
HIPS = ('left_front_hip', 'left_rear_hip', 'right_front_hip', 'right_rear_hip')
#: Arming is refused until no command frame from another sender has come for this long [s]:
#: a script or a second node that commands now and then is still there between its frames.
FOREIGN_COMMAND_HOLD = 1.0
#: What a command frame this node did not send most likely is, for a fault or refusal reason.
ANOTHER_SENDER = ('another sender on the bus (another balance_node, a test script, a second '
                  'computer?)')


def build_protocol(cfg: BalanceConfig) -> MotorProtocol:
    """Build the wheel motors' CAN codec named by ``can.protocol`` (from its can.* section)."""
    return protocol_for(cfg.can.protocol, cfg.can)


def _model(owner, protocol: MotorProtocol):
    """Return the figures (temp_derate, temp_max, ...) of ``protocol``'s motors in ``owner``."""
    return getattr(owner, protocol.config_section, None) or owner.mit


def wheel_motors(cfg: BalanceConfig, directions: bool = True) -> MotorSet:
    """Return the two wheel motors of ``cfg`` (directions +1 where they do not matter)."""
    can = cfg.can
    return MotorSet(build_protocol(cfg), (
        (LEFT_WHEEL, can.left_motor_id, can.left_direction if directions else 1),
        (RIGHT_WHEEL, can.right_motor_id, can.right_direction if directions else 1)))


def hip_motors(cfg: BalanceConfig) -> MotorSet:
    """Return the four hip motors of ``cfg`` (their directions are the legs' business)."""
    return MotorSet(protocol_for(cfg.legs.protocol, cfg.legs),
                    [(name, i, 1) for name, i in zip(HIPS, cfg.legs.motor_ids)])


def all_stop_frames(cfg: BalanceConfig) -> Tuple[List[Frame], List[Frame]]:
    """
    Return zero torque + exit motor mode for every motor of ``cfg``: (the wheels', the hips').

    What the loop sends at start-up and shutdown (BalanceLoop.stop_frames), built from the
    configuration alone for the watchdog (nodes/watchdog.py), which has no loop.
    """
    wheels = wheel_motors(cfg, directions=False).stop_frames()
    return wheels, hip_motors(cfg).stop_frames() if cfg.legs.driven else []


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


def motor_name(m) -> str:
    """Name a motor in a problem's text: 'motor 3 (left_front)'."""
    return 'motor %d (%s)' % (m.motor_id, m.name)


class Sensing:
    """The IMU, the motors' replies and the joint states of the tick (module docstring)."""

    def __init__(self, cfg: BalanceConfig):
        self.cfg = cfg
        self.motors = wheel_motors(cfg)
        self.protocol = self.motors.protocol
        self.hips: Optional[MotorSet] = hip_motors(cfg) if cfg.legs.driven else None
        self.imu = ImuReader(cfg.imu.imu_mounting_rpy, cfg.model.gravity,
                             cfg.safety.stamp_tolerance)
        self.from_can = cfg.wheel_state.wheel_state_source == 'can'
        ws = cfg.wheel_state
        self.wheel_states = [WheelState(m.direction, self.protocol, ws.wheel_speed_time_constant,
                                        wrap=ws.position_wraps)
                             for m in self.motors.motors] if self.from_can else []
        self._wheel_state_of = {m.motor_id: w for m, w in zip(self.motors.motors,
                                                              self.wheel_states)}
        #: The hips' IDs that are no wheel's, where the wheels' replies name their motor in
        #: byte 0 (MIT): a frame with one of them there is no wheel reply (take).
        self._hip_only = frozenset(self.hips.by_id).difference(self.motors.by_id) \
            if self.hips is not None and self.protocol.reply_id_in_first_byte else frozenset()
        #: The hips' angles come from joint_states_in (legs of another driver).
        self.has_leg_joints = bool(joint_state_reader(cfg).legs)
        self._wheels: Optional[JointSample] = None   # newest sample with the wheels
        self.legs_js: Optional[JointSample] = None   # newest sample with the hips
        #: Each motor set with its model's figures (core/motor_health.py).
        self.health = [(self.motors, _model(cfg.can, self.protocol))] + (
            [(self.hips, _model(cfg.legs, self.hips.protocol))] if self.hips is not None else [])
        for motors, model in self.health:   # the reboot check where the model sets a limit
            p = motors.protocol
            if getattr(model, 'position_jump', None):
                codes = p.reply_codes()   # the field wraps every p_codes codes
                motors.jump_limit = model.position_jump
                motors.span = math.inf if codes.saturates or not \
                    cfg.wheel_state.position_wraps else codes.p_codes * codes.p_step
                motors.speed_limit = 0.9 * p.speed_range
        #: Command frames to our motors that this node did not send (a second commander): how
        #: many, the newest's receipt time [s], the motors it addressed, one since the check.
        self.foreign_commands = 0
        self.foreign_last: Optional[float] = None
        self._foreign_motors = ''
        self._foreign_new = False
        #: Wheels whose encoder_mismatch was announced (one warn event per wheel and run).
        self._mismatch_warned: set = set()
        self.snapshot = SensorSnapshot()
        self.configure(cfg)

    def configure(self, cfg: BalanceConfig) -> None:
        """Take the live settings of ``cfg`` (at build and on every parameter change)."""
        self.cfg = cfg
        self.imu.stamp_tolerance = cfg.safety.stamp_tolerance

    @property
    def all_motors(self) -> list:
        """Return every motor: the wheels, then the hips."""
        return self.motors.motors + (self.hips.motors if self.hips is not None else [])

    # ------------------------------------------------------------------------------ per tick

    def take(self, imu, joints, frames, accel: float, events: list) -> None:
        """
        Take what arrived: IMU samples, joint states, CAN frames (receipt time, Frame).

        accel: the robot's own forward acceleration [m/s^2] (the IMU's gravity fallback);
        events: where a one-time warning goes, as (level, text).
        """
        if imu:
            take_imu = self.imu.take
            for sample in imu:
                take_imu(sample, accel)
        for sample in joints:
            if sample.has_wheels:
                self._wheels = sample
            if sample.has_legs:
                self.legs_js = sample
        hips, hip_only, on_frame = self.hips, self._hip_only, self.motors.on_frame
        wheel_state_of = self._wheel_state_of
        for t, frame in frames:
            data = frame.data
            if hip_only and type(data) is bytes and data and data[0] in hip_only:
                # Byte 0 names a hip only: no wheel reply (the wheels' codec reads the
                # replying motor's ID there), so the wheels need not decode it.
                if hips.on_frame(t, frame) is None:
                    self._note_foreign(t, frame)
                continue
            motor = on_frame(t, frame)
            if motor is None:
                if hips is None or hips.on_frame(t, frame) is None:
                    self._note_foreign(t, frame)
            elif wheel_state_of:   # wheel_state_source: can
                fb = motor.feedback
                wheel = wheel_state_of[motor.motor_id]
                wheel.update(fb[1], fb[2], t)   # position, velocity
                if wheel.mismatch and motor.motor_id not in self._mismatch_warned:
                    self._warn_mismatch(motor, wheel, events)

    def read(self, now: float, leg_l: Optional[float], height: float) -> SensorSnapshot:
        """
        Return the snapshot of now [s] (one object, reused).

        leg_l: the driven legs' height [m] (None: the legs are not driven); height: the
        ``height`` parameter, l where no leg joints tell it.
        """
        s, imu = self.snapshot, self.imu
        s.imu_time, s.theta, s.theta_dot, s.roll = imu.time, imu.theta, imu.theta_dot, imu.roll
        if self.from_can:
            # min of the two wheels' reply times as a comparison (a min call costs ten times
            # as much); None until both replied
            left, right = self.motors.reply_times.values()
            s.joint_time = None if left is None or right is None else \
                right if right < left else left
            ws = self.wheel_states
            s.wheel_vel_left, s.wheel_vel_right = ws[0].speed, ws[1].speed   # reading's
        elif self._wheels is None:
            s.joint_time, s.wheel_vel_left, s.wheel_vel_right = None, math.nan, math.nan
        else:
            s.joint_time = self._wheels.t
            s.wheel_vel_left, s.wheel_vel_right = self._wheels.w_left, self._wheels.w_right
        if leg_l is not None:
            s.l = leg_l
        elif self.has_leg_joints:
            legs = self.legs_js
            if legs is None:
                s.joint_time, s.l = None, math.nan
            else:
                s.l = legs.l
                if s.joint_time is not None:
                    s.joint_time = min(s.joint_time, legs.t)
        else:
            s.l = height
        return s

    def reply_times(self) -> Dict[int, Optional[float]]:
        """Return {motor ID: the newest reply's receipt time [s] or None} of every motor."""
        if self.hips is None:
            return self.motors.reply_times
        return {**self.motors.reply_times, **self.hips.reply_times}

    def silent_motor(self, now: float, limit: float) -> Optional[str]:
        """Return why a motor is not ready to arm (it must be answering within limit), or None."""
        if not self.from_can and self.hips is None:
            return None   # the motors answer only once commanded: judged after arming
        sets = ([self.motors] if self.from_can else []) + \
            ([self.hips] if self.hips is not None else [])
        for motors in sets:
            for m in motors.motors:
                if m.last_reply is None or now - m.last_reply > limit:
                    return ('motor %d (%s) does not answer: powered, in MIT mode, on this bus, '
                            'with this CAN ID?' % (m.motor_id, m.name))
        return None

    # ----------------------------------------------------------------- a second commander

    def _note_foreign(self, t: float, frame: Frame) -> None:
        """Count a frame that commands one of our motors but is none of ours (not a reply)."""
        for motors, _ in self.health:
            hit = motors.commanded_motors(frame)
            if hit:
                self.foreign_commands += 1
                self.foreign_last = t
                self._foreign_motors = ', '.join(motor_name(m) for m in hit)
                self._foreign_new = True
                return

    def new_foreign_command(self) -> str:
        """Return the fault's reason once per tick that saw another sender's command, else ''."""
        if not self._foreign_new:
            return ''
        self._foreign_new = False
        return 'command frames to %s that this node did not send: %s' % (
            self._foreign_motors, ANOTHER_SENDER)

    def foreign_reason(self, now: float) -> str:
        """Return why arming is refused for another sender's commands ('' for none lately)."""
        last = self.foreign_last
        if last is None or now - last > FOREIGN_COMMAND_HOLD:
            return ''
        return ('%s got command frames this node did not send: %s; %d so far, the newest '
                '%.3f s ago (arming waits until none came for %.1f s)' % (
                    self._foreign_motors, ANOTHER_SENDER, self.foreign_commands, now - last,
                    FOREIGN_COMMAND_HOLD))

    # ------------------------------------------------------------- encoders that saturate

    def _warn_mismatch(self, motor, wheel: WheelState, events: list) -> None:
        """Announce once per wheel that its replies contradict its speed (encoder_mismatch)."""
        self._mismatch_warned.add(motor.motor_id)
        if motor.rebooted is not None:
            return   # a reboot's jump: motor_rebooted names it (core/motors.py)
        events.append(('warn', '%s: %s: %s; %s' % (
            ENCODER_MISMATCH, motor_name(motor), wheel.mismatch_reason,
            self._mismatch_advice())))

    def _mismatch_advice(self) -> str:
        """Return the likely cause of an encoder_mismatch and its fix, for this configuration."""
        if self.cfg.wheel_state.position_wraps:
            codes = self.protocol.reply_codes()
            return ('likely firmware that saturates the position at its range ends (%g and '
                    '%g rad) instead of wrapping it: set can.mit.wrap: false. The wheel angle '
                    'is dead-reckoned from the reported speed until the position agrees with '
                    'it again' % (codes.p_zero, codes.p_zero + (codes.p_codes - 1)
                                  * codes.p_step))
        return ('with can.mit.wrap: false already: an encoder or reply fault? Check the motor '
                'and can.mit.p_min / p_max. The wheel angle is dead-reckoned from the reported '
                'speed until the position agrees with it again')

    def warnings(self) -> List[Tuple[str, str]]:
        """Return (code, message) of each warning (WARNING_CODES) for /diagnostics."""
        out = []
        for m, w in zip(self.motors.motors, self.wheel_states):
            if w.mismatches and m.rebooted is None:   # a reboot's jump: motor_rebooted
                out.append((ENCODER_MISMATCH, '%s: %s%s' % (
                    motor_name(m), w.mismatch_reason,
                    '; the wheel angle is dead-reckoned from the reported speed' if w.mismatch
                    else '; %d times since the start, the position agrees with the speed again'
                    % w.mismatches)))
        return out

    # ------------------------------------------------------------------------- publishing

    def wheel_joint_values(self, now: float) -> Tuple[List[float], List[float], List[float]]:
        """Return the wheels' (positions, velocities, efforts), forward positive (NaN unknown)."""
        pos, vel, eff = [], [], []
        for k, m in enumerate(self.motors.motors):
            if self.from_can:
                reading = self.wheel_states[k].reading(now)
                pos.append(reading.angle)
                vel.append(reading.speed)
            else:
                pos.append(math.nan)
                vel.append(self.snapshot.wheel_vel_left if k == 0
                           else self.snapshot.wheel_vel_right)
            eff.append(m.torque())
        return pos, vel, eff

    def status(self, now: float, motor_timeout: float) -> Dict[str, Any]:
        """Return the sensing part of /diagnostics (the motors, the IMU, the newest samples)."""
        snap, imu = self.snapshot, self.imu
        motors = {}
        for m in self.all_motors:
            age = math.inf if m.last_reply is None else now - m.last_reply
            fb = m.feedback
            motors[m.motor_id] = {
                'name': m.name, 'alive': age <= motor_timeout, 'reply_age_s': age,
                'replies': m.replies, 'feedback': None if fb is None else tuple(fb)}
        return {
            'foreign_commands': self.foreign_commands,
            'foreign_command_reason': self.foreign_reason(now),
            'warnings': self.warnings(),
            'frozen_imu_samples': imu.frozen,
            'refused_imu_stamps': imu.refused_stamps,
            'refused_imu_reason': imu.refused_reason,
            'protocol': self.protocol.name, 'rx_replies': self.motors.rx_replies,
            'motors': motors,
            'sensors': {
                'imu_age_s': _age(now, snap.imu_time), 'joint_age_s': _age(now, snap.joint_time),
                'theta': snap.theta, 'theta_dot': snap.theta_dot, 'roll': snap.roll,
                'attitude_source': imu.source,
                'wheel_vel_left': snap.wheel_vel_left, 'wheel_vel_right': snap.wheel_vel_right,
                'wheel_state_source': self.cfg.wheel_state.wheel_state_source,
                'l': snap.l}}


def _age(now: float, t: Optional[float]) -> float:
    return math.inf if t is None else now - t
