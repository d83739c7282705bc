r"""
The pitch's answer to the wheel torque, of the sign model (1) says or not (no rclpy, no CAN).

Model (1) splits the pitch acceleration into a part without force and the force's part,
theta_ddot = f(theta, theta_dot, u) = f(theta, theta_dot, 0) + [f(theta, theta_dot, u) -
f(theta, theta_dot, 0)] (``ipc_accel``; about upright the force's part is b u, b = -1 / (M l)).
Per IMU sample it takes the measured change of the pitch rate since the previous sample and the
model's parts over the same time w (the ticks since, each with its commanded torque):

    y = theta_dot(now) - theta_dot(previous sample) - sum(T f(theta, theta_dot, 0)),
    x = sum(T [f(theta, theta_dot, u) - f(theta, theta_dot, 0)]),

with theta = theta~ - d_hat, T a tick and u the force of the torques commanded over it. On the
ground y = k x + c w with k near 1: the residual of model (1), y - x, is what the model leaves
out (the body's own inertia, a push, a slope). ``ResponseCheck`` fits k and c by least squares
over a sliding window of ``window`` seconds: c w takes the slowly changing part of the
residual (an offset estimate d_hat still wrong, a steady push, a wheel held by a kerb: in
proportion to the time each sample covers, which is not the same for all where the IMU and the
loop are not in step), k how the pitch answers the *changes* of the torque. With the IMU's pitch
sign wrong (an IMU turned 180 deg about z and ``imu_mounting_rpy`` not saying so) theta~,
theta_dot and so y change sign while x, made from the commanded torque, does not: k = -1, the
residual is twice the torque's part and of the other sign. Both wheel directions wrong
(``can.left_direction``, ``can.right_direction``) turn the torque instead: k = -1 again. The
controller's torque then drives the fall it should stop.

k below ``gain`` for ``hold`` seconds (the samples' times w summed) is the fault. A window whose
torque term varies by less than ``min_effect`` (the root of the sum of squares of x about what
w explains, rad/s: too little change of torque tells nothing about k) neither adds to nor takes
from that time; a window that says k >= ``gain`` takes its time off again (one such window
amid a sign error, a lump of IMU samples, does not clear it). A push is a force model (1) does
not have: it makes k negative while its start or end lies inside the window, for less than a
window; a sign error lasts. MuJoCo (validation/lockstep.py, docs/faults.md): in main_job's
experiments, driven and fixed legs, the body mass +-30 % and d +-3 deg, the wrong-sign time
reached 32 ms at most (22 ms under test_lifted's 100 N pushes) against ``hold`` 50 ms; with the
pitch sign wrong k stays near -0.4 to -0.9, and armed at 2 deg the robot gets zero torque 72 to
118 ms after the arm, the true pitch at 6 deg at most.

The caller has it judge only where model (1) holds: near upright (no tail on the ground), not
in free fall (a robot off the ground turns under the wheels' reaction alone); the window keeps
its samples through a moment where it does not (the fit of a whole window is what tells).
"""
from collections import deque
import math
from math import isfinite
from typing import Deque, Optional, Tuple

from .model import theta_ddot_free_and_driven
from .params import RobotParams

#: |theta~ - d_hat| [rad] up to which the caller judges: the tail stays off the ground, and a
#: start-up from the tail has left it (MuJoCo's fixed-legs start-up throws the robot off its
#: wheels near 18 deg).
MAX_PITCH = math.radians(15.0)
#: The window's sums are summed afresh after this many samples (rounding kept at a few ulp).
REFRESH = 256


class ResponseCheck:
    """
    The response check (see the module docstring).

    params: m, M, g of model (1) (``RobotParams``); window [s]; min_effect [rad/s]; gain [-];
    hold [s]. ``update`` once per tick while the wheels are commanded, ``reset`` when they
    are not.
    """

    def __init__(self, params: RobotParams, window: float, min_effect: float, gain: float,
                 hold: float):
        self.params = params
        self.window = window
        self.min_effect = min_effect
        self.gain = gain
        self.hold = hold
        self._samples: Deque[Tuple[float, float, float, float]] = deque()   # (t, x, y, w)
        # The fit's sums over the window (sxx, sxy, sxw, swy, sww), kept as samples come and
        # go instead of summed afresh per tick; summed afresh every REFRESH samples so that
        # rounding cannot pile up.
        self._sums = [0.0] * 5
        self._added = 0
        self._theta_dot: Optional[float] = None
        # The model's terms since the newest IMU sample [rad/s], and that sample's mark.
        self._x = self._free = self._span = 0.0
        self._sample: Optional[float] = None
        #: How long the fits have said the wrong sign [s] (the ticks that judged it).
        self.wrong_time = 0.0
        #: The newest fit: k [-] (NaN: the torque varied too little), its excitation [rad/s].
        self.k = math.nan
        self.excitation = 0.0
        #: The lowest k of the present wrong-sign stretch (for the reason).
        self._k_min = math.nan

    def reset(self) -> None:
        """Forget everything (the wheels are not commanded)."""
        self._samples.clear()
        self._sums = [0.0] * 5
        self._theta_dot = None
        self._x = self._free = self._span = 0.0
        self._sample = None
        self.wrong_time = 0.0
        self.k = math.nan
        self.excitation = 0.0

    def update(self, now: float, theta: float, theta_dot: float, u: float, l: float,
               dt: float, judge: bool = True, sample: Optional[float] = None) -> Optional[str]:
        """
        Take one tick; return the reason when the pitch answers with the wrong sign, else None.

        theta: theta~ - d_hat [rad]; theta_dot [rad/s] now; u: the force of the torques
        applied over the last ``dt`` [s] [N]; l [m]; judge: False where model (1) does not
        hold now (the tail on the ground, free fall): the tick goes into the window, but no
        decision is made (the wrong-sign time neither grows nor clears); sample: what tells the
        IMU samples apart (the newest one's receipt time): a tick without a new one adds its
        torque to the next's (the IMU and the loop are not in step on a robot), None: every
        tick has one. A non-finite input restarts the window.
        """
        if not (isfinite(theta) and isfinite(theta_dot) and isfinite(u) and isfinite(l)
                and isfinite(dt)) or dt <= 0.0 or l <= 0.0:
            self.reset()
            return None
        p = self.params
        free, driven = theta_ddot_free_and_driven(theta, theta_dot, u, l, p.body_mass,
                                                  p.wheel_mass, p.gravity)
        # The terms since the newest sample, in locals: stored only where no new one came.
        x = self._x + dt * (driven - free)
        free_sum = self._free + dt * free
        if sample is not None and sample == self._sample:
            self._x, self._free = x, free_sum
            self._span += dt
            return None   # no new measurement: the model's terms wait for it
        self._sample = sample
        previous, self._theta_dot = self._theta_dot, theta_dot
        y = theta_dot - (theta_dot if previous is None else previous) - free_sum
        w = self._span + dt   # the time since the previous sample [s]
        self._x = self._free = self._span = 0.0
        if previous is None:
            return None
        samples, sums = self._samples, self._sums
        samples.append((now, x, y, w))
        # The sums in locals, in the same order of operations as one by one in the list.
        sxx, sxy, sxw, swy, sww = sums
        sxx += x * x
        sxy += x * y
        sxw += x * w
        swy += w * y
        sww += w * w
        span = self.window - 1e-9
        while now - samples[0][0] >= span:
            _, xo, yo, wo = samples.popleft()
            sxx -= xo * xo
            sxy -= xo * yo
            sxw -= xo * wo
            swy -= wo * yo
            sww -= wo * wo
        sums[0], sums[1], sums[2], sums[3], sums[4] = sxx, sxy, sxw, swy, sww
        self._added += 1
        if self._added >= REFRESH:
            self._added = 0
            self._resum()   # for the next ticks: this one judges on the running sums
        if not judge:
            return None
        if now - samples[0][0] < 0.5 * self.window - 1.5 * dt:
            return None   # too few ticks yet (after arming): half a window at least
        # y = k x + c w by least squares: c w is the residual's slow part over each
        # sample's time w (constant c: a plain intercept where the samples come evenly).
        spread = sxx - sxw * sxw / sww   # x's part that w does not explain
        # sqrt(max(spread, 0.0)) without the call: max keeps spread unless 0.0 > spread
        self.excitation = excitation = 0.0 if spread < 0.0 else math.sqrt(spread)
        if excitation < self.min_effect:
            self.k = math.nan
            return None   # too little change of torque: the time neither grows nor clears
        self.k = k = (sxy - sxw * swy / sww) / spread
        if k >= self.gain:
            wrong = self.wrong_time - w
            self.wrong_time = wrong if wrong > 0.0 else 0.0   # max(0.0, wrong), NaN: 0.0
            return None
        if self.wrong_time == 0.0:
            self._k_min = k
        self.wrong_time += w   # the time since the previous sample: ticks without one count
        if k < self._k_min:   # min(k_min, k)
            self._k_min = k
        if self.wrong_time < self.hold - 1e-9:
            return None
        return ('the pitch answers the wheel torque with the wrong sign: %.2f times what model '
                '(1) predicts (down to %.2f) for %.0f ms; check imu_mounting_rpy (the IMU '
                'turned?) and can.left_direction / can.right_direction'
                % (k, self._k_min, 1e3 * self.wrong_time))

    def _resum(self) -> None:
        """Sum the fit's terms over the window afresh."""
        sxx = sxy = sxw = swy = sww = 0.0
        for _, xi, yi, wi in self._samples:
            sxx += xi * xi
            sxy += xi * yi
            sxw += xi * wi
            swy += wi * yi
            sww += wi * wi
        self._sums = [sxx, sxy, sxw, swy, sww]
