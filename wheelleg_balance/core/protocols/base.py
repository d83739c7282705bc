"""
The interface every CAN motor protocol implements (pure bytes: no python-can here).

A protocol turns wheel-motor torques into CAN frames and motor replies into MotorFeedback.
The node wraps ``Frame`` into ``can.Message`` and back; the controllers never see a protocol,
so a new motor family is one new module here (see docs/can_protocols.md).
Torques are motor torques [N m] with the mounting direction already applied
(core/actuation.py); positions [rad] and velocities [rad/s] are at the motor's output shaft.
"""
from abc import ABC, abstractmethod
from typing import Dict, Iterable, List, NamedTuple, Optional, Tuple

#: Largest standard (11-bit) CAN identifier.
MAX_STANDARD_ID = 0x7FF


class Frame(NamedTuple):
    """A classic CAN data frame: 11-bit (or 29-bit when is_extended_id) ID and 0..8 bytes."""

    arbitration_id: int
    data: bytes
    is_extended_id: bool = False


class MotorFeedback(NamedTuple):
    """
    One motor's reply.

    motor_id: the motor's ID on the bus; position [rad]; velocity [rad/s]; torque [N m]
    (output shaft, motor direction); temperature [deg C] or None when the frame carries none;
    error: the motor's error code or None when the frame carries none.
    """

    motor_id: int
    position: float
    velocity: float
    torque: float
    temperature: Optional[float] = None
    error: Optional[int] = None


class MotorProtocol(ABC):
    """
    Encoder/decoder of one motor family's CAN frames.

    Every method is total: encoders never raise for any float (non-finite torques become
    zero torque, out-of-range ones are clamped), and decode_feedback returns None for a frame
    that is not a well-formed reply of this protocol.
    """

    #: Short name, the value of the node's ``can.protocol`` parameter.
    name = ''

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
        if self.reply_motor_id(frame) not in motor_ids:
            return None
        return self.decode_feedback(frame)


def frame_bytes(frame: Frame) -> Optional[bytes]:
    """Return a standard frame's data as bytes; None if extended or malformed (never raises)."""
    try:
        if frame.is_extended_id or not 0 <= frame.arbitration_id <= MAX_STANDARD_ID:
            return None
        if isinstance(frame.data, int):  # bytes(n) would make n zero bytes
            return None
        return bytes(frame.data)
    except (AttributeError, TypeError, ValueError):
        return None
