"""Body attitude from the IMU (core/attitude.py): mounting, roll and pitch, gravity, poses."""
import math

from hypothesis import assume, given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from wheelleg_balance.core.attitude import (
    body_attitude, classify_pose, ImuMounting, is_on_tail, is_upright, pitch_rate, Pose,
    quaternion_from_rpy, roll_pitch_from_gravity, roll_pitch_from_quaternion, TAIL_PITCH)
from wheelleg_balance.core.estimation import pitch_from_quaternion

G = 9.81
DEG = math.pi / 180.0
angle = st.floats(-math.pi, math.pi)


def _rot(roll, pitch, yaw=0.0):
    """R_z(yaw) R_y(pitch) R_x(roll) by scipy (an independent implementation)."""
    return Rotation.from_euler('ZYX', [yaw, pitch, roll])


def _wrap(a):
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def _same_angle(a, b, tol):
    return abs(_wrap(a - b)) <= tol


def _imu_reading(r_wb, omega_b, f_b, mounting_rpy):
    """Return what an IMU mounted at mounting_rpy in base_link reports for a body state."""
    r_bi = _rot(*mounting_rpy)
    q_wi = tuple((r_wb * r_bi).as_quat())  # scalar last: sensor_msgs order
    return q_wi, r_bi.inv().apply(omega_b), r_bi.inv().apply(f_b)


# ---- quaternion and Euler angles -------------------------------------------------------------

@settings(max_examples=300, deadline=None)
@given(roll=angle, pitch=st.floats(-1.55, 1.55), yaw=angle)
def test_quaternion_from_rpy_is_scipys_zyx(roll, pitch, yaw):
    q = np.array(quaternion_from_rpy(roll, pitch, yaw))
    ref = _rot(roll, pitch, yaw).as_quat()
    assert min(np.abs(q - ref).max(), np.abs(q + ref).max()) < 1e-12


@settings(max_examples=500, deadline=None)
@given(roll=angle, pitch=st.floats(-1.45, 1.45), yaw=angle)
def test_euler_quaternion_euler_round_trip_away_from_gimbal_lock(roll, pitch, yaw):
    r, p = roll_pitch_from_quaternion(*quaternion_from_rpy(roll, pitch, yaw))
    assert p == pytest.approx(pitch, abs=1e-9)
    assert _same_angle(r, roll, 1e-9)


@pytest.mark.filterwarnings('ignore:Gimbal lock')  # scipy's, for the cases assume() drops
@settings(max_examples=300, deadline=None)
@given(q=st.tuples(*[st.floats(-1.0, 1.0)] * 4))
def test_roll_pitch_match_scipy_for_any_orientation(q):
    n = math.sqrt(sum(c * c for c in q))
    assume(n > 0.1)
    q = tuple(c / n for c in q)
    _, pitch, roll = Rotation.from_quat(q).as_euler('ZYX')
    assume(abs(pitch) < 1.5)  # roll is undefined at gimbal lock
    r, p = roll_pitch_from_quaternion(*q)
    assert p == pytest.approx(pitch, abs=1e-9)
    assert _same_angle(r, roll, 1e-8)


def test_on_its_side_reads_roll_90_and_is_not_upright():
    q = quaternion_from_rpy(math.pi / 2, 0.0, 0.3)
    roll, pitch = roll_pitch_from_quaternion(*q)
    assert roll == pytest.approx(math.pi / 2, abs=1e-12)
    assert pitch == pytest.approx(0.0, abs=1e-12)
    # Pitch alone (what the node used) reads this robot as upright.
    assert pitch_from_quaternion(*q) == pytest.approx(0.0, abs=1e-12)
    assert not is_upright(roll, pitch, max_pitch=20 * DEG, fall_roll_angle=30 * DEG)
    assert classify_pose(roll, pitch, 20 * DEG, 30 * DEG) is Pose.ON_SIDE
    # Lying on its side with the nose down 20 deg: the pitch is still exact.
    roll, pitch = roll_pitch_from_quaternion(*quaternion_from_rpy(-math.pi / 2, 20 * DEG, 0.0))
    assert (roll, pitch) == pytest.approx((-math.pi / 2, 20 * DEG), abs=1e-12)


def test_upside_down_reads_roll_180():
    roll, pitch = roll_pitch_from_quaternion(*quaternion_from_rpy(math.pi, 0.1, -1.0))
    assert abs(roll) == pytest.approx(math.pi, abs=1e-12)
    assert pitch == pytest.approx(0.1, abs=1e-12)
    assert classify_pose(roll, pitch, 20 * DEG, 30 * DEG) is Pose.UPSIDE_DOWN


@pytest.mark.parametrize('q', [
    (0.0, 0.0, 0.0, 0.0), (0.0, 0.2, 0.0, 1.2), (math.nan, 0.0, 0.0, 1.0),
    (0.0, math.inf, 0.0, 1.0), (1e200, 1e200, 0.0, 0.0)])
def test_implausible_quaternions_give_nan(q):
    assert all(math.isnan(v) for v in roll_pitch_from_quaternion(*q))


# ---- IMU mounting --------------------------------------------------------------------------

BODY_RPY = (0.12, 0.3, 0.7)           # body roll, pitch, yaw in the world [rad]
BODY_OMEGA = np.array([0.2, -0.5, 0.3])  # body-frame angular velocity [rad/s]


@pytest.mark.parametrize('mounting', [
    (0.0, 0.0, math.pi),          # yawed 180 deg: x backwards
    (math.pi / 2, 0.0, 0.0),      # rolled 90 deg: the board stands on its edge
    (math.pi, 0.0, 0.0),          # upside down
    (math.pi, 0.0, math.pi / 2),  # upside down and turned
])
def test_mounted_imu_gives_the_body_attitude_and_rates(mounting):
    r_wb = _rot(*BODY_RPY)
    f_b = r_wb.inv().apply([0.0, 0.0, G])  # at rest: up, +g
    q_wi, omega_i, f_i = _imu_reading(r_wb, BODY_OMEGA, f_b, mounting)
    m = ImuMounting(mounting)
    roll, pitch = roll_pitch_from_quaternion(*m.orientation_to_body(q_wi))
    assert (roll, pitch) == pytest.approx(BODY_RPY[:2], abs=1e-12)
    omega = m.vector_to_body(omega_i)
    assert omega == pytest.approx(BODY_OMEGA, abs=1e-12)
    assert m.vector_to_body(f_i) == pytest.approx(f_b, abs=1e-12)
    att = body_attitude(m, q_wi, 0.0, f_i)
    assert (att.roll, att.pitch, att.source) == pytest.approx((*BODY_RPY[:2], 'orientation'))
    # Without its orientation the IMU's gravity vector gives the same attitude.
    att = body_attitude(m, q_wi, -1.0, f_i)
    assert att.source == 'gravity'
    assert (att.roll, att.pitch) == pytest.approx(BODY_RPY[:2], abs=1e-12)
    # Read as if mounted straight, the same IMU gets the attitude wrong.
    wrong = roll_pitch_from_quaternion(*q_wi)
    assert max(abs(_wrap(wrong[0] - BODY_RPY[0])), abs(wrong[1] - BODY_RPY[1])) > 0.2


def test_yawed_180_flips_the_pitch_sign_unless_mounted():
    r_wb = _rot(0.0, 0.2)
    q_wi, omega_i, _ = _imu_reading(r_wb, [0.0, 0.4, 0.0], [0.0, 0.0, G], (0.0, 0.0, math.pi))
    assert roll_pitch_from_quaternion(*q_wi)[1] == pytest.approx(-0.2, abs=1e-12)
    assert omega_i[1] == pytest.approx(-0.4, abs=1e-12)
    m = ImuMounting((0.0, 0.0, math.pi))
    assert roll_pitch_from_quaternion(*m.orientation_to_body(q_wi))[1] == \
        pytest.approx(0.2, abs=1e-12)
    assert m.vector_to_body(omega_i)[1] == pytest.approx(0.4, abs=1e-12)


@settings(max_examples=300, deadline=None)
@given(body=st.tuples(angle, st.floats(-1.4, 1.4), angle),
       mounting=st.tuples(angle, st.floats(-1.5, 1.5), angle))
def test_any_mounting_any_attitude(body, mounting):
    r_wb = _rot(*body)
    f_b = r_wb.inv().apply([0.0, 0.0, G])
    q_wi, omega_i, f_i = _imu_reading(r_wb, BODY_OMEGA, f_b, mounting)
    m = ImuMounting(mounting)
    for cov in (0.0, -1.0):  # from the orientation, then from gravity
        att = body_attitude(m, q_wi, cov, f_i)
        assert att.pitch == pytest.approx(body[1], abs=1e-9)
        assert _same_angle(att.roll, body[0], 1e-8)
    assert m.vector_to_body(omega_i) == pytest.approx(BODY_OMEGA, abs=1e-12)


@pytest.mark.parametrize('rpy', [(0.0, 0.0), (0.0, 0.0, math.nan), (0.0, 'a', 0.0),
                                 (0.0, 0.0, 0.0, 0.0)])
def test_bad_mounting_is_rejected(rpy):
    with pytest.raises((ValueError, TypeError)):
        ImuMounting(rpy)


# ---- gravity fallback ----------------------------------------------------------------------

@settings(max_examples=500, deadline=None)
@given(roll=angle, pitch=st.floats(-1.5, 1.5), yaw=angle)
def test_gravity_agrees_with_the_quaternion_at_rest(roll, pitch, yaw):
    r_wb = _rot(roll, pitch, yaw)
    f_b = r_wb.inv().apply([0.0, 0.0, G])
    r_g, p_g = roll_pitch_from_gravity(f_b)
    r_q, p_q = roll_pitch_from_quaternion(*r_wb.as_quat())
    assert p_g == pytest.approx(p_q, abs=1e-9)
    assert _same_angle(r_g, r_q, 1e-8)


def test_forward_acceleration_tilts_gravity_and_the_correction_removes_it():
    # Upright, accelerating forward at 2 m/s^2: the specific force points forward and up.
    f_b = (2.0, 0.0, G)
    raw_roll, raw_pitch = roll_pitch_from_gravity(f_b)
    # It looks like leaning *back* by atan(a/g).
    assert raw_pitch == pytest.approx(-math.atan2(2.0, G), abs=1e-12)
    assert math.degrees(raw_pitch) == pytest.approx(-11.52, abs=0.01)
    assert roll_pitch_from_gravity(f_b, forward_acceleration=2.0) == \
        pytest.approx((0.0, 0.0), abs=1e-12)
    # Leaning forward 0.1 rad while accelerating: the correction is exact under pitch too.
    f_b = _rot(0.0, 0.1).inv().apply([2.0, 0.0, G])
    assert roll_pitch_from_gravity(f_b, 2.0)[1] == pytest.approx(0.1, abs=1e-12)
    assert roll_pitch_from_gravity(f_b)[1] == pytest.approx(0.1 - math.atan2(2.0, G), abs=1e-12)


@settings(max_examples=500, deadline=None)
@given(roll=st.floats(-1.2, 1.2), pitch=st.floats(-1.2, 1.2), yaw=angle,
       a_x=st.floats(-5.0, 5.0), a_y=st.floats(-5.0, 5.0))
def test_acceleration_correction_is_exact_in_any_upright_half(roll, pitch, yaw, a_x, a_y):
    assume(G * math.cos(pitch) + a_x * math.sin(pitch) > 0.5)
    r_wb = _rot(roll, pitch, yaw)
    # Horizontal acceleration along the heading (a_x) and to its left (a_y), world axes.
    heading = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    left = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    f_b = r_wb.inv().apply(a_x * heading + a_y * left + [0.0, 0.0, G])
    r_g, p_g = roll_pitch_from_gravity(f_b, a_x, a_y)
    assert p_g == pytest.approx(pitch, abs=1e-9)
    assert r_g == pytest.approx(roll, abs=1e-9)


def test_a_left_turn_reads_as_rolled_right_unless_corrected():
    # 1 m/s at 2 rad/s: centripetal 2 m/s^2 to the left, upright body.
    f_b = (0.0, 2.0, G)
    assert roll_pitch_from_gravity(f_b)[0] == pytest.approx(math.atan2(2.0, G), abs=1e-12)
    assert roll_pitch_from_gravity(f_b, 0.0, 2.0) == pytest.approx((0.0, 0.0), abs=1e-12)


@pytest.mark.parametrize('f', [(0.0, 0.0, 0.0), (0.0, 0.0, 2 * G), (0.0, 0.0, math.nan),
                               (math.inf, 0.0, G), (0.0, 0.0, 0.5 * G)])
def test_gravity_that_is_not_gravity_gives_nan(f):
    assert all(math.isnan(v) for v in roll_pitch_from_gravity(f))


def test_a_wrong_acceleration_estimate_is_caught_by_the_norm():
    assert all(math.isnan(v) for v in roll_pitch_from_gravity((0.0, 0.0, G), 8.0))


# ---- body_attitude never raises ------------------------------------------------------------

def test_source_order_orientation_gravity_none():
    m = ImuMounting()
    q = quaternion_from_rpy(0.0, 0.2, 0.0)
    f = tuple(_rot(0.0, 0.3).inv().apply([0.0, 0.0, G]))
    assert body_attitude(m, q, 0.01, f) == pytest.approx((0.0, 0.2, 'orientation'))
    assert body_attitude(m, q, -1.0, f) == pytest.approx((0.0, 0.3, 'gravity'))
    assert body_attitude(m, (0.0, 0.0, 0.0, 0.0), 0.0, f) == pytest.approx((0.0, 0.3, 'gravity'))
    att = body_attitude(m, (0.0, 0.0, 0.0, 0.0), 0.0, (0.0, 0.0, 0.0))
    assert att.source == 'none' and math.isnan(att.roll) and math.isnan(att.pitch)


@pytest.mark.parametrize('q', [(0.0, 0.5 * math.nan, 0.0, 1.0), (0.0, 0.0, 0.0, 0.5),
                               (0.0, 0.0, math.inf, 1.0), (1.0, 1.0, 1.0, 1.0)])
def test_broken_orientation_is_not_replaced_by_gravity(q):
    f = tuple(_rot(0.0, 0.3).inv().apply([0.0, 0.0, G]))
    att = body_attitude(ImuMounting(), q, 0.01, f)
    assert att.source == 'none' and math.isnan(att.pitch)


finite_or_not = st.floats(allow_nan=True, allow_infinity=True)


@settings(max_examples=2000, deadline=None)
@given(q=st.tuples(*[finite_or_not] * 4), cov=finite_or_not, f=st.tuples(*[finite_or_not] * 3),
       a_x=finite_or_not, a_y=finite_or_not, mounting=st.tuples(angle, angle, angle))
def test_body_attitude_never_raises(q, cov, f, a_x, a_y, mounting):
    att = body_attitude(ImuMounting(mounting), q, cov, f, a_x, a_y)
    if att.source == 'none':
        assert math.isnan(att.roll) and math.isnan(att.pitch)
    else:
        assert -math.pi <= att.roll <= math.pi and -math.pi / 2 <= att.pitch <= math.pi / 2


@pytest.mark.parametrize('bad', [None, (1.0, 2.0), 'abcd'])
def test_body_attitude_survives_wrong_types(bad):
    att = body_attitude(ImuMounting(), bad, 0.0, bad)
    assert att.source == 'none'


# ---- pitch rate ----------------------------------------------------------------------------

@settings(max_examples=300, deadline=None)
@given(rpy=st.tuples(angle, st.floats(-1.3, 1.3), angle),
       rates=st.tuples(*[st.floats(-3.0, 3.0)] * 3))
def test_pitch_rate_is_the_euler_rate_under_roll(rpy, rates):
    # Body angular velocity of an Euler-angle motion, by finite differences of scipy rotations.
    h = 1e-6
    r0 = _rot(*rpy)
    r1 = _rot(*(a + h * v for a, v in zip(rpy, rates)))
    omega_b = (r0.inv() * r1).as_rotvec() / h
    assert pitch_rate(omega_b[1], omega_b[2], rpy[0]) == pytest.approx(rates[1], abs=1e-4)


def test_pitch_rate_on_its_side_comes_from_the_body_z_gyro():
    # Rolled 90 deg to the left side up, the body pitching forward turns about body -z.
    assert pitch_rate(0.0, -0.5, math.pi / 2) == pytest.approx(0.5, abs=1e-12)
    assert pitch_rate(0.7, 0.0, 0.0) == 0.7


# ---- poses ---------------------------------------------------------------------------------

@pytest.mark.parametrize('roll,pitch,pose', [
    (0.0, 0.0, Pose.UPRIGHT),
    (25 * DEG, -15 * DEG, Pose.UPRIGHT),
    (0.0, TAIL_PITCH, Pose.ON_TAIL),
    (5 * DEG, TAIL_PITCH - 8 * DEG, Pose.ON_TAIL),
    (0.0, TAIL_PITCH + 15 * DEG, Pose.TILTED),      # beyond the tail: fallen forward
    (15 * DEG, TAIL_PITCH, Pose.TILTED),            # on the tail but tipping sideways
    (0.0, -60 * DEG, Pose.TILTED),                  # fallen backwards
    (30 * DEG, 0.0, Pose.ON_SIDE),                  # the fall_roll_angle itself
    (-90 * DEG, 10 * DEG, Pose.ON_SIDE),
    (95 * DEG, 0.0, Pose.UPSIDE_DOWN),
    (180 * DEG, 0.0, Pose.UPSIDE_DOWN),
    (math.nan, 0.0, Pose.UNKNOWN),
    (0.0, math.inf, Pose.UNKNOWN),
])
def test_classify_pose(roll, pitch, pose):
    assert classify_pose(roll, pitch, max_pitch=20 * DEG, fall_roll_angle=30 * DEG) is pose


def test_tail_window_is_the_arguments():
    assert is_on_tail(0.0, 0.5, tail_pitch=0.5)
    assert not is_on_tail(0.0, 0.5 + 11 * DEG, tail_pitch=0.5)
    assert is_on_tail(0.0, 0.5 + 11 * DEG, tail_pitch=0.5, pitch_tolerance=12 * DEG)
    assert not is_on_tail(math.nan, 0.5, tail_pitch=0.5)
    assert not is_upright(0.0, math.nan, 1.0, 1.0)


@settings(max_examples=200, deadline=None)
@given(rpy=st.tuples(*[st.floats(-3.0, 3.0)] * 3),
       gyro=st.tuples(*[st.one_of(st.floats(-20.0, 20.0),
                                  st.sampled_from([math.inf, -math.inf, math.nan]))] * 3),
       valid=st.booleans())
def test_an_unrotated_mounting_reads_as_the_rotation_by_the_identity(rpy, gyro, valid):
    # The unrotated mounting's shortcut (no product with the identity) against the general
    # path through the same mounting: the same attitude, rates and gyro (NaN where an
    # infinite rate makes the product's NaN).
    from wheelleg_balance.core.sensors import ImuReader, ImuSample
    q = quaternion_from_rpy(*rpy)
    sample = ImuSample(1.0, 1, 0, *q, valid, *gyro, 0.3, -0.2, 9.7, 1.0)
    fast, general = ImuReader(), ImuReader()
    assert fast.mounting.unrotated and not ImuMounting((0.0, 0.1, 0.0)).unrotated
    general.mounting.unrotated = False
    assert fast.take(sample) and general.take(sample)
    assert fast.source == general.source
    for name in ('theta', 'roll', 'theta_dot', 'yaw_rate', 'gyro'):
        assert np.array_equal(getattr(fast, name), getattr(general, name), equal_nan=True), name
