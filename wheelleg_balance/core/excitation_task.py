"""
The excitation in the tick: core/excitation.py's phases carried out with the tick's parts.

``ExcitationTask`` starts a phase asked for (``TickInputs.excite``) or refuses it, with the
reply the operator's request gets (the stand's once its probe found the wheels free), and per
tick plays it: the wheel torques in EXCITING (stand, tail) through core/actuation.py, or, for
balance, the end checks while core/balance_loop.py hands its references to the controller. A
phase that ends (its end, an abort limit, another mode: ~/stop, ~/arm false, a FAULT) leaves a
line: stand and tail end disarmed (zero torque, exit motor mode), balance aborted in the
sit-down. The stand's planned free wheels are announced to the lift and response checks
(core/lift.py ``FreeWheelNotice``) for its length and withdrawn at its end.
"""
from typing import Callable

from .config import BalanceConfig
from .excitation import BALANCE, Excitation, STAND
from .safety import BALANCING, EXCITING, Mode, SensorSnapshot


class ExcitationTask:
    """The excitation's part of the tick (see the module docstring)."""

    def __init__(self, cfg: BalanceConfig, arming, actuation, balancing, legs,
                 act: Callable):
        """Build it over the tick's parts; act: the loop's ``_act`` (carries out an Action)."""
        self.excitation = Excitation(cfg)
        self.arming, self.actuation, self.balancing, self.legs = arming, actuation, balancing, \
            legs
        self.act = act

    def start(self, now: float, phase: str, s: SensorSnapshot, guarded: bool, r) -> None:
        """Start ``phase`` or refuse it, with the reply (r: the tick's TickResult)."""
        exc, arming = self.excitation, self.arming
        why = exc.refusal(phase, arming.safety._mode.name, s,
                          self.balancing.core.odometry.x_dot, self.balancing.rising)
        if not why and phase != BALANCE:
            why = arming.start_exciting(now, s, guarded)
            if not why:
                self.actuation.enable_wheels(r)
        if why:
            arming.answer(False, '%s refused: %s' % (phase, why))
            return
        line = exc.start(phase, now, s, s.l)
        r.events.append(('info', 'excitation ' + line))
        if phase == STAND:   # answered once the probe found the wheels free
            arming.motion.free_wheels.announce(now + exc.duration, 'the stand phase')
        else:
            arming.answer(True, line)

    def publish(self, state) -> None:
        """Fill the LoopState of an EXCITING tick: the wheel torques [N m], their force u [N]."""
        tau_l, tau_r = state.tau_left, state.tau_right = self.excitation.tau
        state.u = (tau_l + tau_r) / self.balancing.p.wheel_radius

    def step(self, mode: Mode, now: float, s: SensorSnapshot, r, tick: int) -> Mode:
        """Play the running phase's tick, or end it; return the mode after it."""
        exc, arming = self.excitation, self.arming
        phase, probing, done = exc.phase, exc.probing, False
        if phase == BALANCE:
            why, done = ('ended: mode %s' % mode.name, False) if mode is not BALANCING else \
                exc.balance_abort(now, s.theta - self.balancing.d_hat,
                                  self.balancing.core.odometry.x_dot)
        elif mode is not EXCITING:
            why = 'ended: mode %s' % mode.name
        else:
            tau_l, tau_r, why, done = exc.torques(now, s)
            if not why:
                if probing and not exc.probing:
                    arming.answer(True, exc.line)
                exc.tau = (tau_l, tau_r)
                self.actuation.excite(r, tau_l, tau_r, tick)
                return mode
        if not why:
            return mode
        exc.end()
        arming.motion.free_wheels.withdraw()
        if probing:
            arming.answer(False, why if why.startswith('stand refused') else
                          'stand refused: %s' % why)
        r.events.append(('info' if done else 'warn', 'excitation %s%s' % (
            '' if why.startswith(phase) else phase + ': ', why)))
        if mode is EXCITING:
            self.act(arming.disarm(), now, s)
        elif mode is BALANCING and not done:
            if arming.sit_down():
                self.legs.start_sit_down()
            else:
                self.act(arming.disarm(), now, s)
        return arming.safety._mode
