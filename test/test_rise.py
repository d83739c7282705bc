"""The planned rise (core/rise.py) in closed loop on model (1): the paper's 1 deg, and robust."""
from dataclasses import replace
import math

import numpy as np
import pytest

from wheelleg_balance.core import rise, table_cache
from wheelleg_balance.core.params import RobotParams
from wheelleg_balance.core.pipeline import Reference
from wheelleg_balance.core.simulation import _build_core, Plant, Scenario, simulate
from wheelleg_balance.validation.paper.experiments import overshoot_deg
from wheelleg_balance.validation.paper.metrics import rest_point
from wheelleg_balance.validation.paper.table import REST_SPEED, STARTUP_TARGETS

P = RobotParams()
SPEC = rise.RiseSpec(l=P.height_min)


def planned_core(sc: Scenario, planned: bool = True):
    """Return the scenario's core with ``auto.planned_rise`` set (off by default)."""
    core = _build_core(sc)
    core.set_auto_rules(replace(core.config.auto, planned_rise=planned))
    return core


def start_up(planned: bool = True, **kw):
    """Return (run, core) of a start-up from the tail under ``controller: auto``."""
    sc = Scenario(controller='auto', duration=kw.pop('duration', 6.0), **kw)
    core = planned_core(sc, planned)
    return simulate(sc, core), core


def figures(r) -> tuple:
    t_rest, distance = rest_point(r.t, r.x_dot, r.x, REST_SPEED)
    return overshoot_deg(r), t_rest, distance


def test_the_plan_keeps_its_limits_and_ends_upright_at_rest():
    table = rise.rise_table(P, SPEC)
    m, M, g = P.body_mass, P.wheel_mass, P.gravity
    U = SPEC.force_share * 2.0 * SPEC.max_wheel_torque / P.wheel_radius
    assert np.max(np.abs(table[:, 5])) <= U + 1e-6
    tail = table[:, 10] > 0.5
    lift_off = (M + m) * g * math.tan(SPEC.theta_0)
    assert np.max(table[tail, 5]) <= rise.U_TAIL_MARGIN * lift_off + 1e-6
    assert np.min(table[tail, 5]) >= -(M + m) * SPEC.run_up_acceleration - 1e-6   # no tip-over
    assert np.min(table[:, 1]) >= -SPEC.lean_max - 1e-4
    end = table[-1]
    assert abs(end[1]) < 1e-3 and abs(end[2]) < 1e-2 and abs(end[4]) < 1e-2 and end[5] == 0.0
    s = rise.plan_summary(table)
    assert s['run_up_speed_mps'] < -0.5   # the run-up backwards is what the plan is about
    assert np.all(np.isfinite(table))


def test_the_plan_is_solved_once(monkeypatch):
    rise.rise_table(P, SPEC)

    def no_solve(*args):
        raise AssertionError('solved again')
    monkeypatch.setattr(rise, 'plan_rise', no_solve)
    again = rise.rise_table(P, SPEC)
    assert again.shape[1] == rise.COLUMNS


def test_the_planned_rise_meets_the_paper_s_start_up_targets_on_model_1():
    r, core = start_up()
    assert not r.fell
    over, t_rest, distance = figures(r)
    assert over <= STARTUP_TARGETS['overshoot_deg']
    assert t_rest is not None and t_rest <= STARTUP_TARGETS['rest_time_s']
    assert distance <= STARTUP_TARGETS['rest_distance_m']
    assert np.max(np.abs(np.r_[r.tau_left, r.tau_right])) <= 12.0
    assert core.active_controller == 'output_regulation' and not core.planned_rise


def test_ida_pbc_rises_when_the_plan_is_off():
    # The comparison the plan is for: the same start-up, IDA-PBC rising.
    planned, _ = start_up()
    off, core = start_up(planned=False)
    assert not off.fell
    assert figures(off)[0] > 3.0 * max(figures(planned)[0], 1.0)


@pytest.mark.parametrize('mass_factor', [0.7, 1.0, 1.3])
@pytest.mark.parametrize('d_deg', [-3.0, 3.0])
def test_the_rise_stays_within_2_deg_with_mass_and_imu_offset_errors(mass_factor, d_deg):
    r, _ = start_up(mass_factor=mass_factor, imu_offset=math.radians(d_deg))
    assert not r.fell
    over, t_rest, distance = figures(r)
    assert over <= 2.0
    assert t_rest is not None and t_rest <= STARTUP_TARGETS['rest_time_s']
    assert distance <= STARTUP_TARGETS['rest_distance_m']


def test_the_planned_rise_is_off_by_default():
    sc = Scenario(controller='auto', duration=0.1)
    core = _build_core(sc)
    core.reset(Plant(sc).sensors(0.0))
    assert not core.planned_rise and core.rise is None   # not solved: the start stays short
    core = planned_core(sc)
    core.reset(Plant(sc).sensors(0.0))
    assert core.planned_rise


def test_a_robot_off_its_tail_is_not_planned():
    sc = Scenario(controller='auto', theta0=math.radians(10.0), duration=0.1)
    core = planned_core(sc)
    core.reset(Plant(sc).sensors(0.0))
    assert not core.planned_rise


def run(sc, core, ticks):
    plant = Plant(sc)
    us, planned = [], []
    for k in range(ticks):
        t = k * sc.dt
        m = plant.sensors(t)
        if k == 0:
            core.reset(m)
        o = core.step(m, Reference())
        us.append(o.u_cmd)
        planned.append(core.planned_rise)
        tau = sc.motor_torque_limit
        tl, tr = (o.tau_left, o.tau_right) if tau is None else (
            max(-tau, min(tau, o.tau_left)), max(-tau, min(tau, o.tau_right)))
        plant.advance(tl, tr, t)
    return np.array(us), np.array(planned), plant


def test_the_hand_over_to_the_hold_is_bumpless():
    sc = Scenario(controller='auto')
    core = planned_core(sc)
    us, planned, plant = run(sc, core, 1200)
    k = int(np.flatnonzero(~planned[1:] & planned[:-1])[0]) + 1
    assert core.active_controller == 'output_regulation'
    assert np.max(np.abs(np.diff(us[k - 5:k + 50]))) < 2.0   # [N] per tick


def test_the_leg_task_is_told_while_the_run_up_keeps_the_robot_on_its_tail():
    # LegTask.tail_hold follows BalanceCore.rise_on_tail: on the tail from arming, not from
    # the lift-off (the pitch rate), never again in the same rise.
    sc = Scenario(controller='auto')
    core = planned_core(sc)
    plant = Plant(sc)
    theta, flags = [], []
    for k in range(800):
        m = plant.sensors(k * sc.dt)
        if k == 0:
            core.reset(m)
        flags.append(core.rise_on_tail)
        o = core.step(m, Reference())
        theta.append(plant.theta)
        plant.advance(o.tau_left, o.tau_right, k * sc.dt)
    flags, theta = np.array(flags), np.array(theta)
    off = int(np.argmin(flags))
    assert flags[0] and 0 < off and not flags[off:].any()
    assert theta[off - 1] > sc.tail_angle - math.radians(1.0)   # still on the tail then


def test_a_robot_that_cannot_follow_leaves_the_plan_for_ida_pbc():
    # Motors weaker than the controller knows: the pitch falls behind the plan.
    sc = Scenario(controller='auto', motor_torque_limit=2.0)
    core = planned_core(sc)
    us, planned, _ = run(sc, core, 1000)
    left = int(np.argmin(planned))
    assert 0 < left < core.rise.duration / sc.dt
    assert core.active_controller == 'ida_pbc'
    assert np.all(np.isfinite(us))


def test_the_cached_plan_is_the_solved_one():
    solved = rise.sample_plan(SPEC, rise.plan_rise(P, SPEC))
    table_cache.forget()
    table = rise.rise_table(P, SPEC)
    assert np.array_equal(table[:, :6], solved[:, :6])
