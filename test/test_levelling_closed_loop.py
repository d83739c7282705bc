"""
Roll levelling over main_job's ramp, in lockstep: the control tick against the MuJoCo robot.

validation/lockstep.py runs BalanceLoop (the whole tick of balance_node, the hips driven)
against RobotSim and six emulated MIT motors, deterministically, from the folded rest: arm,
homing, the legs raised on the tail, the start-up; then the drive of main_job's slope runs
(1 m/s, yaw_rate_gain 5.0) over the 7 deg, 1.2 m ramp under the left wheel. The same figures as
main_job's ``slope_levelled`` and ``slope`` (validation/paper/main_job/evaluate.py), without
processes, DDS or a loaded machine in between. Levelling runs the default controller; the
fixed-leg run is the paper's experiment 8 and runs its controller, IDA-PBC, as main_job's
``slope`` does.
"""
import math

import numpy as np
import pytest

from wheelleg_balance.core.safety import Mode
from wheelleg_balance.sim.robot_sim import Slope
from wheelleg_balance.validation.lockstep import Lockstep
from wheelleg_balance.validation.paper.main_job.scenarios import FIXED_LEGS, SLOPE
from wheelleg_balance.validation.paper.table import IMU_OFFSET, SIM_YAW_GAIN

RAMP = Slope(SLOPE['slope.start_x'], SLOPE['slope.length'], SLOPE['slope.angle'],
             SLOPE['slope.side'])
X_TOP = RAMP.start_x + RAMP.length * math.cos(RAMP.angle)
#: The wheel is down the fall time of the ramp's height after the axle passes the top [s].
FALL = math.sqrt(2.0 * RAMP.length * math.sin(RAMP.angle) / 9.81)
#: The drive: 1 m/s from DRIVE[0] to DRIVE[1] after balancing [s], then 1 s to brake.
DRIVE = (2.5, 14.0)


def _drive_over_the_ramp(params):
    """Arm from the folded rest, balance, drive over the ramp; return t, x, roll, theta, modes."""
    ls = Lockstep(params=dict({'legs.homing': 'hard_stops', 'yaw_rate_gain': SIM_YAW_GAIN},
                              **params), power_up=True, imu_offset=IMU_OFFSET, slope=RAMP)
    ls.run(0.5)
    ls.arm(True)
    ls.run(6.0, until=lambda: ls.mode == Mode.BALANCING)
    assert ls.mode == Mode.BALANCING, ls.events
    t0 = ls.t
    for _ in range(int(round((DRIVE[1] + 1.0) / ls.period))):
        ls.command(1.0 if DRIVE[0] <= ls.t - t0 < DRIVE[1] else 0.0)
        ls.tick()
    log = [r for r in ls.log if r['t'] >= t0]
    t = np.array([r['t'] for r in log]) - t0
    return (t, np.array([r['x_true'] for r in log]),
            np.degrees([r['roll_true'] for r in log]),
            np.degrees([r['theta_true'] for r in log]), {r['mode'] for r in log})


def _figures(t, x, roll, theta):
    on = (x >= RAMP.start_x) & (x < X_TOP)
    assert on.any() and (x >= X_TOP).any(), 'never over the ramp'
    t_on, t_top = t[np.argmax(on)], t[np.argmax(x >= X_TOP)]
    before = np.mean(theta[(t >= t_on - 1.0) & (t < t_on)])
    # Settled after the drop: from 2 s after the wheel is down until the stick is released
    # (braking from 1 m/s leans the body by up to the hold's max_lean_move; not the ramp's doing).
    late = theta[(t >= t_top + FALL + 2.0) & (t < DRIVE[1])]
    dropped = t >= t_top
    tilted = np.flatnonzero(dropped & (np.abs(roll) > 2.0))
    return {'roll_on_ramp': np.max(np.abs(roll[on])),
            'drop_roll_peak': np.max(np.abs(roll[dropped])),
            'roll_back_s': t[tilted[-1]] - t_top if tilted.size else 0.0,
            'pitch_after': np.max(np.abs(late - before))}


def test_levelling_keeps_the_body_level_on_the_ramp_and_settles_after_the_drop():
    t, x, roll, theta, modes = _drive_over_the_ramp({})
    f = _figures(t, x, roll, theta)
    assert modes == {Mode.BALANCING}
    assert f['roll_on_ramp'] <= 5.0, f          # main_job's slope_levelled criterion
    assert f['pitch_after'] < 3.0, f
    # The drop (0.15 m in 0.17 s) still tilts it; the roll damping brings it back.
    assert f['roll_back_s'] < 2.0, f


def test_fixed_legs_roll_with_the_ramp_as_in_the_paper():
    t, x, roll, theta, modes = _drive_over_the_ramp(dict(FIXED_LEGS, controller='ida_pbc'))
    f = _figures(t, x, roll, theta)
    assert modes == {Mode.BALANCING}
    # The paper: 19 deg; the ramp's top alone tilts the axle by atan(0.146 / 0.47) = 17.3 deg.
    assert f['roll_on_ramp'] == pytest.approx(19.0, abs=2.5), f
    assert f['pitch_after'] < 3.0, f
