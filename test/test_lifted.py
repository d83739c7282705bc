"""
Lifted, wheels free (core/lift.py): the detector, and the whole robot picked up in MuJoCo.

The unit tests drive LiftDetector with the two kinds of wheel a torque can meet: a free wheel
(omega_dot = tau / I_w) and one on the ground (ten times the inertia), and a robot whose legs
stop carrying weight. The closed-loop tests (validation/lockstep.py: BalanceLoop against the
MuJoCo robot and its six emulated MIT motors) pick the balancing robot up (a weld to a stand,
0.1 m up) and require zero wheel torque on the bus within 0.1 s, the legs holding their length,
and a re-arm refused while it is held in the air; and they push the balancing robot, drive it
over bumps and back and forth, where the check must stay silent.
"""
import math

import pytest

from wheelleg_balance.core.balance_loop import Mode
from wheelleg_balance.core.config import DEFAULTS
from wheelleg_balance.core.lift import LiftDetector

S = DEFAULTS.safety
I_W = S.lift_wheel_inertia
DT = 0.002


def detector(**kw) -> LiftDetector:
    args = {'inertia': I_W, 'window': S.lift_window, 'min_dv': S.lift_min_dv,
            'ratio': S.lift_ratio, 'free_time': S.lift_free_time, 'min_load': 13.5,
            'unloaded_time': S.lift_unloaded_time}
    args.update(kw)
    return LiftDetector(**args)


def run(det, seconds, torque, inertia, load=54.0, t0=0.0, w0=(0.0, 0.0)):
    """Apply ``torque`` (per wheel) to wheels of ``inertia``; return (time of fault, reason)."""
    w = list(w0)
    for k in range(int(round(seconds / DT))):
        t = t0 + (k + 1) * DT
        tau = torque(t) if callable(torque) else torque
        taus = tau if isinstance(tau, tuple) else (tau, tau)
        inert = inertia if isinstance(inertia, tuple) else (inertia, inertia)
        for j in (0, 1):
            w[j] += taus[j] * DT / inert[j]
        reason = det.update(t, taus, w, DT, load)
        if reason is not None:
            return t - t0, reason
    return None, None


def test_free_wheels_fault_within_the_window_and_free_time():
    t, reason = run(detector(), 0.5, 2.0, I_W)
    assert reason is not None and 'spin free' in reason
    # One window to judge, then both wheels free for lift_free_time.
    assert t == pytest.approx(S.lift_window + S.lift_free_time, abs=2 * DT)


def test_wheels_on_the_ground_do_not_fault_even_at_the_torque_limit():
    # On the ground the torque moves the whole robot: about ten times the wheel's inertia.
    t, reason = run(detector(), 2.0, lambda t: 12.0 * math.sin(20.0 * t), 10 * I_W)
    assert reason is None


def test_one_wheel_free_faults_only_after_three_times_the_free_time():
    t, reason = run(detector(), 0.5, 2.0, (I_W, 10 * I_W))
    assert reason is not None and 'left' in reason and 'right' not in reason
    assert t == pytest.approx(S.lift_window + 3 * S.lift_free_time, abs=2 * DT)


def test_wheels_briefly_free_over_a_bump_do_not_fault():
    # Both wheels free for 20 ms (shorter than lift_free_time), then back on the ground.
    def inertia_at(t):
        return I_W if 0.1 <= t < 0.12 else 10 * I_W
    det, w, fault = detector(), 0.0, None
    for k in range(500):
        t = (k + 1) * DT
        w += 5.0 * DT / inertia_at(t)
        fault = fault or det.update(t, (5.0, 5.0), (w, w), DT, 54.0)
    assert fault is None


def test_too_little_torque_to_tell_is_not_judged():
    # A ratio of 1, but the torques would change a free wheel by less than lift_min_dv.
    t, reason = run(detector(), 1.0, 0.5 * S.lift_min_dv * I_W / S.lift_window, I_W)
    assert reason is None


def test_unloaded_legs_fault_after_lift_unloaded_time():
    det = detector()
    t, reason = run(det, 0.5, 0.0, 10 * I_W, load=-20.0)
    assert reason is not None and 'legs unloaded' in reason
    assert t == pytest.approx(S.lift_unloaded_time, abs=1.5 * DT)
    # A load dip shorter than that (a bump, a small drop) is not.
    det = detector()
    assert run(det, 0.04, 0.0, 10 * I_W, load=0.0)[1] is None
    assert run(det, 0.5, 0.0, 10 * I_W, load=54.0, t0=0.04)[1] is None


def test_bad_input_never_raises_and_restarts_the_window():
    det = detector()
    for bad in (math.nan, math.inf, -math.inf):
        assert det.update(0.002, (bad, 0.0), (0.0, 0.0), DT, math.nan) is None
        assert det.update(0.004, (0.0, 0.0), (bad, 0.0), DT, bad) is None
    assert det.update(0.006, (1.0, 1.0), (0.0, 0.0), 0.0) is None
    t, reason = run(det, 0.5, 2.0, I_W, t0=0.006)
    assert t == pytest.approx(S.lift_window + S.lift_free_time, abs=2 * DT)


# ----------------------------------------------------------------- closed loop (MuJoCo)

D = math.radians(2.2)


def standing(**sim):
    """Return a Lockstep whose robot stood up from its tail (8 s)."""
    pytest.importorskip('mujoco')
    from wheelleg_balance.validation.lockstep import Lockstep
    ls = Lockstep(imu_offset=D, **sim)
    ls.run(0.5)
    ls.arm(True)
    ls.run(7.5)
    assert ls.mode == int(Mode.BALANCING), ls.events
    return ls


@pytest.mark.slow
@pytest.mark.parametrize('tilt_deg,rule', [(0.0, 'legs unloaded'), (15.0, 'spin free')])
def test_picked_up_while_balancing_cuts_the_wheels_within_0_1_s_legs_holding(tilt_deg, rule):
    # The fault suite's scenario (validation/faults/lockstep.py): every check it makes. Held
    # at its balance pitch the controller asks for little torque: the legs tell (82 ms); held
    # 15 deg off it, the wheels spin up and tell first (40 ms).
    pytest.importorskip('mujoco')
    from wheelleg_balance.validation.faults.lockstep import scenario_lifted
    out = scenario_lifted(None, tilt_deg)
    assert out.handled, out.failures
    assert out.time_to_zero <= 0.1
    assert rule in out.figures['reason']


@pytest.mark.slow
def test_pushes_bumps_and_driving_do_not_trip_the_lifted_check():
    # Pushed forward and back (100 N for 0.1 s), then driven at 0.5 m/s over three 2 cm bumps
    # and back.
    from wheelleg_balance.sim.robot_sim import Push
    ls = standing(pushes=[Push(9.0, 0.1, 100.0), Push(11.0, 0.1, -100.0)],
                  bumps=[0.5, 1.0, 1.5], bump_height=0.02)
    ls.run(4.0)
    for _ in range(int(6.0 / ls.period)):
        ls.command(0.5)
        ls.tick()
    for _ in range(int(4.0 / ls.period)):
        ls.command(-0.5)
        ls.tick()
    modes = [row['mode'] for row in ls.log]
    assert int(Mode.FAULT) not in modes, [e for e in ls.events if e[0] == 'error']
    assert max(row['x_true'] for row in ls.log) > 1.55   # it went over the three bumps
