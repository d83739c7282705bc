"""
BalanceCore: the shared control tick. Controller switches are bumpless and keep the robot up.

Closed loop on the nonlinear plant of core/simulation.py (model (1), 2 ms zero-order hold).
"""
import math

from hypothesis import given, settings, strategies as st
import pytest

from wheelleg_balance.core.params import RobotParams, TABLE_I_IDA_PBC
from wheelleg_balance.core.pipeline import (
    BalanceCore, CONTROLLER_NAMES, CoreConfig, Measurement, Reference)
from wheelleg_balance.core.simulation import Plant, Scenario

DT = 0.002


@pytest.fixture(scope='module')
def core_factory():
    """Build cores once per configuration: construction computes the schedules (~1 s)."""
    cache = {}

    def make(blend=0.1, controller='ida_pbc'):
        key = (blend, controller)
        if key not in cache:
            cache[key] = BalanceCore(RobotParams(), CoreConfig(
                controller=controller, switch_blend_time=blend, d_hat0=math.radians(2.7)))
        return cache[key]
    return make


def run_with_switch(core, first, second, t_switch=3.0, duration=6.0, x_dot_ref=0.3):
    """Balance with ``first``, switch to ``second`` at t_switch; return per-tick u and pitch."""
    sc = Scenario(theta0=math.radians(5.0), imu_offset=math.radians(2.2), duration=duration)
    plant = Plant(sc)
    core.select(first)
    us, thetas = [], []
    for k in range(int(duration / DT)):
        t = k * DT
        meas = plant.sensors(t)
        if k == 0:
            core.reset(meas)
        if abs(t - t_switch) < DT / 2:
            core.select(second)
        ref = Reference(x_dot_ref=x_dot_ref * min(1.0, t))
        out = core.step(meas, ref, DT)
        assert out.controller == (first if t < t_switch - DT / 2 else second)
        us.append(out.u)
        thetas.append(plant.theta)
        plant.advance(out.tau_left, out.tau_right, t)
        assert not plant.fell, 'fell after switching %s -> %s at t=%.3f' % (first, second, t)
    k_switch = int(round(t_switch / DT))
    return us, thetas, k_switch


#: Largest tick-to-tick change of the applied force around a switch [N]: 5 N is 0.25 N m per
#: wheel per 2 ms tick, well inside what the motors follow smoothly.
MAX_SWITCH_STEP = 5.0


def max_step_around(us, k, after=60):
    """Largest |u[i+1] - u[i]| from the tick before the switch to ``after`` ticks past it."""
    return max(abs(us[i + 1] - us[i]) for i in range(k - 1, k + after))


@pytest.mark.parametrize('first,second', [
    ('ida_pbc', 'output_regulation'), ('output_regulation', 'ida_pbc'),
    ('ida_pbc', 'lqr'), ('lqr', 'ida_pbc')])
def test_switch_during_recovery_keeps_balance_without_torque_jump(core_factory, first, second):
    # Switch 0.2 s into the recovery from 5 deg, while the controllers still disagree.
    us, thetas, k = run_with_switch(core_factory(blend=0.1), first, second, t_switch=0.2)
    assert max_step_around(us, k) <= MAX_SWITCH_STEP
    assert max(abs(th) for th in thetas[k:]) < math.radians(10.0)


@pytest.mark.parametrize('first,second', [('ida_pbc', 'output_regulation'), ('ida_pbc', 'lqr')])
def test_blending_is_what_removes_the_jump(core_factory, first, second):
    """Without the blend the same switch steps u by far more: the test above can fail."""
    us_blend, _, k = run_with_switch(core_factory(blend=0.1), first, second, t_switch=0.2)
    us_raw, _, _ = run_with_switch(core_factory(blend=1e-9), first, second, t_switch=0.2)
    raw, blended = max_step_around(us_raw, k), max_step_around(us_blend, k)
    assert raw > MAX_SWITCH_STEP and raw > 10.0 * blended, (raw, blended)


def test_unknown_controller_is_refused_and_nothing_changes(core_factory):
    core = core_factory()
    before = core.active_controller
    with pytest.raises(ValueError):
        core.select('pid')
    assert core.active_controller == before
    with pytest.raises(ValueError):
        BalanceCore(RobotParams(), CoreConfig(controller='pid'))


finite_or_not = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                          st.floats(-10.0, 10.0))


@settings(max_examples=300, deadline=None, database=None)
@given(theta=finite_or_not, theta_dot=finite_or_not, wl=finite_or_not, wr=finite_or_not,
       l=finite_or_not, v=finite_or_not, w=finite_or_not,
       name=st.sampled_from(CONTROLLER_NAMES))
def test_torques_are_finite_and_within_limits_for_any_input(
        core_factory, theta, theta_dot, wl, wr, l, v, w, name):
    core = core_factory()
    core.select(name)
    meas = Measurement(theta, theta_dot, wl, wr, l)
    core.reset(Measurement(0.0, 0.0, 0.0, 0.0, 0.5))
    for _ in range(3):
        out = core.step(meas, Reference(v, w), DT)
        for tau in (out.tau_left, out.tau_right):
            assert math.isfinite(tau) and abs(tau) <= core.config.max_wheel_torque


def startup_overshoot_deg(d_hold_angle):
    """IDA-PBC (Table I, theta~ - d_hat) start-up from the tail; d = 2.2 deg, d_hat0 = 2.7."""
    from wheelleg_balance.core.simulation import simulate
    from wheelleg_balance.validation.paper.experiments import overshoot_deg
    sc = Scenario(controller='ida_pbc', duration=6.0, imu_offset=math.radians(2.2),
                  d_hat0=math.radians(2.7))
    core = BalanceCore(RobotParams(), CoreConfig(d_hat0=sc.d_hat0, ida_pbc=TABLE_I_IDA_PBC))
    core.observer.d_hold_angle = d_hold_angle
    result = simulate(sc, core=core)
    assert not result.fell
    return overshoot_deg(result), math.degrees(result.d_hat[-1])


def test_observer_holds_d_hat_while_lifting_off_the_tail():
    """Far from upright the linear observer mistakes model error for offset: the hold stops it."""
    held, d_end_held = startup_overshoot_deg(math.radians(10.0))
    free, d_end_free = startup_overshoot_deg(math.inf)
    assert held < 3.0, held
    assert free > 2.0 * held, (free, held)
    # Either way the estimate ends at the true offset once upright.
    assert abs(d_end_held - 2.2) < 0.1 and abs(d_end_free - 2.2) < 0.1
