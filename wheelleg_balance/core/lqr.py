"""
LQR state feedback k_x for the linearization (2), scheduled over the height l.

Sign convention of the paper (9): u = k_x @ xi with xi = [theta, theta_dot, x, x_dot] in
[rad, rad/s, m, m/s] and u the force on the cart [N]; a stabilizing k_x makes A + B k_x Hurwitz.
``lqr_gain`` solves the continuous algebraic Riccati equation
    A^T P + P A - P B R^-1 B^T P + Q = 0,   k_x = -R^-1 B^T P,
for the cost J = integral(xi^T Q xi + R u^2) dt.

Default weights (Bryson's rule: 1 / (acceptable excursion)^2):
    Q = diag(1/0.1^2, 1/1.0^2, 1/0.3^2, 1/0.2^2), R = 1/30^2,
i.e. theta 0.1 rad, theta_dot 1 rad/s, x 0.3 m, x_dot 0.2 m/s for u = 30 N (1.5 N m per wheel).
At l = 0.37 m this gives k_x = [929, 150, 100, 197] and at 0.70 m [1181, 275, 100, 209]
(N/rad, N s/rad, N/m, N s/m): 10 deg of pitch asks for 162..206 N, i.e. 8.1..10.3 N m per
wheel, inside the 12 N m limit.
The x weight is not small, unlike Table I (whose x entry 0.001 lets the robot drift away from
where it stands): here position is held against the reference x_ref, and velocity tracking moves
x_ref at x_dot* (core/output_regulation.py), so holding still and tracking a velocity both work.

Table I's k_x = [150, 12, 0.001, 10] does not stabilize (2) at any l in 0.37..0.70 m as a gain to
the force u (a complex pair in the right half plane). Read as a gain to wheel torque it does,
both as the total torque (u = tau_total / r_w, gain x 10) and as the torque of each wheel
(u = 2 tau / r_w, gain x 20); see docs/linear_control.md. ``table_i_force_gain`` converts it.
"""
from typing import Optional

import numpy as np

from . import table_cache
from .height_grid import bracket
from .model import linearize
from .params import RobotParams, TABLE_I_K_X

#: Default LQR state weight Q (Bryson's rule, see the module docstring).
DEFAULT_Q = np.diag([1.0 / 0.1 ** 2, 1.0 / 1.0 ** 2, 1.0 / 0.3 ** 2, 1.0 / 0.2 ** 2])
#: Default LQR input weight R [1/N^2].
DEFAULT_R = 1.0 / 30.0 ** 2
#: Heights of the default schedule: every centimetre from 0.37 m to 0.70 m (34 points).
DEFAULT_HEIGHT_STEP = 0.01

#: Readings of Table I's k_x units: factor from the printed gain to force units [N per unit].
TABLE_I_READINGS = ('force', 'total_torque', 'per_wheel_torque')


def lqr_gain(l: float, p: RobotParams, Q=None, R=None) -> np.ndarray:
    """
    Return the LQR gain k_x (shape (4,), u = k_x @ xi) of (2) at height l [m].

    Q: 4x4 state weight (default DEFAULT_Q); R: scalar input weight [1/N^2] (default DEFAULT_R).
    """
    # Imported here: a start that finds its tables (core/table_cache.py) needs no scipy.
    from scipy.linalg import solve_continuous_are
    A, B = linearize(l, p)
    Q = DEFAULT_Q if Q is None else np.asarray(Q, dtype=float)
    R = DEFAULT_R if R is None else float(np.asarray(R, dtype=float).reshape(-1)[0])
    Bc = B.reshape(4, 1)
    P = solve_continuous_are(A, Bc, Q, np.array([[R]]))
    return -(Bc.T @ P).reshape(4) / R


def table_i_force_gain(p: RobotParams = RobotParams(), reading: str = 'per_wheel_torque'):
    """
    Return Table I's k_x converted to force units [N/rad, N s/rad, N/m, N s/m].

    reading: 'per_wheel_torque' (default; k_x xi is the torque tau of each wheel motor, the only
    torque command of the paper, Sec. V-A: u = 2 tau / r_w, i.e. x 20), 'total_torque'
    (k_x xi = tau_total, u = tau_total / r_w, x 10) or 'force' (as printed, x 1: not
    stabilizing). Both torque readings stabilize (2) over 0.37..0.70 m, so stability alone does
    not decide; per wheel is the default because it is the paper's motor command and because
    k_x then passes Kalman's LQR-optimality test |1 + k G(jw)| >= 1 over 0.37..0.65 m (total
    torque: only up to 0.51 m). See docs/linear_control.md.
    """
    if reading == 'force':
        factor = 1.0
    elif reading == 'total_torque':
        factor = 1.0 / p.wheel_radius
    elif reading == 'per_wheel_torque':
        factor = 2.0 / p.wheel_radius
    else:
        raise ValueError('reading must be one of %s' % ', '.join(TABLE_I_READINGS))
    return factor * TABLE_I_K_X


class FixedGain:
    """
    One k_x at every height, with GainSchedule's interface (Table I's set: the paper's gains).

    k_x: u = k_x @ xi [N/rad, N s/rad, N/m, N s/m].
    """

    def __init__(self, k_x):
        self.k_x = tuple(float(v) for v in k_x)

    def gain_floats(self, l: float) -> tuple:
        """Return k_x (u = k_x @ xi) [N/rad, N s/rad, N/m, N s/m] whatever l [m]."""
        return self.k_x

    def gain(self, l: float) -> np.ndarray:
        """Return k_x as an array."""
        return np.array(self.k_x)


#: Where the linear controllers' k_x comes from (output_regulation.gain_source).
GAIN_SOURCES = ('lqr', 'table_i')


def linear_gains(p: RobotParams, source: str = 'lqr', Q=None, R=None):
    """
    Return the k_x(l) of the linear controllers: 'lqr' (GainSchedule of Q, R) or 'table_i'.

    'table_i': Table I's k_x at every height, read as each wheel's torque (table_i_force_gain).
    """
    if source == 'lqr':
        return GainSchedule(p, Q, R)
    if source == 'table_i':
        return FixedGain(table_i_force_gain(p))
    raise ValueError('unknown gain source %r (one of %s)' % (source, ', '.join(GAIN_SOURCES)))


class GainSchedule:
    """
    k_x(l) precomputed by ``lqr_gain`` over a grid of heights, linearly interpolated per tick.

    Re-tuning for the height (which the paper names as the linear controller's limitation) is
    therefore automatic. ``gain`` / ``gain_floats`` clamp l into the grid and cost a bisect and
    four multiply-adds, no scipy.
    """

    def __init__(self, p: RobotParams = RobotParams(), Q=None, R=None,
                 heights: Optional[np.ndarray] = None):
        if heights is None:
            n = int(round((p.height_max - p.height_min) / DEFAULT_HEIGHT_STEP)) + 1
            heights = np.linspace(p.height_min, p.height_max, n)
        heights = np.asarray(heights, dtype=float)
        if heights.ndim != 1 or heights.size < 1 or np.any(np.diff(heights) <= 0.0):
            raise ValueError('heights must be a non-empty strictly increasing 1-D array')
        self.p = p
        self.Q = DEFAULT_Q if Q is None else np.asarray(Q, dtype=float)
        self.R = DEFAULT_R if R is None else R
        self.heights = heights
        # Solved once for these inputs (core/table_cache.py).
        inputs = {'model': table_cache.floats(p), 'Q': table_cache.floats(self.Q),
                  'R': float(np.asarray(self.R, dtype=float).reshape(-1)[0]),
                  'heights': table_cache.floats(heights)}
        self.gains = table_cache.table('lqr_gains', inputs,
                                       lambda: [lqr_gain(h, p, self.Q, self.R) for h in heights])
        self._h = [float(h) for h in heights]
        self._k = [tuple(float(v) for v in k) for k in self.gains]
        self._last = (None, None)   # (l, k_x(l)) of the last call: l changes on few ticks

    def gain_floats(self, l: float) -> tuple:
        """Return k_x(l) as a tuple of four floats (per-tick form of ``gain``)."""
        last_l, k = self._last
        if l == last_l:
            return k
        i, t = bracket(self._h, l)
        if t == 0.0:
            k = self._k[i]
        else:
            a, b = self._k[i], self._k[i + 1]
            k = (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]),
                 a[2] + t * (b[2] - a[2]), a[3] + t * (b[3] - a[3]))
        self._last = (l, k)
        return k

    def gain(self, l: float) -> np.ndarray:
        """Return k_x(l) (shape (4,), u = k_x @ xi) interpolated at height l [m]."""
        return np.array(self.gain_floats(l))
