"""The tests' own integrator of the nonlinear model (1), shared by the linear-control tests."""
from wheelleg_balance.core.model import ipc_accel


def rk4(state, u, l, h, p):
    """One RK4 step of model (1) for params p: state [theta, theta_dot, x, x_dot], u held."""
    def f(s):
        theta_ddot, x_ddot = ipc_accel(s[0], s[1], u, l, p)
        return (s[1], theta_ddot, s[3], x_ddot)
    k1 = f(state)
    k2 = f([s + 0.5 * h * k for s, k in zip(state, k1)])
    k3 = f([s + 0.5 * h * k for s, k in zip(state, k2)])
    k4 = f([s + h * k for s, k in zip(state, k3)])
    return [s + h / 6.0 * (a + 2 * b + 2 * c + d) for s, a, b, c, d in zip(state, k1, k2, k3, k4)]
