"""
Soak benchmark: balance_node's 2 ms loop while ROS participants come and go.

Issue 14: a process that publishes through Fast DDS's shared-memory transport can be held for
0.33 s, 1 s or 2 s when other participants join and leave, and rclpy keeps the GIL through it,
so every Python thread of that process stops (docs/benchmarks.md, "The 0.33 s stall").
balance_node runs its tick in a process without rclpy (nodes/control_process.py); this run
shows whether that holds, beside a node that does not (``--baseline``).

One run, every process on localhost, ROS isolated by the caller's ROS_DOMAIN_ID:

- each node under test is a bench/node.py Session: balance_node balancing on a udp_multicast
  CAN bus of its own, a plant streaming ``imu`` at 500 Hz (publisher-only and UDP-only, so the
  plant itself does not stall: nodes/dds.py) and the motors (sim/motor_emulator.py's
  MitMotorBank) in a process that records every frame with its kernel receive time;
- ``--baseline DIR``: the same, first, for the node of another source tree (e.g. ``git
  worktree add /tmp/soak-base b9532c0``, the main of issue 14 with the loop in the node's
  process; its wheel speeds come from joint_states and it has two motors). The two nodes run
  one after the other, each with churn of its own: a 2-core machine does not hold two nodes,
  their plants and the churn at once without starving them all;
- a churn process (``churn``) with ROS's default transports (shared memory included, as the
  ``ros2`` tools have): every ``--churn-period`` s (2) it makes and ends four participants at
  once, each against every node under test: an ``~/arm`` call (true: the node already
  balances), a parameter get and set (``yaw_rate_gain`` to the value it has), a subscription to
  ``~/state`` until one message, a node joining and leaving. Every ``--kill-every``-th cycle (4)
  it also starts a participant process and SIGKILLs it 1 to 3 s later (an operator's tool
  killed: a dead process's shared-memory ports and locks stay behind);
- a slow reliable subscriber (``slow``) of every node's ``~/state`` that takes SLOW_CALLBACK
  per message;
- this process reads ``/diagnostics`` throughout (the nodes' own loop counters);
- a floor loop beside each node (bench/loops.py, no ROS, the loop's priority): what the
  machine's load alone does to a 2 ms Python loop in the same minutes.

The plants are test infrastructure on a shared machine: their threads run SCHED_FIFO
(``--plant-priority``, 40: below the loop's 50) so that a starved plant is not taken for a
stalled node, and the recorder's socket has a large receive buffer; the kernel's count of
datagrams it dropped (``recorder_receive_drops``) must be 0 for the frame gaps to be the
node's.

Figures per node (JSON and printed): deadlines skipped (the node's overrun counter, in the
window and since start, i.e. with the arming), the longest tick gap (the node's own period
maximum, every diagnostics message of the window), the longest torque-frame gap on the bus per
wheel (the listener's receive times: what the motors saw), and the longest sensor-to-frame
latency (bench/node.py's probes: a pitch-rate step every 20 ms to the first wheel frame past
half-way; a probe whose step never shows before the next one is counted lost). Targets (issue
14): no torque-frame gap over 10 ms, no deadline skipped.

    python -m wheelleg_balance.validation.bench.soak [--duration 600] [--baseline DIR]
        [--realtime-priority 50] [--output output/soak.json]
"""
import argparse
import datetime
import json
import math
import os
import random
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from typing import Dict, List, Optional, Sequence

import numpy as np

from . import node as bench_node
from .. import json_safe

#: What the slow subscriber spends on each ~/state message [s] (the node publishes 100 Hz).
SLOW_CALLBACK = 0.05
#: A torque-frame gap over this [ms] is a stall (issue 14's target).
GAP_TARGET_MS = 10.0
#: The parameter the churn gets and sets (writable in every tree measured; set to its value).
PARAMETER = 'yaw_rate_gain'
MODULE = 'wheelleg_balance.validation.bench.soak'
#: What each churn cycle does, a participant each (see run_participants).
OPS = ('arm', 'param', 'state', 'join')
#: A FAULT line of a node's log: wall-clock seconds, nanoseconds, the reason.
_FAULT_LINE = re.compile(r'\[(\d+)\.(\d+)\] \[[^\]]*\]: FAULT: (.*)$')
#: balance_node's node name (its ~/ names are under <namespace>/<name>).
NODE_NAME = 'balance_node'


# --------------------------------------------------------------------------- figures

def longest_gap_ms(t_ns) -> float:
    """Return the longest interval between consecutive times [ms] (NaN for fewer than two)."""
    t = np.asarray(t_ns, dtype=np.int64)
    return float(np.max(np.diff(t))) / 1e6 if t.size > 1 else math.nan


def gaps_over(t_ns, limit_ms: float) -> List[tuple]:
    """Return the gaps longer than limit_ms as (start t_ns, length [ms]), in time order."""
    t = np.asarray(t_ns, dtype=np.int64)
    d = np.diff(t)
    idx = np.flatnonzero(d > limit_ms * 1e6)
    return [(int(t[i]), float(d[i]) / 1e6) for i in idx]


def counter_delta(samples: Sequence[tuple], t0_ns: int, t1_ns: int) -> float:
    """
    Return how much a counter grew over [t0_ns, t1_ns] from (t_ns, value) samples.

    The last sample at or before t0_ns (else the first in the window) is the start, the last
    in the window the end; NaN without samples in the window.
    """
    before = [v for t, v in samples if t <= t0_ns and math.isfinite(v)]
    inside = [v for t, v in samples if t0_ns < t <= t1_ns and math.isfinite(v)]
    if not inside:
        return math.nan
    start = before[-1] if before else inside[0]
    return inside[-1] - start


def window_max(samples: Sequence[tuple], t0_ns: int, t1_ns: int) -> float:
    """Return the largest value of (t_ns, value) samples inside [t0_ns, t1_ns] (NaN: none)."""
    values = [v for t, v in samples if t0_ns <= t <= t1_ns and math.isfinite(v)]
    return max(values) if values else math.nan


def _number(text) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan


# ------------------------------------------------------------------------- diagnostics

class DiagnosticsLog(threading.Thread):
    """
    Every balance_node diagnostics status on /diagnostics, with its receive time.

    ``series(hardware_id, status, key)`` -> [(t_ns, value)]. A reader only: a stall of this
    process delays the messages (they are queued), it changes no figure of the nodes.
    """

    def __init__(self, depth: int = 100):
        super().__init__(name='soak_diagnostics', daemon=True)
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
        from diagnostic_msgs.msg import DiagnosticArray
        self._rclpy = rclpy
        self.context = Context()
        rclpy.init(args=[], context=self.context,
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node('soak_diagnostics', context=self.context)
        self.records: List[tuple] = []   # (t_ns, hardware_id, status name, {key: value})
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on, depth)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._halt = threading.Event()

    def _on(self, msg) -> None:
        t = time.time_ns()
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            values['message'] = status.message
            self.records.append((t, status.hardware_id, status.name, values))

    def run(self) -> None:
        """Spin until stop()."""
        while not self._halt.is_set():
            self.executor.spin_once(timeout_sec=0.1)

    def stop(self) -> None:
        """Stop spinning and end the participant."""
        self._halt.set()
        self.join(timeout=5.0)
        self.executor.shutdown()
        self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.context)

    def series(self, hardware_id: str, status: str, key: str) -> List[tuple]:
        """Return [(t_ns, value)] of one key of one node's status."""
        return [(t, _number(v.get(key))) for t, h, s, v in list(self.records)
                if h == hardware_id and s == status]

    def last(self, hardware_id: str, status: str, until_ns: int) -> Dict[str, str]:
        """Return the last values of one node's status received by until_ns ({} if none)."""
        for t, h, s, v in reversed(list(self.records)):
            if h == hardware_id and s == status and t <= until_ns:
                return v
        return {}


# -------------------------------------------------------------------- churn processes

def run_participants(namespaces: Sequence[str], timeout: float = 3.0) -> Dict[str, str]:
    """
    Be four ``ros2`` commands at once, one participant each; return what each op did.

    Default transports (shared memory included), as the ROS tools have. Never raises for a
    node that does not answer (the result says so).
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from rcl_interfaces.msg import Parameter
    from rcl_interfaces.srv import GetParameters, SetParameters
    from std_msgs.msg import Float64MultiArray
    from std_srvs.srv import SetBool

    results = {}

    def call(executor, node, srv_type, name, request):
        client = node.create_client(srv_type, name)
        if not client.wait_for_service(timeout_sec=timeout):
            return None
        future = client.call_async(request)
        executor.spin_until_future_complete(future, timeout_sec=timeout)
        return future.result() if future.done() else None

    def one(op):
        context = Context()
        rclpy.init(args=[], context=context, signal_handler_options=SignalHandlerOptions.NO)
        t0 = time.monotonic()
        outcome = []
        try:
            node = rclpy.create_node('soak_%s_%d' % (op, os.getpid()), context=context)
            executor = SingleThreadedExecutor(context=context)
            executor.add_node(node)
            for ns in namespaces:
                if op == 'arm':
                    reply = call(executor, node, SetBool, ns + '/arm', SetBool.Request(data=True))
                    outcome.append('ok' if reply is not None else 'no reply')
                elif op == 'param':
                    got = call(executor, node, GetParameters, ns + '/get_parameters',
                               GetParameters.Request(names=[PARAMETER]))
                    if got is None or not got.values:
                        outcome.append('no reply')
                        continue
                    request = SetParameters.Request(
                        parameters=[Parameter(name=PARAMETER, value=got.values[0])])
                    reply = call(executor, node, SetParameters, ns + '/set_parameters', request)
                    ok = reply is not None and reply.results and reply.results[0].successful
                    outcome.append('ok' if ok else 'not set')
                elif op == 'state':
                    got = []
                    sub = node.create_subscription(Float64MultiArray, ns + '/state',
                                                   got.append, 10)
                    end = time.monotonic() + timeout
                    while not got and time.monotonic() < end:
                        executor.spin_once(timeout_sec=0.05)
                    node.destroy_subscription(sub)
                    outcome.append('ok' if got else 'no message')
                else:
                    end = time.monotonic() + 0.3
                    while time.monotonic() < end:
                        executor.spin_once(timeout_sec=0.05)
                    outcome.append('ok')
            executor.shutdown()
            node.destroy_node()
        except Exception as exc:  # noqa: B902 -- a churn op reports, it never ends the churn
            outcome.append('error %r' % (exc,))
        finally:
            rclpy.try_shutdown(context=context)
        results[op] = '%s %.2f s' % (','.join(outcome), time.monotonic() - t0)

    # The four at once, each with a participant of its own (as four ros2 commands would be).
    threads = [threading.Thread(target=one, args=(op,)) for op in OPS]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return results


def run_churn(namespaces: Sequence[str], period: float, kill_every: int, log: str) -> None:
    """
    Make participants every period s until SIGINT/SIGTERM; log each cycle (JSON lines).

    Each cycle runs ``run_participants`` here (four participants made and ended); every
    kill_every-th cycle also starts a participant process and SIGKILLs it 1 to 3 s later (in
    its start-up or its calls: a dead process's shared-memory ports and locks stay behind).
    """
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    rng = random.Random(14)
    cmd = [sys.executable, '-m', MODULE, 'participant', '--namespaces', ','.join(namespaces)]
    victims: List[tuple] = []   # (process, kill at [s])
    cycle = 0
    with open(log, 'w') as out:
        next_start = time.monotonic()
        while not stop.is_set():
            cycle += 1
            t0 = time.monotonic()
            if kill_every and cycle % kill_every == 0:
                victims.append((subprocess.Popen(cmd, stdout=subprocess.DEVNULL,
                                                 stderr=subprocess.DEVNULL),
                                t0 + rng.uniform(1.0, 3.0)))
            ops = run_participants(namespaces)
            for entry in list(victims):
                proc, kill_at = entry
                if time.monotonic() >= kill_at or proc.poll() is not None:
                    ended_by_itself = proc.poll() is not None
                    proc.kill()
                    proc.wait()
                    victims.remove(entry)
                    out.write(json.dumps({'killed_process': proc.pid,
                                          'ended_before_kill': ended_by_itself}) + '\n')
            out.write(json.dumps({'cycle': cycle, 't_ns': time.time_ns(),
                                  'took_s': round(time.monotonic() - t0, 3), 'ops': ops}) + '\n')
            out.flush()
            next_start = max(next_start + period, time.monotonic())
            stop.wait(max(0.0, next_start - time.monotonic()))
        for proc, _ in victims:
            proc.kill()
            proc.wait()


def run_slow(namespaces: Sequence[str], callback_s: float = SLOW_CALLBACK) -> None:
    """Subscribe (reliable, depth 10) to every ~/state and take callback_s per message."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import Float64MultiArray

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    rclpy.init(args=[], signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('soak_slow_subscriber')
    for ns in namespaces:
        node.create_subscription(Float64MultiArray, ns + '/state',
                                 lambda _: time.sleep(callback_s), 10)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    while not stop.is_set():
        executor.spin_once(timeout_sec=0.1)
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()


# ------------------------------------------------------------------------------- run

def node_figures(session: bench_node.Session, diag: DiagnosticsLog, t0_ns: int,
                 t1_ns: int) -> Dict:
    """Return one node's soak figures over [t0_ns, t1_ns] (after session.stop)."""
    result = session.analyse(t0_ns, t1_ns)
    rec = session.recording()
    hw, loop = session.hardware_id, bench_node.LOOP_STATUS
    wheels = {}
    for motor_id in bench_node.WHEEL_IDS:
        t, _ = rec.commands(motor_id, t0_ns, t1_ns)
        gaps = gaps_over(t, GAP_TARGET_MS)
        wheels[str(motor_id)] = {'longest_gap_ms': longest_gap_ms(t), 'gaps_over_10ms': len(gaps),
                                 'gaps_over_100ms': sum(1 for _, g in gaps if g > 100.0),
                                 'gaps_over_250ms': sum(1 for _, g in gaps if g > 250.0),
                                 'longest_gaps': sorted(gaps, key=lambda x: -x[1])[:20]}
    overruns = diag.series(hw, loop, 'overruns')
    lat = result['latency']
    figures = {
        'deadlines_skipped': counter_delta(overruns, t0_ns, t1_ns),
        'deadlines_skipped_since_start': overruns[-1][1] if overruns else math.nan,
        'longest_tick_gap_ms': window_max(diag.series(hw, loop, 'period_max_ms'), t0_ns, t1_ns),
        'longest_torque_frame_gap_ms': max(w['longest_gap_ms'] for w in wheels.values()),
        'torque_frame_gaps_over_10ms': max(w['gaps_over_10ms'] for w in wheels.values()),
        'torque_frame_gaps_over_250ms': max(w['gaps_over_250ms'] for w in wheels.values()),
        'longest_sensor_to_frame_latency_ms': lat['max_us'] / 1e3,
        'latency_probes_lost': lat['lost'],
        'latency_probes': lat['probes'],
        'recorder_receive_drops': result['recorder_receive_drops'],
        'sensor_rate_hz': result['sensors']['rate_hz'],
        'sensor_period_max_ms': result['sensors']['period_max_ms'],
    }
    stalls = diag.series(hw, loop, 'stalls')
    if stalls:   # this tree's loop counts its own stalls (ticks > 10 ms late)
        figures['loop_stalls'] = counter_delta(stalls, t0_ns, t1_ns)
        figures['longest_stall_ms_since_start'] = window_max(
            diag.series(hw, loop, 'longest_stall_ms'), 0, t1_ns)
    shares = [m['balancing_share'] for m in result['motors'].values() if 'balancing_share' in m]
    figures['balancing_share'] = min(shares) if shares else math.nan
    figures['first_fault'] = first_fault(diag, hw, t0_ns, t1_ns)
    faults = faults_in_log(session.node_log, t0_ns, t1_ns)
    # A tree that does not log its faults (the main of issue 14) shows them in diagnostics.
    figures['faults'] = max(len(faults), fault_entries(diag, hw, t0_ns, t1_ns))
    result['faults'] = faults[:50]
    result['soak'] = figures
    result['wheels'] = wheels
    # The last status of the window: the stop that follows faults the node (sensors gone).
    result['node_loop'] = diag.last(hw, loop, t1_ns)
    safety = diag.last(hw, bench_node.SAFETY_STATUS, t1_ns)
    result['node_mode'] = safety.get('mode', 'unknown')
    result['node_faults'] = safety.get('fault_reasons', '')
    return result


def first_fault(diag: DiagnosticsLog, hardware_id: str, t0_ns: int, t1_ns: int) -> str:
    """Return when [s into the window] and why the node first faulted in it ('' if not)."""
    for t, h, name, values in list(diag.records):
        if h == hardware_id and name == bench_node.SAFETY_STATUS and t0_ns <= t <= t1_ns \
                and values.get('mode') == 'FAULT':
            return '%.1f s: %s' % ((t - t0_ns) * 1e-9, values.get('fault_reasons', ''))
    return ''


def fault_entries(diag: DiagnosticsLog, hardware_id: str, t0_ns: int, t1_ns: int) -> int:
    """Return how often the node's diagnostics went into FAULT within [t0_ns, t1_ns]."""
    count, before = 0, None
    for t, h, name, values in list(diag.records):
        if h != hardware_id or name != bench_node.SAFETY_STATUS:
            continue
        mode = values.get('mode')
        if t0_ns <= t <= t1_ns and mode == 'FAULT' and before not in (None, 'FAULT'):
            count += 1
        before = mode
    return count


def faults_in_log(path: str, t0_ns: int, t1_ns: int) -> List[tuple]:
    """
    Return the node's FAULT log lines in [t0_ns, t1_ns] as (s into the window, reason).

    Every tree logs a fault as ``[ERROR] [<sec>.<nsec>] [<node>]: FAULT: <reason>`` (rcutils'
    default format, wall-clock time): a node that is armed again (the churn's ~/arm calls do)
    can fault more than once, which the last diagnostics alone would not show.
    """
    out = []
    try:
        with open(path, errors='replace') as f:
            for line in f:
                found = _FAULT_LINE.search(line)
                if found:
                    t = int(found.group(1)) * 1_000_000_000 + int(found.group(2).ljust(9, '0'))
                    if t0_ns <= t <= t1_ns:
                        out.append(((t - t0_ns) * 1e-9, found.group(3).strip()))
    except OSError:
        pass
    return out


def targets(figures: Dict) -> Dict[str, bool]:
    """Return issue 14's targets for one node: no frame gap over 10 ms, no deadline skipped."""
    gap = figures['longest_torque_frame_gap_ms']
    skipped = figures['deadlines_skipped']
    return {'no torque-frame gap over 10 ms': bool(gap <= GAP_TARGET_MS),
            'no deadline skipped': bool(skipped == 0)}


def _address() -> tuple:
    return '239.74.164.%d' % random.randint(10, 250), random.randint(40000, 49999)


def soak_one(key: str, session: bench_node.Session, diag: DiagnosticsLog, duration: float,
             workdir: str, env: Dict[str, str], churn_period: float, kill_every: int,
             warmup: float, start_timeout: float, floor_priority: int = 0) -> Dict:
    """
    Start one node, churn beside it for ``duration`` s, stop it; return its figures.

    A floor loop (bench/loops.py: a bare Python loop to 2 ms deadlines, no ROS, at
    ``floor_priority``) runs beside it through the window: what the machine alone does to a
    2 ms loop under the same load, for reading the node's figures.
    """
    from .benchmark import _loop_command, loop_result
    floor_npz = os.path.join(workdir, 'floor_%s.npz' % key)
    helpers: List[subprocess.Popen] = []
    churn_log = os.path.join(workdir, 'churn_%s.jsonl' % key)
    ns = session.namespace + '/' + NODE_NAME   # ~/arm, ~/state: the node's own names
    error = None
    t0_ns = t1_ns = time.time_ns()
    try:
        print('[soak] %s (%s): starting ...' % (key, session.nut.label), flush=True)
        session.start(start_timeout)
        with open(os.path.join(workdir, 'slow_%s.log' % key), 'w') as log:
            helpers.append(subprocess.Popen(
                [sys.executable, '-m', MODULE, 'slow', '--namespaces', ns], env=env,
                stdout=log, stderr=subprocess.STDOUT))
            helpers.append(subprocess.Popen(
                [sys.executable, '-m', MODULE, 'churn', '--namespaces', ns, '--period',
                 str(churn_period), '--kill-every', str(kill_every), '--log', churn_log],
                env=env, stdout=log, stderr=subprocess.STDOUT))
        time.sleep(warmup)   # the helpers' start-up (imports) is not the churn
        floor = subprocess.Popen(_loop_command('floor', duration, floor_npz, floor_priority),
                                 env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        t0_ns = time.time_ns()
        print('[soak] %s: churn for %.0f s' % (key, duration), flush=True)
        end = time.monotonic() + duration
        while time.monotonic() < end:
            time.sleep(min(5.0, max(0.0, end - time.monotonic())))
            if not session.alive:
                raise RuntimeError('%s died during the run:\n%s' % (
                    key, bench_node._tail(session.node_log)))
        t1_ns = time.time_ns()
        time.sleep(1.5)   # the last diagnostics of the window arrive
        floor.wait(timeout=60)
    except (RuntimeError, subprocess.TimeoutExpired) as err:
        error = str(err)
        t1_ns = time.time_ns()
    finally:
        for proc in reversed(helpers):
            bench_node.stop_process(proc)
        session.stop()
    result = {}
    try:
        if session.node is not None:
            result = node_figures(session, diag, t0_ns, t1_ns)
    except (OSError, KeyError, ValueError, IndexError) as err:
        error = (error + '; ' if error else '') + 'analysis: %r' % (err,)
    if result:
        result['targets'] = targets(result['soak'])
        try:
            result['floor'] = loop_result(floor_npz)
            result['soak']['floor_period_max_ms'] = result['floor']['period_max_ms']
            result['soak']['floor_missed_deadlines'] = result['floor'].get('missed_deadlines')
        except (OSError, KeyError, ValueError):
            result['floor'] = {}
    result['churn'] = churn_summary(churn_log)
    result['window_s'] = (t1_ns - t0_ns) * 1e-9
    if error:
        result['error'] = error
    return result


def run(duration: float, workdir: str, env: Dict[str, str], baseline: Optional[str] = None,
        realtime_priority: int = 0, controller: str = 'ida_pbc', churn_period: float = 2.0,
        kill_every: int = 4, warmup: float = 5.0, start_timeout: float = 90.0,
        plant_priority: int = 40, node_params: Sequence[str] = ()) -> Dict:
    """
    Run the soak (see the module docstring); return the report.

    The baseline (if any) first, then this tree's node, each with churn of its own for
    ``duration`` s: one after the other, so that each has the machine to itself as far as the
    run goes (a 2-core machine cannot hold two nodes, their plants and the churn at once).
    """
    from .host import machine
    nuts = {}
    if baseline:
        path = os.path.abspath(baseline)
        nuts['baseline'] = bench_node.NodeUnderTest(motors=2, joint_states=True, tree=path,
                                                    label=path)
    nuts['node'] = bench_node.NodeUnderTest()
    report: Dict = {'date': datetime.datetime.now(datetime.timezone.utc).isoformat(
        timespec='seconds'), 'machine': machine(), 'errors': {},
        'settings': {'duration': duration, 'ops': OPS, 'baseline': baseline,
                     'controller': controller, 'realtime_priority': realtime_priority,
                     'churn_period': churn_period,
                     'kill_every': kill_every, 'slow_callback_s': SLOW_CALLBACK,
                     'plant_priority': plant_priority, 'node_params': list(node_params),
                     'ros_domain_id': env.get('ROS_DOMAIN_ID')}}
    diag = DiagnosticsLog()
    diag.start()
    try:
        for key, nut in nuts.items():
            session = bench_node.Session(
                workdir, env, *_address(), nut=nut, controller=controller,
                realtime_priority=realtime_priority, tag='_' + key,
                extra_node_args=bench_node.param_args(node_params),
                max_duration=start_timeout + warmup + duration + 60.0,
                plant_priority=plant_priority)
            result = soak_one(key, session, diag, duration, workdir, env, churn_period,
                              kill_every, warmup, start_timeout, realtime_priority)
            if 'error' in result:
                report['errors'][key] = result['error']
            report[key] = result
    finally:
        diag.stop()
    report['machine']['load_average_end'] = [round(v, 2) for v in os.getloadavg()]
    return report


def churn_summary(log: str) -> Dict:
    """Return the churn's cycles, participants made, processes killed and answered ops."""
    rows = []
    try:
        with open(log) as f:
            rows = [json.loads(line) for line in f if line.strip()]
    except (OSError, ValueError):
        pass
    cycles = [r for r in rows if 'cycle' in r]
    answered: Dict[str, int] = {}
    for row in cycles:
        for op, text in row['ops'].items():
            if all(part == 'ok' for part in text.split()[0].split(',')):
                answered[op] = answered.get(op, 0) + 1
    return {'cycles': len(cycles), 'participants': len(OPS) * len(cycles),
            'killed_processes': sum(1 for r in rows if 'killed_process' in r),
            'cycle_time_max_s': max((r['took_s'] for r in cycles), default=math.nan),
            'ops_answered': answered}


def print_report(report: Dict, out=sys.stdout) -> None:
    """Print the soak figures of every node side by side."""
    keys = [k for k in ('node', 'baseline') if report.get(k, {}).get('soak')]
    w = out.write
    s, m = report['settings'], report['machine']
    w('\nsoak, %s: participants every %.1f s (a process SIGKILLed every %d-th cycle), '
      'realtime_priority %d, plant priority %d; %d CPUs, load %s at the start, %s at the end\n'
      % (report['date'], s['churn_period'], s['kill_every'], s['realtime_priority'],
         s['plant_priority'], m['cpus'], m['load_average'], m.get('load_average_end')))
    rows = (('churn time [s]', 'window_s', '%.0f'),
            ('churn cycles', 'cycles', '%d'),
            ('processes SIGKILLed', 'killed_processes', '%d'),
            ('deadlines skipped (window)', 'deadlines_skipped', '%.0f'),
            ('deadlines skipped (since start)', 'deadlines_skipped_since_start', '%.0f'),
            ('longest tick gap [ms]', 'longest_tick_gap_ms', '%.1f'),
            ('longest torque-frame gap [ms]', 'longest_torque_frame_gap_ms', '%.1f'),
            ('torque-frame gaps > 10 ms (a wheel)', 'torque_frame_gaps_over_10ms', '%d'),
            ('torque-frame gaps > 250 ms (a wheel)', 'torque_frame_gaps_over_250ms', '%d'),
            ('longest sensor->frame [ms]', 'longest_sensor_to_frame_latency_ms', '%.1f'),
            ('latency probes lost', 'latency_probes_lost', '%d'),
            ('plant: imu rate [Hz]', 'sensor_rate_hz', '%.1f'),
            ('plant: imu period max [ms]', 'sensor_period_max_ms', '%.1f'),
            ('recorder: datagrams dropped', 'recorder_receive_drops', '%d'),
            ('balancing share of the frames', 'balancing_share', '%.3f'),
            ('faults (the churn re-arms)', 'faults', '%d'),
            ('floor beside: period max [ms]', 'floor_period_max_ms', '%.1f'),
            ('floor beside: deadlines missed', 'floor_missed_deadlines', '%d'))
    w('  %-34s' % '' + ''.join('%18s' % k for k in keys) + '\n')
    for label, key, spec in rows:
        vals = []
        for k in keys:
            r = report[k]
            v = r['soak'].get(key, r['churn'].get(key, r.get(key)))
            vals.append('-' if v is None or (isinstance(v, float) and not math.isfinite(v))
                        else spec % v)
        w('  %-34s' % label + ''.join('%18s' % v for v in vals) + '\n')
    for k in keys:
        r = report[k]
        w('%s: mode %s %s; %s\n' % (k, r['node_mode'], r['node_faults'],
                                    ', '.join('%s %s' % (n, 'PASS' if ok else 'FAIL')
                                              for n, ok in r['targets'].items())))
        w('  first fault in the window: %s\n' % (r['soak']['first_fault'] or 'none'))
        w('  churn ops answered (cycles): %s\n' % r['churn']['ops_answered'])
        w('  own diagnostics: %s\n' % r['node_loop'].get('message', ''))
        if r['node_loop'].get('realtime'):
            w('  realtime: %s\n' % r['node_loop']['realtime'])
    for part, err in report['errors'].items():
        w('%s: ERROR %s\n' % (part, err.strip().splitlines()[0] if err.strip() else err))


def main(argv=None) -> int:
    """Run the soak, or be one of its helper processes (churn, participant, slow)."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0].strip())
    parser.add_argument('role', nargs='?', default='run',
                        choices=('run', 'churn', 'participant', 'slow'))
    parser.add_argument('--duration', type=float, default=600.0, help='churn time [s]')
    parser.add_argument('--baseline', default=None, metavar='DIR',
                        help='also measure the balance_node of this source tree (a checkout '
                        'of an earlier commit) in the same run')
    parser.add_argument('--realtime-priority', type=int, default=0,
                        help="the nodes' realtime_priority (SCHED_FIFO; 0: none)")
    parser.add_argument('--plant-priority', type=int, default=40,
                        help='SCHED_FIFO priority of the plants (sensors, motors; 0: none)')
    parser.add_argument('--controller', default='ida_pbc')
    parser.add_argument('--node-param', action='append', default=[], metavar='NAME:=VALUE',
                        help='a further parameter of every node under test (repeatable)')
    parser.add_argument('--churn-period', type=float, default=2.0, help='[s]')
    parser.add_argument('--kill-every', type=int, default=4,
                        help='SIGKILL every n-th participant process (0: none)')
    parser.add_argument('--output', default=os.path.join('output', 'soak.json'))
    parser.add_argument('--workdir', default=None, help='keep the raw recordings here')
    parser.add_argument('--namespaces', default='', help='helpers: the nodes under test')
    parser.add_argument('--period', type=float, default=2.0, help='churn: [s]')
    parser.add_argument('--log', default=os.devnull, help='churn: JSON lines')
    args = parser.parse_args(argv)
    namespaces = [n for n in args.namespaces.split(',') if n]
    if args.role == 'churn':
        run_churn(namespaces, args.period, args.kill_every, args.log)
        return 0
    if args.role == 'participant':
        print(json.dumps(run_participants(namespaces)), flush=True)
        return 0
    if args.role == 'slow':
        run_slow(namespaces)
        return 0
    # The processes are ended in order also on SIGINT / SIGTERM (a background job may have
    # inherited SIGINT ignored).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    env = dict(os.environ)
    if not env.get('ROS_DOMAIN_ID'):
        print('soak: set ROS_DOMAIN_ID (a domain of its own: the run starts and ends '
              'participants)', file=sys.stderr)
        return 1
    workdir = args.workdir or tempfile.mkdtemp(prefix='soak_')
    os.makedirs(workdir, exist_ok=True)
    report = run(args.duration, workdir, env, args.baseline, args.realtime_priority,
                 args.controller, args.churn_period, args.kill_every,
                 plant_priority=args.plant_priority, node_params=args.node_param)
    report['workdir'] = workdir
    print_report(report)
    os.makedirs(os.path.dirname(os.path.abspath(args.output)), exist_ok=True)
    with open(args.output, 'w') as f:
        json.dump(json_safe(report), f, indent=1)
    print('report: %s' % args.output)
    return 1 if report['errors'] else 0


if __name__ == '__main__':
    sys.exit(main())
