"""Model (1), its linearization (2), E_d of (5) and the partial feedback linearization (3)-(4)."""
import math

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from wheelleg_balance.core.model import (
    disturbance_input, ipc_accel, ipc_dynamics, linearize, pfl_accel, pfl_force)
from wheelleg_balance.core.params import RobotParams

P = RobotParams()
HEIGHTS = st.floats(P.height_min, P.height_max)
ANGLES = st.floats(-1.4, 1.4)       # |theta| < 80 deg: cos(theta) bounded away from 0
RATES = st.floats(-10.0, 10.0)
FORCES = st.floats(-300.0, 300.0)
FAST = settings(max_examples=60, deadline=None)


def numerical_jacobian(l, eps=1e-6):
    """Central differences of ipc_dynamics about the upright equilibrium."""
    A = np.zeros((4, 4))
    for j in range(4):
        e = np.zeros(4)
        e[j] = eps
        A[:, j] = (ipc_dynamics(e, 0.0, l, P) - ipc_dynamics(-e, 0.0, l, P)) / (2 * eps)
    B = (ipc_dynamics(np.zeros(4), eps, l, P) - ipc_dynamics(np.zeros(4), -eps, l, P)) / (2 * eps)
    return A, B


@pytest.mark.parametrize('l', [0.37, 0.45, 0.52, 0.61, 0.70])
def test_linearization_matches_numerical_jacobian(l):
    A, B = linearize(l, P)
    A_num, B_num = numerical_jacobian(l)
    np.testing.assert_allclose(A, A_num, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(B, B_num, rtol=1e-6, atol=1e-9)


def test_linearization_uses_body_as_pendulum():
    # (2): theta_ddot = (M+m) g / (M l) theta - u / (M l) with M = wheels 3 kg, m = body 11 kg.
    A, B = linearize(0.5, P)
    assert A[1, 0] == pytest.approx(14.0 * 9.81 / (3.0 * 0.5))
    assert A[3, 0] == pytest.approx(-11.0 * 9.81 / 3.0)
    assert B[1] == pytest.approx(-1.0 / (3.0 * 0.5))
    assert B[3] == pytest.approx(1.0 / 3.0)


@FAST
@given(theta=ANGLES, theta_dot=RATES, u=FORCES, l=HEIGHTS)
def test_dynamics_satisfy_model_1(theta, theta_dot, u, l):
    """The accelerations returned satisfy both rows of (1) as printed."""
    m, M, g = P.body_mass, P.wheel_mass, P.gravity
    _, theta_ddot, _, x_ddot = ipc_dynamics([theta, theta_dot, 0.3, -0.2], u, l, P)
    row1 = ((M + m) * x_ddot + m * l * math.cos(theta) * theta_ddot
            - m * l * math.sin(theta) * theta_dot ** 2 - u)
    row2 = m * l * math.cos(theta) * x_ddot + m * l ** 2 * theta_ddot - m * g * l * math.sin(theta)
    assert abs(row1) < 1e-9 * (1.0 + abs(u))
    assert abs(row2) < 1e-9 * (1.0 + abs(u))


@FAST
@given(l=HEIGHTS, d=st.floats(-0.1, 0.1), theta=st.floats(-0.1, 0.1), u=FORCES)
def test_disturbance_input_of_5(l, d, theta, u):
    """(2) in the true state equals (5) in the measured state xi~ = xi + d e_1."""
    A, B = linearize(l, P)
    xi = np.array([theta, 0.3, -0.1, 0.2])
    xi_meas = xi + np.array([d, 0.0, 0.0, 0.0])
    lhs = A @ xi + B * u
    rhs = A @ xi_meas + B * u + disturbance_input(l, P) * d
    np.testing.assert_allclose(lhs, rhs, atol=1e-9)
    E_d = disturbance_input(l, P)
    m, M, g = P.body_mass, P.wheel_mass, P.gravity
    np.testing.assert_allclose(E_d, [0.0, -(M + m) * g / (M * l), 0.0, m * g / M])


@FAST
@given(theta=ANGLES, theta_dot=RATES, nu=st.floats(-20.0, 20.0), l=HEIGHTS)
def test_pfl_gives_model_4(theta, theta_dot, nu, l):
    u = pfl_force(theta, theta_dot, nu, l, P)
    _, theta_ddot, _, x_ddot = ipc_dynamics([theta, theta_dot, 0.0, 0.0], u, l, P)
    assert x_ddot == pytest.approx(nu, abs=1e-9)                     # (4b)
    expected = P.gravity / l * math.sin(theta) - math.cos(theta) / l * nu   # (4a)
    assert theta_ddot == pytest.approx(expected, abs=1e-8)


@FAST
@given(theta=ANGLES, theta_dot=RATES, nu=st.floats(-20.0, 20.0), l=HEIGHTS)
def test_pfl_accel_inverts_pfl_force(theta, theta_dot, nu, l):
    u = pfl_force(theta, theta_dot, nu, l, P)
    assert pfl_accel(theta, theta_dot, u, l, P) == pytest.approx(nu, abs=1e-9)
    assert pfl_force(theta, theta_dot, pfl_accel(theta, theta_dot, u, l, P), l, P) == \
        pytest.approx(u, abs=1e-8)


def test_pfl_force_matches_printed_3():
    """(3) as printed: u = m l (g/l cos sin - sin theta_dot^2 + (sin^2 + M/m)/l nu)."""
    m, M, g = P.body_mass, P.wheel_mass, P.gravity
    theta, theta_dot, nu, l = 0.4, -1.3, 2.5, 0.6
    s, c = math.sin(theta), math.cos(theta)
    printed = m * l * (g / l * c * s - s * theta_dot ** 2 + (s * s + M / m) / l * nu)
    assert pfl_force(theta, theta_dot, nu, l, P) == pytest.approx(printed, rel=1e-12)


def test_float_and_array_forms_agree():
    theta_ddot, x_ddot = ipc_accel(0.2, 0.5, 10.0, 0.45, P)
    np.testing.assert_allclose(ipc_dynamics([0.2, 0.5, 1.0, -0.3], 10.0, 0.45, P),
                               [0.5, theta_ddot, -0.3, x_ddot])


def test_leaning_forward_falls_forward_and_force_pushes_forward():
    """Sign conventions: theta > 0 leans forward and accelerates forward; u > 0 pushes forward."""
    theta_ddot, _ = ipc_accel(0.1, 0.0, 0.0, 0.5, P)
    assert theta_ddot > 0.0
    theta_ddot, x_ddot = ipc_accel(0.0, 0.0, 10.0, 0.5, P)
    assert x_ddot > 0.0 and theta_ddot < 0.0
