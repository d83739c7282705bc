"""
DJI RoboMaster C620 speed controller (ESC) with the M3508 P19 gear motor: current commands.

Layouts and sources: docs/can_protocols.md. In short (RoboMaster C620 Brushless DC Motor Speed
Controller User Guide, "CAN communication protocol"):

- command, host -> ESC: standard ID 0x200 carries ESC IDs 1-4, ID 0x1FF ESC IDs 5-8; 8 bytes,
  four big-endian int16 currents, ESC ID 1 (or 5) first; -16384..16384 <-> -20..20 A;
- feedback, ESC -> host, ID 0x200 + ESC ID, 8 bytes: rotor angle uint16 0..8191 (one rotor
  turn), rotor speed int16 [rpm], torque current int16 (same scale as the command),
  motor temperature uint8 [deg C], one unused byte.

Torque <-> current through the M3508 P19's torque constant 0.3 N m/A at the output shaft
(DJI M3508 P19 specifications; the gearbox ratio is 3591/187 ~ 19.2). So 20 A is 6 N m.
The ESC has no enable: enable_frames is empty and disable_frames commands zero current.
``decode_command`` and ``encode_feedback`` are the ESC's side (sim/motor_emulator.py).
"""
import math
import struct
from typing import Dict, Iterable, List, Optional, Tuple

from .base import Frame, frame_bytes, MotorFeedback, MotorProtocol, ReplyCodes
from .emulation import EmulatedMotor, torque_only

#: Command IDs: ESC IDs 1-4 and 5-8.
COMMAND_ID_1_4 = 0x200
COMMAND_ID_5_8 = 0x1FF
#: Feedback ID of ESC i is FEEDBACK_BASE_ID + i.
FEEDBACK_BASE_ID = 0x200
#: Full-scale command / feedback code and the current it stands for [A].
CURRENT_CODE_MAX = 16384
CURRENT_MAX = 20.0
#: M3508 P19 figures at the output shaft.
M3508_TORQUE_CONSTANT = 0.3        # [N m/A]
M3508_GEAR_RATIO = 3591.0 / 187.0  # rotor turns per output turn
ENCODER_COUNTS = 8192              # rotor angle 0..8191

_FOUR_INT16 = struct.Struct('>4h')
_FEEDBACK = struct.Struct('>HhhBx')


class DjiC620Protocol(MotorProtocol):
    """
    C620 current-command codec; motor IDs are the ESC IDs 1..8 (other IDs are ignored).

    torque_constant [N m/A] and gear_ratio describe the motor (defaults: M3508 P19);
    current_limit [A] <= 20 caps the commanded current.
    """

    name = 'dji_c620'
    config_section = 'dji'

    def __init__(self, torque_constant: float = M3508_TORQUE_CONSTANT,
                 gear_ratio: float = M3508_GEAR_RATIO, current_limit: float = CURRENT_MAX):
        if not (torque_constant > 0.0 and gear_ratio > 0.0 and 0.0 < current_limit <= 20.0):
            raise ValueError('invalid C620 parameters')
        self.torque_constant = float(torque_constant)
        self.gear_ratio = float(gear_ratio)
        self.current_limit = float(current_limit)
        self._code_per_nm = CURRENT_CODE_MAX / CURRENT_MAX / self.torque_constant
        self._code_limit = int(self.current_limit * CURRENT_CODE_MAX / CURRENT_MAX)

    @classmethod
    def from_config(cls, section) -> 'DjiC620Protocol':
        """Build the codec from a core/motor_config.py DjiConfig section."""
        if section is None:
            return cls()
        return cls(torque_constant=section.torque_constant, gear_ratio=section.gear_ratio,
                   current_limit=section.current_limit)

    @property
    def position_span(self) -> float:
        """Return the span [rad] of the feedback's position: one rotor turn at the output."""
        return 2.0 * math.pi / self.gear_ratio

    @property
    def torque_limit(self) -> float:
        """Return the largest torque [N m] a command can ask for (current_limit)."""
        return self._code_limit * CURRENT_MAX / CURRENT_CODE_MAX * self.torque_constant

    @property
    def speed_range(self) -> float:
        """Return the largest speed [rad/s] the feedback's int16 rpm field holds."""
        return 32767 * 2.0 * math.pi / 60.0 / self.gear_ratio

    def reply_codes(self) -> ReplyCodes:
        """Return the rotor angle from 0, wrapping each rotor turn, and 1 rpm speed codes."""
        return ReplyCodes(0.0, self.position_span / ENCODER_COUNTS, ENCODER_COUNTS, False,
                          2.0 * math.pi / 60.0 / self.gear_ratio, False)

    def id_problems(self, motor_ids: Iterable[int]) -> List[str]:
        """Return the IDs outside the ESC IDs 1..8."""
        return ['dji_c620: ESC ID %d outside 1..8' % i for i in motor_ids if not 1 <= i <= 8]

    def current_code(self, torque: float) -> int:
        """Command code for a motor torque [N m]: rounded, clamped, 0 for NaN/inf."""
        if not -math.inf < torque < math.inf:  # NaN fails both comparisons
            return 0
        code = torque * self._code_per_nm  # may overflow to inf: clamp before rounding
        limit = self._code_limit
        return limit if code >= limit else -limit if code <= -limit else round(code)

    def torque_frames(self, torques: Dict[int, float]) -> List[Frame]:
        """One frame per ID group (0x200 / 0x1FF) in use; ESCs not in ``torques`` get 0 A."""
        low = high = None
        for motor_id, tau in torques.items():
            if 1 <= motor_id <= 4:
                low = low or [0, 0, 0, 0]
                low[motor_id - 1] = self.current_code(tau)
            elif 5 <= motor_id <= 8:
                high = high or [0, 0, 0, 0]
                high[motor_id - 5] = self.current_code(tau)
        frames = []
        if low is not None:
            frames.append(Frame(COMMAND_ID_1_4, _FOUR_INT16.pack(*low)))
        if high is not None:
            frames.append(Frame(COMMAND_ID_5_8, _FOUR_INT16.pack(*high)))
        return frames

    def zero_torque_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Zero current to the ESCs (frames for their ID groups)."""
        return self.torque_frames(dict.fromkeys(motor_ids, 0.0))

    def enable_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Return no frames: the C620 has no motor mode."""
        return []

    def disable_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Zero current (the C620 has no motor mode to leave)."""
        return self.zero_torque_frames(motor_ids)

    def decode_feedback(self, frame: Frame) -> Optional[MotorFeedback]:
        """
        Decode an ESC's feedback frame (ID 0x201..0x208, 8 bytes); None for anything else.

        position: the rotor's single-turn angle referred to the output, angle 2 pi / 8192 /
        gear_ratio [rad] -- it wraps every 1/gear_ratio output turn, so it is not a wheel
        angle; velocity: rotor rpm 2 pi / 60 / gear_ratio [rad/s]; torque: torque current
        times the torque constant [N m]; temperature [deg C].
        """
        data = frame_bytes(frame)
        if data is None or len(data) != 8:
            return None
        motor_id = frame.arbitration_id - FEEDBACK_BASE_ID
        if not 1 <= motor_id <= 8:
            return None
        angle, rpm, current, temperature = _FEEDBACK.unpack(data)
        if angle >= ENCODER_COUNTS:
            return None
        return MotorFeedback(
            motor_id,
            angle * (2.0 * math.pi / ENCODER_COUNTS) / self.gear_ratio,
            rpm * (2.0 * math.pi / 60.0) / self.gear_ratio,
            current * (CURRENT_MAX / CURRENT_CODE_MAX) * self.torque_constant,
            float(temperature))

    def command_motor_ids(self, frame: Frame) -> Tuple[int, ...]:
        """
        Return the four ESC IDs a 0x200 / 0x1FF command carries (1-4 or 5-8), else ().

        Every ESC of the group takes its slot from any such frame, whoever sent it: a frame
        for other ESCs of the group sets ours too. Feedback (0x201..0x208) is no command.
        """
        codes = self.decode_command(frame)
        return () if codes is None else tuple(codes)

    # ---- ESC side (emulated ESCs) ----------------------------------------------------------

    def decode_command(self, frame: Frame) -> Optional[Dict[int, int]]:
        """
        Decode a current command as the ESCs do: {ESC ID: current code}; None if not one.

        A 0x200 frame carries ESCs 1-4, a 0x1FF frame ESCs 5-8 (8 bytes, standard ID).
        """
        data = frame_bytes(frame)
        if data is None or len(data) != 8:
            return None
        first = {COMMAND_ID_1_4: 1, COMMAND_ID_5_8: 5}.get(frame.arbitration_id)
        if first is None:
            return None
        return dict(zip(range(first, first + 4), _FOUR_INT16.unpack(data)))

    def encode_feedback(self, esc_id: int, angle_code: int, rpm: int, current_code: int,
                        temperature: int) -> Frame:
        """
        Encode ESC ``esc_id``'s feedback frame on 0x200 + esc_id from raw field values.

        angle_code: rotor angle 0..8191 (wrapped); rpm: rotor speed; current_code: torque
        current in command codes; temperature [deg C]; each clamped into its field.
        """
        fields = (angle_code % ENCODER_COUNTS, _clamp(rpm, -32768, 32767),
                  _clamp(current_code, -32768, 32767), _clamp(temperature, 0, 255))
        return Frame(FEEDBACK_BASE_ID + esc_id, _FEEDBACK.pack(*fields))

    def encode_state(self, esc_id: int, position: float, velocity: float, current_code: int,
                     temperature: int) -> Frame:
        """Encode the feedback of an output at position [rad] and speed [rad/s] (rounded)."""
        ratio = self.gear_ratio
        position, velocity = (x if math.isfinite(x) else 0.0 for x in (position, velocity))
        return self.encode_feedback(esc_id,
                                    round(position * ratio * ENCODER_COUNTS / (2.0 * math.pi)),
                                    round(velocity * ratio * 60.0 / (2.0 * math.pi)),
                                    current_code, temperature)

    def make_emulator(self, motor_id: int, **options) -> 'C620MotorEmulator':
        """Return one emulated C620 with its M3508 (C620MotorEmulator's options)."""
        return C620MotorEmulator(motor_id, self, **options)


class C620MotorEmulator(EmulatedMotor):
    """
    One C620 ESC with its M3508 P19: takes current from power-up (the ESC has no motor mode).

    Each group frame (0x200 / 0x1FF) that carries its ESC ID sets its current and is answered
    with its feedback (the real ESC sends feedback at 1 kHz on its own; one per command is
    what a host ticking at 500 Hz sees of it). The torque current reported is the commanded
    one (the ESC's current loop settled within a tick). The user guide documents no command
    timeout (command_timeout 0 by default: the ESC keeps the last current). The rotor encoder
    is single-turn: a reboot leaves the reading within one rotor turn, as it was.
    """

    def __init__(self, motor_id: int, protocol: Optional[DjiC620Protocol] = None,
                 torque_limit: Optional[float] = None, **options):
        self.protocol = protocol if protocol is not None else DjiC620Protocol()
        options.setdefault('gear_ratio', self.protocol.gear_ratio)
        super().__init__(motor_id, self.protocol.torque_limit if torque_limit is None
                         else torque_limit, powered_enabled=True, **options)

    def handle(self, frame: Frame, q: float, q_dot: float, now: float) -> Optional[Frame]:
        """Act on a group frame carrying this ESC as it does; return its feedback or None."""
        p = self.protocol
        codes = p.decode_command(frame)
        if codes is None or self.motor_id not in codes:
            return None
        code = codes[self.motor_id]
        self.frames += 1
        self.last_decoded = code
        amps_per_code = CURRENT_MAX / CURRENT_CODE_MAX
        self.set_command(torque_only(code * amps_per_code * p.torque_constant), now)
        self.torque(q, q_dot, now)
        current = round(self.motor_torque / p.torque_constant / amps_per_code)
        return p.encode_state(self.own_reply_id, self.position(q), self.velocity(q_dot), current,
                              int(self.temperature))


def _clamp(x: int, lo: int, hi: int) -> int:
    return min(max(int(x), lo), hi)
