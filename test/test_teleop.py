"""
core/teleop.py: teleop_twist_joy's mapping, deadzone, timeout, rate limits, height and arming.

The height target for cmd_height, and arming by button combinations with the deadman, beside
the mapping to cmd_vel.

Pure Python, no ROS: samples are (axes, buttons) lists and times are plain floats.
"""
from dataclasses import replace
import math

from hypothesis import given, settings, strategies as st
import pytest

from wheelleg_balance.core.rate_limiter import RateLimiter
from wheelleg_balance.core.teleop import (apply_deadzone, map_joy, MAX_TICK_DT, pad_combo, Teleop,
                                          TeleopConfig)

DT = 0.02   # 50 Hz, the node's default publish rate
# A small layout: enable button 0, turbo 1, x on axis 1, yaw on axis 3; no shaping unless asked.
CFG = TeleopConfig(enable_button=0, enable_turbo_button=1, require_enable_button=True,
                   axis_linear_x=1, scale_linear_x=0.5, scale_linear_turbo_x=1.0,
                   axis_angular_yaw=3, scale_angular_yaw=1.5, scale_angular_turbo_yaw=2.88,
                   inverted_reverse=False, deadzone=0.0, joy_timeout=0.5, max_linear_accel=0.0,
                   max_angular_accel=0.0, max_linear_jerk=0.0, max_angular_jerk=0.0,
                   height_buttons=[], heights=[], axis_height=-1, arm_buttons=[],
                   disarm_buttons=[])
ENABLE = [1, 0]
TURBO = [0, 1]
NONE = [0, 0]


def axes(x=0.0, yaw=0.0):
    return [0.0, x, 0.0, yaw]


def run(teleop, t0, t1, joy=None, dt=DT):
    """
    Tick from t0 (inclusive) to t1 (exclusive); return [(t, command or None)].

    joy = (axes, buttons) is fed before every tick, as a joystick driver's autorepeat would.
    """
    out = []
    n = int(round((t1 - t0) / dt))
    for k in range(n):
        t = t0 + k * dt
        if joy is not None:
            teleop.on_joy(joy[0], joy[1], t)
        out.append((t, teleop.tick(t)))
    return out


# --- mapping (teleop_twist_joy semantics) ---------------------------------------------------

def test_enable_button_scales_the_axes():
    assert map_joy(axes(1.0, 1.0), ENABLE, CFG) == (0.5, 1.5)
    x, yaw = map_joy(axes(-0.4, 0.2), ENABLE, CFG)
    assert x == pytest.approx(-0.2) and yaw == pytest.approx(0.3)


def test_turbo_button_uses_turbo_scales_even_without_enable():
    assert map_joy(axes(1.0, -1.0), TURBO, CFG) == (1.0, -2.88)
    assert map_joy(axes(1.0, -1.0), [1, 1], CFG) == (1.0, -2.88)


def test_no_button_means_disabled_unless_not_required():
    assert map_joy(axes(1.0, 1.0), NONE, CFG) is None
    free = replace(CFG, require_enable_button=False)
    assert map_joy(axes(1.0, 1.0), NONE, free) == (0.5, 1.5)
    # With no turbo button configured, a pressed button 1 means nothing.
    no_turbo = replace(CFG, enable_turbo_button=-1)
    assert map_joy(axes(1.0, 1.0), TURBO, no_turbo) is None


def test_inverted_reverse_turns_like_a_car_backwards():
    inv = replace(CFG, inverted_reverse=True)
    assert map_joy(axes(-1.0, 1.0), ENABLE, inv) == (-0.5, -1.5)
    assert map_joy(axes(1.0, 1.0), ENABLE, inv) == (0.5, 1.5)
    assert map_joy(axes(0.0, 1.0), ENABLE, inv) == (0.0, 1.5)
    assert map_joy(axes(-1.0, 1.0), ENABLE, CFG) == (-0.5, 1.5)


# --- single zero on release, timeout -------------------------------------------------------

def test_nothing_is_published_before_the_first_joy_sample():
    teleop = Teleop(CFG)
    assert all(cmd is None for _, cmd in run(teleop, 0.0, 1.0))


def test_exactly_one_zero_when_the_enable_button_is_released():
    teleop = Teleop(CFG)
    teleop.on_joy(axes(1.0, 0.5), ENABLE, 0.0)
    moving = run(teleop, 0.0, 0.2)
    assert all(cmd == (0.5, 0.75) for _, cmd in moving[1:])
    teleop.on_joy(axes(1.0, 0.5), NONE, 0.2)   # released with the stick still deflected
    released = [cmd for _, cmd in run(teleop, 0.2, 0.6)]
    assert released[0] == (0.0, 0.0)
    assert released[1:] == [None] * (len(released) - 1)
    # Pressed again: commands resume; released again: one more zero.
    teleop.on_joy(axes(1.0, 0.5), ENABLE, 0.6)
    assert teleop.tick(0.62) == (0.5, 0.75)
    teleop.on_joy(axes(0.0, 0.0), NONE, 0.64)
    assert [teleop.tick(0.64 + k * DT) for k in range(3)] == [(0.0, 0.0), None, None]


def test_first_sample_without_enable_sends_one_zero_like_teleop_twist_joy():
    teleop = Teleop(CFG)
    teleop.on_joy(axes(1.0, 1.0), NONE, 0.0)
    assert [cmd for _, cmd in run(teleop, 0.0, 0.1)] == [(0.0, 0.0)] + [None] * 4


def test_silent_joystick_times_out_with_one_zero():
    cfg = replace(CFG, joy_timeout=0.3)
    teleop = Teleop(cfg)
    teleop.on_joy(axes(1.0, 0.0), ENABLE, 0.0)   # the last sample before the link drops
    out = run(teleop, 0.0, 1.0)
    moving = [t for t, cmd in out if cmd is not None and cmd != (0.0, 0.0)]
    zeros = [t for t, cmd in out if cmd == (0.0, 0.0)]
    assert max(moving) <= 0.3 + 1e-9
    assert len(zeros) == 1 and 0.3 < zeros[0] <= 0.3 + DT + 1e-9
    assert teleop.timed_out
    # A fresh sample brings motion back.
    teleop.on_joy(axes(1.0, 0.0), ENABLE, 1.0)
    assert teleop.tick(1.0) == (0.5, 0.0) and not teleop.timed_out


def test_stop_sends_the_zero_only_while_moving():
    teleop = Teleop(CFG)
    teleop.on_joy(axes(1.0, 0.0), ENABLE, 0.0)
    teleop.tick(0.0)
    assert teleop.stop() == (0.0, 0.0)
    assert teleop.stop() is None


# --- deadzone ------------------------------------------------------------------------------

@pytest.mark.parametrize('dz', [0.05, 0.1, 0.3])
def test_deadzone_is_continuous_and_reaches_full_scale(dz):
    assert apply_deadzone(dz, dz) == 0.0 and apply_deadzone(-dz, dz) == 0.0
    assert apply_deadzone(1.0, dz) == 1.0 and apply_deadzone(-1.0, dz) == -1.0
    # Lipschitz with 1 / (1 - dz) across the edge: no step of size dz as a plain cut-off has.
    grid = [i / 2000.0 - 1.0 for i in range(4001)]
    out = [apply_deadzone(v, dz) for v in grid]
    steps = [abs(b - a) for a, b in zip(out, out[1:])]
    assert max(steps) <= (1.0 / 2000.0) / (1.0 - dz) + 1e-12
    assert all(b >= a for a, b in zip(out, out[1:]))
    just_out = dz + 1e-3
    assert apply_deadzone(just_out, dz) == pytest.approx(1e-3 / (1.0 - dz))


def test_deadzone_applies_to_both_axes_of_the_mapping():
    cfg = replace(CFG, deadzone=0.2)
    assert map_joy(axes(0.19, -0.19), ENABLE, cfg) == (0.0, 0.0)
    x, yaw = map_joy(axes(0.6, -0.6), ENABLE, cfg)
    assert x == pytest.approx(0.5 * 0.5) and yaw == pytest.approx(-1.5 * 0.5)


# --- rate limits ---------------------------------------------------------------------------

def test_acceleration_limits_turn_a_step_into_a_ramp_of_that_slope():
    cfg = replace(CFG, max_linear_accel=1.0, max_angular_accel=6.0)
    teleop = Teleop(cfg)
    out = run(teleop, 0.0, 2.0, (axes(1.0, 1.0), TURBO))   # step to 1.0 m/s and 2.88 rad/s
    ts = [t for t, _ in out]
    xs = [cmd[0] for _, cmd in out]
    ws = [cmd[1] for _, cmd in out]
    # Each tick adds exactly accel * dt until the target, which is then held exactly.
    for t, x, w in zip(ts, xs, ws):
        assert x == pytest.approx(min(1.0 * t, 1.0), abs=1e-9)
        assert w == pytest.approx(min(6.0 * t, 2.88), abs=1e-9)
    slope = (xs[25] - xs[5]) / (ts[25] - ts[5])
    assert slope == pytest.approx(1.0, rel=1e-9)
    assert xs[-1] == 1.0 and ws[-1] == 2.88


def test_ramp_also_limits_a_reversal():
    cfg = replace(CFG, max_linear_accel=2.0)
    teleop = Teleop(cfg)
    run(teleop, 0.0, 1.0, (axes(1.0, 0.0), TURBO))          # at +1 m/s
    xs = [cmd[0] for _, cmd in run(teleop, 1.0, 2.5, (axes(-1.0, 0.0), TURBO))]
    assert max(abs(b - a) for a, b in zip(xs, xs[1:])) <= 2.0 * DT + 1e-12
    assert xs[-1] == -1.0


@pytest.mark.parametrize('a_max,j_max', [(1.0, 5.0), (1.0, 20.0), (6.0, 40.0)])
def test_jerk_limit_rounds_the_ramp_without_overshoot(a_max, j_max):
    lim = RateLimiter(a_max, j_max)
    target = 1.0
    v = [0.0] + [lim.step(target, DT) for _ in range(int(4.0 / DT))]
    a = [(y - x) / DT for x, y in zip(v, v[1:])]
    j = [(y - x) / DT for x, y in zip(a, a[1:])]
    assert max(abs(x) for x in a) <= a_max + 1e-9
    assert max(abs(x) for x in j) <= j_max + 1e-6
    assert max(v) <= target + j_max * DT ** 2
    # Settles on the target in about the time-optimal v / a + a / j (plus a few ticks).
    t_settle = next(k * DT for k, x in enumerate(v) if abs(x - target) < 1e-6)
    t_opt = target / a_max + a_max / j_max if a_max ** 2 / j_max < target else \
        2.0 * math.sqrt(target / j_max)
    assert t_opt - DT <= t_settle <= t_opt + 4 * DT
    assert v[-1] == pytest.approx(target, abs=1e-9)


def test_a_stall_never_makes_the_reference_jump():
    cfg = replace(CFG, max_linear_accel=1.0)
    teleop = Teleop(cfg)
    teleop.on_joy(axes(1.0, 0.0), TURBO, 0.0)
    teleop.tick(0.0)
    teleop.on_joy(axes(1.0, 0.0), TURBO, 0.4)
    x, _ = teleop.tick(0.45)                    # 0.45 s since the last tick
    assert x == pytest.approx(1.0 * MAX_TICK_DT)


def test_release_rests_the_limiter_so_the_next_press_ramps_from_zero():
    cfg = replace(CFG, max_linear_accel=1.0)
    teleop = Teleop(cfg)
    run(teleop, 0.0, 1.5, (axes(1.0, 0.0), TURBO))         # at 1 m/s
    released = [cmd for _, cmd in run(teleop, 1.5, 1.6, (axes(1.0, 0.0), NONE))]
    assert released == [(0.0, 0.0)] + [None] * 4
    xs = [cmd[0] for _, cmd in run(teleop, 1.6, 1.7, (axes(1.0, 0.0), TURBO))]
    assert xs == pytest.approx([1.0 * DT * k for k in range(1, 6)])


# --- malformed input -----------------------------------------------------------------------

@pytest.mark.parametrize('ax,bt,expected', [
    ([], [], None),                                    # no buttons: not enabled
    ([0.0, 1.0], [1], (0.5, 0.0)),                     # yaw axis missing -> 0
    ([0.0, math.nan, 0.0, math.inf], [1], (0.0, 0.0)),
    ([0.0, -math.inf, 0.0, 1.0], [1], (0.0, 1.5)),
    ([0.0, 7.0, 0.0, -3.0], [1], (0.5, -1.5)),         # out of [-1, 1]: clamped
    ([0.0, 1.0, 0.0, 1.0], [math.nan, math.nan], None),
    ([0.0, 1.0, 0.0, 1.0], [math.inf], None),
    ([0.0, 'x', None, 1.0], [True], (0.0, 1.5)),
    (None, None, None),
    ([0.0, 1.0, 0.0, 1.0], 5, None),
])
def test_malformed_samples_read_as_zero_and_not_pressed(ax, bt, expected):
    assert map_joy(ax, bt, CFG) == expected
    teleop = Teleop(CFG)
    teleop.on_joy(ax, bt, 0.0)
    assert teleop.tick(0.0) == (expected or (0.0, 0.0))


def test_unused_axes_and_buttons_never_index_from_the_end():
    cfg = replace(CFG, axis_linear_x=-1, axis_angular_yaw=-1, enable_button=-1,
                  enable_turbo_button=-1, require_enable_button=False)
    assert map_joy([1.0, 1.0], [1, 1], cfg) == (0.0, 0.0)
    cfg = replace(CFG, enable_button=-1, enable_turbo_button=1)
    assert map_joy(axes(1.0, 1.0), [1, 0], cfg) is None


# --- configuration checks ------------------------------------------------------------------

def test_default_configuration_is_valid():
    assert TeleopConfig().problems() == []
    assert CFG.problems() == []


@pytest.mark.parametrize('change,word', [
    ({'deadzone': 1.0}, 'deadzone'),
    ({'deadzone': -0.1}, 'deadzone'),
    ({'joy_timeout': 0.0}, 'joy_timeout'),
    ({'max_linear_accel': -1.0}, 'max_linear_accel'),
    ({'max_angular_jerk': math.inf}, 'max_angular_jerk'),
    ({'scale_linear_x': math.nan}, 'scale_linear_x'),
    ({'enable_turbo_button': 0}, 'turbo'),
    ({'enable_button': -2}, 'enable_button'),
    ({'enable_button': -1, 'enable_turbo_button': -1}, 'never'),
    ({'inverted_reverse': 1}, 'inverted_reverse'),
    ({'height_buttons': [3]}, 'one entry each'),
    ({'height_buttons': [3], 'heights': [0.9]}, 'outside'),
    ({'height_min': 0.7, 'height_max': 0.5}, 'below'),
    ({'height_buttons': [0], 'heights': [0.5]}, 'share'),          # the enable button
    ({'height_buttons': [3, 3], 'heights': [0.5, 0.6]}, 'twice'),
    ({'arm_buttons': [4], 'disarm_buttons': [4]}, 'share'),
    ({'arm_buttons': [1]}, 'share'),                               # the turbo button
    ({'arm_buttons': [4], 'enable_button': -1}, 'deadman'),
    ({'axis_height': 3}, 'driving axis'),                          # the yaw axis
])
def test_bad_configuration_is_reported_with_a_reason(change, word):
    problems = replace(CFG, **change).problems()
    assert problems and any(word in p for p in problems), problems


# --- fuzz ----------------------------------------------------------------------------------

_value = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-3, 3),
                   st.none(), st.text(max_size=2))
_sample = st.tuples(st.lists(_value, max_size=8), st.lists(_value, max_size=12))
_scale = st.floats(-5.0, 5.0)


@settings(max_examples=150, deadline=None)
@given(samples=st.lists(_sample, min_size=1, max_size=12),
       idx=st.tuples(*[st.integers(-1, 10)] * 4),
       scales=st.tuples(_scale, _scale, _scale, _scale),
       deadzone=st.floats(0.0, 0.9), inv=st.booleans(), require=st.booleans(),
       limits=st.tuples(*[st.sampled_from([0.0, 0.5, 3.0, 50.0])] * 4),
       dts=st.lists(st.floats(0.0, 0.3), min_size=1, max_size=12))
def test_fuzz_outputs_are_finite_and_within_the_scales(samples, idx, scales, deadzone, inv,
                                                       require, limits, dts):
    enable, turbo, ax_x, ax_w = idx
    if turbo == enable:
        turbo = -1
    cfg = TeleopConfig(enable_button=enable, enable_turbo_button=turbo,
                       require_enable_button=require, axis_linear_x=ax_x,
                       scale_linear_x=scales[0], scale_linear_turbo_x=scales[1],
                       axis_angular_yaw=ax_w, scale_angular_yaw=scales[2],
                       scale_angular_turbo_yaw=scales[3], inverted_reverse=inv,
                       deadzone=deadzone, joy_timeout=0.2, max_linear_accel=limits[0],
                       max_angular_accel=limits[1], max_linear_jerk=limits[2],
                       max_angular_jerk=limits[3])
    x_bound = max(abs(scales[0]), abs(scales[1])) + 1e-9
    w_bound = max(abs(scales[2]), abs(scales[3])) + 1e-9
    teleop = Teleop(cfg)
    t = 0.0
    for k, (ax, bt) in enumerate(samples):
        teleop.on_joy(ax, bt, t)
        for dt in dts:
            t += dt
            cmd = teleop.tick(t)
            if cmd is not None:
                x, w = cmd
                assert math.isfinite(x) and math.isfinite(w)
                assert abs(x) <= x_bound and abs(w) <= w_bound


# --- height target and arming from the pad -------------------------------------------------

# Enable 0, turbo 1; height buttons 2 (0.70 m) and 3 (0.52 m), height axis 2; arm 4, disarm 5.
PAD = replace(CFG, height_buttons=[2, 3], heights=[0.70, 0.52], axis_height=2,
              scale_height=0.1, height_min=0.37, height_max=0.70, arm_buttons=[4],
              disarm_buttons=[5], arm_hold_time=0.5)


def pad(*held, height_axis=0.0):
    """Return a PAD sample with the given buttons held."""
    buttons = [0] * 6
    for b in held:
        buttons[b] = 1
    return [0.0, 0.0, height_axis, 0.0], buttons


def drive(teleop, t0, t1, sample, dt=DT):
    """Feed ``sample`` and tick from t0 to t1; return [(t, height sent, arm request)]."""
    out = []
    for k in range(int(round((t1 - t0) / dt))):
        t = t0 + k * dt
        teleop.on_joy(*sample, t)
        teleop.tick(t)
        out.append((t, teleop.take_height(), teleop.take_arm()))
    return out


def sent(rows, k):
    """Return the times and values sent in the rows: k = 1 the heights, k = 2 arm requests."""
    return [(row[0], row[k]) for row in rows if row[k] is not None]


def test_the_height_starts_at_the_minimum_and_is_sent_only_when_it_changes():
    teleop = Teleop(PAD)
    assert teleop.height == 0.37
    assert sent(drive(teleop, 0.0, 1.0, pad(0)), 1) == []    # enabled, nothing pressed


def test_a_height_button_press_sets_its_height_once_with_the_deadman_held():
    teleop = Teleop(PAD)
    rows = drive(teleop, 0.0, 0.2, pad(0)) + drive(teleop, 0.2, 1.0, pad(0, 2))
    assert sent(rows, 1) == [(pytest.approx(0.2), 0.70)]      # a step: balance_node shapes it
    rows = drive(teleop, 1.0, 1.2, pad(0)) + drive(teleop, 1.2, 1.4, pad(0, 3))
    assert sent(rows, 1) == [(pytest.approx(1.2), 0.52)]
    # Without the deadman a press does nothing, and holding it on while the deadman comes
    # is no press either.
    rows = drive(teleop, 1.4, 1.6, pad()) + drive(teleop, 1.6, 2.0, pad(2)) + \
        drive(teleop, 2.0, 2.4, pad(0, 2))
    assert sent(rows, 1) == [] and teleop.height == 0.52
    # Turbo enables motion too, and with it the height buttons.
    rows = drive(teleop, 2.4, 2.6, pad(1)) + drive(teleop, 2.6, 2.8, pad(1, 2))
    assert sent(rows, 1) == [(pytest.approx(2.6), 0.70)]


def test_the_height_axis_moves_the_target_at_its_rate_within_the_range():
    teleop = Teleop(PAD)
    rows = drive(teleop, 0.0, 1.0, pad(0, height_axis=1.0))
    heights = [h for _, h in sent(rows, 1)]
    assert heights == sorted(heights) and len(heights) == 49  # every tick but the first
    assert heights[-1] == pytest.approx(0.37 + 0.1 * 0.98, abs=1e-9)
    drive(teleop, 1.0, 5.0, pad(0, height_axis=1.0))
    assert teleop.height == 0.70                               # clamped at height_max
    drive(teleop, 5.0, 6.0, pad(0, height_axis=-0.5))          # half deflection down
    assert teleop.height == pytest.approx(0.70 - 0.05, abs=0.002)
    drive(teleop, 6.0, 7.0, pad(height_axis=-1.0))             # no deadman: stays
    assert teleop.height == pytest.approx(0.65, abs=0.002)
    # A silent joystick stops the motion at once.
    teleop.on_joy(*pad(0, height_axis=1.0), 7.0)
    for k in range(100):
        teleop.tick(7.0 + 0.02 * k)
    assert teleop.height == pytest.approx(0.65 + 0.1 * PAD.joy_timeout, abs=0.003)


def test_the_arm_combination_with_the_deadman_asks_once_after_the_hold_time():
    teleop = Teleop(PAD)
    rows = drive(teleop, 0.0, 2.0, pad(0, 4))
    assert sent(rows, 2) == [(pytest.approx(0.5), True)]      # once, after 0.5 s
    rows = drive(teleop, 2.0, 2.2, pad(0)) + drive(teleop, 2.2, 3.0, pad(0, 5))
    assert sent(rows, 2) == [(pytest.approx(2.7), False)]     # released, then disarm
    # Too short, without the deadman, or both combinations at once: nothing.
    rows = drive(teleop, 3.0, 3.4, pad(0, 4)) + drive(teleop, 3.4, 3.6, pad(0)) + \
        drive(teleop, 3.6, 5.0, pad(4)) + drive(teleop, 5.0, 6.0, pad(0, 4, 5))
    assert sent(rows, 2) == []
    # A joystick that falls silent (joy_timeout 0.5 s) while the combination is held for its
    # 1 s cancels it.
    teleop = Teleop(replace(PAD, arm_hold_time=1.0))
    teleop.on_joy(*pad(0, 4), 6.0)
    for k in range(100):
        teleop.tick(6.0 + 0.02 * k)
    assert teleop.take_arm() is None


def test_pad_combo_needs_every_button_of_a_combination():
    cfg = replace(PAD, arm_buttons=[4, 5], disarm_buttons=[3])
    assert pad_combo(pad(0, 4, 5)[1], cfg) is True
    assert pad_combo(pad(0, 4)[1], cfg) is None
    assert pad_combo(pad(0, 3)[1], cfg) is False
    assert pad_combo(pad(4, 5)[1], cfg) is None                # no deadman
    assert pad_combo(pad(0)[1], replace(cfg, arm_buttons=[], disarm_buttons=[])) is None
    assert pad_combo([1, 0, 0, float('nan'), 1, 1], cfg) is True   # NaN: not pressed


@settings(max_examples=100, deadline=None)
@given(samples=st.lists(_sample, min_size=1, max_size=12),
       dts=st.lists(st.floats(0.0, 0.3), min_size=1, max_size=8))
def test_fuzz_the_height_stays_in_range_and_requests_are_booleans(samples, dts):
    teleop = Teleop(PAD)
    t = 0.0
    for ax, bt in samples:
        teleop.on_joy(ax, bt, t)
        for dt in dts:
            t += dt
            teleop.tick(t)
            h = teleop.take_height()
            assert h is None or 0.37 <= h <= 0.70
            assert teleop.take_arm() in (None, True, False)
