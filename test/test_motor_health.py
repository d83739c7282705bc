"""
Motor health (core/motor_health.py) in the control tick: heat, error codes, a reboot.

The tick runs on the fault suite's bench (validation/faults/bench.LoopBench: BalanceLoop on a
virtual clock, its frames to the emulated MIT wheel motors of sim/motor_emulator.py, whose
8-byte replies carry temperature and error code); what the tick sends is decoded as the
firmware decodes it.
"""
import math

import pytest

from wheelleg_balance.core.config import DEFAULTS
from wheelleg_balance.core.motor_health import derate, DERATE_FLOOR, MAX_ACCELERATION, \
    position_jump
from wheelleg_balance.core.protocols.mit import MitProtocol
from wheelleg_balance.core.safety import Mode
from wheelleg_balance.validation.faults.bench import is_zero_torque, LoopBench, make_imu

MIT = DEFAULTS.can.mit
LEFT, RIGHT = DEFAULTS.can.left_motor_id, DEFAULTS.can.right_motor_id


def test_derate_is_linear_from_temp_derate_to_the_floor_at_temp_max():
    assert derate(None, 70.0, 85.0) == 1.0
    assert derate(math.nan, 70.0, 85.0) == 1.0
    assert derate(70.0, 70.0, 85.0) == 1.0
    assert derate(77.5, 70.0, 85.0) == pytest.approx(1.0 - 0.5 * (1.0 - DERATE_FLOOR))
    assert derate(85.0, 70.0, 85.0) == DERATE_FLOOR
    assert derate(120.0, 70.0, 85.0) == DERATE_FLOOR


def test_position_jump_is_taken_modulo_the_wrap_of_the_reply_field():
    span = 25.0
    # Moving at 10 rad/s for 2 ms: no jump; across the wrap (12.49 -> -12.49): none either.
    assert position_jump(1.0, 10.0, 0.0, 1.02, 10.0, 0.002, span) == pytest.approx(0.0)
    wrapped = position_jump(12.49, 10.0, 0.0, -12.49, 10.0, 0.002, span)
    assert wrapped == pytest.approx(0.0, abs=1e-9)
    # A rotor turn of a 9:1 gear lost: 0.70 rad.
    slack = 0.5 * MAX_ACCELERATION * 0.002 ** 2   # what acceleration could explain
    assert position_jump(1.0, 0.0, 0.0, 1.0 - 2 * math.pi / 9, 0.0, 0.002, span) == \
        pytest.approx(2 * math.pi / 9 - slack)
    # A late reply (20 ms) of a wheel accelerating at 1500 rad/s^2 is no jump.
    assert position_jump(0.0, 0.0, 0.0, 0.5 * 1500 * 0.02 ** 2, 30.0, 0.02, span) == 0.0
    error_reason = MitProtocol().error_reason   # the reasons of MIT replies' error codes
    assert error_reason(2) == 'over-current' and error_reason(99) == 'unknown error code'


def armed_bench(wheel_angle: float = 0.0, **params) -> LoopBench:
    bench = LoopBench(**params)
    bench.set_wheel_motion((wheel_angle, 0.0), (0.0, 0.0))   # before the first reply
    for e in bench.motors.emulators.values():
        e.reply_temperature = True   # 8-byte replies: temperature and error code
    bench.feed()
    bench.tick()
    bench.rearm()
    for _ in range(5):
        bench.feed()
        bench.tick()
    assert bench.mode == int(Mode.BALANCING)
    return bench


def lean(bench, ticks=5):
    """Feed a pose leaning 0.3 rad forward (the torque saturates); return the last frames."""
    frames = []
    for _ in range(ticks):
        bench.feed(make_imu(0.3, 0.0))
        frames = bench.tick()
    return frames


def test_heat_derates_the_wheel_torque_then_sits_down_and_refuses_to_arm():
    full = 2.0   # below what the lean asks for: the torque saturates at the limit
    bench = armed_bench(fall_angle=1.0, max_wheel_torque=full)
    frames = lean(bench)
    assert max(abs(c.torque) for _, c in frames) == pytest.approx(full, abs=0.01)
    hot = 78.0   # whole degrees: the reply carries an int8
    bench.motors.motor(RIGHT).set_temperature(hot)
    lean(bench, 1)   # the reply with the temperature comes back
    frames = lean(bench, 3)
    share = 1.0 - (1.0 - DERATE_FLOOR) * (hot - MIT.temp_derate) / (MIT.temp_max - MIT.temp_derate)
    assert 0.6 < share < 0.9
    assert max(abs(c.torque) for _, c in frames) == pytest.approx(share * full, abs=0.01)
    assert bench.mode == int(Mode.BALANCING)
    # At temp_max: the sit-down (class b) at the next tick that sees the reply.
    bench.motors.motor(RIGHT).set_temperature(MIT.temp_max)
    lean(bench, 1)
    bench.feed(make_imu(0.3, 0.0))
    bench.tick()
    assert bench.mode == int(Mode.SITTING)
    assert any('over-temperature' in text for _, text in bench.loop.last_result.events)
    bench.estop()
    bench.tick()
    bench.feed()
    req = bench.request(True)
    bench.tick()
    assert not req.success and 'temp_max' in req.message
    bench.motors.motor(RIGHT).set_temperature(40.0)
    for _ in range(25):   # resting motors answer the exit frames sent every 20 ms
        bench.feed()
        bench.tick()
    bench.feed()
    req = bench.request(True)
    bench.tick()
    assert req.success, req.message


@pytest.mark.parametrize('code,reason', [(1, 'motor over-temperature'), (2, 'over-current'),
                                         (5, 'encoder fault'), (77, 'unknown error code')])
def test_a_motor_error_code_faults_with_the_decoded_reason(code, reason):
    bench = armed_bench()
    bench.motors.motor(LEFT).set_error(code)
    bench.feed()
    bench.tick()             # the motor answers this tick's frames with the error
    bench.feed()
    frames = bench.tick()    # this tick reads it
    assert bench.mode == int(Mode.FAULT)
    faults = bench.loop.supervisor.faults
    assert [f.code for f in faults] == ['motor_error']
    assert reason in faults[0].message and 'error %d' % code in faults[0].message
    assert frames and all(is_zero_torque(c) for _, c in frames)
    bench.motors.motor(LEFT).set_error(0)
    bench.feed()
    bench.tick()
    req = bench.request(True)
    bench.feed()
    bench.tick()
    assert req.success, req.message   # cleared by the drive: re-arm allowed


def test_a_drive_error_at_rest_refuses_every_arm_request_until_the_drive_clears_it():
    # At rest the node asks the motors every 20 ms (exit frames): one reply in ten ticks
    # carries the code. The refusal must hold on every tick between them, not only on the
    # tick that read the reply (it did on 3 ticks of 40 before).
    bench = LoopBench()
    for e in bench.motors.emulators.values():
        e.reply_temperature = True   # 8-byte replies: temperature and error code
    bench.motors.motor(LEFT).set_error(2)
    for _ in range(15):
        bench.feed()
        bench.tick()
    refused = []
    for _ in range(40):
        bench.feed()
        req = bench.request(True)
        bench.tick()
        assert req.done
        refused.append(not req.success and 'over-current' in req.message)
    assert all(refused), '%d of 40 arm requests accepted' % refused.count(False)
    assert bench.mode == int(Mode.DISARMED)
    bench.motors.motor(LEFT).set_error(0)   # the drive's error cleared
    for _ in range(15):                      # the next poll's reply says so
        bench.feed()
        bench.tick()
    bench.feed()
    req = bench.request(True)
    bench.tick()
    assert req.success, req.message


def test_a_rebooted_motor_faults_and_is_never_alive_again():
    # The left wheel at 3 rad: after the reboot it reads its angle modulo a rotor turn.
    bench = armed_bench(wheel_angle=3.0)
    bench.motors.motor(LEFT).reboot(3.0)
    bench.feed()
    bench.tick()
    bench.feed()
    frames = bench.tick()
    assert bench.mode == int(Mode.FAULT)
    faults = bench.loop.supervisor.faults
    assert [f.code for f in faults] == ['motor_rebooted'] and 'rotor turn' in faults[0].message
    assert frames and all(is_zero_torque(c) for _, c in frames)
    for _ in range(50):
        bench.feed()
        bench.tick()
    req = bench.request(True)
    bench.feed()
    bench.tick()
    assert not req.success and 'rebooted' in req.message
