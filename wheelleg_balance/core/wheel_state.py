r"""
Wheel angle and speed from the wheel motors' MIT replies (host side; pure, no CAN here).

On the robot the wheel encoders sit inside the foot motors: each MIT reply (one per command the
host sends, core/protocols/mit.py) is the only wheel reading. ``WheelState`` turns the replies
of one motor into the wheel's angle and speed in the wheel's forward-positive convention
(relative to the leg, as core/estimation.py expects), and keeps the reply's time so the caller
can check its age.

Resolution of the reply (AK80-9 class ranges: +-12.5 rad in 16 bits, +-50 rad/s in 12 bits):

- position: 25 / 65535 = 0.381 mrad per code (38 um of wheel travel at r_w = 0.1 m);
- speed: 100 / 4095 = 0.0244 rad/s per code, i.e. 2.44 mm/s of x_dot at r_w = 0.1 m. The
  firmware truncates (float_to_uint), so a reading lies up to one code *below* the true value:
  a mean bias of -half a code (-1.22 mm/s of x_dot; standing still reads -0.0122 rad/s), which
  integrated is 12 cm of odometry drift in 100 s. Both fields are therefore read at the centre
  of their code's interval (``centre_codes``), which removes the bias;
- the speed estimate blends the reported speed with the position: a complementary filter
  (position observer) with time constant tau,

      x_pred = x_hat + dt (v_rep + v_rep_prev) / 2,   e = p - x_pred,
      x_hat = x_pred + (dt / tau) e,
      speed  = v_rep + e / tau,

  has unit gain from the true speed (both inputs measure it), passes the reported speed's
  quantization error through a high-pass (its slow part, the offset between two codes, is
  replaced by what the position says) and the position's quantization error through s / (1 +
  s tau) (at most +-half a position code / tau: +-1.9 mrad/s for tau = 0.1 s). Measured with
  quantized replies of the emulator (test/test_wheel_state.py, 500 Hz): at steady speeds the
  error has a mean under 0.1 mrad/s and an rms of 1.1 mrad/s (0.11 mm/s of x_dot), where the
  decoded speed alone is off by up to 23.8 mrad/s (one code, always low) and the centred one
  by up to 11.6 mrad/s (a constant offset at a constant speed). While the speed sweeps through
  the codes (4 rad/s at 0.5 Hz) the instantaneous error is like white noise of 7 mrad/s rms,
  as the reading's own, and its 50 ms average 2 mrad/s (12.5 mrad/s for the decoded speed).

The reply's position spans only +-12.5 rad (1.25 m of wheel travel each way). Beyond it the
firmware wraps (bgkatz/motorcontrol and CubeMars AK, see core/protocols/mit.py
float_to_uint_wrapping), so the angle is unwrapped: between two replies the wheel moves by the
code difference plus the multiple of 65536 codes (25.0004 rad) closest to what the speed
predicts, which is exact as long as the speed estimate times the reply interval is off by less
than 12.5 rad (any speed the motor reaches at 2 ms replies; a 0.1 s gap at 50 rad/s is still
fine). Firmware that *saturates* at +-p_max (``wrap=False``) loses the position beyond the
range: there the angle is dead-reckoned from the speed estimate (its error grows with time,
``saturated`` says so) until the reading is back inside the range.
"""
import math
from typing import NamedTuple, Optional

from .protocols.mit import MitProtocol


class WheelReading(NamedTuple):
    """
    The estimate after the latest reply.

    angle [rad] (unwrapped, forward positive, relative to the leg; its zero is the first
    reply's angle); speed [rad/s] (blended); reported_speed [rad/s] (the reply's, centred);
    age [s] of the latest reply at the time asked (inf before the first); saturated: the angle
    is dead-reckoned because a saturating firmware's reading sits at its range limit.
    """

    angle: float
    speed: float
    reported_speed: float
    age: float
    saturated: bool


class WheelState:
    """
    One wheel motor's replies -> wheel angle and speed (see the module docstring).

    direction: +1 when a positive motor position turns the wheel forward, else -1 (the node's
    ``can.left_direction`` / ``can.right_direction``); protocol: the motor model's MIT ranges;
    time_constant: tau of the speed blend [s]; max_gap: a reply gap longer than this [s]
    restarts the speed blend from the reported speed; wrap: the firmware wraps the position
    (True: bgkatz, CubeMars) or saturates it; centre_codes: read each field at the centre of
    its code (firmware that truncates, as both do).
    """

    def __init__(self, direction: int = 1, protocol: Optional[MitProtocol] = None,
                 time_constant: float = 0.1, max_gap: float = 0.1, wrap: bool = True,
                 centre_codes: bool = True):
        if direction not in (1, -1):
            raise ValueError('direction must be 1 or -1')
        if not (time_constant > 0.0 and max_gap > 0.0):
            raise ValueError('time_constant and max_gap must be > 0')
        mit = protocol if protocol is not None else MitProtocol()
        self.direction = direction
        self.time_constant = float(time_constant)
        self.max_gap = float(max_gap)
        self.wrap = bool(wrap)
        self._p_min = mit.p_min
        self._p_step = (mit.p_max - mit.p_min) / 65535.0
        self._v_half = 0.5 * (mit.v_max - mit.v_min) / 4095.0 if centre_codes else 0.0
        self._p_half = 0.5 * self._p_step if centre_codes else 0.0
        self.reset()

    def reset(self) -> None:
        """Forget everything (e.g. after a motor reboot): the next reply starts afresh."""
        self._code: Optional[int] = None    # last position code
        self._turns = 0                     # whole wraps of 65536 codes
        self._pos = 0.0                     # unwrapped motor position [rad]
        self._x_hat = 0.0                   # the blend's position [rad]
        self._speed = 0.0                   # motor speed estimate [rad/s]
        self._v_rep = 0.0
        self._origin = 0.0
        self._stamp = -math.inf
        self.saturated = False
        self.replies = 0
        self.rejected = 0

    def update(self, position: float, velocity: float, stamp: float) -> bool:
        """
        Take one reply: position [rad] and velocity [rad/s] as decoded, received at stamp [s].

        Returns False (and changes nothing) for a non-finite value or a stamp older than the
        last one; a reply with the same stamp replaces the position only.
        """
        if not (math.isfinite(position) and math.isfinite(velocity) and math.isfinite(stamp)) \
                or stamp < self._stamp:
            self.rejected += 1
            return False
        code = int(round((position - self._p_min) / self._p_step))
        v_rep = velocity + self._v_half
        dt = stamp - self._stamp
        if self._code is None:
            self._turns = 0
            self._pos = self._position(code)
            self._origin = self._pos
            self._x_hat, self._speed = self._pos, v_rep
        else:
            self._pos = self._track(code, v_rep, dt)
            if dt > self.max_gap:
                self._x_hat, self._speed = self._pos, v_rep
            elif dt > 0.0:
                alpha = min(1.0, dt / self.time_constant)
                pred = self._x_hat + dt * 0.5 * (self._v_rep + v_rep)   # trapezoid: no lag
                err = self._pos - pred
                self._x_hat = pred + alpha * err
                self._speed = v_rep + alpha * err / dt
        self._code = code
        self._v_rep = v_rep
        self._stamp = stamp
        self.replies += 1
        return True

    def _position(self, code: int) -> float:
        return self._p_min + self._p_half + (code + 65536 * self._turns) * self._p_step

    def _track(self, code: int, v_rep: float, dt: float) -> float:
        """Return the new unwrapped motor position [rad] for a position code."""
        if not self.wrap:
            if code in (0, 65535):      # at the range limit: the reading says nothing more
                self.saturated = True
                return self._pos + max(dt, 0.0) * 0.5 * (self._speed + v_rep)
            self.saturated = False
            return self._position(code)
        # Of the candidates 65536 codes apart, take the one nearest to the speed's prediction.
        expected = max(dt, 0.0) * 0.5 * (self._speed + v_rep) / self._p_step
        delta = code - self._code
        self._turns += int(round((expected - delta) / 65536.0))
        return self._position(code)

    def reading(self, now: float) -> WheelReading:
        """Return the estimate in the wheel's convention, with the reply's age at now [s]."""
        d = self.direction
        if self._code is None:
            return WheelReading(math.nan, math.nan, math.nan, math.inf, False)
        return WheelReading(d * (self._pos - self._origin), d * self._speed, d * self._v_rep,
                            now - self._stamp, self.saturated)

    def age(self, now: float) -> float:
        """Return the age [s] of the latest reply at now [s] (inf before the first)."""
        return now - self._stamp
