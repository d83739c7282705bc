"""
The interface every CAN motor protocol implements (pure bytes: no python-can here).

A protocol turns wheel-motor torques into CAN frames and motor replies into MotorFeedback.
The node wraps ``Frame`` into ``can.Message`` and back; the controllers never see a protocol.
Beside the frames, a protocol answers what the rest of the package would otherwise branch on
(``frames_per_tick``, ``position_span`` and ``position_saturates``, ``reply_codes``,
``speed_range``, ``error_reason``, ``health_interval`` with ``health_frames`` and
``decode_health``, ``clear_error_frames``, ``set_zero_frames``, ``make_emulator``,
``from_config``): see docs/can_protocols.md.
Torques are motor torques [N m] with the mounting direction already applied
(core/actuation.py); positions [rad] and velocities [rad/s] are at the motor's output shaft.
"""
from abc import ABC, abstractmethod
import math
from typing import Any, Dict, Iterable, List, NamedTuple, Optional, Tuple

#: Largest standard (11-bit) and extended (29-bit) CAN identifiers.
MAX_STANDARD_ID = 0x7FF
MAX_EXTENDED_ID = 0x1FFFFFFF


class Frame(NamedTuple):
    """A classic CAN data frame: 11-bit (or 29-bit when is_extended_id) ID and 0..8 bytes."""

    arbitration_id: int
    data: bytes
    is_extended_id: bool = False


class ReplyCodes(NamedTuple):
    """
    How a reply codes the position and speed (core/wheel_state.py unwraps from this).

    p_zero [rad]: the position of code 0; p_step [rad]: one position code; p_codes: the
    codes of the field (it wraps every p_codes codes, or with saturates sticks at codes 0 and
    p_codes - 1); v_step [rad/s]: one speed code (0: not quantized); truncates: the firmware
    truncates to the code below (so a host reads a field at its code's centre).
    """

    p_zero: float
    p_step: float
    p_codes: int
    saturates: bool
    v_step: float
    truncates: bool


#: What reply_codes says of a position field that neither wraps nor ends: 2^52 codes of
#: 1 urad (4.5e9 rad) with code 0 far below any reading.
_ENDLESS_CODES = 1 << 52


class MotorFeedback(NamedTuple):
    """
    One motor's reply.

    motor_id: the motor's ID on the bus; position [rad]; velocity [rad/s]; torque [N m]
    (output shaft, motor direction); temperature [deg C] or None when the frame carries none;
    error: the motor's error code or None when the frame carries none (0: no error); enabled:
    whether the reply says the motor is in its torque mode (None: the reply does not say).
    """

    motor_id: int
    position: float
    velocity: float
    torque: float
    temperature: Optional[float] = None
    error: Optional[int] = None
    enabled: Optional[bool] = None


class MotorHealth(NamedTuple):
    """
    A health reply (``MotorProtocol.decode_health``): what a torque reply lacks.

    motor_id; temperature [deg C] or None when the reply carries none; error: the motor's
    error code (0: no error), in ``error_reason``'s terms.
    """

    motor_id: int
    temperature: Optional[float]
    error: int


class MotorProtocol(ABC):
    """
    Encoder/decoder of one motor family's CAN frames.

    Every method is total: encoders never raise for any float (non-finite torques become
    zero torque, out-of-range ones are clamped), and decode_feedback returns None for a frame
    that is not a well-formed reply of this protocol.
    """

    #: Short name, the value of the node's ``can.protocol`` parameter.
    name = ''
    #: The configuration section of its figures (``can.<config_section>``, and under ``legs``
    #: for a protocol the hips can speak); '' or a missing section: the class defaults.
    config_section = ''
    #: The reply's position field [rad]: the span after which it wraps (inf: it neither wraps
    #: nor ends), or, with position_saturates, the span whose ends it sticks at.
    position_span = math.inf
    position_saturates = False
    #: A reply's first byte is the replying motor's ID and nothing else (MIT): a frame whose
    #: first byte names another motor set's motor is then no reply of this set's.
    reply_id_in_first_byte = False
    #: Time [s] between two health queries (``health_frames``, one motor each, in turn) while
    #: the tick commands torques; 0: none, the torque replies carry the error code already.
    health_interval = 0.0

    @property
    def torque_limit(self) -> float:
        """Return the largest torque [N m] a command can ask for (inf: none known)."""
        return math.inf

    @property
    def speed_range(self) -> float:
        """Return the largest speed [rad/s] the reply's field holds (inf: no limit)."""
        return math.inf

    def position_step(self, previous: float, position: float) -> float:
        """
        Return the change [rad] from one reply's position to the next one's.

        Modulo position_span (the shortest way) where the field wraps, so a caller that adds
        the steps unwraps a single-turn or wrapping reading; plain where it does not. Valid
        while the joint moves less than half the span between two replies (speed_range times
        the gap tells a caller when it may have moved more).
        """
        d = position - previous
        span = self.position_span
        if not self.position_saturates and 0.0 < span < math.inf:
            d = (d + 0.5 * span) % span - 0.5 * span
        return d

    def reply_codes(self) -> ReplyCodes:
        """
        Return how the reply codes position and speed (core/wheel_state.py).

        Default from position_span: 65536 codes over it from 0 (wrapping, or saturating with
        position_saturates); an endless field where the span is inf. A protocol with its own
        code layout says it exactly.
        """
        span = self.position_span
        if 0.0 < span < math.inf:
            return ReplyCodes(0.0, span / 65536, 65536, bool(self.position_saturates), 0.0,
                              False)
        return ReplyCodes(-0.5e-6 * _ENDLESS_CODES, 1e-6, _ENDLESS_CODES, False, 0.0, False)

    def at_position_end(self, position: float) -> bool:
        """Tell whether a saturating position field reads one of its ends (position unknown)."""
        return False

    def frames_per_tick(self, motor_ids: Iterable[int]) -> int:
        """Return how many frames one control tick sends to ``motor_ids`` at most."""
        ids = list(motor_ids)
        torque = len(self.torque_frames(dict.fromkeys(ids, 0.0)))
        return torque + (len(self.health_frames(ids[0])) if self.health_interval and ids else 0)

    def health_frames(self, motor_id: int) -> List[Frame]:
        """Frames that ask motor ``motor_id`` for its error code (health_interval; none here)."""
        return []

    def decode_health(self, frame: Frame) -> Optional[MotorHealth]:
        """Decode an answer to health_frames; None for a frame that is none (never raises)."""
        return None

    def clear_error_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Frames that clear the motors' latched errors (none where the protocol has no such)."""
        return []

    def set_zero_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Frames that make the present position the motors' zero. Never sent automatically."""
        return []

    def id_problems(self, motor_ids: Iterable[int]) -> List[str]:
        """Return what is wrong with these motor IDs for this protocol (the configuration)."""
        return ['%s: motor ID %d is no standard CAN ID' % (self.name, i) for i in motor_ids
                if not 0 <= i <= MAX_STANDARD_ID]

    def mode_query_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Frames that ask the motors which control mode they are in (bring-up; none here)."""
        return []

    def mode_problem(self, frame: Frame) -> Optional[Tuple[int, Optional[str]]]:
        """
        Judge an answer to mode_query_frames: (motor ID, what is wrong and its fix, or None).

        None for a frame that is no such answer. Never raises.
        """
        return None

    def error_reason(self, code: int) -> str:
        """Return the meaning of the reply's error code ``code`` (not 0) in words."""
        return 'error code 0x%X' % int(code)

    def make_emulator(self, motor_id: int, **options) -> Any:
        """
        Return the emulated motor ``motor_id`` of this protocol (core/protocols/emulation.py).

        For the simulated robot and the fault rig; options are the emulator's.
        """
        raise NotImplementedError('no emulator for protocol %r here' % self.name)

    @classmethod
    def from_config(cls, section: Any) -> 'MotorProtocol':
        """Build the codec from its configuration section (codec_kwargs); None: defaults."""
        return cls() if section is None else cls(**section.codec_kwargs())

    @abstractmethod
    def enable_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Frames that put the motors into torque-control mode (arm)."""

    @abstractmethod
    def disable_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Frames that leave torque-control mode (disarm); the motors end up producing none."""

    @abstractmethod
    def torque_frames(self, torques: Dict[int, float]) -> List[Frame]:
        """Frames that command {motor_id: motor torque [N m]} (one control tick)."""

    @abstractmethod
    def zero_torque_frames(self, motor_ids: Iterable[int]) -> List[Frame]:
        """Frames that command zero torque to the motors while staying in torque mode."""

    @abstractmethod
    def decode_feedback(self, frame: Frame) -> Optional[MotorFeedback]:
        """Decode a motor's reply; None for a frame that is not one (never raises)."""

    @abstractmethod
    def command_motor_ids(self, frame: Frame) -> Tuple[int, ...]:
        """
        Return the IDs of the motors a frame commands, as their firmware would act on it.

        Empty for anything else, replies above all (a frame that looks like a command by its
        ID and length but is a reply is none). What tells the node that another sender on
        the bus commands its motors (core/balance_loop.py: input_conflict). Never raises.
        """

    def reply_motor_id(self, frame: Frame) -> Optional[int]:
        """
        Return the ID of the motor a reply comes from; None for a frame that is not one.

        Cheaper than decoding where the protocol allows (a bus carries other motors' replies
        too: each motor set decodes only its own). Never raises.
        """
        feedback = self.decode_feedback(frame)
        return None if feedback is None else feedback.motor_id

    def decode_reply(self, frame: Frame, motor_ids) -> Optional[MotorFeedback]:
        """
        Return the reply of one of ``motor_ids`` (a set or dict of IDs) decoded, else None.

        What a motor set calls for every received frame: a protocol may do it in one pass
        (the MIT codec does). Never raises.
        """
        feedback = self.decode_feedback(frame)   # once: reply_motor_id would decode too
        return feedback if feedback is not None and feedback.motor_id in motor_ids else None


def frame_bytes(frame: Frame, extended: bool = False) -> Optional[bytes]:
    """
    Return the data of a classic CAN frame as bytes (never raises).

    None unless the frame has the kind of ID asked for (standard; ``extended``: 29-bit) within
    its range and at most 8 bytes of data (every codec here also checks its own lengths).
    """
    try:
        if bool(frame.is_extended_id) != extended or not 0 <= frame.arbitration_id <= (
                MAX_EXTENDED_ID if extended else MAX_STANDARD_ID):
            return None
        if isinstance(frame.data, int):  # bytes(n) would make n zero bytes
            return None
        data = bytes(frame.data)
        return data if len(data) <= 8 else None
    except (AttributeError, TypeError, ValueError):
        return None
