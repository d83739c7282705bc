"""
The paper's experiments (Sec. V-B, results Sec. V-C) as data: one table for both runners.

Each entry has its name, title, the paper's figure, what the paper reports, and per runner the
metrics it measures (with their definitions) and the criteria it judges them by (bounds in words
and the numbers the code compares with):

- ``model1``: ``experiments`` (validation/paper/experiments.py), the closed-loop simulation of
  model (1) with BalanceCore; its figures go to ``experiments.json`` under ``model1_key``;
- ``main_job``: ``main_job`` (validation/paper/main_job/), balance_node, sim_node (MuJoCo) and
  teleop_node as separate processes; its figures go to ``report.json``.

The table holds the union of what the two run: ``startup``, ``standing``, ``height`` and
``rotate`` run in both; the start-up variants ``startup_paper``, ``startup_tuned``,
``startup_lqr`` and ``startup_lqr_soft``, and ``s_turn``, ``bumps``, ``push``, ``push_paper``,
``slope``, ``velocity_step`` and the two beyond the
paper, ``slope_levelled`` (the same ramp with the body kept level by the legs) and ``sit_down``
(disarm while balancing, beside an uncontrolled torque cut), only through the real processes
(model (1) has neither legs nor terrain nor pushes; its ``startup`` compares every controller
in one run); ``robustness`` only on model (1). Each runner maps an entry to its own
scenario: core/simulation.Scenario for model (1) (experiments.py), parameter files and a joystick
script for MuJoCo (main_job/scenarios.py). The metrics are computed with validation/paper/
metrics.py; docs/main_job.md and docs/paper_comparison.md discuss the results.
"""
from dataclasses import dataclass, field
import math
from typing import Dict, Mapping, Optional, Tuple

from .metrics import settling_band_note

DEG = math.pi / 180.0
#: The paper's IMU pitch offset d (Sec. V-C 2) and the observer's initial estimate d_hat0 [rad].
IMU_OFFSET = 2.2 * DEG
D_HAT0 = 2.7 * DEG
#: The paper's heights of the changing-height run (Sec. V-C 3) [m].
HEIGHTS = (0.70, 0.52, 0.37)
#: The paper's rate of the rotating run (Sec. V-C 4) [deg/s].
ROTATE_RATE_DPS = 165.0
#: Yaw-rate gain of the paper (Sec. V-A) and the one the MuJoCo robot needs [N m s/rad].
PAPER_YAW_GAIN = 0.3
SIM_YAW_GAIN = 5.0
#: The paper's figures (Sec. V-C) that the model-(1) comparison states beside its own.
PAPER_FIGURES = {
    'startup_overshoot_ida_pbc_deg': 1.0,
    'startup_overshoot_linear_deg': 12.0,
    'imu_offset_deg': 2.2,
    'd_hat0_deg': 2.7,
    'heights_m': HEIGHTS,
}
RUNNERS = ('model1', 'main_job')
#: The issue "control that beats the paper": the start-up of the default configuration, from
#: the tail at 0.37 m (the one place these targets are stated; validation/paper/tuning.py).
STARTUP_TARGETS = {'overshoot_deg': 1.0, 'rest_distance_m': 1.0, 'rest_time_s': 3.0}
#: |x_dot| below this counts as at rest [m/s] (the same issue).
REST_SPEED = 0.05
#: The issue's standing targets: drift over the last 5 s and over the 20 s of standing [m],
#: |d_hat - theta~| at rest [deg].
STANDING_TARGETS = {'drift_last5_m': 0.005, 'drift_20s_m': 0.01, 'd_hat_error_deg': 0.1}
#: How long the standing run holds the robot with output regulation [s].
STANDING_HOLD_S = 20.0


@dataclass(frozen=True)
class Metric:
    """A figure a runner reports: its key in the runner's JSON and what it measures (unit)."""

    name: str
    definition: str


@dataclass(frozen=True)
class Criterion:
    """
    A pass/fail check: its name, the bound in words (as reported), the numbers compared with.

    unmet: the bound reported instead when a precondition fails, by cause (e.g. the robot never
    reached the ramp).
    """

    name: str
    bound: str
    limits: Mapping[str, float] = field(default_factory=dict)
    unmet: Mapping[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class Compare:
    """A row of main_job's side-by-side table: a quantity and what the paper reports for it."""

    key: str
    quantity: str
    paper: str


@dataclass(frozen=True)
class Judging:
    """What one runner measures of an experiment, how it judges it, what it puts beside it."""

    metrics: Tuple[Metric, ...]
    criteria: Tuple[Criterion, ...] = ()
    compare: Tuple[Compare, ...] = ()

    def criterion(self, name: str) -> Criterion:
        """Return the criterion called ``name`` (KeyError if there is none)."""
        for c in self.criteria:
            if c.name == name:
                return c
        raise KeyError(name)

    def limits(self) -> Dict[str, float]:
        """Return every criterion's limits in one dict, in table order."""
        out: Dict[str, float] = {}
        for c in self.criteria:
            out.update(c.limits)
        return out


@dataclass(frozen=True)
class Experiment:
    """
    One entry of the table.

    kind: the family of metrics and evaluator (startup, standing, height, rotate, s_turn, bumps,
    push, slope, slope_levelled, sit_down, robustness); model1 / main_job: what that runner
    measures, None if it does not run the entry; model1_key: the entry's key in
    experiments.json; known_finding: why the main_job run is expected to fail (reported, not
    fatal).
    """

    name: str
    title: str
    figure: str
    paper: str
    kind: str
    model1: Optional[Judging] = None
    main_job: Optional[Judging] = None
    model1_key: str = ''
    known_finding: str = ''

    def runners(self) -> Tuple[str, ...]:
        """Return the runners that run this entry."""
        return tuple(r for r in RUNNERS if getattr(self, r) is not None)


# ---------------------------------------------------------------------------------- model (1)

#: What every model-(1) run reports (validation/paper/experiments.run_metrics).
MODEL1_COMMON = (
    Metric('overshoot_deg', 'largest true pitch past 0 on the side opposite the start [deg]'),
    Metric('settling_time_s', settling_band_note() + ' None when it fell or ends outside [s]'),
    Metric('peak_torque_nm', 'largest |torque| applied to either wheel [N m]'),
    Metric('fell', '|theta| > 45 deg, or back on the tail after rising 5 deg off it'),
    Metric('fall_time_s', 'when it fell [s] (None: it did not)'),
    Metric('duration_s', 'simulated time [s]'),
    Metric('cpu_time_s', 'process time of the run [s]'),
)
_FINAL_MAX_THETA = Metric('max_abs_theta_deg', 'max |theta| (true) over the run [deg]')

MODEL1_STARTUP = Judging(metrics=(
    Metric('peak_speed_mps', 'max |x_dot| (true) [m/s]'),
    Metric('x_final_m', 'x at the end [m]'),
    Metric('x_dot_final_mps', 'x_dot at the end [m/s]'),
))
#: Targets of standing still (issue 2); comparison.md states them under the table.
MODEL1_STANDING = Judging(
    metrics=(
        Metric('d_hat_error_deg', '|d_hat - d| at the end [deg]'),
        Metric('d_hat_error_5s_deg', '|d_hat - d| at d_hat_time_s [deg]'),
        Metric('d_hat_within_0p1deg_s', 'first time after which |d_hat - d| stays within '
               'd_hat_error_deg (None: never) [s]'),
        Metric('x_dot_final_mps', '|mean x_dot| over the last 1 s [m/s]'),
        Metric('drift_m', '|x(end) - x(0)| [m]'),
        Metric('max_excursion_m', 'max |x - x(0)| [m]'),
    ),
    criteria=(
        Criterion('d_hat converges', 'd_hat within 0.1 deg of d in <= 5 s',
                  {'d_hat_error_deg': 0.1, 'd_hat_time_s': 5.0}),
        Criterion('stands still', '|mean x_dot| over the last 1 s < 1 mm/s',
                  {'x_dot_final_mps': 1e-3}),
        Criterion('no drift', '|x(end) - x(0)| < 10 mm', {'drift_m': 0.01}),
    ))
MODEL1_HEIGHT = Judging(metrics=(
    Metric('velocity_error_rms_mps', 'rms of x_dot - x_dot* (true speed) over the run [m/s]'),
    Metric('velocity_error_max_mps', 'max |x_dot - x_dot*| over the run [m/s]'),
    Metric('velocity_error_rms_after_2s_mps', 'the same from 2 s (the start of the drive) on'),
    Metric('velocity_error_max_after_2s_mps', 'the same from 2 s on'),
    _FINAL_MAX_THETA,
))
MODEL1_ROTATE = Judging(metrics=(
    Metric('yaw_rate_final_dps', 'mean yaw rate over the last 1 s [deg/s]'),
    Metric('yaw_rate_error_final_dps', 'mean |yaw rate - 165 deg/s| over the last 1 s [deg/s]'),
    _FINAL_MAX_THETA,
))
MODEL1_ROBUSTNESS = Judging(metrics=())

# ----------------------------------------------------------------------------------- main_job

#: What every main_job run reports and must meet (main_job/evaluate.common). Ground truth
#: (sim_node) unless marked; t = 0 at arming.
MAIN_JOB_COMMON = Judging(
    metrics=(
        Metric('t_homing_s', 'from the arm request to BALANCING: homing the hips and raising '
               'the legs on the tail (time 0 is the start of balancing) [s]'),
        Metric('theta_start_deg', 'true pitch at the start of balancing [deg]'),
        Metric('t_rise_s', 'first time the true pitch is below 10 deg (None: never) [s]'),
        Metric('t_fault_s', 'first ~/state sample from 0.05 s on that is not BALANCING, '
               'before a scripted disarm [s]'),
        Metric('max_abs_theta_after_rise_deg', 'max |theta| after rising [deg]'),
        Metric('max_theta_after_rise_deg', 'max theta after rising (towards the tail) [deg]'),
        Metric('peak_wheel_torque_nm', 'max |tau| of either wheel while balancing [N m]'),
        Metric('peak_abs_x_dot', 'max |x_dot| while balancing [m/s]'),
    ),
    criteria=(
        Criterion('ran', 'armed, balancing and recorded'),
        Criterion('rises', 'theta < 10 deg within 2 s', {'theta_deg': 10.0, 't_s': 2.0}),
        # balance_node's fall_angle default; the tail holds the body at 36 deg and more.
        Criterion('stays up', 'BALANCING to the end (or the scripted disarm), |theta| < 45 deg',
                  {'fall_deg': 45.0}),
        Criterion('off the tail', 'theta < 30 deg after rising', {'tail_deg': 30.0}),
        Criterion('evaluated', 'enough data'),
    ))


def _main_job_startup(paper_overshoot: str, targets: bool = False) -> Judging:
    """Return the start-up's judging; ``targets``: the issue's rest and overshoot targets too."""
    def issue(key: str) -> str:
        return 'issue 12: <= %g' % STARTUP_TARGETS[key]
    return Judging(
        metrics=(
            Metric('theta_final_deg', 'mean true pitch over the last 1 s [deg]'),
            Metric('overshoot_deg', 'largest true pitch past theta_final_deg below it [deg]'),
            Metric('settle_s', 'last time |theta - theta_final| > band_deg (0: never) [s]'),
            Metric('rest_time_s', 'from arming until the true |x_dot| stays below %g m/s '
                   '(None: not by the end) [s]' % REST_SPEED),
            Metric('rest_distance_m', '|x at rest - x at arming|, true axle [m]'),
        ),
        criteria=(Criterion('settles', 'within 2 deg of its final pitch in 3 s',
                            {'band_deg': 2.0, 'settle_s': 3.0}),),
        compare=(Compare('overshoot', 'overshoot [deg]', paper_overshoot + (
                     ' (%s)' % issue('overshoot_deg') if targets else '')),
                 Compare('theta_start', 'initial pitch [deg]', 'about 36'),
                 Compare('settle', 'settling within 2 deg [s]', '-'),
                 Compare('rest_time', 'at rest [s]', issue('rest_time_s') if targets
                         else '"stops slower with IDA-PBC"'),
                 Compare('rest_distance', 'distance to rest [m]',
                         issue('rest_distance_m') if targets else '-'),
                 Compare('peak_torque', 'peak wheel torque [N m]', '-')))


MAIN_JOB_STANDING = Judging(
    metrics=(
        Metric('d_hat_deg', 'mean d_hat over the last 5 s [deg]'),
        Metric('theta_meas_deg', 'mean IMU pitch theta~ over the last 5 s [deg]'),
        Metric('theta_eq_deg', 'mean true pitch over the last 5 s [deg]'),
        Metric('d_deg', "sim_node's IMU offset d [deg]"),
        Metric('d_hat0_deg', "the observer's initial d_hat [deg]"),
        Metric('drift_last5_m', '|x(end) - x(end - 5 s)| [m]'),
        Metric('drift_20s_m', '|x(end) - x(end - %g s)|: over the hold [m]' % STANDING_HOLD_S),
        Metric('span_last5_m', 'max x - min x over the last 5 s [m]'),
        Metric('x_dot_mean_last5', 'mean x_dot over the last 5 s [m/s]'),
        Metric('d_hat_within_0p1_deg_from_s', 'last time |d_hat - d_hat_deg| > 0.1 deg [s]'),
    ),
    criteria=(
        Criterion('d_hat found', '|d_hat - theta~| <= %g deg at rest (last 5 s)'
                  % STANDING_TARGETS['d_hat_error_deg'],
                  {'err_deg': STANDING_TARGETS['d_hat_error_deg']}),
        Criterion('no drift', '|x(end) - x(end - 5 s)| <= %g mm'
                  % (1e3 * STANDING_TARGETS['drift_last5_m']),
                  {'drift_m': STANDING_TARGETS['drift_last5_m']}),
        Criterion('holds its spot', '|x(end) - x(end - %g s)| <= %g mm'
                  % (STANDING_HOLD_S, 1e3 * STANDING_TARGETS['drift_20s_m']),
                  {'drift_20s_m': STANDING_TARGETS['drift_20s_m']}),
        Criterion('stands still', '|mean x_dot| < 1 cm/s over the last 5 s',
                  {'x_dot_mps': 0.01}),
    ),
    compare=(Compare('d_hat', 'd_hat at the end [deg]', 'approaches d, about 2.2'),
             Compare('d_hat0', 'd_hat0 [deg]', '2.7'),
             Compare('d_hat_time', 'd_hat within 0.1 deg of its final value from [s]', '-'),
             Compare('x_dot', 'x_dot at rest [mm/s]', '0 (friction of the carpet)'),
             Compare('drift', 'drift over the last 5 s [mm]', '-')))

MAIN_JOB_HEIGHT = Judging(
    metrics=(
        Metric('x_dot_error_last3_mps', 'per drive: mean |x_dot - x_dot*| over its last 3 s '
               '[m/s]'),
        Metric('x_dot_last3_mps', 'per drive: mean x_dot over its last 3 s [m/s]'),
        Metric('x_dot_asked_mps', 'per drive: the commanded x_dot [m/s]'),
        Metric('theta_eq_deg', 'mean true pitch over the 1 s before the first drive [deg]'),
        Metric('max_theta_dev_driving_deg', 'max |theta - theta_eq| while driving [deg]'),
        Metric('l_max', 'max height while driving [m]'),
        Metric('l_min', 'min height while driving [m]'),
        Metric('height_tracking_rms_m', "rms of the true height l minus balance_node's shaped "
               '(rate- and acceleration-limited) height command l_ref, from the first height '
               'press to the end of the last drive [m]'),
        Metric('height_tracking_max_m', 'max |l - l_ref| over the same window [m]'),
        Metric('height_presses', 'the heights the joystick pressed, in order [m]'),
    ),
    criteria=(
        Criterion('drives both ways', 'mean x_dot over the last 3 s of each drive has the sign '
                  'of x_dot* and at least half its size', {'window_s': 3.0, 'share': 0.5}),
        Criterion('level while driving', '|theta - theta_eq| < 5 deg', {'theta_dev_deg': 5.0}),
        Criterion('heights', 'l reaches 0.70 and 0.37 m (+-2 cm) while driving',
                  {'l_max_above_m': 0.68, 'l_min_below_m': 0.39}),
        Criterion('tracks the height', 'rms of l - l_ref <= 0.03 m',
                  {'rms_m': 0.03}),
    ),
    compare=(Compare('heights', 'heights passed [m]', '0.70, 0.52, 0.37 and back'),
             Compare('speeds', 'speed over the last 3 s of each drive [m/s]',
                     'slow; tracking not considered'),
             Compare('errors', 'mean |x_dot - x_dot*| over the same windows [m/s]', '-'),
             Compare('pitch', 'max pitch deviation while driving [deg]', 'stable'),
             Compare('tracking', 'rms of true height minus shaped command [m]', '-')))

MAIN_JOB_ROTATE = Judging(
    metrics=(
        Metric('yaw_rate_paper_gain_degps', 'mean yaw rate over the 2 s before the gain change '
               "(the paper's gain) [deg/s]"),
        Metric('yaw_rate_pi_degps', 'mean yaw rate over the last 3 s of the rotation (the '
               'default yaw loop: PI) [deg/s]'),
        Metric('yaw_rate_error_pct', '|mean yaw rate over the last 3 s - commanded| / '
               'commanded [%]'),
        Metric('theta_eq_deg', 'mean true pitch over the 1 s before the rotation [deg]'),
        Metric('max_theta_dev_deg', 'max |theta - theta_eq| while rotating [deg]'),
        Metric('max_abs_x_dot_spin', 'max |x_dot| while rotating [m/s]'),
        Metric('abs_x_dot_at_start', '|x_dot| when the rotation starts (IDA-PBC still slows '
               'down from the start-up) [m/s]'),
        Metric('peak_torque_spin_nm', 'max |tau| of either wheel while rotating [N m]'),
    ),
    criteria=(
        Criterion('165 deg/s', 'mean yaw rate over the last 3 s within 5 % of -165 deg/s '
                  '(the default yaw loop: PI)', {'rate_dps': -165.0, 'tol_pct': 5.0}),
        Criterion('balance unaffected', '|theta - theta_eq| < 2 deg, and |x_dot| below its '
                  'value at the start of the rotation + 0.05 m/s',
                  {'theta_dev_deg': 2.0, 'x_dot_margin_mps': 0.05}),
    ),
    compare=(Compare('yaw_rate', 'yaw rate [deg/s]', '-165 (clockwise)'),
             Compare('pitch', 'pitch while rotating', 'unaffected'),
             Compare('torques', 'wheel torques', 'smooth')))

MAIN_JOB_S_TURN = Judging(
    metrics=(
        Metric('x_dot_error_mean', 'mean |x_dot - x_dot*| while turning [m/s]'),
        Metric('yaw_rate_error_mean', 'mean |yaw rate - yaw rate*| while turning [rad/s]'),
        Metric('x_dot_oscillation', 'std of x_dot - x_dot* while turning (the swing without '
               'a steady offset) [m/s]'),
        Metric('yaw_rate_oscillation', 'std of yaw rate - yaw rate* while turning [rad/s]'),
        Metric('yaw_rate_peak_degps', 'max |yaw rate| while turning [deg/s]'),
    ),
    criteria=(
        Criterion('tracks x_dot*', 'mean |x_dot - x_dot*| < 0.1 m/s while turning',
                  {'mean_abs_mps': 0.1}),
        Criterion('tracks yaw rate*', 'mean |yaw rate - yaw rate*| < 0.2 rad/s while turning',
                  {'mean_abs_radps': 0.2}),
    ),
    compare=(Compare('x_dot_osc', 'x_dot oscillation about x_dot* (std) [m/s]',
                     'oscillates (jerky reference)'),
             Compare('yaw_osc', 'yaw-rate oscillation about yaw rate* (std) [deg/s]',
                     'oscillates (jerky reference)'),
             Compare('turns', 'turns', 'left, right, left')))

MAIN_JOB_BUMPS = Judging(
    metrics=(
        Metric('bump_x_m', 'where the bumps are [m]'),
        Metric('t_bumps_s', 'when the axle passes each bump (None: never) [s]'),
        Metric('x_end_m', 'x at the end [m]'),
        Metric('t_bumps_after_drive_s', 't_bumps_s from driving off [s]'),
        Metric('theta_before_deg', 'mean true pitch from 1.5 to 0.5 s before the first bump '
               '[deg]'),
        Metric('bump_pitch_peak_dev_deg', 'max |theta - theta_before| from 0.5 s before the '
               'first bump to 1 s after the last [deg]'),
        Metric('x_dot_range_bumps', 'min and max x_dot over the same window [m/s]'),
        Metric('x_dot_before', 'x_dot 0.5 s before the first bump [m/s]'),
        Metric('theta_after_bumps_dev_deg', 'max |theta - theta_before| from after_s after the '
               'last bump until the stop [deg]'),
    ),
    criteria=(
        Criterion('crosses both bumps', 'axle beyond the last bump + 0.3 m', {'beyond_m': 0.3}),
        Criterion('settles after the bumps', '|theta - theta before the first bump| < 2 deg '
                  'from 2 s after the last bump while driving on',
                  {'dev_deg': 2.0, 'after_s': 2.0}, unmet={'bumps': 'reaches both bumps'}),
    ),
    compare=(Compare('t_bumps', 'axle over the bumps [s after driving off]',
                     "1.5 and 2.8 (from the figure's start)"),
             Compare('pitch', 'largest pitch change at the bumps [deg]', 'sharp'),
             Compare('x_dot', 'x_dot around the bumps [m/s]', 'sharp change')))

#: The push runs' metrics (the paper's and the default configuration's).
_PUSH_METRICS = (
    Metric('kick_times_s', 'when each kick starts (from its sim time) [s]'),
    Metric('kick_pitch_peak_deg', 'per kick: max |theta - theta_before| until the next '
           '(theta_before: mean over the 0.5 s before it) [deg]'),
    Metric('kick_pitch_after_1p5s_deg', 'per kick: the same from after_s after it [deg]'),
    Metric('kick_recovery_s', 'per kick: from the kick until |theta - theta_before| stays '
           'within 1 deg, up to the next kick (None: not within the window) [s]'),
    Metric('x_dot_zero_crossings', 'sign changes of x_dot from the first kick on'),
    Metric('peak_abs_x_dot_kicks', 'max |x_dot| from the first kick on [m/s]'),
    Metric('theta_eq_deg', 'mean true pitch over the 1 s before the first kick [deg]'),
    Metric('theta_meas_eq_deg', 'mean IMU pitch over the same 1 s [deg]'),
)
#: |theta - theta_before| within this counts as recovered (kick_recovery_s) [deg].
KICK_RECOVERY_BAND_DEG = 1.0
#: kick_pitch_after_1p5s_deg looks at the pitch from this long after each kick [s].
KICK_AFTER_S = 1.5
_PUSH_COMPARE = (Compare('reversals', 'velocity reversals (zero crossings of x_dot)',
                         'one per kick'),
                 Compare('pitch', 'pitch change at a kick [deg]', 'sudden change, quick return'),
                 Compare('recovery', 'back within 1 deg after a kick [s]', '-'),
                 Compare('theta_eq', 'equilibrium pitch (IMU) [deg]', 'about 1.2'),
                 Compare('x_dot', 'peak |x_dot| after the kicks [m/s]', '-'))
#: The first kick must come at least this long after the start of balancing [s]: earlier, it
#: falls into the start-up's roll-out (at rest after about 2.4 s in MuJoCo, issue 12's target
#: 3 s), and there is no settled pitch to judge it by. The kicks run on sim time, so an arm that
#: came late (a loaded machine) brings them earlier; the run then fails as 'late'.
KICK_EARLIEST_S = 3.0
_LATE = {'late': 'balancing %g s before the first kick (the arm came late)' % KICK_EARLIEST_S}

MAIN_JOB_PUSH_PAPER = Judging(
    metrics=_PUSH_METRICS,
    criteria=(
        Criterion('recovers from each kick', '|theta - theta_before| 1.5 s after a kick (until '
                  'the next) below half its peak at the kick',
                  {'after_s': KICK_AFTER_S, 'share': 0.5},
                  unmet=_LATE),
    ),
    compare=_PUSH_COMPARE)

MAIN_JOB_PUSH = Judging(
    metrics=_PUSH_METRICS,
    criteria=(
        Criterion('kick pitch', 'every kick: pitch peak <= 3 deg', {'peak_deg': 3.0},
                  unmet=_LATE),
        Criterion('kick recovery', 'every kick: back within 1 deg of its pitch before the '
                  'kick within 1 s', {'recovery_s': 1.0}, unmet=_LATE),
    ),
    compare=_PUSH_COMPARE)

#: velocity_step's step [m/s] (full stick without turbo: teleop's scale_linear.x).
VELOCITY_STEP_MPS = 0.5

MAIN_JOB_VELOCITY_STEP = Judging(
    metrics=(
        Metric('step_times_s', 'when the stick steps to %g m/s and back to 0 [s]'
               % VELOCITY_STEP_MPS),
        Metric('velocity_before_mps', 'mean true x_dot over the 0.5 s before the step up [m/s]'),
        Metric('velocity_rise_time_s', 'step up: from 10 to 90 %% of the way from '
               'velocity_before_mps to %g m/s, true x_dot (None: 90 %% never reached) [s]'
               % VELOCITY_STEP_MPS),
        Metric('velocity_overshoot_pct', 'step up: (max true x_dot until the step down - '
               '%g) / (%g - velocity_before_mps), at least 0 [%%]'
               % (VELOCITY_STEP_MPS, VELOCITY_STEP_MPS)),
        Metric('velocity_step_pitch_peak_deg', 'max |theta - theta_before| from the step up to '
               'the end (theta_before: mean over the 0.5 s before the step up) [deg]'),
        Metric('velocity_at_step_down_mps', 'mean true x_dot over the 0.5 s before the step '
               'down [m/s]'),
        Metric('velocity_fall_time_s', 'step down: from 90 to 10 % of the way from '
               'velocity_at_step_down_mps to 0 (None: 10 % never reached) [s]'),
        Metric('velocity_undershoot_pct', 'step down: -min true x_dot after the step down / '
               'velocity_at_step_down_mps, at least 0 [%]'),
    ),
    criteria=(
        Criterion('rise time', 'step up 0 -> %g m/s: 10 to 90 %% within 1.0 s'
                  % VELOCITY_STEP_MPS, {'rise_s': 1.0}),
        Criterion('overshoot', 'step up: overshoot <= 10 %', {'overshoot_pct': 10.0}),
        Criterion('pitch', 'pitch within 8 deg of its value before the step',
                  {'pitch_deg': 8.0}),
    ),
    compare=(Compare('rise', '10-90 % rise time up / fall time down [s]', '-'),
             Compare('overshoot', 'overshoot up / undershoot down [%]', '-'),
             Compare('pitch', 'pitch peak [deg]', '-')))

MAIN_JOB_SLOPE = Judging(
    metrics=(
        Metric('max_roll_deg', 'max |roll| after arming [deg]'),
        Metric('t_ramp_s', 'first time |roll| > 1 deg (on the ramp) [s]'),
        Metric('t_drop_s', 'first time |roll| < 1 deg after its peak (wheel down) [s]'),
        Metric('theta_before_deg', 'mean true pitch over the 1 s before the ramp [deg]'),
        Metric('heading_change_deg', 'yaw at the roll peak minus yaw at the ramp [deg]'),
        Metric('x_dot_at_ramp', 'x_dot at the ramp [m/s]'),
        Metric('theta_after_drop_dev_deg', 'max |theta - theta_before| from after_s after the '
               'drop [deg]'),
    ),
    criteria=(
        Criterion('climbs the ramp', 'max |roll| > 15 deg (18 deg at its top)',
                  {'roll_deg': 15.0}),
        Criterion('settles after the drop', '|theta - theta_before| < 3 deg from 2 s after the '
                  'wheel is down', {'dev_deg': 3.0, 'after_s': 2.0},
                  unmet={'down': 'the wheel comes down', 'ramp': 'reaches the ramp'}),
    ),
    compare=(Compare('roll', 'max roll [deg]', '19'),
             Compare('x_dot', 'speed at the ramp [m/s]', 'rushes (fast)'),
             Compare('heading', 'heading change on the ramp [deg]', 'keeps straight'),
             Compare('pitch', 'pitch after the drop', 'converges to its equilibrium')))

MAIN_JOB_SLOPE_LEVELLED = Judging(
    metrics=(
        Metric('t_ramp_s', 'when the axle passes the foot of the ramp [s]'),
        Metric('t_top_s', 'when the axle passes the top of the ramp (the wheel drops) [s]'),
        Metric('max_roll_on_ramp_deg', 'max |roll| while the axle is over the ramp [deg]'),
        Metric('max_roll_deg', 'max |roll| after arming [deg]'),
        Metric('drop_roll_peak_deg', 'max |roll| from the top of the ramp on [deg]'),
        Metric('drop_roll_back_s', 'from the top until |roll| stays within 2 deg [s]'),
        Metric('theta_before_deg', 'mean true pitch over the 1 s before the ramp [deg]'),
        Metric('t_down_s', 'when the wheel is down: t_top_s plus the fall time of the ramp '
               'height [s]'),
        Metric('theta_after_drop_dev_deg', 'max |theta - theta_before| from after_s after '
               'the wheel is down [deg]'),
        Metric('drop_pitch_peak_deg', 'max |theta - theta_before| from the top on [deg]'),
        Metric('x_dot_at_ramp', 'x_dot at the foot of the ramp [m/s]'),
    ),
    criteria=(
        Criterion('level on the ramp', '|roll| <= 5 deg while the wheel climbs the ramp',
                  {'roll_deg': 5.0}, unmet={'ramp': 'reaches the ramp'}),
        Criterion('settles after the drop', '|theta - theta_before| < 3 deg from 2 s after the '
                  'wheel is down', {'dev_deg': 3.0, 'after_s': 2.0},
                  unmet={'down': 'the wheel comes down', 'ramp': 'reaches the ramp'}),
    ),
    compare=(Compare('roll', 'max roll on the ramp [deg]', '19 (fixed legs)'),
             Compare('drop', 'roll peak after the drop; back within 2 deg after [deg; s]', '-'),
             Compare('pitch', 'pitch after the drop', 'converges to its equilibrium'),
             Compare('x_dot', 'speed at the ramp [m/s]', 'rushes (fast)')))

#: Tail contact counts from this many seconds of pitch rate before the first contact sample.
CONTACT_WINDOW_S = 0.03

MAIN_JOB_SIT_DOWN = Judging(
    metrics=(
        Metric('t_disarm_s', 'when main_job disarms (the sit-down starts) [s]'),
        Metric('sit_down_contact', "what touched the floor first: 'tail' or 'body' (None: "
               'nothing)'),
        Metric('sit_down_contact_s', 'when, from the disarm [s]'),
        Metric('sit_down_contact_rate_radps', '|true pitch rate| at the first contact: the '
               'largest over the %g s up to the first contact sample [rad/s]'
               % CONTACT_WINDOW_S),
        Metric('sit_down_travel_m', 'max |x - x at the disarm| until the re-arm [m]'),
        Metric('sit_down_time_s', 'from the disarm until balance_node reports DISARMED [s]'),
        Metric('rest_pitch_deg', 'true pitch at rest after the sit-down [deg]'),
        Metric('t_stop_s', 'when main_job calls ~/stop (the torque cut) [s]'),
        Metric('cut_contact', "what touched first after the cut: 'tail' or 'body'"),
        Metric('cut_contact_rate_radps', '|true pitch rate| at that contact, as above [rad/s]'),
        Metric('cut_travel_m', 'max |x - x at the cut| until the end [m]'),
    ),
    criteria=(
        Criterion('onto the tail', 'the tail touches first, not the body', unmet={
            'none': 'touches down before the re-arm'}),
        Criterion('gentle contact', '|pitch rate| at tail contact <= 0.5 rad/s',
                  {'rate_radps': 0.5}, unmet={'none': 'touches down before the re-arm'}),
        Criterion('short travel', 'travel during the sit-down <= 1.0 m', {'travel_m': 1.0}),
        Criterion('rests', 'DISARMED within 10 s of the disarm', {'time_s': 10.0}),
    ),
    compare=(Compare('contact', 'first contact: sit-down / torque cut', 'only the tail side is '
                     'safe'),
             Compare('rate', 'pitch rate at contact: sit-down / torque cut [rad/s]', '-'),
             Compare('travel', 'travel: sit-down / torque cut [m]', '-')))

# -------------------------------------------------------------------------------- the table

EXPERIMENTS: Tuple[Experiment, ...] = (
    Experiment(
        'startup', 'Start-up from the tail at l = 0.37 m: the default configuration '
        '(main_job); every controller (model (1))', 'Fig. 3',
        'starts at about 36 deg; overshoot 1 deg with IDA-PBC (12 deg with the linear '
        'controller); the robot stops slower with IDA-PBC. The issue "control that beats the '
        'paper" asks overshoot <= 1 deg, at rest within 3 s and 1 m', 'startup',
        model1=MODEL1_STARTUP, main_job=_main_job_startup('1 (IDA-PBC)', targets=True),
        model1_key='startup'),
    Experiment(
        'startup_paper', "Start-up from the tail at l = 0.37 m, IDA-PBC (13) with Table I's "
        'gains', 'Fig. 3', 'starts at about 36 deg; overshoot 1 deg with IDA-PBC; the robot '
        'stops slower with IDA-PBC', 'startup', main_job=_main_job_startup('1 (IDA-PBC)')),
    Experiment(
        'startup_tuned', 'Start-up from the tail, IDA-PBC (13) with the tuned gains of '
        'core/ida_pbc.py (m22_0 0.2, k_v 0.068, P 0)', 'Fig. 3',
        'overshoot 1 deg with IDA-PBC', 'startup', main_job=_main_job_startup('1 (IDA-PBC)')),
    Experiment(
        'startup_lqr', 'Start-up from the tail, linear u = k_x xi~ (LQR, core/lqr.py weights)',
        'Fig. 3', 'linear control overshoots 12 deg (Table I k_x)', 'startup',
        main_job=_main_job_startup('12 (linear)'),
        known_finding='the default LQR gains (R = 1/(30 N)^2) saturate the wheels at 12 N m '
        'for the first 0.1 s and the body swings through upright and over: MuJoCo has about a '
        'third more pitch authority per newton than model (1) (wheel inertia, motor reaction '
        'torque; docs/simulation.md)'),
    Experiment(
        'startup_lqr_soft', 'Start-up from the tail, linear u = k_x xi~, softer LQR '
        '(R = 1/(10 N)^2)', 'Fig. 3', 'linear control overshoots 12 deg', 'startup',
        main_job=_main_job_startup('12 (linear)')),
    Experiment(
        'standing', 'Standing still: output regulation (9) with the observer (8), '
        'd = 2.2 deg, d_hat0 = 2.7 deg', 'Fig. 4',
        'the robot stands still on carpet (x_dot = 0); d_hat approaches d, about 2.2 deg, '
        'from 2.7 deg; friction and the motor dead zone make the estimates differ',
        'standing', model1=MODEL1_STANDING, main_job=MAIN_JOB_STANDING,
        model1_key='standing_still'),
    Experiment(
        'height', 'Height 0.70 / 0.52 / 0.37 m while driving at 0.3 m/s, then back, IDA-PBC',
        'Fig. 5', 'passes beams at 0.70, 0.52 and 0.37 m forward and 0.37, 0.52, 0.70 m '
        'backward; stable throughout; l in (13) follows the measured height', 'height',
        model1=MODEL1_HEIGHT, main_job=MAIN_JOB_HEIGHT, model1_key='height_change'),
    Experiment(
        'rotate', 'Rotating clockwise at 165 deg/s at l = 0.70 m (joystick turbo): IDA-PBC '
        '(model (1)), the default configuration (main_job)',
        'Fig. 6', 'rotates clockwise at 165 deg/s smoothly; smooth wheel torques; the yaw does '
        'not disturb the balance', 'rotate', model1=MODEL1_ROTATE, main_job=MAIN_JOB_ROTATE,
        model1_key='rotating'),
    Experiment(
        's_turn', 'S-turn at l = 0.70 m: 0.3 m/s with left, right, left turns (1 rad/s), '
        'IDA-PBC', 'Fig. 7', 'turns anticlockwise, clockwise, anticlockwise; the operator '
        'corrects often and the jerky reference makes x_dot and the yaw rate oscillate; stable',
        's_turn', main_job=MAIN_JOB_S_TURN),
    Experiment(
        'bumps', 'Bumps: driving at up to 1 m/s (turbo) over two 2 cm bumps 0.8 m apart, '
        'IDA-PBC', 'Fig. 8', 'reaches the bumps at 1.5 s and 2.8 s; pitch and velocity change '
        'sharply at the bumps and the robot stays stable after them', 'bumps',
        main_job=MAIN_JOB_BUMPS),
    Experiment(
        'push', 'Kicks on the body: 60 N for 0.1 s, alternating forward and backward, the '
        'default configuration', 'Fig. 9', 'the paper (IDA-PBC: push_paper): each kick '
        'reverses the velocity; the pitch changes suddenly and returns quickly. The issue '
        '"control that beats the paper" asks at most 3 deg per kick, back within 1 deg in 1 s',
        'push', main_job=MAIN_JOB_PUSH),
    Experiment(
        'push_paper', 'Kicks on the body: 60 N for 0.1 s, alternating forward and backward, '
        'IDA-PBC', 'Fig. 9', 'each kick reverses the velocity (zero crossings); the pitch '
        'changes suddenly and returns quickly to its equilibrium (about 1.2 deg)', 'push',
        main_job=MAIN_JOB_PUSH_PAPER),
    Experiment(
        'slope', 'One wheel on a 7 deg, 1.2 m ramp while driving at 1 m/s (turbo), IDA-PBC, '
        'fixed legs (stiff hips, no levelling)',
        'Fig. 10', 'roll rises to 19 deg on the slope, the robot keeps straight and stable; '
        'after the wheel drops off the top the pitch returns to its equilibrium (2.2 deg)',
        'slope', main_job=MAIN_JOB_SLOPE),
    Experiment(
        'slope_levelled', 'The ramp of slope, the body kept level by the legs (roll '
        'levelling), IDA-PBC', 'Fig. 10',
        'not in the paper: its legs were fixed (roll 19 deg); here the legs level the body',
        'slope_levelled', main_job=MAIN_JOB_SLOPE_LEVELLED),
    Experiment(
        'sit_down', 'Sit-down on disarm while balancing, beside a torque cut (~/stop), IDA-PBC',
        '', 'not in the paper: lower, lean onto the tail under control, then zero torque; a '
        'cut drops the robot forward or backward', 'sit_down', main_job=MAIN_JOB_SIT_DOWN),
    Experiment(
        'velocity_step', 'Velocity step 0 -> 0.5 m/s -> 0 at l = 0.37 m through the joystick '
        "and teleop_node's limits, the default configuration", '',
        'not in the paper (it reports velocity tracking only as the S-turn, Fig. 7): the '
        'issue "control that beats the paper" asks a 10-90 % rise within 1 s, overshoot <= 10 '
        '%, pitch within 8 deg', 'velocity_step', main_job=MAIN_JOB_VELOCITY_STEP,
    ),
    Experiment(
        'robustness', 'Start-up from the tail under perturbations, every controller', '',
        'not in the paper (it reports robustness only as the bumps, kicks and slope runs): '
        '+-20 % mass, one tick of delay, a 6 N m torque limit, sensor noise, the IMU offset',
        'robustness', model1=MODEL1_ROBUSTNESS, model1_key='robustness'),
)

BY_NAME: Dict[str, Experiment] = {e.name: e for e in EXPERIMENTS}


def for_runner(runner: str) -> Tuple[Experiment, ...]:
    """Return the entries a runner ('model1' or 'main_job') runs, in table order."""
    if runner not in RUNNERS:
        raise ValueError('no runner %r (%s)' % (runner, ', '.join(RUNNERS)))
    return tuple(e for e in EXPERIMENTS if getattr(e, runner) is not None)


def metric_names(entry: Experiment, runner: str) -> Tuple[str, ...]:
    """Return the names of the metrics a runner reports for an entry, common ones included."""
    common = MODEL1_COMMON if runner == 'model1' else MAIN_JOB_COMMON.metrics
    return tuple(m.name for m in common + getattr(entry, runner).metrics)
