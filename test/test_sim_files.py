"""
The installed simulation files: sim_node on config/sim.yaml, balance_node on balance_sim.yaml.

Both run as separate processes from the very files setup.py installs, as a user runs them:

    sim_node --ros-args --params-file config/sim.yaml
    balance_node --ros-args --params-file config/balance_sim.yaml

with two kinds of overrides. The CAN group and port are this run's, so that parallel runs do
not meet on the bus. And the pair runs in lockstep (sim_node ``lockstep``, balance_node
``clock_source: imu_stamp``, as main_job runs them): on the wall clock a CI machine that ran
another job beside this one starved both loops and the robot swayed to 5.6 deg, a figure of the
machine, not of the files. ``lockstep_timeout`` is its largest, 10 s, so that sim_node waits for
a starved balance_node rather than step on without its torques.

From sim_node's ground truth, not from balance_node's word: the robot, folded on its tail as
after power-up, is lifted (auto_arm: homing, legs raised, stand-up) and held upright off the
tail, and a cmd_height takes it to the commanded height. launch/sim.launch.py starts the same
pair with teleop_node: it is checked by reading it (the launch packages are not installed
here).
"""
import ast
import math
import os
import pathlib
import re
import signal
import subprocess
import sys
import time

import pytest

from wheelleg_balance.processes import end_process

REPO = pathlib.Path(__file__).resolve().parents[1]
CONFIG = REPO / 'config'
#: How long the nodes may take to start and the robot to stand up, wall clock [s] (a loaded
#: machine: the stand-up itself takes about 3 s of sim time after homing).
STAND_TIMEOUT = 60.0
#: How long a few seconds of sim time may take, wall clock [s] (lockstep on a loaded machine:
#: real-time factors down to 0.27 were seen in main_job).
SIM_TIMEOUT = 60.0


def _start(module, params, overrides, env, log):
    args = [sys.executable, '-m', module, '--ros-args', '--params-file', str(params)]
    for name, value in overrides.items():
        args += ['-p', '%s:=%s' % (name, value)]
    return subprocess.Popen(args, env=env, stdout=log, stderr=subprocess.STDOUT)


@pytest.mark.ros
@pytest.mark.slow
def test_the_installed_sim_files_lift_and_hold_the_robot(tmp_path):
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from std_msgs.msg import Float64, Float64MultiArray

    pid = os.getpid()
    domain = 1 + (pid * 13 + 3) % 100
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               PYTHONUNBUFFERED='1',
               PYTHONPATH=str(REPO) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    bus = {'can.channel': '239.76.%d.%d' % ((pid >> 8) % 256, pid % 256 or 1),
           'can.udp_port': str(20000 + pid % 10000)}
    sim_lockstep = dict(bus, lockstep='true', lockstep_timeout='10.0')
    balance_lockstep = dict(bus, clock_source='imu_stamp')
    logs = {n: open(tmp_path / ('%s.log' % n), 'w') for n in ('sim_node', 'balance_node')}
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    gt, state = [], []

    def rows(store):
        def on(msg):
            store.append(dict(zip(msg.layout.dim[0].label.split(','), msg.data)))
        return on

    # The robot's start is seen before balance_node moves it: sim_node alone first, until its
    # ground truth arrives (alone it lies folded on the tail, still). Discovery takes up to
    # about 3 s (docs/benchmarks.md); with both started at once, the first sample came 2.4 s
    # of sim time in, the legs homed and raised by then (CI, 2026-12-07).
    node = rclpy.create_node('sim_files_test', context=ctx)
    node.create_subscription(Float64MultiArray, 'sim_node/ground_truth', rows(gt), 100)
    node.create_subscription(Float64MultiArray, 'balance_node/state', rows(state), 100)
    height = node.create_publisher(Float64, 'cmd_height', 10)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    procs = []
    try:
        procs.append(_start('wheelleg_balance.nodes.sim_node', CONFIG / 'sim.yaml',
                            sim_lockstep, env, logs['sim_node']))

        def spin_until(done, timeout):
            end = time.monotonic() + timeout
            while not done() and time.monotonic() < end and all(
                    p.poll() is None for p in procs):
                executor.spin_once(timeout_sec=0.05)
            return done()

        def sim_time():
            return gt[-1]['time'] if gt else -1.0

        assert spin_until(lambda: gt, 30.0), 'no ground truth'
        first = gt[0]
        assert first['tail_contact'] == 1.0 and first['l'] < 0.30, first   # folded on the tail
        # Nobody arms it: balance_node's auto_arm homes, raises and stands the robot up.
        procs.append(_start('wheelleg_balance.nodes.balance_node', CONFIG / 'balance_sim.yaml',
                            balance_lockstep, env, logs['balance_node']))
        assert spin_until(lambda: state, 30.0), 'no state'
        assert spin_until(lambda: state[-1]['mode'] == 1.0, STAND_TIMEOUT), \
            'never balancing: mode %s' % state[-1]['mode']
        t_bal = sim_time()
        assert spin_until(lambda: sim_time() > t_bal + 6.0, SIM_TIMEOUT)
        held = [g for g in gt if g['time'] > t_bal + 4.0]
        # Held upright off the tail at height_min (0.37 m) for the last 2 s.
        assert max(abs(math.degrees(g['theta'])) for g in held) < 5.0
        assert not any(g['tail_contact'] or g['body_contact'] for g in held)
        assert all(abs(g['l'] - 0.37) < 0.02 for g in held)

        # cmd_height: the hips take the body up to 0.55 m (0.1 m/s: about 2 s).
        t_cmd = sim_time()

        def risen():
            height.publish(Float64(data=0.55))
            return bool(gt) and abs(gt[-1]['l'] - 0.55) < 0.01 and sim_time() > t_cmd + 3.0
        assert spin_until(risen, SIM_TIMEOUT), 'l %.3f' % gt[-1]['l']
        assert state[-1]['mode'] == 1.0 and state[-1]['l_ref'] == pytest.approx(0.55, abs=1e-3)
        assert max(abs(math.degrees(g['theta'])) for g in gt if g['time'] > t_cmd) < 10.0
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
        for p in procs:
            end_process(p, signal.SIGINT, 10.0)
        for f in logs.values():
            f.close()
    for name in logs:
        assert 'Traceback' not in (tmp_path / ('%s.log' % name)).read_text(), name
    # Lockstep held: no tick of the physics went on without balance_node's torques.
    stopped = re.search(r'real-time factor ([\d.]+), (\d+) lockstep timeouts',
                        (tmp_path / 'sim_node.log').read_text())
    assert stopped and int(stopped.group(2)) == 0, stopped and stopped.group(0)


def test_the_sim_launch_file_starts_the_pair_with_teleop_on_the_installed_files():
    path = REPO / 'launch' / 'sim.launch.py'
    tree = ast.parse(path.read_text())
    # Module level: the standard library only (launch, launch_ros come in the function).
    top = {a.name.split('.')[0] for n in tree.body if isinstance(n, ast.Import) for a in n.names}
    top |= {n.module.split('.')[0] for n in tree.body if isinstance(n, ast.ImportFrom)}
    assert top <= set(sys.stdlib_module_names), top
    assert 'generate_launch_description' in {n.name for n in tree.body
                                             if isinstance(n, ast.FunctionDef)}
    strings = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant)
               and isinstance(n.value, str)}
    setup = (REPO / 'setup.py').read_text()
    for exe in ('sim_node', 'balance_node', 'teleop_node'):
        assert exe in strings and "'%s = " % exe in setup
    for name in ('sim.yaml', 'balance_sim.yaml'):
        assert name in strings and (CONFIG / name).is_file()
    choices = next(ast.literal_eval(n.value) for n in ast.walk(tree)
                   if isinstance(n, ast.Assign) and getattr(n.targets[0], 'id', '') ==
                   'JOYSTICKS')
    for joystick in choices:
        assert (CONFIG / ('teleop_%s.yaml' % joystick)).is_file()
    assert {'joy', 'game_controller_node'} <= strings
    assert "glob('config/*.yaml')" in setup and "glob('launch/*.launch.py')" in setup
