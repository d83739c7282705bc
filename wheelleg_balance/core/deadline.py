"""
The one absolute-deadline loop of the package, with its statistics (no rclpy).

balance_node's control loop, sim_node's physics loop, the benchmark's reference loop and the
validation tools' sensor publishers all sleep to absolute deadlines ``start + k period`` on
CLOCK_MONOTONIC (as ros2_control's ros2_control_node does): a late tick does not push the later
ones. What to do after a late tick is the caller's policy:

- ``max_catch_up`` missed deadlines are served late, back to back (the rate and a discretized
  controller's time base hold); a longer stall is skipped and counted as overruns, so a stall
  is not answered by a long burst of frames (a burst longer than the CAN TX queue would fail);
- ``resync_after``: alternatively (sim_node, whose simulated time must follow the wall clock),
  every missed deadline is served until the loop is that many periods behind, then the
  schedule restarts from now.

Statistics per tick: the period since the previous tick, the compute time, and lateness; a tick
that starts more than ``stall_threshold`` (10 ms) later than one period after the previous one
counts as a stall, with its length (docs/benchmarks.md). A tick whose compute time exceeds the
``budget`` (half the period: the other half is the bus's and the other processes') counts as
over budget, counted over the whole run: the share of a window's ticks over budget tests the
compute p99 of any window (within budget when at most 1 % are over), where the rings below
give percentiles of the last ``TIMING_WINDOW`` ticks only.
"""
from array import array
import math
import time
from typing import Callable, Dict, Optional

import numpy as np

#: Ticks of the period and compute-time rings (about 2 s at 500 Hz).
TIMING_WINDOW = 1024
#: A tick this late [s] is a stall of the loop itself: counted, its length kept and reported.
STALL_THRESHOLD = 0.010


class DeadlineLoop:
    """
    Sleep to absolute deadlines and call ``tick(now_ns)``; count what went late.

    period [s]; max_catch_up: missed deadlines served back to back before a stall is skipped
    (None with resync_after set: serve all until resync_after periods behind); on_stall: called
    as on_stall(length [s]: how much later than one period after the previous tick this one
    started) from the loop once per stall (log it; keep it short); late_after [s]: a tick that
    starts later than this after its deadline is late (default a quarter period); budget [s]:
    a tick computing longer than this is over budget (default half the period).
    Counters: ticks, caught_up (ticks served late to catch up), overruns (deadlines skipped),
    resyncs, late (ticks later than late_after), over_budget (ticks computing longer than the
    budget), stalls, longest_stall [s], tick_errors (exceptions the tick let escape, passed to
    on_error).
    """

    def __init__(self, period: float, max_catch_up: Optional[int] = 5,
                 resync_after: Optional[int] = None, stall_threshold: float = STALL_THRESHOLD,
                 late_after: Optional[float] = None, budget: Optional[float] = None,
                 on_stall: Optional[Callable[[float], None]] = None,
                 on_error: Optional[Callable[[int, BaseException], None]] = None,
                 clock_ns: Callable[[], int] = time.monotonic_ns,
                 sleep: Callable[[float], None] = time.sleep):
        if not period > 0.0:
            raise ValueError('period must be > 0')
        self.period = float(period)
        self.period_ns = int(round(period * 1e9))
        self.max_catch_up = max_catch_up
        self.resync_after = resync_after
        self.stall_threshold_ns = int(stall_threshold * 1e9)
        self.late_ns = self.period_ns // 4 if late_after is None else int(late_after * 1e9)
        self.budget_ns = self.period_ns // 2 if budget is None else int(round(budget * 1e9))
        self.on_stall = on_stall
        self.on_error = on_error
        self._clock = clock_ns
        self._sleep = sleep
        self.periods = array('d', [0.0] * TIMING_WINDOW)
        self.computes = array('d', [0.0] * TIMING_WINDOW)
        self.ticks = 0
        self.caught_up = 0
        self.overruns = 0
        self.resyncs = 0
        self.late = 0
        self.over_budget = 0
        self.stalls = 0
        self.longest_stall = 0.0
        self.tick_errors = 0
        self.last_tick_ns: Optional[int] = None
        self._stop = False

    def stop(self) -> None:
        """Make ``run`` return after the tick in progress (any thread)."""
        self._stop = True

    @property
    def stopped(self) -> bool:
        """Return True once ``stop`` was called."""
        return self._stop

    def run(self, tick: Callable[[int], None]) -> None:
        """Run ``tick(now_ns)`` every period until ``stop`` (exceptions go to on_error)."""
        clock, sleep, period_ns = self._clock, self._sleep, self.period_ns
        late_ns, budget_ns = self.late_ns, self.budget_ns
        deadline = clock() + period_ns
        prev_start: Optional[int] = None
        while not self._stop:
            now = clock()
            if now < deadline:
                sleep((deadline - now) * 1e-9)
                now = clock()
            k = self.ticks % TIMING_WINDOW
            if prev_start is not None:
                gap = now - prev_start
                self.periods[k] = gap * 1e-9
                if gap - period_ns > self.stall_threshold_ns:
                    # A tick this much later than one period after the previous one, wherever
                    # the time went (a preempted sleep, a long tick, a skipped stall).
                    self._stall((gap - period_ns) * 1e-9)
            prev_start = now
            if now - deadline > late_ns:
                self.late += 1
            try:
                tick(now)
            except Exception as exc:  # noqa: B902 -- the loop must live on; the owner decides
                self.tick_errors += 1
                if self.on_error is not None:
                    self.on_error(now, exc)
            end = clock()
            self.last_tick_ns = now
            self.computes[k] = (end - now) * 1e-9
            if end - now > budget_ns:
                self.over_budget += 1
            self.ticks += 1
            deadline = self._next_deadline(deadline + period_ns, end)

    def _stall(self, lateness: float) -> None:
        self.stalls += 1
        self.longest_stall = max(self.longest_stall, lateness)
        if self.on_stall is not None:
            self.on_stall(lateness)

    def _next_deadline(self, deadline: int, end: int) -> int:
        period_ns = self.period_ns
        if end <= deadline:
            return deadline
        missed = (end - deadline) // period_ns + 1  # deadlines already passed
        if self.resync_after is not None:
            if missed > self.resync_after:
                self.resyncs += 1
                return end  # far behind: restart the schedule from now
            self.caught_up += 1
            return deadline
        if missed > self.max_catch_up:
            self.overruns += missed
            return deadline + missed * period_ns
        self.caught_up += 1  # the next tick runs at once, on its own deadline
        return deadline

    def stats(self) -> Dict[str, float]:
        """Loop statistics over the last TIMING_WINDOW ticks (periods and compute times [s])."""
        n = min(self.ticks, TIMING_WINDOW)
        periods = np.frombuffer(self.periods, dtype=float)[:n]
        periods = periods[periods > 0.0]
        computes = np.frombuffer(self.computes, dtype=float)[:n]
        ticks = max(self.ticks, 1)
        out = {
            'ticks': self.ticks, 'overruns': self.overruns, 'caught_up': self.caught_up,
            'resyncs': self.resyncs, 'late_share': self.late / ticks,
            'over_budget': self.over_budget, 'budget': self.budget_ns * 1e-9,
            'tick_errors': self.tick_errors, 'stalls': self.stalls,
            'longest_stall': self.longest_stall,
        }
        out.update(window_stats('period', periods))
        out.update(window_stats('compute', computes))
        return out


def window_stats(name: str, values) -> Dict[str, float]:
    """
    Return {name_mean, name_p99, name_max} of a window of times [s] (NaN when empty).

    p99 as numpy.percentile's default (linear between the closest ranks), from one sort:
    percentile's own bookkeeping took most of a status tick (10 a second, 3 windows each).
    """
    v = np.sort(np.asarray(values, dtype=float))
    n = v.size
    if not n:
        return dict.fromkeys((name + '_mean', name + '_p99', name + '_max'), math.nan)
    rank = 0.99 * (n - 1)
    lo = int(rank)
    below, above = float(v[lo]), float(v[min(lo + 1, n - 1)])
    return {name + '_mean': float(np.mean(v)),
            name + '_p99': below + (above - below) * (rank - lo),
            name + '_max': float(v[-1])}
