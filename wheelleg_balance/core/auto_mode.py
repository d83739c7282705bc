"""
``controller: auto``: which of the paper's controllers runs, decided every tick.

The paper has two controllers for two jobs (Sec. IV): IDA-PBC (13) brings the robot up from
large angles (the start-up from the tail, Sec. V-B 1) and tracks velocity; output regulation (9)
stands it still with the IMU offset d estimated by the observer (8), holding its position. The
auto mode runs each where it is good, by two rules on the state, with hysteresis:

- **rise** (IDA-PBC): at arming, and whenever the body is far from upright:
  |theta~ - d_hat| > ``leave_angle`` or |theta_dot| > ``leave_rate``;
- **hold** (output regulation): once the body has been near upright, |theta~ - d_hat| <
  ``enter_angle`` and |theta_dot| < ``enter_rate``, for ``dwell`` seconds. Output regulation
  follows the stick too: its position reference moves at x_dot* (core/output_regulation.py),
  so a command does not leave this mode; only the state does.

The gap between enter and leave thresholds and the dwell keep it from chattering at a
boundary; the switch itself is bumpless (BalanceCore blends the jump in u out over
``switch_blend_time``). The margins of each controller over the height range are in
docs/margins.md.

A robot still moving when the hold takes over (after the rise, or a parameter set) is braked
to x_dot* (``brake_step``): at ``stop_deceleration``, and over the last STOP_TAIL_S * a of
speed at |v| / STOP_TAIL_S, so the body comes back upright while the speed fades instead of
still leaning back when the braking ends (that lean drove a robot braked at a constant rate
back at 0.05 m/s for 2 s, MuJoCo 2026-12-03).
"""
from dataclasses import dataclass
import math
from typing import List

from .schema import param

RISE = 'ida_pbc'
HOLD = 'output_regulation'
#: Time constant of the take-over brake's tail [s] (brake_step).
STOP_TAIL_S = 0.3
#: The tail's least deceleration [m/s^2]: the speed reaches x_dot* in finite time.
STOP_TAIL_MIN = 0.05


def brake_step(v: float, deceleration: float, dt: float) -> float:
    """
    Return the take-over speed offset [m/s] one tick of dt [s] later, from v [m/s].

    It falls at min(deceleration, max(|v| / STOP_TAIL_S, STOP_TAIL_MIN)) [m/s^2] towards 0 and
    stops there (module docstring).
    """
    step = min(deceleration, max(abs(v) / STOP_TAIL_S, STOP_TAIL_MIN)) * dt
    return 0.0 if abs(v) <= step else v - math.copysign(step, v)


@dataclass(frozen=True)
class AutoRules:
    """Thresholds of the auto mode (module docstring); hysteresis: enter below leave."""

    enter_angle: float = param(0.1583, 'auto mode: |theta~ - d_hat| below this '
                               '[rad] ...', 0.001, 0.5)
    enter_rate: float = param(1.0, '... and |theta_dot| below this [rad/s] ...', 0.01, 10.0)
    dwell: float = param(0.1, '... for this long [s]: output regulation holds the robot',
                         0.0, 10.0)
    leave_angle: float = param(0.2225, 'auto mode: |theta~ - d_hat| beyond this '
                               '[rad] ...', 0.002, 1.5)
    leave_rate: float = param(3.0, '... or |theta_dot| beyond this [rad/s]: IDA-PBC',
                              0.02, 50.0)
    stop_deceleration: float = param(1.231, 'a robot still moving when output regulation takes '
                                     'over (the auto mode or a switch) is braked to x_dot* at '
                                     'this rate (its body leans about atan(a/g)), the last '
                                     '%g s x a of speed more gently [m/s^2]' % STOP_TAIL_S,
                                     0.01, 10.0)
    planned_rise: bool = param(False, 'at arming on the tail at height_min, rise along the '
                               'planned trajectory (core/rise.py) instead of IDA-PBC (off: in '
                               'MuJoCo the robot tips over its tail wheel, docs/motions.md); '
                               'read-only: the plan is solved or read at start',
                               read_only=True)

    def problems(self) -> List[str]:
        """Check the hysteresis: each enter threshold below its leave threshold."""
        if self.enter_angle < self.leave_angle and self.enter_rate < self.leave_rate:
            return []
        return ['auto.enter_angle and auto.enter_rate must be below auto.leave_angle and '
                'auto.leave_rate (the hysteresis)']


class AutoSelector:
    """The auto mode's state: the controller it chose, and how long the body has been upright."""

    def __init__(self, rules: AutoRules = AutoRules(), choice: str = RISE):
        self.rules = rules
        self.choice = choice
        self._upright_for = 0.0
        #: Changes of the choice since construction (not reset on arming).
        self.switches = 0

    def reset(self) -> None:
        """Arming: start with IDA-PBC (the robot rises from wherever it is)."""
        self.choice = RISE
        self._upright_for = 0.0

    def choose(self, tilt: float, theta_dot: float, dt: float) -> str:
        """
        Return the controller for this tick.

        tilt: theta~ - d_hat [rad], the body's pitch from upright as estimated; theta_dot
        [rad/s]; dt: the tick's period [s]. Non-finite input counts as far from upright.
        """
        r = self.rules
        tilt, rate = abs(tilt), abs(theta_dot)
        choice = self.choice
        if not (tilt <= r.leave_angle and rate <= r.leave_rate):   # NaN lands here too
            choice = RISE
            self._upright_for = 0.0
        elif tilt < r.enter_angle and rate < r.enter_rate:
            self._upright_for += dt
            if self._upright_for >= r.dwell:
                choice = HOLD
        else:
            self._upright_for = 0.0
        if choice != self.choice:
            self.choice = choice
            self.switches += 1
        return choice
