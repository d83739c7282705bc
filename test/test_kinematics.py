"""Five-bar leg kinematics: height l from the hip angles and back (core/kinematics.py)."""
import math

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from wheelleg_balance.core.kinematics import FiveBarLeg
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
    (LEG.q_max + 0.01, 0.8), (0.8, LEG.q_min - 0.01), (math.nan, 0.5), (0.5, math.inf),
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
