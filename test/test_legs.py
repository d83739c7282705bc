"""
The legs' pure pieces (core/legs.py).

Height shaper, roll levelling, hip commands and state, damping, homing. Closed loops in MuJoCo:
test/test_legs_closed_loop.py.
"""
import math

from hypothesis import given, settings, strategies as st
import numpy as np
import pytest

from wheelleg_balance.core.homing import HipHoming, HomingConfig
from wheelleg_balance.core.kinematics import FiveBarLeg
from wheelleg_balance.core.legs import (
    HeightShaper, HipMotors, LEFT_LEG, LegController, LegGains, RIGHT_LEG, RollLeveller,
    split_heights)
from wheelleg_balance.core.protocols.mit import MitProtocol
from wheelleg_balance.sim.motor_emulator import MitMotorEmulator

LEG = FiveBarLeg()
MIT = MitProtocol()
MOTORS = HipMotors(motor_ids=(11, 12, 13, 14), directions=(1, -1, -1, 1),
                   offsets=(0.3, -0.2, 1.1, 0.05))
DT = 0.002


def _replies(motors, q, q_dot=(0.0,) * 4, tau=(0.0,) * 4):
    """Return the replies (motor frame) of hips at joint angles q."""
    return [(motors.motor_position(i, q[i]), motors.directions[i] * q_dot[i],
             motors.directions[i] * tau[i]) for i in range(4)]


# ---- HeightShaper --------------------------------------------------------------------------

def _profile(shaper, seconds):
    out = [shaper.step(DT) for _ in range(int(round(seconds / DT)))]
    return np.array(out)


def test_height_shaper_limits_rate_and_acceleration_and_arrives_without_overshoot():
    shaper = HeightShaper(0.37, 0.70, max_rate=0.1, max_accel=0.2)
    shaper.reset(0.37)
    assert shaper.command(0.70)
    prof = _profile(shaper, 6.0)
    l, l_dot = prof[:, 0], prof[:, 1]
    assert np.abs(l_dot).max() <= 0.1 + 1e-12
    assert np.abs(np.diff(l_dot)).max() <= 0.2 * DT + 1e-12
    assert l.max() <= 0.70 + 1e-12 and l[-1] == 0.70 and l_dot[-1] == 0.0
    # 0.33 m at 0.1 m/s with 0.5 s ramps at each end: 3.8 s.
    arrival = DT * (1 + np.argmax(l >= 0.70))
    assert arrival == pytest.approx(0.33 / 0.1 + 0.1 / 0.2, abs=0.05)
    # And back down the same way, mid-way reversals included.
    shaper.command(0.37)
    prof = _profile(shaper, 1.0)
    shaper.command(0.60)
    prof = np.vstack([prof, _profile(shaper, 5.0)])
    assert np.abs(np.diff(prof[:, 1])).max() <= 0.2 * DT + 1e-12
    assert prof[-1, 0] == 0.60


def test_height_shaper_clamps_and_refuses_bad_commands():
    shaper = HeightShaper(0.37, 0.70)
    shaper.reset(0.5)
    assert shaper.command(0.9) and shaper.target == 0.70 and shaper.clamped
    assert shaper.command(0.1) and shaper.target == 0.37
    for bad in (math.nan, math.inf, -math.inf, None, 'high'):
        assert not shaper.command(bad)
    assert shaper.target == 0.37 and shaper.refused == 5
    assert shaper.step(math.nan) == (0.5, 0.0)       # a bad dt changes nothing
    with pytest.raises(ValueError):
        HeightShaper(0.7, 0.37)


# ---- roll levelling ------------------------------------------------------------------------

def test_leveller_sign_saturation_and_anti_windup():
    lev = RollLeveller(kp=0.5, ki=2.0, kd=0.1, max_dl=0.05)
    assert lev.update(0.02, 0.0, DT) < 0.0       # left up -> shorten the left leg
    lev.reset()
    for _ in range(2000):                        # a large roll for 4 s: saturated
        dl = lev.update(0.3, 0.0, DT)
    assert dl == -0.05
    assert abs(lev.integral) < 0.05 / 2.0 + 0.3 * DT * 2     # stopped at the limit
    # Roll reversed: the output leaves the limit at once instead of unwinding for seconds.
    assert lev.update(-0.02, 0.0, DT) > -0.05
    assert lev.update(math.nan, 0.0, DT) == lev.dl


def test_leveller_levels_a_body_on_a_slope():
    """Level a model body: roll = slope roll + dl / d_w, the legs lagging by 0.1 s."""
    d_w, ground = 0.47, math.radians(7.0)
    lev = RollLeveller(kp=0.5, ki=2.0)
    dl_actual = 0.0
    rolls = []
    for _ in range(2500):
        roll = math.atan(math.tan(ground) + dl_actual / d_w)
        dl = lev.update(roll, 0.0, DT)
        dl_actual += (dl - dl_actual) * DT / 0.1
        rolls.append(roll)
    assert abs(rolls[-1]) < math.radians(0.05)
    assert dl_actual == pytest.approx(-d_w * math.tan(ground), abs=1e-3)   # 5.8 cm


@pytest.mark.parametrize('l, dl, expected', [
    (0.5, 0.0, (0.5, 0.5)), (0.5, 0.06, (0.53, 0.47)), (0.37, -0.06, (0.37, 0.43)),
    (0.70, 0.06, (0.70, 0.64)), (0.5, 1.0, (0.70, 0.37)), (0.1, 0.0, (0.37, 0.37))])
def test_split_heights_keeps_both_legs_in_range(l, dl, expected):
    assert split_heights(l, dl, 0.37, 0.70) == pytest.approx(expected)


# ---- commands and state --------------------------------------------------------------------

def test_hip_motors_map_joint_angles_both_ways_and_check_their_fields():
    for i in range(4):
        assert MOTORS.joint_angle(i, MOTORS.motor_position(i, 0.77)) == pytest.approx(0.77)
    with pytest.raises(ValueError):
        HipMotors(directions=(1, 1, 0, 1))
    with pytest.raises(ValueError):
        HipMotors(motor_ids=(1, 1, 2, 3))


@settings(max_examples=60, deadline=None)
@given(l_left=st.floats(0.37, 0.70), l_right=st.floats(0.37, 0.70),
       v_left=st.floats(-0.3, 0.3), v_right=st.floats(-0.3, 0.3),
       pitch=st.floats(-0.3, 0.3))
def test_commands_follow_the_kinematics_in_each_motors_frame(l_left, l_right, v_left,
                                                             v_right, pitch):
    ctl = LegController(LEG, MOTORS, LegGains(kp=50.0, kd=2.0), weight_share=54.0)
    cmds = ctl.commands(l_left, l_right, v_left, v_right, pitch)
    assert [c.motor_id for c in cmds] == list(MOTORS.motor_ids)
    for side, l, v in ((0, l_left, v_left), (2, l_right, v_right)):
        q = [MOTORS.joint_angle(side + k, cmds[side + k].position) for k in (0, 1)]
        assert q == pytest.approx(LEG.inverse(l), abs=1e-12)
        q_dot = [MOTORS.directions[side + k] * cmds[side + k].velocity for k in (0, 1)]
        assert LEG.height_rate(*q, *q_dot) == pytest.approx(v, abs=1e-9)
        tau = [MOTORS.directions[side + k] * cmds[side + k].torque for k in (0, 1)]
        assert tau == pytest.approx(LEG.static_torques(*q, 54.0 * math.cos(pitch),
                                                       54.0 * math.sin(pitch)), abs=1e-9)
        assert all(c.kp == 50.0 and c.kd == 2.0 for c in cmds)


def test_commands_of_one_leg_are_that_legs_half_of_both():
    """legs= picks the legs (the tick commands them in turns: legs.command_divider)."""
    ctl = LegController(LEG, MOTORS, weight_share=54.0)
    both = ctl.commands(0.45, 0.60, 0.1, -0.1, pitch=0.05)
    left = ctl.commands(0.45, 0.60, 0.1, -0.1, pitch=0.05, legs=(LEFT_LEG,))
    right = ctl.commands(0.45, 0.60, 0.1, -0.1, pitch=0.05, legs=(RIGHT_LEG,))
    assert left == both[:2] and right == both[2:]
    assert [c.motor_id for c in right] == list(MOTORS.motor_ids[2:])
    assert ctl.commands(0.45, 0.60, legs=()) == []
    # A leg with a bad height goes to damping alone, whichever legs are asked for.
    damped = ctl.commands(math.nan, 0.60, legs=(LEFT_LEG,))
    assert [c.kp for c in damped] == [0.0, 0.0] and [c.motor_id for c in damped] == [11, 12]


def test_commands_drive_motors_to_the_height():
    """Emulated motors at the commanded pose apply exactly the feed-forward torque."""
    ctl = LegController(LEG, MOTORS, weight_share=54.0)
    cmds = ctl.commands(0.52, 0.52)
    q = LEG.inverse(0.52)
    for i, c in enumerate(cmds):
        motor = MitMotorEmulator(c.motor_id, direction=MOTORS.directions[i])
        motor.zero = MOTORS.directions[i] * MOTORS.offsets[i]    # q = d p + offset
        motor.handle(MIT.enable_frames([c.motor_id])[0], 0.0, 0.0, 0.0)
        motor.handle(MIT.command_frame(*c), q[i % 2], 0.0, 0.0)
        expected = LEG.static_torques(*q, 54.0)[i % 2]
        # Truncation of the command's codes: p (0.38 mrad x kp 60 = 23 mN m), v (v = 0 arrives
        # as -12.2 mrad/s, x kd 3 = 37 mN m) and the torque (8.8 mN m).
        assert motor.torque(q[i % 2], 0.0, 0.0) == pytest.approx(expected, abs=0.07)


def test_state_from_replies_gives_heights_rates_and_knees():
    ctl = LegController(LEG, MOTORS)
    q_l, q_r = LEG.inverse(0.45), LEG.inverse(0.60)
    q = q_l + q_r
    rates = LEG.hip_rates(*q_l, 0.1) + LEG.hip_rates(*q_r, -0.1)
    s = ctl.state(_replies(MOTORS, q, rates))
    assert s.valid and not s.problems
    assert s.q == pytest.approx(q) and s.heights == pytest.approx((0.45, 0.60))
    assert s.l == pytest.approx(0.525) and s.l_dot == pytest.approx(0.0, abs=1e-12)
    assert s.knees == pytest.approx(LEG.knee_angles(*q_l) + LEG.knee_angles(*q_r))


def test_state_refuses_missing_and_out_of_reach_replies_without_raising():
    ctl = LegController(LEG, MOTORS)
    q = LEG.inverse(0.5) * 2
    replies = _replies(MOTORS, q)
    replies[2] = None
    s = ctl.state(replies)
    assert not s.valid and math.isnan(s.l) and 'no reply from hip right_front' in s.problems
    replies = _replies(MOTORS, (2.5, 0.5) + q[2:])         # left front beyond its limit
    s = ctl.state(replies)
    assert not s.valid and any('left leg out of reach' in p for p in s.problems)
    assert s.heights[1] == pytest.approx(0.5)
    assert ctl.arm_refusal(s) == 'legs not homed'


def test_state_is_the_same_kept_or_computed_afresh():
    # One controller reads a sequence of replies in which one leg at a time changes (the legs
    # commanded in turns), goes missing and comes back, and new offsets arrive; each state
    # equals what a controller that never saw the earlier replies computes.
    ctl = LegController(LEG, MOTORS)
    rng = np.random.default_rng(3)
    replies = _replies(MOTORS, LEG.inverse(0.5) * 2)
    for k in range(60):
        side = 2 * (k % 2)
        if k % 7 == 3:
            replies[side] = None
        else:
            q = LEG.inverse(rng.uniform(0.38, 0.68))
            rates = LEG.hip_rates(*q, rng.uniform(-0.1, 0.1))
            new = _replies(ctl.motors, q * 2, rates * 2)
            replies[side:side + 2] = new[side:side + 2]
        if k == 40:
            ctl.set_offsets((0.1, 0.2, 0.3, 0.4))   # homing: the same replies, new angles
        fresh = LegController(LEG, ctl.motors)
        got, want = ctl.state(replies), fresh.state(replies)
        assert got.problems == want.problems and got.valid == want.valid
        for a, b in zip(got[:6], want[:6]):
            assert np.array_equal(np.asarray(a, dtype=float), np.asarray(b, dtype=float),
                                  equal_nan=True)


@settings(max_examples=100, deadline=None)
@given(st.floats(0.3, 0.75), st.floats(0.3, 0.75),
       st.lists(st.floats(-30.0, 30.0), min_size=4, max_size=4), st.booleans())
def test_load_is_the_mean_leg_force_at_the_state(l_left, l_right, tau, torque_only_changed):
    # The legs' load from the Jacobians the state kept, as leg_force at the state's angles;
    # also when a reply's torque alone changed (the state the same, the load not).
    ctl = LegController(LEG, MOTORS)
    q = LEG.inverse(l_left) + LEG.inverse(l_right)
    replies = _replies(MOTORS, q)
    ctl.state(replies)
    if torque_only_changed:
        replies = [(p, v, t + 1.0) for p, v, t in replies]
    s = ctl.state(replies)
    joint_tau = [d * t for d, t in zip(MOTORS.directions, tau)]
    want = 0.5 * (LEG.leg_force(*s.q[:2], *joint_tau[:2])[1]
                  + LEG.leg_force(*s.q[2:], *joint_tau[2:])[1])
    assert np.array_equal(ctl.load(tau), want, equal_nan=True)
    assert math.isnan(LegController(LEG, MOTORS).load(tau))   # no state yet
    replies[1] = None
    ctl.state(replies)
    assert math.isnan(ctl.load(tau))   # an invalid state


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(st.none(), st.tuples(st.floats(allow_nan=True, allow_infinity=True),
                                               st.floats(allow_nan=True, allow_infinity=True),
                                               st.floats(allow_nan=True, allow_infinity=True))),
                min_size=0, max_size=5))
def test_state_never_raises_and_commands_stay_finite(replies):
    ctl = LegController(LEG, MOTORS)
    s = ctl.state(replies)
    assert s.valid == (not s.problems)
    for c in ctl.damping_commands(s) + ctl.commands(s.l, s.l, s.l_dot, s.l_dot):
        assert all(math.isfinite(v) for v in c[1:])


def test_damping_mode_has_no_stiffness_and_keeps_part_of_the_weight():
    ctl = LegController(LEG, MOTORS, LegGains(damping_kd=4.0, damping_gravity=0.5), 54.0)
    q = LEG.inverse(0.6) * 2
    s = ctl.state(_replies(MOTORS, q))
    cmds = ctl.damping_commands(s)
    assert all(c.kp == 0.0 and c.kd == 4.0 and c.velocity == 0.0 for c in cmds)
    tau = [MOTORS.directions[i] * c.torque for i, c in enumerate(cmds)]
    assert tau == pytest.approx(list(LEG.static_torques(*q[:2], 27.0)) * 2)
    # Without a valid state: pure damping.
    assert all(c.torque == 0.0 for c in ctl.damping_commands(None))


def test_arming_is_refused_until_homed_from_a_known_pose():
    ctl = LegController(LEG, HipMotors(motor_ids=(11, 12, 13, 14)))
    true = MOTORS        # the real offsets, unknown to the controller
    q = LEG.inverse(0.37) * 2
    replies = _replies(true, q)
    assert ctl.arm_refusal(ctl.state(replies)) == 'legs not homed'
    assert not ctl.home_known_pose(replies[:3] + [None], q)
    assert ctl.home_known_pose(_replies(true, q), q)      # e.g. in a jig at l = 0.37 m
    # The directions are the controller's (here +1): use the true ones for the check.
    ctl = LegController(LEG, HipMotors((11, 12, 13, 14), true.directions))
    assert ctl.home_known_pose(replies, q)
    s = ctl.state(_replies(true, LEG.inverse(0.6) * 2))
    assert s.valid and s.l == pytest.approx(0.6) and ctl.arm_refusal(s) is None


# ---- homing --------------------------------------------------------------------------------

class HipRig:
    """Four 1-DoF hips (inertia, gravity torque, a stiff hard stop) behind emulated motors."""

    def __init__(self, motors, stop, gravity, q0, inertia=0.02, seed=1):
        self.motors = motors
        self.stop, self.gravity, self.inertia = stop, gravity, inertia
        self.q = list(q0)
        self.q_dot = [0.0] * 4
        rng = np.random.default_rng(seed)
        self.emulators = []
        for i in range(4):
            e = MitMotorEmulator(motors.motor_ids[i], direction=motors.directions[i])
            e.zero = motors.directions[i] * motors.offsets[i]
            e.zero += rng.uniform(-3.0, 3.0)          # an old zero, far off
            e.reboot(self.q[i])                       # known only modulo 40 deg now
            e.handle(MIT.enable_frames([e.motor_id])[0], self.q[i], 0.0, 0.0)
            self.emulators.append(e)

    def true_offset(self, i):
        """Return the offset that maps this motor's reading to the joint (q = d p + offset)."""
        return self.q[i] - self.motors.directions[i] * self.emulators[i].position(self.q[i])

    def exchange(self, cmds, now):
        replies = []
        for i, c in enumerate(cmds):
            fb = MIT.decode_feedback(self.emulators[i].handle(MIT.command_frame(*c), self.q[i],
                                                              self.q_dot[i], now))
            replies.append((fb.position, fb.velocity, fb.torque))
        return replies

    def advance(self, now, dt=0.0005, n=4):
        for _ in range(n):
            for i, e in enumerate(self.emulators):
                tau = e.torque(self.q[i], self.q_dot[i], now) + self.gravity
                if self.q[i] < self.stop:            # a stiff, damped stop
                    tau += 5000.0 * (self.stop - self.q[i]) - 20.0 * self.q_dot[i]
                self.q_dot[i] += tau / self.inertia * dt
                self.q[i] += self.q_dot[i] * dt


@pytest.mark.parametrize('gravity', [0.0, -8.0])   # unloaded, and the weight pulling down
def test_homing_finds_the_offsets_at_the_hard_stops(gravity):
    rig = HipRig(MOTORS, stop=-0.2, gravity=gravity, q0=(0.25, 0.3, 0.2, 0.4))
    homing = HipHoming(HipMotors(MOTORS.motor_ids, MOTORS.directions), HomingConfig())
    replies = [None] * 4
    t = 0.0
    peak_speed = 0.0
    while homing.status == 'running' and t < 30.0:
        cmds = homing.step(replies, t)
        replies = rig.exchange(cmds, t)
        rig.advance(t)
        if t > 0.2:     # the first 0.2 s: kp catching the weight (a 0.3 rad droop)
            peak_speed = max(peak_speed, max(abs(v) for v in rig.q_dot))
        t += DT
    assert homing.status == 'done', homing.reason
    truth = [rig.true_offset(i) for i in range(4)]
    # At the stop the hip presses it by the threshold torque / 5000 N m/rad (under 1 mrad).
    assert homing.offsets == pytest.approx(truth, abs=3e-3)
    ctl = LegController(LEG, HipMotors(MOTORS.motor_ids, MOTORS.directions))
    ctl.set_offsets(homing.offsets)
    assert ctl.homed
    s = ctl.state(rig.exchange(homing.step(replies, t), t))
    assert s.q == pytest.approx(rig.q, abs=3e-3)
    assert peak_speed < 0.5       # gently: the 0.3 rad/s ramp, the weight held back


def test_homing_fails_on_timeout_without_replies():
    homing = HipHoming(MOTORS, HomingConfig(timeout=1.0))
    for k in range(600):
        cmds = homing.step([None] * 4, k * DT)
    assert homing.status == 'failed' and 'timeout' in homing.reason
    assert all(c.kp == 0.0 for c in cmds)       # never a stiff command towards nowhere
