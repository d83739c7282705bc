"""
A second publisher on an input (nodes/input_guard.py) and what the tick does with the verdict.

The whole path (balance_node's graph check, a rogue node on imu or cmd_vel, the reaction on
the bus) is in test_faults.py (second_imu_publisher, second_cmd_vel_publisher).
"""
import math

import pytest

from wheelleg_balance.core.balance_loop import CmdVel
from wheelleg_balance.nodes.input_guard import conflicts, full_name, judge
from wheelleg_balance.validation.faults.bench import is_zero_torque, LoopBench, MODE

DRIVER = ('/robot', 'imu_driver')
ROGUE = ('/', 'rosbag2_player')


def test_full_names():
    assert full_name('/', 'a') == '/a'
    assert full_name('/robot', 'a') == '/robot/a'
    assert full_name('', 'a') == '/a'


def test_one_publisher_of_any_name_is_fine_unless_a_driver_is_named():
    assert judge('/imu', [DRIVER]) is None
    assert judge('/imu', []) is None          # silence is the timeouts' business
    assert judge('/imu', [DRIVER, DRIVER]) is None   # one node, two publishers
    assert judge('/imu', [DRIVER], allowed='imu_driver') is None
    assert judge('/imu', [DRIVER], allowed='/robot/imu_driver') is None
    why = judge('/imu', [DRIVER], allowed='/other/imu_driver')
    assert why is not None and '/robot/imu_driver' in why


def test_a_second_node_is_refused_and_named():
    why = judge('/imu', [DRIVER, ROGUE])
    assert why is not None and '2 publishers' in why
    assert '/robot/imu_driver' in why and '/rosbag2_player' in why
    why = judge('/imu', [DRIVER, ROGUE], allowed='imu_driver')
    assert why is not None and '/rosbag2_player' in why and '/robot/imu_driver' not in why


def test_conflicts_per_input():
    graph = {'/imu': [DRIVER, ROGUE], '/cmd_vel': [('/', 'teleop_node')]}
    found = conflicts(lambda t: graph.get(t, []), {'imu': '/imu', 'cmd_vel': '/cmd_vel'},
                      {'imu': '', 'cmd_vel': 'teleop_node'})
    assert set(found) == {'imu'}


def _balancing():
    bench = LoopBench()
    bench.feed()
    bench.rearm()
    assert bench.mode == MODE['BALANCING']
    return bench


@pytest.mark.parametrize('key', ['imu', 'joint_states'])
def test_a_sensor_conflict_faults_at_the_next_tick_and_blocks_arming(key):
    bench = _balancing()
    bench.inputs.conflicts = {key: '%s has 2 publishers' % key}
    bench.feed()
    frames = bench.tick()
    assert bench.mode == MODE['FAULT']
    assert frames and all(is_zero_torque(f) for _, f in frames)
    assert 'input_conflict' in [c for c, _ in bench.safety_values()['faults']]
    bench.feed()
    req = bench.request(True)
    bench.tick()
    assert not req.success and '2 publishers' in req.message
    bench.inputs.conflicts = {}
    bench.feed()
    req = bench.request(True)
    bench.tick()
    assert req.success, req.message


def test_auto_arm_waits_for_a_sensor_conflict_to_end():
    bench = LoopBench(auto_arm=True)
    bench.inputs.conflicts = {'imu': 'imu has 2 publishers'}
    for _ in range(50):
        bench.feed()
        bench.tick()
    assert bench.mode == MODE['DISARMED']
    bench.inputs.conflicts = {}
    bench.feed()
    bench.tick()
    assert bench.mode == MODE['BALANCING']


def test_a_command_conflict_drops_the_command_and_balancing_goes_on():
    bench = _balancing()
    bench.inputs.conflicts = {'cmd_vel': 'cmd_vel has 2 publishers'}
    rejected = bench.rejected_cmd_vel
    for _ in range(50):
        bench.inputs.cmd_vel = CmdVel(bench.t, 0.5, 0.0)
        bench.feed()
        bench.tick()
    assert bench.mode == MODE['BALANCING']
    assert bench.rejected_cmd_vel == rejected + 50
    assert bench.loop.shaper.x_dot_ref == 0.0
    assert 'cmd_vel has 2 publishers' in bench.safety_values()['input_conflicts']
    bench.inputs.conflicts = {}
    for _ in range(50):
        bench.inputs.cmd_vel = CmdVel(bench.t, 0.5, 0.0)
        bench.feed()
        bench.tick()
    assert bench.loop.shaper.x_dot_ref > 0.0 and math.isfinite(bench.loop.shaper.x_dot_ref)
