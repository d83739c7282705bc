"""
The response check (core/response.py): the pitch answers the wheel torque as model (1) says.

The unit tests drive ResponseCheck with model (1) itself: a plant held up by a controller that
sees the true pitch, measured straight (the sign right), turned round (an IMU turned 180 deg
about z: theta~ and theta_dot of the other sign), with a force model (1) does not have (a
steady push), and with a torque that does not change. The closed-loop tests arm the MuJoCo
robot upright at 2 deg with the IMU's pitch sign wrong (``imu_mounting_rpy`` [0, 0, pi] for an
IMU that sits straight): whole robot in lockstep (validation/lockstep.py), legs fixed and
driven, and the fault rig's MuJoCo plant with LoopBench; each must fault ``response``, naming
the mounting and direction parameters, with zero torque before the true pitch leaves 10 deg.
"""
import math

import pytest

from wheelleg_balance.core.config import DEFAULTS
from wheelleg_balance.core.model import ipc_accel
from wheelleg_balance.core.response import ResponseCheck

P = DEFAULTS.model
S = DEFAULTS.safety
DT = 0.002
L = 0.37


def check() -> ResponseCheck:
    return ResponseCheck(P, S.response_window, S.response_min_effect, S.response_gain,
                         S.response_time)


def run(seconds, sign=1.0, push=0.0, excite=lambda t: 40.0 * math.sin(2 * math.pi * 4.0 * t),
        det=None, until=lambda det: False):
    """
    Run model (1) held near upright; return (time of the fault or None, reason, the check).

    u = K theta + excitation (the true pitch); the check sees sign * theta and sign *
    theta_dot. push: a pitch acceleration model (1) does not have [rad/s^2]. ``det.ks``: the
    fits; ``until(det)`` ends the run early.
    """
    det = det or check()
    det.ks = []
    theta, theta_dot, t, u = 0.01, 0.0, 0.0, 0.0
    for _ in range(int(round(seconds / DT))):
        for _ in range(4):   # the plant at 0.5 ms under the torque of the tick
            acc = ipc_accel(theta, theta_dot, u, L, P)[0] + push
            theta_dot += acc * DT / 4
            theta += theta_dot * DT / 4
        t += DT
        reason = det.update(t, sign * theta, sign * theta_dot, u, L, DT)
        if not math.isnan(det.k):
            det.ks.append(det.k)
        if reason is not None or until(det):
            return t, reason, det
        u = 400.0 * theta + 60.0 * theta_dot + excite(t)
    return None, None, det


def test_the_right_sign_is_silent_and_its_gain_is_one():
    t, reason, det = run(3.0)
    assert reason is None
    assert min(det.ks) == pytest.approx(1.0, abs=0.05)
    assert max(det.ks) == pytest.approx(1.0, abs=0.05)


def test_the_pitch_sign_turned_round_faults_naming_the_parameters():
    t, reason, det = run(1.0, sign=-1.0)
    assert reason is not None
    for name in ('imu_mounting_rpy', 'can.left_direction', 'can.right_direction'):
        assert name in reason
    assert max(det.ks) == pytest.approx(-1.0, abs=0.1)
    # Half a window to fit (a full one before the torque's change is enough to judge), then
    # the wrong sign for response_time.
    assert det.wrong_time == pytest.approx(S.response_time, abs=1.5 * DT)
    assert t <= S.response_window + S.response_time + 2 * DT + 1e-9


def test_a_steady_force_model_1_lacks_is_no_wrong_sign():
    # 5 rad/s^2 that the model does not know (a push, a slope, an offset estimate still
    # wrong): the fit's constant takes it, the gain stays near 1.
    t, reason, det = run(3.0, push=5.0)
    assert reason is None
    assert min(det.ks) == pytest.approx(1.0, abs=0.1)


def test_a_torque_that_does_not_change_tells_nothing():
    # Turned round, but the excitation gone and the plant still: no fit, no fault.
    t, reason, det = run(1.0, sign=-1.0, excite=lambda t: 0.0)
    assert reason is None
    assert not det.ks


def test_the_wrong_time_runs_back_on_the_right_sign():
    # Upright (theta 0: the part without force is 0), the pitch rate answering the torque
    # with gain -1, then +1: the wrong-sign time grows, then runs back a tick per tick (one
    # window of the right sign amid the wrong does not clear it).
    det, rate, t = check(), 0.0, 0.0
    trace = []
    for gain, seconds in ((-1.0, None), (1.0, 0.1)):
        for _ in range(int(round((seconds or 1.0) / DT))):
            t += DT
            u = 40.0 * math.sin(2 * math.pi * 4.0 * t)
            rate += gain * DT * ipc_accel(0.0, rate, u, L, P)[0]
            assert det.update(t, 0.0, rate, u, L, DT) is None
            trace.append(det.wrong_time)
            if seconds is None and det.wrong_time >= 0.5 * S.response_time:
                break
    peak = max(trace)
    assert 0.5 * S.response_time <= peak < S.response_time
    assert trace[-1] == 0.0
    drop = trace.index(peak)
    assert all(b <= a for a, b in zip(trace[drop:], trace[drop + 1:]))   # runs back only


def test_bad_input_never_raises_and_restarts_the_window():
    det = check()
    for bad in (math.nan, math.inf, -math.inf):
        assert det.update(0.002, bad, 0.0, 1.0, L, DT) is None
        assert det.update(0.004, 0.0, bad, 1.0, L, DT) is None
        assert det.update(0.006, 0.0, 0.0, bad, L, DT) is None
        assert det.update(0.008, 0.0, 0.0, 1.0, bad, DT) is None
    assert det.update(0.010, 0.0, 0.0, 1.0, L, 0.0) is None
    assert det.update(0.012, 0.0, 0.0, 1.0, 0.0, DT) is None
    assert len(det._samples) == 0


# ----------------------------------------------------------------- closed loop (MuJoCo)

@pytest.mark.slow
@pytest.mark.parametrize('driven', [False, True], ids=['fixed_legs', 'driven_legs'])
def test_armed_upright_with_the_imu_turned_round_faults_response_within_10_deg(driven):
    pytest.importorskip('mujoco')
    from wheelleg_balance.validation.faults.lockstep import scenario_imu_flipped
    out = scenario_imu_flipped(None, driven=driven)
    assert out.handled, (out.failures, out.figures)
    assert out.figures['peak_pitch_before_zero_deg'] < 10.0


@pytest.mark.slow
def test_the_fault_rigs_mujoco_plant_with_the_imu_turned_round_faults_response():
    pytest.importorskip('mujoco')
    from wheelleg_balance.validation.faults.lockstep import scenario_imu_flipped_plant
    out = scenario_imu_flipped_plant(None)
    assert out.handled, (out.failures, out.figures)
    assert out.figures['peak_pitch_before_zero_deg'] < 10.0
