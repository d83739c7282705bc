"""
Timing statistics of the benchmark, computed the same way for every loop that is measured.

Inputs are event times in nanoseconds (one event per tick: a loop's wake-up, or a CAN frame's
kernel receive time). Definitions (docs/benchmarks.md):

- rate: (n - 1) / (t_last - t_first) [Hz];
- period: differences of consecutive events, median / p99 / p99.9 / max [ms];
- late share: the share of 2 ms deadlines not served within 1 ms. The deadline grid is not
  known from outside a process, so each one-second block of the run gets the grid phase that
  the events serve best; a deadline is served when an event falls in [deadline, deadline +
  1 ms]. A loop that catches up after a stall serves the deadlines it passed late; a loop that
  skips them leaves them unserved: both count as late, so the figure is fair to either policy.
  For a loop that knows its own deadlines (the floor) this agrees with its own count of ticks
  more than 1 ms late (the benchmark reports both).
"""
import math
import os
from typing import Dict, Optional

import numpy as np

NS_PER_MS = 1e6


def summary_us(samples_ns) -> Dict[str, float]:
    """Median / p99 / max of durations given in ns, in microseconds."""
    a = np.asarray(samples_ns, dtype=np.float64) / 1e3
    if a.size == 0:
        return {'n': 0, 'median_us': math.nan, 'p99_us': math.nan, 'max_us': math.nan}
    return {'n': int(a.size), 'median_us': float(np.median(a)),
            'p99_us': float(np.percentile(a, 99)), 'max_us': float(a.max())}


def period_stats(t_ns, period_ns: int = 2_000_000, late_ns: int = 1_000_000) -> Dict:
    """
    Rate, period percentiles and late share of a sorted series of event times [ns].

    Returns {'n', 'duration_s', 'rate_hz', 'period_median_ms', 'period_p99_ms',
    'period_p999_ms', 'period_max_ms', 'late_share', 'missed_deadlines', 'deadlines'}.
    """
    t = np.asarray(t_ns, dtype=np.int64)
    out = {'n': int(t.size)}
    if t.size < 3:
        raise ValueError('need at least 3 events, got %d' % t.size)
    span = int(t[-1] - t[0])
    d = np.diff(t).astype(np.float64) / NS_PER_MS
    served, total = served_deadlines(t, period_ns, late_ns)
    out.update({
        'duration_s': span / 1e9,
        'rate_hz': (t.size - 1) * 1e9 / span,
        'period_median_ms': float(np.median(d)),
        'period_p99_ms': float(np.percentile(d, 99)),
        'period_p999_ms': float(np.percentile(d, 99.9)),
        'period_max_ms': float(d.max()),
        'late_share': 1.0 - served / total,
        'missed_deadlines': int(total - served),
        'deadlines': int(total),
    })
    return out


def served_deadlines(t_ns, period_ns: int = 2_000_000, late_ns: int = 1_000_000,
                     block_periods: int = 500, phase_step_ns: int = 10_000):
    """
    Count the deadlines served within late_ns by the events t_ns (sorted) -> (served, total).

    Per block of block_periods deadlines, every phase in [0, period) on a phase_step_ns grid
    is tried and the one serving the most deadlines kept (see the module docstring).
    """
    t = np.asarray(t_ns, dtype=np.int64)
    t0, t_end = int(t[0]), int(t[-1])
    n_deadlines = (t_end - t0) // period_ns  # the last deadline must have had its chance
    phases = np.arange(0, period_ns, phase_step_ns, dtype=np.int64)
    served = total = 0
    for k0 in range(0, n_deadlines, block_periods):
        k = np.arange(k0, min(k0 + block_periods, n_deadlines), dtype=np.int64)
        deadlines = t0 + k[None, :] * period_ns + phases[:, None]  # (phases, deadlines)
        keep = deadlines + late_ns <= t_end
        idx = np.searchsorted(t, deadlines.ravel()).reshape(deadlines.shape)
        nxt = t[np.minimum(idx, t.size - 1)]
        hit = (idx < t.size) & (nxt <= deadlines + late_ns) & keep
        best = int(np.argmax(hit.sum(axis=1)))
        served += int(hit[best].sum())
        total += int(keep[best].sum())
    return served, max(total, 1)


def _stat_cpu(path: str):
    """(command name, user + system CPU seconds) from a /proc stat file."""
    with open(path) as f:
        stat = f.read()
    # Fields after the parenthesised command name (which may hold spaces): utime is the 14th
    # field of the line, stime the 15th (proc(5)).
    fields = stat[stat.rindex(')') + 2:].split()
    comm = stat[stat.index('(') + 1:stat.rindex(')')]
    return comm, (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def proc_cpu_seconds(pid: Optional[int] = None) -> float:
    """User + system CPU time of a whole process (all threads) from /proc/<pid>/stat [s]."""
    return _stat_cpu('/proc/%s/stat' % ('self' if pid is None else pid))[1]


def thread_cpu_seconds(pid: int) -> Dict[int, tuple]:
    """{thread id: (thread name, CPU seconds)} of every thread of process pid."""
    out = {}
    for tid in os.listdir('/proc/%d/task' % pid):
        try:
            out[int(tid)] = _stat_cpu('/proc/%d/task/%s/stat' % (pid, tid))
        except (OSError, ValueError):
            pass  # the thread ended meanwhile
    return out


def thread_cpu_percent(pid: int, before: Dict[int, tuple], after: Dict[int, tuple],
                       wall_s: float, top: int = 6) -> list:
    """
    List the busiest threads between two thread_cpu_seconds samples, percent of one core.

    The main thread (thread id = pid) is named 'main'; others keep their kernel name (python
    threads are all called 'python' unless the program names them with prctl).
    """
    rows = []
    for tid, (comm, cpu1) in after.items():
        if tid in before:
            rows.append({'tid': tid, 'name': 'main' if tid == pid else comm,
                         'cpu_percent': 100.0 * (cpu1 - before[tid][1]) / wall_s})
    rows.sort(key=lambda r: -r['cpu_percent'])
    return rows[:top]


def cpu_percent(cpu_start_s: float, cpu_end_s: float, wall_s: float) -> float:
    """CPU use in percent of one core over a wall-clock interval."""
    return 100.0 * (cpu_end_s - cpu_start_s) / wall_s


def check(value: float, limit: float, lower_is_better: bool = True) -> Dict:
    """Make a pass/fail row: {'value', 'limit', 'pass'} (NaN never passes)."""
    ok = value <= limit if lower_is_better else value >= limit
    return {'value': value, 'limit': limit, 'pass': bool(ok and math.isfinite(value))}
