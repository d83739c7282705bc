"""
The two reference loops of the benchmark, each run as its own process.

- ``floor``: a bare Python loop sleeping to absolute 2 ms deadlines (the best a Python loop
  can do on this machine; a late tick is followed at once by the next, so the rate holds);
- ``baseline``: a bare rclpy node with an empty 2 ms timer spun by a SingleThreadedExecutor
  (what a naive node gets; rcl timers skip the deadlines they missed).

Usage: ``python -m wheelleg_balance.validation.bench.loops floor|baseline --duration S
--output F``.
Writes an .npz with t_ns (monotonic wake-up time of every tick), late_ns (the loop's own
lateness: wake-up minus deadline), cpu_s (process CPU seconds at the start and end of the
loop) and wall_s. Optional ``--fifo PRIORITY`` runs the loop under SCHED_FIFO when allowed.
"""
import argparse
import time

import numpy as np

from .stats import proc_cpu_seconds
from ...core.realtime import set_fifo_priority

PERIOD_NS = 2_000_000


def floor_loop(duration_s: float, period_ns: int = PERIOD_NS):
    """Sleep to absolute deadlines for duration_s; return (t_ns, late_ns, cpu_s, wall_s)."""
    n = int(duration_s * 1e9 / period_ns)
    t = [0] * n
    late = [0] * n
    clock, sleep = time.monotonic_ns, time.sleep
    cpu0 = proc_cpu_seconds()
    start = deadline = clock() + 20_000_000
    for i in range(n):
        now = clock()
        if deadline > now:
            # Python >= 3.11 sleeps with clock_nanosleep on CLOCK_MONOTONIC.
            sleep((deadline - now) * 1e-9)
            now = clock()
        t[i] = now
        late[i] = now - deadline
        deadline += period_ns  # absolute: lateness never accumulates into the schedule
    wall = (clock() - start) * 1e-9
    return t, late, (cpu0, proc_cpu_seconds()), wall


def baseline_loop(duration_s: float, period_ns: int = PERIOD_NS):
    """Spin a node with an empty timer for duration_s; return (t_ns, late_ns, cpu_s, wall_s)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    rclpy.init()
    node = rclpy.create_node('bench_baseline')
    t, late = [], []
    clock = time.monotonic_ns

    def on_timer():
        now = clock()
        # rcl moved the timer's next call one period ahead of the deadline just served (or
        # further when it skipped some), so period - time_until_next_call is the lateness
        # on the timer's own grid.
        late.append(period_ns - timer.time_until_next_call())
        t.append(now)

    executor = SingleThreadedExecutor()
    executor.add_node(node)
    cpu0 = proc_cpu_seconds()
    start = clock()
    timer = node.create_timer(period_ns * 1e-9, on_timer)
    end = start + int(duration_s * 1e9)
    try:
        while clock() < end:
            executor.spin_once(timeout_sec=0.1)
    finally:
        wall = (clock() - start) * 1e-9
        cpu1 = proc_cpu_seconds()
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown()
    return t, late, (cpu0, cpu1), wall


def main(argv=None):
    """Run one loop and write its .npz (see the module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('loop', choices=('floor', 'baseline'))
    parser.add_argument('--duration', type=float, required=True, help='seconds')
    parser.add_argument('--output', required=True, help='.npz path')
    parser.add_argument('--fifo', type=int, default=0, help='SCHED_FIFO priority (0: none)')
    args = parser.parse_args(argv)
    fifo_ok, fifo_msg = set_fifo_priority(args.fifo)
    loop = floor_loop if args.loop == 'floor' else baseline_loop
    t, late, cpu, wall = loop(args.duration)
    np.savez(args.output, t_ns=np.asarray(t, dtype=np.int64),
             late_ns=np.asarray(late, dtype=np.int64), cpu_s=np.asarray(cpu), wall_s=wall,
             fifo=np.asarray([fifo_ok]), fifo_message=np.asarray(fifo_msg))


if __name__ == '__main__':
    main()
