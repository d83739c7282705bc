"""
The result of a fault scenario, and the checks most scenarios share (the FAULT reaction).

An ``Outcome`` is a list of (what was required, whether it held), the time from the fault to
zero torque on the bus, and other measured figures: the test asserts every check, the
``fault_report`` command prints them.
"""
from dataclasses import dataclass, field
import time
from typing import Dict, List, Optional, Tuple

from .bench import MODE
from .doubles import FakeMotors, MOTOR_IDS
from .rig import PERIOD, REACTION_TIME_CHECK, Rig, wait_for
from ...core.deadline import STALL_THRESHOLD

#: Send-time jitter allowed on top of a tick gap at least [s]: a frame goes out after its
#: tick's compute, which the loop reports (compute_max_ms) and which may be longer.
GAP_JITTER = 0.002


@dataclass
class Outcome:
    """
    The result of one scenario.

    checks: (what was required, whether it held); time_to_zero: fault to zero torque on the bus
    [s] (None: not applicable or not reached); figures: other measured numbers; reactions:
    (check text, time the reaction took [s] or None when it never came, its bound [s]) of
    every timed reaction check; injected_at: monotonic time [s] the fault was injected (None:
    the scenario does not say).
    """

    name: str
    fault: str
    expected: str
    checks: List[Tuple[str, bool]] = field(default_factory=list)
    time_to_zero: Optional[float] = None
    figures: Dict[str, object] = field(default_factory=dict)
    reactions: List[Tuple[str, Optional[float], float]] = field(default_factory=list)
    injected_at: Optional[float] = None

    def check(self, text: str, ok) -> bool:
        self.checks.append((text, bool(ok)))
        return bool(ok)

    def reaction(self, text: str, elapsed: Optional[float], bound: float) -> bool:
        """Check that a reaction came within ``bound`` [s]: ``elapsed`` [s], None: never."""
        self.reactions.append((text, elapsed, bound))
        return self.check(text, elapsed is not None and elapsed <= bound)

    def injected(self) -> None:
        """Mark the moment of the injection (the machine's contention is judged before it)."""
        self.injected_at = time.monotonic()

    @property
    def handled(self) -> bool:
        """Tell whether every check held (and there was one)."""
        return bool(self.checks) and all(ok for _, ok in self.checks)

    @property
    def failures(self) -> List[str]:
        return [text for text, ok in self.checks if not ok]

    def as_dict(self) -> dict:
        return {'name': self.name, 'fault': self.fault, 'expected': self.expected,
                'handled': self.handled, 'time_to_zero_s': self.time_to_zero,
                'checks': len(self.checks), 'failures': self.failures,
                'figures': self.figures}


def _torque_before(motors: FakeMotors, t: float) -> bool:
    return any(abs(tau) > 0.1 for tau in motors.torques(1, t - 0.1, t))


def _zero_reaction(out: Outcome, rig: Rig, t_fault: float, bound: float, code: str,
                   not_before: float = 0.0) -> None:
    """
    Check the common FAULT reaction: FAULT, the fault code, zero torque within ``bound``.

    ``not_before`` [s]: the zero torque must not come sooner either (a timeout).
    """
    robot, motors = rig.robot, rig.motors
    out.check('non-zero torque just before the fault (so zero torque is a reaction)',
              _torque_before(motors, t_fault))
    t_mode = robot.wait_mode('FAULT', bound + 1.0)
    text = '%s %.0f ms of the fault' % (REACTION_TIME_CHECK, 1e3 * bound)
    if not out.check('~/state reports FAULT', t_mode is not None):
        out.reaction(text, None, bound)   # the reaction never came
        return
    out.check('diagnostics name the fault %r' % code, robot.wait_fault_code(code, 2.0))
    time.sleep(0.3)
    t_zero = motors.zero_since(t_fault)
    out.time_to_zero = None if t_zero is None else t_zero - t_fault
    out.reaction(text, out.time_to_zero, bound)
    if not_before:
        out.check('but not before %.0f ms' % (1e3 * not_before),
                  out.time_to_zero is not None and out.time_to_zero >= not_before)
    if t_zero is not None:
        _every_tick(out, rig, t_zero, t_zero + 0.3)


def _every_tick(out: Outcome, rig: Rig, t0: float, t1: float) -> None:
    """
    Check that the loop sends its zero torque at every tick it runs within [t0, t1).

    The frames' times are their send times (the virtual bus stamps them), so a gap between
    two frames to a motor is a gap between two ticks' sends: at most one period plus the stall
    threshold (10 ms) or the longest stall the loop itself measured and reported, plus the
    longest compute time it reported (a send comes that much after its tick's start). A stall
    of the loaded machine is the loop's lateness, counted in its diagnostics, not a tick that
    sent nothing; a loop that stopped sending in FAULT leaves a gap nothing it reports
    explains.
    """
    motors = rig.motors
    # The diagnostics that cover the window (published at the rig's 2 Hz, after it).
    wait_for(lambda: any(t > t1 + 0.05 for t, _ in list(rig.robot.diagnostics)), 2.0)
    loop = rig.robot.loop_status()
    stall = 1e-3 * float(loop.get('longest_stall_ms', 'nan'))
    compute = 1e-3 * float(loop.get('compute_max_ms', 'nan'))
    allowed = PERIOD + max(STALL_THRESHOLD, stall if stall == stall else 0.0) + \
        max(GAP_JITTER, compute if compute == compute else 0.0)
    gaps, counts = [], []
    for m in motors.ids:
        times = [t for t, kind, _ in motors.frames(m, t0, t1) if kind == 'torque']
        counts.append(len(times))
        gaps.append(max((b - a for a, b in zip(times, times[1:])), default=t1 - t0))
    out.figures['fault_frame_gap_max_ms'] = 1e3 * max(gaps)
    out.figures['loop_longest_stall_ms'] = 1e3 * stall
    out.figures['loop_compute_max_ms'] = 1e3 * compute
    text = ('FAULT keeps commanding zero torque every tick (no gap between frames over one '
            "period + the stall threshold or the loop's own longest stall + its longest "
            'compute: %.1f ms allowed, %.1f ms seen; %d frames)' % (
                1e3 * allowed, 1e3 * max(gaps), min(counts)))
    out.check(text,
              max(gaps) <= allowed and min(counts) >= 10)


def _torque_flowing(rig: Rig, seconds: float = 0.2) -> bool:
    t0 = time.time()
    time.sleep(seconds)
    return all(len(rig.motors.torques(m, t0)) >= 0.5 * seconds / PERIOD for m in MOTOR_IDS)


def _balancing_since(rig: Rig, t0: float) -> bool:
    modes = rig.robot.modes_since(t0)
    return bool(modes) and all(m == MODE['BALANCING'] for m in modes)
