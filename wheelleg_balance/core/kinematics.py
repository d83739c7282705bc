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
from typing import Optional, Tuple

NAN = math.nan
#: ((dx/dq_front, dx/dq_rear), (dl/dq_front, dl/dq_rear)) [m/rad].
Jacobian = Tuple[Tuple[float, float], Tuple[float, float]]
_ANGLE_TOL = 1e-9  # [rad] rounding allowance at the joint limits
#: How far a *measured* hip angle may lie beyond a joint limit and still be a leg [rad]: a hard
#: stop gives a little under load (and an encoder reads a little off); the inverse kinematics
#: keeps to the limits themselves.
STOP_MARGIN = 0.05
#: Solved linkage poses (and Jacobians) kept per leg: a tick needs two to four.
_POSES_KEPT = 16
_UNSOLVED = object()


def _keep(store: dict, key, value):
    """Keep value under key in store (up to _POSES_KEPT entries, then cleared); return it."""
    if len(store) >= _POSES_KEPT:
        store.clear()
    store[key] = value
    return value


def _jacobian(pose, dfx: float, dfz: float, drx: float, drz: float, singular: float):
    """
    Return the Jacobian of a solved pose (fx, fz, rx, rz, xc, zc) [m], None when singular.

    (dfx, dfz), (drx, drz): the front and rear knee's velocities per unit hip rate [m/rad].
    From the closure of the two shanks: each keeps its length, so (P - K_i) . (dP - dK_i/dq_i
    dq_i) = 0 for the axle P and knee K_i, two linear equations in dP; ``singular``: the
    determinant [m^2] below which the shanks count as in line.
    """
    fx, fz, rx, rz, xc, zc = pose
    # Shank vectors knee -> axle.
    ufx, ufz = xc - fx, zc - fz
    urx, urz = xc - rx, zc - rz
    bf = ufx * dfx + ufz * dfz
    br = urx * drx + urz * drz
    det = ufx * urz - ufz * urx
    if abs(det) < singular:
        return None
    # [ufx ufz; urx urz] dP = diag(bf, br) dq  ->  dP = A^-1 B dq.
    dxc_f, dxc_r = urz * bf / det, -ufz * br / det
    dzc_f, dzc_r = -urx * bf / det, ufx * br / det
    return (dxc_f, dxc_r), (-dzc_f, -dzc_r)   # l = com_height - zc


def force_at(j: Optional[Jacobian], tau_front: float, tau_rear: float) -> Tuple[float, float]:
    """
    Return FiveBarLeg.leg_force at a pose of Jacobian j: (f_x, f_l) [N] (nan, nan: j None).

    For a caller that holds the pose's Jacobian already (core/legs.py, the state's).
    """
    if j is None:
        return NAN, NAN
    (a, b), (c, d) = j
    det = a * d - b * c
    if det == 0.0 or not math.isfinite(det):
        return NAN, NAN
    return (d * tau_front - c * tau_rear) / det, (a * tau_rear - b * tau_front) / det


def _knee_angles(pose, q_front: float, q_rear: float) -> Tuple[float, float]:
    """Return FiveBarLeg.knee_angles of a solved pose (fx, fz, rx, rz, xc, zc) [m]."""
    fx, fz, rx, rz, xc, zc = pose
    phi = math.atan2(-(zc - fz), xc - fx)      # front shank below the forward horizontal
    psi = math.atan2(-(zc - rz), -(xc - rx))   # rear shank below the backward horizontal
    return phi - q_front, psi - q_rear


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
        # Constants of the solves (the geometry is fixed once built), in the same operations.
        a, b = self.thigh, self.shank
        self._reach = (self.q_min - STOP_MARGIN, self.q_max + STOP_MARGIN, 2.0 * b, b * b,
                       1e-9 * b * b)
        self._ik = (abs(a - b), a + b, a * a - b * b, a * a,
                    self.q_min - _ANGLE_TOL, self.q_max + _ANGLE_TOL)
        #: (q_front, q_rear) -> (pose, Jacobian) of _linkage, or measure's (pose, Jacobian, l,
        #: knees) for measured angles.
        self._solutions: dict = {}
        #: The last hip_command's height [m] with its angles and Jacobian (a held height).
        self._held = (NAN, None)

    def _knees(self, q_front: float, q_rear: float):
        a, h = self.thigh, self._half
        return (h + a * math.cos(q_front), -a * math.sin(q_front),
                -h - a * math.cos(q_rear), -a * math.sin(q_rear))

    def in_reach(self, q_front: float, q_rear: float) -> bool:
        """Tell whether both angles [rad] are finite, at the limits, and the shanks can meet."""
        lo, hi = self.q_min - STOP_MARGIN, self.q_max + STOP_MARGIN
        if not (lo <= q_front <= hi and lo <= q_rear <= hi):  # False for NaN too
            return False
        fx, fz, rx, rz = self._knees(q_front, q_rear)
        d = math.hypot(fx - rx, fz - rz)
        return 0.0 < d <= 2.0 * self.shank

    def axle(self, q_front: float, q_rear: float) -> Tuple[float, float]:
        """
        Position (x, z) [m] of the wheel axle in the hip-midpoint frame (base_link).

        x forward, z up: the lower intersection of the two shank circles around the knees.
        Returns (nan, nan) when not in_reach.
        """
        pose = self._pose(q_front, q_rear)
        return (NAN, NAN) if pose is None else (pose[4], pose[5])

    def forward(self, q_front: float, q_rear: float) -> Tuple[float, float]:
        """
        Forward kinematics: (x, l) [m] of the wheel axle for hip angles q_front, q_rear [rad].

        x is the axle's horizontal offset ahead of the COM, l its depth below the COM (body
        axes). Returns (nan, nan) when not in_reach.
        """
        xc, zc = self.axle(q_front, q_rear)
        return xc - self.com_x, self.com_height - zc

    def pose(self, q_front: float, q_rear: float) -> Tuple[float, ...]:
        """
        Return the knees and the axle (fx, fz, rx, rz, xc, zc) [m] in the hip-midpoint frame.

        x forward, z up; all NaN when not in_reach. Where the links are (the mass of the
        legs in identification/fit.py).
        """
        pose = self._pose(q_front, q_rear)
        return (NAN,) * 6 if pose is None else pose

    def _pose(self, q_front: float, q_rear: float):
        """Return knees and axle (fx, fz, rx, rz, xc, zc), hip-midpoint frame; None: no reach."""
        return self._solution(q_front, q_rear)[0]

    def _solution(self, q_front: float, q_rear: float):
        """Return _linkage(q_front, q_rear), kept: a tick asks for the same angles again."""
        key = (q_front, q_rear)
        solution = self._solutions.get(key)
        if solution is None:
            solution = _keep(self._solutions, key, self._linkage(q_front, q_rear))
        return solution

    def _linkage(self, q_front: float, q_rear: float):
        """
        Solve the linkage at hip angles [rad]: (pose, Jacobian), see _pose and jacobian.

        (None, None) when not in_reach; (pose, None) when singular (the shanks in line).
        """
        lo, hi, reach, b2, singular = self._reach
        if not (lo <= q_front <= hi and lo <= q_rear <= hi):  # False for NaN too
            return None, None
        a, h = self.thigh, self._half
        sf, cf, sr, cr = math.sin(q_front), math.cos(q_front), math.sin(q_rear), math.cos(q_rear)
        fx, fz, rx, rz = h + a * cf, -a * sf, -h - a * cr, -a * sr   # the knees
        dx, dz = fx - rx, fz - rz
        d = math.hypot(dx, dz)
        if not 0.0 < d <= reach:
            return None, None
        ex, ez = dx / d, dz / d
        chord2 = b2 - 0.25 * d * d   # (half the chord)^2, >= 0 bar rounding
        half_chord = math.sqrt(chord2) if chord2 > 0.0 else 0.0
        # (ez, -ex) is the downward normal when the front knee is ahead of the rear one.
        xc, zc = 0.5 * (fx + rx) + half_chord * ez, 0.5 * (fz + rz) - half_chord * ex
        pose = (fx, fz, rx, rz, xc, zc)
        # The knees' velocities per unit hip rate: d(fx, fz)/dq_front, d(rx, rz)/dq_rear.
        return pose, _jacobian(pose, -a * sf, -a * cf, a * sr, -a * cr, singular)

    def jacobian(self, q_front: float, q_rear: float) -> Optional[Jacobian]:
        """
        Leg Jacobian d(x, l) / d(q_front, q_rear): ((dx/dq_f, dx/dq_r), (dl/dq_f, dl/dq_r)).

        Units m/rad. From the closure of the two shanks: each shank keeps its length, so
        (P - K_i) . (dP - dK_i/dq_i dq_i) = 0 for the axle P and knee K_i, two linear equations
        in dP. None when out of reach or singular (the shanks in line).
        """
        # Asked for several times per leg and tick at the same angles (l_dot and the leg
        # force of the state): solved once per pair.
        return (self._solutions.get((q_front, q_rear)) or self._solution(q_front, q_rear))[1]

    def measure(self, q_front: float, q_rear: float):
        """
        Return (pose, Jacobian, l, knees) at measured hip angles [rad]: the leg state's needs.

        pose as _pose, the Jacobian as jacobian() (None: out of reach or singular), l [m] as
        height(), knees (knee_front, knee_rear) [rad] as knee_angles(); kept per pair of angles
        with the linkage's solution (which then carries the height and knees too).
        """
        key = (q_front, q_rear)
        solutions = self._solutions
        found = solutions.get(key)
        if found is None or len(found) == 2:
            pose, j = found or self._linkage(q_front, q_rear)
            if pose is None:
                found = (None, j, NAN, (NAN, NAN))
            else:
                found = (pose, j, self.com_height - pose[5], _knee_angles(pose, q_front, q_rear))
            if len(solutions) >= _POSES_KEPT:
                solutions.clear()
            solutions[key] = found
        return found

    def height_rate(self, q_front: float, q_rear: float, q_front_dot: float,
                    q_rear_dot: float) -> float:
        """Return l_dot [m/s] for hip rates [rad/s]; nan when out of reach or singular."""
        j = self.jacobian(q_front, q_rear)
        if j is None:
            return NAN
        return j[1][0] * q_front_dot + j[1][1] * q_rear_dot

    def hip_rates(self, q_front: float, q_rear: float, l_dot: float,
                  x_dot: float = 0.0) -> Tuple[float, float]:
        """
        Hip rates (q_front_dot, q_rear_dot) [rad/s] that move the axle by (x_dot, l_dot) [m/s].

        The inverse of the Jacobian; (nan, nan) when out of reach or singular.
        """
        j = self.jacobian(q_front, q_rear)
        if j is None:
            return NAN, NAN
        (a, b), (c, d) = j
        det = a * d - b * c
        if det == 0.0:
            return NAN, NAN
        return (d * x_dot - b * l_dot) / det, (-c * x_dot + a * l_dot) / det

    def static_torques(self, q_front: float, q_rear: float, f_l: float,
                       f_x: float = 0.0) -> Tuple[float, float]:
        """
        Hip torques (tau_front, tau_rear) [N m] that hold the leg against a load, J^T (f_x, f_l).

        f_l [N]: the force the leg must push with along +l (body away from the axle: the body's
        weight share per leg, m g / 2, when level); f_x [N]: along +x. The torques act in the
        hips' angle convention (positive increases q); virtual work: tau . dq = f_x dx + f_l dl.
        (nan, nan) when out of reach or singular.
        """
        j = self.jacobian(q_front, q_rear)
        if j is None:
            return NAN, NAN
        (a, b), (c, d) = j
        return a * f_x + c * f_l, b * f_x + d * f_l

    def hip_command(self, l: float, l_dot: float, f_l: float, f_x: float):
        """
        Return the hips' (q_front, q_rear, q_front_dot, q_rear_dot, tau_front, tau_rear).

        For the axle l [m] below the COM (x = 0) moving at l_dot [m/s] under the load (f_x, f_l)
        [N]: q [rad] = inverse(l), the rates [rad/s] = hip_rates(q, l_dot), the torques [N m] =
        static_torques(q, f_l, f_x), the same values in one call (nan where those give nan),
        but for rounding: the Jacobian here comes from the inverse solve's knees, not from a
        forward solve at the angles.
        """
        # The angles and Jacobian of a held height are kept (the legs alternate ticks, and
        # without levelling both legs share one height); a new height is solved afresh, not
        # kept with the measured poses (a commanded height seldom comes back exactly).
        held_l, held = self._held
        if l == held_l:
            q_front, q_rear, j = held
        else:
            q_front, q_rear, j = held = self._inverse(l, 0.0)
            self._held = (l, held)
        if j is None:
            return q_front, q_rear, NAN, NAN, NAN, NAN
        (a, b), (c, d) = j
        det = a * d - b * c
        if det == 0.0:   # as hip_rates (x_dot = 0)
            rf = rr = NAN
        else:
            rf, rr = (d * 0.0 - b * l_dot) / det, (-c * 0.0 + a * l_dot) / det
        return q_front, q_rear, rf, rr, a * f_x + c * f_l, b * f_x + d * f_l

    def leg_force(self, q_front: float, q_rear: float, tau_front: float,
                  tau_rear: float) -> Tuple[float, float]:
        """
        Return the load (f_x, f_l) [N] that hip torques [N m] hold (static_torques inverted).

        f_l > 0: the leg pushes the body up (it carries weight); a leg hanging from a lifted
        body holds its wheel: f_l < 0. (nan, nan) when out of reach or singular.
        """
        return force_at(self.jacobian(q_front, q_rear), tau_front, tau_rear)

    def knee_angles(self, q_front: float, q_rear: float) -> Tuple[float, float]:
        """
        Passive knee angles (knee_front, knee_rear) [rad] for hip angles q_front, q_rear.

        Each is the shank's angle below the thigh's outward horizontal minus the hip angle,
        phi - q (front, about +y) and psi - q (rear, about -y), the convention of the knee joints
        in sim/robot.xml and urdf/wheelleg_balance.urdf (balance_node publishes them in
        joint_states); zero = shank in line with its thigh. (nan, nan) when out of reach.
        """
        pose = self._pose(q_front, q_rear)
        if pose is None:
            return NAN, NAN
        return _knee_angles(pose, q_front, q_rear)

    def height(self, q_front: float, q_rear: float) -> float:
        """Return the body height l [m] (axle to COM, body-vertical); nan when out of reach."""
        return self.forward(q_front, q_rear)[1]

    def inverse(self, l: float, x: float = 0.0) -> Tuple[float, float]:
        """
        Inverse kinematics: hip angles (q_front, q_rear) [rad] for an axle position.

        The axle goes l [m] below the COM and x [m] ahead of it, knees outward. Returns
        (nan, nan) when the point is out of reach or needs an angle outside [q_min, q_max].
        """
        return self._inverse(l, x)[:2]

    def _inverse(self, l: float, x: float):
        """
        Return inverse(l, x) and the Jacobian there: (q_front, q_rear, Jacobian or None).

        The Jacobian (see jacobian()) from the solve's own knees and axle, without a forward
        solve; None when out of reach, at a limit's NaN, or singular.
        """
        xc = x + self.com_x
        zc = self.com_height - l
        a_b, reach, a2_b2, a2, lo, hi = self._ik   # |a - b|, a + b, a^2 - b^2, a^2, limits
        q_front = q_rear = NAN
        half = self._half
        knees = []
        # Each hip's thigh angle below its outward horizontal that reaches the axle; (px, pz)
        # is the axle relative to the hip, px measured outward (forward for the front hip,
        # backward for the rear one), so both hips share the formula.
        for rear, px in ((False, xc - half), (True, -(xc + half))):
            d2 = px * px + zc * zc
            d = math.sqrt(d2) if d2 == d2 else NAN
            if not (a_b <= d <= reach) or d == 0.0:
                break   # out of reach: nan
            t = (a2_b2 + d2) / (2.0 * d)       # along hip -> axle
            h2 = a2 - t * t
            h = math.sqrt(h2) if h2 > 0.0 else 0.0     # perpendicular, towards the outside
            ux, uz = px / d, zc / d
            kx = t * ux - h * uz   # the knee from the hip: (a cos q, -a sin q), outward
            kz = t * uz + h * ux
            knees += (kx, kz)
            if rear:
                q_rear = math.atan2(-kz, kx)
            else:
                q_front = math.atan2(-kz, kx)
        if not (lo <= q_front <= hi and lo <= q_rear <= hi):
            return NAN, NAN, None
        # Rounding can put an angle a hair outside a limit it really sits on.
        lo, hi = self.q_min, self.q_max
        kfx, kfz, krx, krz = knees
        # The knees in the hip-midpoint frame; their velocities per unit hip rate, (-a sin q,
        # -a cos q) front and (a sin q, -a cos q) rear, from the same (a cos q, -a sin q).
        return (lo if lo > q_front else hi if hi < q_front else q_front,
                lo if lo > q_rear else hi if hi < q_rear else q_rear,
                _jacobian((half + kfx, kfz, -half - krx, krz, xc, zc), kfz, -kfx, -krz, -krx,
                          self._reach[4]))
