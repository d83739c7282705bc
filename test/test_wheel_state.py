"""
Wheel angle and speed from quantized MIT replies (core/wheel_state.py).

The replies come from the motor emulator (sim/motor_emulator.py) as the host gets them: one per
torque command at 500 Hz, decoded with MitProtocol.
"""
import math

import numpy as np
import pytest

from wheelleg_balance.core.protocols.mit import MitProtocol
from wheelleg_balance.core.wheel_state import WheelState
from wheelleg_balance.sim.motor_emulator import MitMotorEmulator

MIT = MitProtocol()
DT = 0.002
V_CODE = 100.0 / 4095.0      # rad/s per speed code
P_CODE = 25.0 / 65535.0      # rad per position code


def _replies(q, q_dot, direction=1, wrap=True, stamps=None):
    """Yield the decoded replies of a motor whose joint follows q[k], q_dot[k]."""
    motor = MitMotorEmulator(1, direction=direction, wrap=wrap)
    frame = MIT.torque_frames({1: 0.0})[0]
    stamps = np.arange(len(q)) * DT if stamps is None else stamps
    for k, t in enumerate(stamps):
        fb = MIT.decode_feedback(motor.handle(frame, float(q[k]), float(q_dot[k]), float(t)))
        yield fb.position, fb.velocity, float(t)


def _run(q, q_dot, **kw):
    direction = kw.pop('direction', 1)
    wheel = WheelState(direction=direction, wrap=kw.get('wrap', True),
                       time_constant=kw.pop('time_constant', 0.1))
    out = []
    for p, v, t in _replies(q, q_dot, direction, **kw):
        assert wheel.update(p, v, t)
        out.append(wheel.reading(t))
    return wheel, out


@pytest.mark.parametrize('speed', [0.0, 0.004, 0.013, 0.5, 3.3, -7.1])
def test_steady_speed_error_is_far_below_one_speed_code(speed):
    t = np.arange(2500) * DT                 # 5 s
    q = 0.3 + speed * t
    _, out = _run(q, np.full_like(t, speed))
    est = np.array([r.speed for r in out[500:]])          # after the first second
    raw = np.array([r.reported_speed - 0.5 * V_CODE for r in out[500:]])   # as decoded
    err = est - speed
    assert abs(err.mean()) < 1e-3                # 0.1 mm/s of x_dot
    assert np.sqrt((err ** 2).mean()) < 3e-3
    assert np.abs(err).max() < 0.5 * V_CODE
    # The decoded speed alone is biased by truncation: between one code low and exact.
    assert np.all(raw <= speed + 1e-9) and np.all(raw > speed - V_CODE - 1e-9)


def test_standing_still_reads_zero_not_minus_half_a_code():
    t = np.arange(1000) * DT
    wheel, out = _run(np.full_like(t, 1.0), np.zeros_like(t))
    decoded = MIT.decode_feedback(MIT.encode_reply(1, 0.0, 0.0, 0.0)).velocity
    assert decoded == pytest.approx(-0.5 * V_CODE, rel=1e-3)     # -0.0122 rad/s as sent
    assert abs(out[-1].speed) < 1e-9 and abs(out[-1].reported_speed) < 1e-9


def test_speed_follows_a_moving_profile():
    """Accelerating and braking: the blend keeps the reported speed's bandwidth."""
    t = np.arange(3000) * DT
    w = 2.0 * np.pi * 0.5
    q_dot = 4.0 * np.sin(w * t)
    q = 4.0 * (1.0 - np.cos(w * t)) / w
    _, out = _run(q, q_dot)
    err = (np.array([r.speed for r in out]) - q_dot)[250:]
    decoded_err = (np.array([r.reported_speed for r in out]) - 0.5 * V_CODE - q_dot)[250:]
    assert np.abs(err).max() < V_CODE
    # While the speed sweeps through the codes their error is like white noise (rms about
    # code / sqrt(12) = 7 mrad/s); what a controller integrates is its average over 50 ms.
    window = np.ones(25) / 25.0
    assert np.sqrt((np.convolve(err, window, 'valid') ** 2).mean()) < 3e-3
    assert np.sqrt((np.convolve(decoded_err, window, 'valid') ** 2).mean()) > 10e-3


@pytest.mark.parametrize('speed', [20.0, -20.0])
def test_angle_is_unwrapped_across_the_wrap_point_both_ways(speed):
    t = np.arange(2000) * DT        # 4 s: 80 rad, past +-12.5 rad three times
    q0 = 11.0 * math.copysign(1.0, speed)
    q = q0 + speed * t
    _, out = _run(q, np.full_like(t, speed))
    angle = np.array([r.angle for r in out])
    assert np.abs(angle - (q - q0)).max() < 1.5 * P_CODE
    # And back: reverse through the same wrap points.
    q_back = np.concatenate([q, q[-1] - speed * t])
    _, out = _run(q_back, np.concatenate([np.full_like(t, speed), np.full_like(t, -speed)]))
    angle = np.array([r.angle for r in out])
    assert np.abs(angle - (q_back - q0)).max() < 1.5 * P_CODE
    assert abs(angle[-1]) < 1.5 * P_CODE


def test_a_reply_gap_longer_than_half_the_range_is_unwrapped_from_the_speed():
    # 0.3 s without replies at 45 rad/s: 13.5 rad, more than half the 25 rad range.
    stamps = np.concatenate([np.arange(500) * DT, 1.3 + np.arange(100) * DT])
    q = 45.0 * stamps
    wheel = WheelState()
    for p, v, s in _replies(q, np.full_like(q, 45.0), stamps=stamps):
        wheel.update(p, v, s)
    r = wheel.reading(stamps[-1])
    assert r.angle == pytest.approx(q[-1], abs=2 * P_CODE)
    assert r.speed == pytest.approx(45.0, abs=V_CODE)


def test_direction_and_age():
    t = np.arange(200) * DT
    wheel, out = _run(2.0 * t, np.full_like(t, 2.0), direction=-1)
    # The motor turns backwards for a forward wheel: the reading is forward again.
    assert out[-1].speed == pytest.approx(2.0, abs=5e-3)
    assert out[-1].angle == pytest.approx(2.0 * t[-1], abs=2 * P_CODE)
    assert wheel.reading(t[-1] + 0.05).age == pytest.approx(0.05)
    assert WheelState().reading(0.0).age == math.inf


def test_bad_replies_are_refused():
    wheel = WheelState()
    assert wheel.update(0.1, 0.0, 1.0)
    assert not wheel.update(math.nan, 0.0, 1.002)
    assert not wheel.update(0.1, math.inf, 1.002)
    assert not wheel.update(0.1, 0.0, 0.5)          # older than the last one
    assert wheel.rejected == 3 and wheel.replies == 1
    with pytest.raises(ValueError):
        WheelState(direction=0)


def test_saturating_firmware_dead_reckons_beyond_the_range():
    t = np.arange(1500) * DT          # 3 s at 5 rad/s from 5 rad: 7.5 rad past p_max
    q = 5.0 + 5.0 * t
    wheel, out = _run(q, np.full_like(t, 5.0), wrap=False)
    inside = [r for r, qq in zip(out, q) if qq < 12.4]
    beyond = [(r, qq) for r, qq in zip(out, q) if qq > 12.6]
    assert not any(r.saturated for r in inside)
    assert all(r.saturated for r, _ in beyond)
    err = max(abs(r.angle - (qq - 5.0)) for r, qq in beyond)
    assert err < 0.01     # integrated speed: within 10 mrad after 1.5 s past the limit


# ------------------------------------------- replies that contradict the speed (issue 29)

def _track(q, q_dot, stamps=None, firmware_wraps=False, node_wraps=True):
    """Feed a WheelState (node_wraps) replies of a firmware that wraps or saturates."""
    wheel = WheelState(wrap=node_wraps)
    out = []
    for p, v, t in _replies(q, q_dot, wrap=firmware_wraps, stamps=stamps):
        assert wheel.update(p, v, t)
        out.append(wheel.reading(t))
    return wheel, out


def test_a_saturating_encoder_read_as_wrapping_is_a_mismatch_and_dead_reckoned_both_ways():
    """
    Firmware that clamps at +-12.5 rad, the node assuming it wraps (the default).

    Out past the end at 5 rad/s and back: flagged within the window, the angle dead-reckoned
    within the limit of the true one all along, and trusted again once back inside.
    """
    t = np.arange(2000) * DT                        # 4 s: 10 -> 20 rad and back
    q_dot = np.where(t < 2.0, 5.0, -5.0)
    q = 10.0 + np.where(t < 2.0, 5.0 * t, 10.0 - 5.0 * (t - 2.0))
    wheel, out = _track(q, q_dot)
    angle = np.array([r.angle for r in out]) + 10.0
    flagged = [tt for tt, r in zip(t, out) if r.mismatch]
    t_end = (12.5 - 10.0) / 5.0                     # the reading froze here
    assert flagged and t_end < flagged[0] < t_end + 0.05
    # Until it is flagged the angle is the frozen reading, at most the limit (0.05 rad and
    # 12 ms of receipt jitter at the speed) behind; from then on dead-reckoned from where the
    # contradiction began: off by what the speed reading's quantization integrates to (at
    # most half a code, 12 mrad/s, over the 3 s it lasts), never frozen.
    err = np.abs(angle - q)
    assert err.max() < 0.05 + 0.012 * 5.0 + 5.0 * DT
    assert err[t >= flagged[0]].max() < 0.5 * V_CODE * 3.0 + 0.002
    assert wheel.mismatches == 1 and 'rad' in wheel.mismatch_reason
    # Trusted again once off the range end and agreeing for the window, then exact.
    t_back = 2.0 + (20.0 - 12.5) / 5.0
    assert not out[-1].mismatch
    assert t_back < flagged[-1] < t_back + 2.5 * 0.05
    assert abs(angle[-1] - q[-1]) < 2 * P_CODE
    # The old blend read the wheel as nearly still beyond the end: here the frozen reading
    # pulls the speed down by at most the limit over tau (0.1 s) until it is flagged, and the
    # speed is the reported one from then on (but at the reversal's step).
    speed = np.array([r.speed for r in out])
    assert speed[t < 2.0].min() > 5.0 - 1.2
    dead = (t >= flagged[0]) & (np.abs(t - 2.0) > 0.005)
    assert np.abs(speed - q_dot)[dead].max() < 0.5 * V_CODE


def test_a_slow_roll_past_the_end_is_caught_by_the_code_stuck_there():
    """0.4 rad/s (4 cm/s): 0.02 rad per 50 ms is no window mismatch; the stuck code is."""
    t = np.arange(1500) * DT
    q = 12.3 + 0.4 * t                               # reaches 12.5 rad at 0.5 s
    wheel, out = _track(q, np.full_like(t, 0.4))
    flagged = [tt for tt, r in zip(t, out) if r.mismatch]
    assert flagged and 0.5 < flagged[0] < 0.5 + 0.2   # 0.05 rad + jitter at 0.4 rad/s
    assert 'stuck at its range end' in wheel.mismatch_reason
    angle = np.array([r.angle for r in out]) + 12.3
    assert np.abs(angle - q).max() < 0.06


@pytest.mark.parametrize('case', ['steady', 'sweep', 'wraps', 'still_at_end', 'jitter',
                                  'fast'])
def test_no_mismatch_where_position_and_speed_agree(case):
    """Wrapping firmware, the speed sweeping, a wheel still on the end code, late stamps."""
    rng = np.random.default_rng(7)
    t = np.arange(3000) * DT
    stamps = None
    if case == 'steady':
        q_dot = np.full_like(t, 3.3)
        q = 0.3 + 3.3 * t
    elif case == 'sweep':                            # 6 rad/s at 2 Hz: 75 rad/s^2
        w = 2.0 * np.pi * 2.0
        q_dot = 6.0 * np.sin(w * t)
        q = 6.0 * (1.0 - np.cos(w * t)) / w
    elif case == 'wraps':                            # through the wrap point, both ways
        q_dot = np.where(t < 3.0, 20.0, -20.0)
        q = 11.0 + np.where(t < 3.0, 20.0 * t, 60.0 - 20.0 * (t - 3.0))
    elif case == 'still_at_end':                     # on code 65535, the speed reading +1 code
        q_dot = np.full_like(t, 0.02)
        q = np.full_like(t, 12.5 - 1e-6)
    elif case == 'jitter':                           # replies read up to 12 ms late
        q_dot = np.full_like(t, 10.0)
        q = 10.0 * t
        stamps = t + rng.uniform(0.0, 0.012, len(t))
        stamps = np.maximum.accumulate(stamps)
    else:                                            # near the speed field's end: not judged
        q_dot = np.full_like(t, 48.0)
        q = 48.0 * t
    wheel, out = _track(q, q_dot, stamps=stamps, firmware_wraps=True)
    assert wheel.mismatches == 0 and not any(r.mismatch for r in out)


def test_with_wrap_false_the_end_is_no_mismatch_but_a_jump_inside_is():
    t = np.arange(1500) * DT
    q = 5.0 + 5.0 * t
    wheel, out = _track(q, np.full_like(t, 5.0), node_wraps=False)
    assert any(r.saturated for r in out) and wheel.mismatches == 0
    # A reading that jumps by 0.3 rad (an encoder glitch, a reboot) while the speed is 0.
    wheel = WheelState(wrap=False)
    for k in range(100):
        wheel.update(1.0 if k < 50 else 1.3, -0.5 * V_CODE, k * DT)   # 0 as decoded
    assert wheel.mismatches == 1 and wheel.mismatch
    assert wheel.reading(0.2).angle == pytest.approx(0.0, abs=1e-3)   # the jump not taken
