"""
The LK, CyberGear and DaMiao codecs and emulators (core/protocols/lk.py, cybergear.py, damiao.py).

Vectors come from the documents, worked by hand where a document gives a layout and no bytes
(docs/can_protocols.md has the sources):
[LK]  LK-TECH, MS MF MG motor CAN protocol V2.35: the run and stop samples to motor 1
      (``141 88 00 ..``, ``141 81 00 ..``) and the speed command sample (``141 A2 00 00 00 28
      23 00 00``, 90 dps) are the document's own; the 0xA1, reply and state-1 bytes follow
      its tables (little-endian, iq +-2048 for +-16.5 A on MF motors).
[CG]  Xiaomi CyberGear instruction manual ch. 4 (belovictor/cybergear-docs): 29-bit ID
      type << 24 | data << 8 | target, float_to_uint(x, lo, hi, 16) big-endian; no byte
      examples in the manual, so its formula is worked by hand in each comment.
[DM]  DaMiao DM-J4310 manual as read by cmjang/DM_Control_Python DM_CAN.py and jia-xie/
      python-damiao-driver docs: special frames FF..FC/FD/FE/FB, the reply's status nibble,
      register frames on 0x7FF.
"""
import math
import struct
import time

from hypothesis import given, settings
from hypothesis import strategies as st
import pytest
from wheelleg_balance.core.protocols import (
    CybergearProtocol, DamiaoProtocol, Frame, LkProtocol, make_protocol, MotorFeedback,
    MotorProtocol, protocol_for, PROTOCOLS, register_protocol)
from wheelleg_balance.core.protocols.emulation import EmulatedMotor, EmulatedMotors, \
    torque_only

LK = LkProtocol()          # MF9025 class: 16.5 A at code 2048, 0.32 N m/A, 16-bit encoder
CG = CybergearProtocol()   # P +-4 pi, V +-30, T +-12, kp 0..500, kd 0..5, host 0
DM = DamiaoProtocol()      # DM-J4310: P +-12.5, V +-30, T +-10, MST_ID 0
LK_NM_PER_CODE = 16.5 / 2048 * 0.32
NEW = [LK, CG, DM]


def hexb(text: str) -> bytes:
    return bytes.fromhex(text)


# ---- LK ------------------------------------------------------------------------------------

def test_lk_document_samples():
    # [LK] sec. 1 samples: run (0x88) and stop (0x81) to motor 1 on ID 0x141.
    assert LK.enable_frames([1]) == [Frame(0x141, hexb('88 00 00 00 00 00 00 00'))]
    assert LK.decode_command(Frame(0x141, hexb('81 00 00 00 00 00 00 00'))) == 'stop'
    # The speed closed-loop sample (90 dps = 9000 at 0.01 dps/LSB) is a command of another
    # sender to motor 1: the second-commander check sees it.
    assert LK.command_motor_ids(Frame(0x141, hexb('A2 00 00 00 28 23 00 00'))) == (1,)


def test_lk_torque_command_vector():
    # iq 100 codes = 100 * 16.5 / 2048 A = 0.806 A = 0.2578125 N m at 0.32 N m/A;
    # A1 00 00 00 iq_lo iq_hi 00 00, little-endian.
    assert LK.torque_frames({1: 0.2578125}) == [Frame(0x141, hexb('A1 00 00 00 64 00 00 00'))]
    # -100 N m clamps to -2048 = 0xF800; +inf and NaN send 0 (exactly no current).
    assert LK.torque_frames({2: -100.0})[0].data == hexb('A1 00 00 00 00 F8 00 00')
    for bad in (math.inf, -math.inf, math.nan):
        assert LK.torque_frames({3: bad})[0].data == hexb('A1 00 00 00 00 00 00 00')
    # MG scale: 33 A at 2048, so 1 A * Kt is code 62.06 -> 62 = 0x3E.
    mg = LkProtocol(current_max=33.0, torque_constant=1.32)
    assert mg.torque_frames({1: 1.32})[0].data == hexb('A1 00 00 00 3E 00 00 00')


def test_lk_reply_vector():
    # Motor 1: 40 deg C, iq -500 (0xFE0C), 720 dps (0x02D0), encoder 32768 of 65536 (half a
    # turn): A1 28 0C FE D0 02 00 80.
    fb = LK.decode_feedback(Frame(0x141, hexb('A1 28 0C FE D0 02 00 80')))
    assert (fb.motor_id, fb.temperature, fb.error, fb.enabled) == (1, 40.0, None, None)
    assert fb.position == pytest.approx(math.pi)
    assert fb.velocity == pytest.approx(math.radians(720))
    assert fb.torque == pytest.approx(-500 * LK_NM_PER_CODE)
    # The state-2 read (0x9C) answers with the same layout.
    assert LK.decode_feedback(Frame(0x141, hexb('9C 28 0C FE D0 02 00 80'))) == fb
    # The emulator's side packs the same bytes.
    assert LK.encode_reply(1, 0xA1, 40, -500, 720, 32768) == \
        Frame(0x141, hexb('A1 28 0C FE D0 02 00 80'))


def test_lk_state1_and_error_clear():
    # 9A temperature 00 voltage(0.1 V/LSB, LE) 00 00 errorState: 24.0 V = 240 = 0x00F0;
    # errorState 0x09 = bit 0 under-voltage + bit 3 over-temperature.
    st1 = LK.decode_status(Frame(0x142, hexb('9A 28 00 F0 00 00 00 09')))
    assert st1 == (2, 40.0, pytest.approx(24.0), 9)
    assert LK.error_reason(st1.error) == 'under-voltage, over-temperature'
    assert LK.status_frames([2]) == [Frame(0x142, hexb('9A 00 00 00 00 00 00 00'))]
    assert LK.clear_error_frames([2]) == [Frame(0x142, hexb('9B 00 00 00 00 00 00 00'))]
    assert LK.decode_status(LK.status_frames([2])[0]) is None   # the request is no reply


def test_lk_disable_is_zero_torque_then_off():
    assert LK.disable_frames([1]) == [Frame(0x141, hexb('A1 00 00 00 00 00 00 00')),
                                      Frame(0x141, hexb('80 00 00 00 00 00 00 00'))]


@pytest.mark.parametrize('frame', [
    Frame(0x141, hexb('A1 00 00 00 64 00 00 00')),          # our own torque command
    Frame(0x141, hexb('88 00 00 00 00 00 00 00')),          # run (echoed by the motor)
    Frame(0x161, hexb('A1 28 0C FE D0 02 00 80')),          # ID 33: beyond 0x140 + 32
    Frame(0x141, hexb('A1 28 0C FE D0 02 00 80'), True),    # extended
    Frame(0x141, hexb('A1 28 0C FE D0 02 00')),             # short
])
def test_lk_decode_feedback_rejects(frame):
    assert LK.decode_feedback(frame) is None


def test_lk_encoder_width():
    lk14 = LkProtocol(encoder_bits=14)
    assert lk14.decode_feedback(Frame(0x141, hexb('A1 28 00 00 00 00 FF 3F'))).position == \
        pytest.approx(2 * math.pi * 16383 / 16384)
    assert lk14.decode_feedback(Frame(0x141, hexb('A1 28 00 00 00 00 00 40'))) is None


def test_lk_echoes_are_no_commands():
    # Off, stop and run come back byte for byte: they cannot tell another sender.
    for cmd in ('80', '81', '88'):
        assert LK.command_motor_ids(Frame(0x141, hexb(cmd + ' 00' * 7))) == ()
    assert LK.command_motor_ids(Frame(0x141, hexb('A1 28 0C FE D0 02 00 80'))) == ()
    assert LK.command_motor_ids(LK.torque_frames({5: 1.0})[0]) == (5,)


def lk_bank(**options):
    bank = EmulatedMotors(LK, [1], **options)
    return bank, bank.motor(1)


def test_lk_emulator_torque_stop_run_off():
    bank, m = lk_bank()
    bank.joints[1] = (1.0, 2.0)
    (reply,) = bank.handle(LK.torque_frames({1: 1.0})[0], 0.0)   # no enable needed
    fb = LK.decode_feedback(reply)
    assert fb.torque == pytest.approx(1.0, abs=LK_NM_PER_CODE)
    assert fb.position == pytest.approx(1.0, abs=1e-4) and fb.velocity == \
        pytest.approx(2.0, abs=math.radians(1))
    assert bank.torque(1, 0.0) == pytest.approx(1.0, abs=LK_NM_PER_CODE)
    stop = Frame(0x141, hexb('81 00 00 00 00 00 00 00'))
    assert bank.handle(stop, 0.0) == [stop]      # echoed
    assert bank.torque(1, 0.0) == 0.0
    bank.handle(LK.torque_frames({1: 2.0})[0], 0.0)
    assert bank.torque(1, 0.0) == 0.0            # stopped until run
    bank.handle(LK.enable_frames([1])[0], 0.0)
    assert bank.torque(1, 0.0) == pytest.approx(2.0, abs=LK_NM_PER_CODE)
    for f in LK.disable_frames([1]):
        bank.handle(f, 0.0)
    assert bank.torque(1, 0.0) == 0.0 and m.command is None


def test_lk_emulator_errors_and_saturation():
    bank, m = lk_bank()
    m.set_error(0x08)
    bank.handle(LK.torque_frames({1: 1.0})[0], 0.0)
    assert bank.torque(1, 0.0) == 0.0
    (status,) = bank.handle(LK.status_frames([1])[0], 0.0)
    assert LK.decode_status(status).error == 0x08
    (cleared,) = bank.handle(LK.clear_error_frames([1])[0], 0.0)
    assert LK.decode_status(cleared).error == 0 and bank.torque(1, 0.0) > 0.9
    # The speed field saturates (int16 deg/s), it does not wrap: 600 rad/s reads 32767 dps.
    bank.joints[1] = (0.0, 600.0)
    fb = LK.decode_feedback(bank.handle(LK.torque_frames({1: 0.0})[0], 0.0)[0])
    assert fb.velocity == pytest.approx(math.radians(32767))
    # A torque beyond the motor's limit is clamped in the frame and at the shaft.
    bank.handle(LK.torque_frames({1: 100.0})[0], 0.0)
    assert bank.torque(1, 0.0) == pytest.approx(LK.torque_limit)


def test_lk_reboot_keeps_the_single_turn_reading_and_the_host_unwraps():
    bank, m = lk_bank()
    bank.joints[1] = (7.0, 0.0)    # more than one turn
    before = LK.decode_feedback(bank.handle(LK.torque_frames({1: 0.0})[0], 0.0)[0]).position
    assert before == pytest.approx(7.0 - 2 * math.pi, abs=1e-4)
    m.reboot(7.0)
    after = LK.decode_feedback(bank.handle(LK.torque_frames({1: 0.0})[0], 0.0)[0]).position
    assert after == before
    # position_step unwraps across the encoder's wrap: 6.2 rad -> 0.1 rad is +0.183 rad.
    assert LK.position_step(6.2, 0.1) == pytest.approx(0.1 + 2 * math.pi - 6.2)


# ---- CyberGear -----------------------------------------------------------------------------

def test_cybergear_enable_stop_zero_vectors():
    # [CG] 4.1.4-4.1.6: type << 24 | host ID << 8 | motor ID; data zeros, byte 0 = 1 to
    # clear the fault and for the zero.
    assert CG.enable_frames([127]) == [Frame(0x0300007F, bytes(8), True)]
    assert CG.disable_frames([1])[-1] == Frame(0x04000001, bytes(8), True)
    assert CG.clear_error_frames([1]) == [Frame(0x04000001, hexb('01' + ' 00' * 7), True)]
    assert CG.set_zero_frames([1]) == [Frame(0x06000001, hexb('01' + ' 00' * 7), True)]
    host5 = CybergearProtocol(host_id=5)
    assert host5.enable_frames([1]) == [Frame(0x03000501, bytes(8), True)]


def test_cybergear_operation_control_vectors():
    # Torque only, motor 1, 6 N m: torque int(18 * 65535 / 24) = int(49151.25) = 0xBFFF in
    # the ID; angle 0: int(4 pi * 65535 / 8 pi) = 32767; speed 0: int(30 * 65535 / 60) =
    # 32767; kp = kd = 0.
    assert CG.torque_frames({1: 6.0}) == [Frame(0x01BFFF01, hexb('7F FF 7F FF 00 00 00 00'),
                                                True)]
    # p 1 rad: int((1 + 4 pi) * 65535 / 8 pi) = int(35375.05) = 0x8A2F; v -2: 28 * 65535 / 60
    # = 30583 = 0x7777; kp 10: int(1310.7) = 0x051E; kd 0.5: int(6553.5) = 0x1999;
    # t -3: int(9 * 65535 / 24) = int(24575.6) = 0x5FFF.
    assert CG.command_frame(1, 1.0, -2.0, 10.0, 0.5, -3.0) == \
        Frame(0x015FFF01, hexb('8A 2F 77 77 05 1E 19 99'), True)
    # Ends: +-12 N m are codes 0xFFFF and 0; NaN and inf are sent as 0 N m (32767).
    assert CG.torque_frames({1: 99.0})[0].arbitration_id == 0x01FFFF01
    assert CG.torque_frames({1: -12.0})[0].arbitration_id == 0x01000001
    for bad in (math.nan, math.inf, -math.inf):
        assert CG.torque_frames({1: bad})[0].arbitration_id == 0x017FFF01


def test_cybergear_feedback_vector():
    # Type 2 from motor 1 to host 0: mode 2 (run) in ID bits 22-23, no fault, motor 1 in bits
    # 15-8: ID 0x02800100; angle 0x8000, speed 0x7FFF, torque 0xBFFF, 40.0 deg C = 400.
    fb = CG.decode_feedback(Frame(0x02800100, hexb('80 00 7F FF BF FF 01 90'), True))
    assert (fb.motor_id, fb.temperature, fb.error, fb.enabled) == (1, 40.0, 0, True)
    assert fb.position == pytest.approx(32768 * 8 * math.pi / 65535 - 4 * math.pi)
    assert fb.velocity == pytest.approx(32767 * 60 / 65535 - 30)
    assert fb.torque == pytest.approx(49151 * 24 / 65535 - 12)
    # Over-temperature (ID bit 18), reset mode: ID 0x02040100.
    hot = CG.decode_feedback(Frame(0x02040100, hexb('80 00 7F FF BF FF 03 52'), True))
    assert (hot.error, hot.enabled, hot.temperature) == (0b100, False, 85.0)
    assert CG.error_reason(hot.error) == 'over-temperature'
    assert CG.encode_feedback(1, fb.position, fb.velocity, fb.torque, 40.0) == \
        Frame(0x02800100, hexb('80 00 7F FF BF FF 01 90'), True)


def test_cybergear_parameter_frames():
    # [CG] 4.1.8/4.1.9: index little-endian in bytes 0-1, value in bytes 4-7 (uint8 run_mode
    # in byte 4; float32 little-endian: 5.0 = 00 00 A0 40).
    assert CG.param_write_frame(1, 0x7005, 0) == \
        Frame(0x12000001, hexb('05 70 00 00 00 00 00 00'), True)
    assert CG.param_write_frame(1, 0x700B, 5.0) == \
        Frame(0x12000001, hexb('0B 70 00 00 00 00 A0 40'), True)
    assert CG.param_read_frame(1, 0x7005) == \
        Frame(0x11000001, hexb('05 70 00 00 00 00 00 00'), True)
    # The answer: type 17, motor 1 in ID bits 15-8, the host as target: run_mode 2.
    assert CG.decode_param_reply(Frame(0x11000100, hexb('05 70 00 00 02 00 00 00'), True)) == \
        (1, 0x7005, 2)


def test_cybergear_commands_and_replies():
    for frame in (CG.torque_frames({3: 1.0})[0], CG.enable_frames([3])[0],
                  CG.disable_frames([3])[-1], CG.set_zero_frames([3])[0],
                  CG.param_write_frame(3, 0x7005, 2)):
        assert CG.command_motor_ids(frame) == (3,)
    for frame in (Frame(0x02800300, bytes(8), True), CG.param_read_frame(3, 0x7005),
                  Frame(0x11000300, bytes(8), True), Frame(0x0300007F, bytes(8), False)):
        assert CG.command_motor_ids(frame) == ()
    assert CG.decode_feedback(Frame(0x02800100, bytes(8), True)).motor_id == 1
    assert CG.decode_feedback(Frame(0x02800105, bytes(8), True)) is None   # to host 5
    assert CG.decode_feedback(Frame(0x02800100, bytes(8), False)) is None  # standard ID


def test_cybergear_position_saturates():
    frame = CG.encode_feedback(1, 100.0, 0.0, 0.0, 25.0)
    fb = CG.decode_feedback(frame)
    assert fb.position == pytest.approx(4 * math.pi) and CG.at_position_end(fb.position)
    assert CG.position_saturates and not CG.at_position_end(0.0)
    assert CG.position_step(12.0, -12.0) == -24.0   # no unwrapping across the ends


def cg_bank(**options):
    bank = EmulatedMotors(CG, [1], **options)
    return bank, bank.motor(1)


def test_cybergear_emulator_modes():
    bank, m = cg_bank()
    bank.handle(CG.torque_frames({1: 3.0})[0], 0.0)
    assert bank.torque(1, 0.0) == 0.0               # reset mode at power-up
    (reply,) = bank.handle(CG.enable_frames([1])[0], 0.0)
    assert CG.decode_feedback(reply).enabled
    bank.handle(CG.torque_frames({1: 3.0})[0], 0.0)
    assert bank.torque(1, 0.0) == pytest.approx(3.0, abs=24 / 65535)
    # run_mode cannot change while running; stopped, it can, and then type 1 is ignored.
    bank.handle(CG.param_write_frame(1, 0x7005, 2), 0.0)
    assert m.run_mode == 0
    for f in CG.disable_frames([1]) + [CG.param_write_frame(1, 0x7005, 2)] + \
            CG.enable_frames([1]) + CG.torque_frames({1: 3.0}):
        bank.handle(f, 0.0)
    assert bank.torque(1, 0.0) == 0.0
    (answer,) = bank.handle(CG.param_read_frame(1, 0x7005), 0.0)
    assert CG.decode_param_reply(answer) == (1, 0x7005, 2)


def test_cybergear_emulator_fault_timeout_and_reboot():
    bank, m = cg_bank(command_timeout=0.05)
    for f in CG.enable_frames([1]) + CG.torque_frames({1: 2.0}):
        bank.handle(f, 0.0)
    m.set_error(0b100)
    assert bank.torque(1, 0.01) == 0.0
    (reply,) = bank.handle(CG.clear_error_frames([1])[0], 0.02)
    assert CG.decode_feedback(reply).error == 0 and not CG.decode_feedback(reply).enabled
    for f in CG.enable_frames([1]) + CG.torque_frames({1: 2.0}):
        bank.handle(f, 0.03)
    assert bank.torque(1, 0.06) != 0.0
    assert bank.torque(1, 0.09) == 0.0 and not m.enabled and m.timeouts == 1
    # The zero is lost at power-off: a joint at 3 rad reads from the factory zero afterwards.
    bank.joints[1] = (3.0, 0.0)
    bank.handle(CG.set_zero_frames([1])[0], 0.1)
    assert CG.decode_feedback(bank.handle(CG.enable_frames([1])[0], 0.1)[0]).position == \
        pytest.approx(0.0, abs=1e-3)
    m.reboot(3.0)
    (reply,) = bank.handle(CG.disable_frames([1])[-1], 0.2)   # a stop: answered, no torque
    after = CG.decode_feedback(reply)
    assert not after.enabled
    assert abs(after.position) <= math.pi / 7.75 + 1e-3   # within one rotor turn (7.75:1)
    assert after.position != pytest.approx(0.0, abs=1e-2)  # 3 rad * 7.75 is no whole turn


# ---- DaMiao --------------------------------------------------------------------------------

def test_damiao_special_frames():
    # [DM] system commands on the motor's ID.
    assert DM.enable_frames([1]) == [Frame(1, hexb('FF FF FF FF FF FF FF FC'))]
    assert DM.disable_frames([1])[-1] == Frame(1, hexb('FF FF FF FF FF FF FF FD'))
    assert DM.set_zero_frames([1]) == [Frame(1, hexb('FF FF FF FF FF FF FF FE'))]
    assert DM.clear_error_frames([1]) == [Frame(1, hexb('FF FF FF FF FF FF FF FB'))]
    assert DM.decode_command(Frame(1, hexb('FF FF FF FF FF FF FF FB'))) == 'clear'


def test_damiao_command_vector():
    # MIT layout with DM-J4310 ranges: p 0 -> int(12.5 * 65535 / 25) = 0x7FFF; v 0 ->
    # int(30 * 4095 / 60) = 0x7FF; t 5 N m -> int(15 * 4095 / 20) = int(3071.25) = 0xBFF.
    assert DM.torque_frames({1: 5.0}) == [Frame(1, hexb('7F FF 7F F0 00 00 0B FF'))]
    assert DM.torque_frames({1: math.nan})[0].data[6:] == hexb('07 FF')


def test_damiao_reply_vector():
    # On MST_ID 0: status 1 (enabled) << 4 | motor 1, p 0x8000, v 0x7FF, t 0x800, MOS 40,
    # rotor 45 deg C.
    fb = DM.decode_feedback(Frame(0, hexb('11 80 00 7F F8 00 28 2D')))
    assert (fb.motor_id, fb.enabled, fb.error, fb.temperature) == (1, True, 0, 45.0)
    assert fb.position == pytest.approx(32768 * 25 / 65535 - 12.5)
    assert fb.velocity == pytest.approx(2047 * 60 / 4095 - 30)
    assert fb.torque == pytest.approx(2048 * 20 / 4095 - 10)
    # MOS over-temperature (0xB) of motor 2; a reply on another ID is not ours.
    hot = DM.decode_feedback(Frame(0, hexb('B2 80 00 7F F8 00 5A 32')))
    assert (hot.motor_id, hot.enabled, hot.error, hot.temperature) == (2, False, 0xB, 90.0)
    assert DM.error_reason(hot.error) == 'MOS over-temperature'
    assert DM.decode_feedback(Frame(0x11, hexb('11 80 00 7F F8 00 28 2D'))) is None
    assert DamiaoProtocol(master_id=0x11).decode_feedback(
        Frame(0x11, hexb('11 80 00 7F F8 00 28 2D'))).motor_id == 1
    assert DM.encode_state(1, 1, fb.position, fb.velocity, fb.torque, 40, 45) == \
        Frame(0, hexb('11 80 00 7F F8 00 28 2D'))


def test_damiao_registers():
    # [DM] 0x7FF: id_lo id_hi 33|55 rid value(LE); CTRL_MODE is register 10, 1 = MIT.
    assert DM.register_read_frame(1, 10) == Frame(0x7FF, hexb('01 00 33 0A 00 00 00 00'))
    assert DM.register_write_frame(1, 10, 1) == Frame(0x7FF, hexb('01 00 55 0A 01 00 00 00'))
    assert DM.register_write_frame(1, 21, 12.5) == Frame(0x7FF, hexb('01 00 55 15 00 00 48 41'))
    assert DM.decode_register_reply(Frame(0, hexb('01 00 33 0A 03 00 00 00'))) == (1, 10, 3)
    assert DM.decode_register_reply(Frame(0, hexb('01 00 33 15 00 00 48 41'))) == (1, 21, 12.5)
    assert DM.control_mode_problem(1, 1) is None
    text = DM.control_mode_problem(1, 3)
    assert 'velocity mode' in text and 'register 10 = 1' in text


def test_damiao_commands_and_replies():
    assert DM.command_motor_ids(DM.torque_frames({3: 1.0})[0]) == (3,)
    assert DM.command_motor_ids(DM.clear_error_frames([3])[0]) == (3,)
    assert DM.command_motor_ids(DM.register_write_frame(3, 10, 1)) == (3,)
    assert DM.command_motor_ids(DM.register_read_frame(3, 10)) == ()
    assert DM.command_motor_ids(Frame(0, hexb('13 80 00 7F F8 00 28 2D'))) == ()


def dm_bank(**options):
    bank = EmulatedMotors(DM, [1, 2], **options)
    return bank, bank.motor(1)


def test_damiao_emulator_enable_and_wrong_mode():
    bank, m = dm_bank()
    (reply,) = bank.handle(DM.torque_frames({1: 2.0})[0], 0.0)
    assert not DM.decode_feedback(reply).enabled and bank.torque(1, 0.0) == 0.0
    for f in DM.enable_frames([1]) + DM.torque_frames({1: 2.0}):
        (reply,) = bank.handle(f, 0.0)
    assert DM.decode_feedback(reply).enabled
    assert bank.torque(1, 0.0) == pytest.approx(2.0, abs=20 / 4095)
    # A motor in velocity mode ignores MIT frames; bring-up reads register 10 and says why.
    m2 = bank.motor(2)
    m2.control_mode = 3
    for f in DM.enable_frames([2]) + DM.torque_frames({2: 2.0}):
        bank.handle(f, 0.0)
    assert bank.torque(2, 0.0) == 0.0
    (answer,) = bank.handle(DM.register_read_frame(2, 10), 0.0)
    motor, register, mode = DM.decode_register_reply(answer)
    assert (motor, register, mode) == (2, 10, 3) and DM.control_mode_problem(2, mode)
    bank.handle(DM.register_write_frame(2, 10, 1), 0.0)
    bank.handle(DM.torque_frames({2: 2.0})[0], 0.0)
    assert bank.torque(2, 0.0) == pytest.approx(2.0, abs=20 / 4095)


def test_damiao_emulator_timeout_fault_and_reboot():
    bank, m = dm_bank(command_timeout=0.05)
    for f in DM.enable_frames([1]) + DM.torque_frames({1: 2.0}):
        bank.handle(f, 0.0)
    assert bank.torque(1, 0.06) == 0.0
    (reply,) = bank.handle(DM.torque_frames({1: 2.0})[0], 0.07)
    fb = DM.decode_feedback(reply)
    assert (fb.error, fb.enabled) == (0xD, False) and bank.torque(1, 0.07) == 0.0
    bank.handle(DM.enable_frames([1])[0], 0.08)
    assert not m.enabled                                     # refused until cleared
    for f in DM.clear_error_frames([1]) + DM.enable_frames([1]) + DM.torque_frames({1: 2.0}):
        bank.handle(f, 0.08)
    assert bank.torque(1, 0.09) != 0.0
    bank.joints[1] = (5.0, 0.0)
    m.reboot(5.0)
    (reply,) = bank.handle(DM.enable_frames([1])[0], 0.1)
    assert DM.decode_feedback(reply).position == pytest.approx(5.0 - 2 * math.pi, abs=1e-3)


# ---- all three ------------------------------------------------------------------------------

@pytest.mark.parametrize('protocol', NEW, ids=lambda p: p.name)
@settings(max_examples=200, deadline=None)
@given(tau=st.floats(), motor_id=st.integers(1, 15))
def test_torque_frames_never_raise_and_stay_within_the_limit(protocol, tau, motor_id):
    bank = EmulatedMotors(protocol, [motor_id])
    for f in protocol.enable_frames([motor_id]) + protocol.torque_frames({motor_id: tau}):
        bank.handle(f, 0.0)
    applied = bank.torque(motor_id, 0.0)
    limit = protocol.torque_limit
    assert math.isfinite(applied) and abs(applied) <= limit + 1e-9
    lsb = 2 * limit / 4095
    if not math.isfinite(tau):
        assert abs(applied) <= lsb
    else:
        assert applied == pytest.approx(min(limit, max(-limit, tau)), abs=lsb)


@pytest.mark.parametrize('protocol', NEW, ids=lambda p: p.name)
@settings(max_examples=300, deadline=None)
@given(frame=st.builds(Frame, st.integers(-10, 0x1FFFFFFF), st.binary(max_size=8),
                       st.booleans()))
def test_decoders_never_raise(protocol, frame):
    fb = protocol.decode_feedback(frame)
    assert fb is None or isinstance(fb, MotorFeedback)
    assert isinstance(protocol.command_motor_ids(frame), tuple)


@pytest.mark.parametrize('protocol, p_max, v_max', [(CG, 4 * math.pi, 30.0),
                                                    (DM, 12.5, 30.0)], ids=['cybergear',
                                                                            'damiao'])
@pytest.mark.parametrize('x', [-1.0, -0.5, 0.0, 0.5, 1.0])
def test_reply_round_trip_at_the_ends(protocol, p_max, v_max, x):
    bank = EmulatedMotors(protocol, [1], wrap=False) if protocol is DM else \
        EmulatedMotors(protocol, [1])
    bank.joints[1] = (x * p_max, x * v_max)
    (reply,) = bank.handle(protocol.enable_frames([1])[0], 0.0)
    fb = protocol.decode_feedback(reply)
    assert fb.position == pytest.approx(x * p_max, abs=2 * p_max / 65535)
    assert fb.velocity == pytest.approx(x * v_max, abs=2 * v_max / 4095)


def test_registry_builds_from_config_sections():
    from wheelleg_balance.core.config import BalanceConfig
    from wheelleg_balance.core.schema import with_changes
    cfg = with_changes(BalanceConfig(), {'can.lk.current_max': 33.0,
                                         'legs.damiao.t_max': 28.0})
    assert protocol_for('lk', cfg.can).current_max == 33.0
    assert protocol_for('damiao', cfg.legs).t_max == 28.0
    assert protocol_for('cybergear', cfg.legs).t_max == 12.0
    assert isinstance(make_protocol('cybergear', host_id=3), CybergearProtocol)
    assert {'lk', 'cybergear', 'damiao'} <= set(PROTOCOLS)


class _TestProtocol(MotorProtocol):
    """A protocol defined outside the package: one byte of torque in tenths of N m."""

    name = 'test_tenths'

    def enable_frames(self, motor_ids):
        return []

    def disable_frames(self, motor_ids):
        return self.zero_torque_frames(motor_ids)

    def torque_frames(self, torques):
        return [Frame(0x600 + i, struct.pack('b', max(-100, min(100, round(t * 10))))
                      if math.isfinite(t) else b'\0') for i, t in torques.items()]

    def zero_torque_frames(self, motor_ids):
        return self.torque_frames(dict.fromkeys(motor_ids, 0.0))

    def decode_feedback(self, frame):
        return None

    def command_motor_ids(self, frame):
        return (frame.arbitration_id - 0x600,) if 0x600 < frame.arbitration_id < 0x680 else ()

    def make_emulator(self, motor_id, **options):
        return _TestMotor(motor_id, 10.0, powered_enabled=True, **options)


class _TestMotor(EmulatedMotor):
    """_TestProtocol's motor: applies the byte's torque, never answers."""

    def handle(self, frame, q, q_dot, now):
        if frame.arbitration_id == 0x600 + self.motor_id:
            self.set_command(torque_only(struct.unpack('b', frame.data)[0] / 10), now)
        return None


def test_a_protocol_defined_in_a_test_module_plugs_into_the_table(monkeypatch):
    monkeypatch.setitem(PROTOCOLS, _TestProtocol.name, None)   # removed again afterwards
    register_protocol(_TestProtocol)
    assert PROTOCOLS['test_tenths'] is _TestProtocol
    from wheelleg_balance.core.config import BalanceConfig
    proto = protocol_for('test_tenths', BalanceConfig().can)   # no section: its defaults
    assert proto.frames_per_tick([1, 2]) == 2
    bank = EmulatedMotors(proto, [1])
    bank.handle(proto.torque_frames({1: 1.5})[0], 0.0)
    assert bank.torque(1, 0.0) == pytest.approx(1.5)
    with pytest.raises(ValueError):
        register_protocol(int)


@pytest.mark.parametrize('protocol, wrong, words', [
    (CG, {'run_mode': 2}, 'speed mode (run_mode = 2)'),
    (DM, {'control_mode': 2}, 'position-velocity mode (CTRL_MODE = 2)')],
    ids=['cybergear', 'damiao'])
def test_bring_up_finds_a_motor_in_the_wrong_mode(protocol, wrong, words):
    bank = EmulatedMotors(protocol, [1, 2])
    for key, value in wrong.items():
        setattr(bank.motor(2), key, value)
    verdicts = dict(protocol.mode_problem(r) for f in protocol.mode_query_frames([1, 2])
                    for r in bank.handle(f, 0.0))
    assert verdicts[1] is None
    assert words in verdicts[2] and ('run_mode 0' in verdicts[2] or '= 1' in verdicts[2])
    assert protocol.mode_problem(protocol.torque_frames({1: 0.0})[0]) is None
    assert LK.mode_query_frames([1]) == [] and LK.mode_problem(Frame(0x141, bytes(8))) is None


@pytest.mark.parametrize('changes, words', [
    ({'can.protocol': 'lk', 'can.left_motor_id': 33}, 'lk: motor ID 33 outside 1..32'),
    ({'can.protocol': 'damiao', 'can.right_motor_id': 17}, 'damiao: motor ID 17 outside'),
    ({'can.protocol': 'cybergear', 'can.left_motor_id': 0}, 'cybergear: motor ID 0'),
    ({'can.protocol': 'dji_c620', 'can.left_motor_id': 9}, 'dji_c620: ESC ID 9'),
    ({'legs.driven': True, 'legs.can.protocol': 'damiao', 'legs.motor_ids': [3, 4, 5, 16]},
     'damiao: motor ID 16'),
    ({'can.protocol': 'lk', 'can.lk.current_limit': 30.0}, 'lk motor figures'),
    ({'can.protocol': 'lk'}, "max_wheel_torque 12.00 N m above the lk motors' limit 5.28"),
])
def test_each_protocol_judges_its_figures_and_ids_in_the_configuration(changes, words):
    from wheelleg_balance.core.config import BalanceConfig
    from wheelleg_balance.core.schema import check, with_changes
    base = {'wheel_state_source': 'joint_states', 'max_wheel_torque': 5.0}
    if 'max_wheel_torque' in words:
        base.pop('max_wheel_torque')
    problems = check(with_changes(BalanceConfig(), {**base, **changes}))
    assert any(words in p for p in problems), problems
    fine = {k: v for k, v in changes.items() if k in ('can.protocol', 'legs.can.protocol')}
    if 'legs.can.protocol' in fine or 'max_wheel_torque' in words:
        return
    assert check(with_changes(BalanceConfig(), {**base, **fine, 'max_wheel_torque': 4.0})) == []


@pytest.mark.parametrize('protocol', NEW, ids=lambda p: p.name)
def test_per_tick_encode_and_decode_take_microseconds(protocol):
    # As test_protocols.py's for MIT and the C620: two motors' frames and one reply decoded.
    bank = EmulatedMotors(protocol, [1, 2])
    frames = protocol.enable_frames([1]) + protocol.torque_frames({1: 1.0})
    reply = [r for f in frames for r in bank.handle(f, 0.0)][-1]
    torques, ids = {1: 3.2, 2: -3.1}, {1: None, 2: None}
    assert protocol.decode_reply(reply, ids).motor_id == 1
    n, best = 2000, math.inf
    for _ in range(5):  # best of five: the machine is shared
        start = time.perf_counter()
        for _ in range(n):
            protocol.torque_frames(torques)
            protocol.decode_reply(reply, ids)
        best = min(best, (time.perf_counter() - start) / n)
    assert best < 30e-6
