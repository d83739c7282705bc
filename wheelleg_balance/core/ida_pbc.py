"""
IDA-PBC of the paper, Sec. IV: position regulation (11)-(12) and velocity tracking (13).

Derived (docs/ida_pbc.md), not copied: the printed (12b) and the sign of the first term of (12c)
are wrong. The design works on the partial-feedback-linearized model (4) in Hamiltonian form,
q = [theta, x], p = [theta_dot, x_dot] (M = I), V = (g / l) cos(theta), G = [-cos(theta)/l, 1],
following Acosta, Ortega, Astolfi, Mahindrakar 2005 with the paper's

    M_d = [[k c^3 / (3 l^2), -k c^2 / (2 l)], [-k c^2 / (2 l), k c + m22_0]],
    V_d = 3 g l / (k c^2) + P/2 (x - x* + F(theta))^2,
    F = 3 l asinh(tan(theta)) + 6 l m22_0 / k tan(theta)      (asinh(tan) = ln(sec + tan)),

(c = cos(theta), s = sin(theta)). With p~ = M_d^-1 p and e = G^T M_d^-1 p (= A_4 p):

    A_1 = k c / 2 + 2 m22_0                                               (12a)
    p^T A_2 p = k^2 c^2 s / (4 l) e^2 + k^2 c^3 s / (12 l^2) e p~_1            (12b, corrected)
    A_3 = 3 g tan(theta) + P F A_1                                         (12c, sign corrected)
    A_4 p = e                                                              (12d)

    (11) nu = A_1 P (x - x*) + p^T A_2 p + A_3 - k_v A_4 p
    (13) nu = p_bar^T A_2 p_bar + A_3 - k_v A_4 p_bar,  p_bar = [theta_dot, x_dot - x_dot*].

(11) makes the closed loop of (4) port-Hamiltonian with dH_d/dt = -k_v e^2 <= 0. (13) is the exact
IDA-PBC of H_d = 1/2 p_bar^T M_d^-1 p_bar + 3 g l / (k c^2) only for P = 0; with P > 0 no H_d of
that form (any V_d(theta)) is non-increasing (docs/ida_pbc.md, section 5).

k_v is a function of the state here (``damping_gain``): Table I's k_v, plus a bell
k_v_upright exp(-(theta / k_v_width)^2 - (theta_dot / k_v_rate_width)^2) around upright rest.
Any k_v(q, p) > 0 keeps dH_d/dt = -k_v e^2 <= 0, so the design and its proof are unchanged; the
extra damping gives the loop its gain margin at upright (docs/ida_pbc.md, section 8;
docs/margins.md). k_v_upright = 0 is the paper's law.

Domain: M_d > 0 only for |theta| < pi/2. The functions clamp theta to +-THETA_MAX (89.4 deg) and
return 0.0 for non-finite inputs or results, so they never return a non-finite value. The robot
counts as fallen long before (45 deg), so the clamp only matters for garbage inputs.
Per-tick functions use floats and ``math`` only (a few microseconds per call).
"""
from dataclasses import dataclass
import math
from typing import Optional, Tuple

from .controller_base import ControlInput
from .model import pfl_force
from .params import IdaPbcGains, RobotParams

#: |theta| is clamped to this inside the domain |theta| < pi/2 of M_d > 0 [rad] (89.4 deg).
THETA_MAX = 0.5 * math.pi - 0.01

#: Gains tuned in docs/ida_pbc.md, section 7: start-up from 36 deg with <= 1 deg overshoot, at
#: the price of a slow velocity loop (43 s and 23 m to stop at l = 0.37 m). P = 0: exact IDA-PBC;
#: a constant k_v, as tuned.
TUNED_GAINS = IdaPbcGains(k=0.015, m22_0=0.2, k_v=0.068, P=0.0, k_v_upright=0.0)


@dataclass(frozen=True)
class IdaPbcTerms:
    """
    The terms A_1..A_4 of (12) at one (theta, l), for analysis and tests (not per tick).

    A1: scalar; A2: symmetric 2x2 as ((a11, a12), (a12, a22)); A3: scalar; A4: (a41, a42);
    F: F(theta) of (12) [m]. nu = A1 P (x - x*) + p^T A2 p + A3 - k_v A4 p.
    """

    A1: float
    A2: Tuple[Tuple[float, float], Tuple[float, float]]
    A3: float
    A4: Tuple[float, float]
    F: float


def clamp_theta(theta: float) -> float:
    """Clamp theta [rad] into [-THETA_MAX, THETA_MAX], inside the domain of M_d > 0."""
    return min(max(theta, -THETA_MAX), THETA_MAX)


def desired_inertia(theta: float, l: float, gains: IdaPbcGains) -> Tuple[float, float, float]:
    """Entries (m11, m12, m22) of the paper's M_d(theta) at height l [m] (Sec. IV-A)."""
    c = math.cos(theta)
    k = gains.k
    return k * c ** 3 / (3.0 * l * l), -k * c * c / (2.0 * l), k * c + gains.m22_0


def shaping_function(theta: float, l: float, gains: IdaPbcGains) -> float:
    """F(theta) of (12) [m]: 3 l ln(sec + tan) + 6 l m22_0 / k tan(theta)."""
    t = math.tan(theta)
    return 3.0 * l * math.asinh(t) + 6.0 * l * gains.m22_0 / gains.k * t


def damping_gain(theta: float, theta_dot: float, gains: IdaPbcGains) -> float:
    """
    Damping injection k_v at theta [rad], theta_dot [rad/s] (module docstring).

    k_v + k_v_upright exp(-(theta / k_v_width)^2 - (theta_dot / k_v_rate_width)^2): the bell
    acts near upright rest only, so a body swinging through upright (the rise from the tail)
    meets Table I's k_v (docs/ida_pbc.md, section 8).
    """
    z = (theta / gains.k_v_width) ** 2 + (theta_dot / gains.k_v_rate_width) ** 2
    return gains.k_v + gains.k_v_upright * math.exp(-z)


def _core(theta, p1, p2, l, k, m0, k_v, g):
    """
    Return (nu0, A_1, F) for clamped theta: nu0 = p^T A_2 p + 3 g tan(theta) - k_v A_4 p.

    Closed forms of docs/ida_pbc.md; M_d^-1 is written out (2x2).
    """
    s = math.sin(theta)
    c = math.cos(theta)
    c2 = c * c
    m11 = k * c2 * c / (3.0 * l * l)
    m12 = -k * c2 / (2.0 * l)
    m22 = k * c + m0
    det = m11 * m22 - m12 * m12  # = k^2 c^4 / (12 l^2) + k m0 c^3 / (3 l^2) > 0
    pt1 = (m22 * p1 - m12 * p2) / det
    pt2 = (m11 * p2 - m12 * p1) / det
    e = pt2 - c * pt1 / l  # G^T M_d^-1 p
    kin = k * k * c2 * s * e * (e / (4.0 * l) + c * pt1 / (12.0 * l * l))
    t = s / c
    F = 3.0 * l * math.asinh(t) + 6.0 * l * m0 / k * t
    return kin + 3.0 * g * t - k_v * e, 0.5 * k * c + 2.0 * m0, F


def ida_pbc_position(theta: float, theta_dot: float, x: float, x_dot: float, x_ref: float,
                     l: float, gains: IdaPbcGains, g: float = 9.81) -> float:
    """
    IDA-PBC for position regulation (11): outer-loop acceleration nu [m/s^2] of (4).

    theta [rad], theta_dot [rad/s], x [m], x_dot [m/s], x_ref = x* [m], l [m], g [m/s^2].
    Returns 0.0 if any input or the result is not finite; theta is clamped to +-THETA_MAX.
    """
    th = min(max(theta, -THETA_MAX), THETA_MAX)
    try:
        nu0, a1, F = _core(th, theta_dot, x_dot, l, gains.k, gains.m22_0,
                           damping_gain(th, theta_dot, gains), g)
        nu = nu0 + a1 * gains.P * (x - x_ref + F)
    except (ValueError, ZeroDivisionError, OverflowError):
        return 0.0
    return nu if math.isfinite(nu) else 0.0


def ida_pbc_velocity(theta: float, theta_dot: float, x_dot_err: float, l: float,
                     gains: IdaPbcGains, g: float = 9.81) -> float:
    """
    IDA-PBC for velocity tracking (13): nu [m/s^2] with p_bar = [theta_dot, x_dot - x_dot*].

    theta [rad], theta_dot [rad/s], x_dot_err = x_dot - x_dot* [m/s], l [m], g [m/s^2].
    A_3 keeps the paper's P F(theta) A_1 term (zero for P = 0, the exact IDA-PBC case).
    Returns 0.0 if any input or the result is not finite; theta is clamped to +-THETA_MAX.
    """
    th = min(max(theta, -THETA_MAX), THETA_MAX)
    try:
        nu0, a1, F = _core(th, theta_dot, x_dot_err, l, gains.k, gains.m22_0,
                           damping_gain(th, theta_dot, gains), g)
        nu = nu0 + a1 * gains.P * F
    except (ValueError, ZeroDivisionError, OverflowError):
        return 0.0
    return nu if math.isfinite(nu) else 0.0


def _kinetic(theta, p1, p2, l, gains):
    m11, m12, m22 = desired_inertia(theta, l, gains)
    det = m11 * m22 - m12 * m12
    return 0.5 * (m22 * p1 * p1 - 2.0 * m12 * p1 * p2 + m11 * p2 * p2) / det


def hd_position(theta: float, theta_dot: float, x: float, x_dot: float, x_ref: float, l: float,
                gains: IdaPbcGains, g: float = 9.81) -> float:
    """
    Closed-loop energy H_d = 1/2 p^T M_d^-1 p + V_d(q) of (11) (Sec. IV-A).

    V_d = 3 g l / (k cos^2(theta)) + P/2 (x - x* + F(theta))^2. Units of the normalized model
    (4) (M = I): [1/s^2]-like, only its decrease matters. theta is clamped to +-THETA_MAX.
    """
    th = clamp_theta(theta)
    z = x - x_ref + shaping_function(th, l, gains)
    return (_kinetic(th, theta_dot, x_dot, l, gains)
            + 3.0 * g * l / (gains.k * math.cos(th) ** 2) + 0.5 * gains.P * z * z)


def hd_velocity(theta: float, theta_dot: float, x_dot_err: float, l: float,
                gains: IdaPbcGains, g: float = 9.81) -> float:
    """
    H_d(theta, p_bar) = 1/2 p_bar^T M_d^-1 p_bar + 3 g l / (k cos^2(theta)) for (13).

    The paper's velocity-tracking energy (V_d without the x term). It is non-increasing along
    (4) + (13) when P = 0 (exact IDA-PBC); see docs/ida_pbc.md, section 5, for P > 0.
    """
    th = clamp_theta(theta)
    return (_kinetic(th, theta_dot, x_dot_err, l, gains)
            + 3.0 * g * l / (gains.k * math.cos(th) ** 2))


def ida_pbc_terms(theta: float, l: float, gains: IdaPbcGains, g: float = 9.81) -> IdaPbcTerms:
    """
    A_1..A_4 and F of (12) at (theta [rad], l [m]), derived (docs/ida_pbc.md, section 4).

    A_2 = M_d^-1 S M_d^-1 with S = 1/2 [[m12 m11' + 2 a1, m12 m12' + a2],
    [m12 m12' + a2, m12 m22']] and the paper's alpha = [a1, a2] (' = d/dtheta).
    """
    th = clamp_theta(theta)
    s, c = math.sin(th), math.cos(th)
    k = gains.k
    m11, m12, m22 = desired_inertia(th, l, gains)
    dm11 = -k * c * c * s / (l * l)
    dm12 = k * c * s / l
    dm22 = -k * s
    a = -k * k * c ** 3 * s / (12.0 * l * l)
    a1, a2 = a * c / l, -a
    S11 = 0.5 * (m12 * dm11 + 2.0 * a1)
    S12 = 0.5 * (m12 * dm12 + a2)
    S22 = 0.5 * m12 * dm22
    det = m11 * m22 - m12 * m12
    i11, i12, i22 = m22 / det, -m12 / det, m11 / det
    # A_2 = M_d^-1 S M_d^-1 (symmetric: the off-diagonal entry is computed once)
    r11, r12 = i11 * S11 + i12 * S12, i11 * S12 + i12 * S22  # first row of M_d^-1 S
    r21, r22 = i12 * S11 + i22 * S12, i12 * S12 + i22 * S22  # second row
    a12 = r11 * i12 + r12 * i22
    A2 = ((r11 * i11 + r12 * i12, a12), (a12, r21 * i12 + r22 * i22))
    F = shaping_function(th, l, gains)
    A1 = 0.5 * k * c + 2.0 * gains.m22_0
    A3 = 3.0 * g * s / c + gains.P * F * A1
    A4 = (-c / l * i11 + i12, -c / l * i12 + i22)
    return IdaPbcTerms(A1=A1, A2=A2, A3=A3, A4=A4, F=F)


class IdaPbcController:
    """
    Velocity-tracking IDA-PBC (13) as a Controller (core/controller_base.py), name 'ida_pbc'.

    p_bar = [theta_dot, x_dot - x_dot*] (the paper prints [theta, x_dot_err]: a typo; (13) is
    quadratic in a momentum). theta used = theta~ - d_hat when ``compensate_offset``, else
    theta~; it feeds both (13) and (3) (model.pfl_force: nu -> force u [N]). Uncompensated, an
    IMU offset biases the speed by -0.90 m/s per degree through (13) alone and -2.0 m/s per
    degree with (3) included, Table I gains (docs/ida_pbc.md, section 6).
    """

    name = 'ida_pbc'

    def __init__(self, p: RobotParams = RobotParams(), gains: IdaPbcGains = IdaPbcGains(),
                 compensate_offset: bool = True):
        self.p = p
        self.gains = gains
        self.compensate_offset = compensate_offset

    def compute(self, s: ControlInput) -> float:
        """Return the force u [N] on the cart for this tick (0.0 on non-finite input)."""
        return self.compute_floats(s.theta, s.theta_dot, s.x, s.x_dot, s.l, s.x_dot_ref,
                                   s.xi_hat.tolist())

    def compute_floats(self, theta: float, theta_dot: float, x: float, x_dot: float, l: float,
                       x_dot_ref: float, xi_hat) -> float:
        """``compute`` on ControlInput's fields (xi_hat: five floats), the tick's path."""
        if self.compensate_offset:
            theta = theta - xi_hat[4]
        nu = ida_pbc_velocity(theta, theta_dot, x_dot - x_dot_ref, l, self.gains,
                              self.p.gravity)
        u = pfl_force(clamp_theta(theta), theta_dot, nu, l, self.p)
        return u if math.isfinite(u) else 0.0

    def reset(self, s: ControlInput) -> None:
        """Nothing to reset: (13) is a static state feedback."""


class IdaPbcPositionController:
    """
    Position-regulation IDA-PBC (11) as a Controller, name 'ida_pbc_position' (tests, sims).

    Regulates to x* = ``x_ref`` [m]; with ``x_ref=None`` x* is the position at ``reset``.
    Same offset compensation and force conversion (3) as IdaPbcController.
    """

    name = 'ida_pbc_position'

    def __init__(self, p: RobotParams = RobotParams(), gains: IdaPbcGains = IdaPbcGains(),
                 compensate_offset: bool = True, x_ref: Optional[float] = 0.0):
        self.p = p
        self.gains = gains
        self.compensate_offset = compensate_offset
        self._hold = x_ref is None
        self.x_ref = 0.0 if x_ref is None else float(x_ref)

    def compute(self, s: ControlInput) -> float:
        """Return the force u [N] on the cart for this tick (0.0 on non-finite input)."""
        theta = s.theta - s.d_hat if self.compensate_offset else s.theta
        nu = ida_pbc_position(theta, s.theta_dot, s.x, s.x_dot, self.x_ref, s.l, self.gains,
                              self.p.gravity)
        u = pfl_force(clamp_theta(theta), s.theta_dot, nu, s.l, self.p)
        return u if math.isfinite(u) else 0.0

    def reset(self, s: ControlInput) -> None:
        """With x_ref=None, hold the current position: x* = s.x."""
        if self._hold:
            self.x_ref = s.x
