"""LQR gain k_x, its schedule over the height l, and the units of Table I's k_x."""
import math
import timeit

from nonlinear_model import rk4
import numpy as np
import pytest

from wheelleg_balance.core.controller_base import ControlInput
from wheelleg_balance.core.lqr import (
    DEFAULT_Q, DEFAULT_R, GainSchedule, lqr_gain, table_i_force_gain)
from wheelleg_balance.core.model import linearize
from wheelleg_balance.core.output_regulation import LqrController
from wheelleg_balance.core.params import RobotParams, TABLE_I_K_X

P = RobotParams()
DT = 0.002
U_MAX = 2 * 12.0 / P.wheel_radius   # 12 N m per wheel
L_GRID = np.linspace(P.height_min, P.height_max, 67)   # every 5 mm


def max_real_eig(k, l):
    A, B = linearize(l, P)
    return max(np.linalg.eigvals(A + np.outer(B, k)).real)


def simulate(control, theta0, l, duration, substeps=4):
    """Nonlinear (1), u from ``control(state)`` held 2 ms and saturated at 12 N m per wheel."""
    state = [theta0, 0.0, 0.0, 0.0]
    log = []
    for _ in range(int(round(duration / DT))):
        u = max(-U_MAX, min(U_MAX, control(state)))
        log.append(state + [u])
        for _ in range(substeps):
            state = rk4(state, u, l, DT / substeps, P)
    log.append(state + [u])
    return np.array(log)


def min_return_difference(k, l, w=np.logspace(-3, 4, 1500)):
    """Return min over w of |1 - k (jw I - A)^-1 B| (>= 1 for every LQR gain, Kalman 1964)."""
    A, B = linearize(l, P)
    return min(abs(1.0 - k @ np.linalg.solve(1j * wi * np.eye(4) - A, B)) for wi in w)


def test_lqr_gain_stabilizes_and_is_optimal():
    """A + B k_x is Hurwitz and k_x meets Kalman's return-difference condition."""
    for l in L_GRID[::6]:
        k = lqr_gain(l, P)
        assert max_real_eig(k, l) < -0.3
        assert min_return_difference(k, l) >= 1.0 - 1e-6


def test_lqr_gain_sign_convention_and_weights():
    k = lqr_gain(0.37, P)
    # u = k_x xi: leaning forward (theta > 0) must push forward, like Table I's positive entries.
    assert np.all(k > 0)
    # A heavier input weight gives a gentler gain; a heavier x weight a stiffer position hold.
    assert np.all(np.abs(lqr_gain(0.37, P, R=4 * DEFAULT_R)) < np.abs(k))
    Q = DEFAULT_Q.copy()
    Q[2, 2] *= 4
    assert lqr_gain(0.37, P, Q=Q)[2] > 1.5 * k[2]


def test_default_gain_keeps_torque_modest():
    """10 deg of pitch asks for less than the 12 N m per wheel limit at every height."""
    for l in L_GRID:
        tau_per_wheel = lqr_gain(l, P)[0] * math.radians(10.0) * P.wheel_radius / 2
        assert tau_per_wheel < 12.0


def test_schedule_matches_lqr_on_grid_and_between():
    sched = GainSchedule(P)
    assert sched.heights[0] == pytest.approx(0.37) and sched.heights[-1] == pytest.approx(0.70)
    for h, k in zip(sched.heights, sched.gains):
        np.testing.assert_allclose(sched.gain(h), lqr_gain(h, P), rtol=1e-9)
        np.testing.assert_allclose(k, lqr_gain(h, P), rtol=1e-9)
    for l in L_GRID:   # includes midpoints between the 1 cm grid
        k = sched.gain(l)
        np.testing.assert_allclose(k, lqr_gain(l, P), rtol=2e-3)
        assert max_real_eig(k, l) < -0.3
        assert sched.gain_floats(l) == pytest.approx(tuple(k))


def test_schedule_clamps_and_validates():
    sched = GainSchedule(P, heights=np.array([0.4, 0.5, 0.6]))
    np.testing.assert_allclose(sched.gain(0.1), lqr_gain(0.4, P))
    np.testing.assert_allclose(sched.gain(0.9), lqr_gain(0.6, P))
    np.testing.assert_allclose(sched.gain(0.45), (lqr_gain(0.4, P) + lqr_gain(0.5, P)) / 2)
    with pytest.raises(ValueError):
        GainSchedule(P, heights=np.array([0.5, 0.4]))
    Q = np.diag([50.0, 1.0, 4.0, 10.0])
    np.testing.assert_allclose(GainSchedule(P, Q=Q, R=0.01).gain(0.5),
                               lqr_gain(0.5, P, Q, 0.01), rtol=1e-9)


def test_schedule_gain_is_cheap():
    sched = GainSchedule(P)
    n = 5000
    per_call = min(timeit.repeat(lambda: sched.gain_floats(0.4537), number=n, repeat=3)) / n
    assert per_call < 20e-6
    per_call = min(timeit.repeat(lambda: sched.gain(0.4537), number=n, repeat=3)) / n
    assert per_call < 20e-6


def test_table_i_units():
    """Table I's k_x: not stabilizing as a force gain; stabilizing as a torque gain."""
    force = table_i_force_gain(P, 'force')
    total = table_i_force_gain(P, 'total_torque')
    per_wheel = table_i_force_gain(P)
    np.testing.assert_allclose(force, TABLE_I_K_X)
    np.testing.assert_allclose(total, TABLE_I_K_X / P.wheel_radius)
    np.testing.assert_allclose(per_wheel, 2 * TABLE_I_K_X / P.wheel_radius)
    for l in L_GRID:
        assert max_real_eig(force, l) > 0.0
        # The x entry (0.001) leaves a pole near -1e-4 1/s: stable, but only just.
        assert max_real_eig(total, l) < 0.0
        assert max_real_eig(per_wheel, l) < 0.0
        A, B = linearize(l, P)
        for k in (total, per_wheel):
            fast = sorted(np.linalg.eigvals(A + np.outer(B, k)).real)[:3]
            assert max(fast) < -0.6
    with pytest.raises(ValueError):
        table_i_force_gain(P, 'newton')


def test_table_i_is_an_lqr_gain_over_more_heights_per_wheel():
    """Why per wheel is the default reading: Kalman's test passes at 0.60 m only per wheel."""
    total = table_i_force_gain(P, 'total_torque')
    per_wheel = table_i_force_gain(P, 'per_wheel_torque')
    assert min_return_difference(total, 0.37) >= 1.0 - 1e-6
    assert min_return_difference(per_wheel, 0.37) >= 1.0 - 1e-6
    assert min_return_difference(per_wheel, 0.60) >= 1.0 - 1e-6
    assert min_return_difference(total, 0.60) < 0.95
    assert min_return_difference(per_wheel, 0.70) < 0.99


@pytest.mark.parametrize('reading', ['total_torque', 'per_wheel_torque'])
@pytest.mark.parametrize('l', [0.37, 0.70])
def test_table_i_torque_readings_recover_nonlinear_model(reading, l):
    k = table_i_force_gain(P, reading)
    log = simulate(lambda s: float(k @ s), math.radians(10.0), l, 3.0)
    assert np.max(np.abs(log[:, 0])) <= math.radians(10.0) + 1e-9
    assert abs(log[-1, 0]) < math.radians(0.2) and abs(log[-1, 3]) < 0.05


def test_lqr_controller_recovers_from_10_deg_at_every_scheduled_height():
    sched = GainSchedule(P)
    worst = {'overshoot': 0.0, 'theta': 0.0, 'x_dot': 0.0, 'tau': 0.0}
    for l in sched.heights:
        ctl = LqrController(P, sched)
        s = ControlInput(l=float(l))
        ctl.reset(s)

        def control(state):
            s.theta, s.theta_dot, s.x, s.x_dot = state
            return ctl.compute(s)
        log = simulate(control, math.radians(10.0), float(l), 6.0)
        worst['overshoot'] = max(worst['overshoot'], -np.min(log[:, 0]))
        worst['theta'] = max(worst['theta'], abs(log[-1, 0]))
        worst['x_dot'] = max(worst['x_dot'], abs(log[-1, 3]))
        worst['tau'] = max(worst['tau'], np.max(np.abs(log[:, 4])) * P.wheel_radius / 2)
        assert np.max(log[:, 0]) <= math.radians(10.0) + 1e-9   # no growth beyond the start
    print('LQR from 10 deg, worst over %d heights: overshoot %.2f deg, |theta(6 s)| %.4f deg, '
          '|x_dot(6 s)| %.4f m/s, peak torque %.2f N m per wheel'
          % (len(sched.heights), math.degrees(worst['overshoot']), math.degrees(worst['theta']),
             worst['x_dot'], worst['tau']))
    assert worst['overshoot'] < math.radians(3.0)
    assert worst['theta'] < math.radians(0.05)
    assert worst['x_dot'] < 0.01
    assert worst['tau'] < 12.0   # no saturation needed
