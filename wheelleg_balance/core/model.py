"""
The inverted pendulum on a cart (IPC) of the paper, Sec. II, with a variable height l.

State xi = [theta, theta_dot, x, x_dot]: pitch theta [rad] (> 0 leans forward), pitch rate
[rad/s], position x [m] and ground speed x_dot [m/s]; u [N] is the force on the cart (> 0 pushes
forward). m = ``p.body_mass`` is the pendulum (body) and M = ``p.wheel_mass`` the cart (wheels),
see docs/interface.md ("The model").

- ``ipc_dynamics`` / ``ipc_accel``: model (1),
      (M + m) x_ddot + m l cos(theta) theta_ddot - m l sin(theta) theta_dot^2 = u,
      m l cos(theta) x_ddot + m l^2 theta_ddot - m g l sin(theta) = 0,
  solved for the accelerations:
      x_ddot = (u + m l sin(theta) theta_dot^2 - m g sin(theta) cos(theta)) / (M + m sin^2(theta)),
      theta_ddot = (g sin(theta) - cos(theta) x_ddot) / l.
- ``ipc_accel_moving``: model (1) for a height l(t) that moves (the simulation's plant): a
  point mass on a leg of prescribed length l(t) adds, from its Lagrangian,
      (M + m) x_ddot + m l c theta_ddot - m l s theta_dot^2 + m (l_ddot s + 2 l_dot c theta_dot)
          = u,
      c x_ddot + l theta_ddot + 2 l_dot theta_dot - g s = 0,   (s = sin(theta), c = cos(theta)),
  which vanish for l_dot = l_ddot = 0: ``ipc_accel`` is that case.
- ``linearize``: (2), xi_dot = A xi + B u about the upright equilibrium.
- ``disturbance_input``: E_d of (5), the way an IMU offset d (theta~ = theta + d) enters (2)
  written in the measured state xi~ = [theta~, theta_dot, x, x_dot]: E_d = -A e_1.
- ``pfl_force`` / ``pfl_accel``: the partial feedback linearization (3), which turns (1) into
  (4a) theta_ddot = (g sin(theta) - cos(theta) nu) / l, (4b) x_ddot = nu, and its inverse.
"""
import math

import numpy as np

from .params import RobotParams


def ipc_accel_moving(theta: float, theta_dot: float, u: float, l: float, l_dot: float,
                     l_ddot: float, m: float, M: float, g: float) -> tuple:
    """
    Return (theta_ddot [rad/s^2], x_ddot [m/s^2]) of model (1) with a moving height.

    theta [rad], theta_dot [rad/s], u [N], l [m], l_dot [m/s], l_ddot [m/s^2], m (body) and M
    (wheels) [kg], g [m/s^2] (the module docstring gives the equations).
    """
    s = math.sin(theta)
    c = math.cos(theta)
    f1 = u + m * l * s * theta_dot * theta_dot - m * (l_ddot * s + 2.0 * l_dot * c * theta_dot)
    f2 = g * s - 2.0 * l_dot * theta_dot
    x_ddot = (f1 - m * c * f2) / (M + m * s * s)
    return (f2 - c * x_ddot) / l, x_ddot


def theta_ddot_free_and_driven(theta: float, theta_dot: float, u: float, l: float,
                               m: float, M: float, g: float) -> tuple:
    """
    Return model (1)'s theta_ddot [rad/s^2] at height l [m] with no force and with force u [N].

    The same operations as ``ipc_accel_moving`` with l fixed, shared by the two: the response
    check (core/response.py) needs both once a tick.
    """
    s = math.sin(theta)
    c = math.cos(theta)
    f1 = m * l * s * theta_dot * theta_dot
    f2 = g * s
    mcf2 = m * c * f2
    den = M + m * s * s
    return (f2 - c * ((f1 - mcf2) / den)) / l, (f2 - c * ((u + f1 - mcf2) / den)) / l


def ipc_accel(theta: float, theta_dot: float, u: float, l: float,
              p: RobotParams) -> tuple:
    """
    Return (theta_ddot [rad/s^2], x_ddot [m/s^2]) of model (1) for force u [N] at height l [m].

    Plain floats, for simulation loops; ``ipc_dynamics`` wraps it.
    """
    return ipc_accel_moving(theta, theta_dot, u, l, 0.0, 0.0, p.body_mass, p.wheel_mass,
                            p.gravity)


def ipc_dynamics(state, u: float, l: float, p: RobotParams) -> np.ndarray:
    """
    Model (1): d/dt [theta, theta_dot, x, x_dot] for force u [N] at height l [m].

    ``state`` is [theta, theta_dot, x, x_dot] in [rad, rad/s, m, m/s].
    """
    theta, theta_dot, _, x_dot = (float(v) for v in state)
    theta_ddot, x_ddot = ipc_accel(theta, theta_dot, float(u), l, p)
    return np.array([theta_dot, theta_ddot, x_dot, x_ddot])


def linearize(l: float, p: RobotParams, inertia: float = 0.0) -> tuple:
    """
    Linearization (2) of model (1) about theta = theta_dot = x_dot = 0, u = 0.

    Returns (A 4x4, B shape (4,)) with
    A = [[0, 1, 0, 0], [(M+m) g / (M l), 0, 0, 0], [0, 0, 0, 1], [-m g / M, 0, 0, 0]],
    B = [0, -1 / (M l), 0, 1 / M].
    inertia: the pendulum's own inertia about its centre of mass I [kg m^2], which model (1)'s
    point mass has not (0: model (1) itself); with J = m l^2 + I and D = (M+m) J - m^2 l^2,
    theta_ddot = m l ((M+m) g theta - u) / D and x_ddot = (J u - m^2 g l^2 theta) / D (the
    linearized (1) with J in place of m l^2; I = 0 gives the matrices above). For checking
    the controllers against an identified robot (docs/identification.md), not for the design.
    """
    m, M, g = p.body_mass, p.wheel_mass, p.gravity
    if inertia == 0.0:   # model (1) as the design uses it, to the last bit
        A = np.array([
            [0.0, 1.0, 0.0, 0.0],
            [(M + m) * g / (M * l), 0.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
            [-m * g / M, 0.0, 0.0, 0.0],
        ])
        return A, np.array([0.0, -1.0 / (M * l), 0.0, 1.0 / M])
    J = m * l * l + inertia
    D = (M + m) * J - (m * l) ** 2
    A = np.array([
        [0.0, 1.0, 0.0, 0.0],
        [m * l * (M + m) * g / D, 0.0, 0.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
        [-(m * l) ** 2 * g / D, 0.0, 0.0, 0.0],
    ])
    B = np.array([0.0, -m * l / D, 0.0, J / D])
    return A, B


def disturbance_input(l: float, p: RobotParams) -> np.ndarray:
    """
    E_d of (5): xi~_dot = A xi~ + B u + E_d d, with theta~ = theta + d.

    E_d = [0, -(M+m) g / (M l), 0, m g / M] = -A e_1, because theta = theta~ - d enters (2)
    only through A's first column.
    """
    A, _ = linearize(l, p)
    return -A[:, 0].copy()


def pfl_force(theta: float, theta_dot: float, nu: float, l: float, p: RobotParams) -> float:
    """
    Partial feedback linearization (3): the force u [N] that makes x_ddot = nu in model (1).

    u = m l (g/l cos(theta) sin(theta) - sin(theta) theta_dot^2 + (sin^2(theta) + M/m)/l nu)
      = m g sin(theta) cos(theta) - m l sin(theta) theta_dot^2 + (M + m sin^2(theta)) nu,
    after which (1) reads (4a) theta_ddot = (g sin(theta) - cos(theta) nu) / l, (4b) x_ddot = nu.
    nu [m/s^2] is the outer-loop acceleration.
    """
    m = p.body_mass
    s = math.sin(theta)
    return (m * p.gravity * s * math.cos(theta) - m * l * s * theta_dot * theta_dot
            + (p.wheel_mass + m * s * s) * nu)


def pfl_accel(theta: float, theta_dot: float, u: float, l: float, p: RobotParams) -> float:
    """Inverse of (3): the acceleration nu = x_ddot [m/s^2] that force u [N] gives in (1)."""
    m = p.body_mass
    s = math.sin(theta)
    return ((u - m * p.gravity * s * math.cos(theta) + m * l * s * theta_dot * theta_dot)
            / (p.wheel_mass + m * s * s))
