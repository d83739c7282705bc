"""
Luenberger observer (7)-(8) of the IMU pitch offset d, discretized at the control period.

Observer state zeta = [theta~, theta_dot, x, x_dot, d] in [rad, rad/s, m, m/s, rad] (five
states: (8) lists four, but its A_hat = [A E_d] needs d as a fifth state, and Table I's L has
five rows). Model: (5) with d constant,
    zeta_dot = A_hat zeta + B_hat u,  A_hat = [[A, E_d], [0, 0]],  B_hat = [B; 0],
measured y_m = [theta~, x] = C_hat zeta, C_hat = [[1, 0, 0, 0, 0], [0, 0, 1, 0, 0]]  (7).
It is discretized exactly for a zero-order hold of u over dt (scipy.signal.cont2discrete, 'zoh'):
zeta_{k+1} = Ad zeta_k + Bd u_k. (The paper uses forward Euler, I + T_s A_hat.)

Current-estimate form (used here), at tick k with the force u_{k-1} applied over the last period
and the new measurement y_k:
    predict  zeta_k^- = Ad zeta_{k-1} + Bd u_{k-1}
    correct  zeta_k   = zeta_k^- + L (y_k - C_hat zeta_k^-)
so the estimate error evolves as e_k = (I - L C_hat) Ad e_{k-1}. The paper's discretization is the
predictor form (zeta_k from y_{k-1}), which puts one extra sample of delay between the
measurement and u_k; the pipeline reads y_k before it computes u_k, so the current form uses it at
once. L places the eigenvalues of (I - L C_hat) Ad = Ad - L (C_hat Ad) at exp(s_i dt), with s_i the
continuous-time poles ``DEFAULT_OBSERVER_POLES`` (scipy.signal.place_poles on the dual pair
(Ad^T, (C_hat Ad)^T)); Table I's L (five numbers for a two-output measurement) cannot be used.

L, and the matrices F = (I - L C_hat) Ad, G = (I - L C_hat) Bd of the one-line update
zeta_k = F zeta_{k-1} + G u_{k-1} + L y_k, are precomputed on a grid of heights and linearly
interpolated at l (only when l changes); ``update`` is plain float arithmetic.
"""
import math
from typing import Optional

import numpy as np

from . import table_cache
from .height_grid import bracket
from .model import disturbance_input, linearize
from .params import CONTROL_PERIOD, RobotParams

#: Continuous-time observer poles [1/s]: four fast ones for the motion and a slow one (-4 1/s)
#: that d_hat settles with (within about 1 s). With the hold's sensor feedback this gives 6.4
#: dB of gain margin downwards where -8..-16 gave 5.4 (docs/margins.md, "The hold").
DEFAULT_OBSERVER_POLES = (-14.0, -16.0, -18.0, -20.0, -4.0)
#: Spacing of the default height grid [m] (same as core/lqr.py's schedule).
DEFAULT_HEIGHT_STEP = 0.01
#: Measurement matrix C_hat of (7)-(8): y_m = [theta~, x].
C_HAT = np.array([[1.0, 0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0, 0.0]])


def augmented_model(l: float, p: RobotParams) -> tuple:
    """Return (A_hat 5x5, B_hat (5,)) of the observer model (8) at height l [m]."""
    A, B = linearize(l, p)
    A_hat = np.zeros((5, 5))
    A_hat[:4, :4] = A
    A_hat[:4, 4] = disturbance_input(l, p)
    return A_hat, np.append(B, 0.0)


def discretize(l: float, p: RobotParams, dt: float = CONTROL_PERIOD) -> tuple:
    """Return (Ad 5x5, Bd (5,)): the zero-order-hold discretization of (8) at height l."""
    # Imported here: a start that finds its tables (core/table_cache.py) needs no scipy.
    from scipy.signal import cont2discrete
    A_hat, B_hat = augmented_model(l, p)
    Ad, Bd, _, _, _ = cont2discrete(
        (A_hat, B_hat.reshape(5, 1), C_HAT, np.zeros((2, 1))), dt, method='zoh')
    return Ad, Bd.reshape(5)


def observer_gain(l: float, p: RobotParams, dt: float = CONTROL_PERIOD,
                  poles=DEFAULT_OBSERVER_POLES) -> np.ndarray:
    """
    Return L (5x2) of the current-estimate observer at height l [m].

    The eigenvalues of (I - L C_hat) Ad are exp(s dt) for the continuous poles s [1/s].
    """
    from scipy.signal import place_poles
    Ad, _ = discretize(l, p, dt)
    z = np.exp(np.asarray(poles, dtype=float) * dt)
    return place_poles(Ad.T, (C_HAT @ Ad).T, z).gain_matrix.T


def observer_rows(p: RobotParams, dt: float, poles, heights) -> np.ndarray:
    """
    Return the observer's rows per height: [F | G | L | Ad | Bd] (n x 5 x 14).

    F = (I - L C_hat) Ad, G = (I - L C_hat) Bd, L = ``observer_gain``; Ad, Bd = ``discretize``.
    """
    rows = []
    for h in heights:
        Ad, Bd = discretize(h, p, dt)
        L = observer_gain(h, p, dt, poles)
        ILC = np.eye(5) - L @ C_HAT
        rows.append(np.column_stack([ILC @ Ad, ILC @ Bd, L, Ad, Bd]))
    return np.array(rows)


class DisturbanceObserver:
    """
    The observer (8) of [theta~, theta_dot, x, x_dot, d], scheduled over the height l.

    Call ``update`` once per tick with the measured pitch theta~ [rad], the measured position x
    [m], the force u [N] applied during the last period and the height l [m].

    ``d_hold_angle`` [rad]: while the pitch is this far from the estimated equilibrium
    (|theta~ - d_hat| > d_hold_angle, e.g. lifting off the tail at 36 deg), the linearization (2)
    is far off, and the residual it leaves is model error, not IMU offset: d_hat is held and the
    other states are still corrected. None disables the hold (the paper's observer).
    """

    def __init__(self, p: RobotParams = RobotParams(), dt: float = CONTROL_PERIOD,
                 poles=DEFAULT_OBSERVER_POLES, heights: Optional[np.ndarray] = None,
                 d_hold_angle: Optional[float] = math.radians(10.0)):
        self.d_hold_angle = math.inf if d_hold_angle is None else d_hold_angle
        if heights is None:
            n = int(round((p.height_max - p.height_min) / DEFAULT_HEIGHT_STEP)) + 1
            heights = np.linspace(p.height_min, p.height_max, n)
        self.p = p
        self.dt = dt
        self.poles = tuple(poles)
        self.heights = np.asarray(heights, dtype=float)
        self._h = [float(h) for h in self.heights]
        # Per grid height, 5 rows of [F_i0..F_i4, G_i, L_i0, L_i1, Ad_i0..Ad_i4, Bd_i]: solved
        # once for these inputs (core/table_cache.py).
        inputs = {'model': table_cache.floats(p), 'dt': float(dt),
                  'poles': table_cache.floats(self.poles), 'heights': self._h}
        rows = table_cache.table('observer_rows', inputs,
                                 lambda: observer_rows(p, dt, self.poles, self._h))
        self._rows = list(rows)
        # rows[i + 1] - rows[i], for _interp (the same numbers as computed there)
        self._steps = [b - a for a, b in zip(self._rows, self._rows[1:])]
        self.gains = [r[:, 6:8] for r in self._rows]  # L (5x2) per grid height
        self._l = None
        self._cur = None   # rows (F, G, L) at self._l, lists of floats
        self._pred = None  # rows [F | G | L | Ad | Bd] at self._l (the predictor's: Ad, Bd)
        self._z = [0.0] * 5

    def matrices(self, l: float) -> tuple:
        """Return (F 5x5, G (5,), L 5x2) interpolated at height l (for analysis, not per tick)."""
        r = self._interp(l)
        return r[:, :5], r[:, 5], r[:, 6:8]

    def _interp(self, l: float) -> np.ndarray:
        i, t = bracket(self._h, l)
        if t == 0.0:
            return self._rows[i]
        return self._rows[i] + t * self._steps[i]

    def reset(self, xi_hat0) -> None:
        """Set the estimate [theta~_hat, theta_dot_hat, x_hat, x_dot_hat, d_hat]."""
        self._z = [float(v) for v in xi_hat0]

    @property
    def xi_hat(self) -> np.ndarray:
        """Return the estimate [theta~_hat, theta_dot_hat, x_hat, x_dot_hat, d_hat]."""
        return np.array(self._z)

    def update(self, theta_meas: float, x_meas: float, u_applied: float,
               l: float) -> np.ndarray:
        """Run one tick (predict with u_applied, correct with [theta_meas, x_meas])."""
        return np.array(self.update_floats(theta_meas, x_meas, u_applied, l))

    def update_floats(self, theta_meas: float, x_meas: float, u_applied: float,
                      l: float) -> list:
        """
        ``update`` returning the estimate as a list of five floats (the tick's path).

        The list is the observer's own state until the next tick: read it, do not change it.
        """
        if l != self._l:
            r = self._interp(l)
            self._cur = r[:, :8].tolist()
            self._pred = r   # its rows (Ad, Bd) are taken when a measurement is lost
            self._l = l
        z0, z1, z2, z3, z4 = self._z
        u = u_applied if math.isfinite(u_applied) else 0.0
        y0, y1 = theta_meas, x_meas
        if math.isfinite(y0) and math.isfinite(y1):
            # zeta_k = F zeta_{k-1} + G u + L y, row by row (unrolled: this runs every tick)
            c0, c1, c2, c3, c4 = self._cur
            f0, f1, f2, f3, f4, g, l0, l1 = c0
            n0 = f0 * z0 + f1 * z1 + f2 * z2 + f3 * z3 + f4 * z4 + g * u + l0 * y0 + l1 * y1
            f0, f1, f2, f3, f4, g, l0, l1 = c1
            n1 = f0 * z0 + f1 * z1 + f2 * z2 + f3 * z3 + f4 * z4 + g * u + l0 * y0 + l1 * y1
            f0, f1, f2, f3, f4, g, l0, l1 = c2
            n2 = f0 * z0 + f1 * z1 + f2 * z2 + f3 * z3 + f4 * z4 + g * u + l0 * y0 + l1 * y1
            f0, f1, f2, f3, f4, g, l0, l1 = c3
            n3 = f0 * z0 + f1 * z1 + f2 * z2 + f3 * z3 + f4 * z4 + g * u + l0 * y0 + l1 * y1
            if abs(y0 - z4) > self.d_hold_angle:
                n4 = z4  # outside the linear region: hold d_hat
            else:
                f0, f1, f2, f3, f4, g, l0, l1 = c4
                n4 = f0 * z0 + f1 * z1 + f2 * z2 + f3 * z3 + f4 * z4 + g * u + l0 * y0 \
                    + l1 * y1
            z = [n0, n1, n2, n3, n4]
        else:
            # A lost measurement must not poison the estimate: predict only this tick.
            z = [a0 * z0 + a1 * z1 + a2 * z2 + a3 * z3 + a4 * z4 + b * u
                 for a0, a1, a2, a3, a4, b in self._pred[:, 8:].tolist()]
        self._z = z
        return z
