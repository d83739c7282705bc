"""
Xiaomi CyberGear micromotor and RobStride on CAN: operation control mode (``cybergear``).

Layouts and sources: docs/can_protocols.md. In short (Xiaomi, *CyberGear micromotor
instruction manual*, ch. 4 "Driver communication protocol", English translation in
belovictor/cybergear-docs, instructionmanual/instructionmanual.md at 17e371b8):

- 1 Mbit/s, extended 29-bit IDs: communication type in bits 28-24, a 16-bit data area in
  bits 23-8, the target address in bits 7-0; 8 data bytes;
- type 1, operation control (host -> motor): torque in the ID's data area, angle, speed, kp,
  kd as big-endian uint16 in the data; each ``float_to_uint(x, lo, hi, 16)`` over the ranges
  angle +-4 pi rad, speed +-30 rad/s, kp 0..500, kd 0..5, torque +-12 N m (sec. 4.1.2, 4.2.1);
- type 2, feedback (motor -> host, target = host ID): motor ID in bits 15-8, fault bits 16-21
  (under-voltage, over-current, over-temperature, magnetic encoder, HALL encoder, not
  calibrated), mode in bits 22-23 (0 reset, 1 calibration, 2 run); data: angle, speed, torque
  (same ranges), temperature x 10, big-endian uint16 (sec. 4.1.3);
- type 3 enable, type 4 stop (byte 0 = 1 also clears the fault), type 6 set the mechanical zero
  (lost at power-off), each with the host ID in bits 15-8; answered by a type 2 (4.1.4-4.1.6);
- type 17 / 18 read / write one parameter: index little-endian in bytes 0-1, value in bytes
  4-7 (float32 little-endian, or uint8 in byte 4); run_mode 0x7005 (0: operation control,
  the power-up default), limit_torque 0x700B, limit_spd 0x7017, limit_cur 0x7018 (4.1.8-4.1.12).

The reply's angle is taken to saturate at +-p_max (the manual's float_to_uint clamps); the
host treats a reading at an end as unknown (``at_position_end``). RobStride motors speak the
same frames with their own ranges (config ``cybergear.*``).
"""
from dataclasses import dataclass
import math
import struct
from typing import Dict, Iterable, List, Optional, Tuple

from .base import Frame, frame_bytes, MotorFeedback, MotorProtocol, ReplyCodes
from .emulation import Command, EmulatedMotor, rotor_turn_position
from ..schema import param

#: Communication types (manual sec. 4.1).
OPERATION_CONTROL, FEEDBACK, ENABLE, STOP, SET_ZERO = 1, 2, 3, 4, 6
SET_CAN_ID, PARAM_READ, PARAM_WRITE, FAULT, SET_BAUD = 7, 17, 18, 21, 22
#: Types a motor acts on (commands of another sender), beside the operation control.
_ACTING = frozenset((OPERATION_CONTROL, ENABLE, STOP, SET_ZERO, SET_CAN_ID, PARAM_WRITE,
                     SET_BAUD))
#: Parameters (sec. 4.1.12): index -> struct format of the value.
RUN_MODE, IQ_REF, SPD_REF, LIMIT_TORQUE = 0x7005, 0x7006, 0x700A, 0x700B
LIMIT_SPD, LIMIT_CUR, MECH_POS, MECH_VEL = 0x7017, 0x7018, 0x7019, 0x701B
PARAMS = {RUN_MODE: '<B', IQ_REF: '<f', SPD_REF: '<f', LIMIT_TORQUE: '<f', LIMIT_SPD: '<f',
          LIMIT_CUR: '<f', MECH_POS: '<f', MECH_VEL: '<f'}
RUN_MODES = {0: 'operation control', 1: 'position', 2: 'speed', 3: 'current'}
#: Modes in the feedback's bits 22-23.
MODE_RESET, MODE_CALIBRATION, MODE_RUN = 0, 1, 2
#: Fault bits 16-21 of the feedback ID, as bits 0-5 of MotorFeedback.error.
FAULT_BITS = ('under-voltage', 'over-current', 'over-temperature', 'magnetic encoder fault',
              'HALL encoder fault', 'not calibrated')
_U16X4 = struct.Struct('>4H')


@dataclass(frozen=True)
class CybergearConfig:
    """A CyberGear / RobStride model's ranges (core/protocols/cybergear.py)."""

    p_max: float = param(4.0 * math.pi, 'cybergear: angle range +-p_max [rad] (CyberGear: '
                         '4 pi)', 0.1, 1000.0, read_only=True)
    v_max: float = param(30.0, 'cybergear: speed range +-v_max [rad/s] (CyberGear: 30)', 0.1,
                         1000.0, read_only=True)
    t_max: float = param(12.0, 'cybergear: torque range +-t_max [N m] (CyberGear: 12)', 0.1,
                         1000.0, read_only=True)
    kp_max: float = param(500.0, 'cybergear: kp range 0..kp_max [N m/rad]', 0.1, 10000.0,
                          read_only=True)
    kd_max: float = param(5.0, 'cybergear: kd range 0..kd_max [N m s/rad]', 0.01, 1000.0,
                          read_only=True)
    host_id: int = param(0, "cybergear: the host's CAN ID, the motors' CAN_MASTER (default "
                         '0)', 0, 255, read_only=True)
    gear_ratio: float = param(7.75, 'cybergear: rotor turns per output turn (CyberGear: '
                              '7.75)', 0.01, 1000.0, read_only=True)
    temp_derate: float = param(70.0, 'cybergear: motor temperature from which the torque limit '
                               'falls linearly, to half at temp_max [deg C]', -40.0, 200.0,
                               read_only=True)
    temp_max: float = param(75.0, 'cybergear: motor temperature at which balancing ends [deg '
                            'C] (the firmware warns at 75 and stops at 80)', -40.0, 200.0,
                            read_only=True)

    position_jump: float = param(0.3, 'cybergear: a reply position this far off the extrapolation '
                                 'of the previous reply is a reboot: fault [rad]', 0.01, 10.0,
                                 read_only=True)

    def codec_kwargs(self) -> dict:
        """Keyword arguments of CybergearProtocol for this model."""
        return {'p_max': self.p_max, 'v_max': self.v_max, 't_max': self.t_max,
                'kp_max': self.kp_max, 'kd_max': self.kd_max, 'host_id': self.host_id,
                'gear_ratio': self.gear_ratio}


def to_u16(x: float, lo: float, hi: float) -> int:
    """Return the manual's float_to_uint(x, lo, hi, 16): clamped, truncated; NaN/inf as 0."""
    if not -math.inf < x < math.inf:
        x = 0.0
    x = hi if x > hi else lo if x < lo else x
    return int((x - lo) * 65535 / (hi - lo))


def from_u16(u: int, lo: float, hi: float) -> float:
    """Return the value a 16-bit code stands for (uint_to_float)."""
    return u * (hi - lo) / 65535 + lo


def ext_id(kind: int, data: int, target: int) -> int:
    """Return the 29-bit ID: type in bits 28-24, data in 23-8, target in 7-0."""
    return (kind & 0x1F) << 24 | (data & 0xFFFF) << 8 | (target & 0xFF)


def split_id(arbitration_id: int) -> Tuple[int, int, int]:
    """Return (type, data, target) of a 29-bit ID."""
    return arbitration_id >> 24 & 0x1F, arbitration_id >> 8 & 0xFFFF, arbitration_id & 0xFF


class CybergearProtocol(MotorProtocol):
    """
    Operation-control codec with a model's ranges (defaults: CyberGear); motor IDs 1..127.

    p_max [rad], v_max [rad/s], t_max [N m], kp_max, kd_max: the symmetric ranges the motor's
    firmware maps 16-bit codes to; host_id: the host's ID (CAN_MASTER); gear_ratio: rotor
    turns per output turn (the emulator's power-up reading).
    """

    name = 'cybergear'
    config_section = 'cybergear'
    config = CybergearConfig
    position_saturates = True

    def __init__(self, p_max: float = 4.0 * math.pi, v_max: float = 30.0, t_max: float = 12.0,
                 kp_max: float = 500.0, kd_max: float = 5.0, host_id: int = 0,
                 gear_ratio: float = 7.75):
        for x in (p_max, v_max, t_max, kp_max, kd_max, gear_ratio):
            if not 0.0 < x < math.inf:
                raise ValueError('CyberGear ranges must be finite and > 0')
        if not 0 <= host_id <= 0xFF:
            raise ValueError('host_id must be 0..255')
        self.p_max, self.v_max, self.t_max = float(p_max), float(v_max), float(t_max)
        self.kp_max, self.kd_max = float(kp_max), float(kd_max)
        self.host_id = int(host_id)
        self.gear_ratio = float(gear_ratio)
        self.position_span = 2.0 * self.p_max
        self._p0 = to_u16(0.0, -self.p_max, self.p_max)
        self._v0 = to_u16(0.0, -self.v_max, self.v_max)

    @property
    def torque_limit(self) -> float:
        """Return the largest torque [N m] a command can ask for (t_max)."""
        return self.t_max

    @property
    def speed_range(self) -> float:
        """Return the largest speed [rad/s] the feedback's field holds."""
        return self.v_max

    def reply_codes(self) -> ReplyCodes:
        """Return the 16-bit angle over +-p_max that saturates, 16-bit speed, both truncated."""
        return ReplyCodes(-self.p_max, 2.0 * self.p_max / 65535, 65536, True,
                          2.0 * self.v_max / 65535, True)

    def at_position_end(self, position: float) -> bool:
        """Tell whether an angle reading is within one code of an end (it saturated there)."""
        return abs(position) >= self.p_max * (1.0 - 2.0 / 65535)

    def id_problems(self, motor_ids: Iterable[int]) -> List[str]:
        """Return the IDs outside 1..127 (CAN_ID) or equal to the host's."""
        return ['cybergear: motor ID %d outside 1..127 or the host_id' % i for i in motor_ids
                if not 1 <= i <= 127 or i == self.host_id]

    # ---- host side -------------------------------------------------------------------------

    def command_frame(self, motor_id: int, position: float, velocity: float, kp: float,
                      kd: float, torque: float) -> Frame:
        """Encode a type-1 operation control command: kp (p - q) + kd (v - q_dot) + torque."""
        t = to_u16(torque, -self.t_max, self.t_max)
        data = _U16X4.pack(to_u16(position, -self.p_max, self.p_max),
                           to_u16(velocity, -self.v_max, self.v_max), to_u16(kp, 0.0, self.kp_max),
                           to_u16(kd, 0.0, self.kd_max))
        return Frame(ext_id(OPERATION_CONTROL, t, motor_id), data, True)

    def torque_frames(self, torques: Dict[int, float]) -> List[Frame]:
        """One torque-only operation control command (p = v = kp = kd = 0) per motor."""
        data = _U16X4.pack(self._p0, self._v0, 0, 0)
        return [Frame(ext_id(OPERATION_CONTROL, to_u16(tau, -self.t_max, self.t_max), i), data,
                      True) for i, tau in torques.items()]

    def zero_torque_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """
        Torque-only commands of zero torque.

        65535 steps over +-t_max have no code for 0: code 32767 is -t_max / 65535 (0.18 mN m
        for 12 N m).
        """
        return self.torque_frames(dict.fromkeys(motor_ids, 0.0))

    def _host_frames(self, kind: int, motor_ids: Iterable[int], data: bytes) -> List[Frame]:
        return [Frame(ext_id(kind, self.host_id, i), data, True) for i in motor_ids]

    def enable_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Type 3: enable (run mode); the motor answers with a feedback frame."""
        return self._host_frames(ENABLE, motor_ids, bytes(8))

    def disable_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Zero torque, then type 4 stop (reset mode) with data 0."""
        ids = list(motor_ids)
        return self.zero_torque_frames(ids) + self._host_frames(STOP, ids, bytes(8))

    def clear_error_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Type 4 with byte 0 = 1: stop and clear the fault."""
        return self._host_frames(STOP, motor_ids, bytes((1,) + (0,) * 7))

    def set_zero_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Type 6 with byte 0 = 1: the present position becomes zero (lost at power-off)."""
        return self._host_frames(SET_ZERO, motor_ids, bytes((1,) + (0,) * 7))

    def param_read_frame(self, motor_id: int, index: int) -> Frame:
        """Type 17: read parameter ``index``; the motor answers with a type 17 frame."""
        return Frame(ext_id(PARAM_READ, self.host_id, motor_id),
                     struct.pack('<H6x', index), True)

    def param_write_frame(self, motor_id: int, index: int, value: float) -> Frame:
        """Type 18: write parameter ``index`` (PARAMS gives its type; lost at power-off)."""
        value_bytes = struct.pack(PARAMS.get(index, '<f'), value).ljust(4, b'\0')
        return Frame(ext_id(PARAM_WRITE, self.host_id, motor_id),
                     struct.pack('<H2x', index) + value_bytes, True)

    def decode_param_reply(self, frame: Frame) -> Optional[Tuple[int, int, float]]:
        """Decode a type 17 answer to the host: (motor ID, index, value); None otherwise."""
        data = frame_bytes(frame, extended=True)
        if data is None or len(data) != 8:
            return None
        kind, field, target = split_id(frame.arbitration_id)
        if kind != PARAM_READ or target != self.host_id:
            return None
        index = data[0] | data[1] << 8
        value = struct.unpack_from(PARAMS.get(index, '<f'), data, 4)[0]
        return field & 0xFF, index, value

    def mode_query_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Read each motor's run_mode (type 17, index 0x7005)."""
        return [self.param_read_frame(i, RUN_MODE) for i in motor_ids]

    def mode_problem(self, frame: Frame) -> Optional[Tuple[int, Optional[str]]]:
        """Judge a run_mode answer: (motor ID, None in operation control or the fix)."""
        answer = self.decode_param_reply(frame)
        if answer is None or answer[1] != RUN_MODE:
            return None
        motor_id, _, mode = answer
        if mode == 0:
            return motor_id, None
        return motor_id, ('motor %d is in %s mode (run_mode = %d), not operation control: stop '
                          'it (type 4) and write run_mode 0 (type 18, index 0x7005), or power '
                          'it off and on (run_mode is not stored: operation control is the '
                          'power-up mode)' % (motor_id, RUN_MODES.get(mode, 'an unknown'), mode))

    def decode_feedback(self, frame: Frame) -> Optional[MotorFeedback]:
        """
        Decode a type 2 feedback frame to the host; None for anything else.

        error: the fault bits 16-21 as bits 0-5 (FAULT_BITS; 0: none); enabled: mode = run;
        temperature [deg C].
        """
        data = frame_bytes(frame, extended=True)
        if data is None or len(data) != 8:
            return None
        kind, field, target = split_id(frame.arbitration_id)
        if kind != FEEDBACK or target != self.host_id:
            return None
        angle, speed, torque, temp = _U16X4.unpack(data)
        return MotorFeedback(field & 0xFF, from_u16(angle, -self.p_max, self.p_max),
                             from_u16(speed, -self.v_max, self.v_max),
                             from_u16(torque, -self.t_max, self.t_max), temp / 10.0,
                             field >> 8 & 0x3F, field >> 14 == MODE_RUN)

    def error_reason(self, code: int) -> str:
        """Return the feedback's fault bits in words."""
        words = [w for k, w in enumerate(FAULT_BITS) if int(code) >> k & 1]
        return ', '.join(words) or 'no fault'

    def command_motor_ids(self, frame: Frame) -> Tuple[int, ...]:
        """
        Return (target,) for an extended frame a motor acts on (types 1, 3, 4, 6, 7, 18, 22).

        Replies (types 2, 17 and 21 to the host) and parameter reads are no commands.
        """
        data = frame_bytes(frame, extended=True)
        if data is None or len(data) != 8:
            return ()
        kind, _, target = split_id(frame.arbitration_id)
        return (target,) if kind in _ACTING else ()

    # ---- motor side (emulator) -------------------------------------------------------------

    def encode_feedback(self, motor_id: int, position: float, velocity: float, torque: float,
                        temperature: float, faults: int = 0, mode: int = MODE_RUN) -> Frame:
        """Encode a type 2 feedback frame to the host; values clamped to the ranges."""
        field = (mode & 3) << 14 | (faults & 0x3F) << 8 | (motor_id & 0xFF)
        t10 = temperature * 10.0 if math.isfinite(temperature) else 0.0
        data = _U16X4.pack(to_u16(position, -self.p_max, self.p_max),
                           to_u16(velocity, -self.v_max, self.v_max),
                           to_u16(torque, -self.t_max, self.t_max),
                           int(min(max(t10, 0.0), 65535.0)))
        return Frame(ext_id(FEEDBACK, field, self.host_id), data, True)

    def encode_param_reply(self, motor_id: int, index: int, value: float) -> Frame:
        """Encode a type 17 answer: the motor ID in ID bits 15-8, the host as target."""
        value_bytes = struct.pack(PARAMS.get(index, '<f'), value).ljust(4, b'\0')
        return Frame(ext_id(PARAM_READ, motor_id & 0xFF, self.host_id),
                     struct.pack('<H2x', index) + value_bytes, True)

    def make_emulator(self, motor_id: int, **options) -> 'CybergearMotorEmulator':
        """Return an emulated CyberGear with this codec (CybergearMotorEmulator's options)."""
        return CybergearMotorEmulator(motor_id, self, **options)


class CybergearMotorEmulator(EmulatedMotor):
    """
    One CyberGear: reset mode at power-up, operation control mode (run_mode 0) by default.

    As the manual describes: type 3 enables (run mode), type 4 stops (reset; byte 0 = 1 also
    clears the fault), type 6 zeroes the position, type 1 commands act in run mode with
    run_mode 0, a limit_torque write (18) caps the output; types 1, 3, 4, 6 and 18 are
    answered with a type 2 feedback, type 17 with the parameter. run_mode cannot change
    while running (the manual's precaution 2: a write then is ignored). set_error sets fault
    bits (FAULT_BITS) that stop the output. command_timeout stands for the CAN_TIMEOUT
    parameter (0x200C, default 0 = off), whose unit and action the manual does not give:
    'rest' (reset mode) by default here. A reboot loses the zero (type 6 is not stored) and
    the multi-turn count: the angle reads from the factory zero within one rotor turn.
    """

    def __init__(self, motor_id: int, protocol: Optional[CybergearProtocol] = None,
                 torque_limit: Optional[float] = None, **options):
        self.protocol = protocol if protocol is not None else CybergearProtocol()
        options.setdefault('gear_ratio', self.protocol.gear_ratio)
        options.setdefault('timeout_action', 'rest')
        super().__init__(motor_id, self.protocol.t_max if torque_limit is None
                         else torque_limit, **options)
        self.run_mode = 0

    def handle(self, frame: Frame, q: float, q_dot: float, now: float) -> Optional[Frame]:
        """Act on an extended frame to this motor as its firmware does; return the reply."""
        data = frame_bytes(frame, extended=True)
        if data is None or len(data) != 8:
            return None
        p = self.protocol
        kind, field, target = split_id(frame.arbitration_id)
        if target != self.motor_id or kind not in _ACTING | {PARAM_READ}:
            return None
        self.frames += 1
        self.last_decoded = kind
        index = data[0] | data[1] << 8
        if kind == OPERATION_CONTROL:
            if self.run_mode == 0:
                a, v, kp, kd = _U16X4.unpack(data)
                self.set_command(Command(
                    from_u16(a, -p.p_max, p.p_max), from_u16(v, -p.v_max, p.v_max),
                    from_u16(kp, 0.0, p.kp_max), from_u16(kd, 0.0, p.kd_max),
                    from_u16(field, -p.t_max, p.t_max)), now)
        elif kind == ENABLE:
            self.set_enabled(True, now)
        elif kind == STOP:
            self.set_enabled(False, now)
            if data[0] == 1:
                self.error = 0
        elif kind == SET_ZERO and data[0] == 1:
            self.set_zero_here(q)
        elif kind == PARAM_WRITE and index == RUN_MODE and not self.enabled:
            self.run_mode = data[4]
        elif kind == PARAM_WRITE and index == LIMIT_TORQUE:
            value = struct.unpack_from('<f', data, 4)[0]
            if 0.0 < value <= p.t_max:
                self.torque_limit = value
        elif kind == PARAM_READ:
            values = {RUN_MODE: self.run_mode, LIMIT_TORQUE: self.torque_limit,
                      MECH_POS: self.position(q), MECH_VEL: self.velocity(q_dot)}
            return p.encode_param_reply(self.own_reply_id, index, values.get(index, 0.0)) \
                if index in values else None
        self.torque(q, q_dot, now)
        return p.encode_feedback(self.own_reply_id, self.position(q), self.velocity(q_dot),
                                 self.motor_torque, self.temperature, self.error,
                                 MODE_RUN if self.enabled else MODE_RESET)

    def set_control_mode(self, mode: int) -> None:
        """Set run_mode (index 0x7005) to ``mode`` (RUN_MODES; ValueError otherwise)."""
        if mode not in RUN_MODES:
            raise ValueError('CyberGear run_mode is one of %s, not %r' % (sorted(RUN_MODES),
                                                                          mode))
        self.run_mode = int(mode)

    def power_up_position(self, position: float) -> float:
        """Return the angle after power-up: from the factory zero, within one rotor turn."""
        return rotor_turn_position(position + self.zero, self.gear_ratio)
