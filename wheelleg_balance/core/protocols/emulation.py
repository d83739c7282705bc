"""
What every emulated motor shares, whatever its protocol (pure Python: no MuJoCo, no python-can).

A protocol module's emulator (``MotorProtocol.make_emulator``) subclasses ``EmulatedMotor`` and
only turns frames into commands and its state into replies (``handle``); the joint mapping,
the impedance law with its torque limit, the motor's own command timeout, the fault hooks the
fault rig drives (temperature, error, reboot, miswiring, a wrong reply ID) and the power-up
position are here once. ``EmulatedMotors`` puts any protocol's motors on one simulated bus.

Conventions as in sim/motor_emulator.py (the MIT and C620 emulators): q, q_dot and the torque
returned are the *joint's*; the motor's direction (+1 or -1) maps them: motor position =
direction q - zero. A command is a ``Command`` (position, velocity, kp, kd, torque): tau = kp
(position - motor position) + kd (velocity - motor speed) + torque, clamped to the torque
limit; a torque-only protocol's is ``torque_only(torque)``.
"""
import math
from typing import Any, Dict, Iterable, List, Mapping, NamedTuple, Optional, Tuple

from .base import Frame

TIMEOUT_ACTIONS = ('zero', 'rest')


class Command(NamedTuple):
    """An impedance command: kp (position - p) + kd (velocity - v) + torque at the motor."""

    position: float   # [rad]
    velocity: float   # [rad/s]
    kp: float         # [N m/rad]
    kd: float         # [N m s/rad]
    torque: float     # [N m]


def torque_only(tau: float) -> Command:
    """Return the command of a feed-forward torque tau [N m] alone."""
    return Command(0.0, 0.0, 0.0, 0.0, tau)


class EmulatedMotor:
    """
    One motor's state behind its firmware (see the module docstring); subclasses add frames.

    torque_limit [N m]: what the motor can give; gear_ratio: rotor turns per output turn;
    direction: +1 or -1, motor shaft relative to the joint; command_timeout [s] (0: none) and
    timeout_action ('zero': the command is dropped, 'rest': the motor leaves its torque mode,
    as the motor's documentation says); temperature [deg C]; powered_enabled: whether the
    motor takes torque commands right after power-up (no enable frame needed).
    """

    def __init__(self, motor_id: int, torque_limit: float, gear_ratio: float = 1.0,
                 direction: int = 1, command_timeout: float = 0.0,
                 timeout_action: str = 'zero', temperature: float = 25.0,
                 powered_enabled: bool = False):
        if direction not in (1, -1):
            raise ValueError('direction must be 1 or -1')
        if timeout_action not in TIMEOUT_ACTIONS:
            raise ValueError('timeout_action must be one of %s' % ', '.join(TIMEOUT_ACTIONS))
        if not (gear_ratio > 0.0 and command_timeout >= 0.0 and torque_limit > 0.0):
            raise ValueError('gear_ratio and torque_limit must be > 0, command_timeout >= 0')
        self.motor_id = int(motor_id)
        self.torque_limit = float(torque_limit)
        self.gear_ratio = float(gear_ratio)
        self.direction = int(direction)
        self.command_timeout = float(command_timeout)
        self.timeout_action = timeout_action
        self.temperature = float(temperature)
        self.powered_enabled = bool(powered_enabled)
        self.miswired = False
        self.reply_id: Optional[int] = None   # fault: the ID its replies carry (None: its own)
        self.error = 0                        # the protocol's error code or bits (0: none)
        self.zero = 0.0              # motor position [rad] (direction applied) that reads as 0
        self.enabled = self.powered_enabled
        #: The command in force (a Command, or any object with its fields: MitCommand).
        self.command: Optional[Any] = None
        self.motor_torque = 0.0      # torque the motor applies [N m], its own direction
        self.frames = 0              # frames it acted on
        self.timeouts = 0            # times the command timeout fired
        self.last_decoded = None     # what the last frame it acted on was (protocol's words)
        self._last_command_time = -math.inf

    # ---- the motor's view of the joint ----------------------------------------------------

    @property
    def effective_direction(self) -> int:
        """Return the direction the motor really turns (the configured one unless miswired)."""
        return -self.direction if self.miswired else self.direction

    def position(self, q: float) -> float:
        """Return the motor's multi-turn output position [rad] for the joint angle q [rad]."""
        return self.effective_direction * q - self.zero

    def velocity(self, q_dot: float) -> float:
        """Return the motor's output speed [rad/s] for the joint speed q_dot [rad/s]."""
        return self.effective_direction * q_dot

    @property
    def own_reply_id(self) -> int:
        """Return the ID its replies carry (its own unless the reply_id fault is set)."""
        return self.motor_id if self.reply_id is None else self.reply_id

    # ---- what subclasses call -------------------------------------------------------------

    def handle(self, frame: Frame, q: float, q_dot: float, now: float) -> Optional[Frame]:
        """Act on a frame as the firmware does; return the reply, or None (not for it)."""
        raise NotImplementedError

    def set_command(self, command: Optional[Any], now: float) -> None:
        """Take a new command (None: no torque) received at ``now`` [s]."""
        self.command = command
        self._last_command_time = now

    def set_enabled(self, enabled: bool, now: float) -> None:
        """Enter (True) or leave the torque mode; entering starts from no command."""
        if enabled and not self.enabled:
            self.command = None
        self.enabled = bool(enabled)
        self._last_command_time = now

    def set_zero_here(self, q: float) -> None:
        """Make the present position the motor's zero."""
        self.zero = self.effective_direction * q

    # ---- physics ---------------------------------------------------------------------------

    def torque(self, q: float, q_dot: float, now: float) -> float:
        """
        Return the joint torque [N m] the motor applies now (zero outside its torque mode).

        The impedance law on the motor's own position and speed, clamped to the torque limit,
        mapped to the joint through the direction; applies the command timeout first.
        """
        cmd = self.command
        if self.enabled and self.command_timeout > 0.0 \
                and now - self._last_command_time > self.command_timeout:
            self.timeouts += 1
            self._last_command_time = math.inf   # fire once per silence
            self.command = cmd = None
            self.on_timeout()
        if not self.enabled or cmd is None or self.error:
            self.motor_torque = 0.0
            return 0.0
        tau = (cmd.kp * (cmd.position - self.position(q))
               + cmd.kd * (cmd.velocity - self.velocity(q_dot)) + cmd.torque)
        lim = self.torque_limit
        tau = min(max(tau, -lim), lim) if math.isfinite(tau) else 0.0
        self.motor_torque = tau
        return self.effective_direction * tau

    def on_timeout(self) -> None:
        """Act on the command timeout beyond dropping the command (timeout_action)."""
        if self.timeout_action == 'rest':
            self.enabled = False

    # ---- scenario -------------------------------------------------------------------------

    def reboot(self, q: float) -> None:
        """
        Power-cycle at joint angle q [rad]: the power-up state, no command, no error.

        The position afterwards is what ``power_up_position`` says the encoder reads.
        """
        self.enabled = self.powered_enabled
        self.command = None
        self.motor_torque = 0.0
        self.error = 0
        self.zero = self.effective_direction * q - self.power_up_position(self.position(q))

    def power_up_position(self, position: float) -> float:
        """
        Return the reading [rad] after power-up of a motor that was at ``position`` [rad].

        Default: an absolute encoder on the output that keeps its zero (nothing changes).
        """
        return position

    def set_temperature(self, temperature: float) -> None:
        """Set the temperature [deg C] its replies report."""
        self.temperature = float(temperature)

    def set_error(self, code: int) -> None:
        """Set the error code or bits its replies report (0: none); output off until 0."""
        self.error = int(code)

    def set_control_mode(self, mode: int) -> None:
        """
        Put the motor in control mode ``mode``, its mode register's value (a bring-up fault).

        What another tool may leave a motor in; ValueError for a motor with no such register
        (the default) or a value it does not have.
        """
        raise ValueError('motor %d has no control mode register' % self.motor_id)


def rotor_turn_position(position: float, gear_ratio: float,
                        window: Tuple[float, float] = (-math.pi, math.pi)) -> float:
    """
    Return the output reading [rad] of a rotor encoder known only within one rotor turn.

    The rotor angle gear_ratio * position wrapped into the window (lo, hi] [rad], over the
    gear ratio: what a multi-turn count that restarts at power-up reads.
    """
    lo, hi = window
    rotor = gear_ratio * position
    return (hi - (hi - rotor) % (hi - lo)) / gear_ratio


class EmulatedMotors:
    """
    Any protocol's motors on one simulated bus, each joint at an angle and speed the caller sets.

    ``handle`` offers a frame to every motor (a list of replies: none or some); ``torque`` is
    what a motor applies to its joint now. protocol: the codec (its make_emulator builds each
    motor); ids: CAN IDs; directions: {ID: +1 or -1} (default +1); options: the emulators'.
    ``silent``: IDs whose replies are lost (the motor still acts on the frames).
    """

    def __init__(self, protocol, ids: Iterable[int],
                 directions: Optional[Mapping[int, int]] = None, **options):
        directions = directions or {}
        self.protocol = protocol
        self.emulators: Dict[int, EmulatedMotor] = {
            int(i): protocol.make_emulator(int(i), direction=directions.get(i, 1), **options)
            for i in ids}
        self.ids = tuple(self.emulators)
        #: (q [rad], q_dot [rad/s]) of each motor's joint.
        self.joints: Dict[int, Tuple[float, float]] = dict.fromkeys(self.ids, (0.0, 0.0))
        self.silent = set()

    def motor(self, motor_id: int) -> EmulatedMotor:
        """Return the emulator of motor ``motor_id`` (KeyError if none)."""
        return self.emulators[motor_id]

    def handle(self, frame: Frame, now: float) -> List[Frame]:
        """Act on a frame as the motors do; return their replies ([] if none is sent)."""
        out = []
        for motor_id, e in self.emulators.items():
            q, q_dot = self.joints[motor_id]
            reply = e.handle(frame, q, q_dot, now)
            if reply is not None and motor_id not in self.silent:
                out.append(reply)
        return out

    def torque(self, motor_id: int, now: float) -> float:
        """Return the joint torque [N m] motor ``motor_id`` applies at time ``now`` [s]."""
        q, q_dot = self.joints[motor_id]
        return self.emulators[motor_id].torque(q, q_dot, now)
