"""Pitch from the IMU quaternion and wheel odometry (core/estimation.py, paper Sec. V-A)."""
import math

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from wheelleg_balance.core.estimation import (
    pitch_from_quaternion, pitch_rate_from_gyro, WheelOdometry)
from wheelleg_balance.core.params import RobotParams

P = RobotParams()
DT = 0.002


# ---- pitch ---------------------------------------------------------------------------------

@settings(max_examples=200, deadline=None)
@given(yaw=st.floats(-math.pi, math.pi), pitch=st.floats(-1.5, 1.5), roll=st.floats(-0.6, 0.6))
def test_pitch_matches_scipy_euler_zyx(yaw, pitch, roll):
    x, y, z, w = Rotation.from_euler('ZYX', [yaw, pitch, roll]).as_quat()  # scalar last
    assert pitch_from_quaternion(x, y, z, w) == pytest.approx(pitch, abs=1e-7)


@pytest.mark.parametrize('angle', [0.1, 0.63, -0.3])
def test_positive_pitch_means_leaning_forward(angle):
    # Rotation about body y by `angle`: the body's up axis tips towards +x (forward) for angle>0.
    rot = Rotation.from_rotvec([0.0, angle, 0.0])
    up = rot.apply([0.0, 0.0, 1.0])
    x, y, z, w = rot.as_quat()
    theta = pitch_from_quaternion(x, y, z, w)
    assert theta == pytest.approx(angle, abs=1e-12)
    assert math.copysign(1.0, up[0]) == math.copysign(1.0, theta)


def test_pitch_normalizes_slightly_off_quaternions():
    x, y, z, w = Rotation.from_euler('ZYX', [0.4, 0.3, -0.1]).as_quat()
    for scale in (0.95, 1.05):
        assert pitch_from_quaternion(scale * x, scale * y, scale * z, scale * w) == \
            pytest.approx(0.3, abs=1e-12)


@pytest.mark.parametrize('q', [
    (0.0, 0.0, 0.0, 0.0),            # IMU without orientation
    (0.0, 0.2, 0.0, 1.2),            # norm 1.22
    (0.0, 0.1, 0.0, 0.8),            # norm 0.81
    (math.nan, 0.0, 0.0, 1.0),
    (0.0, math.inf, 0.0, 1.0),
    (1e200, 1e200, 0.0, 0.0),        # overflows
])
def test_pitch_rejects_bad_quaternions(q):
    assert math.isnan(pitch_from_quaternion(*q))


def test_pitch_rate_is_gyro_y():
    assert pitch_rate_from_gyro(-0.25) == -0.25
    assert isinstance(pitch_rate_from_gyro(1), float)


# ---- wheel odometry ------------------------------------------------------------------------

def _rolling_while_pitching(t):
    """Ground truth: speed v(t), pitch rate theta_dot(t), encoder rates (relative to the leg)."""
    v = 0.5 + 0.2 * math.sin(0.7 * t)
    theta_dot = 0.2 * 2.0 * math.pi * 1.5 * math.cos(2.0 * math.pi * 1.5 * t)
    # Rolling without slipping: the wheel turns at v / r_w in the world; the encoder's stator
    # (on the leg) turns with the body at theta_dot, so it reads the difference.
    w_rel = v / P.wheel_radius - theta_dot
    return v, theta_dot, w_rel


def test_ground_speed_is_right_only_with_pitch_correction():
    corrected, paper = WheelOdometry(P), WheelOdometry(P, pitch_correction=False)
    err_corrected, err_paper = [], []
    for k in range(1000):
        v, theta_dot, w_rel = _rolling_while_pitching(k * DT)
        _, x_dot, _ = corrected.update(w_rel, w_rel, theta_dot, DT)
        _, x_dot_paper, _ = paper.update(w_rel, w_rel, theta_dot, DT)
        err_corrected.append(abs(x_dot - v))
        err_paper.append(abs(x_dot_paper - v))
    assert max(err_corrected) < 1e-12
    # The paper's x_dot = r_w (w_l + w_r)/2 is off by r_w theta_dot: ~0.19 m/s peak here.
    assert max(err_paper) > 0.15


def test_x_integrates_as_the_paper():
    """x_k = x_{k-1} + T_s x_dot_{k-1}: the current tick's speed enters at the next tick."""
    odo = WheelOdometry(P)
    rng = np.random.default_rng(3)
    w = rng.uniform(-20.0, 20.0, size=(50, 2))
    theta_dot = rng.uniform(-1.0, 1.0, size=50)
    x_dots = []
    for k in range(50):
        x, x_dot, _ = odo.update(w[k, 0], w[k, 1], theta_dot[k], DT)
        assert x == pytest.approx(DT * sum(x_dots), abs=1e-15)
        x_dots.append(x_dot)
    assert odo.x == pytest.approx(DT * sum(x_dots[:-1]), abs=1e-15)


def test_yaw_rate_positive_turns_left_and_pose_follows_the_circle():
    v, omega = 0.5, 0.5  # m/s, rad/s -> radius 1 m, counter-clockwise
    half = 0.5 * omega * P.wheel_separation
    w_left, w_right = (v - half) / P.wheel_radius, (v + half) / P.wheel_radius
    odo = WheelOdometry(P)
    n = int(round(math.pi / omega / DT))  # half a circle
    for _ in range(n + 1):
        _, x_dot, yaw_rate = odo.update(w_left, w_right, 0.0, DT)
    assert yaw_rate == pytest.approx(omega, rel=1e-12)
    assert x_dot == pytest.approx(v, rel=1e-12)
    x_w, y_w, yaw = odo.pose
    radius = v / omega
    t = n * DT
    assert x_w == pytest.approx(radius * math.sin(omega * t), abs=2e-3)
    assert y_w == pytest.approx(radius * (1.0 - math.cos(omega * t)), abs=2e-3)
    assert y_w > 1.9  # went left
    assert abs(yaw) == pytest.approx(math.pi, abs=2e-3)  # wrapped half turn


def test_bad_samples_are_reported_but_not_integrated():
    odo = WheelOdometry(P)
    odo.update(10.0, 10.0, 0.0, DT)
    _, x_dot, yaw_rate = odo.update(math.nan, 10.0, 0.0, DT)
    assert math.isnan(x_dot) and math.isnan(yaw_rate)
    x_before = odo.x
    x, _, _ = odo.update(10.0, 10.0, 0.0, DT)
    assert x == x_before  # the NaN tick contributed zero
    assert all(math.isfinite(c) for c in odo.pose)
    x, _, _ = odo.update(10.0, 10.0, 0.0, -1.0)  # bad dt integrates nothing
    assert x == x_before


def test_reset_zeroes_everything():
    odo = WheelOdometry(P)
    for _ in range(10):
        odo.update(5.0, 8.0, 0.1, DT)
    odo.reset()
    assert odo.pose == (0.0, 0.0, 0.0)
    x, _, _ = odo.update(5.0, 8.0, 0.1, DT)
    assert x == 0.0
