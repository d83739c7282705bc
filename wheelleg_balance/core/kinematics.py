r"""
Five-bar (parallel) leg: body height l from the two hip motor angles, and back.

The paper (Sec. II-A, V-A) computes the height l "in real-time using the angles of body motors
and the lengths of leg links". Each leg is a planar five-bar linkage: two hip motors on the
body, a thigh on each, and two shanks that meet at the wheel axle. Both legs move together, so
one leg gives l.

Geometry, in the leg plane of the body frame (REP 103: x forward, z up), seen from the robot's
right side (x to the right), origin at the midpoint between the two hip axes::

                         * COM  (com_x, com_z), above the hip midpoint by default
                         :
       rear hip  o-------+-------o  front hip          z ^
               .'   hip_spacing   '.                     |
      q_rear  /  thigh      thigh  \  q_front            +--> x (forward)
             o rear knee   front knee o
              \                      /
               \ shank        shank /
                \                  /
                 \                /
                  '.            .'
                    '---(O)----'   wheel axle (xc, zc)
                         :
        l = com_z - zc   (vertical distance from the axle up to the COM)

Angle conventions. q_front is the angle of the front thigh *below the forward horizontal*
(thigh direction (cos q, -sin q)); that is a positive rotation about the body y axis.
q_rear is the mirror image: the angle of the rear thigh below the *backward* horizontal
(direction (-cos q, -sin q)), a positive rotation about -y. So zero means the thigh points
horizontally away from the other hip, positive turns it down, and a symmetric stance has
q_front == q_rear. The node maps the motors' joint_states to these angles (offset and sign).
Working mode: knees outward (front knee ahead of the front hip-axle line, rear knee behind),
axle below the knees.

Default links (thigh 0.30 m, shank 0.42 m, hips 0.10 m apart, COM 0.05 m above the hips) give
l = 0.37 m at q = 0.25 rad and l = 0.70 m at q = 1.12 rad in the symmetric stance, inside
the joint limits [-0.2, 1.6] rad with room for the axle to move +-0.1 m fore and aft.
"""
import math
from typing import Tuple

NAN = math.nan
_ANGLE_TOL = 1e-9  # [rad] rounding allowance at the joint limits


class FiveBarLeg:
    """Forward and inverse kinematics of the five-bar leg (see the module docstring)."""

    def __init__(self, thigh: float = 0.30, shank: float = 0.42, hip_spacing: float = 0.10,
                 com_height: float = 0.05, com_x: float = 0.0,
                 q_min: float = -0.2, q_max: float = 1.6):
        """
        Build a leg.

        thigh, shank: link lengths [m] (both legs of the five-bar alike); hip_spacing: distance
        between the two hip motor axes [m]; com_height, com_x: position of the body's centre of
        mass relative to the hip midpoint [m] (up, forward); q_min, q_max: hip joint limits
        [rad] in the convention of the module docstring, the same for both hips.
        """
        if not (thigh > 0.0 and shank > 0.0 and hip_spacing >= 0.0 and q_min < q_max):
            raise ValueError('invalid five-bar geometry')
        self.thigh = float(thigh)
        self.shank = float(shank)
        self.hip_spacing = float(hip_spacing)
        self.com_height = float(com_height)
        self.com_x = float(com_x)
        self.q_min = float(q_min)
        self.q_max = float(q_max)
        self._half = 0.5 * self.hip_spacing

    def _knees(self, q_front: float, q_rear: float):
        a, h = self.thigh, self._half
        return (h + a * math.cos(q_front), -a * math.sin(q_front),
                -h - a * math.cos(q_rear), -a * math.sin(q_rear))

    def in_reach(self, q_front: float, q_rear: float) -> bool:
        """Tell whether both angles [rad] are finite, within limits, and the shanks can meet."""
        lo, hi = self.q_min, self.q_max
        if not (lo <= q_front <= hi and lo <= q_rear <= hi):  # False for NaN too
            return False
        fx, fz, rx, rz = self._knees(q_front, q_rear)
        d = math.hypot(fx - rx, fz - rz)
        return 0.0 < d <= 2.0 * self.shank

    def forward(self, q_front: float, q_rear: float) -> Tuple[float, float]:
        """
        Forward kinematics: (x, l) [m] of the wheel axle for hip angles q_front, q_rear [rad].

        x is the axle's horizontal offset ahead of the COM, l its depth below the COM. The axle
        is the lower intersection of the two shank circles around the knees. Returns (nan, nan)
        when not in_reach.
        """
        if not self.in_reach(q_front, q_rear):
            return NAN, NAN
        fx, fz, rx, rz = self._knees(q_front, q_rear)
        dx, dz = fx - rx, fz - rz
        d = math.hypot(dx, dz)
        ex, ez = dx / d, dz / d
        half_chord = math.sqrt(max(0.0, self.shank * self.shank - 0.25 * d * d))
        # (ez, -ex) is the downward normal when the front knee is ahead of the rear one.
        xc = 0.5 * (fx + rx) + half_chord * ez
        zc = 0.5 * (fz + rz) - half_chord * ex
        return xc - self.com_x, self.com_height - zc

    def height(self, q_front: float, q_rear: float) -> float:
        """Return the body height l [m] (axle to COM, body-vertical); nan when out of reach."""
        return self.forward(q_front, q_rear)[1]

    def inverse(self, l: float, x: float = 0.0) -> Tuple[float, float]:
        """
        Inverse kinematics: hip angles (q_front, q_rear) [rad] for an axle position.

        The axle goes l [m] below the COM and x [m] ahead of it, knees outward. Returns
        (nan, nan) when the point is out of reach or needs an angle outside [q_min, q_max].
        """
        xc = x + self.com_x
        zc = self.com_height - l
        q_front = self._hip_angle(xc - self._half, zc)
        q_rear = self._hip_angle(-(xc + self._half), zc)
        lo, hi = self.q_min - _ANGLE_TOL, self.q_max + _ANGLE_TOL
        if not (lo <= q_front <= hi and lo <= q_rear <= hi):
            return NAN, NAN
        # Rounding can put an angle a hair outside a limit it really sits on.
        return (min(max(q_front, self.q_min), self.q_max),
                min(max(q_rear, self.q_min), self.q_max))

    def _hip_angle(self, px: float, pz: float) -> float:
        """
        Angle below the outward horizontal of the thigh that reaches the axle.

        (px, pz) is the axle relative to the hip, with px measured outward (forward for the
        front hip, backward for the rear one), so both hips share this formula.
        """
        a, b = self.thigh, self.shank
        d2 = px * px + pz * pz
        d = math.sqrt(d2) if d2 == d2 else NAN
        if not (abs(a - b) <= d <= a + b) or d == 0.0:
            return NAN
        t = (a * a - b * b + d2) / (2.0 * d)       # along hip -> axle
        h = math.sqrt(max(0.0, a * a - t * t))     # perpendicular, towards the outside
        ux, uz = px / d, pz / d
        kx = t * ux - h * uz
        kz = t * uz + h * ux
        return math.atan2(-kz, kx)
