r"""
Lifted, wheels free: wheel motion that ground contact cannot explain (no rclpy, no CAN).

On the ground a wheel torque tau accelerates the whole robot: the wheel speed omega (relative
to the leg, forward positive) changes by about tau dt / J_ground, with J_ground about
I_w + (M / 2 + m / 2) r_w^2, some ten times the wheel's own inertia about its axle, I_w. A
robot that is picked up has free wheels: omega changes by tau dt / I_w, and a balance
controller that sees the wheel speed run away answers with more torque (a free wheel reaches
the MIT reply's 50 rad/s in about 30 ms at 12 N m). The speeds are the wheels' rotation in
the world, omega = w_rel + theta_dot (the encoder's reading relative to the leg plus the body's
pitch rate): a free wheel's follows the torque alone, whatever the body does, and on the
ground the body's swing (rising from the tail at 2 rad/s) does not enter.

``LiftDetector`` compares, over a sliding window of ``window`` seconds, each wheel's
measured speed change d_omega with the change a free wheel would have had from the torques
commanded meanwhile, d_free = sum(tau dt) / I_w. A wheel counts as free while
|d_free| >= ``min_dv`` (torque enough to tell) and d_omega / d_free >= ``ratio`` (on the
ground the ratio is near I_w / J_ground, about 0.1). Both wheels free for ``free_time``, or
one wheel for three times as long (the robot held by one side), is the fault: the caller cuts
the wheel torque. Wheels briefly free (a bump, a wheel over an edge) are not.

A held robot whose controller asks for little torque (held at its balance pitch) spins its
wheels up slowly, under ``min_dv``. With driven legs the hip torques give the load each leg
carries (core/kinematics.py ``leg_force``): on the ground about half the body's weight, in the
air the leg holds its wheel (f_l < 0). The legs' mean load below ``min_load`` for
``unloaded_time`` is the fault too; a bump or a drop of a few centimetres unloads them for less.

Legs that are not driven tell nothing, and the wheel speeds alone do not tell a small torque's
free wheel from one on the ground, where the body's lean moves the wheels as much as so small a
torque does. The body does. On the ground model (1) ties the body's pitch to the wheels'
motion: l theta_ddot = g sin(theta) - cos(theta) x_ddot with x_ddot = r_w omega_dot, so wheels
that speed up by d_omega turn the body's pitch rate by about -(r_w / l) d_omega (and a steady
lean holds a steady acceleration); in a hand the body holds still whatever the wheels do. So
over a longer window, ``still_window``, both wheels count as free too while each changed speed
as a free wheel would (ratio >= ``ratio``) with d_free >= ``still_min_dv`` only, provided the
pitch rate changed by at most ``still_ratio`` of (r_w / l) |d_omega| (the mean of both wheels).
On the ground a wheel that follows its torque like a free one is the body's doing (a steady
state has a ratio near 0.1), and then the body moves. In MuJoCo (validation/lockstep.py)
main_job's experiments had both wheels count as free for at most 4 ms (12 ms in the LQR
start-up with fixed legs, which falls all the same), with fixed legs and driven, the body mass
+-30 % and d +-3 deg; the robot lifted at its balance pitch with fixed legs faults 82 ms after
the pick-up, its wheels at 1.5 rad/s (docs/faults.md has the figures).

A robot in the air but held by nobody (a hop over a bump, a drop off a ramp) is in free fall:
its wheels spin free and its legs carry nothing, but it is no hand's. The IMU's specific force
tells: near g while something carries the robot, near 0 in free fall. Below ``FREE_FALL`` g the
rules rest (the wheels are not counted free, the legs not unloaded). An IMU that never reported
a plausible specific force is not used for it, nor one that reports exact zeros (a driver
without an accelerometer: core/sensors.py gives NaN for them).
"""
from collections import deque
import math
from math import isfinite
from typing import Deque, Optional, Sequence, Tuple

#: Specific force [g] below which the robot is in free fall, held by nobody (a hop, a drop).
FREE_FALL = 0.5
#: Specific forces [g] an accelerometer that measures reports at rest (about 1): one seen
#: tells that the IMU has an accelerometer; a driver without one reports zeros.
PLAUSIBLE_FORCE = (0.5, 1.5)
_FORCE_LOW, _FORCE_HIGH = PLAUSIBLE_FORCE
NAN = math.nan


class FreeWheelNotice:
    """
    A notice that the wheels are free on purpose until ``until`` [s] (a planned window).

    The lift and response checks do not judge meanwhile and start afresh after it.

    One mechanism for every planned free-wheel or flight window: the identification's stand
    phase (core/excitation.py), a jump's flight. ``announce`` it with its end and why,
    ``withdraw`` it when the window ends early.
    """

    def __init__(self):
        self.until = -math.inf
        self.reason = ''

    def announce(self, until: float, reason: str) -> None:
        """Free wheels are planned up to ``until`` [s] (monotonic), for ``reason``."""
        self.until, self.reason = until, reason

    def withdraw(self) -> None:
        """End the window now."""
        self.until, self.reason = -math.inf, ''

    def covers(self, now: float) -> bool:
        """Return True while the window lasts at ``now`` [s]."""
        return now < self.until


class LiftDetector:
    """
    The lifted check (see the module docstring).

    inertia: I_w, one wheel's (and its rotor's) inertia about the axle [kg m^2]; window [s];
    min_dv [rad/s]; ratio [-]; free_time [s]; min_load [N] (-inf: the legs' load is not
    known); unloaded_time [s]; still_window [s], still_min_dv [rad/s], still_ratio [-] of the
    still-body rule; wheel_radius r_w [m]; gravity [m/s^2]. ``update`` (or ``step``, the same
    with the wheels' figures apart) once per tick while the wheels are commanded; ``reset``
    when they are not.
    """

    def __init__(self, inertia: float, window: float, min_dv: float, ratio: float,
                 free_time: float, min_load: float = -math.inf, unloaded_time: float = 0.05,
                 still_window: float = 0.04, still_min_dv: float = 0.5,
                 still_ratio: float = 0.3, wheel_radius: float = 0.1, gravity: float = 9.81):
        self.still_window = still_window
        self.still_min_dv = still_min_dv
        self.still_ratio = still_ratio
        self.wheel_radius = wheel_radius
        self.gravity = gravity
        # The samples over still_window: (time [s], sum of tau dt / I_w of the left and the
        # right wheel [rad/s], omega left and right [rad/s], pitch rate [rad/s]). ``_hist``
        # holds the same tuples over ``window`` (one tuple per tick serves both).
        self._still: Deque[Tuple[float, float, float, float, float, float]] = deque()
        #: True once the IMU reported a plausible specific force (it has an accelerometer).
        self.accel_seen = False
        #: The newest still-body figures: the pitch rate's change over the one (r_w / l)
        #: |d_omega| gives on the ground [-] (NaN: not judged).
        self.still_share = math.nan
        self.min_load = min_load
        self.unloaded_time = unloaded_time
        self._unloaded_since: Optional[float] = None
        self.inertia = inertia
        self.window = window
        self.min_dv = min_dv
        self.ratio = ratio
        self.free_time = free_time
        self._hist: Deque[Tuple[float, float, float, float, float, float]] = deque()
        # sum of tau dt / I_w per wheel [rad/s]; since when each wheel counts as free [s]
        self._impulse_l = self._impulse_r = 0.0
        self._free_l: Optional[float] = None
        self._free_r: Optional[float] = None
        #: The newest ratio d_omega / d_free per wheel (NaN: too little torque to tell).
        self.ratios = [math.nan, math.nan]

    def reset(self) -> None:
        """Forget the history (the wheels are not commanded)."""
        self._reset_wheels()
        self._unloaded_since = None

    def _reset_wheels(self) -> None:
        self._hist.clear()
        self._still.clear()
        self.still_share = math.nan
        self._impulse_l = self._impulse_r = 0.0
        self._free_l = self._free_r = None
        self.ratios = [math.nan, math.nan]

    def update(self, now: float, torques: Sequence[float], speeds: Sequence[float],
               dt: float, load: float = math.nan, pitch_rate: float = math.nan,
               height: float = math.nan, specific_force: float = math.nan) -> Optional[str]:
        """
        Take the torques [N m] applied over the last ``dt`` [s], the speeds [rad/s] now.

        load: the legs' mean load f_l [N] now (NaN: not known); pitch_rate: the body's
        [rad/s] and height: l [m] for the still-body rule (NaN: not judged, e.g. far from
        upright); specific_force: |the IMU's linear acceleration| [m/s^2] (NaN: not known).
        Returns the reason when the robot is lifted (the fault), else None. A non-finite torque
        or speed restarts the windows (the sensor checks name it).
        """
        return self.step(now, torques[0], torques[1], speeds[0], speeds[1], dt, load,
                         pitch_rate, height, specific_force)

    def step(self, now: float, tau_l: float, tau_r: float, omega_l: float, omega_r: float,
             dt: float, load: float, pitch_rate: float, height: float,
             specific_force: float) -> Optional[str]:
        """``update`` with the left and right wheel's torque [N m] and speed [rad/s] apart."""
        g = self.gravity
        if not self.accel_seen and _FORCE_LOW * g <= specific_force <= _FORCE_HIGH * g:
            self.accel_seen = True   # for good: once seen, not judged again
        falling = self.accel_seen and specific_force < FREE_FALL * g   # False for NaN
        if load < self.min_load and not falling:   # False for NaN
            if self._unloaded_since is None:
                self._unloaded_since = now
            if now - self._unloaded_since >= self.unloaded_time - 1e-9:
                return ('legs unloaded (lifted?): they carry %.0f N, less than lift_min_load '
                        '%.0f N, for %.0f ms' % (load, self.min_load,
                                                 1e3 * (now - self._unloaded_since)))
        else:
            self._unloaded_since = None
        if not (isfinite(tau_l) and isfinite(tau_r) and isfinite(omega_l) and isfinite(omega_r)
                and isfinite(dt)) or dt <= 0.0:
            self._reset_wheels()
            return None
        inertia = self.inertia
        self._impulse_l = imp_l = self._impulse_l + tau_l * dt / inertia
        self._impulse_r = imp_r = self._impulse_r + tau_r * dt / inertia
        # One tuple per tick for both windows; its pitch rate serves the still-body rule only.
        sample = (now, imp_l, imp_r, omega_l, omega_r, pitch_rate)
        hist = self._hist
        hist.append(sample)
        span = self.window - 1e-9
        while len(hist) > 1 and now - hist[1][0] >= span:
            hist.popleft()
        still = self._still_body(now, sample, pitch_rate, height)
        t0, imp0_l, imp0_r, w0_l, w0_r, _ = hist[0]
        young = now - t0 < span
        if young and not still:
            return None
        ratio, min_dv, ratios = self.ratio, self.min_dv, self.ratios
        d_free = imp_l - imp0_l
        # |d_free| < min_dv (False for NaN), or the window not yet full: no ratio
        r = NAN if abs(d_free) < min_dv or young else (omega_l - w0_l) / d_free
        ratios[0] = r
        if (r >= ratio or still) and not falling:
            if self._free_l is None:
                self._free_l = now
        else:
            self._free_l = None
        d_free = imp_r - imp0_r
        r = NAN if abs(d_free) < min_dv or young else (omega_r - w0_r) / d_free
        ratios[1] = r
        if (r >= ratio or still) and not falling:
            if self._free_r is None:
                self._free_r = now
        else:
            self._free_r = None
        if self._free_l is None and self._free_r is None:
            return None   # no wheel free (on the ground: nearly every tick)
        return self._free_reason(now, still)

    def _free_reason(self, now: float, still: bool) -> Optional[str]:
        """With a wheel free: the fault's reason once free long enough, else None."""
        free = [k for k, since in enumerate((self._free_l, self._free_r)) if since is not None]
        since = [now - (self._free_l, self._free_r)[k] for k in free]
        if not (len(free) == 2 and min(since) >= self.free_time - 1e-9) \
                and not any(t >= 3.0 * self.free_time - 1e-9 for t in since):
            return None
        if still:
            return ('wheels spin free and the body holds still (lifted?): the pitch rate '
                    "changed by %.2f of what the wheels' acceleration gives on the ground "
                    '(lift_still_ratio %.2f) over %.0f ms windows for %.0f ms' % (
                        self.still_share, self.still_ratio, 1e3 * self.still_window,
                        1e3 * max(since)))
        return ('wheels spin free (lifted?): %s wheel speed changed by %s of what a free '
                'wheel would (lift_ratio %.2f) over %.0f ms windows for %.0f ms' % (
                    ' and '.join(('left', 'right')[k] for k in free),
                    ', '.join('%.2f' % self.ratios[k] for k in free), self.ratio,
                    1e3 * self.window, 1e3 * max(since)))

    def _still_body(self, now: float, sample: Tuple[float, float, float, float, float, float],
                    pitch_rate: float, height: float) -> bool:
        """
        Judge the still-body rule over ``still_window``: both wheels free, the body still.

        sample: this tick's (time, impulse left, right, omega left, right, pitch rate).
        Returns True when both wheels changed speed as free wheels would (d_free >=
        still_min_dv) while the pitch rate changed by at most still_ratio of (r_w / l) |mean
        d_omega| (see the module docstring).
        """
        still = self._still
        if not (isfinite(pitch_rate) and isfinite(height) and height > 0.0):
            still.clear()
            self.still_share = math.nan
            return False
        still.append(sample)
        span = self.still_window - 1e-9
        while len(still) > 1 and now - still[1][0] >= span:
            still.popleft()
        t0, imp0_l, imp0_r, w0_l, w0_r, q0 = still[0]
        self.still_share = math.nan
        if now - t0 < span:
            return False
        _, imp_l, imp_r, omega_l, omega_r, _ = sample
        min_dv, ratio = self.still_min_dv, self.ratio
        d_free = imp_l - imp0_l
        if abs(d_free) < min_dv or (omega_l - w0_l) / d_free < ratio:
            return False
        d_free = imp_r - imp0_r
        if abs(d_free) < min_dv or (omega_r - w0_r) / d_free < ratio:
            return False
        d_omega = 0.5 * (omega_l - w0_l + omega_r - w0_r)
        ground = self.wheel_radius / height * abs(d_omega)
        self.still_share = abs(pitch_rate - q0) / ground
        return self.still_share <= self.still_ratio
