"""
The benchmark command and its helpers (no timing targets here: these machines are shared).

The quick run checks the report's structure and that every figure is positive and finite; the
statistics are checked on event series whose answer is known by construction; the real-time
helpers must return a clean (ok, message) whatever the machine allows.
"""
import io
import json
import math
import os
import pathlib
import shutil
import subprocess
import sys
import threading

import numpy as np
import pytest

from wheelleg_balance.core import realtime
from wheelleg_balance.core.pipeline import CONTROLLER_NAMES
from wheelleg_balance.validation.bench import benchmark, bus as bench_bus, \
    profiling as bench_profile, replay as bench_replay
from wheelleg_balance.validation.bench.node import probe_latencies
from wheelleg_balance.validation.bench.stats import period_stats, served_deadlines

REPO = pathlib.Path(__file__).resolve().parents[1]
MS = 1_000_000


def _positive_finite(value) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value) and value > 0


# ------------------------------------------------------------------------------ quick run

@pytest.fixture(scope='module')
def quick_report(tmp_path_factory):
    out = tmp_path_factory.mktemp('bench') / 'sub' / 'benchmark.json'
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join(p for p in (str(REPO), env.get('PYTHONPATH')) if p)
    proc = subprocess.run(
        [sys.executable, '-m', 'wheelleg_balance.validation.bench.benchmark', '--quick',
         '--parts', 'core,floor', '--output', str(out)],
        env=env, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    with open(out) as f:
        return json.load(f), proc.stdout


def test_quick_report_structure(quick_report):
    report, stdout = quick_report
    assert report['errors'] == {}
    assert report['settings']['quick'] is True
    assert report['settings']['parts'] == ['core', 'floor']
    assert 'baseline' not in report and 'node' not in report
    assert report['machine']['cpus'] >= 1
    assert set(report['core']) == set(CONTROLLER_NAMES)
    # The table names every controller and the floor.
    for name in CONTROLLER_NAMES + ('floor',):
        assert name in stdout


def test_quick_core_figures(quick_report):
    report, _ = quick_report
    for name, core in report['core'].items():
        assert core['n'] == 2000, name
        for key in ('median_us', 'p99_us', 'max_us', 'cpu_p99_us'):
            assert _positive_finite(core[key]), (name, key, core[key])
        assert core['median_us'] <= core['p99_us'] <= core['max_us']
        assert core['fell'] is False, name  # the timed ticks really balanced the robot
    rows = {t['name']: t for t in report['targets']}
    for name in CONTROLLER_NAMES:
        row = rows['core tick p99 %s' % name]
        assert row['value'] == report['core'][name]['p99_us']
        assert row['pass'] == (row['value'] < benchmark.TICK_P99_US)


def test_quick_floor_figures(quick_report):
    report, _ = quick_report
    floor = report['floor']
    for key in ('rate_hz', 'duration_s', 'period_median_ms', 'period_p99_ms', 'period_p999_ms',
                'period_max_ms', 'cpu_percent', 'n', 'deadlines'):
        assert _positive_finite(floor[key]), (key, floor[key])
    assert floor['period_median_ms'] <= floor['period_p99_ms'] <= floor['period_p999_ms'] \
        <= floor['period_max_ms']
    for key in ('late_share', 'own_late_share'):
        assert 0.0 <= floor[key] <= 1.0
    assert floor['duration_s'] > 2.0  # --quick: 3 s


# ---------------------------------------------------------------------------- statistics

def test_perfect_grid():
    t = np.arange(1000, dtype=np.int64) * 2 * MS + 123
    s = period_stats(t)
    assert s['rate_hz'] == pytest.approx(500.0)
    assert s['period_p99_ms'] == pytest.approx(2.0)
    assert s['late_share'] == 0.0
    assert s['deadlines'] == 999


def _wake_jitter(n, seed=0):
    # On-time ticks wake 20..200 us after their deadline, as a sleeping loop does.
    return np.random.default_rng(seed).integers(20_000, 200_000, n)


def test_catch_up_loop_stall():
    # A loop that catches up: tick 100 comes 5.3 ms late, the two after it 3.3 and 1.3 ms late
    # (back-to-back), then it is on time again. Three deadlines missed by more than 1 ms.
    t = np.arange(1000, dtype=np.int64) * 2 * MS + _wake_jitter(1000)
    stall_end = t[100] + 5_300_000
    for k in (100, 101, 102):
        t[k] = stall_end + (k - 100) * 10_000
    served, total = served_deadlines(t)
    assert total - served == 3
    s = period_stats(t)
    assert s['period_max_ms'] == pytest.approx((t[100] - t[99]) / MS)
    assert s['late_share'] == pytest.approx(3 / s['deadlines'])


def test_skipping_loop_counts_skipped_deadlines():
    # A loop that skips: 4 deadlines with no tick at all, every other tick on time.
    grid = np.arange(1000, dtype=np.int64) * 2 * MS
    t = np.delete(grid + _wake_jitter(1000), [300, 301, 302, 303])
    s = period_stats(t)
    assert s['missed_deadlines'] == 4
    assert s['rate_hz'] == pytest.approx(995e9 / (t[-1] - t[0]))


def test_late_threshold_and_phase():
    # The grid's phase is not known from outside: a constant offset is a phase, nothing late.
    base = np.arange(2000, dtype=np.int64) * 2 * MS + 777_777
    assert period_stats(base + 1_400_000)['late_share'] == 0.0
    # Ticks alternately on time and 1.5 ms late: no phase serves more than every other deadline.
    jitter = np.where(np.arange(2000) % 2 == 0, 0, 1_500_000)
    share = period_stats(base + jitter)['late_share']
    assert share == pytest.approx(0.5, abs=0.01)


def _probe_run(delay_ns, stall=None):
    """Frames every 2 ms; each toggle's level shows in the first frame delay_ns after it."""
    frames = np.arange(5000, dtype=np.int64) * 2 * MS
    toggles = np.arange(10, 490, dtype=np.int64) * 20 * MS + 300_000  # between frames
    levels = np.where(np.arange(toggles.size) % 2 == 0, 1, -1)
    tau = np.zeros(frames.size)
    for p, level in zip(toggles, levels):
        tau[frames >= p + delay_ns] = 0.64 * level
    if stall is not None:  # no frames at all in [stall[0], stall[1])
        keep = (frames < stall[0]) | (frames >= stall[1])
        frames, tau = frames[keep], tau[keep]
    return toggles, levels, frames, tau


def test_probe_latencies_recover_known_delay():
    lat = probe_latencies(*_probe_run(1_500_000))
    # Toggle at 20 k ms + 0.3 ms, new torque from 20 k ms + 1.8 ms: the frame at 20 k + 2 ms.
    assert np.all(np.isfinite(lat))
    assert np.allclose(lat, 1_700_000)


def test_probe_lost_in_a_stall():
    # The node sends nothing from just before toggle 100 until after toggle 101: probe 100's
    # level never reaches the bus, it is lost; probe 101 is late by the rest of the stall.
    toggles, levels, frames, tau = _probe_run(1_500_000)
    stall = (toggles[100] - 1 * MS, toggles[101] + 5 * MS)
    lat = probe_latencies(toggles, levels, *_probe_run(1_500_000, stall)[2:])
    assert np.isinf(lat[100])
    assert lat[101] == pytest.approx(5.7 * MS)
    assert np.allclose(np.delete(lat, [100, 101]), 1_700_000)


def test_probe_without_step_is_not_measured():
    toggles, levels, frames, _ = _probe_run(1_500_000)
    lat = probe_latencies(toggles, levels, frames, np.full(frames.size, 0.1))
    assert np.all(np.isnan(lat))


# ------------------------------------------------------------------------- motor process

def test_motor_process_records_every_frame_and_the_firmware_answers(tmp_path):
    import can
    from wheelleg_balance.core.protocols.mit import MitProtocol
    from wheelleg_balance.validation.bench.node import MotorBus, Recording
    mit = MitProtocol()
    channel = 'bench_motors_%d' % os.getpid()
    host = can.Bus(interface='virtual', channel=channel)
    motors = MotorBus(bus=can.Bus(interface='virtual', channel=channel))
    motors.start()
    try:
        frames = (mit.torque_frames({1: 1.0}) + mit.enable_frames([1, 2])
                  + mit.torque_frames({1: 2.0, 2: -3.0}) + mit.disable_frames([1, 2]))
        replies = []
        for frame in frames:
            host.send(can.Message(arbitration_id=frame.arbitration_id, data=frame.data,
                                  is_extended_id=False))
            msg = host.recv(2.0)
            assert msg is not None, frame
            replies.append(mit.decode_feedback(type(frame)(msg.arbitration_id, bytes(msg.data))))
        assert motors.armed_ns() == motors.t_ns[1]   # the first command after both entered
    finally:
        motors.stop()
        host.shutdown()
    # One reply per frame, from the addressed motor; torque only in motor mode (not before
    # the enter frame, nothing after the exit: zero torque, then exit).
    assert [r.motor_id for r in replies] == [f.arbitration_id for f in frames]
    assert abs(replies[0].torque) < 0.01
    assert [r.torque for r in replies[3:5]] == pytest.approx([2.0, -3.0], abs=0.01)
    motors.save(str(tmp_path / 'frames.npz'))
    rec = Recording(str(tmp_path / 'frames.npz'))
    assert list(rec.ids) == [1, 1, 2, 1, 2] and rec.reply_errors == 0
    assert rec.torque[3:].tolist() == pytest.approx([0.0, 0.0], abs=0.01)
    assert [(i, k) for _, i, k in rec.events] == [(1, 'enter'), (2, 'enter'), (1, 'exit'),
                                                  (2, 'exit')]


# ------------------------------------------------------------------------------ targets

def _report(node_p99, node_late, floor_p99=4.0, floor_late=0.02, rate=500.0, cpu=20.0,
            skipped=0, over_budget_share=0.002, core_p99_ms='0.2'):
    return {'core': {'lqr': {'p99_us': 20.0}},
            'floor': {'period_p99_ms': floor_p99, 'late_share': floor_late},
            'node': {'timing': {'rate_hz': rate, 'period_p99_ms': node_p99,
                                'late_share': node_late}, 'cpu_percent': cpu,
                     'overruns_in_window': skipped, 'over_budget_share': over_budget_share,
                     'node_loop': {'core_compute_p99_ms': core_p99_ms},
                     'node_mode': 'BALANCING', 'motors': {'1': {'balancing_share': 1.0},
                                                          '2': {'balancing_share': 1.0},
                                                          '3': {}}}}


def test_targets_against_the_floor_of_the_same_run():
    rows = {t['name']: t['pass'] for t in benchmark.targets(_report(4.7, 0.023))}
    assert all(rows.values()), rows
    rows = {t['name']: t['pass'] for t in benchmark.targets(
        _report(4.9, 0.025, rate=499.4, cpu=36.0))}
    assert not rows['node period p99 <= 1.2 x floor']
    assert not rows['node late share <= 1.2 x floor']
    assert not rows['node rate within 0.1 %']
    assert not rows['node CPU, all processes']
    assert rows['core tick p99 lqr']
    # The compute p99 over the whole window: at most 1 % of its ticks over 1 ms.
    over = 'node ticks computing > 1000 us'
    rows = {t['name']: t['pass'] for t in benchmark.targets(
        _report(4.7, 0.023, skipped=3, over_budget_share=0.0101))}
    assert not rows['node deadlines skipped']
    assert not rows[over]
    assert rows['node BalanceLoop.tick p99']
    rows = {t['name']: t['pass'] for t in benchmark.targets(
        _report(4.7, 0.023, over_budget_share=0.01, core_p99_ms='1.1'))}
    assert rows[over] and not rows['node BalanceLoop.tick p99']
    rows = {t['name']: t['pass'] for t in benchmark.targets(
        _report(4.7, 0.023, over_budget_share=math.nan))}
    assert not rows[over]   # no figure never passes
    faulted = _report(4.7, 0.023)
    faulted['node']['node_mode'] = 'FAULT'
    rows = {t['name']: t['pass'] for t in benchmark.targets(faulted)}
    assert not rows['node balanced throughout']


def test_nan_never_passes():
    rows = benchmark.targets({'core': {'lqr': {'p99_us': math.nan}}})
    assert rows[0]['pass'] is False


def test_parse_args_quick_and_parts():
    args = benchmark.parse_args(['--quick'])
    assert (args.duration, args.ticks) == (3.0, 2000)
    assert args.parts == list(benchmark.PARTS)
    args = benchmark.parse_args(['--parts', 'floor,core'])
    assert (args.duration, args.ticks, args.parts) == (60.0, 20000, ['core', 'floor'])
    assert args.output == os.path.join('output', 'benchmark.json')
    with pytest.raises(SystemExit):
        benchmark.parse_args(['--parts', 'core,gpu'])
    assert benchmark.parse_args([]).bus == 'socketcan_hub'   # the robot's CAN code path
    assert benchmark.parse_args(['--bus', 'udp_multicast']).bus == 'udp_multicast'
    with pytest.raises(SystemExit):
        benchmark.parse_args(['--bus', 'socketcan'])   # no SocketCAN to benchmark on here


# ------------------------------------------------------------------------ the replay part

def test_parse_args_replay_part_and_its_trees():
    args = benchmark.parse_args(['--parts', 'replay', '--before-tree', '/tmp/b',
                                 '--replay-tree', '/tmp/c', '--replay-tree', '/tmp/d'])
    assert args.parts == ['replay'] and 'replay' in benchmark.PARTS
    assert (args.before_tree, args.replay_tree) == ('/tmp/b', ['/tmp/c', '/tmp/d'])
    assert benchmark.parse_args([]).replay_tree == []


def test_replay_part_without_valgrind_is_one_skip_line(monkeypatch):
    real = shutil.which
    monkeypatch.setattr(shutil, 'which', lambda name: None if name == 'valgrind'
                        else real(name))
    report = bench_replay.bench([None])
    assert set(report) == {'skipped'} and 'valgrind' in report['skipped']
    out = io.StringIO()
    bench_replay.print_report(report, out.write)
    assert out.getvalue().strip().count('\n') == 0   # one line
    assert out.getvalue().strip().startswith('replay: skipped: valgrind not found')
    assert bench_replay.targets(report) == []
    with pytest.raises(FileNotFoundError):
        bench_replay.count(None, window=('wheels', 'drive', 2))


def test_replay_part_target_and_table():
    report = {'window': ['six', 'drive', 1000], 'recording': '0714d2b' + '0' * 33,
              'trees': [{'label': label, 'instructions_per_tick': n, 'wall_median_us': 1.0,
                         'wall_mean_us': 1.0, 'as_recorded_share': 1.0, 'modes': [1],
                         'dropped': []}
                        for label, n in (('this tree', 200e3), ('b4848ea', 660e3))]}
    row, = bench_replay.targets(report)
    assert row['value'] == pytest.approx(200 / 660) and row['limit'] == 0.35 and row['pass']
    report['trees'][0]['instructions_per_tick'] = 240e3
    assert not bench_replay.targets(report)[0]['pass']
    out = io.StringIO()
    bench_replay.print_report(report, out.write)
    assert '240000' in out.getvalue() and 'b4848ea' in out.getvalue()


def test_callgrind_totals_are_read(tmp_path):
    path = tmp_path / 'callgrind.out'
    path.write_text('version: 1\ncmd: python\nevents: Ir\nfn=(1) x\n0 5\nsummary: 1234\n'
                    'totals: 1234\n')
    assert bench_replay.callgrind_total(str(path)) == 1234
    path.write_text('events: Ir\n')
    with pytest.raises(ValueError):
        bench_replay.callgrind_total(str(path))


@pytest.mark.skipif(shutil.which('valgrind') is None,
                    reason='valgrind not installed (the replay part then skips itself)')
def test_replay_counts_the_tick_alone_on_a_tiny_window():
    """Ten ticks of the wheels balancing: the count is per tick and of the tick only."""
    window = ('wheels', 'drive', 10)
    result = bench_replay.count(None, mode='callgrind', window=window)
    assert result['ticks'] == 10 and result['modes'] == [1]
    # The interpreter's start, the imports, the decoding and the 700 ticks before the window
    # are several 10^9 instructions: counted, they would swamp the ten ticks.
    assert 1e5 < result['instructions_per_tick'] < 5e6, result
    assert result['instructions'] == pytest.approx(10 * result['instructions_per_tick'])
    timed = bench_replay.count(None, mode='time', window=window, repeat=1)
    assert 0 < timed['wall_median_us'] < 1e5
    if bench_replay.blas_cores() == bench_replay.load()['blas_cores']:
        assert timed['as_recorded_share'] == 1.0


def test_before_param_measures_this_tree_with_other_parameters():
    args = benchmark.parse_args(['--before-param', 'can.raw_frames:=false'])
    nut = benchmark.before_node(args)
    assert nut.tree is None and nut.params == ('can.raw_frames:=false',)
    assert nut.node_args()[-2:] == ['-p', 'can.raw_frames:=false']
    assert 'can.raw_frames:=false' in nut.label
    assert benchmark.before_node(benchmark.parse_args(['--before-tree', '/tmp/x'])).tree == \
        '/tmp/x'
    for bad in (['--before-param', 'can.raw_frames'],
                ['--before-param', 'a:=1', '--before-tree', '/tmp/x']):
        with pytest.raises(SystemExit):
            benchmark.parse_args(bad)


def test_rounds_alternate_which_tree_goes_first_and_the_median_round_stands():
    assert benchmark.node_order(1, False) == ['node']
    assert benchmark.node_order(3, False) == ['node'] * 3
    assert benchmark.node_order(1, True) == ['node_before', 'node']
    assert benchmark.node_order(4, True) == ['node_before', 'node', 'node', 'node_before',
                                             'node_before', 'node', 'node', 'node_before']
    rounds = [{'round': k, 'cpu_percent': c} for k, c in enumerate((41.0, 35.0, 47.0, 39.0))]
    assert benchmark.median_round(rounds)['round'] == 3    # 39: the lower middle of four
    assert benchmark.median_round(rounds[:3])['round'] == 0   # 41 of 35, 41, 47
    assert benchmark.median_round([{'round': 0}, {'round': 1, 'cpu_percent': 40.0}])[
        'round'] == 1   # a round without a CPU figure never stands for the tree
    assert benchmark.parse_args(['--rounds', '3']).rounds == 3
    assert benchmark.parse_args([]).rounds == 1
    with pytest.raises(SystemExit):
        benchmark.parse_args(['--rounds', '0'])
    out = io.StringIO()
    benchmark.print_rounds({'node_rounds': [{'cpu_percent': 33.5, 'over_budget_share': 0.0083},
                                            {'cpu_percent': 45.2}],
                            'node_before_rounds': [{'cpu_percent': 43.4}]}, out.write)
    lines = out.getvalue().splitlines()
    assert lines[-2].split() == ['1', '33.5', '43.4', '0.83']
    assert lines[-1].split() == ['2', '45.2', '-', '-']


# ------------------------------------------------------------------------------ bus part

def test_socketcan_stand_in_carries_frames_both_ways_without_echoes():
    from wheelleg_balance.nodes.socketcan_hub import socketcan_pair
    from wheelleg_balance.core.protocols.base import Frame
    from wheelleg_balance.nodes.can_io import CanIo
    ours, theirs = socketcan_pair()
    a, b = CanIo(ours), CanIo(theirs, raw_frames=False)   # the node's path; python-can's
    try:
        sent = [Frame(0x7FF, bytes(range(8)), False), Frame(0x1ABCDEF, b'\x01\x02\x03', True),
                Frame(0x001, b'', False)]
        assert a.send(sent) is None
        got = []
        assert b.poll(got) == 3
        assert [f for _, f in got] == sent
        mine = []
        assert a.poll(mine) == 0 and a.rx_echoes == 0   # a CAN socket gets no echoes
        assert b.send([Frame(0x101, bytes(8), False)]) is None
        assert a.poll(mine) == 1 and mine[0][1].arbitration_id == 0x101
    finally:
        a.close()
        b.close()


@pytest.mark.parametrize('transport', bench_bus.TRANSPORTS)
def test_bus_part_answers_every_command_on_each_transport(tmp_path, transport):
    out = tmp_path / 'bus.json'
    group, port = benchmark._can_address()
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join(p for p in (str(REPO), env.get('PYTHONPATH')) if p)
    subprocess.run([sys.executable, '-m', 'wheelleg_balance.validation.bench.bus', transport,
                    '--duration', '1', '--warmup', '0.5', '--frames', '3', '--output', str(out),
                    '--group', group, '--port', str(port)], env=env, check=True, timeout=60)
    r = json.loads(out.read_text())
    assert r['transport'] == transport and r['frames'] == 3 and r['send_error'] == ''
    assert r['ticks'] > 100   # about 500 in the 1 s window
    per_tick = r['per_tick']
    assert per_tick['tx_frames'] == pytest.approx(3.0, abs=0.05)
    # One reply per command (the last tick's replies may still be on their way).
    assert per_tick['rx_frames'] == pytest.approx(3.0, abs=6.0 / r['ticks'] + 0.01)
    assert per_tick['tx_errors'] == 0 and per_tick['rx_errors'] == 0
    # udp_multicast hands the sender its own frames back; SocketCAN (and its stand-ins) not.
    echoes = per_tick['rx_echoes']
    assert echoes == (pytest.approx(3.0, abs=0.05) if transport == 'udp_multicast' else 0.0)
    assert _positive_finite(r['cpu_percent']) and _positive_finite(r['io_mean_us'])
    assert r['io_median_us'] <= r['io_p99_us']


def test_bus_frames_per_tick_and_the_socketcan_estimate():
    assert bench_bus.frames_per_tick(1) == 6   # every hip every tick
    assert bench_bus.frames_per_tick(2) == 4   # the legs take turns
    assert bench_bus.frames_per_tick(4) == 3
    bus = {'udp_multicast': {'cpu_percent': 13.0}, 'socketcan_path': {'cpu_percent': 10.0}}
    assert bench_bus.node_cpu_on_socketcan(39.5, bus) == pytest.approx(36.5)
    bus['socketcan_python_can'] = {'cpu_percent': 13.5}
    assert bench_bus.node_cpu_on_socketcan(39.5, bus, 'socketcan_python_can') == \
        pytest.approx(40.0)
    assert math.isnan(bench_bus.node_cpu_on_socketcan(39.5, {'udp_multicast': {}}))
    assert math.isnan(bench_bus.node_cpu_on_socketcan(39.5, {}))
    args = benchmark.parse_args(['--parts', 'bus,node'])
    assert args.parts == ['node', 'bus']
    fig = {'cpu_percent': 13.0, 'io_mean_us': 250.0, 'io_p99_us': 350.0,
           'per_tick': {'rx_echoes': 4.0}}
    out = io.StringIO()
    benchmark.print_bus({'settings': {'duration': 30.0}, 'bus': {
        'frames_per_tick': 4, 'udp_multicast': fig,
        'socketcan_path': {**fig, 'cpu_percent': 10.0, 'per_tick': {'rx_echoes': 0.0}},
        'node_cpu_on_socketcan_path': 36.5}}, out.write)
    text = out.getvalue()
    assert '4 commands out' in text and '250 / 350' in text
    assert "as it runs 36.5 %, with python-can's recv and send - %" in text
    assert [line.split()[-1] for line in text.splitlines()[3:5]] == ['4.0', '0.0']


def test_profile_summary(tmp_path):
    raw = tmp_path / 'raw.txt'
    raw.write_text(
        'thread (10): MainThread;spin (rclpy/__init__.py:247);wait (rclpy/executors.py:697) 6\n'
        'thread (11): balance_control;_run (balance_node.py:329);_tick (balance_node.py:400)'
        ';send (can_io.py:122) 3\n'
        'thread (11): balance_control;_run (balance_node.py:329);_tick (balance_node.py:393) 1\n')
    s = bench_profile.summarize(str(raw))
    assert s['samples'] == 10
    assert s['threads'] == {'MainThread': 60.0, 'balance_control': 40.0}
    assert s['self'][0] == ['wait (rclpy/executors.py)', 60.0]
    inclusive = dict(s['inclusive'])
    assert inclusive['_tick (balance_node.py)'] == 40.0   # lines of a function add up
    assert 'spin (rclpy/__init__.py)' not in inclusive    # frames every stack has are left out


# ------------------------------------------------------------------------ real-time helpers

def _in_thread(fn):
    """Run fn in a fresh thread (scheduler and affinity changes die with it)."""
    out = {}
    th = threading.Thread(target=lambda: out.setdefault('r', fn()))
    th.start()
    th.join()
    return out['r']


def _clean(result):
    ok, message = result
    return isinstance(ok, bool) and isinstance(message, str) and message


def test_fifo_priority_returns_clean_result():
    def attempt():
        result = realtime.set_fifo_priority(1)
        policy = os.sched_getscheduler(0)
        return result, policy

    (ok, message), policy = _in_thread(attempt)
    assert _clean((ok, message))
    assert (policy == os.SCHED_FIFO) == ok  # ok means the thread really runs under FIFO
    assert realtime.set_fifo_priority(0)[0] is True
    ok, message = realtime.set_fifo_priority(1000)
    assert ok is False and 'outside' in message


def test_pinning_to_an_allowed_cpu_works():
    allowed = sorted(os.sched_getaffinity(0))
    cpu = allowed[-1]

    def attempt():
        return realtime.pin_to_cpus([cpu]), os.sched_getaffinity(0)

    (ok, message), affinity = _in_thread(attempt)
    assert ok, message
    assert affinity == {cpu}
    assert os.sched_getaffinity(0) == set(allowed)  # only the helper thread was pinned
    ok, message = _in_thread(lambda: realtime.pin_to_cpus([max(allowed) + 4096]))
    assert ok is False and 'not allowed' in message
    assert realtime.pin_to_cpus([]) == (True, 'CPU pinning not requested')


def test_memory_lock_returns_clean_result():
    result = realtime.lock_memory(on_fault=True)
    try:
        assert _clean(result)
    finally:
        if result[0]:
            assert realtime.unlock_memory()[0]


def test_thread_name_is_visible_to_the_kernel():
    def attempt():
        result = realtime.name_thread('wlb_test_control_thread')
        with open('/proc/self/task/%d/comm' % threading.get_native_id()) as f:
            return result, f.read().strip()

    (ok, message), comm = _in_thread(attempt)
    assert _clean((ok, message))
    if ok:
        assert comm == 'wlb_test_contro'  # the kernel keeps 15 bytes


def test_apply_reports_every_option():
    report = _in_thread(lambda: realtime.apply(priority=0, cpus=(), lock=False))
    assert set(report) == {'priority', 'affinity', 'memory_lock'}
    assert all(_clean(r) and r[0] for r in report.values())
    assert isinstance(realtime.kernel_is_preempt_rt(), bool)
