"""
benchmark: does the 2 ms balance loop hold in Python? Everything measured in one run.

1. core: compute time per tick of the math core for each controller (BalanceCore.step +
   MitProtocol.torque_frames for both motors, closed loop on the simulated robot);
2. floor: a bare Python loop sleeping to absolute 2 ms deadlines, in its own process;
3. baseline: a bare rclpy node with an empty 2 ms timer, in its own process;
4. node: balance_node (its ROS shell, control process and sensor intake) with imu at 500 Hz
   from another process and its six motors emulated on a CAN bus (below); its frames,
   CPU, compute time and latency. ``--before-tree DIR`` measures the node of another source
   tree (a checkout of an earlier commit) the same way in the same run ('node_before');
   ``--node-param NAME:=VALUE`` sets a parameter of this tree's node; ``--rounds N`` measures
   the node N times (with a before tree in the order ABBA..., before and after alternating
   which goes first, so a drift of the host's load shows in both alike): every round is in
   the report, the round of median CPU stands for each tree in the table and the targets.
   ``--before-param NAME:=VALUE`` makes 'node_before' this tree with those parameters instead.
   The node part's bus is python-can's SocketcanBus through a hub (nodes/socketcan_hub.py: the
   robot's CAN code path without SocketCAN in the kernel); ``--bus udp_multicast`` runs it on
   python-can's udp_multicast test bus instead (the only bus of trees before 2026-12-06);
5. bus: the node's CAN traffic through CanIo alone, on python-can's udp_multicast bus and on
   a python-can SocketcanBus over loopback UDP, both as CanIo runs there and through
   python-can's recv and send, each in its own process (bench/bus.py): what each path costs;
   after a node part on udp_multicast, estimates of the node's CPU on SocketCAN (not targets);
6. start: from the balance_node executable (what ``ros2 run`` starts) to its ready line, the
   median of ``--start-runs`` starts (bench/start.py), with ``--before-tree`` that tree's too,
   the two taking turns;
7. replay: valgrind's instruction count of ``BalanceLoop.tick`` alone, 1000 ticks of the six
   motors balancing and driving, its inputs replayed from a recording (bench/replay.py; the
   motors and the replay's own work not counted), and the wall time of the same ticks; for
   this tree, ``--before-tree``'s and each ``--replay-tree``'s. Skipped with one line where
   valgrind is missing.

Prints a table and writes a JSON report; the targets are reported pass/fail, they never change
the exit code (1 only when a part could not run). Methods and figures: docs/benchmarks.md.

    ros2 run wheelleg_balance benchmark [--duration 60] [--output output/benchmark.json]
        [--quick] [--parts core,floor,baseline,node,bus,start] [--profile] [--before-tree DIR]
        [--node-param NAME:=VALUE] [--rounds N] [--before-param NAME:=VALUE]
        [--bus socketcan_hub|udp_multicast] [--start-runs N] [--replay-tree DIR]
"""
import argparse
import datetime
import json
import math
import os
import random
import shutil
import subprocess
import sys
import tempfile
import time
from typing import Dict, List, Optional

import numpy as np

from . import bus as bench_bus, core as bench_core, node as bench_node, \
    profiling as bench_profile
from . import replay as bench_replay, start as bench_start
from .host import machine, package_env
from .stats import check, period_stats
from .. import json_safe
from ...core.config import BalanceConfig
from ...core.pipeline import CONTROLLER_NAMES

PARTS = ('core', 'floor', 'baseline', 'node', 'bus', 'start', 'replay')
PERIOD_NS = 2_000_000
LATE_NS = 1_000_000

# Targets (issues 6 and 10): the tick's compute time p99 within half the period, alone
# (core) and in the node (its own count of ticks over budget, every tick of the window); the
# node at 500 Hz with no deadline skipped, its three processes together under 35 % of a core.
TICK_P99_US = 1000.0
#: ... at the 99th percentile: at most 1 % of the ticks over it [%].
TICK_OVER_BUDGET_PCT = 1.0
RATE_TOLERANCE = 0.001         # achieved rate within 0.1 % of 500 Hz
FLOOR_FACTOR = 1.2             # p99 period and late share no worse than 1.2 x the floor's
NODE_CPU_PERCENT = 35.0


def _loop_command(kind: str, duration: float, out: str, fifo: int) -> List[str]:
    return [sys.executable, '-m', 'wheelleg_balance.validation.bench.loops', kind,
            '--duration', str(duration), '--output', out, '--fifo', str(fifo)]


def run_loop(kind: str, duration: float, env: Dict[str, str], workdir: str,
             fifo: int = 0) -> Dict:
    """Run the floor or baseline loop as its own process; its timing figures."""
    out = os.path.join(workdir, kind + '.npz')
    subprocess.run(_loop_command(kind, duration, out, fifo), env=env, check=True,
                   timeout=duration + 120)
    return loop_result(out)


def run_node(args, env: Dict[str, str], workdir: str,
             nut: bench_node.NodeUnderTest = bench_node.NodeUnderTest(), tag: str = '') -> Dict:
    """
    Run the node part; a floor loop runs beside it through the measured window.

    That second floor ('floor_during_node') sees the load of the node run (sensor and motor
    processes, DDS): it tells how much of the node's late share the machine alone explains.
    It is a figure for reading the result, not the target's reference.
    """
    out = os.path.join(workdir, 'floor_during_node%s.npz' % tag)
    floors = []

    def attach(pid, duration):
        floors.append(subprocess.Popen(
            _loop_command('floor', duration, out, args.realtime_priority), env=env))

    extra = bench_node.param_args(args.node_param) if nut.tree is None and not nut.params \
        else []
    node = bench_node.run(args.duration, workdir, env, *_can_address(),
                          controller=args.controller, realtime_priority=args.realtime_priority,
                          extra_node_args=extra, on_window=attach, nut=nut, tag=tag,
                          interface=args.bus)
    for proc in floors:
        if proc.wait(timeout=120) == 0:
            node['floor_during_node'] = loop_result(out)
    return node


def run_bus(args, env: Dict[str, str], workdir: str) -> Dict:
    """Run the bus part: CanIo alone on each transport, one process each (bench/bus.py)."""
    divider = BalanceConfig().legs.command_divider
    for p in args.node_param:
        name, _, value = p.partition(':=')
        if name == 'legs.command_divider':
            divider = int(value)
    frames = bench_bus.frames_per_tick(divider)
    result = {'frames_per_tick': frames}
    for transport in bench_bus.TRANSPORTS:
        out = os.path.join(workdir, 'bus_%s.json' % transport)
        group, port = _can_address()
        subprocess.run([sys.executable, '-m', 'wheelleg_balance.validation.bench.bus', transport,
                        '--duration', str(args.duration), '--frames', str(frames),
                        '--output', out, '--group', group, '--port', str(port)],
                       env=env, check=True, timeout=args.duration + 120)
        with open(out) as f:
            result[transport] = json.load(f)
    return result


def run_start(args, env: Dict[str, str]) -> Dict:
    """Run the start part: this tree's starts, taking turns with --before-tree's."""
    nodes = [bench_start.tree_command(None, env)]
    if args.before_tree:
        nodes.append(bench_start.tree_command(args.before_tree, env))
    return bench_start.run(nodes, args.start_runs, log=lambda s: print(s, flush=True))


def before_node(args) -> bench_node.NodeUnderTest:
    """
    Describe the 'before' node: another tree's, or this one's with ``--before-param``.

    Another source tree's package must have legs.driven.
    """
    if args.before_tree:
        path = os.path.abspath(args.before_tree)
        return bench_node.NodeUnderTest(tree=path, label=path)
    return bench_node.NodeUnderTest(params=tuple(args.before_param),
                                    label='this tree with ' + ' '.join(args.before_param))


def _can_address():
    """Return a udp_multicast group and port of this run's own (concurrent runs stay apart)."""
    return '239.74.163.%d' % random.randint(10, 250), random.randint(40000, 49999)


def loop_result(out: str) -> Dict:
    """Compute the timing figures of a floor or baseline recording (bench_loops' npz)."""
    data = np.load(out)
    result = period_stats(data['t_ns'], PERIOD_NS, LATE_NS)
    late = data['late_ns']
    cpu = data['cpu_s']
    result['cpu_percent'] = 100.0 * float(cpu[1] - cpu[0]) / float(data['wall_s'])
    # The loop's own view, against the deadlines it really had (cross-check of late_share).
    result['own_late_share'] = float(np.mean(late > LATE_NS))
    result['own_late_p99_ms'] = float(np.percentile(late, 99)) / 1e6
    result['fifo'] = str(data['fifo_message'])
    return result


def targets(report: Dict) -> List[Dict]:
    """Check the issue's targets: pass/fail rows (only for the parts that ran)."""
    rows = []
    for name, core in report.get('core', {}).items():
        rows.append(dict(name='core tick p99 %s' % name, unit='us',
                         **check(core['p99_us'], TICK_P99_US)))
    floor = report.get('floor')
    for key in ('node', 'node_before'):
        if report.get(key):
            rows += node_targets(report[key], floor, 'node' if key == 'node' else 'before')
    if report.get('start'):
        rows += bench_start.targets(report['start'])
    if report.get('replay'):
        rows += bench_replay.targets(report['replay'])
    return rows


def node_targets(node: Dict, floor: Optional[Dict], label: str) -> List[Dict]:
    """Return the node part's pass/fail rows, named with ``label``."""
    rows = []
    t = node['timing']
    rate = t['rate_hz']
    row = check(abs(rate - 500.0) / 500.0, RATE_TOLERANCE)
    rows.append(dict(name='%s rate within 0.1 %%' % label, unit='Hz', value=rate,
                     limit='500 +- %.1f' % (500.0 * RATE_TOLERANCE), **{'pass': row['pass']}))
    skipped = node.get('overruns_in_window', math.nan)
    rows.append(dict(name='%s deadlines skipped' % label, unit='ticks', **check(skipped, 0)))
    # The tick's compute p99 within TICK_P99_US over every tick of the window: at most 1 % of
    # them over that budget (the node's own p99 covers only its last 2 s: printed, not judged).
    over = node.get('over_budget_share', math.nan)
    rows.append(dict(name='%s ticks computing > %.0f us' % (label, TICK_P99_US), unit='%',
                     **check(100.0 * over, TICK_OVER_BUDGET_PCT)))
    # Where the tick's time goes: BalanceLoop.tick alone (the rest is the link and the bus).
    core = _float(node.get('node_loop', {}).get('core_compute_p99_ms'))
    rows.append(dict(name='%s BalanceLoop.tick p99' % label, unit='us',
                     **check(1e3 * core, TICK_P99_US)))
    if floor:
        rows.append(dict(name='%s period p99 <= 1.2 x floor' % label, unit='ms',
                         **check(t['period_p99_ms'], FLOOR_FACTOR * floor['period_p99_ms'])))
        rows.append(dict(name='%s late share <= 1.2 x floor' % label, unit='%',
                         **check(100 * t['late_share'],
                                 100 * FLOOR_FACTOR * floor['late_share'])))
    rows.append(dict(name='%s CPU, all processes' % label, unit='% of a core',
                     **check(node['cpu_percent'], NODE_CPU_PERCENT)))
    # Not a target but the condition for the figures above to mean anything: the node
    # balanced (ran the controller) the whole time, no FAULT.
    share = min(m['balancing_share'] for m in node['motors'].values()
                if 'balancing_share' in m)
    rows.append(dict(name='%s balanced throughout' % label, unit='%', value=100.0 * share,
                     limit=100.0, **{'pass': share == 1.0
                                     and node.get('node_mode') == 'BALANCING'}))
    return rows


def _float(text) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan


# ---------------------------------------------------------------------------------- output

def _fmt(v, spec='%.3f') -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return '-'
    return spec % v


def print_report(report: Dict, out=sys.stdout) -> None:
    """Print the readable table."""
    w = out.write
    m = report['machine']
    w('wheelleg_balance benchmark %s: %d CPUs, Linux %s%s, Python %s, load %s\n' % (
        report['date'], m['cpus'], m['kernel'], ' PREEMPT_RT' if m['preempt_rt'] else '',
        m['python'], '/'.join('%.1f' % v for v in m['load_average'])))
    core = report.get('core')
    if core:
        w('\ncore compute per tick (step + MIT frames, %d ticks, closed loop) [us]\n'
          % next(iter(core.values()))['n'])
        w('  %-20s %10s %10s %10s %14s\n' % (
            'controller', 'median', 'p99', 'max', 'p99 CPU time'))
        for name, c in core.items():
            w('  %-20s %10s %10s %10s %14s\n' % (
                name, _fmt(c['median_us'], '%.1f'), _fmt(c['p99_us'], '%.1f'),
                _fmt(c['max_us'], '%.1f'), _fmt(c['cpu_p99_us'], '%.1f')))
    loops = [k for k in ('floor', 'baseline', 'node', 'node_before') if report.get(k)]
    if loops:
        w('\n2 ms loops, %.0f s each (node: CAN frames of motor 1 seen on the bus)\n'
          % report['settings']['duration'])
        w('  %-22s' % '' + ''.join('%14s' % k for k in loops) + '\n')
        rows = (('rate [Hz]', 'rate_hz', '%.2f', 1), ('period median [ms]', 'period_median_ms',
                                                      '%.3f', 1),
                ('period p99 [ms]', 'period_p99_ms', '%.3f', 1),
                ('period p99.9 [ms]', 'period_p999_ms', '%.3f', 1),
                ('period max [ms]', 'period_max_ms', '%.3f', 1),
                ('late > 1 ms [%]', 'late_share', '%.2f', 100),
                ('CPU [% of a core]', 'cpu_percent', '%.1f', 1))
        for label, key, spec, scale in rows:
            vals = []
            for k in loops:
                src = report[k]['timing'] if k.startswith('node') else report[k]
                v = src.get(key, report[k].get(key))
                vals.append(_fmt(None if v is None else v * scale, spec))
            w('  %-22s' % label + ''.join('%14s' % v for v in vals) + '\n')
    for key in ('node', 'node_before'):
        if report.get(key):
            print_node(key, report[key], w)
    print_rounds(report, w)
    print_bus(report, w)
    if report.get('start'):
        bench_start.print_report(report['start'], w)
    if report.get('replay'):
        bench_replay.print_report(report['replay'], w)
    if report['targets']:
        w('\n  %-34s %14s %14s  %s\n' % ('target', 'value', 'limit', 'result'))
        for t in report['targets']:
            limit = t['limit'] if isinstance(t['limit'], str) else _fmt(t['limit'], '%.3g')
            w('  %-34s %14s %14s  %s\n' % ('%s [%s]' % (t['name'], t['unit']),
                                           _fmt(t['value'], '%.3g'), limit,
                                           'PASS' if t['pass'] else 'FAIL'))
    for part, err in report['errors'].items():
        w('\n%s: NOT RUN: %s\n' % (part, err.strip().splitlines()[0] if err.strip() else err))
    for key in ('profile', 'profile_before'):
        profile = report.get(key)
        if profile and 'threads' in profile:
            w('\n%s of the control process (py-spy, %% of GIL-holding samples): threads %s\n'
              % (key, ', '.join('%s %.0f' % kv for kv in profile['threads'].items())))
            for name, share in profile['inclusive'][:12]:
                w('  %5.1f  %s\n' % (share, name))
            w('  self:\n')
            for name, share in profile['self'][:8]:
                w('  %5.1f  %s\n' % (share, name))


def print_node(key: str, node: Dict, w) -> None:
    """Print one node part's latency, processes, threads and own diagnostics."""
    lat = node['latency']
    w('\n%s (%s, %d motors, %s): latency, sensor sample published -> CAN frame on the bus '
      '[us]: median %s, p99 %s, p99.9 %s, max %s (%d of %d probes measured, %d lost in '
      'stalls)\n' % (
          key, node.get('tree', ''), node.get('motor_count', 0),
          node.get('interface', 'udp_multicast'), _fmt(lat['median_us'], '%.0f'),
          _fmt(lat['p99_us'], '%.0f'), _fmt(lat['p999_us'], '%.0f'),
          _fmt(lat['max_us'], '%.0f'), lat['n'], lat['probes'], lat['lost']))
    w('  processes [%% of a core]: %s%s\n' % (', '.join(
        '%s %.1f' % kv for kv in node.get('processes', {}).items()),
        '; the bus hub beside them (not the node) %s' % _fmt(node['hub_cpu_percent'], '%.1f')
        if 'hub_cpu_percent' in node else ''))
    w('  threads [%% of a core]: %s\n' % ', '.join(
        '%s:%s/%d %.1f' % (t.get('process', ''), t['name'], t['tid'], t['cpu_percent'])
        for t in node['threads']))
    beside = node.get('floor_during_node')
    if beside:
        w('  floor run beside it (same load; for reading, not a target): period p99 %s ms, '
          'late > 1 ms %s %%\n'
          % (_fmt(beside['period_p99_ms']), _fmt(100 * beside['late_share'], '%.2f')))
    loop = node.get('node_loop', {})
    if loop:
        skipped = _fmt(node.get('overruns_in_window'), '%.0f')
        figures = (loop.get('message', ''), loop.get('compute_mean_ms', '-'),
                   loop.get('compute_p99_ms', '-'), loop.get('core_compute_mean_ms', '-'),
                   loop.get('core_compute_p99_ms', '-'), skipped)
        w('  own diagnostics: %s; compute mean %s ms, p99 %s ms (of which BalanceLoop.tick '
          'mean %s ms, p99 %s ms); %s deadlines skipped in the window\n' % figures)
        w('  ticks computing longer than the budget (%s ms), whole window: %s of %s (%s %%)\n' % (
            loop.get('compute_budget_ms', '-'), _fmt(node.get('over_budget_in_window'), '%.0f'),
            _fmt(node.get('ticks_counted'), '%.0f'),
            _fmt(100.0 * node.get('over_budget_share', math.nan), '%.2f')))


def print_rounds(report: Dict, w) -> None:
    """Print every round of a ``--rounds`` run (the table above shows the median ones)."""
    after, before = report.get('node_rounds', []), report.get('node_before_rounds', [])
    if not after:
        return
    w('\nrounds (in the order run%s; the table and the targets take the median-CPU round of '
      'each tree)\n' % (', before and after alternating which goes first' if before else ''))
    w('  %-6s %22s %22s %26s\n' % ('round', 'CPU after [%]', 'CPU before [%]',
                                   'ticks > 1 ms, after [%]'))
    for k, a in enumerate(after):
        b = before[k] if k < len(before) else {}
        w('  %-6d %22s %22s %26s\n' % (
            k + 1, _fmt(a.get('cpu_percent'), '%.1f'), _fmt(b.get('cpu_percent'), '%.1f'),
            _fmt(100.0 * a.get('over_budget_share', math.nan), '%.2f')))


def print_bus(report: Dict, w) -> None:
    """Print the bus part: CanIo alone per transport, and the node's CPU estimated on SocketCAN."""
    bus = report.get('bus')
    if not bus:
        return
    w('\nCAN I/O alone (CanIo at 500 Hz: %d commands out, one reply each in, per tick; a peer '
      'process answers; %.0f s each)\n' % (bus['frames_per_tick'],
                                           report['settings']['duration']))
    w('  %-50s %18s %28s %16s\n' % ('transport', 'CPU [% of a core]',
                                    'poll + send mean / p99 [us]', 'echoes per tick'))
    names = {'udp_multicast': "udp_multicast (the node part's)",
             'socketcan_path': 'socketcan_path (the node on SocketCAN)',
             'socketcan_python_can': "socketcan_python_can (python-can's recv and send)"}
    for transport in bench_bus.TRANSPORTS:
        r = bus.get(transport)
        if r:
            w('  %-50s %18s %28s %16s\n' % (
                names[transport], _fmt(r['cpu_percent'], '%.1f'),
                '%s / %s' % (_fmt(r['io_mean_us'], '%.0f'), _fmt(r['io_p99_us'], '%.0f')),
                _fmt(r['per_tick']['rx_echoes'], '%.1f')))
    labels = (('socketcan_path', 'as it runs'),
              ('socketcan_python_can', "with python-can's recv and send"))
    estimates = [(bus.get('node_cpu_on_' + path), label) for path, label in labels]
    if any(v is not None for v, _ in estimates):
        w('  the node on SocketCAN, estimated (node CPU - udp_multicast + that path; not '
          'measured, no SocketCAN here; not a target):\n    %s\n' % ', '.join(
              '%s %s %%' % (label, _fmt(v, '%.1f')) for v, label in estimates))


# ------------------------------------------------------------------------------------ main

def parse_args(argv=None):
    """Command-line options (see the module docstring)."""
    parser = argparse.ArgumentParser(
        prog='benchmark', description='Measure the 2 ms balance loop: core compute time, a '
        'bare Python loop (floor), a bare rclpy timer (baseline) and balance_node, in one run.')
    parser.add_argument('--duration', type=float, default=None,
                        help='seconds measured for each of floor, baseline and node '
                        '(default 60; 3 with --quick)')
    parser.add_argument('--output', default=os.path.join('output', 'benchmark.json'),
                        help='JSON report path (default ./output/benchmark.json)')
    parser.add_argument('--quick', action='store_true',
                        help='tiny run to check the set-up: 2000 core ticks, 3 s loops')
    parser.add_argument('--parts', default=','.join(PARTS),
                        help='comma-separated subset of %s' % ','.join(PARTS))
    parser.add_argument('--ticks', type=int, default=None,
                        help='core ticks per controller (default 20000; 2000 with --quick)')
    parser.add_argument('--controller', default='ida_pbc', choices=CONTROLLER_NAMES,
                        help='controller balance_node runs (default ida_pbc)')
    parser.add_argument('--realtime-priority', type=int, default=0,
                        help="SCHED_FIFO priority for the floor and the node's control thread "
                        '(default 0: none)')
    parser.add_argument('--profile', action='store_true',
                        help='afterwards, profile balance_node with py-spy (must be installed) '
                        'in an extra run of up to 20 s')
    parser.add_argument('--before-tree', default=None, metavar='DIR',
                        help='also measure the node of this source tree (e.g. a git worktree of '
                        'an earlier commit), just before this one: node_before in the report')
    parser.add_argument('--node-param', action='append', default=[], metavar='NAME:=VALUE',
                        help="a parameter of this tree's balance_node (repeatable; not for "
                        'the node of --before-tree), e.g. legs.command_divider:=1')
    parser.add_argument('--before-param', action='append', default=[], metavar='NAME:=VALUE',
                        help="measure this tree's node with this parameter (repeatable) as "
                        'node_before, e.g. can.raw_frames:=false (not with --before-tree)')
    parser.add_argument('--bus', default='socketcan_hub',
                        choices=('socketcan_hub', 'udp_multicast'),
                        help="the node part's CAN bus: python-can's SocketcanBus through a hub "
                        "of the run's own (default: the robot's code path) or its "
                        'udp_multicast (the bus of the figures before 2026-12-06 and of '
                        'trees from before then)')
    parser.add_argument('--rounds', type=int, default=1,
                        help='measure the node this many times (with a before node in ABBA '
                        'order); the round of median CPU is reported for each tree')
    parser.add_argument('--start-runs', type=int, default=bench_start.RUNS,
                        help='starts of each tree in the start part (default %d; the median '
                        'is the figure)' % bench_start.RUNS)
    parser.add_argument('--replay-tree', action='append', default=[], metavar='DIR',
                        help="the replay part also counts this source tree's tick "
                        "(repeatable; after --before-tree's)")
    parser.add_argument('--workdir', default=None,
                        help='keep the raw recordings (npz, logs) here instead of a temp dir')
    args = parser.parse_args(argv)
    bad = [p for p in args.node_param + args.before_param if ':=' not in p]
    if bad:
        parser.error('--node-param and --before-param take NAME:=VALUE, not %s'
                     % ', '.join(bad))
    if args.before_param and args.before_tree:
        parser.error('--before-param is for this tree: not with --before-tree')
    parts = [p.strip() for p in args.parts.split(',') if p.strip()]
    unknown = set(parts) - set(PARTS)
    if unknown:
        parser.error('unknown part(s) %s; choose from %s' % (
            ', '.join(sorted(unknown)), ', '.join(PARTS)))
    args.parts = [p for p in PARTS if p in parts]
    if args.duration is None:
        args.duration = 3.0 if args.quick else 60.0
    if args.ticks is None:
        args.ticks = 2000 if args.quick else 20000
    if args.duration < 1.0 or args.ticks < 100:
        parser.error('--duration must be >= 1 s and --ticks >= 100')
    if args.rounds < 1:
        parser.error('--rounds must be >= 1')
    if args.start_runs < 1:
        parser.error('--start-runs must be >= 1')
    return args


def main(argv=None) -> int:
    """Run the benchmark; 0 when every requested part ran (whatever the targets say)."""
    args = parse_args(argv)
    env = package_env()
    os.environ.update({k: env[k] for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE')})
    workdir = args.workdir or tempfile.mkdtemp(prefix='wlb_benchmark_')
    os.makedirs(workdir, exist_ok=True)
    report = {
        'date': datetime.datetime.now().isoformat(timespec='seconds'),
        'machine': machine(),
        'settings': {'duration': args.duration, 'ticks': args.ticks, 'quick': args.quick,
                     'parts': args.parts, 'controller': args.controller,
                     'realtime_priority': args.realtime_priority, 'period_ms': 2.0,
                     'late_threshold_ms': 1.0, 'ros_domain_id': int(env['ROS_DOMAIN_ID']),
                     'before_tree': args.before_tree, 'node_params': args.node_param,
                     'before_params': args.before_param, 'bus': args.bus,
                     'rounds': args.rounds, 'start_runs': args.start_runs,
                     'replay_trees': args.replay_tree},
        'errors': {},
    }
    steps = {
        'core': lambda: bench_core.run(args.ticks),
        'floor': lambda: run_loop('floor', args.duration, env, workdir, args.realtime_priority),
        'baseline': lambda: run_loop('baseline', args.duration, env, workdir),
        'node_before': lambda: run_node(args, env, workdir, before_node(args), tag='_before'),
        'node': lambda: run_node(args, env, workdir),
        'bus': lambda: run_bus(args, env, workdir),
        'start': lambda: run_start(args, env),
        'replay': lambda: bench_replay.bench(
            [None] + ([args.before_tree] if args.before_tree else []) + args.replay_tree,
            args.quick, log=lambda s: print(s, flush=True)),
    }
    parts = list(args.parts)
    if 'node' in parts:
        k = parts.index('node')
        parts[k:k + 1] = node_order(args.rounds, bool(args.before_tree or args.before_param))
    rounds: Dict[str, List[Dict]] = {'node': [], 'node_before': []}
    try:
        for part in parts:
            print('[benchmark] %s ...' % part, flush=True)
            t0 = time.monotonic()
            try:
                result = steps[part]()
                if part in rounds:
                    result['round'] = len(rounds[part]) + 1
                    rounds[part].append(result)
                else:
                    report[part] = result
            except Exception as exc:  # noqa: B902 -- report the part as not run, go on
                report['errors'][part] = '%s: %s' % (type(exc).__name__, exc)
            print('[benchmark] %s done in %.0f s' % (part, time.monotonic() - t0), flush=True)
        for part, results in rounds.items():
            if results:
                report[part] = median_round(results)
                if args.rounds > 1:
                    report[part + '_rounds'] = results
        if args.profile:
            report['profile'] = profile(args, env, workdir)
            if args.before_tree or args.before_param:
                report['profile_before'] = profile(args, env, workdir, before_node(args))
    finally:
        if args.workdir is None:
            shutil.rmtree(workdir, ignore_errors=True)
    if report.get('bus') and report.get('node') and args.bus == 'udp_multicast':
        for path in ('socketcan_path', 'socketcan_python_can'):
            report['bus']['node_cpu_on_' + path] = bench_bus.node_cpu_on_socketcan(
                report['node']['cpu_percent'], report['bus'], path)
    report['machine']['load_average_end'] = [round(v, 2) for v in os.getloadavg()]
    report['targets'] = targets(report)
    out_dir = os.path.dirname(os.path.abspath(args.output))
    os.makedirs(out_dir, exist_ok=True)
    with open(args.output, 'w') as f:
        json.dump(json_safe(report), f, indent=2, allow_nan=False)
        f.write('\n')
    print()
    print_report(report)
    print('\nreport: %s' % os.path.abspath(args.output))
    return 1 if report['errors'] else 0


def node_order(rounds: int, before: bool) -> List[str]:
    """
    Return the node parts to run: 'node' ``rounds`` times, each with 'node_before' if asked.

    With a before node the rounds alternate which goes first (before, after, after,
    before, ...): a load that rises or falls through the run then weighs on both alike.
    """
    if not before:
        return ['node'] * rounds
    order = []
    for k in range(rounds):
        pair = ['node_before', 'node']
        order += pair if k % 2 == 0 else pair[::-1]
    return order


def median_round(results: List[Dict]) -> Dict:
    """Return the round whose node CPU is the median (the lower middle one of an even count)."""
    ranked = sorted(results, key=lambda r: r.get('cpu_percent', math.inf))
    return ranked[(len(ranked) - 1) // 2]


def profile(args, env: Dict[str, str], workdir: str,
            nut: bench_node.NodeUnderTest = bench_node.NodeUnderTest()) -> Dict:
    """Profile balance_node's control process with py-spy in an extra run; summarize it."""
    if bench_profile.py_spy() is None:
        return {'error': 'py-spy not found (pip install py-spy)'}
    tag = '_profile' if nut.tree is None else '_profile_before'
    raw = os.path.join(workdir, tag[1:] + '.txt')
    recorders = []

    def attach(pid, duration):
        recorders.append(bench_profile.start_recording(pid, duration - 1.0, raw))

    duration = min(args.duration, 20.0)
    try:
        bench_node.run(duration, workdir, env, *_can_address(), controller=args.controller,
                       on_window=attach, tag=tag, nut=nut, interface=args.bus)
    except Exception as exc:  # noqa: B902
        return {'error': '%s: %s' % (type(exc).__name__, exc)}
    for r in recorders:
        r.wait(timeout=30)
    if not os.path.exists(raw):
        return {'error': 'py-spy wrote no samples (ptrace not permitted?)'}
    summary = bench_profile.summarize(raw)
    summary['duration_s'] = duration
    return summary


if __name__ == '__main__':
    sys.exit(main())
