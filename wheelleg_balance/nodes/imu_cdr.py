"""
sensor_msgs/Imu read straight from its serialized form, for the sensor intake (no rclpy).

rclpy's conversion of a taken message into Python objects builds a header, a quaternion, three
vectors and three 9-element covariance arrays per sample; the tick uses 13 numbers of it. The
intake therefore takes the IMU message serialized (``take_message(..., raw=True)``) and unpacks
those numbers with one ``struct`` call, which at 500 Hz takes about a third off the intake's
CPU time (docs/benchmarks.md, "The loop with six motors").

The layout is the OMG CDR encoding (XCDR version 1) that rmw_fastrtps writes for ROS 2 messages
(Fast CDR, "DDS-XTypes 1.3" 7.4.1, OMG "CORBA 3.4 Part 2" 9.3 for the alignment rules):

- a 4-byte encapsulation header: ``00 01`` little endian (CDR_LE), ``00 00`` big endian
  (CDR_BE), then two option bytes;
- then the fields in declaration order, each aligned to its own size counted from the end of
  the header: ``header.stamp.sec`` int32, ``header.stamp.nanosec`` uint32, ``header.frame_id``
  string (uint32 length including the terminating NUL, then the bytes), then 37 float64 aligned
  to 8: orientation x y z w, orientation_covariance[9], angular_velocity x y z, its
  covariance[9], linear_acceleration x y z, its covariance[9].

Anything else (another encapsulation such as XCDR2's, a buffer too short for its string) gives
None, and the intake falls back to rclpy's deserializer: a decoder that guessed would hand the
tick wrong numbers.
"""
import struct
from typing import Optional

from ..core.sensors import ImuSample

#: Encapsulation identifier -> struct byte order.
_BYTE_ORDER = {b'\x00\x01': '<', b'\x00\x00': '>'}
_ENCAPSULATION = 4
#: stamp.sec, stamp.nanosec, frame_id's length.
_HEAD = {order: struct.Struct(order + 'iII') for order in _BYTE_ORDER.values()}
#: orientation, its covariance, angular_velocity, its covariance, linear_acceleration, its
#: covariance.
_BODY = {order: struct.Struct(order + '37d') for order in _BYTE_ORDER.values()}
#: Indices into the 37 float64 of _BODY.
_Q, _Q_COV0, _W, _A = 0, 4, 13, 25


def imu_sample_from_cdr(data: bytes, t: float, clock: float) -> Optional[ImuSample]:
    """
    Return the ImuSample of a serialized sensor_msgs/Imu received at monotonic ``t`` [s].

    clock: the receiving node's clock at receipt [s] (ImuSample.clock). None when ``data`` is
    not plain CDR (see the module docstring) or too short; never raises.
    """
    order = _BYTE_ORDER.get(data[:2])
    if order is None:
        return None
    try:
        sec, nanosec, length = _HEAD[order].unpack_from(data, _ENCAPSULATION)
        # Past the string, aligned to 8 from the end of the encapsulation header.
        body = _ENCAPSULATION + ((12 + length + 7) & ~7)
        v = _BODY[order].unpack_from(data, body)
    except struct.error:
        return None
    return ImuSample(t, sec, nanosec, v[_Q], v[_Q + 1], v[_Q + 2], v[_Q + 3],
                     v[_Q_COV0] != -1.0,   # sensor_msgs: -1 = no orientation estimate
                     v[_W], v[_W + 1], v[_W + 2], v[_A], v[_A + 1], v[_A + 2], clock)
