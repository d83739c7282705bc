"""
The supervision's per-tick entry points agree with the public ones they stand for.

``LiftDetector.step`` (the wheels' figures apart) is ``update``; ``SafetySupervisor.
update_replies`` (the motor sets' reply maps as groups of pairs, what the tick passes) is
``update`` with the merged map.
"""
import math

from wheelleg_balance.core.lift import LiftDetector
from wheelleg_balance.core.safety import Mode, SafetySupervisor, SensorSnapshot

DT = 0.002


def _detector() -> LiftDetector:
    return LiftDetector(2e-3, 0.02, 3.0, 0.5, 0.03, min_load=13.5, still_min_dv=0.05)


def test_lift_step_is_update():
    a, b = _detector(), _detector()
    w = [0.0, 0.0]
    for k in range(200):
        t = (k + 1) * DT
        tau = (2.0, 1.5) if k < 150 else (math.nan, 0.0)
        w = [w[0] + tau[0] * DT / 2e-3, w[1] + tau[1] * DT / 2e-3]
        load, q, h, f = (54.0 if k < 100 else 5.0), 0.01, 0.2, 9.81
        ra = a.update(t, tau, tuple(w), DT, load, q, h, f)
        rb = b.step(t, tau[0], tau[1], w[0], w[1], DT, load, q, h, f)
        assert ra == rb
        assert repr(a.ratios) == repr(b.ratios) and repr(a.still_share) == repr(b.still_share)


def _fresh(t: float) -> SensorSnapshot:
    return SensorSnapshot(imu_time=t, joint_time=t, theta=0.05, theta_dot=0.0,
                          wheel_vel_left=0.0, wheel_vel_right=0.0, l=0.2)


def test_update_replies_is_update_with_the_merged_map():
    wheels, hips = {1: None, 2: None}, {3: None, 4: None}
    a, b = SafetySupervisor(motor_ids=(1, 2, 3, 4)), SafetySupervisor(motor_ids=(1, 2, 3, 4))
    for sup in (a, b):
        assert sup.arm(10.0, _fresh(10.0), {})[0]
    for k in range(60):
        t = 10.0 + (k + 1) * DT
        for i, times in ((1, wheels), (2, wheels), (3, hips), (4, hips)):
            if not (i == 4 and k > 10):   # motor 4 falls silent
                times[i] = t
        ma = a.update(t, _fresh(t), {**wheels, **hips})
        mb = b.update_replies(t, _fresh(t), (wheels.items(), hips.items()))
        assert ma is mb and a.conditions == b.conditions
    assert a.mode is Mode.FAULT and 'motor 4 silent' in a.faults[0].message
