"""
The parameter files of one main_job run: balance_node, sim_node, and the joystick script.

balance_node and sim_node start from the installed simulation files (config/balance_sim.yaml,
config/sim.yaml: the robot folded on its tail as after power-up, six MIT motors on CAN, the
hips driven by balance_node), on a CAN group and port of this run, with main_job's settings
(it arms the robot itself, the looser timeouts of a shared machine) and the scenario's
overrides (main_job/scenarios.py); the joystick script turns the scenario's steps in m/s and
rad/s into stick deflections through teleop_node's scales and deadzone, so that teleop_node
commands the intended x_dot* and yaw rate* (validation/paper/joy_script.py plays it), and its
height presses into the height buttons of the same file.

``robot``: the motors of another simulated robot (``ROBOTS``), laid over both files:
config/balance_sim_<robot>.yaml and config/sim_<robot>.yaml (LK wheels and DaMiao hips, C620
wheels and CyberGear hips, each on one bus).
"""
import math
import pathlib
from typing import Dict, List, Tuple

import yaml

from .scenarios import ARM_AT, HOMING_S, Scenario
from ..joy_script import flatten
from ..table import IMU_OFFSET

#: balance_node's sensor and motor timeouts against sim_node on the wall clock [s] (default 0.05).
SIM_SENSOR_TIMEOUT = 0.5
#: The simulated robots' motors beside the default (six MIT motors): robot -> what it has.
ROBOTS = {'lk_damiao': 'LK MF9025 wheels, DaMiao DM-J6006 hips, one bus',
          'c620_cybergear': 'C620 + M3508 P19 wheels, CyberGear hips, one bus'}


def _nested(flat: Dict[str, object]) -> dict:
    """{'can.interface': x} -> {'can': {'interface': x}} for a ROS 2 parameter file."""
    out: dict = {}
    for key, value in flat.items():
        parts = key.split('.')
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
    return out


def write_params(path: pathlib.Path, node: str, flat: Dict[str, object]) -> None:
    """Write a ROS 2 parameter file for ``node`` from dotted names."""
    path.write_text(yaml.safe_dump({node: {'ros__parameters': _nested(flat)}},
                                   default_flow_style=None, sort_keys=True))


def installed(name: str, node: str, robot: str = '') -> Dict[str, object]:
    """
    Return a node's parameters from a file of the config folder, by dotted name.

    robot: one of ROBOTS, whose file (``name`` with ``_<robot>`` before .yaml) is laid over.
    """
    doc = yaml.safe_load((config_dir() / name).read_text())
    flat = flatten(doc[node]['ros__parameters'])
    if robot:
        if robot not in ROBOTS:
            raise ValueError('no simulated robot %r (one of %s)' % (robot, ', '.join(ROBOTS)))
        over = yaml.safe_load((config_dir() / name.replace('.yaml', '_%s.yaml' % robot))
                              .read_text())
        flat.update(flatten(over[node]['ros__parameters']))
    return flat


def balance_params(can_group: str, udp_port: int, exp: Scenario,
                   lockstep: bool = True, robot: str = '') -> Dict[str, object]:
    """
    balance_node parameters: config/balance_sim.yaml on this run's bus, the scenario's.

    lockstep: the loop ticks on sim_node's IMU stamps (``clock_source: imu_stamp``); robot:
    one of ROBOTS ('' the default).
    """
    flat = installed('balance_sim.yaml', 'balance_node', robot)
    flat.update({
        'controller': exp.controller,
        'can.channel': can_group, 'can.udp_port': udp_port,
        # main_job arms at ARM_AT, once every node is up.
        'auto_arm': False,
        'state_publish_rate': 100.0,
        'clock_source': 'imu_stamp' if lockstep else 'wall',
    })
    if not lockstep:
        # On the wall clock the simulated sensors stop with sim_node's loop when it is starved
        # of CPU (2 shared cores): a stall is no physical danger there, unlike on the robot.
        # (joint_state_timeout too: the loop's stall limit is the shorter of it and imu's.)
        # In lockstep the robot's own timeouts hold: they run on simulated time.
        flat.update(dict.fromkeys(('imu_timeout', 'joint_state_timeout', 'motor_timeout'),
                                  SIM_SENSOR_TIMEOUT))
    flat.update(exp.balance)
    return flat


def sim_time(t: float) -> float:
    """Return the sim time [s] of sim_node's events at t [s] from the start of balancing."""
    return ARM_AT + HOMING_S + t


def sim_params(can_group: str, udp_port: int, exp: Scenario,
               lockstep: bool = True, robot: str = '') -> Dict[str, object]:
    """sim_node parameters: config/sim.yaml (robot's over it) on this bus, d, the scenario."""
    flat = installed('sim.yaml', 'sim_node', robot)
    flat.update({
        'can.channel': can_group, 'can.udp_port': udp_port,
        'imu_pitch_offset': IMU_OFFSET, 'initial_pose': 'folded', 'ground_truth_rate': 100.0,
        'lockstep': lockstep,
    })
    if exp.pushes:
        flat['pushes'] = [v for t, d, fx, fy in exp.pushes for v in (sim_time(t), d, fx, fy)]
    flat.update(exp.sim)
    return flat


def config_dir() -> pathlib.Path:
    """Return the package's config/ folder: next to the sources, else the installed share/."""
    # This file is <repo>/wheelleg_balance/validation/paper/main_job/params.py.
    here = pathlib.Path(__file__).resolve().parents[4] / 'config'
    if here.is_dir():
        return here
    from ament_index_python.packages import get_package_share_directory
    return pathlib.Path(get_package_share_directory('wheelleg_balance')) / 'config'


def teleop_scales(path: pathlib.Path) -> Dict[str, float]:
    """Read the teleop_node scales and deadzone from a parameter file."""
    p = flatten(yaml.safe_load(path.read_text())['teleop_node']['ros__parameters'])
    return {k: float(p[k]) for k in ('scale_linear.x', 'scale_linear_turbo.x',
                                     'scale_angular.yaw', 'scale_angular_turbo.yaw',
                                     'deadzone')}


def stick(value: float, scale: float, deadzone: float) -> float:
    """
    Return the stick deflection that makes teleop_node command ``value`` at ``scale``.

    Inverts core/teleop.py's rescaled deadzone: value = sign (|a| - dz) / (1 - dz) scale.
    """
    if value == 0.0:
        return 0.0
    frac = abs(value / scale)
    if frac > 1.0 + 1e-9:
        raise ValueError('%g is beyond the stick scale %g' % (value, scale))
    return round(math.copysign(deadzone + min(frac, 1.0) * (1.0 - deadzone), value / scale), 4)


def joy_script_doc(exp: Scenario, scales: Dict[str, float]) -> dict:
    """Return the experiment's joystick steps as a joy_script file (deflections, presses)."""
    steps = []
    turbo = False
    v = w = 0.0
    for s in exp.joy:
        turbo = s.get('turbo', turbo)
        v, w = s.get('v', v), s.get('w', w)
        sx = scales['scale_linear_turbo.x' if turbo else 'scale_linear.x']
        sw = scales['scale_angular_turbo.yaw' if turbo else 'scale_angular.yaw']
        step = {'t': s['t'], 'linear': stick(v, sx, scales['deadzone']),
                'yaw': stick(w, sw, scales['deadzone']), 'turbo': bool(turbo)}
        if s.get('height') is not None:
            step['height'] = float(s['height'])
        steps.append(step)
    return {'end': exp.joy_end, 'steps': steps}


def joy_segments(exp: Scenario) -> List[Tuple[float, float, float, float]]:
    """(t0, t1, v, w) of the joystick script in physical units (held values, merged)."""
    out: List[Tuple[float, float, float, float]] = []
    v = w = 0.0
    for s, nxt in zip(exp.joy, exp.joy[1:] + [{'t': exp.joy_end}]):
        v, w = s.get('v', v), s.get('w', w)
        if out and out[-1][2:] == (v, w):
            out[-1] = (out[-1][0], nxt['t'], v, w)   # a button press between: one segment
        else:
            out.append((s['t'], nxt['t'], v, w))
    return out
