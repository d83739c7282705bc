r"""
Wheel angle and speed from the wheel motors' replies, any protocol (host side; no CAN here).

On the robot the wheel encoders sit inside the foot motors: each reply (one per command the
host sends) is the only wheel reading. ``WheelState`` turns the replies of one motor into the
wheel's angle and speed in the wheel's forward-positive convention (relative to the leg, as
core/estimation.py expects), and keeps the reply's time so the caller can check its age.

The protocol says how its reply codes them (``MotorProtocol.reply_codes``): the position's
code of 0 and step, how many codes the field has and whether it wraps after them (MIT: 65536
codes over +-p_max; LK: the single-turn encoder, 2^14..2^16 codes a rotor turn; the C620:
8192 codes a rotor turn) or sticks at its end codes (CyberGear: 65536 codes over +-4 pi),
the speed's step, and whether the firmware truncates. Everything below works in those codes;
the figures are the MIT defaults'. Other protocols' resolution: LK MF9025 (16-bit encoder,
direct drive) 0.096 mrad and 1 deg/s = 17.5 mrad/s (rounded, no centring); C620 with the
M3508 P19 0.040 mrad and 1 rotor rpm = 5.5 mrad/s at the output; CyberGear 0.38 mrad and
0.92 mrad/s.

Resolution of the MIT reply (AK80-9 class ranges: +-12.5 rad in 16 bits, +-50 rad/s in 12
bits):

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

Replies that contradict the reported speed (``mismatch``). Firmware that saturates while the
node assumes it wraps (``can.mit.wrap: true``, the default) freezes the position at the range
end: the blend then trusted the frozen position over the speed, read the wheel as standing
and the robot rolled away (issue 29: 2.4 m/s and rising). Two rules tell it:

- over MISMATCH_WINDOW (50 ms) the position's change and the integral of the reported speed
  (trapezoid) differ by more than MISMATCH_LIMIT (0.05 rad) plus what the replies' receipt-time
  uncertainty explains at the speed (core/motor_health.py RECEIPT_JITTER, 12 ms, as the reboot
  check allows for it; the same allowance covers a speed reading that lags the position by up
  to 6 ms through a speed reversal, a firmware's velocity filter);
- the code sits at a range end (0 or the field's last code) while the reported speed, above
  two speed codes (STUCK_MIN_SPEED_CODES: 0.05 rad/s) and pointing out of the range, has
  integrated to more than that same limit since the code got there (catches a slow roll the
  window cannot: 0.05 rad per 50 ms is 1 rad/s).

From then on the angle is dead-reckoned from the reported speed, starting from the angle of
the reply the contradiction began after (the window's first reply, or the first one at the
range end), so what the frozen replies said is not kept. The position is trusted again once
the code is off the range ends and no rule has fired for MISMATCH_WINDOW: the angle then goes
over to the reading, the whole turns of the code chosen nearest the dead-reckoned angle (its
error, the speed reading's quantization integrated, at most 12 mrad/s, is far below half the
range). The speed blend restarts from the reported speed at both changes, so the jump is no
speed. Neither rule judges across a reply gap longer than ``max_gap`` nor while a speed
reading is within 10 % of its field's end (there the speed field saturates or wraps, not the
position), and with ``wrap=False`` a code at the range end is the known saturation, not a
contradiction. A motor reboot jumps the position in
one reply and trips the window rule too; core/motors.py (``position_jump``) faults on it, and
the node names that fault, not this one (core/balance_loop.py). In MuJoCo against saturating
motors the robot stops within 3 mm of where it does with wrapping ones
(test/test_encoder_saturation.py; it rolled on at 0.4 to 2.3 m/s before).
"""
from collections import deque
import math
from typing import NamedTuple, Optional

from .motor_health import RECEIPT_JITTER
from .protocols.base import MotorProtocol
from .protocols.mit import MitProtocol

#: The contradiction rules (see the module docstring): the window [s], the limit [rad].
MISMATCH_WINDOW = 0.05
MISMATCH_LIMIT = 0.05
#: A code at a range end judged only while the reported speed is above this many speed codes.
STUCK_MIN_SPEED_CODES = 2.0
#: Share of the speed field's end beyond which no rule judges (the speed field, not the
#: position, saturates or wraps there: core/balance_loop.py's reboot check skips it alike).
SPEED_FIELD_SHARE = 0.9
#: One speed code of the default MIT ranges (+-50 rad/s in 12 bits) [rad/s].
MIT_V_CODE = 100.0 / 4095.0
_INF = math.inf


class WheelReading(NamedTuple):
    """
    The estimate after the latest reply.

    angle [rad] (unwrapped, forward positive, relative to the leg; its zero is the first
    reply's angle); speed [rad/s] (blended); reported_speed [rad/s] (the reply's, centred);
    age [s] of the latest reply at the time asked (inf before the first); saturated: the angle
    is dead-reckoned because a saturating firmware's reading sits at its range limit;
    mismatch: the angle is dead-reckoned because the replies contradict the reported speed.
    """

    angle: float
    speed: float
    reported_speed: float
    age: float
    saturated: bool
    mismatch: bool = False


class WheelState:
    """
    One wheel motor's replies -> wheel angle and speed (see the module docstring).

    direction: +1 when a positive motor position turns the wheel forward, else -1 (the node's
    ``can.left_direction`` / ``can.right_direction``); protocol: the wheel motors' codec
    (default MitProtocol()), whose ``reply_codes`` say how the reply codes position and
    speed; time_constant: tau of the speed blend [s]; max_gap: a reply gap longer than this
    [s] restarts the speed blend from the reported speed; wrap: False says the firmware
    saturates a position field that the protocol says wraps (``can.mit.wrap: false``);
    centre_codes: read each field at the centre of its code where the protocol says the
    firmware truncates.
    """

    def __init__(self, direction: int = 1, protocol: Optional[MotorProtocol] = None,
                 time_constant: float = 0.1, max_gap: float = 0.1, wrap: bool = True,
                 centre_codes: bool = True):
        if direction not in (1, -1):
            raise ValueError('direction must be 1 or -1')
        if not (time_constant > 0.0 and max_gap > 0.0):
            raise ValueError('time_constant and max_gap must be > 0')
        protocol = protocol if protocol is not None else MitProtocol()
        codes = protocol.reply_codes()
        self.direction = direction
        self.time_constant = float(time_constant)
        self.max_gap = float(max_gap)
        #: The field wraps (else it saturates at its end codes: the reading says no more).
        self.wrap = bool(wrap) and not codes.saturates
        self._p_min = codes.p_zero
        self._p_step = codes.p_step
        self._n = codes.p_codes                 # codes per wrap
        self._top = codes.p_codes - 1           # the field's last code
        # A field without speed codes: MIT's two 12-bit codes (0.05 rad/s) judge stuck.
        v_code = codes.v_step if codes.v_step > 0.0 else MIT_V_CODE
        self._stuck_speed = STUCK_MIN_SPEED_CODES * v_code
        self._judged_speed = SPEED_FIELD_SHARE * protocol.speed_range
        centre = centre_codes and codes.truncates
        self._v_half = 0.5 * codes.v_step if centre else 0.0
        self._p_half = 0.5 * self._p_step if centre else 0.0
        self._p_zero = self._p_min + self._p_half   # the position of code 0 [rad]
        self._field = (self._p_min, self._p_step, self._top, self._n, 0.5 * self._n)
        self.reset()

    def reset(self) -> None:
        """Forget everything (e.g. after a motor reboot): the next reply starts afresh."""
        self._code: Optional[int] = None    # last position code
        self._turns = 0                     # whole wraps of the field (_n codes each)
        self._pos = 0.0                     # unwrapped motor position [rad]
        self._x_hat = 0.0                   # the blend's position [rad]
        self._speed = 0.0                   # motor speed estimate [rad/s]
        #: The speed in the wheel's convention [rad/s] (reading's), NaN before the first reply.
        self.speed = math.nan
        self._v_rep = 0.0
        self._origin = 0.0
        self._stamp = -math.inf
        self.saturated = False
        self.replies = 0
        self.rejected = 0
        self._v_int = 0.0                   # integral of the reported speed [rad]
        #: (stamp, position the codes say, _v_int, angle used, |v_rep|) of the recent replies.
        self._hist = deque()
        self._end = None                    # that tuple of the first reply at a range end
        self._clean_since: Optional[float] = None   # no rule fired, off the ends, since [s]
        #: The angle is dead-reckoned: the replies contradicted the reported speed.
        self.mismatch = False
        #: How often a contradiction began, and what the newest one was.
        self.mismatches = 0
        self.mismatch_reason = ''

    def update(self, position: float, velocity: float, stamp: float) -> bool:
        """
        Take one reply: position [rad] and velocity [rad/s] as decoded, received at stamp [s].

        Returns False (and changes nothing) for a non-finite value or a stamp older than the
        last one; a reply with the same stamp replaces the position only.
        """
        # Two replies a tick: the tracking of the whole turns and the contradiction rules are
        # inlined here (one Python call each less), in the order of the module docstring.
        # x - x is 0.0 for a finite x, NaN for NaN and +-inf: the sum is 0.0 only when all
        # three are finite (math.isfinite's test, one comparison).
        if (position - position) + (velocity - velocity) + (stamp - stamp) != 0.0 \
                or stamp < self._stamp:
            self.rejected += 1
            return False
        # One attribute for the field's figures (update runs twice a tick).
        p_min, p_step, top, n, half = self._field
        code = round((position - p_min) / p_step)   # an int (float.__round__)
        at_end = code == 0 or code == top
        v_rep = velocity + self._v_half
        v_abs = abs(v_rep)
        last_code = self._code
        if last_code is None:
            measured = self._start(code, v_rep)
        else:
            dt = stamp - self._stamp   # >= 0: older stamps are refused above
            v_prev = self._v_rep
            self._v_int = v_int = self._v_int + dt * 0.5 * (v_prev + v_rep)
            move = dt * 0.5 * (self._speed + v_rep)
            dead = self._pos + move   # from the speed alone
            wrap = self.wrap
            # -- tracking: the new unwrapped motor position [rad] of the code
            if wrap:
                # Of the candidates n codes apart, take the one nearest to the speed's
                # prediction (round(off / n) is 0 for |off| < n / 2 codes).
                off = move / p_step - (code - last_code)
                if not -half < off < half:
                    self._turns += int(round(off / n))
                measured = self._p_zero + (code + n * self._turns) * p_step
            elif at_end:   # at the range limit: the reading says no more
                self.saturated = True
                measured = dead
            else:
                self.saturated = False
                measured = self._p_zero + (code + n * self._turns) * p_step
            hist = self._hist
            gap = dt > self.max_gap
            if gap:   # judge afresh from this reply
                hist.clear()
                self._end = None
            # -- the contradiction rules (sets mismatch; dead from where one began, measured
            # in the whole turns nearest dead when the position is trusted again)
            restart = False
            if not (wrap and at_end) or code != last_code:
                self._end = None   # not at a range end, or at the other one (the code wrapped)
            if v_abs >= self._judged_speed:
                hist.clear()   # the speed field, not the position, is at its end
                self._end = None
            else:
                found, since = '', None
                while len(hist) >= 2 and hist[1][0] <= stamp - MISMATCH_WINDOW:
                    hist.popleft()
                if hist and stamp - hist[0][0] >= MISMATCH_WINDOW:
                    h = hist[0]
                    moved, integral = measured - h[1], v_int - h[2]
                    apart = abs(moved - integral)
                    # (The allowance is MISMATCH_LIMIT or more: the speed term only when over.)
                    if apart > MISMATCH_LIMIT and apart > MISMATCH_LIMIT + RECEIPT_JITTER * (
                            h[4] if h[4] > v_abs else v_abs):
                        found = ('the position moved %.3f rad in %.0f ms, the reported speed '
                                 '%.3f rad' % (moved, 1e3 * (stamp - h[0]), integral))
                        since = h
                end = self._end
                if not found and end is not None:
                    outward = (v_int - end[2]) * (1.0 if code == top else -1.0)
                    if v_abs > self._stuck_speed and outward > MISMATCH_LIMIT \
                            + RECEIPT_JITTER * v_abs:
                        found = ('the position stuck at its range end (%+.2f rad) while the '
                                 'reported speed (%.2f rad/s) moved the wheel %.3f rad on'
                                 % (self._p_min + code * p_step, v_rep, outward))
                        since = end
                if found or (at_end and wrap):
                    self._clean_since = None
                elif self._clean_since is None:
                    self._clean_since = stamp
                if found and not self.mismatch:
                    self.mismatch, restart = True, True
                    self.mismatches += 1
                    self.mismatch_reason = found
                    # Dead-reckon from the reply the contradiction began after: what the
                    # replies said since is not kept.
                    dead = since[3] + (v_int - since[2])
                elif self.mismatch and self._clean_since is not None \
                        and stamp - self._clean_since >= MISMATCH_WINDOW:
                    self.mismatch, restart = False, True
                    if wrap:   # the code's whole turns nearest the dead-reckoned angle
                        self._turns += int(round((dead - measured) / (n * p_step)))
                        measured = self._p_zero + (code + n * self._turns) * p_step
            # -- the speed blend
            self._pos = pos = dead if self.saturated or self.mismatch else measured
            if restart or gap:
                self._x_hat, self._speed = pos, v_rep
            elif dt > 0.0:
                alpha = dt / self.time_constant
                if not alpha < 1.0:   # min(1.0, dt / tau)
                    alpha = 1.0
                pred = self._x_hat + dt * 0.5 * (v_prev + v_rep)   # trapezoid: no lag
                err = pos - pred
                self._x_hat = pred + alpha * err
                self._speed = v_rep + alpha * err / dt
        self._code = code
        self._v_rep = v_rep
        self._stamp = stamp
        self.replies += 1
        self.speed = self.direction * self._speed
        entry = (stamp, measured, self._v_int, self._pos, v_abs)
        self._hist.append(entry)
        if at_end and self._end is None and self.wrap:
            self._end = entry
        return True

    def _start(self, code: int, v_rep: float) -> float:
        """Take the first reply (after a reset): its position [rad] is the origin."""
        self._turns = 0
        self._pos = self._position(code)
        self._origin = self._pos
        self._x_hat, self._speed = self._pos, v_rep
        self._hist.clear()
        self._end = None
        return self._pos

    def _position(self, code: int) -> float:
        return self._p_zero + (code + self._n * self._turns) * self._p_step

    def reading(self, now: float) -> WheelReading:
        """Return the estimate in the wheel's convention, with the reply's age at now [s]."""
        d = self.direction
        if self._code is None:
            return WheelReading(math.nan, math.nan, math.nan, math.inf, False)
        return WheelReading(d * (self._pos - self._origin), d * self._speed, d * self._v_rep,
                            now - self._stamp, self.saturated, self.mismatch)

    def age(self, now: float) -> float:
        """Return the age [s] of the latest reply at now [s] (inf before the first)."""
        return now - self._stamp
