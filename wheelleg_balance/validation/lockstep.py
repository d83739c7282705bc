"""
The whole robot in lockstep: the control tick against the MuJoCo robot and its six motors.

``Lockstep`` runs core/balance_loop.py's BalanceLoop, tick by tick on simulated time, against
sim/robot_sim.py (hips as torque motors) and sim/robot_motors.py (one MIT firmware emulator per
joint; with ``legs.driven: false`` the legs are the simulator's position servos at the given
height, the robot's fixed legs, and only the wheels have motors): the tick's frames go to the
emulators, their replies (the true joint states, quantized as the firmware packs them) come
back as the next tick's frames, and the IMU sample is the simulated one. No ROS, no bus, no
wall clock: deterministic, faster than real time. It is the offline twin of main_job's
sim_node + balance_node, for tests and tuning. ``play_experiment`` plays one of main_job's
experiments on it, with driven or fixed legs.
"""
import math
from typing import Callable, Dict, List, Optional

from ..core.balance_loop import BalanceLoop, CmdHeight, CmdVel, TickInputs
from ..core.config import BalanceConfig
from ..core.protocols import protocol_for
from ..core.schema import check, from_flat
from ..core.sensors import ImuSample
from ..sim.robot_motors import default_specs, RobotMotors
from ..sim.robot_sim import RobotSim

#: balance_node's parameters for the simulated robot's six motors (config/balance_sim.yaml).
SIM_PARAMS = {'legs.driven': True, 'legs.motor_ids': [3, 4, 5, 6]}


class Lockstep:
    """
    BalanceLoop + RobotSim + RobotMotors (see the module docstring).

    params: balance_node parameter overrides (SIM_PARAMS first; ``legs.driven: False`` for
    fixed legs: RobotSim's servos hold ``height``); pose: RobotSim.reset's ('folded', after
    power-up, by default; 'tail' with fixed legs, which cannot fold);
    imu_offset: the IMU's pitch offset d [rad]; power_up: the hips know their angle only
    modulo a rotor turn (then ``legs.homing: hard_stops`` is needed); sim: further RobotSim
    arguments (pushes, slope, ...).
    """

    def __init__(self, params: Optional[Dict] = None, pose: Optional[str] = None,
                 imu_offset: float = 0.0, power_up: bool = False, height: float = 0.37,
                 **sim):
        cfg = from_flat(BalanceConfig, dict(SIM_PARAMS, **(params or {})))
        problems = check(cfg)
        if problems:
            raise ValueError('; '.join(problems))
        self.cfg = cfg
        self.loop = BalanceLoop(cfg)
        driven = cfg.legs.driven
        self.sim = RobotSim(d_offset=imu_offset, height=height,
                            legs='motors' if driven else 'servo', **sim)
        self.sim.reset(pose or ('folded' if driven else 'tail'))
        lc, can = cfg.legs, cfg.can
        self.motors = RobotMotors(self.sim, default_specs(
            (can.left_motor_id, can.right_motor_id), (can.left_direction, can.right_direction),
            tuple(lc.motor_ids), tuple(lc.directions), tuple(lc.offsets), hips=driven,
            hip_bus=1 if lc.channel and lc.channel != can.channel else 0),
            protocol_for(can.protocol, can), protocol_for(lc.protocol, lc), power_up=power_up)
        self._leg_bus = 1 if lc.channel and lc.channel != can.channel else 0
        self.period = cfg.loop.control_period
        self.t = 0.0
        #: When balancing began in a play (``play_experiment``) [s].
        self.t0: Optional[float] = None
        self.inputs = TickInputs()
        self._replies: List = []
        self._stamp = 0
        self.log: List[Dict[str, float]] = []
        self.events: List = []
        self.arm_replies: List = []
        #: CAN IDs of motors whose replies are lost (they still act on the frames).
        self.silent: set = set()

    def tick(self) -> None:
        """One control period: IMU and replies in, the tick, frames to the motors, physics."""
        t = self.t
        (qx, qy, qz, qw), gyro, accel = self.sim.imu()
        self._stamp += 1
        self.inputs.imu.append(ImuSample(t, 0, self._stamp, qx, qy, qz, qw, True, *gyro,
                                         *accel))
        self.inputs.frames.extend((t, f) for f in self._replies)
        result = self.loop.tick(t, self.inputs)
        self.inputs.clear()
        self.loop.report_send(t, None)
        motors, legs = self.motors, self._leg_bus
        self._replies = [r for f in result.frames for r in motors.replies(f)] + [
            r for f in result.leg_frames for r in motors.replies(f, legs)]
        if self.silent:   # MIT replies name their motor in byte 0
            self._replies = [r for r in self._replies if r.data[0] not in self.silent]
        if result.arm_reply is not None:
            self.arm_replies.append(result.arm_reply)
        self.events += result.events
        gt = self.sim.ground_truth()
        st = result.state
        self.log.append({'t': t, 'mode': st.mode, 'theta_true': gt['theta'],
                         'x_true': gt['x'], 'x_dot_true': gt['x_dot'], 'l_true': gt['l'],
                         'roll_true': gt['roll'], 'theta_dot_true': gt['theta_dot'],
                         'l': st.l, 'l_ref': st.l_ref, 'tau_left': st.tau_left,
                         'tau_right': st.tau_right, 'd_hat': st.d_hat, 'x_dot': st.x_dot,
                         'tail_clearance': self.sim.tail_clearance()})
        self.motors.step(self.period)
        self.t = t + self.period

    def run(self, seconds: float, events: Optional[Dict[float, Callable[[], None]]] = None,
            until: Optional[Callable[[], bool]] = None) -> None:
        """Tick for ``seconds``; ``events`` {time [s] from now: callable}; stop at ``until``."""
        pending = sorted((events or {}).items())
        t0 = self.t
        for _ in range(int(round(seconds / self.period))):
            while pending and pending[0][0] <= self.t - t0 + 1e-9:
                pending.pop(0)[1]()
            self.tick()
            if until is not None and until():
                return

    def arm(self, on: bool = True) -> None:
        """Request arming (``on``) or disarming at the next tick."""
        self.inputs.arm = on

    def command(self, x_dot: float = 0.0, yaw_rate: float = 0.0) -> None:
        """Hand a cmd_vel to the next tick."""
        self.inputs.cmd_vel = CmdVel(self.t, x_dot, yaw_rate)

    def command_height(self, l: float) -> None:
        """Hand a cmd_height [m] to the next tick."""
        self.inputs.cmd_height = CmdHeight(self.t, l)

    @property
    def mode(self) -> int:
        """Return the supervisor's mode."""
        return int(self.loop.mode)

    def series(self, name: str, since: float = -math.inf) -> List[float]:
        """Return the logged quantity ``name`` from ``since`` [s] on."""
        return [row[name] for row in self.log if row['t'] >= since]


#: How long a play waits for balancing after the arm [s] (homing and the leg raise: 2.6 s).
PLAY_START_LIMIT = 8.0


def play_experiment(name: str, driven: bool = True, params: Optional[Dict] = None,
                    duration: Optional[float] = None, imu_offset: Optional[float] = None,
                    arm_at: float = 0.5) -> Lockstep:
    """
    Play main_job's experiment ``name`` in lockstep (validation/paper/main_job/scenarios.py).

    The scenario's controller and balance_node parameters, its terrain (bumps, the ramp), its
    pushes, joystick (as cmd_vel in physical units; the height buttons as cmd_height) and
    actions (parameter changes, disarm, re-arm, ~/stop), timed from the start of balancing as
    main_job times them; the IMU offset d of main_job (table.IMU_OFFSET) unless given. driven:
    False plays it with fixed legs (the scenario's ``legs.*`` parameters dropped, no height
    commands). Armed at ``arm_at`` [s]; the run ends ``duration`` [s] (the scenario's by
    default) after balancing began, which is ``Lockstep.t0``. Raises RuntimeError when it does
    not start balancing.
    """
    from .paper.main_job.params import joy_segments
    from .paper.main_job.scenarios import BY_NAME
    from .paper.table import IMU_OFFSET
    from ..sim.robot_sim import Push, Slope
    sc = BY_NAME[name]
    flat = dict({'controller': sc.controller}, **sc.balance)
    if not driven:
        flat = {k: v for k, v in flat.items() if not k.startswith('legs.')}
        flat['legs.driven'] = False
    flat.update(params or {})
    sim = {}
    if 'bumps' in sc.sim:
        sim['bumps'], sim['bump_height'] = sc.sim['bumps'], sc.sim['bump_height']
    if sc.sim.get('slope.enabled'):
        sim['slope'] = Slope(sc.sim['slope.start_x'], sc.sim['slope.length'],
                             sc.sim['slope.angle'], sc.sim['slope.side'])
    ls = Lockstep(flat, imu_offset=IMU_OFFSET if imu_offset is None else imu_offset, **sim)
    ls.run(arm_at)
    ls.arm(True)
    ls.run(PLAY_START_LIMIT, until=lambda: ls.mode == 1)   # Mode.BALANCING
    if ls.mode != 1:
        raise RuntimeError('%s did not start balancing: %s' % (name, ls.events))
    ls.t0 = t0 = ls.t
    pushes = sorted(sc.pushes)
    segments = joy_segments(sc) if sc.joy else []
    heights = list(sc.height_presses) if driven else []
    actions = sorted(sc.actions, key=lambda a: a[0])
    steps_per_cmd = max(1, int(round(0.02 / ls.period)))   # teleop_node's 50 Hz
    for k in range(int(round((duration or sc.duration) / ls.period))):
        t = ls.t - t0 + 1e-9
        while pushes and pushes[0][0] <= t:
            _, length, fx, fy = pushes.pop(0)
            ls.sim.pushes.append(Push(ls.sim.time, length, fx, fy))
        held = [(v, w) for a, b, v, w in segments if a <= t < b]
        if held and k % steps_per_cmd == 0:
            ls.command(*held[0])
        while heights and heights[0][0] <= t:
            ls.command_height(heights.pop(0)[1])
        while actions and actions[0][0] <= t:
            _, action, value = actions.pop(0)
            if action == 'arm':
                ls.arm(value)
            elif action == 'stop':
                ls.inputs.estop = True
            else:
                ls.loop.apply_parameters({action: value})
        ls.tick()
    return ls
