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
wheels up slowly, under ``min_dv``: the legs tell it then. With driven legs the hip torques
give the load each leg carries (core/kinematics.py ``leg_force``): on the ground about half the
body's weight, in the air the leg holds its wheel (f_l < 0). The legs' mean load below
``min_load`` for ``unloaded_time`` is the fault too; a bump or a drop of a few centimetres
unloads them for less.
"""
from collections import deque
import math
from typing import Deque, Optional, Sequence, Tuple


class LiftDetector:
    """
    The lifted check (see the module docstring).

    inertia: I_w, one wheel's (and its rotor's) inertia about the axle [kg m^2]; window [s];
    min_dv [rad/s]; ratio [-]; free_time [s]; min_load [N] (-inf: the legs' load is not
    known); unloaded_time [s]. ``update`` once per tick while the wheels are commanded;
    ``reset`` when they are not.
    """

    def __init__(self, inertia: float, window: float, min_dv: float, ratio: float,
                 free_time: float, min_load: float = -math.inf, unloaded_time: float = 0.05):
        self.min_load = min_load
        self.unloaded_time = unloaded_time
        self._unloaded_since: Optional[float] = None
        self.inertia = inertia
        self.window = window
        self.min_dv = min_dv
        self.ratio = ratio
        self.free_time = free_time
        # (time [s], sum of tau dt / I_w per wheel [rad/s], omega per wheel [rad/s])
        self._hist: Deque[Tuple[float, Tuple[float, float], Tuple[float, float]]] = deque()
        self._impulse = [0.0, 0.0]
        self._free_since: list = [None, None]
        #: The newest ratio d_omega / d_free per wheel (NaN: too little torque to tell).
        self.ratios = [math.nan, math.nan]

    def reset(self) -> None:
        """Forget the history (the wheels are not commanded)."""
        self._reset_wheels()
        self._unloaded_since = None

    def _reset_wheels(self) -> None:
        self._hist.clear()
        self._impulse = [0.0, 0.0]
        self._free_since = [None, None]
        self.ratios = [math.nan, math.nan]

    def update(self, now: float, torques: Sequence[float], speeds: Sequence[float],
               dt: float, load: float = math.nan) -> Optional[str]:
        """
        Take the torques [N m] applied over the last ``dt`` [s], the speeds [rad/s] now.

        load: the legs' mean load f_l [N] now (NaN: not known). Returns the reason when the
        robot is lifted (the fault), else None. A non-finite torque or speed restarts the
        window (the sensor checks name it).
        """
        if load < self.min_load:   # False for NaN
            if self._unloaded_since is None:
                self._unloaded_since = now
            if now - self._unloaded_since >= self.unloaded_time - 1e-9:
                return ('legs unloaded (lifted?): they carry %.0f N, less than lift_min_load '
                        '%.0f N, for %.0f ms' % (load, self.min_load,
                                                 1e3 * (now - self._unloaded_since)))
        else:
            self._unloaded_since = None
        if not all(math.isfinite(v) for v in (*torques, *speeds, dt)) or dt <= 0.0:
            self._reset_wheels()
            return None
        for k in (0, 1):
            self._impulse[k] += torques[k] * dt / self.inertia
        hist = self._hist
        hist.append((now, (self._impulse[0], self._impulse[1]), (speeds[0], speeds[1])))
        while len(hist) > 1 and now - hist[1][0] >= self.window - 1e-9:
            hist.popleft()
        t0, imp0, w0 = hist[0]
        if now - t0 < self.window - 1e-9:
            return None
        free = []
        for k in (0, 1):
            d_free = self._impulse[k] - imp0[k]
            d_omega = speeds[k] - w0[k]
            if abs(d_free) < self.min_dv:
                self.ratios[k] = math.nan
                self._free_since[k] = None
                continue
            self.ratios[k] = d_omega / d_free
            if self.ratios[k] >= self.ratio:
                if self._free_since[k] is None:
                    self._free_since[k] = now
            else:
                self._free_since[k] = None
            if self._free_since[k] is not None:
                free.append(k)
        since = [now - self._free_since[k] for k in free]
        if not (len(free) == 2 and min(since) >= self.free_time - 1e-9) \
                and not any(t >= 3.0 * self.free_time - 1e-9 for t in since):
            return None
        return ('wheels spin free (lifted?): %s wheel speed changed by %s of what a free '
                'wheel would (lift_ratio %.2f) over %.0f ms windows for %.0f ms' % (
                    ' and '.join(('left', 'right')[k] for k in free),
                    ', '.join('%.2f' % self.ratios[k] for k in free), self.ratio,
                    1e3 * self.window, 1e3 * max(since)))
