"""
tuning: the start-up gains and the auto mode's thresholds by optimisation (issue 12, item 4).

``tuning [--plant mujoco|model] [--output FILE] [--maxiter N] [--popsize N] [--seed N]
[--workers N] [--quick]`` searches, with scipy.optimize.differential_evolution (fixed seed,
deferred updating, no polish), the IDA-PBC parameters of (13) and the thresholds of
``controller: auto`` (core/auto_mode.py) on a fixed set of closed-loop runs. It prints a
before/after table (the start point vs the best found) of every metric per scenario, with the
targets, and writes a JSON report (default ``./tuning_report.json``). It changes no file: a
person decides whether the best point goes into config/balance.yaml. The defaults are the best
point of ``tuning --plant mujoco --maxiter 20 --popsize 5 --seed 12`` (2026-12-04), whose
report is docs/tuning_report.json (docs/auto_mode.md has that run, the earlier ones and why
their best points were not adopted). Deterministic: the same
arguments give the same report (times aside), whatever ``--workers`` (processes that evaluate
a generation; a generation is evaluated as a whole). ``--quick``: a tiny budget, short runs.

Scenarios (``scenarios()``; every run ``controller: auto``, the robot's 12 N m wheel limit).
``--plant mujoco`` (the default) runs the start-ups and main_job's standing hand-over in MuJoCo
(mujoco_runs.py: balance_node's own tick against the MuJoCo robot and its six motors, in
lockstep; model (1) misjudges the start-up's roll-out, about twice MuJoCo's), the rest on
model (1) (core/simulation.py: the node's own BalanceCore, 2 ms); ``--plant model`` all on
model (1):

- ``mujoco/startup/d<d>``: armed on the tail after power-up (the legs raise to height_min), from
  the start of balancing, 6 s; IMU offset d in {0, +2.2, -2.2} deg (d_hat0 = 0: the observer
  has to find d). The robot always rises at height_min (the stand-up), so that is where the
  start-up is judged;
- ``mujoco/standing``: main_job's ``standing``: ``controller: ida_pbc`` with d_hat0 2.7 deg
  (d 2.2), output regulation from 3 s, the drift judged over 8..13 s (``drift_m``; main_job's
  hold is 8..28 s);
- ``startup/l0.37/d<d>`` (``--plant model``): the same start-ups on model (1) (from the tail, 36
  deg, at rest); ``startup_noise/...``: two of them again with experiments.SENSOR_NOISE (pitch
  0.2 deg, pitch rate 0.02 rad/s, wheel speed 0.05 rad/s) and the fixed seeds 1 and 2;
- ``velocity_step``: upright at l = 0.37 m, the stick asks 0.5 m/s at 1.5 s and 0 at 4.5 s;
  x_dot* is that command through the node's reference shaper (core/reference.py, 1 m/s^2);
- ``push``: upright at l = 0.37 m, a kick on the body of 60 N for 0.1 s forward at 2 s and
  backward at 5 s (main_job's ``push``; model (1) itself has no push, so this module adds the
  kick's generalized forces to the plant, ``KickedPlant``).

Metrics (``TARGETS`` holds the issue's targets, the one place they are stated):

- start-up: ``overshoot_deg`` (model (1): experiments.overshoot_deg, true pitch past 0 away
  from the tail; MuJoCo: past the final pitch, as main_job), ``rest_time_s`` (from arming until
  |x_dot| stays within ``REST_SPEED`` 0.05 m/s, the true speed, metrics.settling_time),
  ``rest_distance_m`` (|x at that time - x at arming|). A run still moving at its end
  extrapolates a stop at ``EXTRAPOLATION_DECEL`` (0.5 m/s^2): rest time = duration + |x_dot| /
  a, distance = |x - x0| + x_dot^2 / (2 a);
- standing: ``drift_m`` (|x(13 s) - x(8 s)|, true axle, against main_job's 5 s target);
- velocity step: ``rise_time_s`` (10 to 90 % of the 0.5 m/s, the larger of the step up and
  down, from the true speed), ``overshoot_pct`` (past 0.5 m/s going up, below 0 coming back, in
  % of 0.5 m/s), ``pitch_peak_deg`` (max |theta| from the step on);
- push: ``pitch_peak_deg`` (max |theta - theta_before| after a kick, theta_before the mean over
  the 0.5 s before it), ``recovery_s`` (from the kick until |theta - theta_before| stays within
  ``RECOVERY_BAND_DEG`` 1 deg, the issue's); the worse of the two kicks;
- every run: ``fell``, ``peak_torque_nm``, ``saturated_s`` (time at the torque limit).

Cost (``cost``), with r = min(metric / target, R_CAP) per metric and f(r) = max(0, r - 1)^2 +
``EPS`` r (the square penalises a miss, the small linear term keeps improving below target),
plus ``MISS_WEIGHTS`` w_m (r - 1) for a missed rest target or standing drift (w = 200: they are
within reach, the 1 deg overshoot is not, so the search comes as close to 1 deg as they allow):

    J = sum over groups g (start-up, velocity step, push, standing) of W_g * max over the runs
        s of g of [ sum over the metrics m of g of (f(r_sm) + w_m max(0, r_sm - 1))
        + TORQUE_WEIGHT min(saturated_s / SAT_UNIT_S, R_CAP)^2 ]
        +  FALL_PENALTY * (number of runs that fell)

A group counts its worst run: a robot has one IMU offset, unknown, and must meet the targets
at whichever it has (with the mean, the 2026-12-04 run 2 bought two good offsets with 9.1 deg
at main_job's). The start-up runs with noise belong to the start-up group. A run that fell
counts every term of its own at the cap; ``FALL_PENALTY`` exceeds the largest cost a run set
without a fall can have (``max_cost_without_fall``), so any fall ranks behind every non-fall.
The torque: the core clips at 12 N m as on the robot, so the torque applied never exceeds the
limit; a command above it shows as time at the limit, which costs TORQUE_WEIGHT (saturated_s /
10 ms)^2 (a 50 ms saturation as much as a metric 6 times its target).

Decision variables (``VARIABLES``, bounds inside the parameters' own ranges in core/params.py
and core/auto_mode.py, which ``check_bounds`` asserts): IDA-PBC m22_0, k_v, P (log10-scaled)
with k fixed at Table I's 0.015 -- (13) is invariant under (k, m22_0, k_v, P) -> (lam k,
lam m22_0, lam k_v, P / lam) (docs/ida_pbc.md, section 7), so a free k adds nothing but a flat
direction; the auto thresholds enter_angle, leave_angle (deg) and stop_deceleration (log10),
with the hysteresis enter_angle + HYSTERESIS_MIN_DEG <= leave_angle as a linear constraint.
The damping's bell near upright rest (k_v_upright, k_v_width, k_v_rate_width) stays at the
defaults: it sets the loop's margins (docs/margins.md), not the rise. leave_angle stays within
15 deg (the hold is a linear design for near upright). Gains whose IDA-PBC loop misses issue 12's
margins (6 dB both ways, 10 ms) at CERT_HEIGHTS cost UNCERTIFIED_PENALTY (``certification``:
core/margins.py's loop), so the search cannot trade the certification for a faster rise. The
start point (``START``, fixed: Table I's k, m22_0, k_v, P with that bell, and the hand-set
thresholds of 2026-12-03) is put into the initial population, so the best found is never worse
than the start on this cost.

``rise_estimate`` adds a model-based reference point: the fastest rise from the tail under the
torque limit that lifts off at arming (full forward torque, then full braking, timed so the
body turns at -overshoot), and what stopping afterwards costs if the body may lean back no more
than the overshoot target (the body decelerates at most g tan(overshoot)).
"""
import argparse
import copy
from dataclasses import asdict, fields, replace
import json
import math
import os
import platform
import sys
import time
from typing import Any, Dict, List, NamedTuple, Optional, Sequence, Tuple

import numpy as np
from scipy.optimize import brentq, differential_evolution, LinearConstraint

from .experiments import overshoot_deg, SENSOR_NOISE
from .metrics import extrapolated_stop, settling_time
from .mujoco_runs import hold_drift, Play, run_play, startup_figures
from .table import DEG, REST_SPEED, STARTUP_TARGETS
from .. import json_safe
from ...core.auto_mode import AutoRules
from ...core.margins import core_margins
from ...core.model import ipc_accel_moving
from ...core.output_regulation import HoldShape
from ...core.params import IdaPbcGains, RobotParams, TABLE_I_IDA_PBC
from ...core.pipeline import BalanceCore, CoreConfig, Reference
from ...core.reference import ReferenceShaper
from ...core.schema import spec_by_name
from ...core.simulation import Plant, Scenario, SimResult, simulate, SmoothSchedule, TAIL_ANGLE

#: Issue 12's targets, by scenario group (the start-up's from table.py, which main_job uses).
TARGETS: Dict[str, Dict[str, float]] = {
    'startup': dict(STARTUP_TARGETS),
    'velocity_step': {'rise_time_s': 1.0, 'overshoot_pct': 10.0, 'pitch_peak_deg': 8.0},
    'push': {'pitch_peak_deg': 3.0, 'recovery_s': 1.0},
    # main_job's standing holds 20 s from 8 s (drift_20s_m <= 0.01 m, drift_last5_m <= 0.005
    # m): judged here over its first STANDING_WINDOW_S with the 5 s target, where a robot still
    # braking after the hand-over moves.
    'standing': {'drift_m': 0.005},
}
#: Wheel torque limit of the targets and of the core [N m].
TORQUE_LIMIT = 12.0
#: Weight of each group in the cost.
GROUP_WEIGHTS = {'startup': 1.0, 'velocity_step': 1.0, 'push': 1.0, 'standing': 1.0}
#: Metrics whose miss costs MISS_WEIGHT * (r - 1) on top of f(r): the rest targets and the
#: standing drift are within reach (rise_estimate; the defaults meet the drift), the 1 deg
#: overshoot is not, so the search comes as close to it as the others allow instead of trading
#: them away (a 10 % miss of one costs as much as 2 deg more overshoot from 5 deg). The first
#: MuJoCo run without the drift's weight (2026-12-04) traded standing's drift for overshoot.
MISS_WEIGHTS = {'rest_time_s': 200.0, 'rest_distance_m': 200.0, 'drift_m': 200.0}
#: f(r) = max(0, r - 1)^2 + EPS r, r capped at R_CAP.
EPS = 0.1
R_CAP = 30.0
#: Time at the torque limit: TORQUE_WEIGHT * min(saturated_s / SAT_UNIT_S, R_CAP)^2.
TORQUE_WEIGHT = 1.0
SAT_UNIT_S = 0.01
#: Cost of each run that fell (above any cost without a fall: max_cost_without_fall()).
FALL_PENALTY = 1.0e5
#: Cost of gains whose IDA-PBC loop misses issue 12's margins at one of CERT_HEIGHTS [m]
#: (``certification``; the CI test checks the defaults on a 1 cm grid, test_margins.py).
UNCERTIFIED_PENALTY = FALL_PENALTY
CERT_HEIGHTS = (0.37, 0.55, 0.70)

#: Deceleration a run still moving at its end is extrapolated to stop with [m/s^2].
EXTRAPOLATION_DECEL = 0.5
#: Band of the push's recovery time [deg].
RECOVERY_BAND_DEG = 1.0

#: The start-up grid: heights [m] and IMU offsets d [rad]. The robot always rises at height_min
#: (issue 10's stand-up: armed on the tail at the lowest height, it rises, then goes to the
#: commanded height), so the start-ups are judged there.
HEIGHTS = (0.37,)
OFFSETS = (0.0, 2.2 * DEG, -2.2 * DEG)
#: Start-ups repeated with sensor noise: (l [m], d [rad], seed).
NOISY = ((0.37, 2.2 * DEG, 1), (0.37, -2.2 * DEG, 2))
STARTUP_DURATION = 6.0
#: The plants a run set can judge the start-up on (``scenarios``).
PLANTS = ('mujoco', 'model')
#: main_job's standing in MuJoCo: IDA-PBC alone from the tail with d_hat0 2.7 deg (d 2.2),
#: output regulation from STANDING_SWITCH_S, the drift judged from STANDING_FROM_S (main_job's
#: hold starts there) for STANDING_WINDOW_S.
STANDING_SWITCH_S = 3.0
STANDING_FROM_S = 8.0
STANDING_WINDOW_S = 5.0
STANDING_D_HAT0 = 2.7 * DEG
#: Velocity step: commanded speed [m/s], command times [s], run length [s], shaper limit.
STEP_SPEED = 0.5
STEP_UP_S = 1.5
STEP_DOWN_S = 4.5
STEP_DURATION = 8.0
SHAPER_ACCELERATION = 1.0
#: Kicks on the body: (start [s], duration [s], horizontal force [N]), and the run length [s].
KICKS = ((2.0, 0.1, 60.0), (5.0, 0.1, -60.0))
PUSH_DURATION = 8.0
#: Height of the velocity step and the push [m].
UPRIGHT_HEIGHT = 0.37

#: Table I's k, kept fixed (scale invariance of (13), module docstring).
FIXED_K = IdaPbcGains().k
#: Smallest enter_angle-to-leave_angle gap the search allows [deg].
HYSTERESIS_MIN_DEG = 2.0


class Variable(NamedTuple):
    """A decision variable: its name, whether it is searched as log10, its bounds (SI units)."""

    name: str
    log: bool
    lo: float
    hi: float


#: The decision variables and their search bounds (SI: angles in rad).
VARIABLES: Tuple[Variable, ...] = (
    Variable('m22_0', True, 0.004, 0.6),
    Variable('k_v', True, 0.005, 0.5),
    Variable('P', True, 0.001, 30.0),
    Variable('enter_angle', False, 1.0 * DEG, 10.0 * DEG),
    # The hold hands a robot back to IDA-PBC within 15 deg: a linear design holds near upright
    # (the 2026-12-03 run without this bound chose 22.8 deg, a fall handed to the hold).
    Variable('leave_angle', False, 5.0 * DEG, 15.0 * DEG),
    # The hold leans at most max_lean_move while x_dot* != 0 (the brake's ramp included): a
    # brake harder than g tan(max_lean_move) (1.38 m/s^2 at 8 deg) is one it cannot follow.
    Variable('stop_deceleration', True, 0.05,
             RobotParams().gravity * math.tan(HoldShape().max_lean_move)),
)


class Candidate(NamedTuple):
    """A point of the search: the IDA-PBC gains and the auto mode's thresholds."""

    gains: IdaPbcGains
    rules: AutoRules

    def as_dict(self) -> Dict[str, float]:
        """Return the parameters by name (angles in rad, as the configuration has them)."""
        g, r = self.gains, self.rules
        return dict(asdict(g), enter_angle=r.enter_angle, leave_angle=r.leave_angle,
                    stop_deceleration=r.stop_deceleration)


#: The start point, fixed so that the command reproduces its runs whatever the defaults become:
#: the hand-set point of 2026-12-03 (Table I's IDA-PBC with the damping's bell near upright;
#: enter 7 deg, leave 12 deg, brake 1 m/s^2), from which the defaults were tuned.
START = Candidate(replace(TABLE_I_IDA_PBC, k_v_upright=0.3, k_v_width=0.05, k_v_rate_width=0.5),
                  AutoRules(enter_angle=math.radians(7.0), leave_angle=math.radians(12.0),
                            stop_deceleration=1.0))


def candidate_from(params: Dict[str, float]) -> Candidate:
    """Return the candidate of ``Candidate.as_dict``'s output (e.g. a report's params)."""
    gains = IdaPbcGains(**{f.name: params[f.name] for f in fields(IdaPbcGains)
                           if f.name in params})
    names = ('enter_angle', 'leave_angle', 'stop_deceleration')
    rules = AutoRules(**{k: params[k] for k in names})
    return Candidate(gains, rules)


def check_bounds() -> None:
    """Raise ValueError unless every search bound lies within its parameter's own range."""
    ranges = dict(spec_by_name(IdaPbcGains))
    ranges.update(spec_by_name(AutoRules))
    for v in VARIABLES:
        spec = ranges[v.name]
        if not spec.lo <= v.lo < v.hi <= spec.hi:
            raise ValueError('bounds of %s [%g, %g] outside its range [%g, %g]'
                             % (v.name, v.lo, v.hi, spec.lo, spec.hi))


def encode(c: Candidate) -> np.ndarray:
    """Return the search vector of a candidate (log10 where the variable says so)."""
    values = c.as_dict()
    return np.array([math.log10(values[v.name]) if v.log else values[v.name]
                     for v in VARIABLES])


def decode(z: Sequence[float]) -> Candidate:
    """Return the candidate of a search vector (inverse of ``encode``; k and the bell: START's)."""
    values = {v.name: (10.0 ** float(x) if v.log else float(x)) for v, x in zip(VARIABLES, z)}
    gains = replace(START.gains, m22_0=values['m22_0'], k_v=values['k_v'], P=values['P'])
    rules = AutoRules(enter_angle=values['enter_angle'], leave_angle=values['leave_angle'],
                      stop_deceleration=values['stop_deceleration'])
    return Candidate(gains, rules)


def search_bounds() -> List[Tuple[float, float]]:
    """Return the bounds of the search vector."""
    return [(math.log10(v.lo), math.log10(v.hi)) if v.log else (v.lo, v.hi)
            for v in VARIABLES]


def hysteresis_constraint() -> LinearConstraint:
    """Return leave_angle - enter_angle >= HYSTERESIS_MIN_DEG as a constraint on the vector."""
    names = [v.name for v in VARIABLES]
    a = np.zeros(len(VARIABLES))
    a[names.index('leave_angle')] = 1.0
    a[names.index('enter_angle')] = -1.0
    return LinearConstraint(a.reshape(1, -1), HYSTERESIS_MIN_DEG * DEG, np.inf)


# ------------------------------------------------------------------------------- scenarios

class Run(NamedTuple):
    """
    One scenario: its name, group (a key of TARGETS) and what to simulate.

    kicks: KickedPlant's kicks (the push); step: when the stick asks STEP_SPEED and when 0
    again [s] (the velocity step); play: run in MuJoCo instead (mujoco_runs.py; ``scenario``
    is then None).
    """

    name: str
    group: str
    scenario: Optional[Scenario]
    kicks: Tuple[Tuple[float, float, float], ...] = ()
    step: Tuple[float, ...] = ()
    play: Optional[Play] = None


def shaped_reference(commands: Sequence[Tuple[float, float]], duration: float,
                     dt: float = 0.002) -> Tuple[Tuple[float, float], ...]:
    """
    Return x_dot* as waypoints for Scenario.x_dot_ref: ``commands`` through the node's shaper.

    commands: (time [s], commanded speed [m/s]) steps of the stick. The shaper
    (core/reference.py) runs at every tick; one waypoint per tick where x_dot* changes, so the
    simulation samples exactly the shaper's output (SmoothSchedule is exact at its waypoints).
    """
    shaper = ReferenceShaper(max_velocity=1.0, max_acceleration=SHAPER_ACCELERATION)
    points, last = [], None
    for k in range(int(round(duration / dt))):
        t = k * dt
        cmd = 0.0
        for t_cmd, v in commands:
            if t >= t_cmd - 1e-9:
                cmd = v
        v_ref, _ = shaper.update(t, t, cmd, 0.0, dt)
        if v_ref != last or k == 0:
            if points and last is not None and points[-1][0] < t - dt - 1e-9:
                points.append((t - dt, last))   # the end of a constant stretch
            points.append((t, v_ref))
            last = v_ref
    return tuple(points)


class Robot(NamedTuple):
    """
    The robot tuned for: model (1)'s numbers, its balance_node parameters, its MuJoCo body.

    model: RobotParams of the configuration (the model-(1) plant and every core); params: the
    balance_node parameters of its files (e.g. identify's fitted.yaml), set in the MuJoCo plays
    from power-up; body: the MuJoCo robot (sim_node ``robot.*``; None: the default robot).
    """

    model: RobotParams = RobotParams()
    params: Tuple[Tuple[str, Any], ...] = ()
    body: Optional[Any] = None


def scenarios(quick: bool = False, plant: str = 'mujoco',
              robot: Robot = Robot()) -> Tuple[Run, ...]:
    """
    Return the scenario set (module docstring); ``quick``: one start-up, short runs (tests).

    robot: what the runs simulate (default: the default robot).

    plant 'mujoco': the start-ups and the standing hand-over in MuJoCo (mujoco_runs.py), the
    velocity step and the push on model (1) (the hold does them; the variables barely reach
    them); 'model': everything on model (1), no standing run. Every model-(1) Scenario names
    controller 'auto'; the core that runs it comes from ``make_core``.
    """
    if plant not in PLANTS:
        raise ValueError('plant must be one of %s, not %r' % (PLANTS, plant))
    runs = []
    grid = [(0.37, 2.2 * DEG)] if quick else [(l, d) for l in HEIGHTS for d in OFFSETS]
    duration = 3.0 if quick else STARTUP_DURATION
    if plant == 'mujoco':
        for _, d in grid:
            runs.append(Run('mujoco/startup/d%+.1f' % (d / DEG), 'startup', None,
                            play=Play(d, duration, robot.params, body=robot.body)))
        if not quick:
            runs.append(Run('mujoco/standing', 'standing', None, play=Play(
                2.2 * DEG, STANDING_FROM_S + STANDING_WINDOW_S,
                robot.params + (('controller', 'ida_pbc'), ('d_hat0', STANDING_D_HAT0)),
                STANDING_SWITCH_S, robot.body)))
    else:
        for l, d in grid:
            runs.append(Run('startup/l%.2f/d%+.1f' % (l, d / DEG), 'startup', Scenario(
                name='startup', controller='auto', duration=duration, theta0=TAIL_ANGLE,
                imu_offset=d, height=l, params=robot.model)))
        for l, d, seed in (() if quick else NOISY):
            runs.append(Run('startup_noise/l%.2f/d%+.1f/seed%d' % (l, d / DEG, seed),
                            'startup', Scenario(
                                name='startup_noise', controller='auto', duration=duration,
                                theta0=TAIL_ANGLE, imu_offset=d, height=l,
                                noise_std=SENSOR_NOISE, seed=seed, params=robot.model)))
    up, down, step_end = (0.5, 1.5, 2.5) if quick else (STEP_UP_S, STEP_DOWN_S, STEP_DURATION)
    runs.append(Run('velocity_step', 'velocity_step', Scenario(
        name='velocity_step', controller='auto', duration=step_end, theta0=0.0,
        height=UPRIGHT_HEIGHT, params=robot.model,
        x_dot_ref=shaped_reference(((up, STEP_SPEED), (down, 0.0)), step_end)),
        step=(up, down)))
    kicks = ((0.6, 0.1, 60.0),) if quick else KICKS
    runs.append(Run('push', 'push', Scenario(
        name='push', controller='auto', duration=1.6 if quick else PUSH_DURATION,
        theta0=0.0, height=UPRIGHT_HEIGHT, params=robot.model), kicks))
    return tuple(runs)


# ------------------------------------------------------------------------------ simulation

_BASE_CORE: Dict[str, BalanceCore] = {}


def make_core(c: Candidate, p: RobotParams = RobotParams()) -> BalanceCore:
    """
    Return a BalanceCore in ``controller: auto`` with the candidate's gains and thresholds.

    p: the robot's model (1). Building one solves the LQR schedule (seconds); it is built once
    per robot and deep-copied.
    """
    key = repr(p)
    if key not in _BASE_CORE:
        _BASE_CORE[key] = BalanceCore(p, CoreConfig(
            controller='auto', max_wheel_torque=TORQUE_LIMIT))
    core = copy.deepcopy(_BASE_CORE[key])
    core.set_ida_pbc_gains(c.gains)
    core.set_auto_rules(c.rules)
    return core


class KickedPlant(Plant):
    """
    Model (1) with horizontal forces on the body (kicks): (start [s], duration [s], force [N]).

    A force F on the point mass adds the generalized forces F on x and F l cos(theta) on theta:
    x_ddot += F s^2 / (M + m s^2), theta_ddot += M F c / (m l (M + m s^2)). Held over whole
    control ticks (the kick starts at the tick at or after its start).
    """

    def __init__(self, sc: Scenario, kicks):
        super().__init__(sc)
        self.kicks = tuple(kicks)
        self.force = 0.0

    def advance(self, tau_left: float, tau_right: float, t: float) -> None:
        """Integrate one control period with the kick force of this tick."""
        eps = 1e-9
        self.force = sum(f for t0, span, f in self.kicks if t0 - eps <= t < t0 + span - eps)
        super().advance(tau_left, tau_right, t)

    def _accel(self, th, thd, u, l, ld, ldd):
        th_dd, x_dd = super()._accel(th, thd, u, l, ld, ldd)
        if self.force:
            s, c = math.sin(th), math.cos(th)
            den = self.M + self.m * s * s
            th_dd += self.M * self.force * c / (self.m * l * den)
            x_dd += self.force * s * s / den
        return th_dd, x_dd


def simulate_kicked(sc: Scenario, core: BalanceCore, kicks) -> SimResult:
    """
    Run ``sc`` with ``core`` on KickedPlant: core/simulation.simulate's loop, kicks added.

    Exact sensors and no extra delay (the push scenario uses neither).
    """
    cpu0 = time.process_time()
    dt = sc.dt
    n = int(round(sc.duration / dt))
    plant = KickedPlant(sc, kicks)
    v_ref = SmoothSchedule(sc.x_dot_ref)
    rec = np.full((n, 14), np.nan)
    k_end = n
    for k in range(n):
        t = k * dt
        meas = plant.sensors(t)
        if k == 0:
            core.reset(meas)
        ref = Reference(x_dot_ref=v_ref(t)[0])
        out = core.step(meas, ref, dt)
        rec[k] = (t, plant.theta, plant.theta_dot, plant.x, plant.x_dot, meas.theta_meas,
                  out.x_dot, out.u, out.tau_left, out.tau_right, out.d_hat, meas.l,
                  ref.x_dot_ref, plant.yaw_rate)
        plant.advance(out.tau_left, out.tau_right, t)
        if plant.fell:
            k_end = k + 1
            break
    c = rec[:k_end].T
    return SimResult(scenario=sc, t=c[0], theta=c[1], theta_dot=c[2], x=c[3], x_dot=c[4],
                     theta_meas=c[5], x_dot_est=c[6], u=c[7], tau_left=c[8], tau_right=c[9],
                     d_hat=c[10], l=c[11], x_dot_ref=c[12], yaw_rate=c[13], fell=plant.fell,
                     fall_time=k_end * dt if plant.fell else None,
                     cpu_time=time.process_time() - cpu0)


# --------------------------------------------------------------------------------- metrics

def torque_figures(tau: np.ndarray, dt: float) -> dict:
    """Return peak_torque_nm and saturated_s of the larger wheel torque magnitude per tick."""
    at_limit = tau >= TORQUE_LIMIT * (1 - 1e-9)
    return {'peak_torque_nm': float(np.max(tau)) if tau.size else 0.0,
            'saturated_s': float(np.count_nonzero(at_limit) * dt)}


def _common(r: SimResult, core: BalanceCore) -> dict:
    m = torque_figures(np.maximum(np.abs(r.tau_left), np.abs(r.tau_right)), r.scenario.dt)
    m.update(fell=bool(r.fell), switches=core.auto.switches if core.auto is not None else 0)
    return m


def startup_metrics(r: SimResult) -> dict:
    """Overshoot, rest time and rest distance of a start-up run (module docstring)."""
    rest = settling_time(r.t, r.x_dot, REST_SPEED)
    if rest is not None:
        i = min(int(round(rest / r.scenario.dt)), r.t.size - 1)
        distance = abs(float(r.x[i] - r.x[0]))
        extrapolated = False
    else:
        rest, distance = extrapolated_stop(float(r.t[-1] + r.scenario.dt),
                                           abs(float(r.x[-1] - r.x[0])),
                                           float(r.x_dot[-1]), EXTRAPOLATION_DECEL)
        extrapolated = True
    return {'overshoot_deg': overshoot_deg(r), 'rest_time_s': rest,
            'rest_distance_m': distance, 'rest_extrapolated': extrapolated,
            'peak_speed_mps': float(np.max(np.abs(r.x_dot)))}


def _crossing(t: np.ndarray, cond: np.ndarray) -> Optional[float]:
    idx = np.flatnonzero(cond)
    return float(t[idx[0]]) if idx.size else None


def step_metrics(r: SimResult, up: float, down: float, speed: float = STEP_SPEED) -> dict:
    """Rise time (10-90 %, worse of up and down), overshoot [%] and pitch peak of the step."""
    t, v = r.t, r.x_dot
    rise = []
    for t0, t1, sign, base in ((up, down, 1.0, 0.0), (down, math.inf, -1.0, speed)):
        sel = (t >= t0) & (t < t1)
        progress = sign * (v[sel] - base) / speed
        t10 = _crossing(t[sel], progress >= 0.1)
        t90 = _crossing(t[sel], progress >= 0.9)
        # Never reached: the whole window counts (the cost sees a miss).
        rise.append(t90 - t10 if t10 is not None and t90 is not None
                    else float(min(t1, t[-1]) - t0))
    going = (t >= up) & (t < down)
    back = t >= down
    past = max(float(np.max(v[going])) - speed if going.any() else 0.0,
               -float(np.min(v[back])) if back.any() else 0.0, 0.0)
    return {'rise_time_s': max(rise), 'overshoot_pct': 100.0 * past / speed,
            'pitch_peak_deg': math.degrees(float(np.max(np.abs(r.theta[t >= up]))))
            if (t >= up).any() else 0.0}


def push_metrics(r: SimResult, kicks) -> dict:
    """Pitch peak and recovery time of the worse kick (module docstring)."""
    t, th = r.t, r.theta
    peaks, recoveries = [], []
    starts = [k[0] for k in kicks] + [math.inf]
    for (t0, _, _), t_next in zip(kicks, starts[1:]):
        before = (t >= t0 - 0.5) & (t < t0)
        after = (t >= t0) & (t < t_next)
        if not before.any() or not after.any():
            continue
        dev = th[after] - float(np.mean(th[before]))
        peaks.append(math.degrees(float(np.max(np.abs(dev)))))
        settled = settling_time(t[after], dev, RECOVERY_BAND_DEG * DEG)
        recoveries.append((settled - t0) if settled is not None
                          else float(t[after][-1] - t0))
    return {'pitch_peak_deg': max(peaks) if peaks else 0.0,
            'recovery_s': max(recoveries) if recoveries else 0.0}


def node_parameters(c: Candidate) -> Dict[str, float]:
    """Return the candidate as balance_node parameters (ida_pbc.*, auto.*; SI units)."""
    out = {'ida_pbc.' + k: v for k, v in asdict(c.gains).items()}
    out.update({'auto.' + k: getattr(c.rules, k)
                for k in ('enter_angle', 'leave_angle', 'stop_deceleration')})
    return out


def run_play_metrics(run: Run, c: Candidate) -> dict:
    """Run a MuJoCo play with a candidate and return its metrics (mujoco_runs.py)."""
    tr = run_play(run.play, node_parameters(c))
    m = torque_figures(tr.tau, tr.period)
    m.update(fell=tr.fell, switches=tr.switches)
    if run.group == 'startup':
        m.update(startup_figures(tr, REST_SPEED, EXTRAPOLATION_DECEL))
    else:
        m['drift_m'] = hold_drift(tr, STANDING_FROM_S)
    return m


def run_one(run: Run, c: Candidate) -> dict:
    """Simulate one scenario with a candidate and return its metrics."""
    if run.play is not None:
        return run_play_metrics(run, c)
    core = make_core(c, run.scenario.params)
    if run.kicks:
        r = simulate_kicked(run.scenario, core, run.kicks)
    else:
        r = simulate(run.scenario, core)
    m = _common(r, core)
    if run.group == 'startup':
        m.update(startup_metrics(r))
    elif run.group == 'velocity_step':
        m.update(step_metrics(r, *run.step))
    else:
        m.update(push_metrics(r, run.kicks))
    return m


def evaluate(c: Candidate, runs: Sequence[Run]) -> Dict[str, dict]:
    """Return the metrics of every run for candidate ``c``, by run name."""
    return {run.name: run_one(run, c) for run in runs}


# ------------------------------------------------------------------------------------ cost

def _f(r: float) -> float:
    r = min(r, R_CAP)
    return max(0.0, r - 1.0) ** 2 + EPS * r


def run_cost(group: str, m: dict) -> float:
    """Return a run's terms of the cost without the fall penalty (module docstring)."""
    targets = TARGETS[group]
    if m['fell']:
        return _fall_terms(group) + TORQUE_WEIGHT * R_CAP ** 2
    total = 0.0
    for k, target in targets.items():
        r = max(0.0, m[k]) / target
        total += _f(r) + MISS_WEIGHTS.get(k, 0.0) * max(0.0, min(r, R_CAP) - 1.0)
    sat = min(m['saturated_s'] / SAT_UNIT_S, R_CAP)
    return total + TORQUE_WEIGHT * sat * sat


def cost(metrics: Dict[str, dict], runs: Sequence[Run]) -> float:
    """Return the cost J of a run set's metrics (module docstring); lower is better."""
    groups: Dict[str, List[float]] = {}
    falls = 0
    for run in runs:
        m = metrics[run.name]
        groups.setdefault(run.group, []).append(run_cost(run.group, m))
        falls += bool(m['fell'])
    total = sum(GROUP_WEIGHTS[g] * max(v) for g, v in groups.items())
    return total + FALL_PENALTY * falls


def max_cost_without_fall() -> float:
    """Return the largest cost a run set without a fall can have (every term at its cap)."""
    return sum(w * (_fall_terms(g) + TORQUE_WEIGHT * R_CAP ** 2)
               for g, w in GROUP_WEIGHTS.items())


def _fall_terms(group: str) -> float:
    """Return the metric terms of a run of ``group`` with every metric at the cap."""
    return sum(_f(R_CAP) + MISS_WEIGHTS.get(k, 0.0) * (R_CAP - 1.0) for k in TARGETS[group])


def certification(c: Candidate, heights: Sequence[float] = CERT_HEIGHTS,
                  p: RobotParams = RobotParams()) -> dict:
    """
    Return IDA-PBC's worst margins at the candidate's gains over ``heights`` (core/margins.py).

    The loop of issue 12 item 3 (2 ms, one tick of delay, broken at the wheel torque command)
    at each height; ``certified``: no height falls short (``Margins.shortfalls``, the rule the
    CI test applies: stable, both gain margins at least REQUIRED_GAIN_MARGIN_DB, the delay
    margin at least REQUIRED_DELAY_MARGIN_S and confirmed). p: the robot's model (1).
    """
    found = core_margins(make_core(c, p), 'ida_pbc', heights, 'candidate')
    return {'heights_m': [float(l) for l in heights],
            'stable': all(m.stable for m in found),
            'gain_margin_up_db': min(m.gain_margin_up_db for m in found),
            'gain_margin_down_db': min(m.gain_margin_down_db for m in found),
            'delay_margin_s': min(m.delay_margin_s for m in found),
            'certified': not any(m.shortfalls() for m in found)}


def total_cost(metrics: Dict[str, dict], margins: dict, runs: Sequence[Run]) -> float:
    """Return the search's objective: ``cost`` plus UNCERTIFIED_PENALTY unless ``certified``."""
    return cost(metrics, runs) + (0.0 if margins['certified'] else UNCERTIFIED_PENALTY)


class Objective:
    """The cost of a search vector over a fixed run set; keeps every evaluation's figures."""

    def __init__(self, runs: Sequence[Run], p: RobotParams = RobotParams()):
        self.runs = tuple(runs)
        self.p = p
        self.seen: Dict[Tuple[float, ...], Tuple[float, Dict[str, dict], dict]] = {}

    def evaluate(self, z) -> Tuple[float, Dict[str, dict], dict]:
        """Return (J, metrics by run, margins) at search vector z (computed once per vector)."""
        key = tuple(float(v) for v in z)
        if key not in self.seen:
            c = decode(key)
            metrics, margins = evaluate(c, self.runs), certification(c, p=self.p)
            self.seen[key] = (total_cost(metrics, margins, self.runs), metrics, margins)
        return self.seen[key]

    def __call__(self, z) -> float:
        """Return J at search vector z."""
        return self.evaluate(z)[0]


# ------------------------------------------------------------------------ model estimate

def rise_estimate(l: float, overshoot_deg_max: float = 1.0,
                  max_wheel_torque: float = TORQUE_LIMIT,
                  p: RobotParams = RobotParams()) -> dict:
    """
    Estimate what rising from the tail at height l [m] costs at best (no run-up on the tail).

    Full forward force U = 2 tau_max / r_w until t1, then full braking -U until the body stops
    turning, with t1 chosen so it turns at -overshoot_deg_max (RK4, 0.2 ms). While theta > 0 the
    body (a point mass on a massless leg) accelerates forward (x_b_ddot = tan(theta) (g +
    z_b_ddot)), so its speed when theta first crosses 0 is the rise's; leaning back at most
    the overshoot it slows down at most g tan(overshoot). Returns the crossing time and body
    speed, and rest_time_min = t_cross + v / (g tan) and rest_distance_min = (body travel to
    the crossing) + v^2 / (2 g tan) + l sin(36 deg) (the axle starts that far behind the body).
    overshoot_for_rest_time_deg / overshoot_for_rest_distance_deg: the lean back (overshoot) the
    same rise needs to meet TARGETS' rest time / distance (None: no lean does; the body speed
    hardly depends on the overshoot allowed, so the crossing of this rise is used).
    An estimate, not a proof: it assumes z_b_ddot ~ 0 after the crossing and this control
    shape; on model (1) a run-up (rolling back on the tail first) can do better.
    """
    m, M, g = p.body_mass, p.wheel_mass, p.gravity
    U = 2.0 * max_wheel_torque / p.wheel_radius
    th0, h = TAIL_ANGLE, 2e-4

    def accel(th, thd, u):
        a, b = ipc_accel_moving(th, thd, u, l, 0.0, 0.0, m, M, g)
        return a, b

    def rise(t1):
        th, thd, xd, x, t = th0, 0.0, 0.0, 0.0, 0.0
        cross = None
        while t < 3.0:
            u = U if t < t1 else -U
            k1 = accel(th, thd, u)
            k2 = accel(th + 0.5 * h * thd, thd + 0.5 * h * k1[0], u)
            k3 = accel(th + 0.5 * h * (thd + 0.5 * h * k1[0]), thd + 0.5 * h * k2[0], u)
            k4 = accel(th + h * (thd + 0.5 * h * k2[0]), thd + h * k3[0], u)
            th += h * (thd + h / 6.0 * (k1[0] + k2[0] + k3[0]))
            x += h * (xd + h / 6.0 * (k1[1] + k2[1] + k3[1]))
            thd += h / 6.0 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
            xd += h / 6.0 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
            t += h
            if th >= th0:
                th, thd = th0, min(thd, 0.0)
            if cross is None and th <= 0.0:
                cross = (t, xd + l * math.cos(th) * thd, x + l * math.sin(th) - l * math.sin(th0))
            if t > t1 and thd >= 0.0:
                return th, cross
        return th, cross

    target = -math.radians(overshoot_deg_max)
    t1 = brentq(lambda s: rise(s)[0] - target, 0.01, 0.5, xtol=1e-6)
    _, (t_cross, v, xb) = rise(t1)
    a = g * math.tan(math.radians(overshoot_deg_max))
    time_left = TARGETS['startup']['rest_time_s'] - t_cross
    room = TARGETS['startup']['rest_distance_m'] - xb - l * math.sin(th0)
    return {'l_m': l, 'overshoot_deg': overshoot_deg_max, 'push_s': t1, 't_cross_s': t_cross,
            'body_speed_mps': v, 'rest_time_min_s': t_cross + v / a,
            'rest_distance_min_m': xb + v * v / (2.0 * a) + l * math.sin(th0),
            'overshoot_for_rest_time_deg':
                math.degrees(math.atan(v / (g * time_left))) if time_left > 0.0 else None,
            'overshoot_for_rest_distance_deg':
                math.degrees(math.atan(v * v / (2.0 * g * room))) if room > 0.0 else None}


# ---------------------------------------------------------------------------------- report

def _fmt(v, digits: int = 2) -> str:
    if v is None:
        return '-'
    if isinstance(v, (bool, np.bool_)):
        return 'yes' if v else 'no'
    return '%.*f' % (digits, v)


def _met(group: str, key: str, m: dict) -> str:
    return 'ok' if not m['fell'] and m[key] <= TARGETS[group][key] else 'MISS'


def table_lines(runs: Sequence[Run], before: Dict[str, dict], after: Dict[str, dict]) -> list:
    """Return the before/after table: one row per scenario and metric, with target and verdict."""
    lines = ['| scenario | metric | target | before | after | met before / after |',
             '|---|---|---|---|---|---|']
    extra = (('fell', 2), ('peak_torque_nm', 2), ('saturated_s', 3), ('switches', 0))
    for run in runs:
        b, a = before[run.name], after[run.name]
        for key, target in TARGETS[run.group].items():
            lines.append('| %s | %s | <= %g | %s | %s | %s / %s |' % (
                run.name, key, target, _fmt(b[key]), _fmt(a[key]),
                _met(run.group, key, b), _met(run.group, key, a)))
        for key, digits in extra:
            lines.append('| %s | %s | | %s | %s | |' % (
                run.name, key, _fmt(b[key], digits), _fmt(a[key], digits)))
    return lines


def _candidate_lines(c: Candidate) -> List[str]:
    g, r = c.gains, c.rules
    return ['IDA-PBC: k %.4g, m22_0 %.4g, k_v %.4g, P %.4g; k_v_upright %.4g, k_v_width %.3f '
            'deg, k_v_rate_width %.4g rad/s'
            % (g.k, g.m22_0, g.k_v, g.P, g.k_v_upright, math.degrees(g.k_v_width),
               g.k_v_rate_width),
            'auto: enter_angle %.3f deg, leave_angle %.3f deg, stop_deceleration %.4g m/s^2'
            % (math.degrees(r.enter_angle), math.degrees(r.leave_angle), r.stop_deceleration)]


# ------------------------------------------------------------------------------------ main

def tune(maxiter: int, popsize: int, seed: int, quick: bool = False, plant: str = 'mujoco',
         workers: int = 1, robot: Robot = Robot()) -> dict:
    """
    Run the search and return the report (a JSON-safe dict).

    differential_evolution over ``VARIABLES`` with the hysteresis constraint, ``x0`` = START,
    Latin hypercube start population of popsize * len(VARIABLES) (at least 5) members,
    ``maxiter`` generations, ``seed``, ``polish=False``, ``updating='deferred'`` (a generation
    is evaluated as a whole, so ``workers`` processes give the same result as one). robot:
    the robot tuned for (``Robot``; default: the default robot).
    """
    check_bounds()
    cpu0, wall0 = time.process_time(), time.monotonic()
    runs = scenarios(quick, plant, robot)
    objective = Objective(runs, robot.model)
    z0 = encode(START)
    j0, before, margins0 = objective.evaluate(z0)
    result = differential_evolution(
        objective, search_bounds(), constraints=(hysteresis_constraint(),), x0=z0,
        seed=seed, maxiter=maxiter, popsize=popsize, polish=False, workers=workers,
        updating='deferred', init='latinhypercube', tol=0.0)
    z_best = result.x if result.fun <= j0 else z0
    j_best, after, margins_best = objective.evaluate(z_best)
    best = decode(z_best)
    cost_doc = {
        'definition': 'J = sum_g W_g max_s [sum_m (f(r) + w_m max(0, r - 1)) + TORQUE_WEIGHT '
        'min(saturated_s/SAT_UNIT_S, R_CAP)^2] + FALL_PENALTY * falls + UNCERTIFIED_PENALTY '
        '* (IDA-PBC short of the margins at CERT_HEIGHTS), r = min(m/target, R_CAP), '
        'f(r) = max(0, r - 1)^2 + EPS r, w_m = MISS_WEIGHTS (0 where absent)',
        'group_weights': GROUP_WEIGHTS, 'MISS_WEIGHTS': MISS_WEIGHTS, 'EPS': EPS, 'R_CAP': R_CAP,
        'TORQUE_WEIGHT': TORQUE_WEIGHT, 'SAT_UNIT_S': SAT_UNIT_S, 'FALL_PENALTY': FALL_PENALTY,
        'UNCERTIFIED_PENALTY': UNCERTIFIED_PENALTY, 'CERT_HEIGHTS': CERT_HEIGHTS}
    command = 'tuning --plant %s --maxiter %d --popsize %d --seed %d%s' % (
        plant, maxiter, popsize, seed, ' --quick' if quick else '')
    report = {
        'command': command,
        'targets': TARGETS,
        'cost': cost_doc,
        'variables': [{'name': v.name, 'log10': v.log, 'lo': v.lo, 'hi': v.hi}
                      for v in VARIABLES],
        'fixed': {'k': FIXED_K, 'k_v_upright': START.gains.k_v_upright,
                  'k_v_width': START.gains.k_v_width,
                  'k_v_rate_width': START.gains.k_v_rate_width,
                  'hysteresis_min_deg': HYSTERESIS_MIN_DEG},
        'plant': plant,
        'robot': {'params': dict(robot.params),
                  'body': None if robot.body is None else asdict(robot.body)},
        'scenarios': [run.name for run in runs],
        'start': {'params': START.as_dict(), 'cost': j0, 'metrics': before,
                  'margins': margins0},
        'best': {'params': best.as_dict(), 'cost': j_best, 'metrics': after,
                 'margins': margins_best},
        'optimizer': {'method': 'scipy.optimize.differential_evolution', 'seed': seed,
                      'maxiter': maxiter, 'popsize': popsize, 'nfev': int(result.nfev),
                      'updating': 'deferred', 'workers': workers,
                      'message': str(result.message)},
        # cpu_s: this process only (the workers' CPU is not in it); wall_s: the whole search.
        'meta': {'quick': quick, 'python': platform.python_version(),
                 'machine': platform.machine(), 'cpu_s': time.process_time() - cpu0,
                 'wall_s': time.monotonic() - wall0},
    }
    if not quick:
        report['rise_estimate'] = [rise_estimate(l, TARGETS['startup']['overshoot_deg'],
                                                 p=robot.model)
                                   for l in HEIGHTS]
    return json_safe(report)


def print_report(report: dict, runs: Sequence[Run]) -> None:
    """Print the start and best parameters, their costs and the before/after table."""
    for key, title in (('start', 'before'), ('best', 'after')):
        c = candidate_from(report[key]['params'])
        print('%s (cost %.4g):' % (title, report[key]['cost']))
        print('\n'.join('  ' + line for line in _candidate_lines(c)))
        g = report[key]['margins']
        print('  IDA-PBC margins at %s m: gain up %.2f dB, down %.2f dB, delay %.1f ms (%s)'
              % (', '.join('%.2f' % l for l in g['heights_m']), g['gain_margin_up_db'],
                 g['gain_margin_down_db'], 1e3 * g['delay_margin_s'],
                 'certified' if g['certified'] else 'NOT certified'))
    opt, meta = report['optimizer'], report['meta']
    workers = opt['workers']
    print('%d evaluations, %.0f s (%d worker%s)' % (opt['nfev'], meta['wall_s'], workers,
                                                    '' if workers == 1 else 's'))
    print()
    print('\n'.join(table_lines(runs, report['start']['metrics'], report['best']['metrics'])))
    for e in report.get('rise_estimate', ()):
        print('estimate, l = %.2f m, overshoot <= %g deg: the fastest rise leaves the body at '
              '%.2f m/s; rest >= %.1f s and >= %.1f m; the rest targets need an overshoot of '
              '>= %s deg (time) and >= %s deg (distance)' % (
                  e['l_m'], e['overshoot_deg'], e['body_speed_mps'], e['rest_time_min_s'],
                  e['rest_distance_min_m'], _fmt(e['overshoot_for_rest_time_deg'], 1),
                  _fmt(e['overshoot_for_rest_distance_deg'], 1)))


def robot_of(configs: Sequence[str], sim_params: Optional[str]) -> Robot:
    """Return the Robot of balance_node files (in order) and a sim_node file (ValueError)."""
    import pathlib
    from ...bringup.robot_config import build, read_params
    flat: Dict[str, Any] = {}
    for path in configs:
        flat.update(read_params(pathlib.Path(path)))
    body = None
    if sim_params:
        from ...identification.cli import sim_variant
        body = sim_variant(sim_params)[0]
    return Robot(build(flat).model, tuple(sorted(flat.items())), body)


def main(argv=None) -> int:
    """Entry point of the ``tuning`` executable."""
    parser = argparse.ArgumentParser(
        prog='tuning', description='Tune the IDA-PBC gains and the auto thresholds: the '
        'start-up in MuJoCo (or on model (1)), the velocity step and push on model (1) '
        '(differential evolution, fixed scenarios and seeds; prints before/after).')
    parser.add_argument('--plant', choices=PLANTS, default='mujoco',
                        help='where the start-ups run (default mujoco: the lockstep robot)')
    parser.add_argument('--workers', type=int, default=1,
                        help='processes evaluating a generation (the result does not depend '
                        'on it; default 1)')
    parser.add_argument('--output', default='tuning_report.json',
                        help='JSON report (default: ./tuning_report.json)')
    parser.add_argument('--maxiter', type=int, default=10, help='generations (default 10)')
    parser.add_argument('--popsize', type=int, default=4,
                        help='population members per variable (default 4)')
    parser.add_argument('--seed', type=int, default=12, help='seed of the search (default 12)')
    parser.add_argument('--quick', action='store_true',
                        help='one start-up, short runs, a tiny budget (tests)')
    parser.add_argument('--config', action='append', default=[], metavar='FILE.yaml',
                        help="balance_node parameter files, in order (the robot's, then "
                        "identify's fitted.yaml): tune for that robot's model (1)")
    parser.add_argument('--sim-params', metavar='FILE.yaml',
                        help='a sim_node parameter file: its robot.* is the MuJoCo robot')
    args = parser.parse_args(argv)
    maxiter, popsize = (1, 1) if args.quick else (args.maxiter, args.popsize)
    try:
        robot = robot_of(args.config, args.sim_params)
    except (ValueError, OSError) as e:
        print('tuning: %s' % e, file=sys.stderr)
        return 1
    report = tune(maxiter, popsize, args.seed, args.quick, args.plant, args.workers, robot)
    print_report(report, scenarios(args.quick, args.plant, robot))
    with open(args.output, 'w') as f:
        json.dump(report, f, indent=2)
    print('report: %s' % os.path.abspath(args.output))
    return 0


if __name__ == '__main__':
    sys.exit(main())
