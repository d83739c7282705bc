"""
How much the machine kept runnable tasks from a CPU over a window.

The evidence that lets a timing-dependent test attribute a late or missing reaction to the
machine, not to the node.

Two of the kernel's own counters, both system-wide:

- CPU pressure (PSI, ``/proc/pressure/cpu``, Linux >= 4.20): the share of wall time in which
  at least one runnable task waited for a CPU ("some"; kernel docs,
  Documentation/accounting/psi.rst). None where the kernel has no PSI.
- steal time (``/proc/stat``, the 8th value of the ``cpu`` line): the share of CPU time the
  hypervisor gave to other guests while this VM had work (man 5 proc).

docs/faults.md gives the figures of quiet and loaded runs that the thresholds of
test/test_faults.py come from.
"""
from collections import deque
import threading
import time
from typing import Deque, Dict, Optional, Tuple

PRESSURE = '/proc/pressure/cpu'
STAT = '/proc/stat'


def _pressure_us() -> Optional[int]:
    """Return PSI's cumulative 'some' CPU stall time [us], or None without PSI."""
    try:
        with open(PRESSURE) as f:
            some = f.readline()
    except OSError:
        return None
    return int(some.rsplit('total=', 1)[1])


def _steal_jiffies() -> Optional[Tuple[int, int]]:
    """Return (steal, all) jiffies of all CPUs from /proc/stat, or None where unreadable."""
    try:
        with open(STAT) as f:
            values = [int(v) for v in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    # user nice system idle iowait irq softirq steal guest guest_nice: guest time is already
    # counted in user/nice, so the sum stops at steal.
    return (values[7], sum(values[:8])) if len(values) >= 8 else None


class CpuContention:
    """
    CPU pressure and steal time over a window: from construction to ``figures()``.

    ``figures()`` returns {'cpu_pressure_pct', 'cpu_steal_pct'} [% of the window], each None
    where the machine does not count it.
    """

    def __init__(self):
        self._t0 = time.monotonic()
        self._pressure0 = _pressure_us()
        self._steal0 = _steal_jiffies()

    def figures(self) -> Dict[str, Optional[float]]:
        """Return {'cpu_pressure_pct', 'cpu_steal_pct'} from construction to now."""
        return _shares(time.monotonic() - self._t0, self._pressure0, _pressure_us(),
                       self._steal0, _steal_jiffies())


def _shares(elapsed: float, p0: Optional[int], p1: Optional[int],
            s0: Optional[Tuple[int, int]], s1: Optional[Tuple[int, int]]
            ) -> Dict[str, Optional[float]]:
    """CPU pressure and steal [%] between two readings of the counters ``elapsed`` [s] apart."""
    out: Dict[str, Optional[float]] = {'cpu_pressure_pct': None, 'cpu_steal_pct': None}
    if p0 is not None and p1 is not None and elapsed > 0.0:
        out['cpu_pressure_pct'] = round(100.0 * 1e-6 * (p1 - p0) / elapsed, 1)
    if s0 is not None and s1 is not None and s1[1] > s0[1]:
        out['cpu_steal_pct'] = round(100.0 * (s1[0] - s0[0]) / (s1[1] - s0[1]), 1)
    return out


class CpuHistory:
    """
    The counters read every ``period`` [s] in a thread: the contention over any past window.

    What a test needs to judge the machine *before* it injected a fault (the node's own
    reaction to the fault cannot then count as contention). ``window(t0, t1)`` uses the
    readings nearest to the two monotonic times; ``keep`` [s] of readings are kept.
    """

    def __init__(self, period: float = 0.1, keep: float = 120.0):
        self.period = period
        self._readings: Deque[Tuple[float, Optional[int], Optional[Tuple[int, int]]]] = \
            deque(maxlen=max(2, int(keep / period)))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='cpu_history', daemon=True)

    def __enter__(self) -> 'CpuHistory':
        self._read()
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def _read(self) -> None:
        self._readings.append((time.monotonic(), _pressure_us(), _steal_jiffies()))

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            self._read()

    def window(self, t0: float, t1: float) -> Dict[str, Optional[float]]:
        """Return {'cpu_pressure_pct', 'cpu_steal_pct'} over [t0, t1] (None where unknown)."""
        self._read()
        readings = list(self._readings)

        def nearest(t):
            return min(readings, key=lambda r: abs(r[0] - t))
        a, b = nearest(t0), nearest(t1)
        return _shares(b[0] - a[0], a[1], b[1], a[2], b[2])


def contended(figures: Dict[str, Optional[float]], pressure_pct: float,
              steal_pct: float) -> bool:
    """Whether ``figures`` (CpuContention.figures) reach either threshold [%]."""
    pressure, steal = figures.get('cpu_pressure_pct'), figures.get('cpu_steal_pct')
    return (pressure is not None and pressure >= pressure_pct) or \
        (steal is not None and steal >= steal_pct)
