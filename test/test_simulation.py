"""
The closed-loop simulation (core/simulation.py): plant physics, the tail, determinism.

Physics checks run the plant open loop; the closed-loop checks run BalanceCore, the code of the
node, against the nonlinear model (1).
"""
import math

import numpy as np
import pytest

from wheelleg_balance.core import model
from wheelleg_balance.core.params import RobotParams
from wheelleg_balance.core.pipeline import BalanceCore, CoreConfig
from wheelleg_balance.core.simulation import (
    Plant, plant_accel, Scenario, simulate, SmoothSchedule, TAIL_ANGLE)
from wheelleg_balance.validation.paper.experiments import peak_torque_nm, settling_time_s

P = RobotParams()


def _free_plant(**kw):
    """Return a plant with the tail and fall checks out of the way (free pendulum on a cart)."""
    return Plant(Scenario(tail_angle=100.0, fall_angle=100.0, **kw))


def test_plant_is_model_1_at_constant_height():
    rng = np.random.default_rng(1)
    for _ in range(50):
        theta, theta_dot, u = rng.uniform(-1.2, 1.2), rng.uniform(-3, 3), rng.uniform(-100, 100)
        l = rng.uniform(P.height_min, P.height_max)
        th_dd, x_dd = plant_accel(theta, theta_dot, u, l, 0.0, 0.0,
                                  P.body_mass, P.wheel_mass, P.gravity)
        ref = model.ipc_dynamics([theta, theta_dot, 0.0, 0.3], u, l, P)
        assert th_dd == pytest.approx(ref[1], rel=1e-9, abs=1e-9)
        assert x_dd == pytest.approx(ref[3], rel=1e-9, abs=1e-9)


def test_energy_and_momentum_conserved_without_input():
    # u = 0, no damping: a free pendulum on a cart falls through several swings; the energy of
    # (1) and the horizontal momentum stay constant up to the RK4 error.
    plant = _free_plant(theta0=0.3, theta_dot0=-1.0, x_dot0=0.2, height=0.5)
    l = 0.5
    e0 = plant.energy()

    def momentum():
        return ((plant.M + plant.m) * plant.x_dot
                + plant.m * l * math.cos(plant.theta) * plant.theta_dot)

    p0 = momentum()
    swing = 0.0
    for k in range(1000):  # 2 s
        plant.advance(0.0, 0.0, k * plant.sc.dt)
        swing = max(swing, abs(plant.theta))
    assert swing > 2.0  # it really swung far from upright
    assert abs(plant.energy() - e0) < 1e-6 * abs(e0)
    assert abs(momentum() - p0) < 1e-8


def test_work_of_the_force_goes_into_energy():
    # With a force, dE/dt = u x_dot: checks the sign of u in the plant.
    plant = _free_plant(theta0=0.1, height=0.4)
    e0 = plant.energy()
    work = 0.0
    tau = 1.5  # per wheel -> u = 30 N
    for k in range(100):
        x0 = plant.x
        plant.advance(tau, tau, k * plant.sc.dt)
        work += 2.0 * tau / P.wheel_radius * (plant.x - x0)
    assert plant.x > 0.0
    assert plant.energy() - e0 == pytest.approx(work, rel=1e-4)


def test_tail_holds_the_robot_at_36_deg_with_zero_torque():
    plant = Plant(Scenario())
    assert plant.theta == pytest.approx(math.radians(36.0))
    for k in range(1000):
        plant.advance(0.0, 0.0, k * plant.sc.dt)
    assert plant.theta == pytest.approx(TAIL_ANGLE, abs=1e-12)
    assert plant.theta_dot == 0.0 and plant.x_dot == 0.0 and plant.x == 0.0
    assert not plant.fell and not plant.risen


def test_tail_lift_off_needs_enough_forward_acceleration():
    # On the tail the robot rolls as one body; it lifts when x_ddot > g tan(36 deg),
    # i.e. u > (M + m) g tan(36 deg) ~ 100 N (5 N m per wheel).
    lift = (P.body_mass + P.wheel_mass) * P.gravity * math.tan(TAIL_ANGLE) * P.wheel_radius / 2
    low, high = Plant(Scenario()), Plant(Scenario())
    for k in range(50):
        low.advance(0.9 * lift, 0.9 * lift, k * 0.002)
        high.advance(1.1 * lift, 1.1 * lift, k * 0.002)
    assert low.on_tail and low.x_dot > 0.0
    assert not high.on_tail and high.theta < TAIL_ANGLE - 0.01


def test_falling_back_onto_the_tail_counts_as_a_fall():
    plant = Plant(Scenario(theta0=0.2, theta_dot0=0.5))  # risen, leaning forward, no torque
    for k in range(1000):
        plant.advance(0.0, 0.0, k * 0.002)
        if plant.fell:
            break
    assert plant.fell and plant.on_tail


def test_smooth_schedule():
    s = SmoothSchedule(((1.0, 0.7), (2.0, 0.5), (3.0, 0.5)))
    assert s(0.0) == (0.7, 0.0, 0.0) and s(5.0) == (0.5, 0.0, 0.0)
    assert s(1.5)[0] == pytest.approx(0.6) and s(1.5)[1] == pytest.approx(-0.3)
    assert s(2.5) == (0.5, 0.0, 0.0)


def test_same_seed_same_run_other_seed_other_run():
    sc = Scenario(controller='ida_pbc', duration=1.0, noise_std=(0.002, 0.02, 0.1), seed=7)
    a, b = simulate(sc), simulate(sc)
    c = simulate(Scenario(controller='ida_pbc', duration=1.0,
                          noise_std=(0.002, 0.02, 0.1), seed=8))
    for name in ('theta', 'x_dot', 'u', 'd_hat', 'theta_meas'):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.theta_meas, c.theta_meas)


def test_sensors_are_what_the_robot_reports():
    plant = Plant(Scenario(theta0=0.1, theta_dot0=0.2, x_dot0=0.5, imu_offset=0.04,
                           height=0.6))
    plant.yaw_rate = 0.4
    meas = plant.sensors(0.0)
    assert meas.theta_meas == pytest.approx(0.14)
    w_l, w_r = meas.wheel_vel_left, meas.wheel_vel_right
    # Odometry of Sec. V-A with the pitch-rate correction (docs/interface.md) recovers speed
    # and yaw rate.
    assert P.wheel_radius * ((w_l + w_r) / 2 + meas.theta_dot) == pytest.approx(0.5)
    assert P.wheel_radius * (w_r - w_l) / P.wheel_separation == pytest.approx(0.4)
    assert meas.l == 0.6


def test_ida_pbc_start_up_from_the_tail_does_not_fall():
    r = simulate(Scenario(controller='ida_pbc', duration=5.0))
    assert not r.fell
    assert r.theta[0] == pytest.approx(TAIL_ANGLE)
    assert np.max(np.abs(r.theta[-250:])) < math.radians(1.0)  # upright over the last 0.5 s
    assert settling_time_s(r) is not None
    assert peak_torque_nm(r) <= 12.0 + 1e-9


def test_no_torque_means_a_fall_is_reported():
    # Balanced start with the torque limit at 0: the robot must fall, and the run stops there.
    r = simulate(Scenario(controller='ida_pbc', theta0=-0.05, max_wheel_torque=0.0,
                          duration=5.0))
    assert r.fell and r.fall_time is not None and r.fall_time < 5.0
    assert settling_time_s(r) is None


def test_delay_and_motor_limit_act_on_the_applied_torque():
    base = simulate(Scenario(controller='ida_pbc', duration=0.3))
    late = simulate(Scenario(controller='ida_pbc', duration=0.3, delay_ticks=1))
    clipped = simulate(Scenario(controller='ida_pbc', duration=0.3, motor_torque_limit=6.0))
    assert abs(base.u[0]) > 50.0  # the start-up pushes hard from the first tick
    assert late.u[0] == 0.0 and late.u[1] == pytest.approx(base.u[0])
    assert peak_torque_nm(base) > 6.5
    assert peak_torque_nm(clipped) == pytest.approx(6.0)


@pytest.mark.parametrize('kw', [
    {'controller': 'output_regulation', 'max_wheel_torque': 6.0, 'd_hat0': 0.02},
    {'controller': 'ida_pbc', 'compensate_offset': False, 'd_hat0': 0.03},
])
def test_a_reused_core_runs_like_a_freshly_built_one(kw):
    # simulate() deep-copies a cached BalanceCore and then sets the scenario's tuning; the run
    # must be the one a BalanceCore built with that tuning gives.
    sc = Scenario(duration=1.0, imu_offset=0.03, **kw)
    fresh = simulate(sc, BalanceCore(P, CoreConfig(**kw)))
    simulate(Scenario(duration=0.1))  # the cached template has the default tuning
    reused = simulate(sc)
    assert np.array_equal(fresh.u, reused.u) and np.array_equal(fresh.d_hat, reused.d_hat)
    assert not np.array_equal(fresh.u, simulate(Scenario(duration=1.0, imu_offset=0.03)).u)
