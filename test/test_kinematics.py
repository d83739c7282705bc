"""Five-bar leg kinematics: height l from the hip angles and back (core/kinematics.py)."""
import math

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from wheelleg_balance.core.kinematics import FiveBarLeg, STOP_MARGIN
from wheelleg_balance.core.params import RobotParams

P = RobotParams()
LEG = FiveBarLeg()


@pytest.mark.parametrize('l', np.linspace(P.height_min, P.height_max, 12))
@pytest.mark.parametrize('x', [-0.1, 0.0, 0.1])
def test_inverse_then_forward_round_trips_over_the_height_range(l, x):
    q_front, q_rear = LEG.inverse(l, x)
    assert LEG.in_reach(q_front, q_rear)
    assert LEG.forward(q_front, q_rear) == pytest.approx((x, l), abs=1e-12)
    assert LEG.height(q_front, q_rear) == pytest.approx(l, abs=1e-12)


@settings(max_examples=300, deadline=None)
@given(l=st.floats(P.height_min, P.height_max), x=st.floats(-0.1, 0.1))
def test_round_trip_property(l, x):
    q = LEG.inverse(l, x)
    assert all(math.isfinite(a) for a in q)
    assert LEG.forward(*q) == pytest.approx((x, l), abs=1e-10)


@settings(max_examples=300, deadline=None)
@given(q_front=st.floats(LEG.q_min, LEG.q_max), q_rear=st.floats(LEG.q_min, LEG.q_max))
def test_forward_closes_the_linkage(q_front, q_rear):
    """Independent check of the FK: both shanks reach the axle, which hangs below the knees."""
    x, l = LEG.forward(q_front, q_rear)
    xc, zc = x + LEG.com_x, LEG.com_height - l
    half = 0.5 * LEG.hip_spacing
    front_knee = (half + LEG.thigh * math.cos(q_front), -LEG.thigh * math.sin(q_front))
    rear_knee = (-half - LEG.thigh * math.cos(q_rear), -LEG.thigh * math.sin(q_rear))
    for kx, kz in (front_knee, rear_knee):
        assert math.hypot(xc - kx, zc - kz) == pytest.approx(LEG.shank, abs=1e-12)
        assert zc < kz
    assert LEG.inverse(l, x) == pytest.approx((q_front, q_rear), abs=1e-9)


def test_angle_conventions():
    # Symmetric stance -> axle under the COM; more thigh angle (down) -> taller.
    heights = [LEG.height(q, q) for q in np.linspace(LEG.q_min, LEG.q_max, 20)]
    assert np.all(np.diff(heights) > 0)
    assert LEG.forward(0.6, 0.6)[0] == pytest.approx(0.0, abs=1e-15)
    # Front thigh down, rear thigh up: the axle moves backward (x < 0).
    assert LEG.forward(0.8, 0.4)[0] < 0.0 < LEG.forward(0.4, 0.8)[0]


def test_defaults_span_the_robot_height_range_inside_the_joint_limits():
    assert LEG.height(LEG.q_min, LEG.q_min) < P.height_min
    assert LEG.height(LEG.q_max, LEG.q_max) > P.height_max
    assert LEG.inverse(P.height_min) == pytest.approx((0.25, 0.25), abs=0.01)
    assert LEG.inverse(P.height_max) == pytest.approx((1.12, 1.12), abs=0.01)


@pytest.mark.parametrize('q', [
    # beyond the hard stops by more than the reading tolerance kinematics allows
    (LEG.q_max + STOP_MARGIN + 0.01, 0.8), (0.8, LEG.q_min - STOP_MARGIN - 0.01),
    (math.nan, 0.5), (0.5, math.inf),
])
def test_out_of_reach_angles_are_detected(q):
    assert not LEG.in_reach(*q)
    assert all(math.isnan(v) for v in LEG.forward(*q))
    assert math.isnan(LEG.height(*q))


def test_shanks_that_cannot_meet_are_out_of_reach():
    leg = FiveBarLeg(thigh=0.3, shank=0.2, hip_spacing=0.1, q_min=-1.0, q_max=2.0)
    assert not leg.in_reach(0.0, 0.0)  # knees 0.7 m apart, shanks reach 0.4 m
    assert math.isnan(leg.height(0.0, 0.0))
    assert leg.in_reach(1.2, 1.2)


@pytest.mark.parametrize('l, x', [
    (0.2, 0.0),        # needs thighs above q_min
    (0.8, 0.0),        # beyond full extension
    (0.5, 0.5),        # too far forward
    (math.nan, 0.0), (0.5, math.inf),
])
def test_inverse_out_of_reach_is_nan(l, x):
    assert all(math.isnan(v) for v in LEG.inverse(l, x))


def test_invalid_geometry_is_rejected():
    with pytest.raises(ValueError):
        FiveBarLeg(thigh=0.0)
    with pytest.raises(ValueError):
        FiveBarLeg(q_min=1.0, q_max=0.5)


def test_com_offset_moves_the_height_one_to_one():
    raised = FiveBarLeg(com_height=0.08)
    assert raised.height(0.7, 0.7) - LEG.height(0.7, 0.7) == pytest.approx(0.03, abs=1e-12)


# ---- Jacobian, rates, static torques, knee angles ------------------------------------------

REACH = {'q_front': st.floats(LEG.q_min + 0.01, LEG.q_max - 0.01),
         'q_rear': st.floats(LEG.q_min + 0.01, LEG.q_max - 0.01)}


@settings(max_examples=200, deadline=None)
@given(**REACH)
def test_jacobian_matches_finite_differences(q_front, q_rear):
    j = np.array(LEG.jacobian(q_front, q_rear))
    e = 1e-6
    fd = np.empty((2, 2))
    for col, (df, dr) in enumerate(((e, 0.0), (0.0, e))):
        plus = np.array(LEG.forward(q_front + df, q_rear + dr))
        minus = np.array(LEG.forward(q_front - df, q_rear - dr))
        fd[:, col] = (plus - minus) / (2 * e)
    assert np.allclose(j, fd, atol=1e-7)


@settings(max_examples=200, deadline=None)
@given(f_l=st.floats(-200.0, 200.0), f_x=st.floats(-100.0, 100.0),
       direction=st.floats(0.0, 2.0 * math.pi), **REACH)
def test_static_torques_do_the_virtual_work_of_the_load(q_front, q_rear, f_l, f_x, direction):
    """The torques do the load's work: tau . dq = f_x dx + f_l dl, for any small dq."""
    dq_f, dq_r = 1e-5 * math.cos(direction), 1e-5 * math.sin(direction)
    tau_f, tau_r = LEG.static_torques(q_front, q_rear, f_l, f_x)
    x0, l0 = LEG.forward(q_front - 0.5 * dq_f, q_rear - 0.5 * dq_r)
    x1, l1 = LEG.forward(q_front + 0.5 * dq_f, q_rear + 0.5 * dq_r)
    work_load = f_x * (x1 - x0) + f_l * (l1 - l0)
    # Central difference: the error is third order in dq (plus rounding).
    tol = 1e-12 * (abs(f_l) + abs(f_x) + 1.0)
    assert tau_f * dq_f + tau_r * dq_r == pytest.approx(work_load, abs=tol)


def test_weight_share_needs_positive_hip_torques_over_the_height_range():
    """Carrying the body pushes each thigh down (towards larger q); figures in docs/legs.md."""
    share = P.body_mass * P.gravity / 2.0
    for l in np.linspace(P.height_min, P.height_max, 8):
        q = LEG.inverse(l)
        tau_f, tau_r = LEG.static_torques(*q, share)
        assert tau_f == pytest.approx(tau_r) and 6.0 < tau_f < 12.0


@settings(max_examples=100, deadline=None)
@given(l=st.floats(P.height_min, P.height_max), l_dot=st.floats(-1.0, 1.0),
       x_dot=st.floats(-0.5, 0.5))
def test_hip_rates_invert_the_jacobian(l, l_dot, x_dot):
    q = LEG.inverse(l)
    rates = LEG.hip_rates(*q, l_dot, x_dot)
    assert LEG.height_rate(*q, *rates) == pytest.approx(l_dot, abs=1e-9)
    j = np.array(LEG.jacobian(*q))
    assert j @ np.array(rates) == pytest.approx([x_dot, l_dot], abs=1e-9)


@settings(max_examples=200, deadline=None)
@given(**REACH)
def test_knee_angles_close_the_chain(q_front, q_rear):
    """Thigh then shank at (hip angle + knee angle) ends on the axle, for both knees."""
    k_f, k_r = LEG.knee_angles(q_front, q_rear)
    x, l = LEG.forward(q_front, q_rear)
    xc, zc = x + LEG.com_x, LEG.com_height - l
    h, a, b = 0.5 * LEG.hip_spacing, LEG.thigh, LEG.shank
    front = (h + a * math.cos(q_front) + b * math.cos(q_front + k_f),
             -a * math.sin(q_front) - b * math.sin(q_front + k_f))
    rear = (-h - a * math.cos(q_rear) - b * math.cos(q_rear + k_r),
            -a * math.sin(q_rear) - b * math.sin(q_rear + k_r))
    assert front == pytest.approx((xc, zc), abs=1e-12)
    assert rear == pytest.approx((xc, zc), abs=1e-12)


def test_out_of_reach_gives_nan_everywhere():
    for q in ((2.5, 0.5), (math.nan, 0.5)):
        assert LEG.jacobian(*q) is None
        assert all(math.isnan(v) for v in LEG.static_torques(*q, 50.0))
        assert all(math.isnan(v) for v in LEG.knee_angles(*q))
        assert all(math.isnan(v) for v in LEG.hip_rates(*q, 0.1))
        assert math.isnan(LEG.height_rate(*q, 0.1, 0.1))


@settings(max_examples=300, deadline=None)
@given(q_front=st.floats(LEG.q_min, LEG.q_max), q_rear=st.floats(LEG.q_min, LEG.q_max))
def test_knee_angles_walk_both_open_chains_to_the_axle(q_front, q_rear):
    k_front, k_rear = LEG.knee_angles(q_front, q_rear)
    if not LEG.in_reach(q_front, q_rear):
        assert math.isnan(k_front) and math.isnan(k_rear)
        return
    xc, zc = LEG.axle(q_front, q_rear)
    h, a, b = 0.5 * LEG.hip_spacing, LEG.thigh, LEG.shank
    # Front chain: thigh at q below the forward horizontal, shank at q + knee.
    s = q_front + k_front
    front = (h + a * math.cos(q_front) + b * math.cos(s),
             -a * math.sin(q_front) - b * math.sin(s))
    # Rear chain, mirrored: angles below the backward horizontal.
    s = q_rear + k_rear
    rear = (-h - a * math.cos(q_rear) - b * math.cos(s),
            -a * math.sin(q_rear) - b * math.sin(s))
    assert front == pytest.approx((xc, zc), abs=1e-9)
    assert rear == pytest.approx((xc, zc), abs=1e-9)
    assert LEG.forward(q_front, q_rear) == pytest.approx((xc - LEG.com_x, LEG.com_height - zc))


def test_knees_bend_less_as_the_robot_rises():
    low = LEG.knee_angles(*LEG.inverse(P.height_min))
    high = LEG.knee_angles(*LEG.inverse(P.height_max))
    assert low[0] == pytest.approx(low[1]) and high[0] == pytest.approx(high[1])
    assert high[0] < low[0] < math.pi


@settings(max_examples=100, deadline=None)
@given(l=st.floats(0.2, 0.9), l_dot=st.floats(-0.3, 0.3), f_l=st.floats(-60.0, 60.0),
       f_x=st.floats(-20.0, 20.0))
def test_hip_command_is_inverse_hip_rates_and_static_torques_in_one_call(l, l_dot, f_l, f_x):
    leg = FiveBarLeg()
    for _ in range(2):   # solved afresh, then the held height's kept solve
        got = leg.hip_command(l, l_dot, f_l, f_x)
        q = LEG.inverse(l)
        want = q + LEG.hip_rates(*q, l_dot) + LEG.static_torques(*q, f_l, f_x)
        assert got[:2] == q or np.isnan(q).all() and np.isnan(got).all()
        # The rates and torques through the inverse solve's Jacobian: equal bar rounding.
        assert np.isnan(got).tolist() == np.isnan(want).tolist()
        assert np.allclose(got, want, rtol=1e-9, atol=1e-12, equal_nan=True), (got, want)


@settings(max_examples=100, deadline=None)
@given(q_front=st.floats(-0.4, 1.8), q_rear=st.floats(-0.4, 1.8))
def test_measure_is_height_jacobian_and_knees_in_one_call(q_front, q_rear):
    leg = FiveBarLeg()
    for _ in range(2):   # solved, then kept
        pose, j, l, knees = leg.measure(q_front, q_rear)
        assert np.array_equal(l, LEG.height(q_front, q_rear), equal_nan=True)
        assert j == LEG.jacobian(q_front, q_rear)
        assert np.array_equal(knees, LEG.knee_angles(q_front, q_rear), equal_nan=True)
        assert (pose is None) == (not LEG.in_reach(q_front, q_rear))


@settings(max_examples=200, deadline=None)
@given(l=st.floats(0.2, 0.9), x=st.floats(-0.15, 0.15))
def test_the_inverse_solves_jacobian_is_the_forward_ones(l, x):
    # hip_command takes the Jacobian from the inverse solve's knees (no forward solve).
    q_front, q_rear, j = LEG._inverse(l, x)
    assert (q_front, q_rear) == LEG.inverse(l, x) or math.isnan(q_front)
    want = LEG.jacobian(q_front, q_rear)
    if want is None or j is None:
        assert want is None and j is None or math.isnan(q_front) and j is None
        return
    assert np.allclose(j, want, rtol=1e-9, atol=1e-12), (j, want)
