"""
State estimation from the IMU and the wheel encoders (paper Sec. V-A).

Conventions (REP 103): x forward, y left, z up; theta > 0 = body leans forward, which is a
positive rotation about the body y axis; yaw rate > 0 turns left (counter-clockwise seen from
above). Wheel angular velocities are forward positive (after the motor direction mapping of
core/actuation.py) and measured by the motor encoders, i.e. *relative to the leg*.

Ground speed and the pitch-rate correction (docs/interface.md, "The model"). The wheel's
stator sits on the leg, and the leg pitches with the body (the leg joints hold their angles
while balancing), so the encoder reads w_rel = w_abs - theta_dot, where w_abs is the wheel's
rotation rate about y in the world. Rolling without slipping gives x_dot = r_w w_abs (rolling
forward is a positive rotation about y, the same sense as a forward lean). Hence

    x_dot = r_w ((w_l + w_r) / 2 + theta_dot),

whereas the paper's x_dot = r_w (w_r + w_l) / 2 reads r_w theta_dot of pure pitching as motion
(about 0.1 m/s per rad/s of pitch rate with r_w = 0.1 m). Both wheels see the same theta_dot, so
the yaw rate r_w (w_r - w_l) / d_w is unaffected.
"""
import math
from typing import Tuple

from .attitude import roll_pitch_from_quaternion
from .params import RobotParams


def pitch_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """
    Pitch theta [rad] of an orientation quaternion (REP 103, sensor_msgs/Imu order x, y, z, w).

    The pitch of the z-y'-x'' (yaw-pitch-roll) Euler decomposition: the angle of the body x
    axis below the horizontal plane, in [-pi/2, pi/2], positive when the body leans forward
    (positive rotation about y). It does not depend on yaw and is exact under roll too; it does
    not tell a robot on its side from an upright one (core/attitude.py gives the roll as well).
    Returns NaN when a component is not finite or the norm differs from 1 by more than
    core/attitude.py QUATERNION_NORM_TOLERANCE (e.g. the all-zero quaternion of an IMU that
    publishes no orientation), so the safety layer can reject the sample.
    """
    return roll_pitch_from_quaternion(x, y, z, w)[1]


def pitch_rate_from_gyro(angular_velocity_y: float) -> float:
    """
    Pitch rate theta_dot [rad/s] from the gyro's body-frame angular velocity about y.

    sensor_msgs/Imu.angular_velocity is in the IMU (body) frame. The Euler pitch rate is
    omega_y cos(roll) - omega_z sin(roll); the robot balances with roll near zero (the paper
    reports at most 19 deg on a one-sided slope, a 6 % error there), so theta_dot = omega_y,
    which is also the rate the wheel encoders see the leg turn at (see WheelOdometry).
    """
    return float(angular_velocity_y)


class WheelOdometry:
    """
    Wheel odometry of Sec. V-A with the pitch-rate correction, plus planar dead reckoning.

    update() returns, per tick k:
      x_dot_k = r_w ((w_l + w_r)/2 + theta_dot)   (the paper's formula without the
                                                   theta_dot term when pitch_correction=False),
      yaw_rate_k = r_w (w_r - w_l) / d_w           (positive turns left),
      x_k = x_{k-1} + dt x_dot_{k-1}               (the paper's explicit integration).
    The pose (x_world, y_world, yaw) for nav_msgs/Odometry is integrated with the same previous
    velocities, the heading taken at the middle of the step (second-order on circles), so the
    path length equals |x| when driving one way.
    A non-finite velocity is returned as is (the caller sees it) but integrated as zero, so one
    bad sample does not poison x and the pose for good.
    """

    def __init__(self, p: RobotParams = RobotParams(), pitch_correction: bool = True):
        self.p = p
        self.pitch_correction = pitch_correction
        self.reset()

    def reset(self) -> None:
        """Set x, the pose and the previous velocities to zero."""
        self._x_world = 0.0
        self._y_world = 0.0
        self._yaw = 0.0
        self.reset_travel()

    def reset_travel(self) -> None:
        """Set x and the previous velocities to zero (on arm); the odom pose goes on."""
        self._x = 0.0
        self._x_dot_prev = 0.0
        self._yaw_rate_prev = 0.0
        self.x_dot = 0.0
        self.yaw_rate = 0.0

    def update(self, w_left: float, w_right: float, theta_dot: float,
               dt: float) -> Tuple[float, float, float]:
        """
        Advance one tick.

        w_left, w_right: wheel angular velocities relative to the leg, forward positive [rad/s];
        theta_dot: pitch rate [rad/s]; dt: time since the previous tick [s] (a non-positive or
        non-finite dt integrates nothing). Returns (x [m], x_dot [m/s], yaw_rate [rad/s]).
        """
        if 0.0 < dt < math.inf:   # NaN fails the comparison
            ds = dt * self._x_dot_prev
            yaw = self._yaw
            dyaw = dt * self._yaw_rate_prev
            heading = yaw + 0.5 * dyaw
            self._x += ds
            self._x_world += ds * math.cos(heading)
            self._y_world += ds * math.sin(heading)
            self._yaw = (yaw + dyaw + math.pi) % (2.0 * math.pi) - math.pi   # into [-pi, pi)
        p = self.p
        r_w = p.wheel_radius
        w_mean = 0.5 * (w_left + w_right)
        x_dot = r_w * (w_mean + theta_dot) if self.pitch_correction else r_w * w_mean
        yaw_rate = r_w * (w_right - w_left) / p.wheel_separation
        self.x_dot = x_dot
        self.yaw_rate = yaw_rate
        self._x_dot_prev = x_dot if math.isfinite(x_dot) else 0.0
        self._yaw_rate_prev = yaw_rate if math.isfinite(yaw_rate) else 0.0
        return self._x, x_dot, yaw_rate

    @property
    def x(self) -> float:
        """Return the travelled distance x [m] along the body's forward axis since reset."""
        return self._x

    @property
    def pose(self) -> Tuple[float, float, float]:
        """Return the planar odom pose: x_world [m], y_world [m], yaw [rad] in [-pi, pi)."""
        return self._x_world, self._y_world, self._yaw
