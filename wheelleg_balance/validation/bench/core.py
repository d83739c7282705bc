"""
Compute time of one control tick, per controller: ``BalanceLoop.tick`` as balance_node runs it.

One tick = what the control loop does between reading its inputs and handing frames to
python-can: the IMU and joint samples and both motors' replies taken (core/sensors.py,
core/motors.py), the safety checks, the reference shaping, ``BalanceCore.step`` (wheel
odometry, observer (8), the controller, the Sec. V-A torque split) and one MIT torque frame per
motor (core/balance_loop.py).

The inputs are realistic because they are closed-loop: the simulated robot of
core/simulation.py (model (1), IMU offset 2.7 deg, sensor noise) is balanced by the tick under
test while it drives forward and back, turns both ways and changes height over 0.37..0.70 m.
Both wheel motors are the firmware emulator (sim/motor_emulator.py): they answer each tick's
frames before the next one. Only the tick is timed (time.perf_counter_ns around ``tick``), not
the plant or the motors.
"""
import gc
import math
import time
from typing import Dict

import numpy as np

from .stats import summary_us
from ..faults.bench import LEG_PARAMS, wheel_motors
from ...core.balance_loop import BalanceLoop, CmdVel, Mode, STATE_FIELDS, TickInputs
from ...core.config import BalanceConfig
from ...core.pipeline import CONTROLLER_NAMES
from ...core.schema import from_flat
from ...core.sensors import ImuSample, JointSample
from ...core.simulation import Plant, Scenario, SmoothSchedule

#: A 40 s drive (waypoints (t [s], value)); runs longer than 40 s repeat it.
HEIGHT = ((0, 0.37), (5, 0.37), (10, 0.70), (20, 0.70), (25, 0.37))
X_DOT_REF = ((0, 0.0), (4, 0.0), (6, 0.8), (12, 0.8), (14, -0.5), (20, -0.5), (22, 0.0))
YAW_RATE_REF = ((0, 0.0), (8, 0.0), (9, 1.0), (15, 1.0), (16, -1.0), (24, -1.0), (25, 0.0))
DRIVE_TIME = 40.0


def scenario(controller: str, seed: int = 0) -> Scenario:
    """Return the drive the compute benchmark balances (IMU offset, noise as on the robot)."""
    return Scenario(name='benchmark', controller=controller, duration=DRIVE_TIME,
                    theta0=0.05, imu_offset=math.radians(2.7), height=HEIGHT,
                    x_dot_ref=X_DOT_REF, yaw_rate_ref=YAW_RATE_REF,
                    noise_std=(0.002, 0.02, 0.05), seed=seed)


def time_controller(name: str, ticks: int = 20000, seed: int = 0) -> Dict:
    """
    Balance the simulated robot with controller ``name`` for ``ticks`` ticks, timing each.

    Returns summary_us of the per-tick wall-clock compute time (the target), 'cpu_p99_us'
    (the same ticks in thread CPU time: preemption by other processes excluded),
    'saturated_share' and 'fell'.
    """
    sc = scenario(name, seed)
    dt = sc.dt
    loop = BalanceLoop(from_flat(BalanceConfig, dict(LEG_PARAMS, controller=name)))
    motors = wheel_motors(loop)   # they answer each tick's frames before the next tick
    replies = []
    plant = Plant(sc)
    v_ref, yaw_ref = SmoothSchedule(sc.x_dot_ref), SmoothSchedule(sc.yaw_rate_ref)
    std = sc.noise_std
    noise = (np.random.default_rng(seed).standard_normal((ticks, 4))
             * np.array([std[0], std[1], std[2], std[2]])).tolist()
    clock, cpu_clock = time.perf_counter_ns, time.thread_time_ns
    tick = loop.tick
    inputs = TickInputs()
    durations = [0] * ticks
    cpu_times = [0] * ticks
    saturated = 0
    fell = False
    limit = loop.cfg.safety.max_wheel_torque
    i_left, i_right = STATE_FIELDS.index('tau_left'), STATE_FIELDS.index('tau_right')
    now = 1000.0
    ids = loop.motors.ids
    angles = [0.0, 0.0]   # the wheels' angles [rad], for the motors' replies
    gc.collect()  # the collector stays on, as in the node: its pauses belong to the tail
    for k in range(ticks):
        t = (k * dt) % DRIVE_TIME
        now += dt
        m = plant.sensors(t, noise[k])
        half = 0.5 * m.theta_meas
        inputs.imu.append(ImuSample(now, 0, k + 1, 0.0, math.sin(half), 0.0, math.cos(half),
                                    True, 0.0, m.theta_dot, 0.0, 0.0, 0.0, 9.81))
        # The wheels come from the motors' replies (wheel_state_source can), l from the hips'
        # joint states (legs not driven).
        speeds = (m.wheel_vel_left, m.wheel_vel_right)
        for i in (0, 1):
            angles[i] += speeds[i] * dt
            motors.joints[ids[i]] = (angles[i], speeds[i])
        inputs.joints.append(JointSample(now, False, math.nan, math.nan, True, m.l))
        inputs.frames.extend((now, f) for f in replies)
        inputs.cmd_vel = CmdVel(now, v_ref(t)[0], yaw_ref(t)[0])
        if k % 10 == 0 and loop.mode is not Mode.BALANCING:
            inputs.arm = True   # accepted once the motors answer the resting polls
        c0 = cpu_clock()
        t0 = clock()
        result = tick(now, inputs)
        durations[k] = clock() - t0
        cpu_times[k] = cpu_clock() - c0
        loop.report_send(now, None)
        inputs.clear()
        replies = [r for f in result.frames for r in motors.handle(f, now)]
        state = result.state.values()
        tau_l, tau_r = state[i_left], state[i_right]
        saturated += max(abs(tau_l), abs(tau_r)) >= limit - 1e-9
        plant.advance(tau_l, tau_r, t)
        fell = fell or plant.fell
    result = summary_us(durations)
    result['cpu_p99_us'] = summary_us(cpu_times)['p99_us']
    result['saturated_share'] = saturated / ticks
    result['fell'] = bool(fell)
    return result


def run(ticks: int = 20000, seed: int = 0) -> Dict[str, Dict]:
    """Compute-time summaries {controller: {n, median_us, p99_us, max_us, ...}} for each."""
    return {name: time_controller(name, ticks, seed) for name in CONTROLLER_NAMES}
