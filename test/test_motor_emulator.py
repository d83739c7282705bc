"""The motor firmware emulators (sim/motor_emulator.py) against what the firmware does."""
import math
import struct

from hypothesis import given, settings, strategies as st
import pytest

from wheelleg_balance.core.protocols.base import Frame
from wheelleg_balance.core.protocols.dji import DjiC620Protocol
from wheelleg_balance.core.protocols.mit import (
    float_to_uint, float_to_uint_wrapping, MitProtocol, uint_to_float)
from wheelleg_balance.sim.motor_emulator import (DjiC620Emulator, MitMotorBank,
                                                 MitMotorEmulator)

MIT = MitProtocol()
DJI = DjiC620Protocol()
STEP_P = 25.0 / 65535.0     # position code step [rad]


def _send(motor, frame, q=0.0, q_dot=0.0, now=0.0):
    reply = motor.handle(frame, q, q_dot, now)
    return None if reply is None else MIT.decode_feedback(reply)


def _enter(motor, q=0.0, now=0.0):
    return _send(motor, MIT.enable_frames([motor.motor_id])[0], q, 0.0, now)


def test_rest_mode_until_enter_then_zero_torque_until_a_command():
    motor = MitMotorEmulator(3)
    fb = _send(motor, MIT.torque_frames({3: 5.0})[0])
    assert fb is not None and fb.motor_id == 3 and abs(fb.torque) < 0.01   # answers, no torque
    assert motor.torque(0.0, 0.0, 0.0) == 0.0
    fb = _enter(motor)
    assert motor.enabled and abs(fb.torque) < 0.01
    assert motor.torque(0.0, 0.0, 0.0) == 0.0         # the stale command was dropped
    fb = _send(motor, MIT.torque_frames({3: 5.0})[0])
    assert fb.torque == pytest.approx(5.0, abs=0.01)
    assert motor.torque(0.0, 0.0, 0.0) == pytest.approx(5.0, abs=0.01)
    fb = _send(motor, MIT.disable_frames([3])[-1])
    assert not motor.enabled and motor.torque(0.0, 0.0, 0.0) == 0.0 and fb is not None


@settings(max_examples=50, deadline=None)
@given(p=st.floats(-3.0, 3.0), v=st.floats(-10.0, 10.0), kp=st.floats(0.0, 100.0),
       kd=st.floats(0.0, 5.0), t=st.floats(-5.0, 5.0), q=st.floats(-3.0, 3.0),
       q_dot=st.floats(-10.0, 10.0), direction=st.sampled_from([1, -1]))
def test_impedance_law_on_the_decoded_command(p, v, kp, kd, t, q, q_dot, direction):
    motor = MitMotorEmulator(5, direction=direction, torque_limit=1e9)
    _enter(motor)
    frame = MIT.command_frame(5, p, v, kp, kd, t)
    motor.handle(frame, q, q_dot, 0.0)
    cmd = MIT.decode_command(frame)
    q_m, v_m = direction * q, direction * q_dot       # the motor's own position and speed
    expected = cmd.kp * (cmd.position - q_m) + cmd.kd * (cmd.velocity - v_m) + cmd.torque
    assert motor.torque(q, q_dot, 0.0) == pytest.approx(direction * expected, abs=1e-9)
    assert motor.motor_torque == pytest.approx(expected, abs=1e-9)


def test_torque_is_clamped_to_the_limit_and_the_reply_reports_it():
    motor = MitMotorEmulator(1, torque_limit=12.0)
    _enter(motor)
    fb = _send(motor, MIT.command_frame(1, 12.0, 0.0, 500.0, 0.0, 18.0))
    assert fb.torque == pytest.approx(12.0, abs=0.01)
    assert motor.torque(0.0, 0.0, 0.0) == pytest.approx(12.0)
    assert motor.torque(24.0, 0.0, 0.0) == pytest.approx(-12.0)


def test_one_reply_per_frame_to_its_id_only():
    motor = MitMotorEmulator(2)
    for frame in (MIT.enable_frames([2])[0], MIT.set_zero_frames([2])[0],
                  MIT.torque_frames({2: 1.0})[0], MIT.disable_frames([2])[-1]):
        reply = motor.handle(frame, 0.0, 0.0, 0.0)
        assert reply is not None and reply.arbitration_id == MIT.master_id
        assert len(reply.data) == 6 and reply.data[0] == 2
    assert motor.handle(MIT.torque_frames({4: 1.0})[0], 0.0, 0.0, 0.0) is None
    assert motor.handle(Frame(2, b'\x00' * 6), 0.0, 0.0, 0.0) is None          # not 8 bytes
    assert motor.handle(Frame(2, b'\x00' * 8, True), 0.0, 0.0, 0.0) is None    # extended
    assert motor.frames == 4


def test_reply_carries_the_true_state_quantized():
    motor = MitMotorEmulator(1, direction=-1)
    fb = _send(motor, MIT.enable_frames([1])[0], q=1.234, q_dot=-2.5)
    assert fb.position == pytest.approx(-1.234, abs=STEP_P)
    assert fb.velocity == pytest.approx(2.5, abs=100.0 / 4095)


def test_temperature_and_error_code_in_8_byte_replies_and_an_error_cuts_the_output():
    motor = MitMotorEmulator(1, reply_temperature=True, temperature=31.0)
    _enter(motor)
    fb = _send(motor, MIT.torque_frames({1: 4.0})[0])
    assert (fb.temperature, fb.error) == (31.0, 0)
    motor.set_temperature(92.0)
    motor.set_error(1)          # over-temperature
    fb = _send(motor, MIT.torque_frames({1: 4.0})[0])
    assert (fb.temperature, fb.error) == (92.0, 1)
    assert abs(fb.torque) < 0.01 and motor.torque(0.0, 0.0, 0.0) == 0.0
    motor.set_error(0)
    assert motor.torque(0.0, 0.0, 0.0) == pytest.approx(4.0, abs=0.01)


@pytest.mark.parametrize('p', [12.5 + 0.1, 12.5 + 7.0, -12.5 - 0.1, -12.5 - 7.0, 30.0, -40.0])
def test_position_beyond_the_range_wraps_like_the_firmware(p):
    motor = MitMotorEmulator(1)
    fb = _send(motor, MIT.enable_frames([1])[0], q=p)
    # bgkatz: p_int = (int)((p - p_min) * 65535 / span), low 16 bits sent.
    code = int((p + 12.5) * 65535 / 25.0) & 0xFFFF
    assert fb.position == pytest.approx(uint_to_float(code, -12.5, 12.5, 16), abs=1e-12)
    period = 65536 * STEP_P
    assert (fb.position - p) / period == pytest.approx(round((fb.position - p) / period),
                                                       abs=2 * STEP_P / period)
    saturating = MitMotorEmulator(1, wrap=False)
    fb = _send(saturating, MIT.enable_frames([1])[0], q=p)
    assert fb.position == pytest.approx(math.copysign(12.5, p))


def test_wrapping_and_clamping_agree_inside_the_range():
    for x in (-12.5, -3.3, 0.0, 0.001, 7.77, 12.5):
        assert float_to_uint_wrapping(x, -12.5, 12.5, 16) == float_to_uint(x, -12.5, 12.5, 16)
    # Just below p_min the C cast truncates towards zero: code 0, then 0xFFFF.
    assert float_to_uint_wrapping(-12.5 - 0.5 * STEP_P, -12.5, 12.5, 16) == 0
    assert float_to_uint_wrapping(-12.5 - 1.5 * STEP_P, -12.5, 12.5, 16) == 0xFFFF


@pytest.mark.parametrize('action', ['zero', 'rest'])
def test_command_timeout(action):
    motor = MitMotorEmulator(1, command_timeout=0.05, timeout_action=action)
    _enter(motor, now=0.0)
    motor.handle(MIT.torque_frames({1: 3.0})[0], 0.0, 0.0, 0.01)
    assert motor.torque(0.0, 0.0, 0.059) == pytest.approx(3.0, abs=0.01)
    assert motor.torque(0.0, 0.0, 0.061) == 0.0            # silent for more than 50 ms
    assert motor.timeouts == 1
    assert motor.enabled == (action == 'zero')
    motor.handle(MIT.torque_frames({1: 3.0})[0], 0.0, 0.0, 0.07)
    resumed = motor.torque(0.0, 0.0, 0.07)
    assert resumed == (pytest.approx(3.0, abs=0.01) if action == 'zero' else 0.0)
    # Without a timeout the last command stays in force.
    motor = MitMotorEmulator(1)
    _enter(motor)
    motor.handle(MIT.torque_frames({1: 3.0})[0], 0.0, 0.0, 0.0)
    assert motor.torque(0.0, 0.0, 100.0) == pytest.approx(3.0, abs=0.01)


def test_set_zero_acts_in_rest_mode_only():
    motor = MitMotorEmulator(1, direction=-1)
    motor.handle(MIT.set_zero_frames([1])[0], 0.7, 0.0, 0.0)
    fb = _enter(motor, q=0.9)
    assert fb.position == pytest.approx(-0.2, abs=STEP_P)
    motor.handle(MIT.set_zero_frames([1])[0], 0.9, 0.0, 0.0)   # ignored in motor mode
    assert motor.position(0.9) == pytest.approx(-0.2)


@settings(max_examples=40, deadline=None)
@given(q=st.floats(-6.0, 6.0), zero=st.floats(-1.0, 1.0), gear=st.sampled_from([6.0, 9.0]))
def test_reboot_keeps_the_position_only_modulo_one_rotor_turn(q, zero, gear):
    motor = MitMotorEmulator(1, gear_ratio=gear)
    motor.zero = zero
    _enter(motor, q=q)
    motor.handle(MIT.torque_frames({1: 2.0})[0], q, 0.0, 0.0)
    before = motor.position(q)
    motor.reboot(q)
    after = motor.position(q)
    turn = 2.0 * math.pi / gear          # 40 deg of output for 9:1
    k = (before - after) / turn
    assert k == pytest.approx(round(k), abs=1e-9)
    assert -1.5 * math.pi < gear * after <= 0.5 * math.pi + 1e-12
    assert not motor.enabled and motor.torque(q, 0.0, 0.0) == 0.0
    # The reading changes one to one with the joint after the reboot.
    assert motor.position(q + 0.1) - after == pytest.approx(0.1)


def test_miswired_motor_turns_the_other_way():
    motor = MitMotorEmulator(1)
    _enter(motor)
    motor.handle(MIT.torque_frames({1: 2.0})[0], 0.0, 0.0, 0.0)
    assert motor.torque(0.0, 0.0, 0.0) == pytest.approx(2.0, abs=0.01)
    motor.miswired = True
    assert motor.torque(0.0, 0.0, 0.0) == pytest.approx(-2.0, abs=0.01)
    assert motor.velocity(1.0) == -1.0 and motor.position(1.0) == -1.0


def test_invalid_configuration_is_rejected():
    with pytest.raises(ValueError):
        MitMotorEmulator(1, direction=0)
    with pytest.raises(ValueError):
        MitMotorEmulator(1, timeout_action='stop')
    with pytest.raises(ValueError):
        MitMotorEmulator(1, gear_ratio=0.0)


def test_reply_id_fault_names_another_motor_in_the_replies():
    motor = MitMotorEmulator(2)
    motor.reply_id = 7
    fb = _enter(motor)
    assert fb.motor_id == 7 and motor.enabled       # it still acts on its own frames
    motor.reply_id = None
    assert _send(motor, MIT.torque_frames({2: 1.0})[0]).motor_id == 2


# ---- a bank of motors without a simulator -----------------------------------------------------

def test_bank_answers_each_motor_with_its_firmware():
    bank = MitMotorBank((1, 2), {2: -1})
    assert bank.handle(MIT.enable_frames([3])[0], 0.0) == []               # no such motor
    assert bank.handle(Frame(1, MIT.enable_frames([1])[0].data, True), 0.0) == []  # extended
    for frame in MIT.enable_frames([1, 2]):
        (reply,) = bank.handle(frame, 0.0)
        assert MIT.decode_feedback(reply).motor_id == frame.arbitration_id
    (reply,) = bank.handle(MIT.torque_frames({2: 3.0})[0], 0.0)
    assert MIT.decode_feedback(reply).torque == pytest.approx(3.0, abs=0.01)
    # Joint torques through each motor's direction: motor 2 is mounted mirrored.
    assert bank.torque(2, 0.0) == pytest.approx(-3.0, abs=0.01)
    assert bank.torque(1, 0.0) == 0.0               # entered, no command yet
    bank.joints[2] = (0.5, -1.0)
    fb = MIT.decode_feedback(bank.handle(MIT.torque_frames({2: 3.0})[0], 0.0)[0])
    assert fb.position == pytest.approx(-0.5, abs=STEP_P) and fb.velocity == pytest.approx(
        1.0, abs=100.0 / 4095)


def test_a_silent_motor_acts_on_its_frames_but_sends_nothing():
    bank = MitMotorBank((1, 2))
    bank.silent.add(2)
    assert bank.handle(MIT.enable_frames([2])[0], 0.0) == []
    assert bank.handle(MIT.torque_frames({2: 2.0})[0], 0.0) == []
    assert bank.torque(2, 0.0) == pytest.approx(2.0, abs=0.01)
    assert bank.motor(2).frames == 2
    bank.silent.clear()
    assert len(bank.handle(MIT.torque_frames({2: 2.0})[0], 0.0)) == 1


# ---- DJI C620 --------------------------------------------------------------------------------

def test_c620_answers_each_command_with_the_feedback_of_the_escs_it_addresses():
    escs = DjiC620Emulator((1, 2, 6), temperature=40)
    frames = DJI.torque_frames({1: 1.5, 2: -0.75, 6: 0.3})
    replies = escs.handle(frames[0])
    assert [r.arbitration_id for r in replies] == [0x201, 0x202]
    # Hand-packed layout (angle, rpm, torque current, temperature, unused), the commanded
    # current as the torque current: 1.5 N m = 5 A = code 4096.
    assert replies[0].data == struct.pack('>HhhBx', 0, 0, 4096, 40)
    assert [DJI.decode_feedback(r).torque for r in replies] == [pytest.approx(1.5, abs=1e-3),
                                                                pytest.approx(-0.75, abs=1e-3)]
    assert escs.torque(1) == pytest.approx(1.5, abs=1e-3)
    (reply,) = escs.handle(frames[1])             # 0x1FF: ESCs 5-8
    assert reply.arbitration_id == 0x206 and escs.torque(6) == pytest.approx(0.3, abs=1e-3)
    assert escs.handle(Frame(0x201, bytes(8))) == []                   # feedback, not a command


def test_c620_feedback_carries_the_motor_state_and_silent_escs_send_none():
    escs = DjiC620Emulator((1, 2))
    ratio = DJI.gear_ratio
    escs.state[2] = (0.1, 2.0)                  # output angle [rad] and speed [rad/s]
    escs.silent.add(1)
    (reply,) = escs.handle(DJI.torque_frames({1: 1.0, 2: 1.0})[0])
    fb = DJI.decode_feedback(reply)
    assert fb.motor_id == 2
    turn = 2.0 * math.pi / ratio                # the angle wraps every rotor turn
    assert (fb.position - 0.1) / turn == pytest.approx(round((fb.position - 0.1) / turn),
                                                       abs=1e-3)
    assert fb.velocity == pytest.approx(2.0, abs=2.0 * math.pi / 60.0 / ratio)
    assert escs.torque(1) == pytest.approx(1.0, abs=1e-3)   # the silent ESC still drives
    with pytest.raises(ValueError):
        DjiC620Emulator((0, 9))
