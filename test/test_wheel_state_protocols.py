"""
Wheel angle and speed from every protocol's replies (core/wheel_state.py, reply_codes).

Each protocol's own emulator answers its torque commands at 500 Hz as the host gets them; the
wheel state unwraps the single-turn encoders (LK, the C620), the wrapping MIT-framed fields
(DaMiao) and dead-reckons past the ends of a saturating one (CyberGear).
"""
import math

import numpy as np
import pytest

from wheelleg_balance.core.config import BalanceConfig
from wheelleg_balance.core.protocols import make_protocol
from wheelleg_balance.core.protocols.base import Frame, MotorFeedback, MotorProtocol
from wheelleg_balance.core.schema import check, with_changes
from wheelleg_balance.core.wheel_state import WheelState

DT = 0.002

#: (protocol name, constructor parameters): the wheel motors builders use.
WHEELS = [('lk', {}),                                          # MF9025: 16-bit, direct drive
          ('lk', {'encoder_bits': 14, 'gear_ratio': 10.0}),    # an MG with a 10:1 gear
          ('dji_c620', {}),                                    # M3508 P19, 8192 codes a turn
          ('damiao', {}),
          ('cybergear', {})]


def _replies(protocol, q, q_dot, stamps=None):
    """Yield the decoded replies of an emulated motor whose joint follows q[k], q_dot[k]."""
    motor = protocol.make_emulator(1)
    stamps = np.arange(len(q)) * DT if stamps is None else stamps
    for frame in protocol.enable_frames([1]):
        motor.handle(frame, float(q[0]), 0.0, 0.0)
    frame = protocol.torque_frames({1: 0.0})[0]
    for k, t in enumerate(stamps):
        fb = protocol.decode_feedback(motor.handle(frame, float(q[k]), float(q_dot[k]),
                                                   float(t)))
        yield fb.position, fb.velocity, float(t)


def _run(protocol, q, q_dot, stamps=None):
    wheel = WheelState(protocol=protocol)
    out = []
    for p, v, t in _replies(protocol, q, q_dot, stamps):
        assert wheel.update(p, v, t)
        out.append(wheel.reading(t))
    return wheel, out


@pytest.mark.parametrize('name, params', WHEELS)
@pytest.mark.parametrize('speed', [9.0, -9.0])
def test_the_angle_is_unwrapped_over_many_turns_and_back(name, params, speed):
    """36 rad each way at 9 rad/s (0.9 m/s of a 0.1 m wheel): many encoder turns."""
    protocol = make_protocol(name, **params)
    codes = protocol.reply_codes()
    t = np.arange(2000) * DT
    q = np.concatenate([0.2 + speed * t, 0.2 + speed * t[-1] - speed * t])
    q_dot = np.concatenate([np.full_like(t, speed), np.full_like(t, -speed)])
    if codes.saturates:   # stay inside the range: saturation is the next test's
        q = np.clip(q, -0.9 * codes.p_step * 32767, 0.9 * codes.p_step * 32767)
        q_dot = np.gradient(q, DT)
    wheel, out = _run(protocol, q, q_dot)
    angle = np.array([r.angle for r in out])
    assert np.abs(angle - (q - q[0])).max() < 2.0 * codes.p_step
    speed_err = np.array([r.speed for r in out]) - q_dot
    steady = np.r_[250:1900, 2250:3900]
    # Far below one speed code (LK: 17.5 mrad/s; the C620: 5.5) on average.
    assert abs(speed_err[steady].mean()) < max(0.1 * codes.v_step, 1e-3)
    assert wheel.mismatches == 0 and not any(r.saturated for r in out)


def test_a_saturating_field_is_dead_reckoned_past_its_end_and_taken_back():
    """The CyberGear's angle sticks at +-4 pi: past it the angle comes from the speed."""
    protocol = make_protocol('cybergear')
    t = np.arange(2500) * DT
    w = 2.0 * math.pi / 5.0
    q = 10.0 + 4.0 * np.sin(w * t)                    # out past 4 pi (12.57) and back in
    speed = 4.0 * w * np.cos(w * t)
    wheel, out = _run(protocol, q, speed)
    angle = np.array([r.angle for r in out])
    saturated = np.array([r.saturated for r in out])
    assert saturated.any() and not saturated[-1]
    assert np.abs(angle - (q - q[0])).max() < 0.01    # 1 mm of wheel travel
    assert wheel.mismatches == 0


class _EndlessProtocol(MotorProtocol):
    """A test protocol whose reply position neither wraps nor ends (the default codes)."""

    name = 'endless_test'

    def enable_frames(self, motor_ids):
        return []

    def disable_frames(self, motor_ids):
        return []

    def torque_frames(self, torques):
        return [Frame(0x300 + i, b'') for i in torques]

    def zero_torque_frames(self, motor_ids):
        return self.torque_frames(dict.fromkeys(motor_ids, 0.0))

    def decode_feedback(self, frame):
        return None

    def command_motor_ids(self, frame):
        return ()


class _TurnProtocol(_EndlessProtocol):
    """One that only says its position wraps every 1 rad (default reply_codes from it)."""

    position_span = 1.0


@pytest.mark.parametrize('cls', [_EndlessProtocol, _TurnProtocol])
def test_a_protocol_with_only_a_position_span_is_unwrapped(cls):
    protocol = cls()
    wheel = WheelState(protocol=protocol)
    t = np.arange(1000) * DT
    q = -3.0 + 4.0 * t
    for k in range(len(t)):
        p = math.fmod(q[k], protocol.position_span) if math.isfinite(protocol.position_span) \
            else q[k]
        fb = MotorFeedback(1, p, 4.0, 0.0)
        assert wheel.update(fb.position, fb.velocity, float(t[k]))
    r = wheel.reading(float(t[-1]))
    step = protocol.reply_codes().p_step
    assert r.angle == pytest.approx(q[-1] - q[0], abs=step)
    # A position code's error passes the blend as at most step / tau (0.1 s).
    assert r.speed == pytest.approx(4.0, abs=step / 0.1)
    assert wheel.mismatches == 0


@pytest.mark.parametrize('name', ['lk', 'dji_c620', 'cybergear', 'damiao'])
def test_wheel_state_from_can_takes_any_protocol(name):
    cfg = with_changes(BalanceConfig(), {'can.protocol': name, 'max_wheel_torque': 1.0})
    assert cfg.wheel_state.wheel_state_source == 'can'
    assert check(cfg) == []
