"""
The robot's CAN motors as the tick sees them: IDs, mounting directions, replies (no python-can).

``MotorSet`` maps joint-convention torques (forward positive for a wheel) to the protocol's
frames through each motor's ID and direction, and turns the replies that arrive into per-motor
status: the time of the last reply, a reply counter and the last decoded feedback, whose
position, velocity and torque it hands back in the joint's convention. Everything the safety
supervisor needs to judge a motor's liveness comes from here.
"""
import math
from typing import Dict, Iterable, List, Mapping, Optional, Sequence, Tuple

from .actuation import check_direction
from .motor_health import MAX_ACCELERATION, RECEIPT_JITTER
from .protocols.base import Frame, MotorFeedback, MotorProtocol

_INF = math.inf


def _quiet(jump_limit: float, span: float) -> float:
    """
    Return how far [rad] a reply may be off the extrapolation without the rest of the check.

    Below half the limit the offset stays below it after the wrap (for a span of 4 to 1e6
    limits the wrap moves it by rounding only, under 1e-9 limits) and the allowances only
    lower it; 0 (check it all) for a limit below 1 urad, inf or NaN, or another span.
    """
    if not 1e-6 <= jump_limit < math.inf:
        return 0.0
    if 0.0 < span < math.inf and not 4.0 * jump_limit <= span <= 1e6 * jump_limit:
        return 0.0
    return 0.5 * jump_limit


class Motor:
    """One motor: name, CAN ID, direction (+1/-1) and what its replies said."""

    __slots__ = ('name', 'motor_id', 'direction', 'last_reply', 'replies', 'feedback',
                 'rebooted', 'error', 'drive_error', 'switched_off')

    def __init__(self, name: str, motor_id: int, direction: int):
        self.name = name
        self.motor_id = int(motor_id)
        self.direction = check_direction(direction)
        self.last_reply: Optional[float] = None   # monotonic [s]
        self.replies = 0
        self.feedback: Optional[MotorFeedback] = None
        #: Why the motor counts as rebooted (a position jump), None while it does not.
        self.rebooted: Optional[str] = None
        #: The newest non-zero error code a reply carried since the tick read it (0: none), so
        #: that a clean reply after it within one tick does not hide it.
        self.error = 0
        #: The error code the drive reports now: the newest reply's that carries a code (0: none).
        #: It stays until a reply says the error is gone (a drive keeps its error latched until
        #: cleared), so every tick judges it and arming is refused while it lasts.
        self.drive_error = 0
        #: A reply said "disabled" after one said "enabled" (protocols whose replies carry
        #: the state: DaMiao, CyberGear); motor_health.judge_motors takes (resets) it.
        self.switched_off = False

    def velocity(self) -> float:
        """Last reported velocity in the joint's convention [rad/s] (NaN: no reply yet)."""
        fb = self.feedback
        return float('nan') if fb is None else self.direction * fb.velocity

    def position(self) -> float:
        """Last reported position in the joint's convention [rad] (NaN: no reply yet)."""
        fb = self.feedback
        return float('nan') if fb is None else self.direction * fb.position

    def torque(self) -> float:
        """Last reported torque in the joint's convention [N m] (NaN: no reply yet)."""
        fb = self.feedback
        return float('nan') if fb is None else self.direction * fb.torque


class MotorSet:
    """
    A group of motors on one bus behind one protocol.

    motors: (name, CAN ID, direction) per motor. ``reply_times`` ({motor ID: monotonic time of
    the last reply or None}) is what the safety supervisor reads each tick.
    """

    def __init__(self, protocol: MotorProtocol, motors: Sequence[Tuple[str, int, int]]):
        self.protocol = protocol
        self.motors = [Motor(name, i, d) for name, i, d in motors]
        ids = [m.motor_id for m in self.motors]
        if len(set(ids)) != len(ids):
            raise ValueError('motor IDs must differ: %s' % ids)
        self.by_name: Dict[str, Motor] = {m.name: m for m in self.motors}
        self.by_id: Dict[int, Motor] = {m.motor_id: m for m in self.motors}
        self.ids: Tuple[int, ...] = tuple(ids)
        self.reply_times: Dict[int, Optional[float]] = dict.fromkeys(ids)
        self.rx_replies = 0
        #: Reboot check: a reply position off the last one's extrapolation by more than
        #: jump_limit [rad], modulo the reply field's span [rad] (inf: no check); not judged
        #: while a speed reading is beyond speed_limit [rad/s] (near the end of its field, where
        #: it saturates or wraps: the extrapolation would be wrong).
        self._jump_limit = self._span = math.inf
        self._quiet = 0.0
        self.speed_limit = math.inf
        #: Something for motor_health.judge_motors to judge: a motor's newest reply carries a
        #: temperature, an error code is pending, a motor rebooted (it clears the flag after a
        #: pass that found none; until then every motor is judged each tick).
        self.notable = True
        #: The protocol's health replies (MotorProtocol.decode_health), None where it sends
        #: no health query: its torque replies carry the error code.
        self._decode_health = protocol.decode_health if protocol.health_interval else None

    @property
    def jump_limit(self) -> float:
        """Return the reboot check's limit [rad] (inf: no check)."""
        return self._jump_limit

    @jump_limit.setter
    def jump_limit(self, value: float) -> None:
        self._jump_limit = value
        self._quiet = _quiet(value, self._span)

    @property
    def span(self) -> float:
        """Return the reply field's span [rad] the reboot check wraps by (inf: no wrap)."""
        return self._span

    @span.setter
    def span(self, value: float) -> None:
        self._span = value
        self._quiet = _quiet(self._jump_limit, value)

    def on_frame(self, t: float, frame: Frame) -> Optional[Motor]:
        """Take a received frame at monotonic time ``t`` [s]; return the motor that replied."""
        by_id = self.by_id
        feedback = self.protocol.decode_reply(frame, by_id)
        if feedback is None:
            if self._decode_health is not None:
                self._take_health(frame)
            return None  # not a reply, or another motor set's (or a stranger's) on the bus
        # MotorFeedback's fields by index (motor_id, position, velocity, torque, temperature,
        # error): a reply or six a tick, each name a descriptor call.
        motor = by_id[feedback[0]]
        prev = motor.feedback
        if prev is not None and motor.rebooted is None and self._jump_limit < _INF:
            limit = self.speed_limit
            v_prev, v = prev[2], feedback[2]
            if -limit < v_prev < limit and -limit < v < limit:
                # motor_health.position_jump inlined (the same operations, in its order),
                # its end skipped where the offset d cannot exceed the limit (_quiet).
                gap = t - motor.last_reply
                v_sum = v_prev + v
                d = feedback[1] - (prev[1] + 0.5 * v_sum * gap)
                quiet = self._quiet
                if -quiet < d < quiet:
                    jump = 0.0
                else:
                    span = self._span
                    if 0.0 < span < _INF:
                        d = (d + 0.5 * span) % span - 0.5 * span
                    d = abs(d) - 0.5 * MAX_ACCELERATION * gap * gap \
                        - 0.5 * abs(v_sum) * RECEIPT_JITTER
                    jump = d if d > 0.0 else 0.0
                if jump > self._jump_limit:
                    motor.rebooted = ('position jumped by %.2f rad (jump limit %.2f rad): '
                                      'rebooted? its angle is known only modulo a rotor turn'
                                      % (jump, self.jump_limit))
                    self.notable = True
        motor.last_reply = t
        motor.replies += 1
        motor.feedback = feedback
        code = feedback[5]
        if code:
            motor.error = motor.drive_error = code
            self.notable = True
        else:
            if code is not None and motor.drive_error:
                motor.drive_error = 0   # the drive's error is cleared
            if feedback[6] is False and prev is not None and prev[6]:
                # Enabled, now disabled without an error code (that one names its cause): a
                # reboot (DaMiao and CyberGear power up disabled) or the drive's own
                # protection; within +-pi a DaMiao reboot leaves no position jump.
                motor.switched_off = True
                self.notable = True
        if feedback[4] is not None:   # a temperature
            self.notable = True
        self.reply_times[motor.motor_id] = t
        self.rx_replies += 1
        return motor

    def _take_health(self, frame: Frame) -> None:
        """Take a health reply of one of ours: its error code and temperature, for judging."""
        health = self._decode_health(frame)
        motor = self.by_id.get(health.motor_id) if health is not None else None
        if motor is None:
            return
        motor.drive_error = health.error
        if health.error:
            motor.error = health.error
            self.notable = True
        if health.temperature is not None and motor.feedback is not None:
            motor.feedback = motor.feedback._replace(temperature=health.temperature)
            self.notable = True

    def commanded_motors(self, frame: Frame) -> List[Motor]:
        """
        Return the motors of this set that a frame commands ([] for every other frame).

        The protocol decides (``command_motor_ids``): a reply is no command.
        """
        ids = self.protocol.command_motor_ids(frame)
        by_id = self.by_id
        return [by_id[i] for i in ids if i in by_id] if ids else []

    def torque_frames(self, torques: Mapping[str, float]) -> List[Frame]:
        """Frames commanding {motor name: joint torque [N m]} (directions applied here)."""
        by_name, motor_torques = self.by_name, {}
        for name, tau in torques.items():   # a loop, not a comprehension: one call less a tick
            m = by_name[name]
            motor_torques[m.motor_id] = m.direction * tau
        return self.protocol.torque_frames(motor_torques)

    def zero_torque_frames(self, names: Optional[Iterable[str]] = None) -> List[Frame]:
        """Zero-torque commands, staying in motor mode (all motors by default)."""
        return self.protocol.zero_torque_frames(self._ids(names))

    def enable_frames(self, names: Optional[Iterable[str]] = None) -> List[Frame]:
        """Enter motor mode."""
        return self.protocol.enable_frames(self._ids(names))

    def stop_frames(self, names: Optional[Iterable[str]] = None) -> List[Frame]:
        """Zero torque, then exit motor mode (disarm, start-up, shutdown)."""
        ids = self._ids(names)
        return self.protocol.zero_torque_frames(ids) + self.protocol.disable_frames(ids)

    def _ids(self, names: Optional[Iterable[str]]) -> Tuple[int, ...]:
        if names is None:
            return self.ids
        return tuple(self.by_name[n].motor_id for n in names)
