r"""
The identification's excitation as a part of the tick (issue 32): scripted phases on the robot.

No rclpy, no CAN. Three phases, each recorded for identification/fit.py (docs/identification.md
says which quantity each makes identifiable):

- ``stand``: the robot on a stand, wheels free; torque steps then a chirp per wheel (the
  wheel's inertia, damping and the command's delay). Played in the mode EXCITING from
  DISARMED, after a probe: ``PROBE_TORQUE`` on both wheels for ``PROBE_TIME`` must change
  their speed by at least ``PROBE_RATIO`` of what a free wheel's inertia I_w
  (``lift_wheel_inertia``) gives, tau t / I_w. On the ground the whole robot's inertia,
  about ten times I_w, takes it (core/lift.py): the probe refuses the phase then. The lift and
  response checks are told the wheels are free on purpose (core/lift.py ``FreeWheelNotice``).
- ``tail``: resting on the tail, torque pulses both ways (the rolling mass M + m and the wheel
  radius against the IMU's specific force), in EXCITING from DISARMED. The pulses stay below
  ``TAIL_SHARE`` of the torque that lifts the body off its tail. Model (1) with the pitch held
  by the tail at theta_t and the tail's force zero: the body leaves the tail (theta_ddot < 0)
  once cos(theta_t) x_ddot > g sin(theta_t), with x_ddot = (u - m g s c) / (M + m s^2)
  (s, c of theta_t, theta_dot = 0), that is once u > (M + m) g tan(theta_t): per wheel
  tau_lift = (M + m) g tan(theta_t) r_w / 2 (``tail_lift_torque``), taken at the lowest pitch
  that still counts as the tail (tail_pitch - arm_pose_tolerance). Table I: 3.35 N m.
- ``balance``: balancing (BALANCING), the references replaced: at each height of ``HEIGHTS``
  (the driven legs; else the height as it is) ``SETTLE`` s still, then ``SWEEP`` s of x_dot* =
  ``X_DOT_AMPLITUDE`` times a chirp from 0.3 to 1.5 Hz (the pendulum's m l, the centre of mass
  from the heights, the IMU offset d). The operator's cmd_vel and cmd_height are ignored
  meanwhile.

Refused, with the reason, unless DISARMED (stand, tail; tail also resting on the tail), or
BALANCING and still (balance: not rising, |theta_dot| below ``arm_still_rate``, |x_dot| below
``STILL_SPEED``). Abort limits end a phase with a one-line reason: a wheel speed beyond
``STAND_MAX_SPEED`` / ``TAIL_MAX_SPEED``, the body moved on its stand by ``STAND_MAX_PITCH``,
left its tail, or (balance) |theta~ - d_hat| beyond ``BALANCE_MAX_PITCH`` or |x_dot| beyond
``BALANCE_MAX_SPEED``; each phase ends at its program's end, and at ``MAX_OVERRUN`` s past it
whatever the clock did. Stand and tail end in DISARMED (zero torque, the motors to rest),
balance in the sit-down; ``~/stop`` and ``~/arm false`` end any at once. The stand's torque
amplitude is bounded by the abort speed: a step of STAND_STEP s changes a free wheel's speed by
A STAND_STEP / I_w, kept at half of STAND_MAX_SPEED (``stand_amplitude``).
"""
import math
from typing import Optional, Sequence, Tuple

import numpy as np

from .config import BalanceConfig
from .safety import SensorSnapshot
from .tick_io import CmdHeight, CmdVel

#: The control period the programs are written at [s] (balance_node's).
PERIOD = 0.002
STAND, TAIL, BALANCE = 'stand', 'tail', 'balance'
PHASES = (STAND, TAIL, BALANCE)
#: ~/state's ``excitation`` value of each phase (0: none runs).
PHASE_INDEX = {STAND: 1, TAIL: 2, BALANCE: 3}

#: stand: duration [s], torque amplitude [N m], step length [s]; tail: duration [s], pulse
#: torque [N m] per wheel, pulse length [s].
STAND_DURATION, STAND_AMPLITUDE, STAND_STEP = 3.0, 0.8, 0.2
TAIL_DURATION, TAIL_AMPLITUDE, TAIL_PULSE = 3.0, 0.5, 0.25
#: balance: heights [m], still time and chirp time per height [s], x_dot* amplitude [m/s].
HEIGHTS = (0.37, 0.46, 0.55)
SETTLE, SWEEP, X_DOT_AMPLITUDE = 1.0, 3.0, 0.25

#: The stand's probe: torque per wheel [N m], time [s], measured over free speed change [-]
#: from which the wheels count as free (on the ground <= 0.45, MuJoCo: ``lift_ratio``'s doc;
#: a free wheel 1 less what the command's delay takes of the probe).
PROBE_TORQUE, PROBE_TIME, PROBE_RATIO = 0.3, 0.1, 0.5
#: Abort limits: wheel speed in the world [rad/s] (stand, tail), the body's pitch change on
#: the stand [rad], balance: |theta~ - d_hat| [rad] and |x_dot| [m/s].
STAND_MAX_SPEED, TAIL_MAX_SPEED = 40.0, 20.0
STAND_MAX_PITCH = math.radians(5.0)
BALANCE_MAX_PITCH, BALANCE_MAX_SPEED = math.radians(10.0), 1.0
#: The tail's pulses at most this share of the torque that lifts the body off its tail.
TAIL_SHARE = 0.25
#: |x_dot| [m/s] below which a balancing robot counts as still for the balance phase.
STILL_SPEED = 0.1
#: A phase ends at the latest this long after its program's end [s].
MAX_OVERRUN = 0.5


def chirp(t: np.ndarray, f0: float, f1: float, duration: float) -> np.ndarray:
    """Return sin of a linear chirp from f0 to f1 [Hz] over duration [s] at times t [s]."""
    k = (f1 - f0) / duration
    return np.sin(2.0 * math.pi * (f0 * t + 0.5 * k * t * t))


def stand_torques(duration: float = STAND_DURATION, amplitude: float = STAND_AMPLITUDE,
                  period: float = PERIOD) -> np.ndarray:
    """
    Return the stand's wheel torque program [N m] per tick: (left, right) rows.

    The first half steps between +amplitude and -amplitude every STAND_STEP s (starting up, so
    the wheel speed stays one-signed and bounded), the second half a chirp from 1 to 20 Hz; the
    right wheel plays the left's program shifted by a quarter of it, so both wheels' data
    are not one.
    """
    n = int(round(duration / period))
    t = np.arange(n) * period
    half = 0.5 * duration
    steps = amplitude * np.where(np.floor(t / STAND_STEP) % 2 == 0, 1.0, -1.0)
    sweep = amplitude * chirp(t - half, 1.0, 20.0, half)
    left = np.where(t < half, steps, sweep)
    return np.stack([left, np.roll(left, n // 4)], axis=1)


def tail_torques(duration: float = TAIL_DURATION, amplitude: float = TAIL_AMPLITUDE,
                 period: float = PERIOD) -> np.ndarray:
    """
    Return the tail's wheel torque program [N m] per tick (left, right rows): pulses.

    TAIL_PULSE s pulses of +amplitude, a pause, -amplitude, a pause, repeated: the robot rolls
    forward and back about where it started, the body on its tail.
    """
    n = int(round(duration / period))
    t = np.arange(n) * period
    phase = np.floor(t / TAIL_PULSE) % 4
    tau = amplitude * np.select([phase == 0, phase == 2], [1.0, -1.0], 0.0)
    return np.stack([tau, tau], axis=1)


def balance_references(heights: Sequence[float], settle: float = SETTLE,
                       sweep: float = SWEEP, amplitude: float = X_DOT_AMPLITUDE,
                       period: float = PERIOD) -> np.ndarray:
    """Return the balance phase's (x_dot* [m/s], l* [m]) per tick: per height, still, a chirp."""
    n_settle, n_sweep = int(round(settle / period)), int(round(sweep / period))
    s = np.arange(n_sweep) * period
    x_dot = np.concatenate([np.zeros(n_settle), amplitude * chirp(s, 0.3, 1.5, sweep)])
    rows = [np.stack([x_dot, np.full(x_dot.size, l)], axis=1) for l in heights]
    # Still again at the end: the operator's references take over from x_dot* = 0.
    rows.append(np.stack([np.zeros(n_settle), np.full(n_settle, heights[-1])], axis=1))
    return np.concatenate(rows)


def tail_lift_torque(cfg: BalanceConfig) -> float:
    """Return the per-wheel torque [N m] that lifts the body off its tail (module docstring)."""
    p, sc = cfg.model, cfg.safety
    theta = sc.tail_pitch - sc.arm_pose_tolerance
    return (p.body_mass + p.wheel_mass) * p.gravity * math.tan(theta) * p.wheel_radius / 2.0


def stand_amplitude(cfg: BalanceConfig) -> float:
    """Return the stand's torque amplitude [N m]: STAND_AMPLITUDE within the speed bound."""
    bound = 0.5 * STAND_MAX_SPEED * cfg.safety.lift_wheel_inertia / STAND_STEP
    return min(STAND_AMPLITUDE, bound, cfg.safety.max_wheel_torque)


def tail_amplitude(cfg: BalanceConfig) -> float:
    """Return the tail's pulse torque [N m]: TAIL_AMPLITUDE within TAIL_SHARE of the lift's."""
    return min(TAIL_AMPLITUDE, TAIL_SHARE * tail_lift_torque(cfg), cfg.safety.max_wheel_torque)


class Excitation:
    """
    The excitation's state (see the module docstring): which phase runs, since when.

    ``refusal`` says why a phase may not start, ``start`` starts it; per tick ``torques``
    (stand, tail) or ``references`` and ``balance_abort`` (balance); ``end`` at any end.
    """

    def __init__(self, cfg: BalanceConfig):
        self.phase = ''
        self.probing = False
        #: The operator's line of the running phase (the stand's reply after its probe).
        self.line = ''
        #: The wheel torques of the newest tick [N m] (stand, tail).
        self.tau = (0.0, 0.0)
        #: The newest probe's speed change over a free wheel's, left and right [-].
        self.probe_ratios = (math.nan, math.nan)
        self.start_time = 0.0
        self.program = np.zeros((0, 2))
        self._theta0 = 0.0
        self._w0 = (0.0, 0.0)
        self.configure(cfg)

    def configure(self, cfg: BalanceConfig) -> None:
        """Take the settings of ``cfg`` (a running phase keeps its program)."""
        self.cfg = cfg

    @property
    def index(self) -> int:
        """Return ~/state's ``excitation`` value: PHASE_INDEX of the phase, 0 for none."""
        return PHASE_INDEX.get(self.phase, 0)

    @property
    def duration(self) -> float:
        """Return the running phase's length [s]: the probe and the program."""
        probe = PROBE_TIME if self.phase == STAND else 0.0
        return probe + len(self.program) * self.cfg.loop.control_period

    def progress(self, now: float) -> float:
        """Return the share of the running phase played [0..1] (0 when none runs)."""
        if not self.phase:
            return 0.0
        return min(1.0, max(0.0, (now - self.start_time) / self.duration))

    # ------------------------------------------------------------------------ starting

    def refusal(self, phase: str, mode_name: str, s: SensorSnapshot, x_dot: float,
                rising: bool) -> str:
        """Return why ``phase`` may not start now ('' when it may; the mode by its name)."""
        if phase not in PHASES:
            return 'unknown phase %r (%s)' % (phase, ', '.join(PHASES))
        if self.phase:
            return 'the %s phase runs' % self.phase
        sc = self.cfg.safety
        if phase == BALANCE:
            if mode_name != 'BALANCING':
                return 'balance needs the robot balancing (mode %s): ~/arm true first' % mode_name
            if rising:
                return 'balance: still rising from the tail'
            if not abs(s.theta_dot) <= sc.arm_still_rate or not abs(x_dot) <= STILL_SPEED:
                return ('balance: not still (|theta_dot| %.2f rad/s, limit %.2f; |x_dot| %.2f '
                        'm/s, limit %.2f)' % (abs(s.theta_dot), sc.arm_still_rate, abs(x_dot),
                                              STILL_SPEED))
            return ''
        if mode_name != 'DISARMED':
            return '%s needs the robot disarmed (mode %s): ~/arm false first' % (phase, mode_name)
        if phase == TAIL and not abs(s.theta - sc.tail_pitch) <= sc.arm_pose_tolerance:
            return ('tail: not resting on its tail (pitch %.1f deg, the tail %.0f +- %.0f deg)'
                    % (math.degrees(s.theta), math.degrees(sc.tail_pitch),
                       math.degrees(sc.arm_pose_tolerance)))
        return ''

    def start(self, phase: str, now: float, s: SensorSnapshot, height: float) -> str:
        """Start ``phase`` (its refusal was ''); return the line for the operator."""
        cfg, period = self.cfg, self.cfg.loop.control_period
        self.phase, self.start_time, self.probing = phase, now, phase == STAND
        self._theta0 = s.theta
        self._w0 = (s.wheel_vel_left + s.theta_dot, s.wheel_vel_right + s.theta_dot)
        if phase == STAND:
            a = stand_amplitude(cfg)
            self.program = stand_torques(STAND_DURATION, a, period)
            self.line = ('stand: probing the wheels (%.2f N m for %.0f ms), then steps and a '
                         'chirp of %.2f N m for %.1f s' % (PROBE_TORQUE, 1e3 * PROBE_TIME, a,
                                                           STAND_DURATION))
            return self.line
        if phase == TAIL:
            a = tail_amplitude(cfg)
            self.program = tail_torques(TAIL_DURATION, a, period)
            self.line = ('tail: pulses of %.2f N m per wheel for %.1f s (%.2f N m lifts the body '
                         'off its tail)' % (a, TAIL_DURATION, tail_lift_torque(cfg)))
            return self.line
        p = cfg.model
        heights = [p.clamp_height(l) for l in HEIGHTS] if cfg.legs.driven else [height]
        self.program = balance_references(heights, period=period)
        self.line = ('balance: x_dot* chirps of %.2f m/s at %s m, %.1f s' % (
            X_DOT_AMPLITUDE, ', '.join('%.2f' % l for l in heights), self.duration))
        return self.line

    def end(self) -> None:
        """End the running phase (none runs afterwards)."""
        self.phase, self.probing, self.tau = '', False, (0.0, 0.0)
        self.program = np.zeros((0, 2))

    # ------------------------------------------------------------------------ per tick

    def _row(self, now: float, offset: float) -> Optional[np.ndarray]:
        """Return the program's row at ``now`` [s] (None: past its end)."""
        k = int((now - self.start_time - offset) / self.cfg.loop.control_period + 1e-9)
        return self.program[max(k, 0)] if k < len(self.program) else None

    def torques(self, now: float, s: SensorSnapshot) -> Tuple[float, float, str, bool]:
        """
        Return (tau_left, tau_right [N m], why it ends ('': it goes on), done) for stand, tail.

        done: the program played to its end (else an abort or a refusal after the probe).
        """
        elapsed = now - self.start_time
        if elapsed > self.duration + MAX_OVERRUN:
            return 0.0, 0.0, '%s: past its end by %.1f s' % (self.phase, MAX_OVERRUN), False
        w_l, w_r = s.wheel_vel_left + s.theta_dot, s.wheel_vel_right + s.theta_dot
        sc = self.cfg.safety
        if self.phase == STAND:
            if abs(s.theta - self._theta0) > STAND_MAX_PITCH:
                return 0.0, 0.0, ('stand: the body moved on its stand by %.1f deg (limit %.0f)'
                                  % (math.degrees(abs(s.theta - self._theta0)),
                                     math.degrees(STAND_MAX_PITCH))), False
            limit = STAND_MAX_SPEED
        else:
            if not abs(s.theta - sc.tail_pitch) <= sc.arm_pose_tolerance:
                return 0.0, 0.0, ('tail: the body left its tail (pitch %.1f deg)'
                                  % math.degrees(s.theta)), False
            limit = TAIL_MAX_SPEED
        if not (abs(w_l) <= limit and abs(w_r) <= limit):
            return 0.0, 0.0, ('%s: wheel speed %.1f / %.1f rad/s beyond %.0f rad/s' % (
                self.phase, w_l, w_r, limit)), False
        if self.probing:
            if elapsed < PROBE_TIME:
                return PROBE_TORQUE, PROBE_TORQUE, '', False
            why = self._probe_verdict(elapsed, w_l, w_r)
            if why:
                return 0.0, 0.0, why, False
            self.probing = False
        row = self._row(now, PROBE_TIME if self.phase == STAND else 0.0)
        if row is None:
            return 0.0, 0.0, '%s: done, %.1f s' % (self.phase, elapsed), True
        return float(row[0]), float(row[1]), '', False

    def _probe_verdict(self, elapsed: float, w_l: float, w_r: float) -> str:
        """Return why the probe says the wheels are not free ('' when both are)."""
        free = PROBE_TORQUE * elapsed / self.cfg.safety.lift_wheel_inertia
        self.probe_ratios = ratios = ((w_l - self._w0[0]) / free, (w_r - self._w0[1]) / free)
        if min(ratios) >= PROBE_RATIO:
            return ''
        return ('stand refused: the wheels are not free (the probe changed their speed by '
                "%.2f / %.2f of a free wheel's, at least %.2f): put the robot on its stand"
                % (ratios[0], ratios[1], PROBE_RATIO))

    @property
    def probe_passed(self) -> bool:
        """Return True once the stand's probe found the wheels free (the program plays)."""
        return self.phase == STAND and not self.probing

    def references(self, now: float) -> Tuple[Optional[CmdVel], Optional[CmdHeight]]:
        """Return the balance phase's cmd_vel and cmd_height at ``now`` (the height None: kept)."""
        row = self._row(now, 0.0)
        if row is None:
            return CmdVel(now, 0.0, 0.0), None
        height = CmdHeight(now, float(row[1])) if self.cfg.legs.driven else None
        return CmdVel(now, float(row[0]), 0.0), height

    def balance_abort(self, now: float, theta: float, x_dot: float) -> Tuple[str, bool]:
        """Return (why the balance phase ends, '' when it goes on; done) at theta~ - d_hat."""
        if not abs(theta) <= BALANCE_MAX_PITCH:
            return ('balance: |theta| %.1f deg beyond %.0f deg' % (
                math.degrees(abs(theta)), math.degrees(BALANCE_MAX_PITCH))), False
        if not abs(x_dot) <= BALANCE_MAX_SPEED:
            return 'balance: |x_dot| %.2f m/s beyond %.1f m/s' % (abs(x_dot),
                                                                  BALANCE_MAX_SPEED), False
        if self._row(now, 0.0) is None:
            return 'balance: done, %.1f s' % (now - self.start_time), True
        return '', False

    def status(self, now: float) -> dict:
        """Return the excitation's part of /diagnostics: the phase and its progress."""
        return {'excitation': self.phase or 'none',
                'excitation_progress': self.progress(now),
                'excitation_probing': self.probing,
                'excitation_probe_ratios': self.probe_ratios}
