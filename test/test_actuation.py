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


# ------------------------------------------------------------------- the yaw loop's PI + FF

def _turn(ki, ff=0.0, seconds=6.0, scrub=3.9, ref=-2.88, dt=0.002):
    """
    Simulate a turn on the spot: yaw inertia 0.33 kg m^2, scrub moment scrub * yaw rate.

    3.9 N m s/rad: 2.1 N m per wheel hold 2.5 rad/s, as in MuJoCo (docs/main_job.md). The
    wheels' torque difference turns the robot: moment = (tau_right - tau_left) d_w / (2 r_w).
    Returns the yaw rate [rad/s] after ``seconds``.
    """
    from wheelleg_balance.core.actuation import YawLoop
    loop, rate = YawLoop(ki=ki, ff=ff), 0.0
    for _ in range(int(seconds / dt)):
        tl, tr, sat = wheel_torques(0.0, rate, ref, P, 0.3, 12.0, loop.extra(ref))
        loop.update(rate, ref, dt, sat)
        moment = (tr - tl) * 0.5 * P.wheel_separation / P.wheel_radius
        rate += dt * (moment - scrub * rate) / 0.33
    return rate


def test_the_integral_holds_a_turn_the_proportional_term_alone_cannot():
    from wheelleg_balance.core.config import DEFAULTS
    paper, pi = _turn(ki=0.0), _turn(ki=DEFAULTS.control.yaw_rate_ki)
    assert abs(paper) < 0.5 * 2.88                  # the paper's loop: far short
    assert pi == pytest.approx(-2.88, rel=0.02)     # PI: within 2 % after 6 s
    # A feed-forward of the scrub (3.9 / (d_w / r_w) N m s/rad) nearly does it alone.
    ff = 3.9 / (P.wheel_separation / P.wheel_radius)
    assert _turn(ki=0.0, ff=ff) == pytest.approx(-2.88, rel=0.1)


def test_the_integral_is_limited_held_while_saturated_and_reset():
    from wheelleg_balance.core.actuation import YawLoop
    loop = YawLoop(ki=10.0, limit=1.5)
    for _ in range(1000):
        loop.update(0.0, 5.0, 0.002, saturated=False)
    assert loop.integral == pytest.approx(1.5)
    before = loop.integral
    loop.update(0.0, -100.0, 0.002, saturated=True)   # cut by a limit: no wind-up
    loop.update(math.nan, 1.0, 0.002, saturated=False)
    assert loop.integral == before
    assert loop.extra(math.nan) == before              # a NaN feed-forward counts as zero
    loop.reset()
    assert loop.integral == 0.0


def test_the_yaw_loops_integral_acts_on_the_gyros_yaw_rate_where_there_is_one():
    """
    yaw_rate_source imu: a turn the wheels report but the body does not make is no turn.

    The proportional term stays on the wheels' yaw rate (it damps a free wheel).
    """
    from wheelleg_balance.core.pipeline import BalanceCore, CoreConfig, Measurement, Reference
    # The wheels say 1 rad/s to the left, as asked; the gyro says the body stands still.
    w = 1.0 * 0.5 * P.wheel_separation / P.wheel_radius
    meas = Measurement(0.0, 0.0, -w, w, 0.37, yaw_rate_gyro=0.0)

    def yaw_torque(source, m=meas, ticks=250):
        core = BalanceCore(P, CoreConfig(controller='lqr', yaw_rate_source=source,
                                         yaw_rate_ki=2.0))
        core.reset(m)
        for _ in range(ticks):
            out = core.step(m, Reference(yaw_rate_ref=1.0))
        return 0.5 * (out.tau_left - out.tau_right)
    assert yaw_torque('wheels') == pytest.approx(0.0, abs=1e-9)   # at its reference
    # Integral on the gyro's error: 2.0 N m/rad x 1 rad/s x 0.5 s, turning left (negative).
    assert yaw_torque('imu') == pytest.approx(-2.0 * 1.0 * 0.5, rel=0.01)
    no_gyro = Measurement(0.0, 0.0, -w, w, 0.37)
    assert yaw_torque('imu', no_gyro) == pytest.approx(0.0, abs=1e-9)   # falls back to wheels


def test_euler_yaw_rate_from_the_gyro():
    from wheelleg_balance.core.attitude import yaw_rate
    assert yaw_rate(0.3, 1.0, 0.0, 0.0) == pytest.approx(1.0)
    assert yaw_rate(0.0, 1.0, 0.0, math.radians(60)) == pytest.approx(2.0)
    assert yaw_rate(1.0, 0.0, math.radians(90), 0.0) == pytest.approx(1.0)
