"""TF transforms odom -> base_footprint -> base_link (core/frames.py)."""
import math

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from wheelleg_balance.core.frames import base_footprint_to_base_link, odom_to_base_footprint
from wheelleg_balance.core.kinematics import FiveBarLeg
from wheelleg_balance.core.params import RobotParams

P = RobotParams()
LEG = FiveBarLeg()


def _apply(transform, point):
    """Map a point from the child frame to the parent frame."""
    t, q = transform
    return Rotation.from_quat(q).apply(point) + np.array(t)


def test_upright_at_the_lowest_height_base_link_is_042_m_up():
    axle = LEG.axle(*LEG.inverse(P.height_min))
    t, q = base_footprint_to_base_link(0.0, *axle, P.wheel_radius)
    # Wheel radius 0.1 m + axle 0.32 m below the hips (l = 0.37 m, COM 0.05 m above the hips).
    assert t == pytest.approx((0.0, 0.0, 0.42), abs=1e-12)
    assert q == pytest.approx((0.0, 0.0, 0.0, 1.0))


@settings(max_examples=300, deadline=None)
@given(theta=st.floats(-1.2, 1.2), l=st.floats(P.height_min, P.height_max),
       x=st.floats(-0.1, 0.1))
def test_the_axle_lands_one_wheel_radius_above_the_footprint(theta, l, x):
    axle_x, axle_z = LEG.axle(*LEG.inverse(l, x))
    tf = base_footprint_to_base_link(theta, axle_x, axle_z, P.wheel_radius)
    axle = _apply(tf, [axle_x, 0.0, axle_z])
    assert axle == pytest.approx([0.0, 0.0, P.wheel_radius], abs=1e-12)
    # The rotation is the pitch alone: theta > 0 tips base_link's x axis down (leaning forward).
    roll, pitch, yaw = Rotation.from_quat(tf[1]).as_euler('xyz')
    assert (roll, pitch, yaw) == pytest.approx((0.0, theta, 0.0), abs=1e-12)


@pytest.mark.parametrize('theta', [-0.4, 0.0, 0.2, 0.63])
@pytest.mark.parametrize('l', [P.height_min, P.height_max])
def test_the_com_leans_with_theta(theta, l):
    # Axle under the COM (x = 0): the COM is l sin(theta) ahead of the footprint, l cos(theta)
    # above the axle; theta > 0 puts it ahead (leaning forward).
    tf = base_footprint_to_base_link(theta, *LEG.axle(*LEG.inverse(l)), P.wheel_radius)
    com = _apply(tf, [LEG.com_x, 0.0, LEG.com_height])
    assert com == pytest.approx([l * math.sin(theta), 0.0, P.wheel_radius + l * math.cos(theta)],
                                abs=1e-12)


def test_leaning_forward_moves_base_link_ahead_of_the_footprint():
    axle = LEG.axle(*LEG.inverse(0.5))
    t, _ = base_footprint_to_base_link(0.3, *axle, P.wheel_radius)
    assert t[0] > 0.1 and t[2] < 0.1 + 0.45


@settings(max_examples=200, deadline=None)
@given(x=st.floats(-50.0, 50.0), y=st.floats(-50.0, 50.0), yaw=st.floats(-math.pi, math.pi))
def test_odom_to_base_footprint_is_the_planar_pose(x, y, yaw):
    tf = odom_to_base_footprint(x, y, yaw)
    assert tf[0] == (x, y, 0.0)
    # The footprint's x axis points along the heading.
    assert _apply(tf, [1.0, 0.0, 0.0]) == pytest.approx([x + math.cos(yaw),
                                                         y + math.sin(yaw), 0.0], abs=1e-9)
    assert np.linalg.norm(tf[1]) == pytest.approx(1.0)
