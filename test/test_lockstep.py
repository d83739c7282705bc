"""
The whole robot on CAN, closed loop: BalanceLoop against the MuJoCo robot and its six motors.

validation/lockstep.py runs the control tick on simulated time against the simulated robot:
the only inputs are the IMU sample and the six MIT motors' replies (no joint_states), as on the
hardware. Each test starts from the robot as it is after power-up, folded onto its tail, with
the IMU's pitch offset d of the paper's robot (2.2 deg).
"""
import math

import pytest

pytest.importorskip('mujoco')

from wheelleg_balance.core.balance_loop import Mode  # noqa: E402
from wheelleg_balance.core.params import RobotParams  # noqa: E402
from wheelleg_balance.validation.lockstep import Lockstep  # noqa: E402

D = math.radians(2.2)
P = RobotParams()
TAIL = math.radians(36.0)


def standing(params=None, **kwargs) -> Lockstep:
    """Return a Lockstep whose robot was armed on its tail and has stood up (8 s)."""
    ls = Lockstep(params, imu_offset=D, **kwargs)
    ls.run(0.5)
    ls.arm(True)
    ls.run(8.0)
    return ls


def window(ls: Lockstep, name: str, seconds: float):
    return ls.series(name, since=ls.t - seconds)


def test_stands_up_from_the_folded_rest_on_the_imu_and_the_motor_replies_alone():
    ls = Lockstep(imu_offset=D)
    assert ls.loop.sensing.from_can and ls.loop.legs is not None
    rest = ls.sim.ground_truth()
    assert rest['l'] < P.height_min and rest['theta'] > 0.1   # folded, on the tail
    ls.run(0.5)
    ls.arm(True)
    ls.run(8.0)
    assert ls.arm_replies and ls.arm_replies[0][0], ls.arm_replies
    modes = ls.series('mode')
    # Arming homes and raises the legs on the tail first, then balances, never faulting.
    assert int(Mode.HOMING) in modes and int(Mode.FAULT) not in modes
    assert ls.mode == int(Mode.BALANCING)
    theta = window(ls, 'theta_true', 2.0)
    assert max(abs(v) for v in theta) < math.radians(2.0)
    assert all(abs(v - P.height_min) < 0.01 for v in window(ls, 'l_true', 2.0))
    # The observer has found the IMU's offset d.
    assert ls.log[-1]['d_hat'] == pytest.approx(D, abs=math.radians(0.5))
    # Torques finite and within the limit on every tick.
    limit = ls.cfg.safety.max_wheel_torque
    assert all(math.isfinite(t) and abs(t) <= limit + 1e-9
               for row in ls.log for t in (row['tau_left'], row['tau_right']))


def test_cmd_height_is_tracked_clamped_and_refused_when_not_finite():
    ls = standing()
    ls.command_height(0.60)
    ls.run(4.0)
    assert all(abs(v - 0.60) < 0.01 for v in window(ls, 'l_true', 1.0))
    assert max(abs(v) for v in ls.series('theta_true', since=ls.t - 4.0)) < math.radians(5.0)
    refused = ls.loop.balancing.rejected_cmd_height
    for bad in (math.nan, math.inf, -math.inf):
        ls.command_height(bad)
        ls.run(0.05)
    assert ls.loop.balancing.rejected_cmd_height == refused + 3
    assert ls.log[-1]['l_ref'] == pytest.approx(0.60)
    # Out of range: clamped to [height_min, height_max], reached within the legs' rate limits.
    ls.command_height(5.0)
    ls.run(4.0)
    assert ls.log[-1]['l_ref'] == pytest.approx(P.height_max)
    assert abs(ls.log[-1]['l_true'] - P.height_max) < 0.01
    ls.command_height(0.0)
    ls.run(5.0)
    assert ls.log[-1]['l_ref'] == pytest.approx(P.height_min)
    assert ls.mode == int(Mode.BALANCING)


@pytest.mark.parametrize('divider', [2, 1])
def test_the_hips_are_commanded_in_turns_and_track_the_height_either_way(divider):
    """
    The hips are commanded in turns (legs.command_divider) and the legs track the height.

    Divider 2 (the default): two hip frames per tick, the legs taking turns, each hip at
    250 Hz (half the CAN load of the hips at 500 Hz); 1: all four every tick. Either way the
    legs track a height change and the body stays upright.
    """
    ls = standing({'legs.command_divider': divider})
    assert ls.cfg.legs.command_divider == divider
    ls.command_height(0.60)
    per_tick = []
    for _ in range(int(round(4.0 / ls.period))):
        ls.tick()
        per_tick.append(tuple(f.arbitration_id for f in ls.loop.last_result.leg_frames))
    left, right = tuple(ls.cfg.legs.motor_ids[:2]), tuple(ls.cfg.legs.motor_ids[2:])
    if divider == 2:
        assert all(len(ids) == 2 for ids in per_tick)
        assert all({a, b} == {left, right} for a, b in zip(per_tick, per_tick[1:]))
    else:
        assert all(ids == left + right for ids in per_tick)
    assert all(abs(v - 0.60) < 0.01 for v in window(ls, 'l_true', 1.0))
    assert max(abs(v) for v in window(ls, 'theta_true', 4.0)) < math.radians(5.0)
    assert ls.mode == int(Mode.BALANCING)


def test_the_height_changes_within_the_rate_limit():
    ls = standing()
    ls.command_height(P.height_max)
    ls.run(3.0)
    l_ref = ls.series('l_ref', since=ls.t - 3.0)
    rate = max(abs(b - a) for a, b in zip(l_ref, l_ref[1:])) / ls.period
    assert rate <= ls.cfg.legs.max_height_rate * 1.001
    assert max(l_ref) > P.height_min + 0.2   # it did move


def test_disarm_sits_the_robot_down_onto_its_tail():
    ls = standing()
    x0, t0 = ls.log[-1]['x_true'], ls.t
    ls.arm(False)
    ls.run(10.0, until=lambda: ls.mode == int(Mode.DISARMED))
    assert ls.mode == int(Mode.DISARMED), 'the sit-down ended'
    sitting = [row for row in ls.log if row['t'] >= t0]
    # The body's true pitch rate when the tail wheel touches the floor (at most 0.5 rad/s).
    contact = next(row for row in sitting if row['tail_clearance'] <= 0.0)
    assert abs(contact['theta_dot_true']) <= 0.5, contact
    assert contact['theta_true'] > TAIL - math.radians(4.0)   # the tail, not a fall
    travel = max(abs(row['x_true'] - x0) for row in sitting)
    assert travel <= 1.0, travel
    sat = ls.loop.legs_task.last_sit_down
    assert sat is not None and sat.contact_rate <= 0.5
    assert int(Mode.FAULT) not in [row['mode'] for row in sitting]
    # Then it stays where it is, at rest on the tail with the legs folded, no torque.
    ls.run(2.0)
    rest = window(ls, 'theta_true', 1.0)
    assert max(rest) - min(rest) < math.radians(0.5) and min(rest) > 0.1
    # Braked below the sit-down's stop_speed before the motors rest; the free wheels may
    # roll on slowly (this floor has no rolling resistance), never faster.
    speeds = [abs(v) for v in window(ls, 'x_dot_true', 1.0)]
    assert max(speeds) < ls.loop.legs_task.sit_down_config.stop_speed and speeds[-1] <= speeds[0]
    assert all(row['tau_left'] == 0.0 and row['tau_right'] == 0.0 for row in ls.log[-500:])


def test_an_emergency_stop_cuts_at_once_and_the_robot_falls_uncontrolled():
    # The comparison for the sit-down: zero torque while upright drops the robot.
    ls = standing()
    t0 = ls.t
    ls.inputs.estop = True
    ls.run(3.0)
    assert ls.mode == int(Mode.DISARMED)
    after = [row for row in ls.log if row['t'] > t0 + 0.004]
    assert all(row['tau_left'] == 0.0 and row['tau_right'] == 0.0 for row in after)
    # It fell, one way or the other: the limp legs fold and the body lands on its tail (at
    # about 10 deg once folded) or swings far past upright the other way.
    landed = any(row['tail_clearance'] <= 0.0 for row in after)
    assert landed or abs(ls.log[-1]['theta_true']) > math.radians(20.0)


def test_homing_at_the_hard_stops_after_power_up():
    # After power-up a 9:1 hip knows its angle only modulo a rotor turn (40 deg).
    ls = Lockstep({'legs.homing': 'hard_stops'}, imu_offset=D, power_up=True)
    ls.run(0.5)
    ls.arm(True)
    ls.run(12.0)
    assert ls.loop.legs.controller.homed
    assert ls.mode == int(Mode.BALANCING)
    assert all(abs(v - P.height_min) < 0.01 for v in window(ls, 'l_true', 1.0))
    assert max(abs(v) for v in window(ls, 'theta_true', 1.0)) < math.radians(2.0)


def test_a_silent_hip_motor_ends_balancing_without_an_exception():
    ls = standing()
    t0 = ls.t
    ls.silent.add(ls.cfg.legs.motor_ids[0])
    ls.run(6.0)
    modes = ls.series('mode', since=t0)
    assert int(Mode.BALANCING) != modes[-1]
    # The lost motor is named: a fault (class a, zero torque) or the sit-down (class b).
    codes = [code for code, _ in ls.loop.status(ls.t)['faults']]
    assert ls.mode == int(Mode.DISARMED) or any(c in ('motor_silent', 'legs') for c in codes), \
        codes
    limit = ls.cfg.safety.max_wheel_torque
    assert all(math.isfinite(row['tau_left']) and abs(row['tau_left']) <= limit
               for row in ls.log)
    assert ls.loop.last_result.state.tau_left == 0.0


def _kicked(params=None):
    """
    Kick the standing robot (60 N for 0.1 s, main_job's push) and watch it for 15 s.

    Returns (Lockstep, distance rolled [m], recovery [s]: until the pitch stays within 1 deg
    of its mean over the 0.5 s before the kick, as main_job's kick_recovery_s).
    """
    import numpy as np
    from wheelleg_balance.sim.robot_sim import Push
    from wheelleg_balance.validation.paper.metrics import settling_time
    t_kick = 10.0
    ls = standing(params, pushes=[Push(t_kick, 0.1, 60.0)])
    ls.run(t_kick - ls.t)
    theta_before = float(np.mean(window(ls, 'theta_true', 0.5)))
    x0 = ls.log[-1]['x_true']
    ls.run(15.0)
    t = np.array(ls.series('t', since=t_kick))
    theta = np.array(ls.series('theta_true', since=t_kick))
    settled = settling_time(t, theta - theta_before, math.radians(1.0), since=t_kick,
                            edge='outside')
    return ls, ls.log[-1]['x_true'] - x0, settled - t_kick


@pytest.mark.slow
def test_a_kicked_robot_comes_to_rest_within_max_roll_out_its_pitch_back_within_1_s():
    # The hold brakes a kick gently (output_regulation.max_lean_hold, so the pitch is back
    # within 1 deg in 1 s: issue 12's push target) but hard enough to stop within max_roll_out
    # of where the roll began. Without that bound the same kick rolls it on for metres.
    ls, roll, recovery = _kicked()
    max_roll = ls.cfg.output_regulation.max_roll_out
    assert 0.0 < roll <= max_roll
    assert all(abs(v) < 0.05 for v in window(ls, 'x_dot_true', 1.0))   # at rest
    assert recovery <= 1.0
    assert int(Mode.BALANCING) == ls.mode
    _, unbounded, _ = _kicked({'output_regulation.max_roll_out': 0.0})
    assert unbounded > 1.3 * roll
