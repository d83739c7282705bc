"""
How MuJoCo plays each main_job entry of the table (validation/paper/table.py).

A ``Scenario`` pairs a table entry (name, title, figure, what the paper reports, criteria) with
what the nodes get and what happens when: the run's length, the controller and balance_node
parameters, sim_node's pushes and terrain, the joystick steps (sticks, and the height buttons
that teleop_node turns into cmd_height) and the actions on balance_node (live parameter
changes, disarm, re-arm, ~/stop). Every run starts as the robot does after power-up: folded on
its tail, armed at sim time ``ARM_AT``; balance_node homes the hips, raises the legs and stands
up. Times are seconds from the start of balancing (time 0, about ``HOMING_S`` after the arm);
sim_node's own events run on sim time (``ARM_AT + HOMING_S + t``).
"""
from dataclasses import dataclass, field, fields
from typing import Dict, List, Optional, Tuple

from .. import table
from ..table import D_HAT0, DEG, HEIGHTS, PAPER_YAW_GAIN, SIM_YAW_GAIN
from ....core.config import DEFAULTS
from ....core.ida_pbc import TUNED_GAINS
from ....core.params import IdaPbcGains, TABLE_I_IDA_PBC

HEIGHT_MAX, HEIGHT_MIN = HEIGHTS[0], HEIGHTS[-1]
#: LQR input weight of the softer linear start-up [1/N^2] (core/lqr.py default: 1/30^2).
SOFT_LQR_R = 1.0 / 10.0 ** 2
#: Sim time at which the robot is armed [s]: room for the processes to start and discover.
ARM_AT = 3.5
#: About how long balance_node takes from the arm to balancing (homing the hips on their
#: stops, raising the legs on the tail; 2.6 s in validation/lockstep.py) [s]: sim_node's own
#: events are scheduled this much after ARM_AT, and mapped back through the recorded clock.
HOMING_S = 3.0
#: The ramp of the slope runs (the paper's: 7 deg, 1.2 m, under the left wheel) [m, rad].
SLOPE = {'slope.enabled': True, 'slope.start_x': 5.0, 'slope.length': 1.2,
         'slope.angle': 7.0 * DEG, 'slope.side': 'left'}
#: Fixed legs for the paper's slope: no roll levelling, stiff hips (the paper's legs did not
#: move; the default impedance, kp 60, lets the body roll 11 deg further on the ramp).
FIXED_LEGS = {'legs.roll_kp': 0.0, 'legs.roll_ki': 0.0, 'legs.roll_kd': 0.0, 'legs.kp': 400.0,
              'legs.kd': 5.0}


def ida_pbc_params(gains: IdaPbcGains) -> Dict[str, float]:
    """balance_node's ``ida_pbc.*`` parameters that set ``gains``."""
    return {'ida_pbc.' + f.name: getattr(gains, f.name) for f in fields(gains)}


#: The paper's experiments (and slope_levelled, driven as slope is) run the paper's IDA-PBC
#: (Table I; the defaults add damping near upright rest, docs/ida_pbc.md section 8): what
#: config/paper_table_i.yaml sets.
PAPER_IDA_PBC = ida_pbc_params(TABLE_I_IDA_PBC)


@dataclass
class Scenario:
    """
    One main_job run: its table entry, what the nodes get, what happens when, what is plotted.

    pushes: (t, duration [s], f_x, f_y [N]) on the body; joy: joystick steps {'t', 'v' [m/s],
    'w' [rad/s], 'turbo', 'height' [m]} in physical units ('height' presses that height's
    button for the step), turned into stick deflections and buttons through the teleop
    configuration; actions: (t, name, value) on balance_node: a parameter set, or 'arm' (True:
    arm, False: disarm) or 'stop' (~/stop); balancing_until: when the scripted disarm ends the
    balancing the common criteria judge (None: the run's end); panels: the plot's panels
    (main_job/plots.py).
    """

    entry: table.Experiment
    duration: float
    panels: Tuple[str, ...]
    short_duration: Optional[float] = None
    controller: str = 'ida_pbc'
    balance: Dict[str, object] = field(default_factory=dict)
    sim: Dict[str, object] = field(default_factory=dict)
    pushes: List[Tuple[float, float, float, float]] = field(default_factory=list)
    joy: List[dict] = field(default_factory=list)
    joy_end: float = 0.0
    actions: List[Tuple[float, str, object]] = field(default_factory=list)
    balancing_until: Optional[float] = None

    @property
    def name(self) -> str:
        """Return the table entry's name."""
        return self.entry.name

    @property
    def title(self) -> str:
        """Return the table entry's title."""
        return self.entry.title

    @property
    def figure(self) -> str:
        """Return the paper's figure of the entry."""
        return self.entry.figure

    @property
    def paper(self) -> str:
        """Return what the paper reports (Sec. V-C)."""
        return self.entry.paper

    @property
    def kind(self) -> str:
        """Return the entry's evaluator (main_job/evaluate.EVALUATORS)."""
        return self.entry.kind

    @property
    def known_finding(self) -> str:
        """Return why this run is expected to fail ('' if it is not)."""
        return self.entry.known_finding

    @property
    def judging(self) -> table.Judging:
        """Return main_job's metrics, criteria and paper quotes of the entry."""
        return self.entry.main_job

    def duration_for(self, short: bool) -> float:
        """Return the run's length [s] (``--short``: the shorter one, if it has one)."""
        return self.short_duration if short and self.short_duration else self.duration

    @property
    def height_presses(self) -> List[Tuple[float, float]]:
        """(t [s], l [m]) of the joystick's height button presses."""
        return [(s['t'], s['height']) for s in self.joy if s.get('height') is not None]


def press(t: float, height: float, hold: float = 0.3) -> List[dict]:
    """Joystick steps that press the button of ``height`` [m] at t [s] for ``hold`` s."""
    return [{'t': t, 'height': height}, {'t': t + hold}]


#: Up to 0.70 m after the start-up (0.1 m/s: there by about 5 s).
UP_07 = press(1.0, HEIGHT_MAX)
STARTUP_PANELS = ('theta', 'theta_dot', 'x_dot', 'u')
SLOPE_DRIVE = [{'t': 0.0}, {'t': 2.5, 'v': 1.0, 'turbo': True},
               {'t': 12.0, 'v': 0.0, 'turbo': False}]

#: main_job's kicks: (t [s], duration [s], f_x, f_y [N]) on the body, the paper's 60 N for 0.1 s.
#: They run on sim time (params.sim_time): an arm later than ARM_AT (nodes slow to come up on a
#: loaded machine: 2.1 s late seen on 2026-12-03) brings them earlier after the start-up, so the
#: first comes 6 s after the planned start of balancing, well after the start-up has come to
#: rest (table.KICK_EARLIEST_S guards the rest).
KICKS = [(6.0, 0.1, 60.0, 0.0), (8.0, 0.1, -60.0, 0.0), (10.0, 0.1, 60.0, 0.0),
         (12.0, 0.1, -60.0, 0.0)]
PUSH_PANELS = ('theta', 'x_dot', 'u', 'torques')

#: Per table entry: the Scenario fields besides ``entry``.
_PLAYS: Dict[str, dict] = {
    # The default configuration (issue 12): long enough to come to rest (rest_time_s).
    'startup': {'duration': 8.0, 'panels': STARTUP_PANELS, 'short_duration': 4.0,
                'controller': DEFAULTS.control.controller},
    'startup_paper': {'duration': 6.0, 'panels': STARTUP_PANELS, 'short_duration': 4.0,
                      'balance': PAPER_IDA_PBC},
    'startup_tuned': {
        'duration': 6.0, 'panels': STARTUP_PANELS, 'short_duration': 4.0,
        'balance': ida_pbc_params(TUNED_GAINS)},
    'startup_lqr': {'duration': 4.0, 'panels': STARTUP_PANELS, 'controller': 'lqr'},
    'startup_lqr_soft': {'duration': 6.0, 'panels': STARTUP_PANELS, 'short_duration': 4.0,
                         'controller': 'lqr', 'balance': {'output_regulation.r': SOFT_LQR_R}},
    'standing': {
        # Output regulation from 3 s; 5 s to brake IDA-PBC's roll-out and find d, then the
        # STANDING_HOLD_S the issue judges (drift_20s_m).
        'duration': 8.0 + table.STANDING_HOLD_S,
        'panels': ('theta', 'theta_dot', 'x', 'x_dot', 'd_hat', 'u'),
        'balance': {'d_hat0': D_HAT0},
        'actions': [(3.0, 'controller', 'output_regulation')]},
    'height': {
        # Through the joystick's height buttons, teleop_node and cmd_height: balance_node shapes
        # each step at 0.1 m/s and 0.2 m/s^2 (0.70 -> 0.52 m in about 2.3 s), and the drives
        # pass each height for at least 1 s.
        'duration': 26.5, 'panels': ('l', 'x_dot', 'theta', 'torques'), 'balance': PAPER_IDA_PBC,
        'joy': [{'t': 0.0}] + UP_07 + [{'t': 5.0, 'v': 0.3}] + press(8.0, 0.52) +
        press(11.8, HEIGHT_MIN) + [{'t': 15.0, 'v': -0.3}] + press(16.5, 0.52) +
        press(20.5, HEIGHT_MAX) + [{'t': 25.0, 'v': 0.0}],
        'joy_end': 26.0},
    'rotate': {
        # The default configuration (issue 12) but for the yaw loop: the paper's proportional
        # loop on the wheels' yaw rate first, then the default yaw loop (PI on the gyro's)
        # from 9.5 s, judged over the turn's last 3 s.
        'duration': 17.0, 'panels': ('yaw_rate', 'torques', 'theta', 'x_dot'),
        'controller': DEFAULTS.control.controller,
        'balance': {'yaw_rate_gain': PAPER_YAW_GAIN, 'yaw_rate_ki': 0.0,
                    'yaw_rate_source': 'wheels'},
        'joy': [{'t': 0.0}] + UP_07 + [{'t': 5.5, 'w': -2.88, 'turbo': True},
                                       {'t': 15.5, 'w': 0.0, 'turbo': False}],
        'joy_end': 16.5,
        'actions': [(9.5, 'yaw_rate_ki', DEFAULTS.control.yaw_rate_ki),
                    (9.5, 'yaw_rate_source', DEFAULTS.control.yaw_rate_source)]},
    's_turn': {
        'duration': 18.0, 'panels': ('x_dot', 'yaw_rate', 'theta', 'torques'),
        'balance': dict(PAPER_IDA_PBC, yaw_rate_gain=SIM_YAW_GAIN),
        # Driving off at 3 s leaves IDA-PBC's slow velocity loop 5 s to reach 0.3 m/s before
        # the turns; the operator's corrections (+-0.2 rad/s) within each turn, as in the paper.
        'joy': [{'t': 0.0}] + UP_07 + [
            {'t': 3.0, 'v': 0.3}, {'t': 8.0, 'w': 1.0}, {'t': 9.0, 'w': 0.8},
            {'t': 9.6, 'w': 1.2}, {'t': 10.5, 'w': -1.0}, {'t': 11.4, 'w': -1.2},
            {'t': 12.2, 'w': -0.8}, {'t': 13.0, 'w': 1.0}, {'t': 13.9, 'w': 1.2},
            {'t': 14.7, 'w': 0.8}, {'t': 15.5, 'w': 0.0}, {'t': 16.5, 'v': 0.0}],
        'joy_end': 17.5},
    'bumps': {
        'duration': 12.0, 'panels': ('theta', 'x_dot', 'x', 'torques'),
        'sim': {'bumps': [3.0, 3.8], 'bump_height': 0.02}, 'balance': PAPER_IDA_PBC,
        'joy': [{'t': 0.0}, {'t': 2.0, 'v': 1.0, 'turbo': True},
                {'t': 10.0, 'v': 0.0, 'turbo': False}], 'joy_end': 11.0},
    'push': {'duration': 16.0, 'panels': PUSH_PANELS, 'pushes': KICKS,
             'controller': DEFAULTS.control.controller},
    'push_paper': {'duration': 16.0, 'panels': PUSH_PANELS, 'pushes': KICKS,
                   'balance': PAPER_IDA_PBC},
    'slope': {
        'duration': 14.0, 'panels': ('theta', 'roll', 'x_dot', 'torques'),
        'balance': dict(FIXED_LEGS, yaw_rate_gain=SIM_YAW_GAIN, **PAPER_IDA_PBC), 'sim': SLOPE,
        'joy': SLOPE_DRIVE, 'joy_end': 13.0},
    'slope_levelled': {
        # Driven as slope drives it (the same IDA-PBC, Table I's): only the legs differ.
        'duration': 14.0, 'panels': ('theta', 'roll', 'l', 'x_dot'),
        'balance': dict(PAPER_IDA_PBC, yaw_rate_gain=SIM_YAW_GAIN), 'sim': SLOPE,
        'joy': SLOPE_DRIVE, 'joy_end': 13.0},
    'sit_down': {
        # Balance, disarm (the sit-down), re-arm from the tail (the legs are homed: raise,
        # stand up), then ~/stop (the torque cut) for the comparison.
        'duration': 22.0, 'panels': ('theta', 'theta_dot', 'x', 'l'), 'balancing_until': 5.0,
        'actions': [(5.0, 'arm', False), (12.0, 'arm', True), (18.0, 'stop', None)]},
    'velocity_step': {
        # The default configuration; the step comes at 10 s, from rest (velocity_before_mps
        # says how close), back to 0 at 18 s.
        'controller': DEFAULTS.control.controller, 'duration': 26.0,
        'panels': ('x_dot', 'theta', 'u', 'torques'),
        'short_duration': 20.0,
        'joy': [{'t': 0.0}, {'t': 10.0, 'v': table.VELOCITY_STEP_MPS}, {'t': 18.0, 'v': 0.0}],
        'joy_end': 25.0},
}


def _scenarios() -> Tuple[Scenario, ...]:
    """Return a Scenario per main_job entry of the table, in table order."""
    names = [e.name for e in table.for_runner('main_job')]
    if set(names) != set(_PLAYS):
        raise RuntimeError('main_job scenarios %s do not match the table %s'
                           % (sorted(_PLAYS), sorted(names)))
    return tuple(Scenario(entry=table.BY_NAME[n], **_PLAYS[n]) for n in names)


SCENARIOS = _scenarios()
BY_NAME: Dict[str, Scenario] = {s.name: s for s in SCENARIOS}
