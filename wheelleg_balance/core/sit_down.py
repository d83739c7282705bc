r"""
The sit-down sequence: lower the body, lean it onto its tail under control, stop, let go.

Cutting the wheel torque of a balancing robot drops it forward or backward at random; only the
tail side is safe (the robot rests on its tail at +36 deg). So a disarm while balancing, and a
fault that leaves the sensors valid but ends balancing, run this sequence (core/balance_loop.py
drives it; the phases are the ``phase`` attribute):

1. ``lower``: the height reference goes to height_min (the legs' own rate limits), the balance
   controller keeps the robot standing; done when the reference is there and the measured
   height within 1 cm of it;
2. ``lean``: the body is rotated forward onto the tail along a *virtual constraint* on the
   pitch rate, theta_dot*(theta) = w_c + (w_peak - w_c) sin(pi s), s = (theta - theta_0) /
   (theta_tail - theta_0) in [0, 1]: fast through the middle, w_c at the tail. Tracking it with
   theta_ddot* = k e + k_i int(e) + (d theta_dot* / d theta) theta_dot, e = theta_dot* -
   theta_dot (the integral takes what model (1) leaves out: on the robot the wheel motors'
   reaction torque pitches the body too, so the model's force is too much), the cart
   acceleration that model (1)'s (4a) needs is nu = (g sin(theta) - l theta_ddot*) / cos(theta),
   and the partial feedback linearization (3) turns nu into the force u (core/model.py). The cart
   first moves back (nu < 0 tips the body forward), then forward to slow the rotation, so the
   robot hardly travels: on model (1) at l = 0.37 m, w_peak 2 rad/s and w_c 0.3 rad/s reach the
   tail in 0.6 s at 0.30 rad/s, 0.1 m from the start, at 1.9 m/s, with |u| below 110 N. The
   tail counts as reached contact_margin before it, or when the pitch stops rising within
   stall_margin of it. Holding the body near the tail takes a cart acceleration of g
   tan(theta) (6.6 m/s^2 at 34 deg), more than the wheels give for long, so the lean does not
   creep onto the tail: the brake takes over and its deceleration tips the body the rest of
   the way (where the tail touches depends on the legs' height and their give under the lean:
   34 deg at 0.35 m in the simulation, 36 deg at 0.37 m);
3. ``brake``: resting on the tail, the wheels brake the robot to a stop (a backward torque
   presses the body onto the tail, it cannot tip it back up). The force is blended from the
   lean's last one over brake_ramp: a step from the lean's forward force to the brake's
   backward one jolts the body onto the tail (0.70 rad/s at contact in the simulation,
   against 0.42 rad/s at the switch);
4. ``fold`` (driven legs): the legs fold down to their stops under control, the body still on
   its tail: once the motors rest, nothing holds the legs, and the body must already lie where
   it will stay (hips let go at 0.37 m unfolded the legs and tipped the robot back off its
   tail in the simulation);
5. ``done``: zero torque, exit motor mode (the loop disarms).

theta is the body's pitch (the IMU's theta~ minus the observer's d_hat), SI units throughout.
"""
from dataclasses import dataclass
import math
from typing import Optional

from .model import pfl_force
from .params import RobotParams

LOWER, LEAN, BRAKE, FOLD, DONE = 'lower', 'lean', 'brake', 'fold', 'done'


@dataclass(frozen=True)
class SitDownConfig:
    """
    Tuning of the sequence (see the module docstring).

    peak_rate: w_peak [rad/s]; contact_rate: w_c [rad/s]; rate_gain: k [1/s]; rate_ki: k_i
    [1/s^2]; tail_pitch: the pitch of the tail rest [rad]; contact_margin: the tail counts as
    reached this far before tail_pitch [rad]; stall_margin, stall_time: ... or when the pitch
    rate stays below 0.05 rad/s for stall_time [s] within stall_margin [rad] of it;
    brake_gain: wheel force per speed while braking [N s/m]; stop_speed: |x_dot| [m/s] below
    which the robot counts as stopped; timeout: longest lean [s] (then the wheels are cut, as
    a fault would); brake_ramp: time [s] over which the brake force replaces the lean's.
    """

    peak_rate: float = 2.0
    contact_rate: float = 0.3
    rate_gain: float = 20.0
    rate_ki: float = 60.0
    stall_margin: float = math.radians(10.0)
    stall_time: float = 0.1
    tail_pitch: float = math.radians(36.0)
    contact_margin: float = math.radians(2.0)
    brake_gain: float = 60.0
    stop_speed: float = 0.05
    timeout: float = 3.0
    brake_ramp: float = 0.1


class SitDown:
    """
    One run of the sequence; ``force`` gives u [N] for the lean and brake phases.

    p: the model; config: SitDownConfig; height_min [m]: where the lower phase goes.
    """

    def __init__(self, p: RobotParams, config: SitDownConfig = SitDownConfig(),
                 lower: bool = True):
        self.p = p
        self.config = config
        self.legs = lower   # driven legs: lowered first, folded last
        self.phase = LOWER if lower else LEAN
        self.theta_0: Optional[float] = None
        self.t_phase: Optional[float] = None
        self.contact_rate: Optional[float] = None   # pitch rate at tail contact [rad/s]
        self.max_force = 0.0
        self._u_lean = 0.0          # the lean's newest force [N], where the brake starts
        self._integral = 0.0
        self._last: Optional[float] = None
        self._stalled_since: Optional[float] = None

    def lowered(self, now: float, l_ref: float, l: float) -> None:
        """In ``lower``: move on to ``lean`` once the height reference and l [m] are down."""
        if self.phase == LOWER and abs(l_ref - self.p.height_min) < 1e-4 \
                and abs(l - self.p.height_min) < 0.01:
            self.phase = LEAN
            self.t_phase = now

    def force(self, now: float, theta: float, theta_dot: float, x_dot: float,
              l: float) -> float:
        """
        Return the force u [N] of the lean or brake phase (0 in the others).

        theta [rad] and theta_dot [rad/s]: body pitch and rate; x_dot [m/s]; l [m].
        """
        c = self.config
        if self.phase == LEAN:
            if self.t_phase is None:
                self.t_phase = now
            if self.theta_0 is None:
                self.theta_0 = min(theta, c.tail_pitch - 0.1)
            dt = 0.0 if self._last is None else max(0.0, now - self._last)
            self._last = now
            near = theta >= c.tail_pitch - c.stall_margin and abs(theta_dot) < 0.05
            self._stalled_since = (now if self._stalled_since is None else
                                   self._stalled_since) if near else None
            stalled = near and now - self._stalled_since >= c.stall_time
            if theta >= c.tail_pitch - c.contact_margin or stalled or \
                    now - self.t_phase > c.timeout:
                self.contact_rate = theta_dot
                self.phase = BRAKE
                self.t_phase = now
            else:
                self._u_lean = self._lean(theta, theta_dot, l, dt)
                return self._u_lean
        if self.phase == BRAKE:
            if abs(x_dot) < c.stop_speed:
                self.phase = FOLD if self.legs else DONE
                return 0.0
            blend = self.brake_blend(now)
            return (1.0 - blend) * self._u_lean - blend * c.brake_gain * x_dot
        if self.phase == FOLD:
            return -c.brake_gain * x_dot   # keep it standing still on the tail
        return 0.0

    def brake_blend(self, now: float) -> float:
        """Return how far [0, 1] the brake has taken over from the lean (1 after brake_ramp)."""
        if self.phase in (LOWER, LEAN) or self.t_phase is None:
            return 0.0
        ramp = self.config.brake_ramp
        return 1.0 if ramp <= 0.0 else min(1.0, max(0.0, (now - self.t_phase) / ramp))

    def folded(self) -> None:
        """In ``fold``: the legs are at their stops; the sequence is done."""
        if self.phase == FOLD:
            self.phase = DONE

    def _lean(self, theta: float, theta_dot: float, l: float, dt: float) -> float:
        c, p = self.config, self.p
        span = c.tail_pitch - self.theta_0
        s = min(max((theta - self.theta_0) / span, 0.0), 1.0)
        rise = c.peak_rate - c.contact_rate
        w_des = c.contact_rate + rise * math.sin(math.pi * s)
        dw = rise * math.pi / span * math.cos(math.pi * s) if 0.0 < s < 1.0 else 0.0
        error = w_des - theta_dot
        # Bounded: the integral corrects the model, it must not run away with the robot.
        self._integral = min(max(self._integral + c.rate_ki * error * dt, -20.0), 20.0)
        theta_ddot = c.rate_gain * error + self._integral + dw * theta_dot
        nu = (p.gravity * math.sin(theta) - l * theta_ddot) / math.cos(theta)
        u = pfl_force(theta, theta_dot, nu, l, p)
        self.max_force = max(self.max_force, abs(u))
        return u
