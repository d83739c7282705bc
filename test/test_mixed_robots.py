"""
The simulated robot on the motors builders use, two mixed robots on one bus each.

LK wheels with DaMiao hips, C620 wheels with CyberGear hips (config/*_lk_damiao.yaml,
config/*_c620_cybergear.yaml). The files over the simulation files are valid and agree
between the two nodes; sim_node's motors are each protocol's emulator with the model's
limits; the closed loop balances in lockstep (BalanceLoop against MuJoCo and the
emulators); and one mixed robot stands through the real processes (main_job --robot, short).
"""
import json
import math
import os
import pathlib
import subprocess
import sys

import pytest
from wheelleg_balance.core.config import BalanceConfig
from wheelleg_balance.core.protocols import protocol_for
from wheelleg_balance.core.schema import check, from_flat
from wheelleg_balance.sim.config import motor_protocol, SimConfig
from wheelleg_balance.validation.paper.main_job.params import installed, ROBOTS

REPO = pathlib.Path(__file__).resolve().parents[1]
#: robot -> (wheel protocol, hip protocol, wheel emulator class name, hip emulator class name)
EXPECTED = {'lk_damiao': ('lk', 'damiao', 'LkMotorEmulator', 'DamiaoMotorEmulator'),
            'c620_cybergear': ('dji_c620', 'cybergear', 'C620MotorEmulator',
                               'CybergearMotorEmulator')}


def _configs(robot):
    balance = from_flat(BalanceConfig, installed('balance_sim.yaml', 'balance_node', robot))
    sim = from_flat(SimConfig, installed('sim.yaml', 'sim_node', robot))
    return balance, sim


@pytest.mark.parametrize('robot', sorted(ROBOTS))
def test_the_files_of_each_robot_are_valid_and_the_nodes_agree(robot):
    assert set(ROBOTS) == set(EXPECTED)
    balance, sim = _configs(robot)
    assert check(balance) == [] and check(sim) == []
    wheels, hips = EXPECTED[robot][:2]
    assert (balance.can.protocol, balance.legs.protocol) == (wheels, hips)
    assert (sim.can.protocol, sim.legs.protocol) == (wheels, hips)
    assert balance.legs.command_divider == 2 and not balance.legs.channel
    assert balance.wheel_state.wheel_state_source == 'can'
    # Both sides build the same codecs: the same figures from the same sections.
    for ours, theirs in ((balance.can, sim.can), (balance.legs, sim.legs)):
        a, b = protocol_for(ours.protocol, ours), motor_protocol(theirs)
        assert type(a) is type(b) and a.reply_codes() == b.reply_codes()
        assert a.torque_limit == b.torque_limit
    # max_wheel_torque is what the wheel motor gives, no more and not far below.
    wheel = protocol_for(balance.can.protocol, balance.can)
    assert wheel.torque_limit - 0.01 <= balance.safety.max_wheel_torque <= wheel.torque_limit


@pytest.mark.parametrize('robot', sorted(ROBOTS))
def test_sim_motors_are_each_protocols_emulator_with_the_models_limits(robot):
    mujoco = pytest.importorskip('mujoco')   # noqa: F841 -- RobotSim needs it
    from wheelleg_balance.sim.robot_motors import default_specs, RobotMotors
    from wheelleg_balance.sim.robot_sim import RobotSim
    _, sim = _configs(robot)
    wheel_p, hip_p = motor_protocol(sim.can), motor_protocol(sim.legs)
    motors = RobotMotors(RobotSim(legs='motors'), default_specs(), wheel_p, hip_p)
    names = {type(e).__name__: e for e in motors.emulators.values()}
    assert set(names) == set(EXPECTED[robot][2:])
    for joint, e in motors.emulators.items():
        p = hip_p if 'leg' in joint else wheel_p
        assert e.torque_limit == pytest.approx(p.torque_limit)
    # Every wheel frame of a tick is answered by each motor it commands.
    frames = wheel_p.enable_frames([1, 2]) + wheel_p.torque_frames({1: 0.5, 2: -0.5})
    replies = [r for f in frames for r in motors.replies(f)]
    fed = [wheel_p.decode_feedback(r) for r in replies]
    assert {fb.motor_id for fb in fed if fb is not None} == {1, 2}
    # The hips answer on the same bus, in their own framing (CyberGear: 29-bit IDs).
    for f in hip_p.enable_frames([3]):
        assert all(r.is_extended_id == f.is_extended_id for r in motors.replies(f))


@pytest.mark.parametrize('robot', sorted(ROBOTS))
def test_each_mixed_robot_rises_and_stands_in_lockstep(robot):
    pytest.importorskip('mujoco')
    from wheelleg_balance.validation.lockstep import play_experiment
    flat = installed('balance_sim.yaml', 'balance_node', robot)
    params = {k: flat[k] for k in flat if k.startswith(('can.', 'legs.')) and k not in (
        'can.interface', 'can.channel', 'can.udp_port', 'legs.can.channel')}
    params['max_wheel_torque'] = flat['max_wheel_torque']
    ls = play_experiment('standing', params=params, duration=6.0)
    assert ls.mode == 1                                      # still balancing
    theta = ls.series('theta_true', ls.t0 + 2.0)
    assert max(abs(v) for v in theta) < math.radians(10.0)
    torque = ls.series('tau_left', ls.t0)
    assert max(abs(v) for v in torque) <= flat['max_wheel_torque'] + 1e-9


@pytest.mark.ros
@pytest.mark.slow
def test_a_mixed_robot_stands_through_the_real_processes(tmp_path):
    """main_job --robot c620_cybergear --only standing --short: sim_node and balance_node."""
    pid = os.getpid()
    env = dict(os.environ, ROS_DOMAIN_ID=str(1 + (pid * 11) % 100),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1',
               PYTHONPATH=str(REPO) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    out = tmp_path / 'job'
    proc = subprocess.run(
        [sys.executable, '-m', 'wheelleg_balance.validation.paper.main_job', '--robot',
         'c620_cybergear', '--only', 'standing', '--short', '--output', str(out),
         '--can-group', '239.77.%d.%d' % ((pid >> 8) % 256, pid % 256 or 1), '--udp-port',
         str(31000 + pid % 10000)],
        env=env, cwd=str(REPO), capture_output=True, text=True, timeout=400)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log
    report = json.loads((out / 'report.json').read_text())
    assert report['robot'] == 'c620_cybergear'
    (run,) = report['experiments']
    assert run['passed'], log
    load = run['can_bus_load']
    # A tick: the group frame and two feedbacks (8 bytes: 135 bits at worst each), two hip
    # frames and their replies (extended: 160 bits): 1045 bits / 2 ms = 52 % of 1 Mbit/s.
    assert load['protocol'] == 'dji_c620' and 30.0 < load['bus_load_median_pct'] < 70.0
