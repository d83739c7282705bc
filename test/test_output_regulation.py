"""Observer (7)-(8), output regulation (9)-(10) and the linear controllers, in closed loop."""
import math
import timeit

from nonlinear_model import rk4
import numpy as np
import pytest

from wheelleg_balance.core.controller_base import ControlInput
from wheelleg_balance.core.lqr import GainSchedule, table_i_force_gain
from wheelleg_balance.core.model import disturbance_input, linearize
from wheelleg_balance.core.observer import (
    C_HAT, DEFAULT_OBSERVER_POLES, discretize, DisturbanceObserver)
from wheelleg_balance.core.output_regulation import (
    check_regulator_solvable, HoldShape, LqrController, MAX_POSITION_ERROR,
    OutputRegulationController, PAPER_HOLD, regulator_kd, regulator_solution)
from wheelleg_balance.core.params import RobotParams, TABLE_I_K_D

P = RobotParams()
DT = 0.002
U_MAX = 2 * 12.0 / P.wheel_radius   # 12 N m per wheel
D_TRUE = math.radians(2.2)          # the paper's standing-still experiment
D_HAT0 = math.radians(2.7)
L_GRID = np.linspace(P.height_min, P.height_max, 67)


@pytest.fixture(scope='module')
def schedule():
    return GainSchedule(P)


@pytest.fixture(scope='module')
def observer():
    return DisturbanceObserver(P)


def simulate_output_regulation(l, duration, controller=None, d=D_TRUE, d_hat0=D_HAT0,
                               substeps=4, height=None):
    """
    Nonlinear model (1) under output regulation, u held 2 ms (zero-order hold).

    The observer sees theta~ = theta + d and x; it starts exact except d_hat = d_hat0. The robot
    starts upright at rest; ``height(t)``, if given, moves l. Returns rows
    [t, theta, theta_dot, x, x_dot, d_hat, u].
    """
    schedule = GainSchedule(P)
    obs = DisturbanceObserver(P, DT)
    ctl = controller(schedule) if controller else OutputRegulationController(P, schedule)
    state = [0.0, 0.0, 0.0, 0.0]
    obs.reset([state[0] + d, state[1], state[2], state[3], d_hat0])
    s = ControlInput(l=l, xi_hat=obs.xi_hat)
    ctl.reset(s)
    u = 0.0
    log = []
    for k in range(int(round(duration / DT)) + 1):
        if height is not None:
            l = s.l = height(k * DT)
        s.xi_hat = obs.update(state[0] + d, state[2], u, l)
        s.theta, s.theta_dot, s.x, s.x_dot = state[0] + d, state[1], state[2], state[3]
        u = max(-U_MAX, min(U_MAX, ctl.compute(s)))
        log.append([k * DT] + state + [s.xi_hat[4], u])
        for _ in range(substeps):
            state = rk4(state, u, l, DT / substeps, P)
    return np.array(log)


class FixedKd:
    """OutputRegulationController with its k_d replaced (to show what a wrong k_d does)."""

    name = 'fixed_kd'

    def __init__(self, k_x, k_d):
        self.k_x, self.k_d = k_x, k_d

    def reset(self, s):
        pass

    def compute(self, s):
        return float(self.k_x @ s.xi_hat[:4] + self.k_d * s.xi_hat[4])


# --- regulator equations and the solvability check -----------------------------------------


@pytest.mark.parametrize('l', [0.37, 0.45, 0.52, 0.61, 0.70])
def test_regulator_solution(l):
    """Pi = e_1, Gamma = 0 solve A Pi + B Gamma + E_d = 0, C Pi = 0 at every height."""
    Pi, Gamma = regulator_solution(l, P)
    A, B = linearize(l, P)
    np.testing.assert_allclose(A @ Pi + B * Gamma + disturbance_input(l, P), 0.0, atol=1e-9)
    np.testing.assert_allclose(Pi, [1.0, 0.0, 0.0, 0.0], atol=1e-12)
    assert Gamma == pytest.approx(0.0, abs=1e-9)
    k_x = np.array([900.0, 150.0, 100.0, 200.0])
    assert regulator_kd(k_x, l, P) == pytest.approx(-900.0)
    assert regulator_kd(table_i_force_gain(P), l, P) == pytest.approx(-3000.0)


def test_regulator_check_for_the_gains_in_use(schedule, observer):
    for l in L_GRID:
        k_x = schedule.gain(l)
        r = check_regulator_solvable(k_x, regulator_kd(k_x, l, P), l, P, observer)
        assert r.solvable and r.unique
        assert r.spectral_radius < 0.999
        assert r.output_residual < 1e-9
        assert abs(r.displacement) < 1e-6      # stands where it is
        assert r.d_hat_gain == pytest.approx(1.0, abs=1e-9)   # d_hat -> d
        assert r.X_c[0] == pytest.approx(1.0, abs=1e-9)      # theta~ -> d: theta -> 0


def test_regulator_check_detects_failures(schedule, observer):
    l = 0.52
    k_x = schedule.gain(l)
    k_d = regulator_kd(k_x, l, P)
    # No position feedback: x is an uncontrolled integrator, X_c is not unique.
    r = check_regulator_solvable(k_x * [1.0, 1.0, 0.0, 1.0], k_d, l, P, observer)
    assert not r.solvable and not r.unique
    # Table I's k_x read as a force gain: the closed loop is not Schur.
    r = check_regulator_solvable(table_i_force_gain(P, 'force'), TABLE_I_K_D, l, P, observer)
    assert not r.solvable and r.spectral_radius > 1.0
    # Table I as per-wheel torque with its k_d: (10) is solvable but the steady state is
    # ~17000 m per rad of d away (the creep shown below); with the regulator's k_d it is 0.
    k_t = table_i_force_gain(P)
    r = check_regulator_solvable(k_t, TABLE_I_K_D * k_t[0] / 150.0, l, P, observer)
    assert r.solvable and r.displacement == pytest.approx(17000.0, rel=1e-3)
    r = check_regulator_solvable(k_t, regulator_kd(k_t, l, P), l, P, observer)
    assert r.solvable and abs(r.displacement) < 1e-6


# --- observer ------------------------------------------------------------------------------


def test_observer_error_poles_on_grid_and_between(observer):
    target = np.sort(np.exp(np.array(DEFAULT_OBSERVER_POLES) * DT))
    for i, h in enumerate(observer.heights):
        Ad, _ = discretize(h, P)
        L = observer.gains[i]
        eig = np.linalg.eigvals((np.eye(5) - L @ C_HAT) @ Ad)
        np.testing.assert_allclose(np.sort(eig.real), target, atol=1e-8)
        np.testing.assert_allclose(eig.imag, 0.0, atol=1e-8)
    for l in L_GRID:   # interpolated matrices between the grid heights stay convergent
        F, _, _ = observer.matrices(l)
        assert max(abs(np.linalg.eigvals(F))) < 1.0 - 0.5 * (1.0 - target.max())


def test_observer_converges_on_the_linear_model():
    """Exact discrete model (5), arbitrary input: every estimate error decays as placed."""
    l = 0.6
    obs = DisturbanceObserver(P, d_hold_angle=None)  # the paper's observer, no hold
    Ad, Bd = discretize(l, P)
    zeta = np.array([0.05, 0.1, 0.2, -0.1, math.radians(2.2)])   # true [theta~, .., d]
    obs.reset([0.0, 0.0, 0.0, 0.0, 0.0])
    u_prev = 0.0   # force applied over the last period
    errors = []
    for k in range(1000):   # 2 s
        zeta = Ad @ zeta + Bd * u_prev
        est = obs.update(zeta[0], zeta[2], u_prev, l)
        errors.append(np.abs(est - zeta))
        u_prev = 5.0 * math.sin(0.01 * k)
    errors = np.array(errors)
    # The slowest placed pole, -4 1/s, leaves e^-8 = 3.4e-4 of an error after 2 s; the fast
    # ones (-14 1/s and faster) e^-28 after the same time, so over the last second the error
    # shrinks as e^-4 (a slower decay, e.g. a pole at -3 1/s, gives e^-3 and fails).
    assert np.max(errors[0]) > 1e-3
    assert np.max(errors[-1]) < 5e-3 * np.max(errors[0])
    ratio = np.max(errors[-1]) / np.max(errors[-501])
    assert ratio == pytest.approx(math.exp(-4.0), rel=0.05)


def test_observer_survives_lost_measurement():
    obs = DisturbanceObserver(P)
    obs.reset([0.04, 0.0, 0.0, 0.0, 0.04])
    est = obs.update(float('nan'), 0.0, 1.0, 0.5)
    assert np.all(np.isfinite(est))
    Ad, Bd = discretize(0.5, P)
    np.testing.assert_allclose(est, Ad @ np.array([0.04, 0.0, 0.0, 0.0, 0.04]) + Bd * 1.0)
    est = obs.update(0.04, 0.0, float('inf'), 0.5)
    assert np.all(np.isfinite(est))


# --- closed loop on the nonlinear model ----------------------------------------------------


@pytest.mark.parametrize('l', [0.37, 0.52, 0.70])
def test_output_regulation_stands_still_under_unknown_offset(l):
    log = simulate_output_regulation(l, 20.0)
    t, x, x_dot, d_hat = log[:, 0], log[:, 3], log[:, 4], log[:, 5]
    err = np.abs(d_hat - D_TRUE)
    converged = t[np.nonzero(err >= math.radians(0.1))[0][-1] + 1]
    mean_v = np.mean(x_dot[t >= 19.0])
    drift = x[-1] - x[0]
    print('l=%.2f: |d_hat-d| < 0.1 deg from t=%.3f s, mean x_dot(19..20 s) %.2e m/s, '
          'drift %.2e m, max |x| %.4f m, max |u| %.1f N'
          % (l, converged, mean_v, drift, np.max(np.abs(x)), np.max(np.abs(log[:, 6]))))
    assert err[0] > math.radians(0.4)
    assert np.all(err[t >= 5.0] < math.radians(0.1))
    assert abs(mean_v) < 1e-3
    assert abs(drift) < 0.01


def test_output_regulation_while_the_height_changes():
    """
    Height sweep 0.37 -> 0.70 -> 0.37 m during the standing-still transient.

    l peaks at 0.26 m/s; gains and observer follow the schedule.
    """
    def height(t):
        return 0.535 - 0.165 * math.cos(2 * math.pi * t / 4.0)
    log = simulate_output_regulation(0.37, 16.0, height=height)
    t, err = log[:, 0], np.abs(log[:, 5] - D_TRUE)
    print('height sweep: max |d_hat - d| after 5 s %.2e deg, max |x| %.4f m, x(16 s) %.2e m'
          % (math.degrees(np.max(err[t >= 5.0])), np.max(np.abs(log[:, 3])), log[-1, 3]))
    assert np.max(np.abs(log[:, 3])) > 0.005   # the transient happened
    assert np.max(err[t >= 5.0]) < math.radians(0.1)
    assert abs(log[-1, 3]) < 0.01 and abs(log[-1, 4]) < 1e-3


def test_table_i_kd_creeps():
    """
    Table I's k_d = -167 leaves the robot driving; k_d = -k_x[0] keeps it still.

    Same k_x (Table I, per-wheel reading, k_d scaled alike), d_hat exact from the start.
    """
    k_x = table_i_force_gain(P)
    scale = k_x[0] / 150.0
    predicted = -(k_x[0] + TABLE_I_K_D * scale) * D_TRUE / k_x[3]   # quasi-steady speed
    creep = simulate_output_regulation(
        0.52, 10.0, controller=lambda _: FixedKd(k_x, TABLE_I_K_D * scale), d_hat0=D_TRUE)
    still = simulate_output_regulation(
        0.52, 10.0, controller=lambda _: FixedKd(k_x, regulator_kd(k_x, 0.52, P)),
        d_hat0=D_TRUE)
    v_creep = np.mean(creep[creep[:, 0] >= 9.0, 4])
    v_still = np.mean(still[still[:, 0] >= 9.0, 4])
    print('Table I k_d: mean x_dot(9..10 s) %.4f m/s (quasi-steady %.4f); regulator k_d: %.1e'
          % (v_creep, predicted, v_still))
    assert predicted == pytest.approx(0.065, abs=0.001)
    assert v_creep == pytest.approx(predicted, rel=0.05)
    assert abs(v_still) < 1e-4


def test_lqr_controller_without_offset_compensation_does_not_stand_still():
    """
    Experiment 1's u = k_x xi~ on theta~ = theta + d does not stand still.

    The robot leans on its position hold and, past the 0.3 m leash, keeps driving.
    """
    log = simulate_output_regulation(
        0.52, 10.0, controller=lambda sched: LqrController(P, sched))
    k = GainSchedule(P).gain(0.52)
    # Past the leash u = k_x[0] d - k_x[2] 0.3 + k_x[3] x_dot = 0 (theta = 0, u = 0).
    predicted = -(k[0] * D_TRUE - k[2] * MAX_POSITION_ERROR) / k[3]
    print('LQR on theta~ with d = 2.2 deg: x(10 s) = %.3f m, x_dot(10 s) = %.4f m/s '
          '(predicted %.4f)' % (log[-1, 3], log[-1, 4], predicted))
    assert log[-1, 3] < -MAX_POSITION_ERROR
    assert log[-1, 4] == pytest.approx(predicted, rel=0.05)


# --- controllers -------------------------------------------------------------------------------


def test_controllers_follow_the_schedule_and_velocity_reference(schedule):
    l = 0.45
    k = schedule.gain(l)
    # (9) as printed: the observer's xi_hat fed back (the sensors read the same here).
    orc = OutputRegulationController(P, schedule, shape=PAPER_HOLD)
    lqr = LqrController(P, schedule)
    xi_hat = np.array([0.05, 0.1, 0.02, 0.03, 0.04])
    s = ControlInput(theta=0.05, theta_dot=0.1, x=0.02, x_dot=0.03, l=l, xi_hat=xi_hat)
    s0 = ControlInput(l=l)
    orc.reset(s0)
    lqr.reset(s0)
    assert orc.compute(s) == pytest.approx(k @ xi_hat[:4] - k[0] * xi_hat[4])
    assert orc.k_d(l) == pytest.approx(-k[0])
    assert lqr.compute(s) == pytest.approx(k @ xi_hat[:4])
    # Take-over latches the position: no force from where the robot already is.
    orc.reset(s)
    lqr.reset(s)
    assert orc.compute(s) == pytest.approx(k @ xi_hat[:4] - k[0] * xi_hat[4] - k[2] * 0.02)
    # x_dot* moves x_ref: after 1 s at 0.2 m/s the reference is 0.2 m ahead.
    s.x_dot_ref = 0.2
    for _ in range(500):
        u = lqr.compute(s)
    assert u == pytest.approx(k @ [0.05, 0.1, -(0.2 - 0.2 * DT), 0.03 - 0.2])


@pytest.mark.parametrize('shape', [HoldShape(), PAPER_HOLD], ids=['measured', 'observer'])
def test_output_regulation_tracks_velocity_reference_both_feedbacks(shape):
    """The same through the sensors (balance_node's default) and through xi_hat ((9))."""
    obs = DisturbanceObserver(P)
    ctl = OutputRegulationController(P, GainSchedule(P), shape=shape)
    l, state, u = 0.6, [0.0, 0.0, 0.0, 0.0], 0.0
    obs.reset([D_TRUE, 0.0, 0.0, 0.0, 0.0])
    s = ControlInput(l=l, xi_hat=obs.xi_hat, x_dot_ref=0.3)
    ctl.reset(s)
    for _ in range(5000):
        s.theta, s.theta_dot, s.x, s.x_dot = state[0] + D_TRUE, state[1], state[2], state[3]
        s.xi_hat = obs.update(state[0] + D_TRUE, state[2], u, l)
        u = ctl.compute(s)
        for _ in range(4):
            state = rk4(state, u, l, DT / 4, P)
    assert state[3] == pytest.approx(0.3, abs=1e-3)
    assert abs(state[0]) < math.radians(0.05)
    assert s.xi_hat[4] == pytest.approx(D_TRUE, abs=math.radians(0.01))


def test_measured_feedback_uses_the_sensors_and_d_hat_only():
    sched = GainSchedule(P)
    l = 0.45
    k = sched.gain(l)
    ctl = OutputRegulationController(P, sched, shape=HoldShape(max_lean_hold=0.0,
                                                               max_lean_rest=0.0))
    ctl.reset(ControlInput(l=l))
    xi_hat = np.array([0.5, 0.5, 0.5, 0.5, 0.01])   # only d_hat of it may count
    s = ControlInput(theta=0.03, theta_dot=0.1, x=0.02, x_dot=0.04, l=l, xi_hat=xi_hat)
    assert ctl.compute(s) == pytest.approx(k @ [0.03 - 0.01, 0.1, 0.02, 0.04])


def _hold_force(ctl, l, x_dot, x_dot_ref=0.0, ticks=1):
    s = ControlInput(l=l, x_dot=x_dot, x_dot_ref=x_dot_ref)
    for _ in range(ticks):
        u = ctl.compute(s)
    return u


def test_the_lean_limit_caps_the_position_and_speed_terms():
    """Stopped at x_dot* = 0, a robot rolling at 0.5 m/s gets at most the force of the lean."""
    sched = GainSchedule(P)
    shape = HoldShape(lean_limit_growth=0.0, max_roll_out=0.0)
    l = 0.45
    k0 = sched.gain(l)[0]
    weight = (P.body_mass + P.wheel_mass) * P.gravity
    ctl = OutputRegulationController(P, sched, shape=shape)
    ctl.reset(ControlInput(l=l, x_dot=0.5))   # taken over rolling: the rolling limit at once
    cap = (k0 - weight) * math.tan(shape.max_lean_hold)
    u = _hold_force(ctl, l, 0.5)
    assert u == pytest.approx(cap, rel=1e-9)
    assert cap < 0.1 * sched.gain(l)[3] * 0.5   # it did cut: unlimited is ten times more
    assert _hold_force(ctl, l, -0.5) == pytest.approx(-cap, rel=1e-9)
    # On the linear model the steady lean of that force is the limit: theta = -u / (k0 - (M+m)g).
    assert math.atan(u / (k0 - weight)) == pytest.approx(shape.max_lean_hold)
    # 0 switches it off.
    free = OutputRegulationController(P, sched, shape=HoldShape(max_lean_hold=0.0))
    free.reset(ControlInput(l=l))
    assert _hold_force(free, l, 0.5) == pytest.approx(sched.gain(l)[3] * 0.5)


def test_near_rest_the_position_hold_gets_the_rest_limit():
    """Below 0.05 m/s at x_dot* = 0 the cap is max_lean_rest's, above it max_lean_hold's."""
    sched = GainSchedule(P)
    shape = HoldShape(lean_limit_growth=0.0, max_roll_out=0.0)
    assert shape.max_lean_rest > shape.max_lean_hold > 0.0
    l = 0.45
    gap = sched.gain(l)[0] - (P.body_mass + P.wheel_mass) * P.gravity
    ctl = OutputRegulationController(P, sched, shape=shape)
    ctl.reset(ControlInput(l=l))
    # 0.2 m behind the held spot, creeping at 0.04 m/s: the position term saturates.
    creep = ControlInput(l=l, x=-0.2, x_dot=0.04)
    ticks = int(math.ceil((shape.max_lean_rest - shape.max_lean_hold)
                          / (shape.lean_limit_rate * DT))) + 1
    for _ in range(ticks):
        u = ctl.compute(creep)
    assert abs(u) == pytest.approx(gap * math.tan(shape.max_lean_rest), rel=1e-9)
    # Kicked to 0.5 m/s: the limit closes to the rolling one at lean_limit_rate (no step).
    u1 = _hold_force(ctl, l, 0.5)
    assert abs(u1) == pytest.approx(
        gap * math.tan(shape.max_lean_rest - shape.lean_limit_rate * DT), rel=1e-9)
    u = _hold_force(ctl, l, 0.5, ticks=ticks)
    assert abs(u) == pytest.approx(gap * math.tan(shape.max_lean_hold), rel=1e-9)
    # The paper's (9) has no limit at all.
    assert PAPER_HOLD.max_lean_hold == PAPER_HOLD.max_lean_rest == PAPER_HOLD.max_lean_move == 0


def test_a_robot_that_rolls_on_gets_a_growing_limit_one_that_slows_does_not():
    sched = GainSchedule(P)
    shape = HoldShape(max_roll_out=0.0)   # the other rule: the next test
    l = 0.45
    gap = sched.gain(l)[0] - (P.body_mass + P.wheel_mass) * P.gravity
    base = gap * math.tan(shape.max_lean_hold)
    # Rolling on at a constant 0.4 m/s (a bias holds it there) for 2 s: the limit has grown by
    # lean_limit_growth * 2 s.
    ctl = OutputRegulationController(P, sched, shape=shape)
    ctl.reset(ControlInput(l=l))
    u = _hold_force(ctl, l, 0.4, ticks=1000)
    assert u == pytest.approx(gap * math.tan(shape.max_lean_hold + 2.0 * shape.lean_limit_growth),
                              rel=1e-3)
    # Slowing down as braking at the limit's lean does (g tan(lean)): no growth.
    ctl = OutputRegulationController(P, sched, shape=shape)
    ctl.reset(ControlInput(l=l))
    decel = P.gravity * math.tan(shape.max_lean_hold)
    for k in range(1000):
        u = _hold_force(ctl, l, 0.4 - decel * k * DT)
    assert u == pytest.approx(base, rel=1e-9)
    # Stopped (below 0.05 m/s): the extra is gone, the limit slews back to the rest limit's.
    _hold_force(ctl, l, 0.4, ticks=1000)
    u = _hold_force(ctl, l, 0.04, ticks=1000)
    assert abs(u) <= gap * math.tan(shape.max_lean_rest) + 1e-9


def test_a_rolling_robot_brakes_hard_enough_to_stop_within_max_roll_out():
    sched = GainSchedule(P)
    shape = HoldShape(lean_limit_growth=0.0)
    assert shape.max_roll_out > 0.0
    l = 0.45
    gap = sched.gain(l)[0] - (P.body_mass + P.wheel_mass) * P.gravity
    ctl = OutputRegulationController(P, sched, shape=shape)
    ctl.reset(ControlInput(l=l, x_dot=0.6))   # taken over rolling: the rolling limit at once
    # Rolling on at 0.6 m/s for 1 s (0.6 m of max_roll_out used): the cap is the force of the
    # lean that decelerates at v^2 / (2 s_left), the cart-pole's g tan(lean).
    ticks = 500
    u = _hold_force(ctl, l, 0.6, ticks=ticks)
    s_left = shape.max_roll_out - 0.6 * ticks * DT
    lean = math.atan(0.6 ** 2 / (2.0 * P.gravity * s_left))
    assert lean > shape.max_lean_hold   # the bound is what acts here
    assert u == pytest.approx(gap * math.tan(lean), rel=1e-6)
    # Rolled past max_roll_out: the cap is the move limit's (slewed there at lean_limit_rate).
    u = _hold_force(ctl, l, 0.6, ticks=1000 + int(shape.max_roll_out / 0.6 / DT))
    assert u == pytest.approx(min(gap * math.tan(shape.max_lean_move), sched.gain(l)[3] * 0.6),
                              rel=1e-9)
    # Slow enough to stop within what is left: only the rolling limit.
    ctl.reset(ControlInput(l=l, x_dot=0.1))
    assert _hold_force(ctl, l, 0.1) == pytest.approx(gap * math.tan(shape.max_lean_hold),
                                                     rel=1e-9)


def test_the_lean_limit_slews_to_the_move_limit_and_back():
    sched = GainSchedule(P)
    shape = HoldShape(lean_limit_growth=0.0, max_roll_out=0.0)
    l = 0.45
    k0 = sched.gain(l)[0]
    gap = (k0 - (P.body_mass + P.wheel_mass) * P.gravity)
    ctl = OutputRegulationController(P, sched, shape=shape)
    ctl.reset(ControlInput(l=l))
    # The stick asks for motion while the robot lags by 0.5 m/s: the limit opens at the rate
    # (from the rest limit: taken over at rest).
    u1 = _hold_force(ctl, l, 0.0, 0.5)
    lean1 = shape.max_lean_rest + shape.lean_limit_rate * DT
    assert -u1 == pytest.approx(gap * math.tan(lean1), rel=1e-9)
    ticks = int(math.ceil((shape.max_lean_move - shape.max_lean_rest)
                          / (shape.lean_limit_rate * DT))) + 1
    u = _hold_force(ctl, l, 0.0, 0.5, ticks)
    assert -u == pytest.approx(min(gap * math.tan(shape.max_lean_move),
                                   sched.gain(l)[3] * 0.5), rel=1e-9)
    # Back at x_dot* = 0 it closes at the same rate: no step in u.
    u_back = _hold_force(ctl, l, 0.5, 0.0)
    assert abs(u_back) <= gap * math.tan(shape.max_lean_move) + 1e-9
    assert abs(u_back) > gap * math.tan(shape.max_lean_hold)


def test_moving_holds_no_position_and_the_stop_holds_where_the_command_ended():
    sched = GainSchedule(P)
    l = 0.45
    k = sched.gain(l)
    shape = HoldShape(max_lean_hold=0.0, max_lean_rest=0.0, max_lean_move=0.0)
    ctl = OutputRegulationController(P, sched, shape=shape)
    ctl.reset(ControlInput(l=l))
    # 2 m further on at the commanded speed: no pull back to where it started.
    s = ControlInput(l=l, x=2.0, x_dot=0.3, x_dot_ref=0.3)
    assert ctl.compute(s) == pytest.approx(0.0, abs=1e-9)
    # The command ends at x = 2.1: that is the spot it holds.
    s = ControlInput(l=l, x=2.1, x_dot=0.3, x_dot_ref=0.3)
    ctl.compute(s)
    s = ControlInput(l=l, x=2.2, x_dot=0.0, x_dot_ref=0.0)
    assert ctl.compute(s) == pytest.approx(k[2] * (2.2 - 2.1 - 0.3 * DT), rel=1e-6)


def test_per_tick_calls_are_cheap(schedule):
    obs = DisturbanceObserver(P)
    obs.reset([0.03, 0.0, 0.0, 0.0, 0.04])
    orc = OutputRegulationController(P, schedule)
    lqr = LqrController(P, schedule)
    s = ControlInput(theta=0.01, theta_dot=0.02, x=0.01, l=0.45, xi_hat=obs.xi_hat)
    heights = [0.45 + 1e-5 * i for i in range(1000)]
    counter = iter(range(10 ** 9))
    n = 3000
    cases = {
        'observer (fixed l)': lambda: obs.update(0.03, 0.001, 1.0, 0.45),
        'observer (l changing)': lambda: obs.update(0.03, 0.001, 1.0,
                                                    heights[next(counter) % 1000]),
        'output_regulation': lambda: orc.compute(s),
        'lqr': lambda: lqr.compute(s),
    }
    for name, call in cases.items():
        per_call = min(timeit.repeat(call, number=n, repeat=3)) / n
        print('%s: %.2f us' % (name, per_call * 1e6))
        assert per_call < 25e-6, name


def test_a_live_parameter_set_reaches_the_running_hold():
    # ros2 param set of a hold parameter is live (docs/interface.md): the controller must see it.
    from wheelleg_balance.core.balance_loop import BalanceLoop
    from wheelleg_balance.core.config import BalanceConfig
    loop = BalanceLoop(BalanceConfig())
    hold = loop.core.controllers['output_regulation']
    assert hold.shape.max_roll_out == HoldShape().max_roll_out
    loop.apply_parameters({'output_regulation.max_roll_out': 0.5,
                           'output_regulation.max_lean_hold': 0.01})
    assert (hold.shape.max_roll_out, hold.shape.max_lean_hold) == (0.5, 0.01)
