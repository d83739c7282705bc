"""
Linear output regulation (9)-(10) and the plain linear controller u = k_x xi~ (experiment 1).

Regulator equations (Francis; the paper's ref. [6]). The offset d is a constant exosystem
(d_dot = 0) entering (5) as E_d d; the regulated output is y = C xi~ = [theta_dot, x_dot] (6).
A steady state xi~ = Pi d, u = Gamma d with y = 0 exists iff
    A Pi + B Gamma + E_d = 0,    C Pi = 0.                                          (R)
With E_d = -A e_1 (model.disturbance_input) the rows of (R) give pi_2 = pi_4 = 0 (C Pi = 0) and
    ((M+m) g / (M l)) (pi_1 - 1) - Gamma / (M l) = 0,   -(m g / M) (pi_1 - 1) + Gamma / M = 0,
whose only solution is pi_1 = 1, Gamma = 0 at every height l; pi_3 (where the robot stands) is
free because x is not in y. We take pi_3 = 0: the robot stands where it is, and the controller
    u = k_x (xi_hat - Pi d_hat) + Gamma d_hat = k_x xi_hat + k_d d_hat,   k_d = Gamma - k_x Pi,
gives k_d = -k_x[0]: the feedback sees the true pitch theta~_hat - d_hat. Table I's k_d = -167
against k_x[0] = 150 leaves (150 - 167) d in u, which the robot balances by driving at
x_dot = -(k_x[0] + k_d) d / k_x[3] ~ 6.5 cm/s for d = 2.2 deg (it creeps; test_output_regulation).

``check_regulator_solvable`` checks the discrete-time counterpart of (10) for the loop that runs
(plant (5) with a zero-order hold, the current-estimate observer of core/observer.py, u = K zeta):
1. the closed-loop matrix Phi of [xi~_k, zeta_k] is Schur (spectral radius < 1): the error system
   is asymptotically stable;
2. (10a) (I - Phi) X_c = Gamma_d has a unique solution X_c (I - Phi nonsingular; implied by 1);
3. (10b) [C 0] X_c = 0: the steady state has zero theta_dot and x_dot.
It also reports X_c's x entry (where the robot settles per radian of d; 0 for the k_d above) and
its d_hat entry (1: the observer is unbiased).

Velocity reference: both controllers feed back x - x_ref and x_dot - x_dot*, with x_ref moving at
x_dot* (so standing still is x_dot* = 0). x_ref is latched on ``reset`` (take-over) and kept within
``max_position_error`` of x so a long push does not wind up a large restoring force.

The hold (``HoldShape``, issue 12; docs/linear_control.md, "The hold"): output regulation as
balance_node runs it by default differs from (9) as printed in three ways, each a parameter:
- ``feedback: measured``: the pitch, pitch rate, position and speed come from the sensors
  (u = k_x [theta~ - d_hat, theta_dot, x - x_ref, x_dot - x_dot*]); only d_hat comes from the
  observer. Through the observer's xi_hat (``feedback: observer``, the paper's (9)) the loop
  keeps 2.3 dB of gain margin downwards, on the sensors 6.4 dB (docs/margins.md).
- a lean limit: the position and speed terms together ask for at most the force that holds the
  body at a steady lean of ``max_lean_hold`` while x_dot* = 0 and the robot rolls (a kicked
  robot rolls out and brakes gently instead of leaning back hard to stop: the cart-pole (1)
  decelerates at g tan(lean) only while leaning back by it), ``max_lean_rest`` while x_dot* = 0
  and it is near rest (|x_dot| <= ROLLING_SPEED: the position hold settles a creep without the
  slow swing a small limit gives it), ``max_lean_move`` while the stick asks for motion; the
  limit moves between them at ``lean_limit_rate``, so a change does not step u; while
  the hold sees the robot roll on slower to stop than half of what the limit's lean brakes, its
  limit grows at ``lean_limit_growth``, so a bias the
  limit cannot overcome (d_hat off while rolling, from friction model (1) lacks) does not keep
  it rolling; and it brakes at least at v^2 / (2 s_left), so a kick stops within
  ``max_roll_out`` of where the roll began (s_left: what is left of it);
- while x_dot* != 0 the position is not held (x_ref follows x): the robot tracks the speed and
  holds the spot where the command returns to zero, rather than making up the lag of the
  acceleration with an overshoot in speed.
Near the equilibrium none of the three limits is active, so the margins are those of the linear
feedback.
"""
from dataclasses import dataclass
import math

import numpy as np

from .controller_base import ControlInput
from .lqr import GainSchedule
from .model import disturbance_input, linearize
from .observer import C_HAT, discretize, DisturbanceObserver
from .params import CONTROL_PERIOD, RobotParams
from .schema import param

#: Regulated output (6): y = [theta_dot, x_dot] = C xi~.
C_OUT = np.array([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
#: Largest position error the position hold acts on [m] (x_ref follows beyond it).
MAX_POSITION_ERROR = 0.3
#: Above this speed error the robot counts as rolling (HoldShape.lean_limit_growth) [m/s].
ROLLING_SPEED = 0.05
#: max_roll_out's braking is judged on at least this much distance left [m] (the lean it
#: asks for stays finite; it is capped at max_lean_move anyway).
MIN_ROLL_LEFT = 0.01
#: Values of ``output_regulation.feedback``.
FEEDBACKS = ('measured', 'observer')


@dataclass(frozen=True)
class HoldShape:
    """How output regulation holds and moves the robot (module docstring, "The hold")."""

    feedback: str = param('measured', 'output regulation feeds back: measured = the sensors '
                          '(theta~ - d_hat, theta_dot, odometry x and x_dot; d_hat from the '
                          "observer) | observer = the observer's xi_hat, (9) as printed",
                          choices=FEEDBACKS)
    max_lean_hold: float = param(math.radians(0.15), 'output regulation, x_dot* = 0, rolling '
                                 '(|x_dot| > %g m/s): the position and speed terms ask for at '
                                 'most the force of this steady lean [rad] (braking at '
                                 'g tan(lean)); 0: no limit' % ROLLING_SPEED, 0.0, 0.5)
    max_lean_rest: float = param(math.radians(0.3), '... the same near rest (|x_dot| <= %g '
                                 'm/s) [rad]; 0: no limit' % ROLLING_SPEED, 0.0, 0.5)
    max_lean_move: float = param(math.radians(8.0), '... the same while x_dot* != 0 [rad]; '
                                 '0: no limit', 0.0, 0.5)
    lean_limit_rate: float = param(math.radians(20.0), 'how fast the lean limit moves from '
                                   'one to the other [rad/s]', 1e-3, 100.0)
    lean_limit_growth: float = param(math.radians(0.5), 'output regulation, x_dot* = 0: while '
                                     'the robot rolls on (|x_dot| > 0.05 m/s) slower to stop '
                                     'than half of braking at max_lean_hold, the hold limit '
                                     'grows at this rate [rad/s] (up to max_lean_move), so a '
                                     'bias (d_hat off while rolling: friction the model lacks) '
                                     'cannot keep it rolling', 0.0, 10.0)
    max_roll_out: float = param(2.0, 'output regulation, x_dot* = 0: a robot set rolling (a '
                                'kick) brakes at least hard enough to stop within this '
                                'distance of where the roll began [m] (the limit grows to '
                                'atan(v^2 / (2 g s_left))); 0: no such bound', 0.0, 100.0)


def regulator_solution(l: float, p: RobotParams) -> tuple:
    """
    Solve the regulator equations (R) with pi_3 = 0 (stand where you are).

    Returns (Pi shape (4,), Gamma float); raises ValueError if (R) has no exact solution.
    """
    A, B = linearize(l, p)
    E_d = disturbance_input(l, p)
    # Unknowns [Pi (4), Gamma]; equations A Pi + B Gamma = -E_d, C Pi = 0, pi_3 = 0.
    M = np.zeros((7, 5))
    M[:4, :4] = A
    M[:4, 4] = B
    M[4:6, :4] = C_OUT
    M[6, 2] = 1.0
    rhs = np.concatenate([-E_d, np.zeros(3)])
    sol, _, rank, _ = np.linalg.lstsq(M, rhs, rcond=None)
    if rank < 5 or np.linalg.norm(M @ sol - rhs) > 1e-9 * (1.0 + np.linalg.norm(rhs)):
        raise ValueError('regulator equations have no unique solution at l = %g' % l)
    return sol[:4], float(sol[4])


def regulator_kd(k_x, l: float, p: RobotParams) -> float:
    """Return k_d = Gamma - k_x Pi [N/rad] for the gain k_x (u = k_x xi) at height l [m]."""
    Pi, Gamma = regulator_solution(l, p)
    return float(Gamma - np.asarray(k_x, dtype=float) @ Pi)


@dataclass(frozen=True)
class RegulatorCheck:
    """
    Result of ``check_regulator_solvable``.

    solvable: schur and unique and output_residual <= tol.
    spectral_radius: of the closed-loop matrix Phi (schur: < 1).
    unique: I - Phi is nonsingular (condition number below 1e12).
    X_c: steady state [xi~ (4), zeta (5)] per radian of d.
    output_residual: |[C 0] X_c| [(rad/s, m/s) per rad].
    displacement: X_c's x entry [m per rad of d]; d_hat_gain: X_c's d_hat entry.
    """

    solvable: bool
    spectral_radius: float
    unique: bool
    X_c: np.ndarray
    output_residual: float
    displacement: float
    d_hat_gain: float


def closed_loop_matrices(k_x, k_d: float, l: float, p: RobotParams,
                         observer: DisturbanceObserver) -> tuple:
    """
    Return (Phi 9x9, Gamma_d (9,)) of the sampled closed loop w_{k+1} = Phi w_k + Gamma_d d.

    w_k = [xi~_k, zeta_k]; xi~_{k+1} = Ad xi~_k + Bd u_k + Ed d (ZOH of (5)), u_k = K zeta_k with
    K = [k_x, k_d], zeta_{k+1} = F zeta_k + G u_k + L C_m xi~_{k+1} (core/observer.py).
    """
    Ad5, Bd5 = discretize(l, p, observer.dt)
    Ad, Ed, Bd = Ad5[:4, :4], Ad5[:4, 4], Bd5[:4]
    F, G, L = observer.matrices(l)
    K = np.append(np.asarray(k_x, dtype=float), k_d).reshape(1, 5)
    Cm = C_HAT[:, :4]
    Phi = np.zeros((9, 9))
    Phi[:4, :4] = Ad
    Phi[:4, 4:] = Bd.reshape(4, 1) @ K
    Phi[4:, :4] = L @ Cm @ Ad
    Phi[4:, 4:] = F + G.reshape(5, 1) @ K + L @ Cm @ Bd.reshape(4, 1) @ K
    Gamma_d = np.concatenate([Ed, L @ Cm @ Ed])
    return Phi, Gamma_d


def check_regulator_solvable(k_x, k_d: float, l: float, p: RobotParams,
                             observer: DisturbanceObserver, tol: float = 1e-9) -> RegulatorCheck:
    """
    Check the discrete-time (10) for gains K = [k_x, k_d] and ``observer``'s L at height l.

    See the module docstring for exactly what is checked.
    """
    Phi, Gamma_d = closed_loop_matrices(k_x, k_d, l, p, observer)
    rho = float(max(abs(np.linalg.eigvals(Phi))))
    I_Phi = np.eye(9) - Phi
    unique = bool(np.linalg.cond(I_Phi) < 1e12)
    if unique:
        X_c = np.linalg.solve(I_Phi, Gamma_d)
    else:
        X_c = np.full(9, np.nan)
    residual = float(np.linalg.norm(C_OUT @ X_c[:4])) if unique else float('inf')
    return RegulatorCheck(
        solvable=bool(rho < 1.0 and unique and residual <= tol), spectral_radius=rho,
        unique=unique, X_c=X_c, output_residual=residual, displacement=float(X_c[2]),
        d_hat_gain=float(X_c[8]))


#: Output regulation as (9) prints it: the observer's xi_hat fed back, no lean limit.
PAPER_HOLD = HoldShape(feedback='observer', max_lean_hold=0.0, max_lean_rest=0.0,
                       max_lean_move=0.0)


class _PositionReference:
    """x_ref moving at x_dot*, latched on take-over, kept within MAX_POSITION_ERROR of x."""

    def __init__(self, dt: float, max_error: float):
        self.dt = dt
        self.max_error = max_error
        self.x_ref = 0.0

    def error(self, x: float, x_dot_ref: float) -> float:
        e = x - self.x_ref
        if e > self.max_error:
            self.x_ref = x - self.max_error
            e = self.max_error
        elif e < -self.max_error:
            self.x_ref = x + self.max_error
            e = -self.max_error
        self.x_ref += x_dot_ref * self.dt
        return e


class OutputRegulationController:
    """
    Output regulation (9): u = k_x(l) zeta_hat[:4] + k_d(l) d_hat, k_d = -k_x(l) Pi.

    Uses the observer state s.xi_hat (it does not run the observer). With x_dot* = 0 the robot
    stands still where it was when this controller took over, whatever the IMU offset d.
    ``shape`` (HoldShape): which states are fed back, the lean limit, the move rule.
    """

    name = 'output_regulation'

    def __init__(self, p: RobotParams, schedule: GainSchedule, dt: float = CONTROL_PERIOD,
                 max_position_error: float = MAX_POSITION_ERROR,
                 shape: HoldShape = HoldShape()):
        self.p = p
        self.schedule = schedule
        self.shape = shape
        Pi, Gamma = regulator_solution(p.height_min, p)
        # Pi = e_1 and Gamma = 0 at every l (module docstring); the tests check it on a grid.
        self._pi = tuple(float(v) for v in Pi)
        self._gamma = Gamma
        self._ref = _PositionReference(dt, max_position_error)
        self._weight = (p.body_mass + p.wheel_mass) * p.gravity   # (M + m) g [N]
        self._lean = shape.max_lean_hold
        # _roll_extra's state: speed when the rolling began [m/s], time [s] and distance [m]
        # since, extra lean [rad].
        self._roll_v0 = self._roll_t = self._roll_s = self._extra = 0.0

    def k_d(self, l: float) -> float:
        """Return the gain on d_hat at height l [m]: Gamma - k_x(l) Pi [N/rad]."""
        k = self.schedule.gain_floats(l)
        return self._gamma - sum(ki * pi for ki, pi in zip(k, self._pi))

    def reset(self, s: ControlInput) -> None:
        """Hold the position at take-over (measured or estimated, as fed back)."""
        measured = self.shape.feedback == 'measured'
        self._ref.x_ref = float(s.x if measured else s.xi_hat[2])
        self._lean = self._lean_target(s.x_dot_ref, s.x_dot - s.x_dot_ref)
        self._roll_v0 = self._roll_t = self._roll_s = self._extra = 0.0

    def _lean_target(self, x_dot_ref: float, speed_error: float) -> float:
        sh = self.shape
        if x_dot_ref != 0.0:
            lean = sh.max_lean_move
        elif abs(speed_error) > ROLLING_SPEED:
            lean = sh.max_lean_hold
        else:
            lean = sh.max_lean_rest
        return lean if lean > 0.0 else math.inf

    def _roll_extra(self, x_dot_ref: float, speed: float, lean: float) -> float:
        """
        Return the extra lean [rad] the hold allows a rolling robot, beyond ``lean``.

        Two rules, the larger wins. Braking at a steady lean ``lean`` slows the robot at
        g tan(lean); one rolling on at less than half that (a bias the limit cannot overcome)
        gets lean_limit_growth per second more. And a robot at ``speed`` with s_left of
        max_roll_out still to go must brake at speed^2 / (2 s_left), which the lean
        atan(speed^2 / (2 g s_left)) does (the cart-pole (1) decelerates at g tan(lean)):
        a kick cannot send it rolling for metres at the gentle limit.
        """
        if x_dot_ref != 0.0 or speed <= ROLLING_SPEED:
            self._roll_v0 = self._roll_t = self._roll_s = self._extra = 0.0
            return 0.0
        dt = self._ref.dt
        if speed > self._roll_v0:   # a new disturbance: judge the slowing from here
            self._roll_v0, self._roll_t = speed, 0.0
        if speed > self._roll_v0 - 0.5 * self.p.gravity * math.tan(lean) * self._roll_t:
            self._extra += self.shape.lean_limit_growth * dt
        self._roll_t += dt
        self._roll_s += speed * dt
        extra = self._extra
        if self.shape.max_roll_out > 0.0:
            s_left = max(self.shape.max_roll_out - self._roll_s, MIN_ROLL_LEFT)
            extra = max(extra, math.atan(speed * speed / (2.0 * self.p.gravity * s_left))
                        - lean)
        return extra

    def compute(self, s: ControlInput) -> float:
        """Return the force u [N]."""
        return self.compute_floats(s.theta, s.theta_dot, s.x, s.x_dot, s.l, s.x_dot_ref,
                                   s.xi_hat.tolist())

    def compute_floats(self, theta: float, theta_dot: float, x: float, x_dot: float, l: float,
                       x_dot_ref: float, xi_hat) -> float:
        """``compute`` on ControlInput's fields (xi_hat: five floats), the tick's path."""
        k0, k1, k2, k3 = self.schedule.gain_floats(l)
        z0, z1, z2, z3, d_hat = xi_hat
        if self.shape.feedback == 'measured':
            z0, z1, z2, z3 = theta, theta_dot, x, x_dot
        p0, p1, p2, p3 = self._pi
        x = z2 - p2 * d_hat
        # ref.error(x, x_dot_ref) inline (_PositionReference: x_ref moving at x_dot*, within
        # max_error of x); while moving, x_ref = x: track the speed, hold where the command ends
        ref = self._ref
        x_ref = x if x_dot_ref != 0.0 else ref.x_ref
        e_x = x - x_ref
        max_error = ref.max_error
        if e_x > max_error:
            x_ref = x - max_error
            e_x = max_error
        elif e_x < -max_error:
            x_ref = x + max_error
            e_x = -max_error
        ref.x_ref = x_ref + x_dot_ref * ref.dt
        e_v = z3 - p3 * d_hat - x_dot_ref
        outer = k2 * e_x + k3 * e_v
        limit = self._outer_limit(k0, x_dot_ref, e_v)
        # max(-limit, min(limit, outer)), as comparisons (a NaN outer gives +limit, as there)
        outer = outer if outer < limit else limit
        outer = outer if outer > -limit else -limit
        return k0 * (z0 - p0 * d_hat) + k1 * (z1 - p1 * d_hat) + outer + self._gamma * d_hat

    def _outer_limit(self, k0: float, x_dot_ref: float, speed_error: float) -> float:
        """Return the largest |position + speed term| [N]: the force of the lean limit."""
        # _lean_target and _roll_extra's reset inline (every tick); min(a, b) is written
        # b if b < a else a, max(a, b) b if b > a else a (the same, NaN included)
        sh = self.shape
        speed = abs(speed_error)
        if x_dot_ref != 0.0:
            lean = sh.max_lean_move
        elif speed > ROLLING_SPEED:
            lean = sh.max_lean_hold
        else:
            lean = sh.max_lean_rest
        if 0.0 < lean < math.inf:
            target = lean
            if x_dot_ref != 0.0 or speed <= ROLLING_SPEED:
                # _roll_extra's reset: no extra lean (target + 0.0 is target, within its cap)
                self._roll_v0 = self._roll_t = self._roll_s = self._extra = 0.0
            else:   # min(target + extra, max(max_lean_move, target))
                move = sh.max_lean_move
                cap = target if target > move else move
                target += self._roll_extra(x_dot_ref, speed, target)
                if cap < target:
                    target = cap
        else:
            target = math.inf   # no limit
        held = self._lean
        if math.isinf(target) or math.isinf(held):
            held = self._lean = target
        else:   # slew, so that a change of limit does not step u
            step = sh.lean_limit_rate * self._ref.dt
            d = target - held
            d = d if d < step else step
            held = self._lean = held + (d if d > -step else -step)
        if math.isinf(held):
            return math.inf
        # Linearized, u = k0 theta + outer holds a steady lean theta = -outer / (k0 - (M+m) g).
        gap = k0 - self._weight
        return (0.0 if 0.0 > gap else gap) * math.tan(1.5 if 1.5 < held else held)


class LqrController:
    """
    The paper's linear controller u = k_x(l) xi~ on the measured states (experiment 1).

    xi~ = [theta~, theta_dot, x - x_ref, x_dot - x_dot*]: the IMU offset is not compensated (the
    paper's choice). With d != 0 the robot settles k_x[0] d / k_x[2] from x_ref or, if that is
    beyond the position leash, drives at -(k_x[0] d - k_x[2] MAX_POSITION_ERROR) / k_x[3]
    (about -5 cm/s for d = 2.2 deg; docs/linear_control.md).
    """

    name = 'lqr'

    def __init__(self, p: RobotParams, schedule: GainSchedule, dt: float = CONTROL_PERIOD,
                 max_position_error: float = MAX_POSITION_ERROR):
        self.p = p
        self.schedule = schedule
        self._ref = _PositionReference(dt, max_position_error)

    def reset(self, s: ControlInput) -> None:
        """Hold the position measured at take-over."""
        self._ref.x_ref = float(s.x)

    def compute(self, s: ControlInput) -> float:
        """Return the force u [N]."""
        return self.compute_floats(s.theta, s.theta_dot, s.x, s.x_dot, s.l, s.x_dot_ref, None)

    def compute_floats(self, theta: float, theta_dot: float, x: float, x_dot: float, l: float,
                       x_dot_ref: float, xi_hat) -> float:
        """``compute`` on ControlInput's fields, the tick's path (xi_hat is not used)."""
        k0, k1, k2, k3 = self.schedule.gain_floats(l)
        e_x = self._ref.error(x, x_dot_ref)
        return k0 * theta + k1 * theta_dot + k2 * e_x + k3 * (x_dot - x_dot_ref)
