"""
The identification's phases played on the MuJoCo robot in-process, recorded as records.py lays out.

Each phase drives sim/robot_sim.py RobotSim (a variant from sim_node's ``robot.*``,
sim/config.RobotBodyConfig) tick by tick at the control period and records what balance_node
would: the IMU, the joint states (wheels forward positive relative to the leg, hips in
FiveBarLeg's convention) and the state's commanded wheel torques and height. Within a tick,
as in balance_node, the sensors are read, then the torques commanded, then the physics advances
one period; the commands reach the wheels after ``robot.motor_delay``.

- ``stand``: the body held on the stand (a weld), legs held by the servos, wheels free; torque
  steps then a chirp on each wheel;
- ``tail``: resting on the tail at the lowest height; small torque pulses both ways, the body
  staying on its tail (checked: the phase raises otherwise);
- ``balance``: the package's own control tick (validation/lockstep.py: core/balance_loop.py
  and the wheel motors' emulators) balancing; at each height of ``heights`` a chirp in
  x_dot*, the legs held there by the simulator's stiff servos. The heights are separate runs
  here: with the driven legs (hip impedance, 60 N m/rad) the body moves on its legs while it
  balances, which the fit's rigid pendulum does not model (measured: m l off by half).
"""
import math
from typing import Dict, Optional, Sequence

import numpy as np

from .records import IMU, IMU_COLUMNS, joint_columns, JOINTS, Record, SeriesBuilder, STATE
# The programs are the tick's (core/excitation.py, balance_node's excitation plays them too).
from ..core.excitation import chirp, HEIGHTS, PERIOD, stand_torques, \
    tail_torques  # noqa: F401
from ..core.tick_io import STATE_FIELDS
from ..sim.config import RobotBodyConfig
from ..sim.layout import LEG_JOINTS, WHEEL_JOINTS

#: The time between the balance phase's runs (one per height) in the Record [s].
GAP = 1.0
#: Joints recorded: the wheels, then the hips.
JOINT_NAMES = WHEEL_JOINTS + LEG_JOINTS


class _Recorder:
    """The three topics of a Record, filled once a tick."""

    def __init__(self, phase: str):
        self.phase = phase
        self.imu = SeriesBuilder(IMU_COLUMNS)
        self.joints = SeriesBuilder(joint_columns(JOINT_NAMES))
        self.state = SeriesBuilder(STATE_FIELDS)

    def sample(self, t: float, sim) -> None:
        (qx, qy, qz, qw), gyro, accel = sim.imu()
        self.imu.add(t, (qx, qy, qz, qw) + tuple(gyro) + tuple(accel))
        efforts = list(sim.wheel_torques()) + list(sim.leg_torques())
        self.joints.add(t, list(sim.wheel_angles()) + list(sim.leg_angles())
                        + list(sim.wheel_velocities()) + list(sim.leg_velocities()) + efforts)

    def command(self, t: float, values: Dict[str, float]) -> None:
        row = dict(values, time=t)   # the tick's time, as balance_node's ~/state has it
        self.state.add(t, [row.get(n, math.nan) for n in STATE_FIELDS])

    def record(self) -> Record:
        return Record(self.phase, {IMU: self.imu.series(), JOINTS: self.joints.series(),
                                   STATE: self.state.series()})


def play_stand(body: RobotBodyConfig, d_offset: float = 0.0,
               duration: float = 3.0) -> Record:
    """Return the ``stand`` phase's Record (see the module docstring)."""
    from ..sim.robot_sim import RobotSim
    sim = RobotSim(d_offset=d_offset, body=body)
    sim.hold(pitch=0.0, z=1.0)
    sim.step(0.0, 0.0, 0.5)   # the legs settle on the stand
    rec = _Recorder('stand')
    for k, (left, right) in enumerate(stand_torques(duration)):
        t = k * PERIOD
        rec.sample(t, sim)
        rec.command(t, {'tau_left': left, 'tau_right': right, 'mode': 0.0})
        sim.step(left, right, PERIOD)
    return rec.record()


def play_tail(body: RobotBodyConfig, d_offset: float = 0.0, duration: float = 3.0,
              height: float = 0.37) -> Record:
    """Return the ``tail`` phase's Record; raises RuntimeError when the body left the tail."""
    from ..sim.robot_sim import RobotSim
    sim = RobotSim(d_offset=d_offset, height=height, body=body)
    sim.reset('tail', settle=0.5)
    rec = _Recorder('tail')
    for k, (left, right) in enumerate(tail_torques(duration)):
        t = k * PERIOD
        rec.sample(t, sim)
        rec.command(t, {'tau_left': left, 'tau_right': right, 'mode': 0.0, 'l': height})
        sim.step(left, right, PERIOD)
        if sim.ground_truth()['tail_contact'] < 0.5 and sim.tail_clearance() > 1e-3:
            raise RuntimeError('the body left its tail at %.2f s: smaller pulses' % t)
    return rec.record()


def play_balance(body: RobotBodyConfig, d_offset: float = 0.0,
                 heights: Sequence[float] = HEIGHTS, settle: float = 1.0, sweep: float = 3.0,
                 amplitude: float = 0.25, params: Optional[Dict] = None) -> Record:
    """
    Return the ``balance`` phase's Record: at each height, balancing, then a chirp in x_dot*.

    Per height [m] one run of the package's control tick (validation/lockstep.py) with the
    legs held at that height by the simulator's stiff servos (``legs.driven: false``,
    balance_node's ``height``), armed upright; ``settle`` s still, then ``sweep`` s of x_dot* =
    amplitude [m/s] times a chirp from 0.3 to 1.5 Hz. The runs follow each other in the
    Record with a gap of GAP s (the fit leaves the samples by a gap out). params:
    balance_node parameters beyond these. Raises RuntimeError when a run does not balance or
    falls.
    """
    from ..validation.lockstep import Lockstep
    rec = _Recorder('balance')
    n_settle, n_sweep = int(round(settle / PERIOD)), int(round(sweep / PERIOD))
    every = max(1, int(round(0.02 / PERIOD)))   # cmd_vel at teleop_node's 50 Hz
    start = 0.0
    for l in heights:
        flat = dict({'controller': 'auto', 'legs.driven': False, 'height': l}, **(params or {}))
        ls = Lockstep(flat, pose='pitch', imu_offset=d_offset, height=l, body=body)
        ls.run(0.02)   # the sensors and the motors' replies are fresh
        ls.arm(True)
        ls.run(1.0, until=lambda: ls.mode == 1)   # Mode.BALANCING
        if ls.mode != 1:
            raise RuntimeError('did not start balancing at %.2f m: %s' % (l, ls.arm_replies))
        offset = start - ls.t
        for k in range(n_settle + n_sweep):
            if k >= n_settle and k % every == 0:
                s = (k - n_settle) * PERIOD
                ls.command(amplitude * float(chirp(np.array([s]), 0.3, 1.5, sweep)[0]))
            t = ls.t + offset
            rec.sample(t, ls.sim)
            ls.tick()
            row = ls.log[-1]
            rec.command(t, {n: row[n] for n in ('tau_left', 'tau_right', 'l', 'mode', 'd_hat',
                                                'x_dot')})
            if ls.mode != 1:
                raise RuntimeError('stopped balancing at %.2f m: %s' % (l, ls.events[-3:]))
        start = ls.t + offset + GAP
    return rec.record()


def play_all(body: RobotBodyConfig, d_offset: float = 0.0,
             heights: Sequence[float] = HEIGHTS) -> Dict[str, Record]:
    """Return the three phases' Records of a robot variant (stand, tail, balance)."""
    return {'stand': play_stand(body, d_offset), 'tail': play_tail(body, d_offset),
            'balance': play_balance(body, d_offset, heights)}
