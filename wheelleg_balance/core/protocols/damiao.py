"""
DaMiao DM-J series on CAN in MIT mode (``can.protocol`` / ``legs.can.protocol: damiao``).

Layouts and sources: docs/can_protocols.md. The command is the MIT layout (core/protocols/
mit.py: p[16] v[12] kp[12] kd[12] t[12] on the motor's ID, ESC_ID) with the model's ranges
(registers PMAX, VMAX, TMAX; DM-J4310: 12.5 rad, 30 rad/s, 10 N m), kp 0..500, kd 0..5. What
differs, after DaMiao's DM-J4310-2EC instruction manual (V1.1 / V1.2) as the open drivers
read it (cmjang/DM_Control_Python DM_CAN.py at 3803814c; jia-xie/python-damiao-driver
docs/concept/communication-protocol.md at 190037da and registers.md at 3e46e44c):

- special frames on the motor's ID: ``FF x7 FC`` enable, ``.. FD`` disable, ``.. FE`` set zero,
  ``.. FB`` clear error;
- the reply, on the feedback ID (MST_ID, register 7), 8 bytes: byte 0 = status << 4 | motor
  ID (low 4 bits), then p[16] v[12] t[12] as in MIT, byte 6 the MOS temperature, byte 7 the
  rotor temperature [deg C]; status 0 disabled, 1 enabled, 8 over-voltage, 9 under-voltage,
  0xA over-current, 0xB MOS over-temperature, 0xC rotor over-temperature, 0xD communication
  lost (the TIMEOUT register, 9: the motor disables), 0xE overload;
- registers on ID 0x7FF: ``id_lo id_hi 33 rid 00 00 00 00`` read, ``id_lo id_hi 55 rid value``
  write (4 bytes little-endian, uint32 or float32 by register), ``.. AA ..`` store to flash;
  the motor answers on MST_ID with ``id_lo id_hi 33|55 rid value``. Register 10, CTRL_MODE:
  1 MIT, 2 position-velocity, 3 velocity, 4 force-position; only MIT mode takes our frames
  (bring-up checks it, ``control_mode_problem``).

The reply's motor ID has 4 bits: motors sharing one MST_ID need IDs 1..15. A register reply
has a state reply's ID and length: only bring-up, with the motors disabled, reads registers.
"""
from dataclasses import dataclass
import math
import struct
from typing import Iterable, List, Optional, Tuple

from .base import Frame, frame_bytes, MAX_STANDARD_ID, MotorFeedback, MotorProtocol
from .emulation import EmulatedMotor, rotor_turn_position
from .mit import float_to_uint, float_to_uint_wrapping, MitProtocol, uint_to_float
from ..schema import param

CLEAR_ERROR = bytes((0xFF,) * 7 + (0xFB,))
#: Register frames: their ID and the command byte (byte 2).
REGISTER_ID = 0x7FF
REG_READ, REG_WRITE, REG_STORE = 0x33, 0x55, 0xAA
#: Registers (DM_CAN.py DM_variable; registers.md).
MST_ID, ESC_ID, TIMEOUT, CTRL_MODE = 7, 8, 9, 10
PMAX, VMAX, TMAX = 21, 22, 23
#: Registers holding a uint32 (the others a float32).
UINT_REGISTERS = frozenset((7, 8, 9, 10, 13, 14, 15, 16, 35, 36))
CONTROL_MODES = {1: 'MIT', 2: 'position-velocity', 3: 'velocity', 4: 'force-position'}
MIT_MODE = 1
#: Reply status codes (byte 0, high nibble).
DISABLED, ENABLED, LOST_COMM = 0x0, 0x1, 0xD
STATUS_CODES = {0x8: 'over-voltage', 0x9: 'under-voltage', 0xA: 'over-current',
                0xB: 'MOS over-temperature', 0xC: 'rotor over-temperature',
                0xD: 'communication lost (the TIMEOUT register: the motor disabled itself)',
                0xE: 'overload'}


@dataclass(frozen=True)
class DamiaoConfig:
    """A DaMiao DM-J model's mapping ranges (its PMAX, VMAX, TMAX registers)."""

    p_max: float = param(12.5, 'damiao: position range +-p_max [rad] (register PMAX)', 0.1,
                         1000.0, read_only=True)
    v_max: float = param(30.0, 'damiao: velocity range +-v_max [rad/s] (register VMAX; '
                         'DM-J4310: 30)', 0.1, 1000.0, read_only=True)
    t_max: float = param(10.0, 'damiao: torque range +-t_max [N m] (register TMAX; DM-J4310: '
                         '10)', 0.1, 1000.0, read_only=True)
    kp_max: float = param(500.0, 'damiao: kp range 0..kp_max [N m/rad]', 0.1, 10000.0,
                          read_only=True)
    kd_max: float = param(5.0, 'damiao: kd range 0..kd_max [N m s/rad]', 0.01, 1000.0,
                          read_only=True)
    master_id: int = param(0, "damiao: the motors' feedback ID (register MST_ID)", 0,
                           MAX_STANDARD_ID, read_only=True)
    temp_derate: float = param(70.0, 'damiao: motor temperature (the hotter of MOS and rotor) '
                               'from which the torque limit falls linearly, to half at '
                               'temp_max [deg C]', -40.0, 200.0, read_only=True)
    temp_max: float = param(85.0, 'damiao: motor temperature at which balancing ends [deg C]',
                            -40.0, 200.0, read_only=True)

    position_jump: float = param(0.3, 'damiao: a reply position this far off the extrapolation '
                                 'of the previous reply is a reboot: fault [rad]', 0.01, 10.0,
                                 read_only=True)

    def codec_kwargs(self) -> dict:
        """Keyword arguments of DamiaoProtocol for this model."""
        return {'p_max': self.p_max, 'v_max': self.v_max, 't_max': self.t_max,
                'kp_max': self.kp_max, 'kd_max': self.kd_max, 'master_id': self.master_id}


class DamiaoProtocol(MitProtocol):
    """
    DaMiao MIT-mode codec: the MIT command with DaMiao's reply, special frames and registers.

    p_max [rad], v_max [rad/s], t_max [N m]: the motor's PMAX, VMAX, TMAX (symmetric ranges);
    kp_max, kd_max; master_id: the feedback ID (MST_ID) its replies come on.
    """

    name = 'damiao'
    config_section = 'damiao'
    #: Byte 0 carries the status nibble above the ID (0x11: motor 1 enabled).
    reply_id_in_first_byte = False
    config = DamiaoConfig

    def __init__(self, p_max: float = 12.5, v_max: float = 30.0, t_max: float = 10.0,
                 kp_max: float = 500.0, kd_max: float = 5.0, master_id: int = 0):
        super().__init__(p_min=-p_max, p_max=p_max, v_min=-v_max, v_max=v_max, kp_max=kp_max,
                         kd_max=kd_max, t_min=-t_max, t_max=t_max, master_id=master_id)

    @classmethod
    def from_config(cls, section) -> 'DamiaoProtocol':
        """Build the codec from its configuration section (DamiaoConfig)."""
        return cls(**section.codec_kwargs())

    def id_problems(self, motor_ids: Iterable[int]) -> List[str]:
        """Return the IDs a reply cannot name (its 4-bit ID: 1..15) or the feedback ID's."""
        return ['damiao: motor ID %d outside 1..15 (the reply names 4 bits) or the master_id'
                % i for i in motor_ids if not 1 <= i <= 15 or i == self.master_id]

    # ---- host side -------------------------------------------------------------------------

    def clear_error_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Clear the motors' latched errors (FF .. FB); enable_frames afterwards."""
        return [Frame(i, CLEAR_ERROR) for i in motor_ids]

    def register_read_frame(self, motor_id: int, register: int) -> Frame:
        """Read register ``register`` of motor ``motor_id`` (answered on MST_ID)."""
        return Frame(REGISTER_ID, bytes((motor_id & 0xFF, motor_id >> 8 & 0xFF, REG_READ,
                                         register & 0xFF, 0, 0, 0, 0)))

    def register_write_frame(self, motor_id: int, register: int, value: float) -> Frame:
        """Write register ``register`` (RAM; lost at power-off unless stored)."""
        return Frame(REGISTER_ID, bytes((motor_id & 0xFF, motor_id >> 8 & 0xFF, REG_WRITE,
                                         register & 0xFF)) + _pack_register(register, value))

    def decode_register_reply(self, frame: Frame) -> Optional[Tuple[int, int, float]]:
        """Decode a register answer on MST_ID: (motor ID, register, value); None otherwise."""
        data = frame_bytes(frame)
        if data is None or len(data) != 8 or frame.arbitration_id != self.master_id \
                or data[2] not in (REG_READ, REG_WRITE):
            return None
        fmt = '<I' if data[3] in UINT_REGISTERS else '<f'
        return data[0] | data[1] << 8, data[3], struct.unpack_from(fmt, data, 4)[0]

    @staticmethod
    def control_mode_problem(motor_id: int, mode: float) -> Optional[str]:
        """Return what is wrong with a CTRL_MODE (register 10) reading and its fix, or None."""
        if mode == MIT_MODE:
            return None
        return ('motor %d is in %s mode (CTRL_MODE = %s), not MIT: write register 10 = 1 '
                '(DaMiao debugging tool, or a 0x7FF frame %02X %02X 55 0A 01 00 00 00) and store '
                'it (AA)' % (motor_id, CONTROL_MODES.get(int(mode), 'an unknown'), mode,
                             motor_id & 0xFF, motor_id >> 8 & 0xFF))

    def mode_query_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Read each motor's CTRL_MODE (register 10)."""
        return [self.register_read_frame(i, CTRL_MODE) for i in motor_ids]

    def mode_problem(self, frame: Frame) -> Optional[Tuple[int, Optional[str]]]:
        """Judge a CTRL_MODE answer: (motor ID, control_mode_problem); None for other frames."""
        answer = self.decode_register_reply(frame)
        if answer is None or answer[1] != CTRL_MODE:
            return None
        return answer[0], self.control_mode_problem(answer[0], answer[2])

    def decode_feedback(self, frame: Frame) -> Optional[MotorFeedback]:
        """
        Decode a reply on MST_ID: [status|ID, p16, v12, t12, T_MOS, T_rotor]; else None.

        temperature: the hotter of MOS and rotor [deg C]; error: the status when it is a
        fault (8..0xE), else 0; enabled: status 1.
        """
        data = frame_bytes(frame)
        if data is None or len(data) != 8 or frame.arbitration_id != self.master_id:
            return None
        status = data[0] >> 4
        p = (data[1] << 8) | data[2]
        v = (data[3] << 4) | (data[4] >> 4)
        t = ((data[4] & 0xF) << 8) | data[5]
        return MotorFeedback(data[0] & 0xF, uint_to_float(p, self.p_min, self.p_max, 16),
                             uint_to_float(v, self.v_min, self.v_max, 12),
                             uint_to_float(t, self.t_min, self.t_max, 12),
                             float(max(data[6], data[7])), status if status >= 8 else 0,
                             status == ENABLED)

    decode_reply = MotorProtocol.decode_reply   # not MIT's one-pass: the reply differs

    def reply_motor_id(self, frame: Frame) -> Optional[int]:
        """Return the motor ID (low 4 bits) of a reply on MST_ID, else None."""
        data = frame_bytes(frame)
        if data is None or len(data) != 8 or frame.arbitration_id != self.master_id:
            return None
        return data[0] & 0xF

    def error_reason(self, code: int) -> str:
        """Return the reply's status code in words."""
        return STATUS_CODES.get(int(code), 'status 0x%X' % int(code))

    def command_motor_ids(self, frame: Frame) -> Tuple[int, ...]:
        """
        Return (ID,) for an 8-byte standard frame to a motor, or a register write or store.

        Frames on MST_ID are replies, register reads change nothing: those give ().
        """
        data = frame_bytes(frame)
        if data is None or len(data) != 8 or frame.arbitration_id == self.master_id:
            return ()
        if frame.arbitration_id == REGISTER_ID:
            return (data[0] | data[1] << 8,) if data[2] in (REG_WRITE, REG_STORE) else ()
        return (frame.arbitration_id,)

    # ---- motor side (emulator) -------------------------------------------------------------

    def decode_command(self, frame: Frame):
        """Decode as MitProtocol.decode_command does, and 'clear' for FF .. FB."""
        data = frame_bytes(frame)
        if data == CLEAR_ERROR:
            return 'clear'
        return super().decode_command(frame)

    def encode_state(self, motor_id: int, status: int, position: float, velocity: float,
                     torque: float, t_mos: float, t_rotor: float, wrap: bool = True) -> Frame:
        """Encode a reply on MST_ID; fields beyond their range wrap (or clamp, wrap=False)."""
        pack = float_to_uint_wrapping if wrap else float_to_uint
        p = pack(_finite(position), self.p_min, self.p_max, 16)
        v = pack(_finite(velocity), self.v_min, self.v_max, 12)
        t = pack(_finite(torque), self.t_min, self.t_max, 12)
        return Frame(self.master_id, bytes((
            (status & 0xF) << 4 | (motor_id & 0xF), p >> 8, p & 0xFF, v >> 4,
            (v & 0xF) << 4 | t >> 8, t & 0xFF, _temp(t_mos), _temp(t_rotor))))

    def encode_register_reply(self, motor_id: int, command: int, register: int,
                              value: float) -> Frame:
        """Encode a register answer on MST_ID."""
        return Frame(self.master_id, bytes((motor_id & 0xFF, motor_id >> 8 & 0xFF, command,
                                            register & 0xFF)) + _pack_register(register, value))

    def make_emulator(self, motor_id: int, **options) -> 'DamiaoMotorEmulator':
        """Return an emulated DaMiao motor with this codec (DamiaoMotorEmulator's options)."""
        return DamiaoMotorEmulator(motor_id, self, **options)


def _pack_register(register: int, value: float) -> bytes:
    if register in UINT_REGISTERS:
        return struct.pack('<I', int(value) & 0xFFFFFFFF)
    return struct.pack('<f', value)


def _finite(x: float) -> float:
    return x if math.isfinite(x) else 0.0


def _temp(x: float) -> int:
    return int(min(max(_finite(x), 0.0), 255.0))


class DamiaoMotorEmulator(EmulatedMotor):
    """
    One DaMiao DM-J motor in the control mode of its CTRL_MODE register (MIT by default).

    Disabled at power-up; FC enables (not while a fault is latched), FD disables, FE zeroes,
    FB clears the fault; MIT commands act in MIT mode only (another mode's motor ignores
    them but still answers, status and all, which is how bring-up sees it); every frame on
    its ID is answered on MST_ID. Register reads and writes on 0x7FF (CTRL_MODE, TIMEOUT,
    MST_ID, PMAX/VMAX/TMAX) are answered too. command_timeout stands for the TIMEOUT register
    (its unit is not given by the sources): when it fires the motor disables itself with
    status 0xD until FB clears it. set_error sets a status code (8..0xE). The output shaft's
    single-turn absolute encoder keeps the zero across a reboot but not the turn count: the
    position reads within +-pi afterwards.
    """

    def __init__(self, motor_id: int, protocol: Optional[DamiaoProtocol] = None,
                 torque_limit: Optional[float] = None, control_mode: int = MIT_MODE,
                 wrap: bool = True, **options):
        self.protocol = protocol if protocol is not None else DamiaoProtocol()
        super().__init__(motor_id, self.protocol.t_max if torque_limit is None
                         else torque_limit, **options)
        self.control_mode = int(control_mode)
        self.wrap = bool(wrap)
        self.mos_temperature: Optional[float] = None   # None: the rotor's temperature

    def on_timeout(self) -> None:
        """Disable the motor with status 0xD: the TIMEOUT register fired."""
        self.enabled = False
        self.error = LOST_COMM

    def handle(self, frame: Frame, q: float, q_dot: float, now: float) -> Optional[Frame]:
        """Act on a frame to this motor (its ID, or a register frame); return the reply."""
        p = self.protocol
        if frame.arbitration_id == REGISTER_ID:
            return self._register(frame_bytes(frame), q)
        if frame.arbitration_id != self.motor_id:
            return None
        decoded = p.decode_command(frame)
        if decoded is None:
            return None
        self.frames += 1
        self.last_decoded = decoded
        if decoded == 'enter':
            if not self.error:
                self.set_enabled(True, now)
        elif decoded == 'exit':
            self.set_enabled(False, now)
        elif decoded == 'zero':
            self.set_zero_here(q)
        elif decoded == 'clear':
            self.error = 0
        elif self.control_mode == MIT_MODE:
            self.set_command(decoded, now)   # a MitCommand: its fields are a Command's
        self.torque(q, q_dot, now)
        status = self.error or (ENABLED if self.enabled else DISABLED)
        t_mos = self.temperature if self.mos_temperature is None else self.mos_temperature
        return p.encode_state(self.own_reply_id, status, self.position(q), self.velocity(q_dot),
                              self.motor_torque, t_mos, self.temperature, self.wrap)

    def _register(self, data: Optional[bytes], q: float) -> Optional[Frame]:
        if data is None or len(data) != 8 or (data[0] | data[1] << 8) != self.motor_id \
                or data[2] not in (REG_READ, REG_WRITE):
            return None
        p, register = self.protocol, data[3]
        if data[2] == REG_WRITE:
            value = struct.unpack_from('<I' if register in UINT_REGISTERS else '<f', data, 4)[0]
            if register == CTRL_MODE and value in CONTROL_MODES:
                self.control_mode = int(value)
        values = {CTRL_MODE: self.control_mode, MST_ID: p.master_id, ESC_ID: self.motor_id,
                  PMAX: p.p_max, VMAX: p.v_max, TMAX: p.t_max}
        if register not in values:
            return None
        return p.encode_register_reply(self.motor_id, data[2], register, values[register])

    def set_control_mode(self, mode: int) -> None:
        """Set CTRL_MODE (register 10) to ``mode`` (CONTROL_MODES; ValueError otherwise)."""
        if mode not in CONTROL_MODES:
            raise ValueError('DaMiao CTRL_MODE is one of %s, not %r' % (sorted(CONTROL_MODES),
                                                                        mode))
        self.control_mode = int(mode)

    def power_up_position(self, position: float) -> float:
        """Return the reading after power-up: the output angle within +-pi (zero kept)."""
        return rotor_turn_position(position, 1.0)
