r"""
Body attitude from the IMU: mounting, roll and pitch, gravity fallback, poses, pitch rate.

The IMU's mounting rotation, roll and pitch exact in any attitude, roll and pitch from the
gravity vector where the orientation is missing, pose classes for the safety supervisor, and the
Euler pitch rate under roll.

Frames (REP 103 and REP 145: x forward, y left, z up; an accelerometer at rest reads +g up):
world w (the IMU's reference, z up), the body b = base_link, the sensor i = the IMU's own frame.
sensor_msgs/Imu carries q_wi, the orientation of the IMU frame in the world (v_w = R(q_wi) v_i),
and angular_velocity omega_i and linear_acceleration f_i (specific force) in the IMU frame.

Mounting. ``imu_mounting_rpy`` = [roll, pitch, yaw] [rad] is the orientation of the IMU frame in
base_link, read as a URDF joint origin's rpy: R_bi = R_z(yaw) R_y(pitch) R_x(roll), so a vector
in IMU coordinates is v_b = R_bi v_i in body coordinates. Then R_wi = R_wb R_bi, hence::

    R_wb = R_wi R_bi^T,   q_wb = q_wi * q_bi^-1     (body orientation in the world)
    omega_b = R_bi omega_i,   f_b = R_bi f_i        (body-frame rates and specific force)

The rotation does not move the point where the accelerometer measures: the lever arm from
base_link's origin adds omega x (omega x r) + alpha x r (0.05 m/s^2 at 1 rad/s and r = 5 cm),
which is neglected.

Roll and pitch are the z-y'-x'' (yaw-pitch-roll) Euler angles, R_wb = R_z(yaw) R_y(pitch)
R_x(roll): theta = pitch > 0 leans forward, roll > 0 lifts the left side. Both follow from where
"up" lies in body coordinates alone, u = R_wb^T e_z = (-sin p, cos p sin r, cos p cos r)::

    roll = atan2(u_y, u_z),   pitch = atan2(-u_x, hypot(u_y, u_z)),

exact in every attitude: on its side (roll +-90 deg) the pitch is still the body x axis' angle
below the horizontal, upside down the roll is +-180 deg; only at pitch +-90 deg is roll undefined
(gimbal lock). The same formula serves the quaternion (u is its rotation matrix' third row) and
the accelerometer (u is the specific force's direction at rest).
"""
from enum import Enum
import math
from typing import NamedTuple, Sequence, Tuple

Quaternion = Tuple[float, float, float, float]  # (x, y, z, w), sensor_msgs order
Vector = Tuple[float, float, float]

NAN = math.nan
#: Quaternions whose norm is farther than this from 1 are implausible (roll, pitch NaN).
QUATERNION_NORM_TOLERANCE = 0.1
#: A specific force whose norm differs from the expected hypot(a, g) by more than this fraction
#: of g (a free fall, a bump) does not show where up is (roll, pitch NaN).
GRAVITY_NORM_TOLERANCE = 0.25
#: Pitch of the robot resting on its tail [rad] (about 36 deg; sim/robot.xml draws it so).
TAIL_PITCH = math.radians(36.0)


def quaternion_from_rpy(roll: float, pitch: float, yaw: float) -> Quaternion:
    """
    Quaternion (x, y, z, w) of R_z(yaw) R_y(pitch) R_x(roll) (URDF rpy, tf2 setRPY) [rad].

    The same rotation as z-y'-x'' Euler angles (yaw, pitch, roll).
    """
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return (sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy)


def quaternion_multiply(a: Quaternion, b: Quaternion) -> Quaternion:
    """Hamilton product a * b of (x, y, z, w) quaternions: rotate by b, then by a."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


def quaternion_conjugate(q: Quaternion) -> Quaternion:
    """Conjugate (the inverse of a unit quaternion)."""
    x, y, z, w = q
    return (-x, -y, -z, w)


def rotation_matrix(q: Quaternion) -> Tuple[Vector, Vector, Vector]:
    """Rows of the rotation matrix of a unit quaternion (x, y, z, w)."""
    x, y, z, w = q
    return ((1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)),
            (2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)),
            (2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)))


class ImuMounting:
    """
    The IMU's mounting in base_link: rotates its readings into the body frame.

    rpy: ``imu_mounting_rpy`` [roll, pitch, yaw] [rad], the IMU frame's orientation in
    base_link (see the module docstring). Raises ValueError for anything but three finite
    numbers (a parameter check); the per-sample methods never raise and pass NaN through.
    """

    def __init__(self, rpy: Sequence[float] = (0.0, 0.0, 0.0)):
        values = [float(v) for v in rpy]
        if len(values) != 3 or not all(math.isfinite(v) for v in values):
            raise ValueError('imu_mounting_rpy must be three finite angles [rad]')
        self.rpy = tuple(values)
        self.q_bi = quaternion_from_rpy(*values)
        self._q_ib = quaternion_conjugate(self.q_bi)
        self._r_bi = rotation_matrix(self.q_bi)
        #: No rotation (rpy all zero): the readings are the body's as they are (a sample a
        #: tick skips the product with the identity, which changes no value).
        self.unrotated = values == [0.0, 0.0, 0.0]

    def orientation_to_body(self, q_wi: Quaternion) -> Quaternion:
        """Body orientation in the world q_wb = q_wi * q_bi^-1 from the IMU's q_wi (x, y, z, w)."""
        return quaternion_multiply(q_wi, self._q_ib)

    def vector_to_body(self, v_i: Sequence[float]) -> Vector:
        """Rotate an IMU-frame vector (angular velocity, specific force) to base_link: R_bi v_i."""
        x, y, z = v_i
        r0, r1, r2 = self._r_bi
        return (r0[0] * x + r0[1] * y + r0[2] * z,
                r1[0] * x + r1[1] * y + r1[2] * z,
                r2[0] * x + r2[1] * y + r2[2] * z)


def roll_pitch_from_up(ux: float, uy: float, uz: float) -> Tuple[float, float]:
    """
    (roll, pitch) [rad] from the world's up direction in body coordinates (any length > 0).

    Euler z-y'-x'': roll in [-pi, pi], pitch in [-pi/2, pi/2] (module docstring).
    """
    return math.atan2(uy, uz), math.atan2(-ux, math.hypot(uy, uz))


def orientation_absent(q: Quaternion, covariance0: float = 0.0) -> bool:
    """
    Tell whether the driver says it has no orientation, rather than sending a broken one.

    True for sensor_msgs/Imu's orientation_covariance[0] == -1 and for the all-zero quaternion
    (what drivers without a fusion filter leave in the message).
    """
    if covariance0 == -1.0:
        return True
    try:
        return all(float(v) == 0.0 for v in q)
    except (TypeError, ValueError):
        return False


def orientation_valid(q: Quaternion, covariance0: float = 0.0) -> bool:
    """
    Tell whether an Imu orientation can be used.

    False when the IMU says it has none (orientation_covariance[0] == -1, sensor_msgs/Imu's
    convention), a component is not finite, or the norm differs from 1 by more than
    QUATERNION_NORM_TOLERANCE (e.g. the all-zero quaternion).
    """
    if covariance0 == -1.0:
        return False
    x, y, z, w = q
    n2 = x * x + y * y + z * z + w * w
    return math.isfinite(n2) and abs(math.sqrt(n2) - 1.0) <= QUATERNION_NORM_TOLERANCE


def roll_pitch_from_quaternion(x: float, y: float, z: float, w: float) -> Tuple[float, float]:
    """
    Body (roll, pitch) [rad] of an orientation quaternion (x, y, z, w), exact in any attitude.

    The quaternion need not be normalized (u scales with its squared norm, atan2 does not
    care). (NaN, NaN) when it is implausible (see orientation_valid).
    """
    if not orientation_valid((x, y, z, w)):
        return NAN, NAN
    # Third row of the (unnormalized) rotation matrix: up in body coordinates.
    return roll_pitch_from_up(2.0 * (x * z - w * y), 2.0 * (y * z + w * x),
                              w * w - x * x - y * y + z * z)


def roll_pitch_from_gravity(f: Sequence[float], forward_acceleration: float = 0.0,
                            lateral_acceleration: float = 0.0,
                            gravity: float = 9.81) -> Tuple[float, float]:
    """
    Body (roll, pitch) [rad] from the body-frame specific force f [m/s^2] (an accelerometer).

    forward_acceleration a_x and lateral_acceleration a_y [m/s^2]: the robot's own horizontal
    acceleration along its heading and to its left, e.g. d(x_dot)/dt of the wheel odometry and
    x_dot * yaw_rate in a turn. Uncorrected, a forward acceleration a tilts the apparent up by
    atan(a/g) forwards, which reads as leaning *back*: upright at a = 2 m/s^2, the raw pitch is
    atan2(-2, 9.81) = -11.5 deg. The correction solves f = R^T (a_x, a_y, g) (heading axes) for
    roll and pitch exactly::

        rho = hypot(f_y, f_z),   roll = atan2(f_y, f_z) - asin(a_y / rho),
        pitch = atan2(a_x, g) + atan2(-f_x, sqrt(rho^2 - a_y^2)),

    valid while the body is not tipped beyond horizontal (g cos(pitch) + a_x sin(pitch) > 0).
    (NaN, NaN) when f is not finite or |f| is farther than GRAVITY_NORM_TOLERANCE g from
    hypot(a_x, a_y, g) (a free fall, a hit, or a wrong acceleration estimate).
    """
    fx, fy, fz = (float(v) for v in f)
    ax, ay, g = float(forward_acceleration), float(lateral_acceleration), float(gravity)
    norm = math.sqrt(fx * fx + fy * fy + fz * fz)
    expected = math.sqrt(ax * ax + ay * ay + g * g)
    if not (abs(norm - expected) <= GRAVITY_NORM_TOLERANCE * g):  # False for NaN
        return NAN, NAN
    rho2 = fy * fy + fz * fz
    rho = math.sqrt(rho2)
    roll = math.atan2(fy, fz)
    if ay != 0.0:
        roll -= math.asin(min(1.0, max(-1.0, ay / rho))) if rho > 0.0 else 0.0
        roll = (roll + math.pi) % (2.0 * math.pi) - math.pi
    pitch = math.atan2(ax, g) + math.atan2(-fx, math.sqrt(max(0.0, rho2 - ay * ay)))
    return roll, min(max(pitch, -0.5 * math.pi), 0.5 * math.pi)


def pitch_rate(omega_y: float, omega_z: float, roll: float) -> float:
    """
    Euler pitch rate theta_dot [rad/s] from the body-frame gyro (omega_y, omega_z) [rad/s].

    theta_dot = omega_y cos(roll) - omega_z sin(roll), exact for z-y'-x'' angles; at roll 0 it
    is omega_y. (The wheel encoders' stators turn with the body about its y axis at omega_y, so
    the odometry's pitch-rate correction takes omega_y, not this.)
    """
    return omega_y * math.cos(roll) - omega_z * math.sin(roll)


def yaw_rate(omega_y: float, omega_z: float, roll: float, pitch: float) -> float:
    """
    Euler yaw rate psi_dot [rad/s] (about the world vertical) from the body-frame gyro [rad/s].

    psi_dot = (omega_y sin(roll) + omega_z cos(roll)) / cos(pitch), exact for z-y'-x'' angles;
    upright it is omega_z. The robot's true turn rate, which the wheels' speeds overstate when
    they scrub or slip in a turn on the spot.
    """
    return (omega_y * math.sin(roll) + omega_z * math.cos(roll)) / math.cos(pitch)


class Attitude(NamedTuple):
    """Body roll and pitch [rad] and where they came from ('orientation', 'gravity', 'none')."""

    roll: float
    pitch: float
    source: str


def body_attitude(mounting: ImuMounting, orientation: Quaternion, covariance0: float,
                  linear_acceleration: Sequence[float], forward_acceleration: float = 0.0,
                  lateral_acceleration: float = 0.0, gravity: float = 9.81) -> Attitude:
    """
    Roll and pitch of base_link from one Imu sample, never raising.

    The orientation (rotated by the mounting) when orientation_valid; where the driver has none
    (orientation_absent), the gravity vector in linear_acceleration corrected for the robot's
    own acceleration (roll_pitch_from_gravity); else NaN with source 'none'. A broken
    orientation (not finite, not of unit norm) is 'none', not gravity: a driver that sends
    garbage in one field is not trusted in the others.
    """
    try:
        if covariance0 != -1.0:
            # orientation_valid, the mounting's orientation_to_body (quaternion_multiply) and
            # roll_pitch_from_quaternion inlined, the same operations (a sample a tick). The
            # sqrt of a NaN or inf norm fails the comparison, as math.isfinite would.
            x, y, z, w = orientation
            if abs(math.sqrt(x * x + y * y + z * z + w * w) - 1.0) <= QUATERNION_NORM_TOLERANCE:
                if mounting.unrotated:   # q_wi * (0, 0, 0, 1) is q_wi, of unit norm already
                    qx, qy, qz, qw, unit = x, y, z, w, True
                else:
                    bx, by, bz, bw = mounting._q_ib
                    qx = w * bx + x * bw + y * bz - z * by
                    qy = w * by - x * bz + y * bw + z * bx
                    qz = w * bz + x * by - y * bx + z * bw
                    qw = w * bw - x * bx - y * by - z * bz
                    unit = abs(math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw) - 1.0) \
                        <= QUATERNION_NORM_TOLERANCE
                if unit:
                    # Up in body coordinates (roll_pitch_from_up).
                    uy, uz = 2.0 * (qy * qz + qw * qx), qw * qw - qx * qx - qy * qy + qz * qz
                    roll = math.atan2(uy, uz)
                    if roll == roll:
                        return _attitude(Attitude, (roll, math.atan2(
                            -(2.0 * (qx * qz - qw * qy)), math.hypot(uy, uz)), 'orientation'))
        if not orientation_absent(orientation, covariance0):
            return Attitude(NAN, NAN, 'none')
        f_b = mounting.vector_to_body(linear_acceleration)
        roll, pitch = roll_pitch_from_gravity(f_b, forward_acceleration, lateral_acceleration,
                                              gravity)
    except (TypeError, ValueError, OverflowError):
        return Attitude(NAN, NAN, 'none')
    if roll == roll and pitch == pitch:
        return Attitude(roll, pitch, 'gravity')
    return Attitude(NAN, NAN, 'none')


#: An Attitude from a tuple of its fields without NamedTuple's __new__ (a Python call).
_attitude = tuple.__new__


# ---- poses for the safety supervisor -------------------------------------------------------

class Pose(Enum):
    """What the attitude says the robot is doing (classify_pose)."""

    UPRIGHT = 'upright'          # balancing range: |pitch| and |roll| small
    ON_TAIL = 'on_tail'          # resting on the tail: the safe state
    ON_SIDE = 'on_side'          # |roll| beyond fall_roll_angle, body z still above horizontal
    UPSIDE_DOWN = 'upside_down'  # body z axis below the horizontal
    TILTED = 'tilted'            # none of the above (fallen forward or back, in between)
    UNKNOWN = 'unknown'          # roll or pitch not finite


def is_upright(roll: float, pitch: float, max_pitch: float, fall_roll_angle: float) -> bool:
    """|pitch| <= max_pitch and |roll| < fall_roll_angle [rad]; False for NaN."""
    return abs(pitch) <= max_pitch and abs(roll) < fall_roll_angle


def is_on_tail(roll: float, pitch: float, tail_pitch: float = TAIL_PITCH,
               pitch_tolerance: float = math.radians(10.0),
               roll_tolerance: float = math.radians(10.0)) -> bool:
    """Resting on the tail: |pitch - tail_pitch| <= pitch_tolerance, |roll| <= roll_tolerance."""
    return abs(pitch - tail_pitch) <= pitch_tolerance and abs(roll) <= roll_tolerance


def is_upside_down(roll: float, pitch: float) -> bool:
    """Tell whether the body z axis points below the horizontal (cos(pitch) cos(roll) < 0)."""
    return math.cos(pitch) * math.cos(roll) < 0.0


def classify_pose(roll: float, pitch: float, max_pitch: float, fall_roll_angle: float,
                  tail_pitch: float = TAIL_PITCH, tail_pitch_tolerance: float = math.radians(10.0),
                  tail_roll_tolerance: float = math.radians(10.0)) -> Pose:
    """
    Classify an attitude (roll, pitch) [rad] for the safety supervisor.

    max_pitch: |pitch| of the upright (balancing) range; fall_roll_angle: |roll| beyond which
    the robot lies on a side; tail_*: the tail rest window (is_on_tail). The tail is tested
    before upright, so a pose inside both windows is ON_TAIL.
    """
    if not (math.isfinite(roll) and math.isfinite(pitch)):
        return Pose.UNKNOWN
    if is_upside_down(roll, pitch):
        return Pose.UPSIDE_DOWN
    if is_on_tail(roll, pitch, tail_pitch, tail_pitch_tolerance, tail_roll_tolerance):
        return Pose.ON_TAIL
    if is_upright(roll, pitch, max_pitch, fall_roll_angle):
        return Pose.UPRIGHT
    if abs(roll) >= fall_roll_angle:
        return Pose.ON_SIDE
    return Pose.TILTED
