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
import time
from typing import Dict, Optional, Tuple

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
        elapsed = time.monotonic() - self._t0
        pressure, steal = _pressure_us(), _steal_jiffies()
        out: Dict[str, Optional[float]] = {'cpu_pressure_pct': None, 'cpu_steal_pct': None}
        if pressure is not None and self._pressure0 is not None and elapsed > 0.0:
            out['cpu_pressure_pct'] = round(100.0 * 1e-6 * (pressure - self._pressure0)
                                            / elapsed, 1)
        if steal is not None and self._steal0 is not None and steal[1] > self._steal0[1]:
            out['cpu_steal_pct'] = round(100.0 * (steal[0] - self._steal0[0])
                                         / (steal[1] - self._steal0[1]), 1)
        return out


def contended(figures: Dict[str, Optional[float]], pressure_pct: float,
              steal_pct: float) -> bool:
    """Whether ``figures`` (CpuContention.figures) reach either threshold [%]."""
    pressure, steal = figures.get('cpu_pressure_pct'), figures.get('cpu_steal_pct')
    return (pressure is not None and pressure >= pressure_pct) or \
        (steal is not None and steal >= steal_pct)
