"""The sensor intake's IMU decoder (nodes/imu_cdr.py) against rclpy's own serialization."""
import math
import struct

from hypothesis import given, settings, strategies as st
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Imu

from wheelleg_balance.nodes.imu_cdr import imu_sample_from_cdr
from wheelleg_balance.nodes.sensor_intake import imu_sample

ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True, width=64)


def make_imu(frame_id: str, sec: int = 1796500000, nanosec: int = 123456789, values=None,
             no_orientation: bool = False) -> Imu:
    msg = Imu()
    msg.header.frame_id = frame_id
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    v = list(values) if values is not None else [0.01 * k for k in range(10)]
    o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
    o.x, o.y, o.z, o.w = v[0:4]
    w.x, w.y, w.z = v[4:7]
    a.x, a.y, a.z = v[7:10]
    msg.orientation_covariance[1] = 0.5    # the decoder must not read a neighbour's field
    msg.angular_velocity_covariance[0] = -7.0
    msg.linear_acceleration_covariance[8] = 3.0
    if no_orientation:
        msg.orientation_covariance[0] = -1.0
    return msg


def same(a, b) -> bool:
    """Tuples equal field by field, NaN equal to NaN."""
    return len(a) == len(b) and all(
        x == y or (isinstance(x, float) and isinstance(y, float) and math.isnan(x)
                   and math.isnan(y)) for x, y in zip(a, b))


def test_every_frame_id_length_decodes_as_rclpy_converts():
    # The string's length moves the float64 block through every alignment (padding 0..7).
    for n in range(0, 17):
        for no_orientation in (False, True):
            msg = make_imu('i' * n, sec=-3 + n, nanosec=999999999 - n,
                           no_orientation=no_orientation)
            data = serialize_message(msg)
            assert data[:2] == b'\x00\x01'   # CDR little endian, as rmw_fastrtps writes
            got = imu_sample_from_cdr(data, 12.5, 1796500000.25)
            assert got == imu_sample(msg, 12.5, 1796500000.25), n
            assert got.orientation_valid is not no_orientation


def test_a_big_endian_message_decodes_too():
    msg = make_imu('imu_link', values=[0.1, -0.2, 0.3, 0.9, 1.5, -2.5, 3.5, 0.5, -0.25, 9.81])
    name = b'imu_link\x00'
    head = struct.pack('>iII', msg.header.stamp.sec, msg.header.stamp.nanosec, len(name)) + name
    head += bytes(-len(head) % 8)
    floats = ([msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w]
              + list(msg.orientation_covariance)
              + [msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z]
              + list(msg.angular_velocity_covariance)
              + [msg.linear_acceleration.x, msg.linear_acceleration.y,
                 msg.linear_acceleration.z] + list(msg.linear_acceleration_covariance))
    data = b'\x00\x00\x00\x00' + head + struct.pack('>37d', *floats)
    assert imu_sample_from_cdr(data, 1.0, 2.0) == imu_sample(msg, 1.0, 2.0)


def test_what_is_not_plain_cdr_is_left_to_rclpy():
    data = serialize_message(make_imu('imu_link'))
    # XCDR2 (encapsulation 0x0007 / 0x0011 ...) aligns float64 to 4: not guessed at.
    assert imu_sample_from_cdr(b'\x00\x07' + data[2:], 0.0, 0.0) is None
    assert imu_sample_from_cdr(b'\x00\x11' + data[2:], 0.0, 0.0) is None
    for cut in (0, 1, 3, 10, 20, len(data) - 1):
        assert imu_sample_from_cdr(data[:cut], 0.0, 0.0) is None, cut
    # A string length that runs past the end of the buffer.
    bad = data[:12] + struct.pack('<I', 10 ** 6) + data[16:]
    assert imu_sample_from_cdr(bad, 0.0, 0.0) is None


@settings(max_examples=2000, deadline=None)
@given(values=st.lists(ANY_FLOAT, min_size=10, max_size=10),
       frame_id=st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=0x2FF),
                        max_size=40),
       sec=st.integers(-2 ** 31, 2 ** 31 - 1), nanosec=st.integers(0, 2 ** 32 - 1),
       no_orientation=st.booleans())
def test_any_message_decodes_as_rclpy_converts_it(values, frame_id, sec, nanosec,
                                                  no_orientation):
    # Any values, NaN and infinities included, and frame_ids of multi-byte UTF-8.
    msg = make_imu(frame_id, sec, nanosec, values, no_orientation)
    got = imu_sample_from_cdr(serialize_message(msg), 3.0, 4.0)
    assert got is not None and same(got, imu_sample(msg, 3.0, 4.0))
