"""
Fault scenarios on the control tick itself, in lockstep with the MuJoCo robot (no ROS).

``LoopBench`` (validation/faults/bench.py) runs the tick on a virtual clock, the plant moves one
period per tick under the torques the tick's frames command: deterministic runs, faster than
real time; the lifted and the flipped-IMU scenarios run the whole robot (validation/lockstep.py:
emulated MIT motors, the legs driven or fixed) and read the frames the tick sends. The
``context`` argument keeps the scenarios' common signature (unused here).
"""
import math
from typing import List, Tuple

from .bench import decode, LoopBench, MODE, TORQUE_LSB
from .outcome import Outcome
from .plants import MujocoPlant
from .rig import PERIOD

#: IMU mounting offset of the switch scenario [rad]: the paper's robot had about 2.2 deg, which
#: the linear controller 'lqr' does not compensate, so the controllers disagree at a switch.
SWITCH_IMU_OFFSET = math.radians(3.0)
#: Switches of the scenario: (time [s] after arming, controller), driving at 1 m/s from 1.5 s.
SWITCHES = ((3.0, 'lqr'), (4.0, 'ida_pbc'), (5.0, 'output_regulation'))


def _switch_run(context, blend: float):
    plant = MujocoPlant('pitch', 0.0, imu_offset=SWITCH_IMU_OFFSET)
    bench = LoopBench(controller='output_regulation', switch_blend_time=blend)

    def switch(name):
        return lambda: bench.set_parameters(controller=name)
    bench.feed()
    bench.rearm()
    log = bench.closed_loop(plant, SWITCHES[-1][0] + 1.0, x_dot_cmd=1.0,
                            events={t: switch(name) for t, name in SWITCHES})
    return log, plant.truth()


def scenario_controller_switch(context) -> Outcome:
    """
    Switch the controller while driving at x_dot* = 1 m/s (MuJoCo robot, lockstep, IMU 3 deg off).

    The bound: BalanceCore blends the jump J between the old and the new controller's command
    out over N = switch_blend_time / T = 50 ticks, so the switch itself adds at most J / N per
    tick to what the new controller changes by itself. J is measured as the torque step of the
    same switch with switch_blend_time = 0 (the runs are deterministic and identical up to the
    switch). Required, in the 0.2 s after each switch: max per-tick step of the left wheel
    command <= J / N + the largest step of the 0.5 s of steady driving before + 2 codes of the
    12-bit MIT torque (quantization, 8.8 mN m each).
    """
    out = Outcome('controller_switch_1mps', 'controller switches at x_dot* = 1 m/s, '
                  'IMU 3 deg off (MuJoCo, lockstep)', 'bumpless: torque step at a switch <= '
                  'J/50 + steady step + 2 codes (J: the unblended jump)')
    blended, truth = _switch_run(context, 0.1)
    raw, _ = _switch_run(context, 0.0)
    n_blend = 0.1 / PERIOD
    out.check('still BALANCING after the switches', blended[-1][2] == MODE['BALANCING'])
    out.check('drives at 1 m/s (%.2f)' % truth['x_dot'], abs(truth['x_dot'] - 1.0) < 0.2)
    worst = 0.0
    for t_switch, name in SWITCHES:
        steady = _max_step(blended, t_switch - 0.5, t_switch)
        step = _max_step(blended, t_switch, t_switch + 0.2)
        jump = _max_step(raw, t_switch, t_switch + 0.2)
        bound = jump / n_blend + steady + 2 * TORQUE_LSB
        out.figures['to_%s' % name] = {'step_nm': round(step, 4), 'unblended_nm': round(jump, 4),
                                       'steady_nm': round(steady, 4), 'bound_nm': round(bound, 4)}
        out.check('switch to %s: step %.4f <= bound %.4f N m (unblended %.3f)'
                  % (name, step, bound, jump), step <= bound)
        worst = max(worst, step)
    out.figures['worst_step_nm'] = round(worst, 4)
    return out


#: The nudge during the IMU dropout of the recovery scenario: (force_x [N], duration [s]). With
#: no torque the balanced robot falls whichever way it happens to lean; 20 N for 0.2 s makes it
#: fall forward, onto its tail, every time.
RECOVERY_NUDGE = (20.0, 0.2)


def scenario_recovery_needs_rearm(context) -> Outcome:
    """
    Drop the IMU for 0.3 s while the MuJoCo robot balances, auto_arm on (lockstep).

    It must fault, fall onto its tail with zero torque, stay there without torque for 10 s
    although every sensor is healthy again (no re-arm by itself, auto_arm included), and
    balance again after an explicit re-arm (the start-up from the tail).
    """
    out = Outcome('recovery_rearm', 'IMU silent for 0.3 s while balancing, nudged forward '
                  '(MuJoCo, auto_arm, lockstep)', 'FAULT; falls onto the tail with zero '
                  'torque; no re-arm by itself in 10 s; an explicit re-arm stands it up')
    plant = MujocoPlant('tail')
    bench = LoopBench(auto_arm=True)
    timeout = bench.config.safety.imu_timeout
    log = bench.closed_loop(plant, 4.0)
    up = log[-1][2] == MODE['BALANCING'] and abs(plant.truth()['theta']) < 0.1
    if not out.check('auto_arm stood it up from the tail', up):
        return out
    plant.push(*RECOVERY_NUDGE)
    log = bench.closed_loop(plant, 10.0, imu_gap=(0.0, 0.3))
    faulted = [t for t, _, mode in log if mode == MODE['FAULT']]
    out.check('FAULT', bool(faulted))
    if not faulted:
        return out
    out.time_to_zero = faulted[0]   # from the last IMU sample (virtual time)
    out.check('FAULT within imu_timeout + 2 ticks of the last sample',
              faulted[0] <= timeout + 2 * PERIOD)
    out.check('fault code imu_stale',
              any(f.code == 'imu_stale' for f in bench.loop.supervisor.faults))
    after = [(mode, torques) for t, torques, mode in log if t >= faulted[0]]
    out.check('FAULT and zero torque on every tick of the 10 s (IMU back after 0.3 s)',
              all(mode == MODE['FAULT'] and all(abs(v) <= TORQUE_LSB
                                                for v in torques.values())
                  for mode, torques in after))
    theta = plant.truth()['theta']
    out.figures['theta_after_fault_deg'] = round(math.degrees(theta), 1)
    out.check('lies on its tail (theta %.1f deg, tail %.1f deg)' % (
        math.degrees(theta), math.degrees(plant.tail_pitch)),
        abs(theta - plant.tail_pitch) < 0.03)
    req = bench.request(True)
    log = bench.closed_loop(plant, 4.0)
    out.check('explicit re-arm accepted on the tail (%s)' % req.message, req.success)
    out.check('stood up again: BALANCING, |theta| < 0.1 rad',
              log[-1][2] == MODE['BALANCING'] and abs(plant.truth()['theta']) < 0.1)
    return out


def _max_step(log, t0: float, t1: float) -> float:
    """Largest change of the left command between consecutive ticks, from the tick before t0."""
    taus = [torques[1] for t, torques, _ in log if t0 - 1.5 * PERIOD < t < t1 - 0.5 * PERIOD]
    return max((abs(b - a) for a, b in zip(taus, taus[1:])), default=0.0)


#: The pick-up: the body welded to a stand this far [m] above where it balanced (0.1 m left
#: the wheels on the floor once the unloaded legs had pushed out).
LIFT_HEIGHT = 0.2
#: The lifted reaction's bound [s] with driven legs (issue 11: zero wheel torque within 0.1 s)
#: and with fixed legs (issue 29: 0.15 s).
LIFT_BOUND = 0.1
LIFT_BOUND_FIXED = 0.15
#: Issue 29: where the controller asks little torque (below LIFT_LITTLE_TORQUE [N m] until the
#: cut), zero torque before either free wheel passes LIFT_SLOW_SPEED [rad/s].
LIFT_LITTLE_TORQUE = 1.0
LIFT_SLOW_SPEED = 8.0
#: Fixed legs (the default robot): the hips are the simulator's servos, balance_node has none.
FIXED_LEGS = {'legs.driven': False}


def lifted_name(tilt_deg: float, driven: bool) -> str:
    """Return the scenario's name: lifted[_fixed_legs][_tilted_<deg>]."""
    return 'lifted' + ('' if driven else '_fixed_legs') + (
        '_tilted_%.0f' % tilt_deg if tilt_deg else '')


def _recorded(ls) -> List[Tuple[float, int, object]]:
    """Return the list that gets (time [s], motor ID, the frame decoded) of each frame sent."""
    bus = []
    replies = ls.motors.replies   # what Lockstep.tick hands every frame to

    def record(frame, bus_index=0):
        bus.append((ls.t, frame.arbitration_id, decode(frame.arbitration_id, frame.data)))
        return replies(frame, bus_index)
    ls.motors.replies = record
    return bus


def scenario_lifted(context, tilt_deg: float = 0.0, driven: bool = True) -> Outcome:
    """
    Pick the balancing robot up, 0.2 m, held ``tilt_deg`` off its balance pitch (lockstep).

    The whole robot of validation/lockstep.py (legs driven, or fixed: ``legs.driven: false``
    with the simulator's servos) stands up from its tail, then its body is welded to a stand
    0.2 m up. Required: FAULT ``lifted``, zero torque to both wheels on every frame from within
    0.1 s of the pick-up (fixed legs: 0.15 s, and before a free wheel passes 8 rad/s while the
    torque stayed below 1 N m); with driven legs also the legs holding their length (not damped
    down to their stops) and a re-arm refused while it is held in the air (fixed legs cannot
    tell the air from the ground before arming).
    """
    from ..lockstep import Lockstep
    from ...core.protocols.mit import MitCommand
    bound = LIFT_BOUND if driven else LIFT_BOUND_FIXED
    out = Outcome(lifted_name(tilt_deg, driven), 'picked up while balancing, %.0f deg off its '
                  'balance pitch, legs %s (MuJoCo, lockstep)' % (
                      tilt_deg, 'driven' if driven else 'fixed'),
                  'FAULT lifted, zero wheel torque within %.2f s%s' % (
                      bound, ', legs holding, no re-arm in the air' if driven else
                      ', before a wheel passes 8 rad/s where the torque stays below 1 N m'))
    ls = Lockstep(None if driven else FIXED_LEGS, imu_offset=math.radians(2.2))
    bus = _recorded(ls)
    ls.run(0.5)
    ls.arm(True)
    ls.run(7.5)
    if not out.check('stood up from its tail', ls.mode == MODE['BALANCING']):
        return out
    wheels = ls.loop.motors.ids
    t_lift = ls.t
    ls.sim.hold(ls.log[-1]['theta_true'] + math.radians(tilt_deg),
                float(ls.sim.data.qpos[2]) + LIFT_HEIGHT, float(ls.sim.data.qpos[0]))
    peak = 0.0
    speeds = []
    for _ in range(int(round(1.0 / ls.period))):
        ls.tick()
        speeds.append((ls.t, max(abs(w) for w in ls.sim.wheel_velocities())))
        peak = max(peak, speeds[-1][1])
    faults = [f.code for f in ls.loop.supervisor.faults]
    out.figures['reason'] = '; '.join(f.message for f in ls.loop.supervisor.faults)
    out.check('FAULT lifted (%s)' % ','.join(faults), ls.mode == MODE['FAULT']
              and faults == ['lifted'])
    t_zero = t_lift
    torque = 0.0
    for t, motor, cmd in bus:
        if t >= t_lift and motor in wheels and isinstance(cmd, MitCommand) \
                and abs(cmd.torque) > TORQUE_LSB:
            t_zero = t + ls.period   # zero from the next frame on, if any
            torque = max(torque, abs(cmd.torque))
    out.time_to_zero = t_zero - t_lift
    out.check('zero torque to both wheels within %.0f ms of the pick-up' % (1e3 * bound),
              out.time_to_zero <= bound)
    frames = [cmd for t, m, cmd in bus if t >= t_zero and m in wheels]
    out.check('zero torque frames every tick after', len(frames) >= 2 * 0.8 / ls.period)
    # The free wheels' speed when the torque went (they coast on from there).
    at_cut = max((w for t, w in speeds if t <= t_zero + 1e-9), default=0.0)
    out.figures['wheel_speed_at_cut_rad_s'] = round(at_cut, 2)
    out.figures['max_torque_nm'] = round(torque, 2)
    if not driven and torque < LIFT_LITTLE_TORQUE:
        out.check('little torque (%.2f N m): cut before a wheel passed %.0f rad/s (%.1f)'
                  % (torque, LIFT_SLOW_SPEED, at_cut), at_cut < LIFT_SLOW_SPEED)
    # Without torque a free wheel coasts down on its bearing's friction alone.
    out.figures['peak_wheel_speed_rad_s'] = round(peak, 2)
    out.check("wheels never near the MIT reply's 50 rad/s (peak %.1f rad/s)" % peak,
              peak < 25.0)
    if not driven:
        return out
    # Held, the legs overshoot the length they had at the fault (they were extending: the
    # weight's share pushed them until then) and sag under the hanging wheels, then stay. The
    # damping of the other faults would let them run out to their stops (0.7 m).
    hold = ls.loop.legs_task.lift_hold
    after = [row['l_true'] for row in ls.log if row['t'] >= t_zero]
    if out.check('legs held at their length at the fault', hold is not None):
        dev = max(abs(v - 0.5 * (hold[0] + hold[1])) for v in after)
        out.figures['leg_deviation_m'] = round(dev, 4)
        out.check('legs within 5 cm of it (%.1f cm)' % (100 * dev), dev < 0.05)
    settled = [row['l_true'] for row in ls.log if row['t'] >= ls.t - 0.5]
    out.check('legs still in the last 0.5 s', max(settled) - min(settled) < 0.002)
    hips = [cmd for t, m, cmd in bus if t >= t_zero + 0.01 and m not in wheels]
    out.check('hips commanded with stiffness (holding, not damping)',
              bool(hips) and all(isinstance(c, MitCommand) and c.kp > 0.0 for c in hips))
    ls.arm(True)
    ls.run(0.02)
    reply = ls.arm_replies[-1]
    out.check('re-arm refused in the air (%s)' % reply[1], not reply[0] and 'lifted' in reply[1]
              and ls.mode == MODE['FAULT'])
    return out


#: The flipped-IMU scenarios: armed upright, held this far [rad] off upright until the arm;
#: the IMU turned 180 deg about z and balance_node not told (imu_mounting_rpy [0, 0, 0]), or
#: told so where it is not: either way its pitch sign is wrong. IMU offset d [rad] as the
#: paper's robot.
FLIP_PITCH = math.radians(2.0)
FLIP_MOUNTING = [0.0, 0.0, math.pi]
FLIP_IMU_OFFSET = math.radians(2.2)
#: The true pitch [rad] the robot must not leave before zero torque (issue 29).
FLIP_LIMIT = math.radians(10.0)


def _flip_checks(out: Outcome, faults, reason: str, t_zero, theta_zero, peak) -> None:
    out.figures['reason'] = reason
    out.check('FAULT response alone (%s)' % ','.join(faults), faults == ['response'])
    out.check('the reason names imu_mounting_rpy and the wheel directions',
              'imu_mounting_rpy' in reason and 'can.left_direction' in reason
              and 'can.right_direction' in reason)
    out.time_to_zero = t_zero
    if out.check('zero torque to both wheels', t_zero is not None):
        out.figures['pitch_at_zero_deg'] = round(math.degrees(theta_zero), 2)
        out.figures['peak_pitch_before_zero_deg'] = round(math.degrees(peak), 2)
        out.check('zero torque before the true pitch left +-%.0f deg (%.1f deg at most)'
                  % (math.degrees(FLIP_LIMIT), math.degrees(peak)), peak < FLIP_LIMIT)


def scenario_imu_flipped(context, pitch: float = FLIP_PITCH, driven: bool = False,
                         imu_offset: float = FLIP_IMU_OFFSET) -> Outcome:
    """
    Arm the robot upright with its IMU's pitch sign wrong (whole robot, lockstep).

    The body is held on a stand ``pitch`` [rad] off upright, wheels on the floor, while the
    motors come up; armed, it is let go. balance_node is told imu_mounting_rpy [0, 0, pi], the
    MuJoCo IMU sits straight: theta~, theta_dot and the accelerometer's x all read the wrong
    way round and the controller drives the fall it should stop. Required: FAULT ``response``
    (not ``lifted`` or another), its reason naming ``imu_mounting_rpy`` and
    ``can.left_direction`` / ``can.right_direction``, zero torque to both wheels on the bus
    before the true pitch leaves +-10 deg. time_to_zero is from the arm.
    """
    from ..lockstep import Lockstep
    from ...core.protocols.mit import MitCommand
    params = {'imu_mounting_rpy': FLIP_MOUNTING}
    if not driven:
        params.update(FIXED_LEGS)
    out = Outcome('imu_flipped%s' % ('' if driven else '_fixed_legs'),
                  'armed upright at %.0f deg with the IMU turned 180 deg about z, legs %s '
                  '(MuJoCo, lockstep)' % (math.degrees(pitch), 'driven' if driven else 'fixed'),
                  'FAULT response, zero wheel torque before the true pitch leaves +-10 deg')
    ls = Lockstep(params, imu_offset=imu_offset, pose='pitch' if driven else None)
    bus = _recorded(ls)
    ls.sim.hold(pitch)   # wheels on the floor
    ls.run(0.1)
    ls.arm(True)
    ls.tick()
    ls.sim.release()
    if not out.check('armed upright (%s)' % (ls.arm_replies[-1:],),
                     ls.mode == MODE['BALANCING']):
        return out
    t_arm = ls.t - ls.period
    ls.run(0.4, until=lambda: ls.mode == MODE['FAULT'])
    ls.run(0.05)
    wheels = ls.loop.motors.ids
    t_zero = None
    for t, motor, cmd in bus:
        if t >= t_arm and motor in wheels and isinstance(cmd, MitCommand):
            if abs(cmd.torque) > TORQUE_LSB:
                t_zero = None
            elif t_zero is None:
                t_zero = t
    before = [row for row in ls.log if t_arm <= row['t'] <= (t_zero or ls.t)]
    theta = before[-1]['theta_true'] if before else math.nan
    peak = max(abs(row['theta_true']) for row in before) if before else math.inf
    _flip_checks(out, [f.code for f in ls.loop.supervisor.faults],
                 '; '.join(f.message for f in ls.loop.supervisor.faults),
                 None if t_zero is None else t_zero - t_arm, theta, peak)
    return out


def scenario_imu_flipped_plant(context, pitch: float = FLIP_PITCH) -> Outcome:
    """
    Arm the fault rig's MuJoCo plant with the IMU turned round (LoopBench, servo legs).

    The plant stands at ``pitch`` [rad] with its IMU 2.2 deg off; the bench arms balance_node's
    tick (imu_mounting_rpy [0, 0, pi]) and closes the loop through the emulated wheel motors.
    The rig's IMU messages carry no linear acceleration (zeros). Required as in
    ``scenario_imu_flipped``; time_to_zero is from the arm.
    """
    out = Outcome('imu_flipped_plant', 'armed upright at %.0f deg with the IMU turned 180 deg '
                  "about z (the fault rig's MuJoCo plant, lockstep)" % math.degrees(pitch),
                  'FAULT response, zero wheel torque before the true pitch leaves +-10 deg')
    plant = MujocoPlant('pitch', pitch, imu_offset=FLIP_IMU_OFFSET)
    bench = LoopBench(imu_mounting_rpy=FLIP_MOUNTING)
    bench.feed()
    bench.rearm()
    rows = []
    t_zero = None
    for _ in range(int(round(0.4 / bench.period))):
        (t, torques, mode), = bench.closed_loop(plant, bench.period)
        theta = plant.truth()['theta']
        zero = all(abs(v) <= TORQUE_LSB for v in torques.values())
        if zero and t_zero is None:
            t_zero = len(rows) * bench.period
        elif not zero:
            t_zero = None
        rows.append(theta)
        if mode == MODE['FAULT'] and t_zero is not None:
            break
    n = len(rows) if t_zero is None else int(round(t_zero / bench.period)) + 1
    sup = bench.loop.supervisor
    _flip_checks(out, [f.code for f in sup.faults], '; '.join(f.message for f in sup.faults),
                 t_zero, rows[n - 1] if rows else math.nan,
                 max((abs(v) for v in rows[:n]), default=math.inf))
    return out
