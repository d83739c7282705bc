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
