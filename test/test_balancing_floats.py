"""
The tick's float path equals the object path: the same numbers, bit for bit.

BalanceCore.advance (what Balancing.step runs) against BalanceCore.step, the controllers'
compute_floats against compute, the observer's update_floats against update.
"""
import math

import numpy as np
import pytest

from wheelleg_balance.core.controller_base import ControlInput
from wheelleg_balance.core.observer import DisturbanceObserver
from wheelleg_balance.core.params import RobotParams
from wheelleg_balance.core.pipeline import (
    BalanceCore, CONTROLLER_NAMES, CoreConfig, Measurement, Reference)

DT = 0.002


def _measurements(n=600):
    """Measurements of a robot swaying and driving, with a few non-finite samples."""
    out = []
    for k in range(n):
        t = k * DT
        theta = 0.04 * math.sin(3.0 * t) + 0.01
        w = 4.0 * math.sin(0.7 * t) + 0.5 * math.cos(5.0 * t)
        l = 0.45 + 0.05 * math.sin(0.9 * t)
        gyro = math.nan if k % 97 == 5 else 0.1 * math.sin(t)
        if k % 131 == 7:
            theta = math.nan
        out.append(Measurement(theta, 0.12 * math.cos(3.0 * t), w, w + 0.3, l, gyro))
    return out


@pytest.mark.parametrize('controller', CONTROLLER_NAMES + ('auto',))
def test_advance_equals_step(controller):
    cores = [BalanceCore(RobotParams(), CoreConfig(controller=controller, yaw_rate_ki=2.0))
             for _ in range(2)]
    meas = _measurements()
    for core in cores:
        core.reset(meas[0])
    for k, m in enumerate(meas):
        ref = Reference(0.3 if 100 < k < 400 else 0.0, 0.5 if k > 300 else 0.0)
        if k == 250 and controller != 'auto':   # a bumpless switch on both
            for core in cores:
                core.select('lqr' if controller != 'lqr' else 'ida_pbc')
        want = cores[0].step(m, ref, DT)
        got = cores[1].advance(m.theta_meas, m.theta_dot, m.wheel_vel_left, m.wheel_vel_right,
                               m.l, m.yaw_rate_gyro, ref.x_dot_ref, ref.yaw_rate_ref, DT)
        for name in got.__slots__:
            assert repr(getattr(got, name)) == repr(getattr(want, name)), (k, name)


@pytest.mark.parametrize('controller', CONTROLLER_NAMES)
def test_compute_floats_equals_compute(controller):
    a, b = (BalanceCore(RobotParams(), CoreConfig(controller=controller)).controllers[
        controller] for _ in range(2))
    rng = np.random.default_rng(3)
    s = ControlInput()
    for c in (a, b):
        c.reset(s)
    for _ in range(300):
        v = rng.normal(scale=[0.1, 0.5, 0.2, 0.3, 0.1, 0.5, 0.2, 0.3, 0.03])
        s = ControlInput(theta=v[0], theta_dot=v[1], x=v[2], x_dot=v[3],
                         l=float(rng.uniform(0.37, 0.7)), x_dot_ref=float(rng.choice([0.0, 0.2])),
                         xi_hat=np.array(v[4:]))
        want = a.compute(s)
        got = b.compute_floats(s.theta, s.theta_dot, s.x, s.x_dot, s.l, s.x_dot_ref,
                               s.xi_hat.tolist())
        assert repr(got) == repr(want)


def test_update_floats_equals_update():
    a, b = DisturbanceObserver(RobotParams()), DisturbanceObserver(RobotParams())
    for o in (a, b):
        o.reset([0.05, 0.0, 0.0, 0.0, 0.0])
    for k, m in enumerate(_measurements(300)):
        u = math.nan if k == 40 else 20.0 * math.sin(0.1 * k)
        want = a.update(m.theta_meas, 0.001 * k, u, m.l)
        got = b.update_floats(m.theta_meas, 0.001 * k, u, m.l)
        assert isinstance(got, list)
        assert [repr(v) for v in got] == [repr(float(v)) for v in want]
