"""
LingKong (LK-TECH) MF/MG series on CAN: torque closed-loop commands (``can.protocol: lk``).

Layouts and sources: docs/can_protocols.md. In short (LK-TECH, *MS MF MG motor CAN protocol*
V2.35, sec. 1 "CAN bus parameters and single motor commands"):

- 1 Mbit/s, standard frames, DLC 8; command and reply on ID 0x140 + motor ID (1..32);
- torque closed loop (0xA1): ``A1 00 00 00 iq_lo iq_hi 00 00``, iqControl int16 little-endian,
  -2048..2048 for -16.5..16.5 A (MF) or -33..33 A (MG);
- its reply, and the reply of the state-2 read (0x9C): ``cmd temperature iq_lo iq_hi speed_lo
  speed_hi encoder_lo encoder_hi``: int8 [deg C], int16 iq (same scale), int16 [deg/s], uint16
  single-turn encoder (14, 15 or 16 bits by model);
- motor off (0x80: output off, command and running state cleared), stop (0x81: output off,
  command kept), run (0x88: resume after a stop): the motor echoes the frame;
- state-1 and error read (0x9A) and error clear (0x9B), replied as ``cmd temperature 00
  voltage_lo voltage_hi 00 00 errorState``: uint16 voltage, 0.1 V/LSB; errorState bit 0
  under-voltage, bit 3 over-temperature.

Torque <-> current: the model's torque constant at the output (config ``can.lk``; the
MF9025 with 16 turns: 0.32 N m/A). The encoder is single-turn: the position is known modulo
one rotor turn (2 pi / gear_ratio at the output) and the host unwraps it
(``MotorProtocol.position_step``); after a reboot it reads the same, so the position is not
lost by a reboot, only by a silence long enough to turn half a rotor turn.
The torque reply carries no error bits: the tick asks one motor at a time with 0x9A every
HEALTH_INTERVAL (``health_frames``, ``decode_health``), so a motor that switched its output
off on a latched error is seen within 2 HEALTH_INTERVAL and two ticks (docs/faults.md).
``decode_command`` / ``encode_reply`` and ``LkMotorEmulator`` are the motor's side.
"""
from dataclasses import dataclass
import math
import struct
from typing import Dict, Iterable, List, NamedTuple, Optional, Tuple, Union

from .base import Frame, frame_bytes, MotorFeedback, MotorHealth, MotorProtocol, ReplyCodes
from .emulation import EmulatedMotor, torque_only
from ..schema import param

#: Command and reply ID of motor i: BASE_ID + i, i in 1..MAX_MOTOR_ID.
BASE_ID = 0x140
MAX_MOTOR_ID = 32
#: Command bytes (V2.35).
TORQUE = 0xA1
MOTOR_OFF, MOTOR_STOP, MOTOR_RUN = 0x80, 0x81, 0x88
READ_STATE1, CLEAR_ERROR, READ_STATE2 = 0x9A, 0x9B, 0x9C
#: Closed-loop commands whose reply is the state-2 layout (temperature, iq, speed, encoder).
STATE2_REPLIES = frozenset((TORQUE, 0xA2, 0xA3, 0xA4, 0xA5, 0xA6, 0xA7, 0xA8, READ_STATE2))
#: Full-scale iq code and the current it stands for on MF and MG motors [A].
IQ_CODE_MAX = 2048
MF_CURRENT_MAX = 16.5
MG_CURRENT_MAX = 33.0
#: errorState bits of the state-1 reply: bit 0 and bit 3 as open RoboMaster drivers name them
#: (an LkMotorErr_e enum: 0x01 low voltage, 0x08 motor temperature); V2.35's table itself was
#: not in the stored excerpt (docs/can_protocols.md). Other bits are reported by number.
ERROR_BITS = {0x01: 'under-voltage', 0x08: 'over-temperature'}
#: Words of the commands without data (decode_command).
_SIMPLE = {MOTOR_OFF: 'off', MOTOR_STOP: 'stop', MOTOR_RUN: 'run', READ_STATE1: 'read_state1',
           CLEAR_ERROR: 'clear_error', READ_STATE2: 'read_state2'}
#: Time [s] between two 0x9A queries, one wheel each: with two wheels each motor is asked every
#: 20 ms, for 2 x 135 bit times (query and reply, worst-case stuffing) per 10 ms: 2.7 % of the
#: 1 Mbit/s bus, one frame more on one tick in five of a 2 ms loop.
HEALTH_INTERVAL = 0.01
_STATE2 = struct.Struct('<BbhhH')
_STATE1 = struct.Struct('<BbxHxxB')


@dataclass(frozen=True)
class LkConfig:
    """An LK MF/MG motor model's figures (core/protocols/lk.py)."""

    current_max: float = param(MF_CURRENT_MAX, 'lk: torque current at iq code 2048 [A] (MF '
                               'series 16.5, MG series 33)', 0.1, 100.0, read_only=True)
    torque_constant: float = param(0.32, 'lk: output torque per ampere of iq [N m/A] (MF9025 '
                                   'with 16 turns: 0.32)', 0.001, 100.0, read_only=True)
    current_limit: float = param(MF_CURRENT_MAX, 'lk: largest torque current commanded [A] '
                                 '(at most current_max)', 0.1, 100.0, read_only=True)
    encoder_bits: int = param(16, "lk: the model's single-turn encoder width [bit] (14, 15 or "
                              '16)', 14, 16, read_only=True)
    gear_ratio: float = param(1.0, 'lk: rotor turns per output turn (MF: 1, MG: its gearbox)',
                              0.01, 1000.0, read_only=True)
    temp_derate: float = param(70.0, 'lk: motor temperature from which the torque limit falls '
                               'linearly, to half at temp_max [deg C]', -40.0, 200.0,
                               read_only=True)
    temp_max: float = param(85.0, 'lk: motor temperature at which balancing ends [deg C]',
                            -40.0, 200.0, read_only=True)

    def codec_kwargs(self) -> dict:
        """Keyword arguments of LkProtocol for this model."""
        return {'current_max': self.current_max, 'torque_constant': self.torque_constant,
                'current_limit': self.current_limit, 'encoder_bits': self.encoder_bits,
                'gear_ratio': self.gear_ratio}


class LkStatus(NamedTuple):
    """A state-1 (0x9A) or error-clear (0x9B) reply: temperature [deg C], voltage [V], bits."""

    motor_id: int
    temperature: float
    voltage: float
    error: int


class LkProtocol(MotorProtocol):
    """
    LK torque closed-loop codec; motor IDs 1..32.

    current_max [A]: the current of iq code 2048 (MF 16.5, MG 33); torque_constant [N m/A] at
    the output; current_limit [A] <= current_max caps the command; encoder_bits: 14..16;
    gear_ratio: rotor turns per output turn (encoder and speed are the rotor's).
    """

    name = 'lk'
    config_section = 'lk'
    config = LkConfig
    health_interval = HEALTH_INTERVAL

    def __init__(self, current_max: float = MF_CURRENT_MAX, torque_constant: float = 0.32,
                 current_limit: Optional[float] = None, encoder_bits: int = 16,
                 gear_ratio: float = 1.0):
        current_limit = current_max if current_limit is None else current_limit
        if not (0.0 < current_max < math.inf and 0.0 < torque_constant < math.inf
                and 0.0 < current_limit <= current_max and 14 <= encoder_bits <= 16
                and 0.0 < gear_ratio < math.inf):
            raise ValueError('invalid LK parameters')
        self.current_max = float(current_max)
        self.torque_constant = float(torque_constant)
        self.current_limit = float(current_limit)
        self.encoder_counts = 1 << int(encoder_bits)
        self.gear_ratio = float(gear_ratio)
        self.position_span = 2.0 * math.pi / self.gear_ratio
        self._code_per_nm = IQ_CODE_MAX / self.current_max / self.torque_constant
        self._code_limit = int(self.current_limit * IQ_CODE_MAX / self.current_max)
        self._nm_per_code = 1.0 / self._code_per_nm

    @property
    def speed_range(self) -> float:
        """Return the largest output speed [rad/s] the reply's int16 deg/s field holds."""
        return math.radians(32767) / self.gear_ratio

    @property
    def torque_limit(self) -> float:
        """Return the largest torque [N m] a command asks for (current_limit)."""
        return self._code_limit * self._nm_per_code

    def reply_codes(self) -> ReplyCodes:
        """Return the single-turn encoder from 0, wrapping each turn, and 1 deg/s codes."""
        return ReplyCodes(0.0, self.position_span / self.encoder_counts, self.encoder_counts,
                          False, math.radians(1.0) / self.gear_ratio, False)

    def id_problems(self, motor_ids: Iterable[int]) -> List[str]:
        """Return the IDs outside 1..32 (ID 0x140 + ID)."""
        return ['lk: motor ID %d outside 1..%d' % (i, MAX_MOTOR_ID) for i in motor_ids
                if not 1 <= i <= MAX_MOTOR_ID]

    # ---- host side -------------------------------------------------------------------------

    def current_code(self, torque: float) -> int:
        """Return the iq code for a motor torque [N m]: rounded, clamped, 0 for NaN/inf."""
        if not -math.inf < torque < math.inf:  # NaN fails both comparisons
            return 0
        code = torque * self._code_per_nm
        limit = self._code_limit
        return limit if code >= limit else -limit if code <= -limit else round(code)

    def torque_frames(self, torques: Dict[int, float]) -> List[Frame]:
        """One 0xA1 torque command per motor (IDs outside 1..32 are skipped)."""
        frames = []
        for motor_id, tau in torques.items():
            if 1 <= motor_id <= MAX_MOTOR_ID:
                code = self.current_code(tau) & 0xFFFF
                frames.append(Frame(BASE_ID + motor_id,
                                    bytes((TORQUE, 0, 0, 0, code & 0xFF, code >> 8, 0, 0))))
        return frames

    def zero_torque_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Torque commands of 0 A (code 0 is exactly zero)."""
        return self.torque_frames(dict.fromkeys(motor_ids, 0.0))

    def enable_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Motor run (0x88): resumes a stopped motor; a powered motor takes commands anyway."""
        return self._simple(motor_ids, MOTOR_RUN)

    def disable_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Zero torque, then motor off (0x80: output off, command and running state cleared)."""
        ids = list(motor_ids)
        return self.zero_torque_frames(ids) + self._simple(ids, MOTOR_OFF)

    def clear_error_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Clear the error flags (0x9B); the motor clears only causes that have gone."""
        return self._simple(motor_ids, CLEAR_ERROR)

    def status_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Read state 1 and the error flags (0x9A); the reply is decode_status's."""
        return self._simple(motor_ids, READ_STATE1)

    def health_frames(self, motor_id: int) -> List[Frame]:
        """Return the state-1 read (0x9A) to one motor: its reply has the errorState bits."""
        return self.status_frames((motor_id,))

    def decode_health(self, frame: Frame) -> Optional[MotorHealth]:
        """Return a state-1 (0x9A) or error-clear (0x9B) reply's temperature and errorState."""
        status = self.decode_status(frame)
        return None if status is None else MotorHealth(status.motor_id, status.temperature,
                                                       status.error)

    def _simple(self, motor_ids: Iterable[int], command: int) -> List[Frame]:
        return [Frame(BASE_ID + i, bytes((command,) + (0,) * 7)) for i in motor_ids
                if 1 <= i <= MAX_MOTOR_ID]

    def decode_feedback(self, frame: Frame) -> Optional[MotorFeedback]:
        """
        Decode a state-2 layout reply (0xA1..0xA8, 0x9C) on 0x141..0x160; None for anything else.

        position: the single-turn encoder at the output [rad] in [0, 2 pi / gear_ratio);
        velocity [rad/s]; torque: iq times the torque constant [N m]; temperature [deg C].
        The reply has no error bits (decode_status has them).
        """
        data = frame_bytes(frame)
        motor_id = frame.arbitration_id - BASE_ID if data is not None else 0
        if not (1 <= motor_id <= MAX_MOTOR_ID and len(data) == 8
                and data[0] in STATE2_REPLIES and not self._is_command(data)):
            return None
        _, temperature, iq, dps, encoder = _STATE2.unpack(data)
        if encoder >= self.encoder_counts:
            return None
        g = self.gear_ratio
        return MotorFeedback(motor_id, encoder * (2.0 * math.pi / self.encoder_counts) / g,
                             math.radians(dps) / g, iq * self._nm_per_code, float(temperature))

    def decode_status(self, frame: Frame) -> Optional[LkStatus]:
        """Decode a state-1 (0x9A) or error-clear (0x9B) reply; None for anything else."""
        data = frame_bytes(frame)
        motor_id = frame.arbitration_id - BASE_ID if data is not None else 0
        if not (1 <= motor_id <= MAX_MOTOR_ID and len(data) == 8
                and data[0] in (READ_STATE1, CLEAR_ERROR) and any(data[1:])):
            return None
        _, temperature, voltage, bits = _STATE1.unpack(data)
        return LkStatus(motor_id, float(temperature), voltage * 0.1, bits)

    def error_reason(self, code: int) -> str:
        """Return the errorState bits in words."""
        code = int(code)
        words = [ERROR_BITS.get(1 << k, 'error bit %d' % k) for k in range(8) if code >> k & 1]
        return ', '.join(words) or 'no error'

    def command_motor_ids(self, frame: Frame) -> Tuple[int, ...]:
        """
        Return (motor ID,) for a closed-loop command to 0x141..0x160, else ().

        A command and its reply share the ID and the first byte: a closed-loop command has
        bytes 1-3 zero (0xA1 also bytes 6-7), where the reply carries the temperature and iq,
        so a reply at exactly 0 deg C, 0 A (and encoder 0 for 0xA1) reads as a command, and
        commands with data in bytes 1-3 (0xA4, 0xA6, 0xA8) are not seen. Off, stop and run are
        echoed by the motor byte for byte, so they cannot count: another sender's stop is not
        seen either (it stops the motor: the safe direction).
        """
        data = frame_bytes(frame)
        motor_id = frame.arbitration_id - BASE_ID if data is not None else 0
        if 1 <= motor_id <= MAX_MOTOR_ID and len(data) == 8 and self._is_command(data):
            return (motor_id,)
        return ()

    @staticmethod
    def _is_command(data: bytes) -> bool:
        if data[0] not in STATE2_REPLIES or data[0] == READ_STATE2 or any(data[1:4]):
            return False
        return data[0] != TORQUE or not any(data[6:8])

    # ---- motor side (emulator) -------------------------------------------------------------

    def decode_command(self, frame: Frame) -> Union[int, str, None]:
        """
        Decode a frame as motor (ID - 0x140) does: an iq code, or a command's word.

        The iq code of a torque command, or 'off', 'stop', 'run', 'read_state1',
        'clear_error', 'read_state2'; None for anything else.
        """
        data = frame_bytes(frame)
        if data is None or len(data) != 8 or not 1 <= frame.arbitration_id - BASE_ID \
                <= MAX_MOTOR_ID:
            return None
        if data[0] == TORQUE and self._is_command(data):
            return max(-IQ_CODE_MAX, min(IQ_CODE_MAX, struct.unpack_from('<h', data, 4)[0]))
        if data[0] in _SIMPLE and not any(data[1:]):
            return _SIMPLE[data[0]]
        return None

    def encode_reply(self, motor_id: int, command: int, temperature: float, iq_code: int,
                     speed_dps: float, encoder: int) -> Frame:
        """Encode a state-2 layout reply to ``command``: fields clamped (speed saturates)."""
        return Frame(BASE_ID + motor_id, _STATE2.pack(
            command, _clamp(temperature, -128, 127), _clamp(iq_code, -IQ_CODE_MAX, IQ_CODE_MAX),
            _clamp(speed_dps, -32768, 32767), int(encoder) % self.encoder_counts))

    def encode_status(self, motor_id: int, command: int, temperature: float, voltage: float,
                      error: int) -> Frame:
        """Encode a state-1 layout reply (0x9A, 0x9B): voltage [V] at 0.1 V/LSB."""
        return Frame(BASE_ID + motor_id, _STATE1.pack(
            command, _clamp(temperature, -128, 127), _clamp(voltage * 10.0, 0, 65535),
            int(error) & 0xFF))

    def make_emulator(self, motor_id: int, **options) -> 'LkMotorEmulator':
        """Return an emulated LK motor with this codec (LkMotorEmulator's options)."""
        return LkMotorEmulator(motor_id, self, **options)


def _clamp(x: float, lo: int, hi: int) -> int:
    x = round(x) if math.isfinite(x) else 0
    return lo if x < lo else hi if x > hi else x


class LkMotorEmulator(EmulatedMotor):
    """
    One LK motor: takes torque commands from power-up, answers every frame it acts on.

    As V2.35 describes: a torque command is applied and answered with temperature, iq, speed
    and encoder; off (0x80) drops the command and is echoed; stop (0x81) keeps the command
    but gives no torque until run (0x88); a torque command after off is applied (off clears
    the state, it does not lock the motor). The state-1 read and the error clear answer with
    temperature, voltage and the error bits (set_error: ERROR_BITS); a latched error keeps
    the output off. V2.35 documents no command timeout (command_timeout: 0 by default).
    The encoder is single-turn and absolute: a reboot leaves the reading as it was.
    """

    def __init__(self, motor_id: int, protocol: Optional[LkProtocol] = None,
                 torque_limit: Optional[float] = None, voltage: float = 24.0, **options):
        self.protocol = protocol if protocol is not None else LkProtocol()
        limit = self.protocol.torque_limit if torque_limit is None else torque_limit
        options.setdefault('gear_ratio', self.protocol.gear_ratio)
        super().__init__(motor_id, limit, powered_enabled=True, **options)
        self.voltage = float(voltage)
        self.stopped = False

    def handle(self, frame: Frame, q: float, q_dot: float, now: float) -> Optional[Frame]:
        """Act on a frame to 0x140 + motor_id as the motor does; return its reply or None."""
        if frame.arbitration_id != BASE_ID + self.motor_id:
            return None
        p = self.protocol
        decoded = p.decode_command(frame)
        if decoded is None:
            return None
        self.frames += 1
        self.last_decoded = decoded
        if isinstance(decoded, int):
            self.set_command(torque_only(decoded * p._nm_per_code), now)
            self.enabled = not self.stopped
        elif decoded == 'off':
            self.set_command(None, now)
            self.stopped = self.enabled = False
        elif decoded == 'stop':
            self.stopped, self.enabled = True, False
        elif decoded == 'run':
            self.stopped, self.enabled = False, True
        elif decoded == 'clear_error':
            self.error = 0
        self.torque(q, q_dot, now)
        rid = self.own_reply_id
        if decoded in ('off', 'stop', 'run'):
            return Frame(BASE_ID + rid, frame_bytes(frame))   # echoed
        if decoded in ('read_state1', 'clear_error'):
            return p.encode_status(rid, frame_bytes(frame)[0], self.temperature, self.voltage,
                                   self.error)
        g = self.gear_ratio
        rotor = self.position(q) * g
        encoder = math.floor(rotor / (2.0 * math.pi) * p.encoder_counts) \
            if math.isfinite(rotor) else 0
        speed = math.degrees(self.velocity(q_dot) * g) if math.isfinite(q_dot) else 0.0
        return p.encode_reply(rid, TORQUE if isinstance(decoded, int) else READ_STATE2,
                              self.temperature, p.current_code(self.motor_torque), speed,
                              encoder)
