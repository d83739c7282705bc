"""
MIT-mode CAN protocol (mini-cheetah motor firmware, CubeMars/T-Motor AK series).

Layouts, the float<->uint mapping, sources and byte vectors: docs/can_protocols.md. In short:

- command, host -> motor: standard ID = motor ID, 8 bytes, big-endian bit fields
  p[16] v[12] kp[12] kd[12] t[12];
- reply, motor -> host: [motor ID, p[16], v[12], t[12]] (6 bytes), or 8 bytes with
  temperature and error code appended (newer CubeMars firmware);
- special frames: FF FF FF FF FF FF FF FC enter motor mode, ... FD exit, ... FE set zero;
- float -> uint: u = int((clamp(x, lo, hi) - lo) * ((1 << bits) - 1) / (hi - lo)), truncating,
  as the firmware does (bgkatz/motorcontrol math_ops.c float_to_uint); the CubeMars manual's
  example code omits the -1, the firmware and the drivers in use keep it, and so do we.

This module is both sides: the host (torque_frames, decode_feedback) and, for the simulated
robot, the motor (decode_command, encode_reply). Per-tick encoding is int math and bytes only.
"""
import math
from typing import Dict, Iterable, List, NamedTuple, Optional, Tuple, Union

from .base import (Frame, frame_bytes, MAX_STANDARD_ID, MotorFeedback, MotorProtocol,
                   ReplyCodes)
from .emulation import EmulatedMotor, rotor_turn_position

ENTER_MOTOR_MODE = bytes((0xFF,) * 7 + (0xFC,))
EXIT_MOTOR_MODE = bytes((0xFF,) * 7 + (0xFD,))
SET_ZERO_POSITION = bytes((0xFF,) * 7 + (0xFE,))
_SPECIAL = {ENTER_MOTOR_MODE: 'enter', EXIT_MOTOR_MODE: 'exit', SET_ZERO_POSITION: 'zero'}
#: 8-byte reply error codes of CubeMars AK firmware (neurobionics/TMotorCANControl mit_can.py,
#: ERROR_CODES).
MIT_ERROR_CODES = {
    1: 'motor over-temperature', 2: 'over-current', 3: 'over-voltage', 4: 'under-voltage',
    5: 'encoder fault', 6: 'phase current unbalance (hardware damage?)',
}


def float_to_uint(x: float, x_min: float, x_max: float, bits: int) -> int:
    """
    Map x in [x_min, x_max] to an unsigned int of ``bits`` bits, as the motor firmware does.

    x is clamped into the range first; truncation, not rounding. NaN maps like 0.0.
    """
    if x != x:
        x = 0.0
    x = min(max(x, x_min), x_max)
    return int((x - x_min) * ((1 << bits) - 1) / (x_max - x_min))


def float_to_uint_wrapping(x: float, x_min: float, x_max: float, bits: int) -> int:
    """
    Map x as the motor firmware packs a reply field: no clamp, only the low ``bits`` bits.

    bgkatz/motorcontrol packs the reply's position, velocity and torque with a float_to_uint
    that does not clamp (Core/Src/math_ops.c) and stores only the low bits (Core/Src/can.c
    pack_reply), so a value beyond [x_min, x_max] wraps around by 2^bits codes; the C cast
    truncates towards zero, as int() does. CubeMars AK firmware wraps too (neurobionics/
    TMotorCANControl mit_can.py counts the wraps: "The TMotor will wrap around to -max at the
    limits for all values it returns"). NaN maps like 0.0.
    """
    if x != x:
        x = 0.0
    return int((x - x_min) * ((1 << bits) - 1) / (x_max - x_min)) & ((1 << bits) - 1)


def uint_to_float(x_int: int, x_min: float, x_max: float, bits: int) -> float:
    """Inverse of float_to_uint (up to its truncation): the value the motor decodes."""
    return x_int * (x_max - x_min) / ((1 << bits) - 1) + x_min


#: A MotorFeedback (a Frame) from a tuple of all its fields without NamedTuple's __new__ (a
#: Python call).
_feedback = _frame = tuple.__new__
_INF = math.inf
#: int()'s truncation of a float without a type call (twice as fast): the encoders' per tick.
_trunc = math.trunc


class MitCommand(NamedTuple):
    """A decoded MIT command: tau = kp (p - q) + kd (v - q_dot) + torque on the motor."""

    motor_id: int
    position: float
    velocity: float
    kp: float
    kd: float
    torque: float


class MitProtocol(MotorProtocol):
    """
    MIT-mode codec with the motor model's ranges (defaults: CubeMars AK80-9 class).

    p_min/p_max [rad], v_min/v_max [rad/s], kp 0..kp_max [N m/rad], kd 0..kd_max [N m s/rad],
    t_min/t_max [N m]: the ranges the motor firmware was built with (they must match, or every
    value is scaled wrong). master_id: the standard ID the motor replies on (the firmware's
    CAN_MASTER, 0 by default); replies on the motor's own ID are accepted too, as some CubeMars
    firmware sends them that way.
    """

    name = 'mit'
    config_section = 'mit'
    reply_id_in_first_byte = True

    def __init__(self, p_min: float = -12.5, p_max: float = 12.5, v_min: float = -50.0,
                 v_max: float = 50.0, kp_max: float = 500.0, kd_max: float = 5.0,
                 t_min: float = -18.0, t_max: float = 18.0, master_id: int = 0):
        ranges = ((p_min, p_max), (v_min, v_max), (0.0, kp_max), (0.0, kd_max), (t_min, t_max))
        for lo, hi in ranges:
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError('MIT range [%r, %r] is not a finite, non-empty interval'
                                 % (lo, hi))
        if not 0 <= master_id <= MAX_STANDARD_ID:
            raise ValueError('master_id must be a standard 11-bit CAN ID')
        self.p_min, self.p_max = float(p_min), float(p_max)
        self.v_min, self.v_max = float(v_min), float(v_max)
        self.kp_max, self.kd_max = float(kp_max), float(kd_max)
        self.t_min, self.t_max = float(t_min), float(t_max)
        self.master_id = int(master_id)
        #: The reply's position field wraps (float_to_uint_wrapping) every p_max - p_min.
        self.position_span = self.p_max - self.p_min
        # Torque-only command (p = v = kp = kd = 0): the first six bytes and kd's low nibble
        # never change, so a tick only packs the 12-bit torque.
        p0 = float_to_uint(0.0, self.p_min, self.p_max, 16)
        v0 = float_to_uint(0.0, self.v_min, self.v_max, 12)
        self._torque_prefix = bytes((p0 >> 8, p0 & 0xFF, v0 >> 4, (v0 & 0xF) << 4, 0, 0))
        self._t_span = self.t_max - self.t_min
        #: decode_reply's ranges: (x_min, x_max - x_min) of position, velocity, torque.
        self._reply_fields = (self.p_min, self.p_max - self.p_min, self.v_min,
                              self.v_max - self.v_min, self.t_min, self._t_span)
        #: command_frame's ranges: x_min, x_max, x_max - x_min of p and v; kp_max; kd_max; t's.
        self._ranges = (self.p_min, self.p_max, self.p_max - self.p_min, self.v_min, self.v_max,
                        self.v_max - self.v_min, self.kp_max, self.kd_max, self.t_min,
                        self.t_max, self._t_span)
        #: The newest command's kp and kd and their codes in place (command_frame encodes them
        #: anew only when they change).
        self._gain_codes = (math.nan, math.nan, 0)

    @classmethod
    def from_config(cls, section) -> 'MitProtocol':
        """Build the codec from a core/motor_config.py MitLimits section (its codec_ranges)."""
        return cls() if section is None else cls(**section.codec_ranges())

    @property
    def torque_limit(self) -> float:
        """Return the largest torque [N m] a command can ask for (the T range's)."""
        return min(-self.t_min, self.t_max)

    @property
    def speed_range(self) -> float:
        """Return the largest speed [rad/s] the reply's velocity field holds."""
        return min(-self.v_min, self.v_max)

    def make_emulator(self, motor_id: int, **options) -> 'MitMotorEmulator':
        """Return an emulated MIT motor with this codec (MitMotorEmulator's options)."""
        return MitMotorEmulator(motor_id, self, **options)

    def reply_codes(self) -> ReplyCodes:
        """Return the 16-bit position wrapping every 65536 codes, the 12-bit speed: truncated."""
        return ReplyCodes(self.p_min, (self.p_max - self.p_min) / 65535.0, 65536, False,
                          (self.v_max - self.v_min) / 4095.0, True)

    def error_reason(self, code: int) -> str:
        """Return the meaning of an 8-byte reply's error code (CubeMars AK firmware)."""
        return MIT_ERROR_CODES.get(int(code), 'unknown error code')

    # ---- host side -------------------------------------------------------------------------

    def command_frame(self, motor_id: int, position: float, velocity: float, kp: float,
                      kd: float, torque: float) -> Frame:
        """
        Encode a full MIT command: the motor applies kp (p - q) + kd (v - q_dot) + torque.

        Values are clamped to the ranges; non-finite ones are sent as 0. (A command with every
        field at its maximum would read FF FF FF FF FF FF FF Fx, which the firmware takes for a
        special frame; keep p below p_max if you ever need such a command.)
        """
        # float_to_uint of each field, inlined and unrolled (ten hip frames a tick at most):
        # the same operations as (clamp(x) - lo) * top / span. A value within its range (the
        # usual case) costs one chained comparison; one outside is clamped, and a non-finite
        # one (x - x is NaN for NaN and inf) is sent as 0.
        p_lo, p_hi, p_span, v_lo, v_hi, v_span, kp_hi, kd_hi, t_lo, t_hi, t_span = self._ranges
        if not p_lo <= position <= p_hi:
            position = 0.0 if position - position != 0.0 else p_hi if position > p_hi else p_lo
        if not v_lo <= velocity <= v_hi:
            velocity = 0.0 if velocity - velocity != 0.0 else v_hi if velocity > v_hi else v_lo
        if not t_lo <= torque <= t_hi:
            torque = 0.0 if torque - torque != 0.0 else t_hi if torque > t_hi else t_lo
        last_kp, last_kd, gains = self._gain_codes
        if kp != last_kp or kd != last_kd:   # the gains change seldom (NaN: every time)
            # kp[12] kd[12] in bits 12..35 of the frame
            gains = _gain_code(kp, kp_hi) << 24 | _gain_code(kd, kd_hi) << 12
            self._gain_codes = (kp, kd, gains)
        # p[16] v[12] kp[12] kd[12] t[12], big-endian.
        return _frame(Frame, (motor_id, (_trunc((position - p_lo) * 65535 / p_span) << 48
                                         | _trunc((velocity - v_lo) * 4095 / v_span) << 36
                                         | gains | _trunc((torque - t_lo) * 4095 / t_span))
                              .to_bytes(8, 'big'), False))

    def torque_frames(self, torques: Dict[int, float]) -> List[Frame]:
        """One torque-only command (p = v = kp = kd = 0) per motor; NaN/inf torque sends 0."""
        frames = []
        t_min, t_max, span, prefix = self.t_min, self.t_max, self._t_span, self._torque_prefix
        for motor_id, tau in torques.items():
            if not t_min <= tau <= t_max:   # as in command_frame: non-finite sends 0
                tau = 0.0 if tau - tau != 0.0 else t_max if tau > t_max else t_min
            t = _trunc((tau - t_min) * 4095 / span)  # float_to_uint(tau, t_min, t_max, 12)
            frames.append(_frame(Frame, (motor_id, prefix + t.to_bytes(2, 'big'), False)))
        return frames

    def zero_torque_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """
        Torque-only commands of zero torque.

        A 12-bit code over a symmetric range has no exact zero: the firmware applies
        t_min + 2047 (t_max - t_min) / 4095 (-4.4 mN m for +-18 N m), far below friction.
        """
        return self.torque_frames(dict.fromkeys(motor_ids, 0.0))

    def enable_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Enter motor mode (FF .. FC); the motor answers with its state."""
        return [Frame(i, ENTER_MOTOR_MODE) for i in motor_ids]

    def disable_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """
        Zero torque, then exit motor mode (FF .. FD), per motor.

        The zero command first means a motor that is enabled again does not start from a stale
        command (observed with CubeMars motors by dfki-ric-underactuated-lab's driver).
        """
        frames = []
        for i in motor_ids:
            frames += self.zero_torque_frames((i,))
            frames.append(Frame(i, EXIT_MOTOR_MODE))
        return frames

    def set_zero_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Make the present position the motors' zero (FF .. FE). Never sent automatically."""
        return [Frame(i, SET_ZERO_POSITION) for i in motor_ids]

    def decode_feedback(self, frame: Frame) -> Optional[MotorFeedback]:
        """
        Decode a reply: [id, p16, v12, t12] (6 bytes) or + [temperature, error] (8 bytes).

        Accepted on a standard ID equal to master_id or to the motor ID in byte 0; anything
        else (other lengths, extended IDs, other IDs) gives None.
        """
        data = frame_bytes(frame)
        motor_id = self._reply_id(frame, data)
        if motor_id is None:
            return None
        p = (data[1] << 8) | data[2]
        v = (data[3] << 4) | (data[4] >> 4)
        t = ((data[4] & 0xF) << 8) | data[5]
        temperature = error = None
        if len(data) == 8:
            temperature = float(data[6] - 256 if data[6] > 127 else data[6])  # int8 [deg C]
            error = data[7]
        return MotorFeedback(motor_id, uint_to_float(p, self.p_min, self.p_max, 16),
                             uint_to_float(v, self.v_min, self.v_max, 12),
                             uint_to_float(t, self.t_min, self.t_max, 12), temperature, error)

    def decode_reply(self, frame: Frame, motor_ids) -> Optional[MotorFeedback]:
        """
        Return the reply of one of ``motor_ids`` decoded (decode_feedback), else None.

        One pass over the frame, six a tick: a bytes payload is read as it is (frame_bytes
        copies and checks it; a reply's ID, master_id or byte 0, is a standard one anyway).
        """
        data = frame.data
        if type(data) is not bytes or frame.is_extended_id:
            data = frame_bytes(frame)   # the careful path: any other payload, extended IDs
            if data is None:
                return None
        n = len(data)
        if n != 6 and n != 8:
            return None
        motor_id = data[0]
        if motor_id not in motor_ids:
            return None
        i = frame.arbitration_id
        if i != self.master_id and i != motor_id:
            return None
        # uint_to_float of each field, the same operations (x_int * span / top + x_min).
        p_min, p_span, v_min, v_span, t_min, t_span = self._reply_fields
        d4 = data[4]
        temperature = error = None
        if n == 8:
            d6 = data[6]
            temperature = float(d6 - 256 if d6 > 127 else d6)  # int8 [deg C]
            error = data[7]
        return _feedback(MotorFeedback, (
            motor_id, ((data[1] << 8) | data[2]) * p_span / 65535 + p_min,
            ((data[3] << 4) | (d4 >> 4)) * v_span / 4095 + v_min,
            (((d4 & 0xF) << 8) | data[5]) * t_span / 4095 + t_min, temperature, error, None))

    def reply_motor_id(self, frame: Frame) -> Optional[int]:
        """Return byte 0 of what decode_feedback would accept as a reply, else None."""
        return self._reply_id(frame, frame_bytes(frame))

    def command_motor_ids(self, frame: Frame) -> Tuple[int, ...]:
        """
        Return (the frame's ID,) for an 8-byte standard frame a motor acts on, else ().

        A motor takes every 8-byte frame on its ID for a command (a special frame or an MIT
        command, ``decode_command``), but an 8-byte reply has that shape too: one on master_id
        (byte 0 = the replying motor), or on the replying motor's own ID (byte 0 = that ID:
        some CubeMars firmware, or a motor whose master_id is its own ID). Those count as the
        replies they are. The cost: a command whose position's high byte equals the motor ID
        (p within 1/256 of the range above p_min + ID/256 of it) is not seen; torque-only
        commands (p = 0: byte 0 = 0x7F) are, for every ID but 127. Special frames always count.
        (A master_id equal to a motor's ID would make that motor take the others' replies for
        commands: never configure it so.)
        """
        data = frame_bytes(frame)
        if data is None or len(data) != 8:
            return ()
        if data not in _SPECIAL and frame.arbitration_id in (data[0], self.master_id):
            return ()   # a reply: on the master ID, or on the motor's own ID
        return (frame.arbitration_id,)

    def _reply_id(self, frame: Frame, data: Optional[bytes]) -> Optional[int]:
        if data is None or len(data) not in (6, 8):
            return None
        motor_id = data[0]
        if frame.arbitration_id != self.master_id and frame.arbitration_id != motor_id:
            return None
        return motor_id

    # ---- motor side (simulated robot) ------------------------------------------------------

    def decode_command(self, frame: Frame) -> Union[MitCommand, str, None]:
        """
        Decode a frame as a motor does: 'enter', 'exit', 'zero', a MitCommand, or None.

        None for frames that are not 8-byte standard frames. The motor ID is the frame's ID;
        a motor only acts on frames with its own ID (the caller filters).
        """
        data = frame_bytes(frame)
        if data is None or len(data) != 8:
            return None
        special = _SPECIAL.get(data)
        if special is not None:
            return special
        p = (data[0] << 8) | data[1]
        v = (data[2] << 4) | (data[3] >> 4)
        kp = ((data[3] & 0xF) << 8) | data[4]
        kd = (data[5] << 4) | (data[6] >> 4)
        t = ((data[6] & 0xF) << 8) | data[7]
        return MitCommand(frame.arbitration_id,
                          uint_to_float(p, self.p_min, self.p_max, 16),
                          uint_to_float(v, self.v_min, self.v_max, 12),
                          uint_to_float(kp, 0.0, self.kp_max, 12),
                          uint_to_float(kd, 0.0, self.kd_max, 12),
                          uint_to_float(t, self.t_min, self.t_max, 12))

    def encode_reply(self, motor_id: int, position: float, velocity: float, torque: float,
                     temperature: Optional[float] = None, error: int = 0,
                     wrap: bool = False) -> Frame:
        """
        Encode the motor's reply on master_id: 6 bytes, or 8 with temperature and error code.

        temperature [deg C]. Non-finite values are sent as 0. Values beyond the ranges are
        clamped, or with ``wrap`` wrap around as the firmware sends them (float_to_uint_wrapping:
        a position of p_max + 0.1 rad reads about p_min + 0.1 rad).
        """
        pack = float_to_uint_wrapping if wrap else float_to_uint
        p = pack(_finite(position), self.p_min, self.p_max, 16)
        v = pack(_finite(velocity), self.v_min, self.v_max, 12)
        t = pack(_finite(torque), self.t_min, self.t_max, 12)
        fields = [motor_id & 0xFF, p >> 8, p & 0xFF, v >> 4, ((v & 0xF) << 4) | (t >> 8),
                  t & 0xFF]
        if temperature is not None:
            temp = int(min(127.0, max(-128.0, _finite(temperature))))
            fields += [temp & 0xFF, error & 0xFF]
        return Frame(self.master_id, bytes(fields))


def _gain_code(x: float, x_max: float) -> int:
    """Return float_to_uint(x, 0, x_max, 12), the same operations; non-finite x gives 0."""
    if not -_INF < x < _INF:
        x = 0.0
    return int(((x_max if x > x_max else 0.0 if x < 0.0 else x) - 0.0) * 4095 / x_max)


def _finite(x: float) -> float:
    """Return x if it is a finite number, else 0.0."""
    return x if math.isfinite(x) else 0.0


#: Rotor angle window of the first encoder sample after power-up [rad] (position_sensor.c).
POWER_UP_WINDOW = (-1.5 * math.pi, 0.5 * math.pi)


class MitMotorEmulator(EmulatedMotor):
    """
    One MIT motor as sim/motor_emulator.py's docstring describes (bgkatz/motorcontrol).

    The state it shares with every protocol's emulator is EmulatedMotor's.

    motor_id: its standard CAN ID; protocol: the MIT ranges it was built with (default
    MitProtocol(), the AK80-9 class); torque_limit [N m]: what the motor can give (default the
    protocol's t_max); gear_ratio: rotor turns per output turn (for reboot); direction: +1 or
    -1, motor shaft relative to the joint; command_timeout [s], 0 = none; timeout_action:
    'zero' or 'rest'; wrap: reply fields beyond their range wrap (firmware) or clamp;
    reply_temperature: 8-byte replies with temperature [deg C] and error code.
    """

    def __init__(self, motor_id: int, protocol: Optional[MitProtocol] = None,
                 torque_limit: Optional[float] = None, gear_ratio: float = 9.0,
                 direction: int = 1, command_timeout: float = 0.0,
                 timeout_action: str = 'zero', wrap: bool = True,
                 reply_temperature: bool = False, temperature: float = 25.0):
        self.protocol = protocol if protocol is not None else MitProtocol()
        super().__init__(motor_id, self.protocol.t_max if torque_limit is None else torque_limit,
                         gear_ratio, direction, command_timeout, timeout_action, temperature)
        self.wrap = bool(wrap)
        self.reply_temperature = bool(reply_temperature)

    def handle(self, frame: Frame, q: float, q_dot: float, now: float) -> Optional[Frame]:
        """
        Act on a frame as the firmware does and return the reply, or None if not for this motor.

        q [rad], q_dot [rad/s]: the joint's state now; now [s]: the motor's clock (for the
        command timeout). Frames with another ID or that are not 8-byte standard frames get no
        reply.
        """
        if frame.arbitration_id != self.motor_id:
            return None
        decoded = self.protocol.decode_command(frame)
        if decoded is None:
            return None
        self.frames += 1
        self.last_decoded = decoded
        if decoded == 'enter':
            self.set_enabled(True, now)   # from zero torque, not a stale command
        elif decoded == 'exit':
            self.enabled = False
            self.command = None
        elif decoded == 'zero':
            if not self.enabled:
                self.set_zero_here(q)
        else:
            self.set_command(decoded, now)
        self.torque(q, q_dot, now)
        return self.protocol.encode_reply(
            self.own_reply_id, self.position(q), self.velocity(q_dot), self.motor_torque,
            temperature=self.temperature if self.reply_temperature else None,
            error=self.error, wrap=self.wrap)

    def power_up_position(self, position: float) -> float:
        """
        Return the reading after power-up: the position modulo one rotor turn.

        The rotor angle from the stored zero, wrapped into POWER_UP_WINDOW, over the gear
        ratio; the stored zero itself is kept.
        """
        return rotor_turn_position(position, self.gear_ratio, POWER_UP_WINDOW)

    def set_error(self, code: int) -> None:
        """
        Set the error code reported in 8-byte replies (0 = none); the output is off until 0.

        CubeMars AK codes (neurobionics/TMotorCANControl mit_can.py ERROR_CODES): 1
        over-temperature, 2 over-current, 3 over-voltage, 4 under-voltage, 5 encoder fault,
        6 phase current unbalance.
        """
        self.error = int(code) & 0xFF
