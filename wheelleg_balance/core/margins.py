"""
Stability margins of the sampled balance loop, per controller and height l (docs/margins.md).

The loop certified is the one ``BalanceCore.step`` (core/pipeline.py) runs every T_s = 2 ms,
linearized at the upright equilibrium (theta = theta_dot = x_dot = 0, d = 0, zero command):

- plant: model (1) linearized at l, i.e. (2), xi_dot = A xi + B u (core/model.py ``linearize``),
  discretized for a zero-order hold of u over T_s (scipy.signal.cont2discrete, 'zoh'), plus one
  tick of delay at its input: the force computed at tick k acts over [t_{k+1}, t_{k+2});
- sensors: theta~ (IMU; = theta here), theta_dot (gyro), x_dot = r_w ((w_l + w_r) / 2 +
  theta_dot) (the exact ground speed in the linear model: the wheel-speed blend of
  core/wheel_state.py has unit gain from the true speed) and x from the odometry,
  x_k = x_{k-1} + T_s x_dot_{k-1} (core/estimation.py; the plant's own x is not fed back, so it
  is left out: a free integrator outside the loop);
- controller: the tick's controller object (``BalanceCore.controllers[name]``) linearized by
  central differences of its ``compute`` in all its inputs (theta~, theta_dot, x, x_dot and the
  observer state xi_hat = [theta~, theta_dot, x, x_dot, d]_hat) -- for IDA-PBC (13) through (3)
  that is the Jacobian of the shipped nonlinear law, for LQR and output regulation (9) it
  returns the state-feedback gains -- together with the observer (8) of core/observer.py, which
  runs whatever controller is selected: zeta_k = F zeta_{k-1} + G u_{k-1} + L [theta~_k, x_k]
  with the force the software last commanded (its copy of u is inside the controller);
- torque: u becomes tau = r_w u / 2 per wheel (core/actuation.py); the yaw term cancels in the
  sum and the saturation is inactive near the equilibrium, so the command is u up to the
  constant r_w / 2, which no margin depends on.

The loop is broken at the plant input (the wheel torque command). The return ratio is
L(z) = -K(z) P(z) z^-1 (the sign turns the paper's u = +K xi of (9) into the negative-feedback
convention: the closed loop is 1 + L = 0), kept as a discrete ``scipy.signal.StateSpace``. With
an actuator gain k the closed loop is A_L - k B_L C_L. The plant is open-loop unstable, so the
loop is stable only for k in an interval (k_min, k_max) around 1: the gain margins are
20 log10(k_max) up and -20 log10(k_min) down [dB], both positive when the loop is stable. The
phase margin [deg] is 180 deg + arg L at a gain crossover (|L| = 1); an extra pure delay tau
turns L by -omega tau, so the delay margin [s] is the smallest phase (taken in [0, 360) deg)
over omega_c across the crossovers, checked by adding floor(margin / T_s) ticks of delay.
"""
from dataclasses import dataclass, replace
import math
from typing import List, Optional, Sequence, Tuple

import numpy as np
from scipy.optimize import brentq
from scipy.signal import cont2discrete, StateSpace

from .balancing import core_config
from .config import BalanceConfig
from .controller_base import ControlInput
from .model import linearize
from .observer import DisturbanceObserver
from .output_regulation import PAPER_HOLD
from .params import CONTROL_PERIOD, RobotParams, TABLE_I_IDA_PBC
from .pipeline import BalanceCore, CONTROLLER_NAMES

#: Gain sets certified: the configuration's defaults (what balance_node runs unconfigured) and
#: the paper's Table I.
GAIN_SETS = ('default', 'table_i')
#: Required margins: gain margin both ways [dB] and delay margin [s] (issue 12, item 3).
REQUIRED_GAIN_MARGIN_DB = 6.0
REQUIRED_DELAY_MARGIN_S = 0.010
#: Central-difference step of the controller Jacobian [rad, rad/s, m, m/s].
JACOBIAN_STEP = 1e-6
#: Frequency grid of the crossing search: lowest frequency [rad/s] and number of points
#: (log-spaced up to the Nyquist frequency pi / T_s).
OMEGA_MIN = 1e-4
OMEGA_POINTS = 6000
#: Gain grid [dB] walked outwards from k = 1 by eigenvalues, as a check of the crossing
#: candidates: up to this far, in these steps.
GAIN_SCAN_DB = 60.0
GAIN_SCAN_STEP_DB = 0.25
#: Extra ticks of delay tried at most when confirming the delay margin (an infinite margin is
#: confirmed up to this many).
MAX_EXTRA_TICKS = 100

# Names of the controller's inputs, in the order of ``controller_jacobian``.
_INPUTS = ('theta', 'theta_dot', 'x', 'x_dot', 'theta_hat', 'theta_dot_hat', 'x_hat',
           'x_dot_hat', 'd_hat')
# Plant-side states: [theta, theta_dot, x_dot] of (2), the delayed command, the odometry x.
_PLANT_STATES = 5
_XO = 4            # index of the odometry x among the plant-side states
_X_HAT = 2         # index of x_hat in the observer state


@dataclass(frozen=True)
class Margins:
    """
    Margins of the balance loop at one height.

    l: height [m]. stable: the nominal closed loop is Schur (spectral radius < 1).
    gain_margin_up_db / gain_margin_down_db: how far the loop gain can rise / fall before the
    loop goes unstable [dB] (inf: never; NaN when not stable). phase_margin_deg: 180 + arg L
    at the gain crossover where it is smallest in magnitude [deg] (inf: no crossover).
    delay_margin_s: extra pure delay the loop tolerates [s], min over the gain crossovers of
    phase margin (in [0, 360) deg) / omega_c. spectral_radius: of the nominal closed loop.
    crossover_rad_s: the gain crossover frequency that sets the delay margin [rad/s].
    delay_ticks: the largest n such that 0..n extra ticks of delay all keep the loop stable
    (checked by eigenvalues up to floor(delay_margin_s / T_s) + 1). controller, gains_set:
    what was certified ('' for a bare loop).
    """

    l: float
    stable: bool
    gain_margin_up_db: float
    gain_margin_down_db: float
    phase_margin_deg: float
    delay_margin_s: float
    spectral_radius: float = math.nan
    crossover_rad_s: float = math.nan
    delay_ticks: int = 0
    dt: float = CONTROL_PERIOD
    controller: str = ''
    gains_set: str = ''

    @property
    def delay_confirmed(self) -> bool:
        """floor(delay_margin_s / dt) extra ticks of delay keep the loop stable."""
        if not self.stable or not self.delay_margin_s >= 0.0:
            return False
        if math.isinf(self.delay_margin_s):
            return self.delay_ticks >= MAX_EXTRA_TICKS
        return self.delay_ticks >= math.floor(self.delay_margin_s / self.dt + 1e-9)

    def shortfalls(self, gain_margin_db: float = REQUIRED_GAIN_MARGIN_DB,
                   delay_margin_s: float = REQUIRED_DELAY_MARGIN_S) -> List[str]:
        """Return what falls short of the required margins (empty: certified)."""
        out = []
        if not self.stable:
            out.append('unstable (spectral radius %.6f)' % self.spectral_radius)
            return out
        if not self.gain_margin_up_db >= gain_margin_db:
            out.append('gain margin up %.2f dB < %.1f dB'
                       % (self.gain_margin_up_db, gain_margin_db))
        if not self.gain_margin_down_db >= gain_margin_db:
            out.append('gain margin down %.2f dB < %.1f dB'
                       % (self.gain_margin_down_db, gain_margin_db))
        if not self.delay_margin_s >= delay_margin_s:
            out.append('delay margin %.2f ms < %.1f ms'
                       % (1e3 * self.delay_margin_s, 1e3 * delay_margin_s))
        if not self.delay_confirmed:
            out.append('delay margin %.2f ms not confirmed: only %d extra ticks stable'
                       % (1e3 * self.delay_margin_s, self.delay_ticks))
        return out


def build_core(gains_set: str, cfg: BalanceConfig = BalanceConfig()) -> BalanceCore:
    """
    Return the BalanceCore (controllers and observer of the tick) for a gain set.

    'default': ``cfg`` as balance_node runs it. 'table_i': IDA-PBC with Table I's k, m22_0, k_v,
    P, and the linear controllers with Table I's k_x = [150, 12, 0.001, 10] read as the torque
    of each wheel (core/lqr.py ``table_i_force_gain``: x 20 in force units) at every height;
    output regulation derives its k_d = -k_x[0] from the regulator equations as it always does
    (Table I's printed k_d = -167 is not what the shipped controller uses,
    docs/linear_control.md).
    """
    if gains_set not in GAIN_SETS:
        raise ValueError('unknown gain set %r (one of %s)' % (gains_set, ', '.join(GAIN_SETS)))
    p = cfg.model
    config = core_config(cfg)
    if gains_set == 'table_i':   # what config/paper_table_i.yaml sets (test_config.py)
        config = replace(config, ida_pbc=TABLE_I_IDA_PBC, linear_gain_source='table_i',
                         hold=PAPER_HOLD)
    return BalanceCore(p, config, cfg.loop.control_period)


def controller_jacobian(controller, l: float, step: float = JACOBIAN_STEP) -> np.ndarray:
    """
    Return d u / d input (shape (9,)) of ``controller.compute`` at the equilibrium, height l [m].

    Inputs in order: theta~ [rad], theta_dot [rad/s], x [m], x_dot [m/s] (the measurements)
    and the observer state [theta~, theta_dot, x, x_dot, d]_hat; u in [N]. Central differences
    of the real function at zero command (x_dot* = 0); the controller is reset to the
    equilibrium before every evaluation (its position reference x_ref = 0).
    """
    def u_at(v):
        s0 = ControlInput(l=l)
        controller.reset(s0)
        s = ControlInput(theta=v[0], theta_dot=v[1], x=v[2], x_dot=v[3], l=l, x_dot_ref=0.0,
                         xi_hat=np.array(v[4:], dtype=float))
        return float(controller.compute(s))

    J = np.zeros(len(_INPUTS))
    for i in range(len(_INPUTS)):
        v = [0.0] * len(_INPUTS)
        v[i] = step
        up = u_at(v)
        v[i] = -step
        J[i] = (up - u_at(v)) / (2.0 * step)
    return J


def plant_matrices(l: float, p: RobotParams, dt: float = CONTROL_PERIOD,
                   radius_ratio: float = 1.0, inertia: float = 0.0) -> tuple:
    """
    Return (Ap 5x5, Bp (5,), Cp 4x5): the plant side of the loop at height l [m].

    States [theta, theta_dot, x_dot, u_{k-1}, x_odo]: (2) without x (no row of A depends on x),
    zero-order hold over dt [s]; u_{k-1} [N], the command of the last tick, is what acts during
    this one (the tick of delay); x_odo [m] is the odometry's x_k = x_{k-1} + dt x_dot_{k-1}.
    Input: the command u_k [N]. Outputs, what the tick measures: [theta~, theta_dot, x, x_dot].
    radius_ratio: the controller's wheel radius over the plant's, when the controller was built
    for another robot: its force u becomes radius_ratio u on p (tau = r_c u / 2, F = 2 tau / r_p)
    and its odometry reads radius_ratio times the true x and x_dot. inertia: the pendulum's own
    inertia about its centre of mass [kg m^2] (core/model.py ``linearize``; 0: model (1)).
    """
    A, B = linearize(l, p, inertia)
    keep = [0, 1, 3]
    A3, B3 = A[np.ix_(keep, keep)], B[keep].reshape(3, 1)
    Ad, Bd, _, _, _ = cont2discrete((A3, B3, np.eye(3), np.zeros((3, 1))), dt, method='zoh')
    Ap = np.zeros((_PLANT_STATES, _PLANT_STATES))
    Ap[:3, :3] = Ad
    Ap[:3, 3] = radius_ratio * Bd[:, 0]
    Ap[_XO, 2] = radius_ratio * dt   # the odometry integrates the x_dot it reads
    Ap[_XO, _XO] = 1.0
    Bp = np.zeros(_PLANT_STATES)
    Bp[3] = 1.0
    Cp = np.zeros((4, _PLANT_STATES))
    Cp[0, 0] = Cp[1, 1] = Cp[2, _XO] = 1.0
    Cp[3, 2] = radius_ratio
    return Ap, Bp, Cp


def controller_matrices(J: np.ndarray, observer: DisturbanceObserver, l: float) -> tuple:
    """
    Return (Ak 6x6, Bk 6x4, Ck (6,), Dk (4,)): the tick's controller as a discrete system.

    State q_k = [zeta_{k-1}, u_{k-1}], input the measurements m_k = [theta~, theta_dot, x,
    x_dot], output u_k [N]. The observer (8), current-estimate form of core/observer.py:
    zeta_k = F zeta_{k-1} + G u_{k-1} + L [theta~_k, x_k]; then u_k = J_m m_k + J_z zeta_k with
    J = [J_m, J_z] from ``controller_jacobian``. The observer is fed the command the software
    sent, so that feedback of u stays inside the controller.
    """
    F, G, Lo = observer.matrices(l)
    Jm, Jz = np.asarray(J[:4], dtype=float), np.asarray(J[4:], dtype=float)
    Cy = np.zeros((2, 4))
    Cy[0, 0] = Cy[1, 2] = 1.0          # the observer measures theta~ and x (7)
    LC = Lo @ Cy
    Dk = Jm + Jz @ LC
    Ck = np.append(Jz @ F, Jz @ G)
    Ak = np.zeros((6, 6))
    Ak[:5, :5] = F
    Ak[:5, 5] = G
    Ak[5, :] = Ck
    Bk = np.vstack([LC, Dk.reshape(1, 4)])
    return Ak, Bk, Ck, Dk


def _drop_free_position(A, B, C, v) -> tuple:
    """
    Remove the direction v from (A, B, C) if it is a fixed, unobservable mode at z = 1.

    A controller that does not regulate the position (IDA-PBC (13) tracks a velocity) leaves
    the robot free to stand anywhere: shifting the odometry x and x_hat together changes
    nothing the controller sees, a closed-loop eigenvalue at exactly 1 for every loop gain.
    It is not a stability property of the loop, so the loop is certified on the quotient by v.
    """
    v = v / np.linalg.norm(v)
    scale = 1.0 + np.abs(A).max()
    if np.linalg.norm(A @ v - v) > 1e-9 * scale or abs(C @ v) > 1e-9 * (1.0 + np.abs(C).max()):
        return A, B, C
    # Rows of S span the orthogonal complement of v: coordinates w = S s of R^n / span(v).
    S = np.linalg.svd(v.reshape(1, -1))[2][1:]
    return S @ A @ S.T, S @ B, C @ S.T


def build_loop(controller, observer: DisturbanceObserver, l: float,
               p: RobotParams = RobotParams(), dt: float = CONTROL_PERIOD,
               radius_ratio: float = 1.0, inertia: float = 0.0) -> StateSpace:
    """
    Return the return ratio L(z) = -K(z) P(z) z^-1 at height l [m] (discrete, sampling dt [s]).

    ``controller``: a Controller of core/controller_base.py (linearized by central
    differences); ``observer``: the DisturbanceObserver that feeds it xi_hat. Input: the actuator
    signal at the loop break [N]; output: minus the controller's command [N]. D = 0 (the tick of
    delay makes it strictly proper). radius_ratio, inertia: the plant's, as ``plant_matrices``'s.
    """
    J = controller_jacobian(controller, l)
    Ap, Bp, Cp = plant_matrices(l, p, dt, radius_ratio, inertia)
    Ak, Bk, Ck, Dk = controller_matrices(J, observer, l)
    n_p, n_k = Ap.shape[0], Ak.shape[0]
    A = np.zeros((n_p + n_k, n_p + n_k))
    A[:n_p, :n_p] = Ap
    A[n_p:, :n_p] = Bk @ Cp
    A[n_p:, n_p:] = Ak
    B = np.append(Bp, np.zeros(n_k))
    C = -np.append(Dk @ Cp, Ck)
    v = np.zeros(n_p + n_k)
    v[_XO] = v[n_p + _X_HAT] = 1.0
    A, B, C = _drop_free_position(A, B, C, v)
    n = A.shape[0]
    return StateSpace(A, B.reshape(n, 1), C.reshape(1, n), np.zeros((1, 1)), dt=dt)


def freq_response(loop: StateSpace, omega) -> np.ndarray:
    """
    Return L(exp(j omega dt)) at the frequencies omega [rad/s] (complex array).

    Solved directly, (z I - A) x = B for every z (numpy, batched): scipy.signal.dfreqresp goes
    through the polynomial form, which loses digits for a dozen states with poles clustered at
    z = 1 and z = 0.
    """
    A, B, C, D = (np.asarray(m, dtype=float) for m in (loop.A, loop.B, loop.C, loop.D))
    z = np.exp(1j * np.asarray(omega, dtype=float).reshape(-1) * loop.dt)
    n = A.shape[0]
    M = z[:, None, None] * np.eye(n)[None, :, :] - A[None, :, :]
    rhs = np.broadcast_to(B.astype(complex), (z.size, n, 1))
    x = np.linalg.solve(M, rhs)
    return (C @ x)[:, 0, 0] + D[0, 0]


def closed_loop_matrix(loop: StateSpace, k: float = 1.0, extra_ticks: int = 0) -> np.ndarray:
    """
    Return the closed-loop matrix of 1 + k L z^-extra_ticks = 0 (actuator gain k, extra delay).

    ``loop`` must be strictly proper (D = 0), as ``build_loop``'s is.
    """
    A, B, C = (np.asarray(m, dtype=float) for m in (loop.A, loop.B, loop.C))
    n = A.shape[0]
    B = B.reshape(n)
    C = C.reshape(n)
    if extra_ticks <= 0:
        return A - k * np.outer(B, C)
    # A shift register of extra_ticks samples in front of the loop's input.
    m = extra_ticks
    Acl = np.zeros((n + m, n + m))
    Acl[:n, :n] = A
    Acl[:n, n + m - 1] = B
    for i in range(1, m):
        Acl[n + i, n + i - 1] = 1.0
    Acl[n, :n] = -k * C
    return Acl


def spectral_radius(loop: StateSpace, k: float = 1.0, extra_ticks: int = 0) -> float:
    """Return the spectral radius of ``closed_loop_matrix`` (< 1: stable)."""
    return float(np.max(np.abs(np.linalg.eigvals(closed_loop_matrix(loop, k, extra_ticks)))))


def _roots(f, grid, values) -> List[float]:
    """Refine every sign change of f over ``grid`` (its ``values`` given) with brentq."""
    out = []
    s = np.sign(values)
    for i in np.nonzero(s[:-1] * s[1:] < 0)[0]:
        out.append(brentq(f, grid[i], grid[i + 1], xtol=1e-12 * grid[i], rtol=1e-12))
    return out


def _frequencies(dt: float) -> np.ndarray:
    return np.logspace(math.log10(OMEGA_MIN), math.log10(math.pi / dt), OMEGA_POINTS)


def negative_real_crossings(loop: StateSpace) -> List[Tuple[float, float]]:
    """
    Return [(omega [rad/s], k)]: where L crosses the negative real axis, L = -1 / k.

    Each such k (> 0) is a loop gain at which a closed-loop pole sits on the unit circle.
    Includes the Nyquist frequency pi / dt and, without a pole at z = 1, omega = 0, where L is
    real.
    """
    dt = loop.dt
    w = _frequencies(dt)
    Lw = freq_response(loop, w)

    def im(x):
        return float(freq_response(loop, [x])[0].imag)

    out = []
    for x in _roots(im, w, Lw.imag):
        re = float(freq_response(loop, [x])[0].real)
        if re < 0.0:
            out.append((x, -1.0 / re))
    nyq = freq_response(loop, [math.pi / dt])[0].real
    if nyq < 0.0:
        out.append((math.pi / dt, -1.0 / nyq))
    # At omega = 0 L is real too, unless it has a pole at z = 1 (an integrator: the balance
    # loops have two, x_dot and the odometry x).
    A = np.asarray(loop.A, dtype=float)
    if np.linalg.cond(np.eye(A.shape[0]) - A) < 1e12:
        dc = freq_response(loop, [0.0])[0].real
        if dc < 0.0:
            out.insert(0, (0.0, -1.0 / dc))
    return out


def gain_crossovers(loop: StateSpace) -> List[Tuple[float, float]]:
    """Return [(omega_c [rad/s], phase margin [deg] in (-180, 180])] where |L| = 1."""
    w = _frequencies(loop.dt)
    mag = np.log(np.abs(freq_response(loop, w)))

    def logmag(x):
        return float(np.log(abs(freq_response(loop, [x])[0])))

    out = []
    for x in _roots(logmag, w, mag):
        phase = math.degrees(np.angle(freq_response(loop, [x])[0]))
        pm = (phase + 180.0 + 180.0) % 360.0 - 180.0   # 180 + arg L, wrapped into [-180, 180)
        out.append((x, 180.0 if pm == -180.0 else pm))
    return out


def _boundary(loop: StateSpace, points: Sequence[float], k0: float = 1.0) -> Optional[float]:
    """
    Walk the gains ``points`` (sorted away from k0, all on one side) from a stable k0.

    Stability is tested by eigenvalues at the geometric midpoint of each pair of neighbours;
    at the first unstable one the boundary is found by brentq on spectral radius - 1 between
    the last stable gain and it. Returns the boundary gain, or None if all are stable.
    """
    last = k0
    for a, b in zip([k0] + list(points[:-1]), points):
        mid = math.sqrt(a * b)
        if spectral_radius(loop, mid) >= 1.0:
            return brentq(lambda k: spectral_radius(loop, k) - 1.0, last, mid,
                          xtol=1e-12, rtol=1e-10)
        last = mid
    return None


def _beyond(loop: StateSpace, k_last: float, k_far: float) -> float:
    """Boundary beyond the scanned gains: k_far if still stable there, else brentq in log k."""
    if spectral_radius(loop, k_far) < 1.0:
        return k_far
    return math.exp(brentq(lambda q: spectral_radius(loop, math.exp(q)) - 1.0,
                           math.log(k_last), math.log(k_far), xtol=1e-10))


def gain_margins(loop: StateSpace) -> Tuple[float, float]:
    """
    Return (k_min, k_max): the interval of actuator gains around 1 that keeps the loop stable.

    Candidates are the negative-real-axis crossings of L (``negative_real_crossings``), merged
    with a grid of GAIN_SCAN_STEP_DB steps out to GAIN_SCAN_DB each way so a crossing the
    frequency grid missed cannot hide an unstable band; each interval between neighbouring
    candidates is tested by eigenvalues. Beyond the scan, k_max = inf if the loop is still
    stable at k = 1e12 and k_min = 0 if it is stable at k = 1e-12 (an open-loop stable plant).
    Call it only for a loop that is stable at k = 1.
    """
    ks = [k for _, k in negative_real_crossings(loop)]
    steps = np.arange(GAIN_SCAN_STEP_DB, GAIN_SCAN_DB + 1e-9, GAIN_SCAN_STEP_DB)
    up = sorted({k for k in ks if k > 1.0} | set(10.0 ** (steps / 20.0)))
    down = sorted({k for k in ks if 0.0 < k < 1.0} | set(10.0 ** (-steps / 20.0)), reverse=True)
    k_max = _boundary(loop, up)
    if k_max is None:
        k_max = _beyond(loop, up[-1], 1e12)
        k_max = math.inf if k_max == 1e12 else k_max
    k_min = _boundary(loop, down)
    if k_min is None:
        k_min = _beyond(loop, down[-1], 1e-12)
        k_min = 0.0 if k_min == 1e-12 else k_min
    return k_min, k_max


def _db(k: float) -> float:
    if k == 0.0:
        return -math.inf
    return 20.0 * math.log10(k) if math.isfinite(k) else math.inf


def loop_margins(loop: StateSpace, l: float = math.nan, controller: str = '',
                 gains_set: str = '') -> Margins:
    """
    Return the Margins of a return ratio ``loop`` (discrete StateSpace, D = 0).

    See the module docstring for what each margin means; all but ``stable`` and
    ``spectral_radius`` are NaN when the nominal loop is not stable.
    """
    dt = float(loop.dt)
    rho = spectral_radius(loop)
    nan = math.nan
    if not rho < 1.0:
        return Margins(l, False, nan, nan, nan, nan, rho, nan, 0, dt, controller, gains_set)
    k_min, k_max = gain_margins(loop)
    crossovers = gain_crossovers(loop)
    if crossovers:
        pm = min((pm for _, pm in crossovers), key=abs)
        delays = [(math.radians(pm % 360.0) / w, w) for w, pm in crossovers]
        dm, wc = min(delays)
    else:
        pm, dm, wc = math.inf, math.inf, nan
    # Confirm the delay margin by eigenvalues: extra ticks 1, 2, ... up to one past it.
    limit = MAX_EXTRA_TICKS
    if math.isfinite(dm):
        limit = min(limit, math.floor(dm / dt + 1e-9) + 1)
    ticks = 0
    while ticks < limit and spectral_radius(loop, 1.0, ticks + 1) < 1.0:
        ticks += 1
    return Margins(l, True, _db(k_max), -_db(k_min), pm, dm, rho, wc, ticks, dt, controller,
                   gains_set)


def height_grid(step: float = 0.01, p: RobotParams = RobotParams()) -> np.ndarray:
    """Return heights from p.height_min to p.height_max [m] every ``step`` [m], both ends."""
    n = int(round((p.height_max - p.height_min) / step)) + 1
    return np.linspace(p.height_min, p.height_max, n)


def delayed(loop: StateSpace, ticks: int) -> StateSpace:
    """
    Return ``loop`` with ``ticks`` more ticks of delay at its input: L(z) z^-ticks.

    A measured actuator latency (identification's motor delay) as part of the loop, so that the
    margins are what is left beyond it. ``loop`` must be strictly proper (D = 0).
    """
    if ticks <= 0:
        return loop
    A, B, C = (np.asarray(m, dtype=float) for m in (loop.A, loop.B, loop.C))
    n, m = A.shape[0], int(ticks)
    Ad = np.zeros((n + m, n + m))
    Ad[:n, :n] = A
    Ad[:n, n + m - 1:] = B.reshape(n, 1)   # the last of the register drives the loop
    for i in range(1, m):
        Ad[n + i, n + i - 1] = 1.0
    Bd = np.zeros((n + m, 1))
    Bd[n, 0] = 1.0
    Cd = np.append(C.reshape(n), np.zeros(m)).reshape(1, n + m)
    return StateSpace(Ad, Bd, Cd, np.zeros((1, 1)), dt=loop.dt)


def delay_ticks(delay: float, dt: float = CONTROL_PERIOD) -> int:
    """Return an actuator delay [s] as whole ticks of dt [s], rounded up (the safe side)."""
    return max(0, math.ceil(delay / dt - 1e-6))


def certify(controller_name: str, gains_set: str, heights: Optional[Sequence[float]] = None,
            cfg: BalanceConfig = BalanceConfig(), extra_ticks: int = 0,
            plant: Optional[RobotParams] = None, inertia: float = 0.0) -> List[Margins]:
    """
    Return the Margins of ``controller_name`` at ``gains_set`` for every height [m].

    controller_name: one of core/pipeline.py CONTROLLER_NAMES (ida_pbc, output_regulation,
    lqr); gains_set: one of GAIN_SETS; heights: default every 1 cm over height_min..height_max;
    cfg: the configuration (robot, observer period, default gains); extra_ticks: ticks of
    actuator delay in the loop (``delay_ticks``); plant: the robot the loop is closed on when
    it is not the one cfg's controllers are built for (default: cfg's; the controllers' own
    wheel radius then scales their force and odometry, ``plant_matrices``); inertia: the
    plant pendulum's own inertia about its centre of mass [kg m^2] (0: model (1)).
    """
    if controller_name not in CONTROLLER_NAMES:
        raise ValueError('unknown controller %r (one of %s)'
                         % (controller_name, ', '.join(CONTROLLER_NAMES)))
    if heights is None:
        heights = height_grid(0.01, cfg.model)
    return core_margins(build_core(gains_set, cfg), controller_name, heights, gains_set,
                        extra_ticks, plant, inertia)


def core_margins(core: BalanceCore, controller_name: str, heights: Sequence[float],
                 gains_set: str = '', extra_ticks: int = 0,
                 plant: Optional[RobotParams] = None, inertia: float = 0.0) -> List[Margins]:
    """
    Return the Margins of ``core``'s controller ``controller_name`` at every height [m].

    ``certify`` for a core built elsewhere (e.g. the tuning's candidates); gains_set: the
    label the Margins carry; extra_ticks, plant, inertia: as ``certify``'s.
    """
    p = plant or core.p
    ratio = core.p.wheel_radius / p.wheel_radius
    return [loop_margins(delayed(build_loop(core.controllers[controller_name], core.observer,
                                            float(l), p, core.dt, ratio, inertia),
                                 extra_ticks),
                         float(l), controller_name, gains_set)
            for l in heights]
