"""
The planned rise: the start-up from the tail as a trajectory of model (1) (issue 33, part 1).

It is tracked by a time-varying LQR.

Why a plan. Pushed up from the tail at rest, the body gains about 1.1 m/s of forward speed
before it passes upright, whatever the controller (validation/paper/tuning.py
``rise_estimate``), and a body leaning back at most 1 deg brakes at most g tan(1 deg): rest
after 6.6 s and 3.9 m. The tail has a passive wheel, though: resting on it, the robot can
first roll backwards (a run-up; its pitch stays the tail's while u < (M + m) g tan(theta_0)),
so that the push that lifts the body cancels that backward speed and the body arrives upright
at rest. ``plan_rise`` finds such a motion:

- phase A, on the tail: theta = theta_0, (M + m) x_ddot = u, u <= U_TAIL_MARGIN (M + m) g
  tan(theta_0) (the body stays on the tail) and u >= -(M + m) ``run_up_acceleration`` (the
  robot does not tip forward over its tail wheel: model (1) has no such limit, a real robot
  does);
- phase B, off it: model (1) at height l (core/model.py), theta >= -``lean_max`` (the
  overshoot the plan allows itself), ending upright at rest: theta = theta_dot = x_dot = u = 0;
- |u| <= ``force_share`` x 2 tau_max / r_w in both (the rest is the feedback's);
- cost: the duration plus effort and the force's rate of change (a motion a tracker follows).

It is solved by direct single shooting: the force piecewise linear through a few knots per
phase, the flight integrated with RK4, the end state and the lean as constraints of
scipy.optimize.minimize's SLSQP (about 2 s of CPU; a collocation of the same problem with
finite-difference Jacobians took minutes).

``tracking_gains`` samples the plan at the control period and solves the discrete
time-varying LQR about it (the Riccati recursion backwards from the upright hold's stationary
solution, core/lqr.py's weights), so u = u_ff + K (xi - xi_ref) (the paper's sign convention
(9)). On the tail the pitch feedback is zero: the pitch there is the tail's, and a pitch error
is the IMU's offset, which the wheels cannot move. After the plan the last gain holds the
robot at the plan's end until the auto mode's hold takes over (core/pipeline.py).

The IMU offset d is not known at arming (d_hat0), and a tracker of theta~ - d_hat0 would bring
the body to -d. In flight, model (1)'s pendulum row l theta_ddot = g sin(theta) - cos(theta)
x_ddot holds whatever the masses, so the gyro and the wheels' speed give d
(``PlannedRise.offset``), and the tracker uses it from about 0.1 s after the lift-off.

Plans are solved once per model, height and limits, and cached (core/table_cache.py): the
default configuration's comes with the installed package. ``PlannedRise`` is the per-tick part:
a table look-up and four multiply-adds.
"""
from dataclasses import dataclass
import math

import numpy as np

from . import table_cache
from .lqr import DEFAULT_Q, DEFAULT_R
from .params import CONTROL_PERIOD, RobotParams

#: Share of the tail's lift-off force the run-up may use on the tail (margin against lifting).
U_TAIL_MARGIN = 0.9
#: Free knots of the force in the two phases (shooting parameters).
KNOTS_TAIL, KNOTS_FLIGHT = 4, 8
#: Evidence the flight must give before its offset estimate is used [m/s] (PlannedRise.offset).
OFFSET_EVIDENCE = 0.8
#: Pitch rate [rad/s] (rising: negative) from which the body counts as off the tail.
LIFTED_RATE = 0.3
#: The most the flight's offset estimate may differ from the one at arming [rad] (6 deg).
OFFSET_MAX = math.radians(6.0)
#: The plan's table columns: t, theta, theta_dot, x, x_dot, u_ff, K (4), on_tail.
COLUMNS = 11


@dataclass(frozen=True)
class RiseSpec:
    """
    What a plan is solved for (its cache key with the model).

    l: height [m]; theta_0: the tail's pitch, where the rise starts [rad]; max_wheel_torque:
    per-wheel limit [N m]; force_share: the plan's share of the force limit; lean_max: the
    largest lean back the plan may use [rad]; run_up_acceleration: the most the run-up may
    accelerate backwards [m/s^2] (harder tips the robot forward over its tail wheel, lifting
    the drive wheels: 2.9 m/s^2 did in MuJoCo, 2026-12-07; model (1) does not see it); dt:
    control period [s].
    """

    l: float = 0.37
    theta_0: float = math.radians(36.0)
    max_wheel_torque: float = 12.0
    force_share: float = 0.6
    lean_max: float = math.radians(0.3)
    run_up_acceleration: float = 1.5
    dt: float = CONTROL_PERIOD


def _flight_accel(theta, theta_dot, u, l, m, M, g):
    """Model (1) solved for (theta_ddot, x_ddot) (core/model.py ipc_accel), on arrays."""
    s, c = np.sin(theta), np.cos(theta)
    x_ddot = (u + m * l * s * theta_dot * theta_dot - m * g * s * c) / (M + m * s * s)
    return (g * s - c * x_ddot) / l, x_ddot


def _force(t, knots_t, knots_u):
    """Return the plan's force [N] at time t [s]: piecewise linear through its knots."""
    return np.interp(t, knots_t, knots_u)


def _simulate(p: RobotParams, spec: RiseSpec, z, steps: int = 120):
    """
    Integrate the plan of parameters z (``plan_rise``); return (t, theta, theta_dot, x, x_dot, u).

    Phase A exactly (a double integrator under a piecewise-linear force, fine steps), phase B
    with RK4 under model (1) (``steps`` steps).
    """
    m, M, g, l = p.body_mass, p.wheel_mass, p.gravity, spec.l
    ta, tb = z[0], z[1]
    ka = np.linspace(0.0, ta, KNOTS_TAIL + 2)
    ua = np.concatenate([[0.0], z[2:3 + KNOTS_TAIL]])
    kb = ta + np.linspace(0.0, tb, KNOTS_FLIGHT + 2)
    ub = np.concatenate([z[3 + KNOTS_TAIL:], [0.0]])
    n_a = 100
    t_a = np.linspace(0.0, ta, n_a + 1)
    acc = _force(t_a, ka, ua) / (M + m)
    h = ta / n_a
    v = np.concatenate([[0.0], np.cumsum(0.5 * h * (acc[1:] + acc[:-1]))])
    x = np.concatenate([[0.0], np.cumsum(0.5 * h * (v[1:] + v[:-1]))])
    out = [(t_a[i], spec.theta_0, 0.0, x[i], v[i], ua_i) for i, ua_i in
           enumerate(_force(t_a, ka, ua))]
    th, w, xb, vb = spec.theta_0, 0.0, x[-1], v[-1]
    h = tb / steps

    def f(t, th, w):
        return _flight_accel(th, w, _force(t, kb, ub), l, m, M, g)
    for i in range(steps):
        t = ta + i * h
        a1, b1 = f(t, th, w)
        a2, b2 = f(t + 0.5 * h, th + 0.5 * h * w, w + 0.5 * h * a1)
        a3, b3 = f(t + 0.5 * h, th + 0.5 * h * (w + 0.5 * h * a1), w + 0.5 * h * a2)
        a4, b4 = f(t + h, th + h * (w + 0.5 * h * a2), w + h * a3)
        th = th + h * (w + h / 6.0 * (a1 + a2 + a3))
        w = w + h / 6.0 * (a1 + 2 * a2 + 2 * a3 + a4)
        xb = xb + h * (vb + h / 6.0 * (b1 + b2 + b3))
        vb = vb + h / 6.0 * (b1 + 2 * b2 + 2 * b3 + b4)
        out.append((t + h, th, w, xb, vb, float(_force(t + h, kb, ub))))
    return np.array(out), n_a


def plan_rise(p: RobotParams, spec: RiseSpec) -> np.ndarray:
    """
    Solve the rise (module docstring) by direct single shooting; raise RuntimeError if it fails.

    Parameters: the durations of the run-up T_A and the flight T_B [s], the force [N] at
    KNOTS_TAIL knots of the run-up (it starts at 0), at the lift-off, and at KNOTS_FLIGHT knots
    of the flight (it ends at 0), linear in between. Returns ``_simulate``'s rows.
    """
    from scipy.optimize import minimize
    m, M, g = p.body_mass, p.wheel_mass, p.gravity
    U = spec.force_share * 2.0 * spec.max_wheel_torque / p.wheel_radius
    u_tail = U_TAIL_MARGIN * (M + m) * g * math.tan(spec.theta_0)
    n_a = KNOTS_TAIL
    memo = {}

    def run(z):
        # z: durations [s], then the knots' forces in units of U; cached per z (SLSQP asks
        # the cost and both constraints at the same points).
        key = z.tobytes()
        if key not in memo:
            if len(memo) > 64:
                memo.clear()
            memo[key] = _simulate(p, spec, np.concatenate([z[:2], z[2:] * U]), steps=80)
        return memo[key]

    def cost(z):
        rows, _ = run(z)
        u = rows[:, 5] / U
        dt = np.diff(rows[:, 0])
        return z[0] + z[1] + 0.2 * np.sum(dt * u[1:] ** 2) + 0.002 * np.sum(
            np.diff(u) ** 2 / dt)

    def end(z):
        rows, _ = run(z)
        return np.array([rows[-1, 1] * 10.0, rows[-1, 2], rows[-1, 4]])

    def path(z):
        rows, k = run(z)
        th = rows[k::4, 1]
        return np.concatenate([th + spec.lean_max, spec.theta_0 - th[1:],
                               u_tail / U - z[2:3 + n_a]])

    back = -(M + m) * spec.run_up_acceleration / U
    bounds = ([(0.05, 3.0), (0.15, 1.5)] + [(back, 1.0)] * (1 + n_a)
              + [(-1.0, 1.0)] * (1 + KNOTS_FLIGHT))
    # A start near the optimum's shape: full reverse, back to the tail's limit, a full push
    # that lifts the body, then braking.
    z0 = np.array([1.0 + 0.2 / spec.run_up_acceleration, 0.32, back, back, back, back, 0.6,
                   1.0, 1.0, 1.0, 0.5, 0.0, -0.5, -0.5, -0.3, -0.1])
    res = minimize(cost, z0, method='SLSQP', bounds=bounds,
                   constraints=[{'type': 'eq', 'fun': end}, {'type': 'ineq', 'fun': path}],
                   options={'maxiter': 300, 'ftol': 1e-10})
    if np.max(np.abs(end(res.x))) > 1e-4 or np.min(path(res.x)) < -1e-5:
        raise RuntimeError('the rise plan did not converge: %s' % res.message)
    z = np.concatenate([res.x[:2], res.x[2:] * U])
    return _simulate(p, spec, z, steps=400)


def sample_plan(spec: RiseSpec, plan) -> np.ndarray:
    """
    Return the plan at the control period: rows [t, theta, theta_dot, x, x_dot, u_ff, on_tail].

    plan: ``plan_rise``'s (rows, index of the lift-off row), interpolated linearly.
    """
    rows, k = plan
    # Every tick up to the first at or after the plan's end, which gets the end itself.
    t = np.minimum(np.arange(int(math.ceil(rows[-1, 0] / spec.dt - 1e-9)) + 1) * spec.dt,
                   rows[-1, 0])
    out = np.zeros((t.size, 7))
    out[:, 0] = t
    for j in range(1, 6):
        out[:, j] = np.interp(t, rows[:, 0], rows[:, j])
    out[:, 6] = t < rows[k, 0]
    return out


def _jacobians(p: RobotParams, l: float, theta, theta_dot, u, on_tail: bool):
    """Continuous-time (A 4x4, B (4,)) of model (1) (on the tail: the rolling robot)."""
    m, M, g = p.body_mass, p.wheel_mass, p.gravity
    A = np.zeros((4, 4))
    A[2, 3] = 1.0
    if on_tail:
        return A, np.array([0.0, 0.0, 0.0, 1.0 / (M + m)])
    A[0, 1] = 1.0
    eps = 1e-6
    f0 = np.array(_flight_accel(theta, theta_dot, u, l, m, M, g))
    A[[1, 3], 0] = (np.array(_flight_accel(theta + eps, theta_dot, u, l, m, M, g)) - f0) / eps
    A[[1, 3], 1] = (np.array(_flight_accel(theta, theta_dot + eps, u, l, m, M, g)) - f0) / eps
    b = (np.array(_flight_accel(theta, theta_dot, u + eps, l, m, M, g)) - f0) / eps
    return A, np.array([0.0, b[0], 0.0, b[1]])


def tracking_gains(p: RobotParams, spec: RiseSpec, rows: np.ndarray, Q=None,
                   R=None) -> np.ndarray:
    """
    Return the time-varying LQR gains K_k (n x 4) about the sampled plan ``rows``.

    Discrete Riccati recursion backwards over the plan (Q dt, R dt per tick, Euler-discretized
    with the second-order term), starting from the stationary solution at upright rest.
    u = u_ff + K_k (xi - xi_ref). On the tail the pitch columns are zero (module docstring).
    """
    from scipy.linalg import solve_discrete_are
    Q = (DEFAULT_Q if Q is None else np.asarray(Q, dtype=float)) * spec.dt
    R = (DEFAULT_R if R is None else float(R)) * spec.dt
    dt = spec.dt

    def discrete(A, B):
        Ad = np.eye(4) + dt * A + 0.5 * dt * dt * A @ A
        return Ad, (dt * B + 0.5 * dt * dt * A @ B).reshape(4, 1)

    Ad, Bd = discrete(*_jacobians(p, spec.l, 0.0, 0.0, 0.0, False))
    P = solve_discrete_are(Ad, Bd, Q, np.array([[R]]))
    n = rows.shape[0]
    K = np.zeros((n, 4))
    for k in range(n - 1, -1, -1):
        Ad, Bd = discrete(*_jacobians(p, spec.l, rows[k, 1], rows[k, 2], rows[k, 5],
                                      rows[k, 6] > 0.5))
        BtP = Bd.T @ P
        gain = np.linalg.solve(R + BtP @ Bd, BtP @ Ad)
        K[k] = -gain.reshape(4)
        Acl = Ad - Bd @ gain
        P = Q + Ad.T @ P @ Acl
        P = 0.5 * (P + P.T)
        if rows[k, 6] > 0.5:
            K[k, :2] = 0.0
    return K


def rise_table(p: RobotParams, spec: RiseSpec) -> np.ndarray:
    """Return the plan with its gains, n x COLUMNS (module constant), solved once and cached."""
    def solve():
        rows = sample_plan(spec, plan_rise(p, spec))
        K = tracking_gains(p, spec, rows)
        return np.column_stack([rows[:, :6], K, rows[:, 6]])
    inputs = {'model': table_cache.floats(p), 'spec': table_cache.floats(spec),
              'Q': table_cache.floats(DEFAULT_Q), 'R': float(DEFAULT_R),
              'knots': [KNOTS_TAIL, KNOTS_FLIGHT], 'tail_margin': U_TAIL_MARGIN}
    return table_cache.table('rise_plan', inputs, solve)


class PlannedRise:
    """
    The rise's tracker, per tick: u = u_ff(k) + K(k) (xi - xi_ref(k)) at tick k since arming.

    xi = [theta~ - d_0, theta_dot, x, x_dot] with d_0 the IMU offset estimate at arming (the
    observer's linear model does not hold at large angles, so its d_hat is not used during the
    rise). ``running``: begun and not yet handed over (core/pipeline.py hands over). After the
    plan's last row (``finished``) the last gain holds the plan's end.
    """

    def __init__(self, p: RobotParams, spec: RiseSpec, max_error: float = math.radians(8.0)):
        """Look the plan of ``spec`` up (or solve it once: ``rise_table``)."""
        self.p = p
        self.spec = spec
        #: |pitch - the plan's| beyond which the plan is left [rad] (``off_plan``).
        self.max_error = max_error
        table = rise_table(p, spec)
        self.rows = [tuple(float(v) for v in r) for r in table]
        self.duration = float(table[-1, 0])
        self.running = False
        self._k = 0
        self._d0 = 0.0
        self._num = self._den = 0.0
        self._last = None   # (theta, theta_dot, x_dot) of the last tick in flight

    def applies(self, theta: float, theta_dot: float, l: float, max_wheel_torque: float,
                tolerance: float = math.radians(6.0)) -> bool:
        """
        Return True when a robot fits the plan: on the tail, at its height and torque limit.

        theta: pitch with the offset estimate removed [rad]; theta_dot [rad/s]; l [m];
        max_wheel_torque: the limit now [N m] (a derated wheel motor does not fit).
        """
        return (abs(l - self.spec.l) < 0.02 and abs(theta - self.spec.theta_0) < tolerance
                and abs(theta_dot) < 0.2 and max_wheel_torque >= self.spec.max_wheel_torque)

    def start(self, d_0: float) -> None:
        """Arming: the plan begins at its first row, with the IMU offset estimate d_0 [rad]."""
        self.running, self._k, self._d0 = True, 0, d_0
        self._num = self._den = 0.0
        self._last = None

    def stop(self) -> None:
        """End the plan (handed over, or not used)."""
        self.running = False

    @property
    def finished(self) -> bool:
        """Return True once the last row of the plan has been used."""
        return self._k >= len(self.rows)

    @property
    def on_tail(self) -> bool:
        """Return True while running and the body has not left the tail (by plan and gyro)."""
        return self.running and self._last is None and self._k < len(self.rows)

    def off_plan(self, theta: float) -> bool:
        """Return True when the pitch theta~ [rad] is over max_error from this tick's row."""
        r = self.rows[min(self._k, len(self.rows) - 1)]
        return not abs(theta - self._d0 - r[1]) <= self.max_error   # NaN: off the plan

    @property
    def offset(self) -> float:
        """
        Return the IMU offset as the flight shows it [rad]: d_0 plus what (4a) says is left.

        Model (1)'s pendulum row, l theta_ddot = g sin(theta) - cos(theta) x_ddot, holds
        whatever the masses; with theta = theta~ - d_0 - delta and delta small, summed over the
        flight's ticks, delta = -sum(l dtheta_dot - g s dt + c dx_dot) / sum(g c dt + s dx_dot)
        (s, c of theta~ - d_0). Used once the sum has seen OFFSET_EVIDENCE [m/s] (about 0.1 s
        of flight), at most OFFSET_MAX from d_0.
        """
        if abs(self._den) < OFFSET_EVIDENCE:
            return self._d0
        delta = -self._num / self._den
        return self._d0 + max(-OFFSET_MAX, min(OFFSET_MAX, delta))

    def _learn(self, theta: float, theta_dot: float, x_dot: float, dt: float) -> None:
        """Add this tick of the flight to the offset's sums (``offset``)."""
        last = self._last
        self._last = (theta, theta_dot, x_dot)
        if last is None:
            return
        th = 0.5 * (theta + last[0]) - self._d0
        s, c = math.sin(th), math.cos(th)
        dv = x_dot - last[2]
        g = self.p.gravity
        self._num += self.spec.l * (theta_dot - last[1]) - g * s * dt + c * dv
        self._den += g * c * dt + s * dv

    def step(self, theta: float, theta_dot: float, x: float, x_dot: float) -> float:
        """Return the force u [N] of this tick (theta~ [rad] as measured) and move on a row."""
        rows = self.rows
        k = self._k
        r = rows[min(k, len(rows) - 1)]
        self._k += 1
        # The sums start once the body has left the tail (the tail's push is not in (4a)).
        if r[10] < 0.5 and k < len(rows) and (self._last is not None or theta_dot < -LIFTED_RATE):
            self._learn(theta, theta_dot, x_dot, self.spec.dt)
        u = (r[5] + r[6] * (theta - self.offset - r[1]) + r[7] * (theta_dot - r[2])
             + r[8] * (x - r[3]) + r[9] * (x_dot - r[4]))
        return u if math.isfinite(u) else 0.0


def on_tail_rows(table: np.ndarray) -> int:
    """Return how many rows of a plan table are on the tail (the run-up)."""
    return int(np.sum(table[:, 10] > 0.5))


def plan_summary(table: np.ndarray) -> dict:
    """Return the plan's figures: duration, lift-off, run-up speed and travel, peak force."""
    k = on_tail_rows(table)
    return {'duration_s': float(table[-1, 0]), 'lift_off_s': float(table[k, 0]),
            'run_up_speed_mps': float(table[k, 4]), 'min_x_m': float(np.min(table[:, 3])),
            'end_x_m': float(table[-1, 3]), 'peak_force_n': float(np.max(np.abs(table[:, 5]))),
            'min_theta_deg': math.degrees(float(np.min(table[:, 1])))}
