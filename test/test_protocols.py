"""
CAN codecs (core/protocols): byte vectors from public sources, robustness, speed.

Sources of the MIT-mode vectors (see docs/can_protocols.md):
[K] Ben Katz's motor firmware, github.com/bgkatz/motorcontrol: Core/Src/can.c (unpack_cmd,
    pack_reply bit layout), Core/Src/math_ops.c (float_to_uint: int((x - x_min) *
    ((1 << bits) - 1) / span)), Core/Src/stm32f4xx_it.c (FF..FC/FD/FE special frames).
[D] dfki-ric-underactuated-lab/mini-cheetah-tmotor-python-can, src/motor_driver/canmotorlib.py:
    the same float_to_uint (with 2**bits - 1), enable/disable/zero byte strings, 6-byte replies
    and the 8-byte (temperature, error) replies of newer CubeMars firmware.
[C] CubeMars AK Series Actuator Driver Manual V1.0.8, sec. 5.3 "MIT power mode": same layout
    and special frames, reply with temperature and error code; its example float_to_uint
    omits the -1 (we follow [K] and [D], see test_minus_one_convention).
DJI vectors: RoboMaster C620 user guide (CAN protocol) and the M3508 P19 specifications
(0.3 N m/A, 3591/187), as also used by ASR-Crash/XMU-RM-SWSD-UM docs/Motor-Parameters.md and
Chosen-Zeng/lib lib/periph/M3508.h.
"""
import math
import struct
import time

from hypothesis import given, settings
from hypothesis import strategies as st
import pytest
from wheelleg_balance.core.protocols import (
    DjiC620Protocol, Frame, make_protocol, MitCommand, MitProtocol, MotorFeedback)
from wheelleg_balance.core.protocols.mit import float_to_uint, uint_to_float

MIT = MitProtocol()  # AK80-9 class: P +-12.5, V +-50, KP 0..500, KD 0..5, T +-18
DJI = DjiC620Protocol()

# Resolution (one LSB) of each MIT field with the default ranges.
LSB_P, LSB_V, LSB_T = 25.0 / 65535, 100.0 / 4095, 36.0 / 4095


# ---- MIT: byte vectors ---------------------------------------------------------------------

def test_torque_command_vector():
    # tau = 5 N m, p = v = kp = kd = 0, formula of [K]/[D]:
    #   p  = int((0 + 12.5) * 65535 / 25)  = int(32767.5) = 32767 = 0x7FFF
    #   v  = int((0 + 50) * 4095 / 100)    = int(2047.5)  = 2047  = 0x7FF
    #   kp = kd = 0
    #   t  = int((5 + 18) * 4095 / 36)     = int(2616.25) = 2616  = 0xA38
    # layout [K] unpack_cmd: p[15:8] p[7:0] v[11:4] v[3:0]|kp[11:8] kp[7:0] kd[11:4]
    #   kd[3:0]|t[11:8] t[7:0]
    (frame,) = MIT.torque_frames({1: 5.0})
    assert frame == Frame(1, bytes.fromhex('7F FF 7F F0 00 00 0A 38'), False)


def test_full_command_vector_and_motor_side_decode():
    # p = 1 rad:   int(13.5 * 65535 / 25) = int(35388.9) = 35388 = 0x8A3C
    # v = -2 rad/s: int(48 * 4095 / 100)   = int(1965.6)  = 1965  = 0x7AD
    # kp = 10:     int(10 * 4095 / 500)    = int(81.9)    = 81    = 0x051
    # kd = 0.5:    int(0.5 * 4095 / 5)     = int(409.5)   = 409   = 0x199
    # t = -3 N m:  int(15 * 4095 / 36)     = int(1706.25) = 1706  = 0x6AA
    frame = MIT.command_frame(3, 1.0, -2.0, 10.0, 0.5, -3.0)
    assert frame == Frame(3, bytes.fromhex('8A 3C 7A D0 51 19 96 AA'))
    cmd = MIT.decode_command(frame)
    assert isinstance(cmd, MitCommand) and cmd.motor_id == 3
    expected = (1.0, -2.0, 10.0, 0.5, -3.0)
    lsb = (LSB_P, LSB_V, 500.0 / 4095, 5.0 / 4095, LSB_T)
    for got, want, step in zip(cmd[1:], expected, lsb):
        assert want - step < got <= want + 1e-12  # truncation: never above the value


def test_reply_vector_six_bytes():
    # motor 1, p = -1 rad: int(11.5 * 65535 / 25) = int(30146.1) = 30146 = 0x75C2
    #          v = 3 rad/s: int(53 * 4095 / 100)   = int(2170.35) = 2170  = 0x87A
    #          t = 2 N m:   int(20 * 4095 / 36)    = 2275 = 0x8E3
    # layout [K] pack_reply: id p[15:8] p[7:0] v[11:4] v[3:0]|t[11:8] t[7:0]; sent on the
    # master ID (CAN_MASTER, 0 by default)
    data = bytes.fromhex('01 75 C2 87 A8 E3')
    assert MIT.encode_reply(1, -1.0, 3.0, 2.0) == Frame(0, data)
    fb = MIT.decode_feedback(Frame(0, data))
    assert fb.motor_id == 1
    assert fb.position == pytest.approx(-1.0, abs=LSB_P)
    assert fb.velocity == pytest.approx(3.0, abs=LSB_V)
    assert fb.torque == pytest.approx(2.0, abs=1e-12)  # 2275 is exact
    assert fb.temperature is None and fb.error is None


def test_reply_vector_eight_bytes_with_temperature_and_error():
    # [C]/[D]: newer CubeMars firmware appends temperature and an error code
    fb = MIT.decode_feedback(Frame(0, bytes.fromhex('02 75 C2 87 A8 E3 28 00')))
    assert (fb.motor_id, fb.temperature, fb.error) == (2, 40.0, 0)
    fb = MIT.decode_feedback(Frame(2, bytes.fromhex('02 75 C2 87 A8 E3 F6 01')))
    assert (fb.motor_id, fb.temperature, fb.error) == (2, -10.0, 1)  # reply on own ID too
    assert MIT.encode_reply(2, -1.0, 3.0, 2.0, temperature=40.0).data == \
        bytes.fromhex('02 75 C2 87 A8 E3 28 00')


def test_special_frames():
    enter = bytes.fromhex('FF FF FF FF FF FF FF FC')
    leave = bytes.fromhex('FF FF FF FF FF FF FF FD')
    zero = bytes.fromhex('FF FF FF FF FF FF FF FE')
    assert MIT.enable_frames([1, 2]) == [Frame(1, enter), Frame(2, enter)]
    assert MIT.set_zero_frames([2]) == [Frame(2, zero)]
    frames = MIT.disable_frames([1])
    assert frames[-1] == Frame(1, leave)
    assert frames[:-1] == MIT.zero_torque_frames([1])  # zero torque before leaving
    for data, name in ((enter, 'enter'), (leave, 'exit'), (zero, 'zero')):
        assert MIT.decode_command(Frame(1, data)) == name


def test_minus_one_convention():
    # [K]/[D] scale by 2**bits - 1, so the range ends map to 0 and all ones. [C]'s example
    # (x - x_min) * (1 << bits) / span would give 4096 at t_max (13 bits: overflow) and
    # 0x8000 instead of 0x7FFF at p = 0.
    assert MIT.torque_frames({1: 18.0})[0].data[6:] == bytes.fromhex('0F FF')
    assert MIT.torque_frames({1: -18.0})[0].data[6:] == bytes.fromhex('00 00')
    assert float_to_uint(0.0, -12.5, 12.5, 16) == 0x7FFF
    assert int((0.0 + 12.5) * (1 << 16) / 25.0) == 0x8000  # [C], for contrast


def test_zero_torque_is_within_one_lsb_of_zero():
    (frame,) = MIT.zero_torque_frames([1])
    assert abs(MIT.decode_command(frame).torque) < LSB_T


# ---- MIT: robustness -----------------------------------------------------------------------

@settings(max_examples=300, deadline=None)
@given(tau=st.floats(), motor_id=st.integers(1, 127))
def test_torque_frames_never_raise_and_stay_in_range(tau, motor_id):
    (frame,) = MIT.torque_frames({motor_id: tau})
    assert frame.arbitration_id == motor_id and len(frame.data) == 8
    cmd = MIT.decode_command(frame)
    assert (cmd.position, cmd.kp, cmd.kd) == (pytest.approx(0.0, abs=LSB_P), 0.0, 0.0)
    assert -18.0 <= cmd.torque <= 18.0
    if not math.isfinite(tau):
        assert abs(cmd.torque) < LSB_T  # NaN/inf -> zero torque
    else:
        clamped = min(18.0, max(-18.0, tau))
        assert clamped - LSB_T - 1e-9 < cmd.torque <= clamped + 1e-9


@settings(max_examples=500, deadline=None)
@given(values=st.lists(st.one_of(st.floats(), st.sampled_from(
    [12.5, -12.5, 50.0, -50.0, 500.0, 5.0, 18.0, -18.0, 0.0, -0.0])), min_size=5, max_size=5))
def test_full_command_is_float_to_uint_of_each_field(values):
    # command_frame packs each field as the firmware's float_to_uint does (clamped, truncated;
    # NaN and inf as 0), whatever the value, at the ends of the ranges too.
    ranges = ((-12.5, 12.5, 16), (-50.0, 50.0, 12), (0.0, 500.0, 12), (0.0, 5.0, 12),
              (-18.0, 18.0, 12))
    p, v, kp, kd, t = (float_to_uint(x if math.isfinite(x) else 0.0, lo, hi, bits)
                       for x, (lo, hi, bits) in zip(values, ranges))
    expected = bytes((p >> 8, p & 0xFF, v >> 4, ((v & 0xF) << 4) | (kp >> 8), kp & 0xFF,
                      kd >> 4, ((kd & 0xF) << 4) | (t >> 8), t & 0xFF))
    assert MIT.command_frame(9, *values) == Frame(9, expected)


@settings(max_examples=300, deadline=None)
@given(p=st.floats(-12.5, 12.5), v=st.floats(-50, 50), t=st.floats(-18, 18))
def test_reply_round_trip(p, v, t):
    fb = MIT.decode_feedback(MIT.encode_reply(7, p, v, t))
    assert fb.motor_id == 7
    assert p - LSB_P - 1e-9 < fb.position <= p + 1e-9
    assert v - LSB_V - 1e-9 < fb.velocity <= v + 1e-9
    assert t - LSB_T - 1e-9 < fb.torque <= t + 1e-9


@pytest.mark.parametrize('frame', [
    Frame(0, bytes(5)),                                         # short
    Frame(0, bytes(7)),                                         # odd length
    Frame(0, bytes.fromhex('01 75 C2 87 A8 E3'), True),         # extended ID
    Frame(0x201, bytes.fromhex('01 75 C2 87 A8 E3')),           # foreign ID
    Frame(1, bytes.fromhex('7F FF 7F F0 00 00 0A 38')),         # our own torque command
    Frame(1, bytes.fromhex('FF FF FF FF FF FF FF FC')),         # enter motor mode
    Frame(0x203, bytes.fromhex('10 00 03 E8 F8 00 28 00')),     # a C620 feedback frame
    Frame(0x800, bytes(6)), Frame(-1, bytes(6)),                # not an 11-bit ID
    Frame(0, 6), Frame(0, None), Frame(0, [1, 2, 3, 4, 5, 999]),  # not bytes
])
def test_mit_decode_feedback_rejects_foreign_and_malformed_frames(frame):
    assert MIT.decode_feedback(frame) is None


frames = st.builds(Frame, st.integers(-10, 0x1FFFFFFF), st.binary(max_size=8), st.booleans())


@settings(max_examples=300, deadline=None)
@given(frame=frames)
def test_decoders_never_raise(frame):
    for result in (MIT.decode_feedback(frame), DJI.decode_feedback(frame)):
        assert result is None or isinstance(result, MotorFeedback)
    assert MIT.decode_command(frame) is None or len(frame.data) == 8


def test_decode_command_rejects_short_frames():
    assert MIT.decode_command(Frame(1, bytes(6))) is None


def test_bad_ranges_are_rejected():
    with pytest.raises(ValueError):
        MitProtocol(t_min=18.0, t_max=-18.0)
    with pytest.raises(ValueError):
        MitProtocol(v_max=math.inf)
    with pytest.raises(ValueError):
        MitProtocol(master_id=0x800)


def test_other_ranges_scale_the_torque():
    ak10 = MitProtocol(t_min=-65.0, t_max=65.0)
    (frame,) = ak10.torque_frames({1: 5.0})
    t = int((5.0 + 65.0) * 4095 / 130.0)
    assert frame.data[6:] == bytes((t >> 8, t & 0xFF))
    assert uint_to_float(t, -65.0, 65.0, 12) == pytest.approx(5.0, abs=130.0 / 4095)


# ---- DJI C620 ------------------------------------------------------------------------------

def test_dji_current_vectors():
    # 1.5 N m / 0.3 N m/A = 5 A -> 5 * 16384 / 20 = 4096 = 0x1000, int16 big-endian,
    # ESC 1 in bytes 0-1 of ID 0x200; ESC 6 in bytes 2-3 of ID 0x1FF; -4096 = 0xF000.
    assert DJI.torque_frames({1: 1.5, 6: -1.5}) == [
        Frame(0x200, bytes.fromhex('10 00 00 00 00 00 00 00')),
        Frame(0x1FF, bytes.fromhex('00 00 F0 00 00 00 00 00'))]
    # ESCs 2 and 4 on one frame; full scale +-6 N m = +-20 A = +-16384 = 0x4000 / 0xC000
    assert DJI.torque_frames({2: 100.0, 4: -6.0}) == [
        Frame(0x200, bytes.fromhex('00 00 40 00 00 00 C0 00'))]


def test_dji_feedback_vector():
    # ID 0x201: angle 0x1000 = 4096 (half a rotor turn), 0x03E8 = 1000 rpm,
    # 0xF800 = -2048 -> -2.5 A -> -0.75 N m, 0x28 = 40 deg C
    fb = DJI.decode_feedback(Frame(0x201, bytes.fromhex('10 00 03 E8 F8 00 28 00')))
    ratio = 3591.0 / 187.0
    assert fb.motor_id == 1
    assert fb.position == pytest.approx(math.pi / ratio)
    assert fb.velocity == pytest.approx(1000.0 * 2.0 * math.pi / 60.0 / ratio)
    assert fb.torque == pytest.approx(-0.75)
    assert fb.temperature == 40.0


@pytest.mark.parametrize('frame', [
    Frame(0x200, bytes(8)), Frame(0x1FF, bytes(8)), Frame(0x209, bytes(8)),  # not feedback
    Frame(0x201, bytes(7)),                                                  # short
    Frame(0x201, bytes(8), True),                                            # extended
    Frame(0x201, bytes.fromhex('20 00 00 00 00 00 00 00')),                  # angle 8192
    Frame(0, bytes.fromhex('01 75 C2 87 A8 E3')),                            # an MIT reply
])
def test_dji_decode_feedback_rejects_foreign_and_malformed_frames(frame):
    assert DJI.decode_feedback(frame) is None


@settings(max_examples=300, deadline=None)
@given(taus=st.dictionaries(st.integers(-3, 12), st.floats(), max_size=8))
def test_dji_torque_frames_never_raise_and_stay_in_range(taus):
    frames = DJI.torque_frames(taus)
    valid = {i: t for i, t in taus.items() if 1 <= i <= 8}
    assert len(frames) == (any(i <= 4 for i in valid) + any(i >= 5 for i in valid))
    codes = {}
    for frame in frames:
        assert frame.arbitration_id in (0x200, 0x1FF) and len(frame.data) == 8
        base = 1 if frame.arbitration_id == 0x200 else 5
        for k, code in enumerate(struct.unpack('>4h', frame.data)):
            assert -16384 <= code <= 16384
            codes[base + k] = code
    for i, tau in valid.items():
        if not math.isfinite(tau):
            assert codes[i] == 0
        else:
            wanted = max(-16384.0, min(16384.0, tau / 0.3 * 16384 / 20))  # [code]
            assert abs(codes[i] - wanted) <= 0.5 + 1e-9  # rounded to the nearest code


def test_dji_esc_side_against_the_vectors():
    # The ESC's side of the same layouts: a command decoded per ESC, feedback encoded.
    assert DJI.decode_command(Frame(0x200, bytes.fromhex('10 00 00 00 00 00 C0 00'))) == \
        {1: 4096, 2: 0, 3: 0, 4: -16384}
    assert DJI.decode_command(Frame(0x1FF, bytes.fromhex('00 00 F0 00 00 00 00 00'))) == \
        {5: 0, 6: -4096, 7: 0, 8: 0}
    for frame in (Frame(0x201, bytes(8)), Frame(0x200, bytes(7)), Frame(0x200, bytes(8), True)):
        assert DJI.decode_command(frame) is None
    assert DJI.encode_feedback(1, 4096, 1000, -2048, 40) == \
        Frame(0x201, bytes.fromhex('10 00 03 E8 F8 00 28 00'))
    # Fields out of their range: the angle wraps (one rotor turn), the others clamp.
    assert DJI.encode_feedback(2, 8192 + 5, 40000, -40000, 300) == \
        Frame(0x202, bytes.fromhex('00 05 7F FF 80 00 FF 00'))


def test_dji_enable_disable():
    assert DJI.enable_frames([1, 2]) == []
    assert DJI.disable_frames([1, 2]) == [Frame(0x200, bytes(8))]
    assert DJI.zero_torque_frames([7]) == [Frame(0x1FF, bytes(8))]


def test_dji_current_limit():
    limited = DjiC620Protocol(current_limit=10.0)
    assert struct.unpack('>4h', limited.torque_frames({1: 100.0})[0].data)[0] == 8192
    with pytest.raises(ValueError):
        DjiC620Protocol(current_limit=25.0)


# ---- factory and speed ---------------------------------------------------------------------

def test_make_protocol():
    assert isinstance(make_protocol('mit', t_min=-12.0, t_max=12.0), MitProtocol)
    assert isinstance(make_protocol('dji_c620'), DjiC620Protocol)
    with pytest.raises(ValueError):
        make_protocol('lk_tech')


@pytest.mark.parametrize('protocol', [MIT, DJI])
def test_per_tick_encode_and_decode_take_microseconds(protocol):
    torques = {1: 3.2, 2: -3.1}
    reply = MIT.encode_reply(1, 0.1, 2.0, 3.0) if protocol is MIT else \
        Frame(0x201, bytes.fromhex('10 00 03 E8 F8 00 28 00'))
    n = 2000
    best = math.inf
    for _ in range(5):  # best of five: the machine is shared
        start = time.perf_counter()
        for _ in range(n):
            protocol.torque_frames(torques)
            protocol.decode_feedback(reply)
        best = min(best, (time.perf_counter() - start) / n)
    # two motors' frames plus one decode; a few microseconds on a desktop CPU
    assert best < 30e-6
