"""
Compute time of one control tick of the math core, per controller.

One tick = ``BalanceCore.step`` (wheel odometry, observer (8), the controller, Sec. V-A torque
split and saturation) + ``MitProtocol.torque_frames`` for both wheel motors: the work the node's
control thread does between reading the samples and handing frames to python-can.

The inputs are realistic because they are closed-loop: the simulated robot of
core/simulation.py (model (1), IMU offset 2.7 deg, sensor noise) is balanced by the core under
test while it drives forward and back, turns both ways and changes height over 0.37..0.70 m.
Only the core's work is timed (time.perf_counter_ns around step + torque_frames), not the plant.
"""
import copy
import gc
import math
import time
from typing import Dict, Optional

import numpy as np

from .bench_stats import summary_us
from ..core.params import CONTROL_PERIOD, RobotParams
from ..core.pipeline import BalanceCore, CONTROLLER_NAMES, CoreConfig, Reference
from ..core.protocols.mit import MitProtocol
from ..core.simulation import Plant, Scenario, SmoothSchedule

LEFT_ID, RIGHT_ID = 1, 2
LEFT_DIR, RIGHT_DIR = 1.0, -1.0   # the node's default motor directions

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


def time_controller(name: str, ticks: int = 20000, seed: int = 0,
                    prototype: Optional[BalanceCore] = None) -> Dict:
    """
    Balance the simulated robot with controller ``name`` for ``ticks`` ticks, timing each.

    Returns summary_us of the per-tick wall-clock compute time (the target), 'cpu_p99_us'
    (the same ticks in thread CPU time: preemption by other processes excluded),
    'saturated_share' and 'fell'. prototype: a built BalanceCore to copy (building one solves
    the LQR schedule and places the observer poles, which takes a while).
    """
    sc = scenario(name, seed)
    dt = sc.dt
    if prototype is None:
        prototype = BalanceCore(RobotParams(), CoreConfig(), dt)
    core = copy.deepcopy(prototype)
    core.select(name)
    protocol = MitProtocol()
    plant = Plant(sc)
    v_ref, yaw_ref = SmoothSchedule(sc.x_dot_ref), SmoothSchedule(sc.yaw_rate_ref)
    std = sc.noise_std
    noise = (np.random.default_rng(seed).standard_normal((ticks, 4))
             * np.array([std[0], std[1], std[2], std[2]])).tolist()
    clock, cpu_clock = time.perf_counter_ns, time.thread_time_ns
    step, frames = core.step, protocol.torque_frames
    durations = [0] * ticks
    cpu_times = [0] * ticks
    saturated = 0
    fell = False
    gc.collect()  # the collector stays on, as in the node: its pauses belong to the tail
    for k in range(ticks):
        t = (k * dt) % DRIVE_TIME
        meas = plant.sensors(t, noise[k])
        if k == 0:
            core.reset(meas)
        ref = Reference(v_ref(t)[0], yaw_ref(t)[0])
        c0 = cpu_clock()
        t0 = clock()
        out = step(meas, ref, dt)
        frames({LEFT_ID: LEFT_DIR * out.tau_left, RIGHT_ID: RIGHT_DIR * out.tau_right})
        durations[k] = clock() - t0
        cpu_times[k] = cpu_clock() - c0
        saturated += out.saturated
        plant.advance(out.tau_left, out.tau_right, t)
        fell = fell or plant.fell
    result = summary_us(durations)
    result['cpu_p99_us'] = summary_us(cpu_times)['p99_us']
    result['saturated_share'] = saturated / ticks
    result['fell'] = bool(fell)
    return result


def run(ticks: int = 20000, seed: int = 0) -> Dict[str, Dict]:
    """Compute-time summaries {controller: {n, median_us, p99_us, max_us, ...}} for all three."""
    prototype = BalanceCore(RobotParams(), CoreConfig(), CONTROL_PERIOD)
    return {name: time_controller(name, ticks, seed, prototype) for name in CONTROLLER_NAMES}
