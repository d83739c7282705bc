"""Force -> wheel torques with the yaw loop, saturation, motor directions (core/actuation.py)."""
import math

from hypothesis import given, settings
from hypothesis import strategies as st
import pytest
from wheelleg_balance.core.actuation import (
    check_direction, motor_torque, wheel_torques, wheel_velocity)
from wheelleg_balance.core.params import RobotParams

P = RobotParams()


def test_each_wheel_gets_half_of_r_w_u():
    tau_l, tau_r, sat = wheel_torques(40.0, 0.0, 0.0, P)
    assert tau_l == tau_r == pytest.approx(0.5 * P.wheel_radius * 40.0)
    assert not sat


def test_yaw_torque_added_left_subtracted_right():
    tau_l, tau_r, sat = wheel_torques(20.0, 0.5, 0.0, P, yaw_rate_gain=0.3)
    assert tau_l - 1.0 == pytest.approx(0.3 * 0.5)
    assert tau_r - 1.0 == pytest.approx(-0.3 * 0.5)
    assert tau_l + tau_r == pytest.approx(P.wheel_radius * 20.0)  # balance untouched
    assert not sat


def test_yaw_loop_tracks_the_reference_in_closed_loop():
    """Yaw dynamics I_z psi_ddot = (d_w / 2)(F_r - F_l), F = tau / r_w; the loop converges."""
    inertia = 0.4  # [kg m^2] about z, body and wheels
    dt, yaw_rate, ref = 0.002, 0.0, 1.0
    for _ in range(1500):  # 3 s
        tau_l, tau_r, _ = wheel_torques(0.0, yaw_rate, ref, P)
        yaw_acc = 0.5 * P.wheel_separation * (tau_r - tau_l) / P.wheel_radius / inertia
        yaw_rate += dt * yaw_acc
    # time constant I r_w / (d_w gain) = 0.28 s: 3 s is over ten of them
    assert yaw_rate == pytest.approx(ref, abs=1e-3)


def test_balance_keeps_priority_at_the_limit():
    u = 2.0 * 11.5 / P.wheel_radius  # common torque 11.5 N m, headroom 0.5 N m
    tau_l, tau_r, sat = wheel_torques(u, 10.0, 0.0, P, yaw_rate_gain=0.3, max_torque=12.0)
    assert sat
    assert (tau_l, tau_r) == pytest.approx((12.0, 11.0))
    assert tau_l + tau_r == pytest.approx(P.wheel_radius * u)  # the force is still applied

    tau_l, tau_r, sat = wheel_torques(-3.0 * u, -10.0, 0.0, P, max_torque=12.0)
    assert sat and tau_l == tau_r == -12.0  # no headroom left for yaw


@settings(max_examples=300, deadline=None)
@given(u=st.floats(), yaw_rate=st.floats(), ref=st.floats(), gain=st.floats(),
       max_torque=st.floats())
def test_outputs_always_finite_and_within_limit(u, yaw_rate, ref, gain, max_torque):
    tau_l, tau_r, sat = wheel_torques(u, yaw_rate, ref, P, gain, max_torque)
    limit = max_torque if 0.0 < max_torque < math.inf else 0.0
    for tau in (tau_l, tau_r):
        assert math.isfinite(tau)
        assert abs(tau) <= limit
    assert isinstance(sat, bool)


finite = st.floats(-1e6, 1e6)


@settings(max_examples=300, deadline=None)
@given(u=finite, yaw_rate=finite, ref=finite, max_torque=st.floats(0.1, 50.0))
def test_sum_is_the_clipped_balance_torque(u, yaw_rate, ref, max_torque):
    tau_l, tau_r, sat = wheel_torques(u, yaw_rate, ref, P, 0.3, max_torque)
    tau = min(max_torque, max(-max_torque, 0.5 * P.wheel_radius * u))
    assert tau_l + tau_r == pytest.approx(2.0 * tau, rel=1e-12, abs=1e-9)
    requested_diff = 0.3 * (yaw_rate - ref)
    if not sat:
        assert tau_l - tau_r == pytest.approx(2.0 * requested_diff, rel=1e-9, abs=1e-9)


def test_direction_check():
    assert check_direction(1) == 1 and check_direction(-1) == -1
    for bad in (0, 2, 0.5, -2):
        with pytest.raises(ValueError):
            check_direction(bad)


@pytest.mark.parametrize('direction', [1, -1])
def test_forward_torque_gives_forward_wheel_motion(direction):
    # A motor turns the way its own torque pushes it; mapped back, the wheel goes forward.
    tau_motor = motor_torque(2.0, direction)
    motor_vel = math.copysign(5.0, tau_motor)
    assert wheel_velocity(motor_vel, direction) == 5.0
    assert motor_torque(-2.0, direction) == -tau_motor
