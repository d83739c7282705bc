"""
The tick's sensor inputs as plain numbers, and what each sample says (no rclpy).

The ROS side reduces a message to a small tuple once, on receipt (the shape crosses a process
boundary cheaply: nodes/control_link.py); the readers here turn those tuples into the
measurements the tick uses:

- ``ImuSample`` (sensor_msgs/Imu): orientation, its validity, angular velocity, linear
  acceleration, header stamp and receipt time. ``ImuReader`` drops a sample that repeats the
  previous header stamp (a driver republishing one reading: it must go stale, not look fresh)
  and gives theta~ and the roll from the whole orientation (or from gravity where the
  orientation is missing), rotated by the IMU's mounting, and theta_dot (core/attitude.py).
- ``JointSample`` (sensor_msgs/JointState, already matched by joint name by
  ``JointStateReader.reduce``): the wheels' velocities, forward positive, and the four hip
  angles in FiveBarLeg's convention, giving the height l through the five-bar kinematics.
"""
import math
from typing import NamedTuple, Optional, Sequence, Tuple

from .attitude import body_attitude, ImuMounting
from .kinematics import FiveBarLeg

NAN = math.nan


class ImuSample(NamedTuple):
    """
    One IMU message.

    t: monotonic receipt time [s]; stamp_sec, stamp_nanosec: header stamp; qx..qw: orientation
    of the IMU frame (REP 103); orientation_valid: False when the driver says it has no
    orientation estimate (orientation_covariance[0] == -1); wx, wy, wz: angular velocity [rad/s]
    and ax, ay, az: linear acceleration [m/s^2], both in the IMU frame; clock: the receiving
    node's clock (ROS time) at receipt [s], NaN when not known (the stamp is then not compared
    with it).
    """

    t: float
    stamp_sec: int
    stamp_nanosec: int
    qx: float
    qy: float
    qz: float
    qw: float
    orientation_valid: bool
    wx: float
    wy: float
    wz: float
    ax: float = 0.0
    ay: float = 0.0
    az: float = 0.0
    clock: float = NAN


class ImuReader:
    """
    The newest IMU measurement in the body frame (base_link), with its receipt time [s].

    theta: pitch theta~ [rad] (the body's pitch plus the IMU's unknown offset d, which the
    observer estimates); roll [rad]; both from the whole orientation rotated by the mounting,
    or from gravity where the orientation is missing (core/attitude.py); theta_dot: the Euler
    pitch rate [rad/s]; gyro: the body-frame angular velocity (x, y, z) [rad/s]; source:
    'orientation', 'gravity' or 'none'. ``frozen`` counts samples dropped for repeating the
    previous header stamp. mounting: ``imu_mounting_rpy`` [rad]. specific_force: the norm of
    the linear acceleration [m/s^2] (about g at rest, near 0 in free fall; NaN before the
    first sample and for exact zeros, what a driver without an accelerometer sends). A sample
    whose stamp runs backwards, or lies ahead of the node's clock by more than
    ``stamp_tolerance`` [s], is refused (``refused_stamps``, ``refused_reason``): it goes stale
    instead of being used.
    """

    def __init__(self, mounting=(0.0, 0.0, 0.0), gravity: float = 9.81,
                 stamp_tolerance: float = 0.1):
        self.mounting = ImuMounting(mounting)
        self.gravity = gravity
        self.time: Optional[float] = None
        self.theta = NAN
        self.roll = NAN
        self.theta_dot = NAN
        self.gyro = (NAN, NAN, NAN)
        #: Yaw rate about the world vertical from the gyro [rad/s] (attitude.yaw_rate).
        self.yaw_rate = NAN
        self.specific_force = NAN
        self.source = 'none'
        self.frozen = 0
        self._stamp: Optional[int] = None   # the previous header stamp [ns]
        self.stamp_tolerance = stamp_tolerance
        self.refused_stamps = 0
        self.refused_reason = ''

    def take(self, s: ImuSample, forward_acceleration: float = 0.0) -> bool:
        """
        Take a sample; return False when it was dropped (a repeated stamp).

        forward_acceleration [m/s^2]: the robot's own, for the gravity fallback.
        """
        t, sec, nanosec, qx, qy, qz, qw, valid, wx, wy, wz, ax, ay, az, clock = s
        # One integer [ns]: a pair compares wrongly when nanosec is not normalised (>= 1e9).
        stamp = sec * 1_000_000_000 + nanosec
        last = self._stamp
        if stamp == last and stamp != 0:
            # A driver republishing one sample: keep the first receipt time so it goes stale.
            self.frozen += 1
            return False
        # Unstamped drivers (0): receipt time only. _stamp_problem's two tests, asked here
        # first (it words the reason).
        if stamp != 0 and ((last is not None and last != 0 and stamp < last)
                           or 1e-9 * stamp - clock > self.stamp_tolerance):
            self.refused_stamps += 1
            self.refused_reason = self._stamp_problem(stamp, clock)
            return False
        self._stamp = stamp
        self.time = t
        mounting = self.mounting
        roll, pitch, self.source = body_attitude(mounting, (qx, qy, qz, qw),
                                                 0.0 if valid else -1.0, (ax, ay, az),
                                                 forward_acceleration, 0.0, self.gravity)
        self.theta, self.roll = pitch, roll
        force = math.sqrt(ax * ax + ay * ay + az * az)
        self.specific_force = force if force > 0.0 else NAN
        # mounting.vector_to_body, pitch_rate and yaw_rate inlined (the same operations). An
        # unrotated mounting's identity changes no finite rate; its zeros turn an infinite one
        # into NaN in the other two, which the checks must see: those take the product.
        if mounting.unrotated and (wx - wx) + (wy - wy) + (wz - wz) == 0.0:
            omega_y, omega_z = wy, wz
            self.gyro = (wx, wy, wz)
        else:
            r0, r1, r2 = mounting._r_bi
            omega_y = r1[0] * wx + r1[1] * wy + r1[2] * wz
            omega_z = r2[0] * wx + r2[1] * wy + r2[2] * wz
            self.gyro = (r0[0] * wx + r0[1] * wy + r0[2] * wz, omega_y, omega_z)
        if roll == roll:
            cos_r, sin_r = math.cos(roll), math.sin(roll)
            self.theta_dot = omega_y * cos_r - omega_z * sin_r
            self.yaw_rate = (omega_y * sin_r + omega_z * cos_r) / math.cos(pitch)
        else:
            self.theta_dot, self.yaw_rate = omega_y, omega_z
        return True

    @property
    def stamp_ns(self) -> Optional[int]:
        """Return the header stamp of the newest sample taken [ns] (None before the first)."""
        return self._stamp

    def _stamp_problem(self, stamp: int, clock: float) -> Optional[str]:
        """Return why a header stamp [ns] is refused (backwards, or ahead of the clock)."""
        if self._stamp is not None and self._stamp != 0 and stamp < self._stamp:
            return 'IMU stamp ran backwards: %.9f s after %.9f s' % (1e-9 * stamp,
                                                                     1e-9 * self._stamp)
        ahead = 1e-9 * stamp - clock
        if ahead > self.stamp_tolerance:   # False for a NaN clock
            return ('IMU stamp %.3f s ahead of our clock (stamp_tolerance %.3f s)'
                    % (ahead, self.stamp_tolerance))
        return None


class JointSample(NamedTuple):
    """
    What one JointState message says about the joints the tick uses.

    t: monotonic receipt time [s]; has_wheels: the message carries both wheels; w_left,
    w_right: their velocities relative to the leg, forward positive [rad/s]; has_legs: it
    carries the four configured hips; l: the body height from them [m] (NaN when out of the
    legs' reach).
    """

    t: float
    has_wheels: bool
    w_left: float
    w_right: float
    has_legs: bool
    l: float


class JointStateReader:
    """
    Reduces a JointState message to a JointSample by the configured joint names.

    wheels: (left name, right name); wheel_directions: (+-1, +-1) from the joint's velocity to
    forward positive; legs: per leg (front name, rear name, front direction, rear direction,
    front offset, rear offset), empty for no hips (q = offset + direction * position).
    """

    def __init__(self, wheels: Tuple[str, str], wheel_directions: Tuple[int, int],
                 legs: Sequence[Tuple[str, str, int, int, float, float]] = (),
                 leg: Optional[FiveBarLeg] = None):
        self.wheels = tuple(wheels)
        self.wheel_directions = tuple(wheel_directions)
        self.legs = tuple(legs)
        self.leg = leg or FiveBarLeg()

    def reduce(self, t: float, names: Sequence[str], position: Sequence[float],
               velocity: Sequence[float]) -> Optional[JointSample]:
        """Return the sample of one message, or None when it carries none of our joints."""
        has_wheels = has_legs = False
        w_l = w_r = l = NAN
        try:
            i_l = names.index(self.wheels[0])
            i_r = names.index(self.wheels[1])
            w_l = float(self.wheel_directions[0] * velocity[i_l])
            w_r = float(self.wheel_directions[1] * velocity[i_r])
            has_wheels = True
        except (ValueError, IndexError, TypeError):
            pass  # a message without our wheels (e.g. from another publisher)
        if self.legs:
            try:
                total = 0.0
                for front, rear, d_f, d_r, o_f, o_r in self.legs:
                    q_front = o_f + d_f * position[names.index(front)]
                    q_rear = o_r + d_r * position[names.index(rear)]
                    total += self.leg.height(q_front, q_rear)
                l = total / len(self.legs)
                has_legs = True
            except (ValueError, IndexError, TypeError):
                pass
        if not (has_wheels or has_legs):
            return None
        return JointSample(t, has_wheels, w_l, w_r, has_legs, l)
