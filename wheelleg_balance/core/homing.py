"""
Homing the hips at their hard stops (pure; the legs' other pieces: core/legs.py).

A hip motor knows its output angle after power-up only modulo one rotor turn through its gear
(40 deg for 9:1; sim/motor_emulator.py reboot). ``HipHoming`` drives each hip at a low speed
towards its hard stop with a soft position ramp (low kp), detects the stop (speed about zero
while the torque towards the stop has grown past a threshold) and records the offset that makes
the reading the stop's known angle (``LegController.set_offsets``).
"""
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

from .legs import _finite, HipMotors, Reply
from .protocols.mit import MitCommand


@dataclass(frozen=True)
class HomingConfig:
    """
    Homing at the hard stops.

    stop_angles: the joint angle [rad] of each hip's stop (FiveBarLeg convention; default: the
    lower joint limit -0.2 rad, legs folded, where the body's weight helps); toward: -1 to
    reach the stops by decreasing q, +1 by increasing it; speed: joint speed of the ramp
    [rad/s]; kp [N m/rad], kd [N m s/rad]: the soft ramp's gains; torque_threshold: torque
    towards the stop [N m] and speed_threshold [rad/s] below which, for dwell [s], a hip is at
    its stop; max_torque: the ramp never leads the hip by more than this torque's worth [N m];
    timeout [s]: homing fails if not done by then.
    """

    stop_angles: Tuple[float, float, float, float] = (-0.2, -0.2, -0.2, -0.2)
    toward: int = -1
    speed: float = 0.3
    kp: float = 30.0
    kd: float = 1.0
    torque_threshold: float = 3.0
    speed_threshold: float = 0.05
    dwell: float = 0.1
    max_torque: float = 6.0
    timeout: float = 20.0

    def __post_init__(self):
        """Check the ranges."""
        if self.toward not in (1, -1) or len(self.stop_angles) != 4:
            raise ValueError('toward must be 1 or -1, stop_angles four angles')
        if not (self.speed > 0.0 and self.kp > 0.0 and self.kd >= 0.0
                and 0.0 < self.torque_threshold < self.max_torque
                and self.speed_threshold > 0.0 and self.dwell >= 0.0 and self.timeout > 0.0):
            raise ValueError('homing: speed, kp > 0; 0 < torque_threshold < max_torque; ...')


class HipHoming:
    """
    Drives the four hips to their hard stops and measures their offsets (see HomingConfig).

    Call step(replies, now) every tick with the hips' replies (position, velocity, torque in
    the motor frame; None where none came) and send the commands it returns. ``status`` is
    'running', 'done' (then ``offsets`` holds the four offsets for LegController.set_offsets)
    or 'failed' (``reason`` says why). The motors must be in motor mode.
    """

    def __init__(self, motors: HipMotors, config: HomingConfig = HomingConfig()):
        self.motors = motors
        self.config = config
        self.status = 'running'
        self.reason = ''
        self.offsets: Optional[Tuple[float, ...]] = None
        self._start: Optional[float] = None
        self._ref: List[Optional[float]] = [None] * 4     # ramp position, motor frame [rad]
        self._stopped_since: List[Optional[float]] = [None] * 4
        self._at_stop: List[Optional[float]] = [None] * 4  # motor position at the stop [rad]
        self._last: Optional[float] = None

    def step(self, replies: Sequence[Reply], now: float) -> List[MitCommand]:
        """Advance the homing to time now [s]; return the four hips' commands."""
        c, m = self.config, self.motors
        if self._start is None:
            self._start = now
        dt = 0.0 if self._last is None else max(0.0, now - self._last)
        self._last = now
        if self.status == 'running' and now - self._start > c.timeout:
            self.status, self.reason = 'failed', 'timeout after %.1f s' % c.timeout
        out = []
        for i in range(4):
            d = m.directions[i]
            r = replies[i] if i < len(replies) else None
            ok = r is not None and all(_finite(v) for v in r)
            if self.status != 'running' or self._at_stop[i] is not None:
                hold = self._at_stop[i] if self._at_stop[i] is not None else self._ref[i]
                out.append(self._command(i, hold, 0.0))
                continue
            if not ok:
                out.append(self._command(i, self._ref[i], 0.0))
                continue
            p, v, tau = r
            if self._ref[i] is None:
                self._ref[i] = p
            # Motor-frame direction towards the stop; the ramp leads the hip by at most
            # max_torque / kp (a hip that runs ahead, pulled by the weight, is held back).
            s = d * c.toward
            ref = self._ref[i] + s * c.speed * dt
            if s * (ref - p) > c.max_torque / c.kp:
                ref = p + s * c.max_torque / c.kp
            self._ref[i] = ref
            pushing = s * tau >= c.torque_threshold
            if pushing and abs(v) < c.speed_threshold:
                since = self._stopped_since[i]
                if since is None:
                    self._stopped_since[i] = now
                elif now - since >= c.dwell:
                    self._at_stop[i] = p
            else:
                self._stopped_since[i] = None
            out.append(self._command(i, self._ref[i], s * c.speed))
        if self.status == 'running' and all(a is not None for a in self._at_stop):
            self.offsets = tuple(c.stop_angles[i] - m.directions[i] * self._at_stop[i]
                                 for i in range(4))
            self.status = 'done'
        return out

    def _command(self, i: int, p: Optional[float], v: float) -> MitCommand:
        c = self.config
        if p is None:   # no reply yet: damping only
            return MitCommand(self.motors.motor_ids[i], 0.0, 0.0, 0.0, c.kd, 0.0)
        return MitCommand(self.motors.motor_ids[i], p, v, c.kp, c.kd, 0.0)
