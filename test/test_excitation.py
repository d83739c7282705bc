"""
The identification's excitation in the tick (core/excitation.py), on the MuJoCo robot in lockstep.

The phases as balance_node plays them (validation/lockstep.py: the tick against the simulated
robot and its motors' emulators, fixed legs): accepted or refused with the reason, their
torques within the bounds, ended by their abort limits, by ~/stop at once, and the lift and
response checks quiet during the stand's planned free wheels and firing outside that window.
"""
from dataclasses import replace
import math

import pytest

from wheelleg_balance.core import excitation as ex
from wheelleg_balance.core.config import BalanceConfig
from wheelleg_balance.core.model import ipc_accel
from wheelleg_balance.core.safety import LIFTED, Mode, RESPONSE, SensorSnapshot
from wheelleg_balance.validation.lockstep import Lockstep

FIXED = {'legs.driven': False}


def on_stand() -> Lockstep:
    """Return the robot held on a stand (a weld at pitch 0), wheels free, fresh replies."""
    ls = Lockstep(FIXED, pose='tail')
    ls.sim.hold(pitch=0.0, z=1.0)
    ls.sim.step(0.0, 0.0, 0.5)
    ls.run(0.05)
    return ls


def on_tail() -> Lockstep:
    """Return the robot resting on its tail, fresh replies."""
    ls = Lockstep(FIXED, pose='tail')
    ls.run(0.5)
    return ls


def excite(ls: Lockstep, phase: str, seconds: float) -> None:
    """Ask for ``phase`` at the next tick, then run ``seconds``."""
    ls.inputs.excite = phase
    ls.run(seconds)


def snapshot(theta: float = 0.0, w: float = 0.0, theta_dot: float = 0.0) -> SensorSnapshot:
    """Return a fresh, finite snapshot."""
    return SensorSnapshot(imu_time=0.0, joint_time=0.0, theta=theta, theta_dot=theta_dot,
                          wheel_vel_left=w, wheel_vel_right=w, l=0.37)


def test_stand_plays_within_its_bound_and_ends_disarmed():
    ls = on_stand()
    start = len(ls.log)
    excite(ls, 'stand', 0.5)
    assert ls.arm_replies and ls.arm_replies[-1][0], ls.arm_replies
    assert ls.mode == int(Mode.EXCITING)
    assert ls.loop.last_result.state.excitation == ex.PHASE_INDEX['stand']
    ls.run(3.0)
    assert ls.mode == int(Mode.DISARMED), ls.events[-3:]
    assert ls.events[-1] == ('info', 'excitation stand: done, %.1f s' % (
        ex.PROBE_TIME + ex.STAND_DURATION)), ls.events[-3:]
    bound = ex.stand_amplitude(ls.cfg)
    taus = [abs(r[k]) for r in ls.log[start:] for k in ('tau_left', 'tau_right')]
    assert max(taus) <= bound + 1e-12 and max(taus) > 0.9 * bound
    assert ls.loop.last_result.state.excitation == 0
    # the wheels' speed stayed within the abort limit (the bound's purpose)
    assert max(abs(v) for v in ls.sim.wheel_velocities()) < ex.STAND_MAX_SPEED


def test_stand_refused_by_the_probe_on_the_ground():
    ls = on_tail()
    excite(ls, 'stand', 0.3)
    ok, message = ls.arm_replies[-1]
    assert not ok and 'the wheels are not free' in message, message
    assert ls.mode == int(Mode.DISARMED)
    assert max(abs(t) for t in ls.sim.wheel_torques()) == 0.0


def test_lift_and_response_checks_quiet_on_the_stand_and_firing_outside_the_notice():
    ls = on_stand()
    excite(ls, 'stand', 1.0)
    assert ls.mode == int(Mode.EXCITING), ls.events[-3:]
    notice = ls.loop.arming.motion.free_wheels
    assert notice.covers(ls.t)
    # the same free wheels without the notice: the checks fire as before
    notice.withdraw()
    ls.run(0.5, until=lambda: ls.mode != int(Mode.EXCITING))
    faults = {f.code for f in ls.loop.supervisor.faults}
    assert ls.mode == int(Mode.FAULT) and faults & {LIFTED, RESPONSE}, faults
    ls.tick()   # the FAULT's zero torque reached the motors' emulators
    st = ls.loop.last_result.state
    assert (st.tau_left, st.tau_right) == (0.0, 0.0)
    # zero as the MIT torque code carries it: within one step of its 12 bits
    assert max(abs(t) for t in ls.sim.wheel_torques()) < 0.01


def test_tail_stays_on_its_tail_within_the_lift_bound():
    ls = on_tail()
    start = len(ls.log)
    excite(ls, 'tail', 3.2)
    assert ls.arm_replies[-1][0], ls.arm_replies
    assert ls.events[-1][1].startswith('excitation tail: done'), ls.events[-3:]
    rows = ls.log[start:]
    assert max(r['tail_clearance'] for r in rows) < 1e-3
    taus = [abs(r[k]) for r in rows for k in ('tau_left', 'tau_right')]
    assert 0.0 < max(taus) <= ex.TAIL_SHARE * ex.tail_lift_torque(ls.cfg)


def test_tail_lift_torque_is_where_model_1_leaves_the_tail():
    cfg = BalanceConfig()
    p = cfg.model
    theta = cfg.safety.tail_pitch - cfg.safety.arm_pose_tolerance
    u = 2.0 * ex.tail_lift_torque(cfg) / p.wheel_radius   # both wheels' force [N]
    for l in (p.height_min, p.height_max):   # no tail force: theta_ddot's sign flips there
        assert ipc_accel(theta, 0.0, 0.99 * u, l, p)[0] > 0.0
        assert ipc_accel(theta, 0.0, 1.01 * u, l, p)[0] < 0.0
    assert ex.tail_amplitude(cfg) <= ex.TAIL_SHARE * ex.tail_lift_torque(cfg)


def test_stop_mid_phase_gives_zero_torque_at_once():
    ls = on_stand()
    excite(ls, 'stand', 1.0)
    assert ls.mode == int(Mode.EXCITING)
    assert max(abs(t) for t in ls.sim.wheel_torques()) > 0.0
    ls.inputs.estop = True
    ls.tick()
    assert ls.mode == int(Mode.DISARMED)
    assert ls.loop.excitation.phase == ''
    ls.tick()   # the stop frames reached the motors' emulators
    assert max(abs(t) for t in ls.sim.wheel_torques()) == 0.0
    assert any(text.startswith('excitation stand: ended: mode DISARMED')
               for _, text in ls.events), ls.events[-3:]


def test_arm_refused_while_exciting():
    ls = on_stand()
    excite(ls, 'stand', 0.3)
    ls.arm(True)
    ls.tick()
    ok, message = ls.arm_replies[-1]
    assert not ok and 'excitation' in message
    assert ls.mode == int(Mode.EXCITING)


def test_refusals_name_their_reason():
    cfg = BalanceConfig()
    e = ex.Excitation(cfg)
    tail = cfg.safety.tail_pitch
    assert 'unknown phase' in e.refusal('jump', 'DISARMED', snapshot(tail), 0.0, False)
    assert 'needs the robot disarmed' in e.refusal('stand', 'BALANCING', snapshot(), 0.0,
                                                   False)
    assert 'not resting on its tail' in e.refusal('tail', 'DISARMED', snapshot(0.0), 0.0,
                                                  False)
    assert e.refusal('tail', 'DISARMED', snapshot(tail), 0.0, False) == ''
    assert 'needs the robot balancing' in e.refusal('balance', 'DISARMED', snapshot(), 0.0,
                                                    False)
    assert 'still rising' in e.refusal('balance', 'BALANCING', snapshot(), 0.0, True)
    assert 'not still' in e.refusal('balance', 'BALANCING', snapshot(theta_dot=1.0), 0.0,
                                    False)
    assert 'not still' in e.refusal('balance', 'BALANCING', snapshot(), 0.3, False)
    assert e.refusal('balance', 'BALANCING', snapshot(), 0.0, False) == ''
    e.start('tail', 0.0, snapshot(tail), 0.37)
    assert 'the tail phase runs' in e.refusal('stand', 'DISARMED', snapshot(), 0.0, False)


def test_tick_refuses_a_phase_with_its_reason():
    ls = on_stand()   # upright on the stand: no tail phase
    excite(ls, 'tail', 0.01)
    ok, message = ls.arm_replies[-1]
    assert not ok and message.startswith('tail refused: tail: not resting on its tail')
    excite(ls, 'balance', 0.01)
    assert ls.arm_replies[-1] == (False, 'balance refused: balance needs the robot balancing '
                                  '(mode DISARMED): ~/arm true first')
    assert ls.mode == int(Mode.DISARMED)


@pytest.mark.parametrize('phase, s, why', [
    ('stand', snapshot(w=ex.STAND_MAX_SPEED + 1.0), 'wheel speed'),
    ('stand', snapshot(theta=ex.STAND_MAX_PITCH + 0.01), 'moved on its stand'),
    ('stand', snapshot(w=math.nan), 'wheel speed'),
    ('tail', snapshot(theta=0.0), 'left its tail'),
])
def test_abort_limits(phase, s, why):
    cfg = BalanceConfig()
    e = ex.Excitation(cfg)
    start = snapshot(cfg.safety.tail_pitch if phase == 'tail' else 0.0)
    e.start(phase, 0.0, start, 0.37)
    if phase == 'tail':
        assert e.torques(0.01, replace(start, wheel_vel_left=ex.TAIL_MAX_SPEED + 1.0))[2]
    tau_l, tau_r, reason, done = e.torques(0.01, s)
    assert (tau_l, tau_r, done) == (0.0, 0.0, False) and why in reason, reason


def test_phase_ends_past_its_time_whatever_the_sensors():
    cfg = BalanceConfig()
    e = ex.Excitation(cfg)
    e.start('tail', 0.0, snapshot(cfg.safety.tail_pitch), 0.37)
    s = snapshot(cfg.safety.tail_pitch)
    assert e.torques(1.0, s)[2] == ''
    assert 'done' in e.torques(e.duration + 0.01, s)[2]
    assert 'past its end' in e.torques(e.duration + ex.MAX_OVERRUN + 0.01, s)[2]
    e.end()
    e.start('balance', 0.0, snapshot(), 0.37)
    assert 'beyond' in e.balance_abort(1.0, ex.BALANCE_MAX_PITCH + 0.01, 0.0)[0]
    assert 'beyond' in e.balance_abort(1.0, 0.0, ex.BALANCE_MAX_SPEED + 0.1)[0]
    assert e.balance_abort(1.0, 0.0, 0.0) == ('', False)


def test_balance_phase_chirps_x_dot_and_keeps_balancing():
    ls = Lockstep(FIXED, pose='pitch')
    ls.run(0.02)
    ls.arm(True)
    ls.run(1.0, until=lambda: ls.mode == int(Mode.BALANCING))
    ls.run(1.5)
    assert ls.mode == int(Mode.BALANCING), ls.events[-3:]
    start = len(ls.log)
    excite(ls, 'balance', 0.01)
    assert ls.arm_replies[-1][0], ls.arm_replies[-1]
    duration = ls.loop.excitation.duration
    ls.run(duration + 0.1)
    assert ls.mode == int(Mode.BALANCING), ls.events[-3:]
    assert ls.events[-1][1].startswith('excitation balance: done'), ls.events[-3:]
    x_dot = [r['x_dot_true'] for r in ls.log[start:]]
    # the chirp moved the robot both ways, within the abort limit
    assert max(x_dot) > 0.1 and min(x_dot) < -0.1
    assert max(abs(v) for v in x_dot) < ex.BALANCE_MAX_SPEED
