r"""
Transforms for TF: odom -> base_footprint -> base_link (REP 105, REP 120), as plain tuples.

Each transform is (translation (x, y, z) [m], rotation (x, y, z, w)): the child frame's pose in
the parent frame, as geometry_msgs/TransformStamped carries it.

- odom: the world-fixed frame of the wheel odometry (core/estimation.py WheelOdometry.pose).
- base_footprint: on the floor under the wheel-axle midpoint, x along the heading, z up; it
  yaws with the robot but never pitches. The odometry integrates the axle midpoint's motion,
  so odom -> base_footprint is that pose.
- base_link: the body, origin at the midpoint between the hip axes (urdf/wheelleg_balance.urdf,
  sim/robot.xml), pitched by theta. Its origin sits above and, when pitched or with the axle off
  centre, ahead of or behind the footprint::

      t = (0, 0, r_w) + R_y(theta) (-axle_x, 0, -axle_z),   rotation R_y(theta),

  where (axle_x, axle_z) is the wheel axle in base_link (core/kinematics.py FiveBarLeg.axle;
  with the height l alone, (com_x + x, com_height - l)). Upright at l = 0.37 m with the default
  leg that is 0.1 + 0.32 = 0.42 m, robot.xml's start height of base_link.
"""
import math
from typing import Tuple

from .attitude import Quaternion, quaternion_from_rpy, Vector

Transform = Tuple[Vector, Quaternion]


def odom_to_base_footprint(x: float, y: float, yaw: float) -> Transform:
    """Return odom -> base_footprint from the odometry pose x, y [m], yaw [rad]."""
    return (float(x), float(y), 0.0), quaternion_from_rpy(0.0, 0.0, yaw)


def base_footprint_to_base_link(theta: float, axle_x: float, axle_z: float,
                                wheel_radius: float) -> Transform:
    """
    Return base_footprint -> base_link.

    theta: body pitch [rad] (> 0 leans forward); axle_x, axle_z: the wheel axle's position in
    base_link [m] (x forward, z up; FiveBarLeg.axle); wheel_radius r_w [m].
    """
    # R_y(theta) applied to (-axle_x, 0, -axle_z): the hip midpoint seen from the axle.
    c, s = math.cos(theta), math.sin(theta)
    return ((-c * axle_x - s * axle_z, 0.0, wheel_radius + s * axle_x - c * axle_z),
            quaternion_from_rpy(0.0, theta, 0.0))
