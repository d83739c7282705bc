"""
The start part: from ``ros2 run`` to balance_node's ready line, the median of N starts.

``ros2 run wheelleg_balance balance_node`` runs the executable ``<prefix>/lib/
wheelleg_balance/balance_node``; each start here runs that file of a tree's colcon install
(``tree_command``; a tree without an install: ``python -P -m wheelleg_balance.nodes.
balance_node`` on its source, said so in the report) on python-can's udp_multicast bus (a
group and port of the run's own, nothing answering: the start does not wait for motors), and
times it from just before the process is created to the moment the node logs its ready line,
the one naming the controller and the bus (``READY_MARK``), by that line's own stamp. The
node is then stopped (SIGINT) and has ended before the next start. Beside each start: the CPU
seconds every process of the node had used by then (where the time goes: the ROS shell, the
control process, the sensor intake, the watchdog).

With several trees the starts take turns (first start of each tree, second start of each, ...,
the order rotating every round), so a change of the machine's load weighs on every tree alike.
The figure is the median of a tree's starts; the target (issue 30) is ``TARGET_S`` for this
tree's. The ``benchmark`` command's ``start`` part runs it (with ``--before-tree``); alone:

    python -m wheelleg_balance.validation.bench.start [--runs 5] [--tree DIR ...]
        [--output FILE]

(no ``--tree``: this package's own install). docs/benchmarks.md, "Start-up", has figures.
"""
import argparse
import datetime
import json
import os
import random
import re
import select
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from typing import Dict, List, NamedTuple, Optional, Sequence

#: The ready line's text (nodes/balance_node.py): the controller and the bus are named.
READY_MARK = 'balance_node: controller '
#: The target (issue 30): the median start of this tree at most this [s].
TARGET_S = 2.0
#: Starts per tree (the median of them is the figure).
RUNS = 5
#: A start that has not logged its ready line by then failed [s].
TIMEOUT_S = 60.0
#: A ROS log line's stamp: '[INFO] [1796662465.751621391] [name]: text'.
_STAMP = re.compile(r'^\[[A-Z]+\] \[(\d+\.\d+)\]')


class NodeCommand(NamedTuple):
    """How to start one tree's balance_node: the command, its environment, what it is."""

    label: str
    command: List[str]
    env: Dict[str, str]
    how: str


def install_of(package_parent: str) -> Optional[str]:
    """
    Return the colcon install prefix whose package folder is ``package_parent``, else None.

    An install keeps the package in <prefix>/lib/pythonX.Y/site-packages and the executables
    ``ros2 run`` starts in <prefix>/lib/wheelleg_balance.
    """
    parts = os.path.normpath(package_parent).split(os.sep)
    if len(parts) >= 3 and parts[-1] == 'site-packages' and parts[-3] == 'lib':
        prefix = os.sep.join(parts[:-3]) or os.sep
        if os.path.isfile(executable(prefix)):
            return prefix
    return None


def executable(prefix: str) -> str:
    """Return the balance_node executable of the install ``prefix`` (what ros2 run starts)."""
    return os.path.join(prefix, 'lib', 'wheelleg_balance', 'balance_node')


def tree_command(tree: Optional[str], env: Dict[str, str], label: str = '') -> NodeCommand:
    """
    Return how to start the balance_node of ``tree`` as ``ros2 run`` would.

    tree: a source tree (its colcon install ``.colcon/install/wheelleg_balance`` is used when
    it has one, else its source with ``python -P -m``); None: this package (its install's
    executable when it runs from one).
    """
    env = dict(env)
    if tree is None:
        from ...processes import package_root
        parent = package_root()
        prefix = install_of(parent)
        source = parent
    else:
        tree = os.path.abspath(tree)
        prefix = os.path.join(tree, '.colcon', 'install', 'wheelleg_balance')
        site = os.path.join(prefix, 'lib', 'python%d.%d' % sys.version_info[:2],
                            'site-packages')
        prefix = install_of(site)
        source = site if prefix else tree
    # The tree's package first on the path (the executable's entry point looks it up there),
    # its share folder first for ament_index (the intake's DDS profile).
    env['PYTHONPATH'] = os.pathsep.join(p for p in (source, env.get('PYTHONPATH')) if p)
    if prefix:
        env['AMENT_PREFIX_PATH'] = os.pathsep.join(
            p for p in (prefix, env.get('AMENT_PREFIX_PATH')) if p)
        return NodeCommand(label or tree or 'this tree', [executable(prefix)], env,
                           'installed executable ' + executable(prefix))
    return NodeCommand(label or tree or 'this tree',
                       [sys.executable, '-P', '-m', 'wheelleg_balance.nodes.balance_node'],
                       env, 'python -P -m wheelleg_balance.nodes.balance_node on ' + source)


def node_arguments(namespace: str, group: str, port: int) -> List[str]:
    """Return the ROS arguments of a start: its own namespace and udp_multicast bus."""
    return ['--ros-args', '-r', '__ns:=' + namespace, '-p', 'can.interface:=udp_multicast',
            '-p', 'can.channel:=' + group, '-p', 'can.udp_port:=%d' % port]


def ready_stamp(line: str) -> Optional[float]:
    """
    Return the stamp [s, wall clock] of the ready line ``line``, NaN if it has none; else None.

    None: ``line`` is not the ready line.
    """
    if READY_MARK not in line:
        return None
    m = _STAMP.match(line.strip())
    return float(m.group(1)) if m else float('nan')


def cpu_by_process(root_pid: int) -> Dict[str, float]:
    """Return the CPU seconds of the node's processes so far: {role: s}."""
    from .node import tree_cpu_seconds
    out: Dict[str, float] = {}
    for pid, (name, seconds) in tree_cpu_seconds(root_pid).items():
        name = 'ros_shell' if pid == root_pid else name
        out[name] = out.get(name, 0.0) + seconds
    return out


def time_start(node: NodeCommand, args: Sequence[str], timeout: float = TIMEOUT_S) -> Dict:
    """
    Start the node once, time it to its ready line, stop it; return the figures.

    ready_s: from just before the process is created to the ready line's stamp [s] (the time
    the line was read when it has no stamp); seen_s: to the moment it was read; cpu_s: CPU
    seconds of each process by then. RuntimeError with the output if it never gets ready.
    """
    wall0, t0 = time.time(), time.monotonic()
    # From a folder of no package: trees older than 8d01ec0 start their children with
    # ``python -m`` (the working folder first on the path), which would run this one's.
    proc = subprocess.Popen(node.command + list(args), env=node.env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, cwd=tempfile.gettempdir())
    lines: List[str] = []
    pending = b''
    try:
        while True:
            left = timeout - (time.monotonic() - t0)
            if left <= 0 or not select.select([proc.stdout], [], [], left)[0]:
                raise RuntimeError('no ready line within %.0f s:\n%s'
                                   % (timeout, ''.join(lines[-20:])))
            chunk = os.read(proc.stdout.fileno(), 65536)
            if not chunk:
                raise RuntimeError('balance_node ended before its ready line (exit %s):\n%s'
                                   % (proc.wait(), ''.join(lines[-20:])))
            seen = time.monotonic() - t0
            pending += chunk
            *complete, pending = pending.split(b'\n')
            for raw in complete:
                line = raw.decode(errors='replace') + '\n'
                lines.append(line)
                stamp = ready_stamp(line)
                if stamp is not None:
                    cpu = cpu_by_process(proc.pid)
                    ready = stamp - wall0 if stamp == stamp else seen
                    return {'ready_s': ready, 'seen_s': seen, 'cpu_s': cpu}
    finally:
        _stop(proc)


def _stop(proc: subprocess.Popen) -> None:
    from ...processes import end_process
    end_process(proc, signal.SIGINT, 10.0, then=(signal.SIGTERM,))
    proc.stdout.close()


def run_order(runs: int, trees: int) -> List[int]:
    """
    Return the order of the starts: tree indices, ``runs`` rounds of every tree.

    Each round takes every tree once, the first tree of the round moving on by one every
    round (0 1 2, 1 2 0, 2 0 1, ...): none always starts first after the previous one's end.
    """
    order = []
    for k in range(runs):
        order += [(k + i) % trees for i in range(trees)]
    return order


def summary(starts: Sequence[Dict]) -> Dict:
    """Return the figures of a tree's starts: median, lowest, highest [s], each start's."""
    times = [s['ready_s'] for s in starts]
    cpu: Dict[str, List[float]] = {}
    for s in starts:
        for name, seconds in s['cpu_s'].items():
            cpu.setdefault(name, []).append(seconds)
    return {'n': len(times), 'median_s': statistics.median(times), 'min_s': min(times),
            'max_s': max(times), 'ready_s': times,
            'cpu_median_s': {k: statistics.median(v) for k, v in sorted(cpu.items())},
            'cpu_total_median_s': statistics.median(sum(s['cpu_s'].values()) for s in starts)}


def run(nodes: Sequence[NodeCommand], runs: int = RUNS, timeout: float = TIMEOUT_S,
        log=None) -> Dict:
    """Time ``runs`` starts of each node, taking turns (``run_order``); figures per node."""
    group = '239.74.164.%d' % random.randint(10, 250)
    port = random.randint(40000, 49999)
    starts: List[List[Dict]] = [[] for _ in nodes]
    for n, k in enumerate(run_order(runs, len(nodes))):
        args = node_arguments('/start_%d_%d' % (os.getpid(), n), group, port)
        result = time_start(nodes[k], args, timeout)
        starts[k].append(result)
        if log is not None:
            log('[start] %s: %.3f s' % (nodes[k].label, result['ready_s']))
    return {'runs': runs, 'target_s': TARGET_S, 'bus': 'udp_multicast',
            'trees': [dict(label=node.label, how=node.how, **summary(s))
                      for node, s in zip(nodes, starts)]}


def targets(report: Dict) -> List[Dict]:
    """Return the pass/fail row of this tree's median start (the first tree of the report)."""
    first = report['trees'][0]
    value = first['median_s']
    return [dict(name='start to ready, median of %d' % first['n'], unit='s', value=value,
                 limit=TARGET_S, **{'pass': value <= TARGET_S})]


def print_report(report: Dict, w) -> None:
    """Print the start part's table."""
    w('\nstart: from the balance_node executable to its ready line, %d starts per tree, '
      'taking turns [s]\n' % report['runs'])
    w('  %-34s %8s %8s %8s   %s\n' % ('tree', 'median', 'min', 'max',
                                      'CPU by then, medians [s]'))
    for t in report['trees']:
        w('  %-34s %8.3f %8.3f %8.3f   %s\n' % (
            t['label'][-34:], t['median_s'], t['min_s'], t['max_s'],
            ', '.join('%s %.2f' % kv for kv in t['cpu_median_s'].items())))
    for t in report['trees']:
        w('  %s: %s; starts %s\n' % (t['label'], t['how'],
                                     ' '.join('%.3f' % v for v in t['ready_s'])))


def main(argv=None) -> int:
    """Time the starts of this tree's node and of each ``--tree``; print and write them."""
    parser = argparse.ArgumentParser(description='balance_node: from the executable to its '
                                     'ready line, median of N starts per tree')
    parser.add_argument('--runs', type=int, default=RUNS, help='starts per tree (default 5)')
    parser.add_argument('--tree', action='append', default=[], metavar='DIR',
                        help='also time the node of this source tree (its colcon install '
                        'if it has one); repeatable')
    parser.add_argument('--output', default=os.path.join('output', 'start.json'))
    args = parser.parse_args(argv)
    if args.runs < 1:
        parser.error('--runs must be >= 1')
    from . import host
    env = host.package_env()
    nodes = [tree_command(None, env)] + [tree_command(t, env) for t in args.tree]
    report = {'date': datetime.datetime.now().isoformat(timespec='seconds'),
              'machine': host.machine()}
    report.update(run(nodes, args.runs, log=lambda s: print(s, flush=True)))
    report['targets'] = targets(report)
    os.makedirs(os.path.dirname(os.path.abspath(args.output)), exist_ok=True)
    with open(args.output, 'w') as f:
        json.dump(report, f, indent=2)
        f.write('\n')
    print_report(report, sys.stdout.write)
    print('\nreport: %s' % os.path.abspath(args.output))
    return 0


if __name__ == '__main__':
    sys.exit(main())
