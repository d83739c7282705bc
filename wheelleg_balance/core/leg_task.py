"""
The leg task, a part of the tick: homing, raising, the height and roll, folding, the sit-down.

What the legs do in each mode (no rclpy, no CAN):

- HOMING: the hips homed where their angles are not known (core/legs.py ``HipHoming``), then
  the legs raised on the tail to height_min, the start of the paper's start-up (Sec. V-B 1);
  once there for RAISED_TIME the task reports ``RAISED`` and the tick starts balancing;
- BALANCING: the shaped height (cmd_height; height_min while rising from the tail) with the
  roll levelling, as impedance commands with the weight's share through the Jacobian; each
  leg every ``legs.command_divider``-th tick, the legs taking turns;
- SITTING: the sit-down (core/sit_down.py): the legs go down, the body leans onto its tail,
  the legs hold their length while the tail brakes the body, then fold; ``sat_down`` tells
  the tick to end it;
- FAULT: damping (the body is lowered, not dropped), or, lifted, holding their length.

The task reports what the tick must act on (``RAISED``, a fault of the legs, a line to log) in
its events instead of calling back into the tick. ``NoLegs`` is the task where the legs are not
driven: no frames, l from joint_states_in or the ``height`` parameter; its sit-down only leans
and brakes.
"""
import math
from typing import List, Optional, Tuple

from .config import BalanceConfig
from .homing import HipHoming, HomingConfig
from .legs import (HeightShaper, HipMotors, LEFT_LEG, LegController, LegGains, LegState,
                   RIGHT_LEG, RollLeveller, split_heights)
from .motors import MotorSet
from .protocols.base import Frame
from .safety import BALANCING, FAULT, HOMING, Mode, SensorSnapshot, SITTING
from .sensing import five_bar
from .sit_down import BRAKE, DONE, FOLD, LOWER, SitDown, SitDownConfig

#: The legs count as raised to height_min on the tail within this [m] for this long [s].
RAISED_TOLERANCE = 0.005
RAISED_TIME = 0.3
#: How far above the folded height the sit-down folds the legs before the motors rest [m].
FOLD_MARGIN = 0.005
#: The share of the body's weight the legs carry while the robot rests on its tail, and the
#: integral gain [1/s] and limit [m] that correct the height for the rest.
TAIL_LOAD = 0.5
RAISE_KI = 3.0
RAISE_LIMIT = 0.04
#: Events of the task (the tick acts on them): the legs are raised on the tail (start
#: balancing); a fault of the legs (its text follows).
RAISED = 'raised'
LEG_FAULT = 'legs'


class NoLegs:
    """
    The leg task where the legs are not driven (the null object; see the module docstring).

    It owns the sit-down, which without driven legs leans onto the tail and brakes.
    """

    driven = False
    #: The driven legs' hardware (``Legs``); None here.
    legs = None

    def __init__(self, cfg: BalanceConfig):
        self.p = cfg.model
        self.sit_down_config = SitDownConfig(tail_pitch=cfg.safety.tail_pitch)
        self.sit: Optional[SitDown] = None
        self.last_sit_down: Optional[SitDown] = None   # the newest finished one (its figures)
        self._sit_d_hat: Optional[float] = None
        #: The commanded height l* [m]: cmd_height, clamped; a new ``height`` parameter.
        self.commanded = cfg.control.height
        self.height = cfg.control.height
        self.configure(cfg)

    def configure(self, cfg: BalanceConfig) -> None:
        """Take the live settings of ``cfg`` (at build and on every parameter change)."""
        if cfg.control.height != self.height:
            self.commanded = cfg.control.height
        self.height = cfg.control.height

    # The legs' part of the tick: nothing to read, command or report.
    def read(self) -> Optional[float]:
        """Return the driven legs' height for the snapshot [m]; None: not driven."""
        return None

    def ready(self) -> bool:
        """Return True when the legs are ready to balance (always, when not driven)."""
        return True

    @property
    def l_ref(self) -> float:
        """Return the height reference [m]."""
        return self.height

    @property
    def target(self) -> float:
        """Return the height the legs go to [m] (here the ``height`` parameter)."""
        return self.height

    def command_height(self, height: float) -> None:
        """Take a cmd_height [m] (finite), clamped to [height_min, height_max]."""
        self.commanded = min(max(float(height), self.p.height_min), self.p.height_max)

    def load(self) -> float:
        """Return the legs' mean load [N] (NaN: not known)."""
        return math.nan

    def homing_plan(self) -> str:
        """Return what an arm that homes and raises the legs will do (nothing here)."""
        return ''

    def start_homing(self) -> None:
        """Prepare homing and raising (nothing to home here)."""

    def start_balancing(self) -> None:
        """Balancing begins."""

    def lifted(self) -> None:
        """Keep what the legs need now that the robot is in a hand: its wheels are cut."""

    def step(self, mode: Mode, now: float, s: SensorSnapshot, dt: float, theta: float,
             rising: bool, tick: int, lifted: bool, gyro_x: float) -> Tuple[List[Frame], list]:
        """Return this tick's hip frames and events (none)."""
        return [], []

    def enable_frames(self) -> List[Frame]:
        """Return the hips' enter-motor-mode frames (none)."""
        return []

    def stop_frames(self) -> List[Frame]:
        """Return the hips' zero torque and exit frames (none)."""
        return []

    def poll_frames(self) -> List[Frame]:
        """Return the exit frames that keep resting hips answering (none)."""
        return []

    def joint_values(self) -> Tuple[list, list, list]:
        """Return the hips' and knees' (positions, velocities, efforts) (none)."""
        return [], [], []

    def status(self) -> Optional[dict]:
        """Return the legs' part of /diagnostics (None: not driven)."""
        return None

    # The sit-down, with or without driven legs.
    def start_sit_down(self) -> None:
        """Start the sit-down sequence (a disarm while balancing, or heat)."""
        self.sit = SitDown(self.p, self.sit_down_config, lower=self.driven)
        self._sit_d_hat = None
        self._on_sit_down()

    def _on_sit_down(self) -> None:
        pass

    def sit_wheels(self, now: float, s: SensorSnapshot, x_dot: float, d_hat: float,
                   limit: float) -> Optional[Tuple[float, float, float]]:
        """
        Return the sit-down's (tau_left, tau_right, u) [N m, N m, N] (None: still lowering).

        The lean onto the tail and the brake (core/sit_down.py), within ``limit`` [N m] (the
        wheels' torque limit, derated when hot). d_hat: the observer's offset estimate [rad].
        """
        sit = self.sit
        sit.lowered(now, self.l_ref, s.l)
        if sit.phase == LOWER:
            return None
        # The offset estimate of the moment the lean starts: while the body leans far from
        # upright the observer holds d_hat, and it is fed the controller's force.
        if self._sit_d_hat is None:
            self._sit_d_hat = d_hat
        u = sit.force(now, s.theta - self._sit_d_hat, s.theta_dot, x_dot, s.l)
        r_w = self.p.wheel_radius
        tau = min(max(0.5 * r_w * u, -limit), limit)
        return tau, tau, (tau + tau) / r_w

    @property
    def sat_down(self) -> bool:
        """Return True once the sit-down has come to its end (the tick then disarms)."""
        return self.sit is not None and self.sit.phase == DONE

    def finish_sit_down(self) -> str:
        """End the sit-down; return the line to log."""
        sit = self.last_sit_down = self.sit
        self.sit = None
        return 'sat down: tail contact at %.2f rad/s, peak force %.0f N' % (
            sit.contact_rate or math.nan, sit.max_force)

    def end(self) -> None:
        """Forget a sit-down under way (a disarm, a stop)."""
        self.sit = None


class Legs:
    """The driven legs' hardware and controllers: hips, state, height shaping, levelling."""

    def __init__(self, cfg: BalanceConfig, motors: MotorSet):
        lc, p = cfg.legs, cfg.model
        self.motors = motors
        self.protocol = motors.protocol
        self.controller = LegController(
            five_bar(cfg), HipMotors(tuple(lc.motor_ids), tuple(lc.directions),
                                     tuple(lc.offsets)),
            LegGains(lc.kp, lc.kd, lc.damping_kd, lc.damping_gravity),
            weight_share=0.5 * p.body_mass * p.gravity)
        if lc.homing == 'set_zero':
            self.controller.set_offsets(lc.offsets)
        self.homing_config = HomingConfig(
            stop_angles=tuple(lc.stop_angles), speed=lc.homing_speed,
            torque_threshold=lc.homing_torque,
            max_torque=max(2.0 * lc.homing_torque, lc.homing_torque + 1.0))
        self.homing: Optional[HipHoming] = None
        self.shaper = HeightShaper(p.height_min, p.height_max, lc.max_height_rate,
                                   lc.max_height_accel)
        self.leveller = RollLeveller(lc.roll_kp, lc.roll_ki, lc.roll_kd, lc.max_roll_dl)
        self.levelling = lc.roll_kp > 0.0 or lc.roll_ki > 0.0
        self.divider = lc.command_divider
        self._phases = ((LEFT_LEG, 0), (RIGHT_LEG, self.divider // 2))
        #: due(tick) for each tick % divider.
        self._due = tuple(tuple(leg for leg, at in self._phases if at == phase)
                          for phase in range(self.divider))
        #: The hips' replies as read() last passed them (their torques may be older), with the
        #: feedback they came from.
        self._replies: List[Optional[tuple]] = [None] * len(motors.motors)
        self._feedback: list = [None] * len(motors.motors)
        self.state: Optional[LegState] = None
        leg = self.controller.leg
        #: The height with the hips at their lower stops (the rest after power-up) [m].
        self.folded_height = leg.height(leg.q_min, leg.q_min)

    def configure(self, cfg: BalanceConfig) -> None:
        """Take the live settings of ``cfg``."""
        lc = cfg.legs
        self.controller.gains = LegGains(lc.kp, lc.kd, lc.damping_kd, lc.damping_gravity)
        self.shaper.max_rate, self.shaper.max_accel = lc.max_height_rate, lc.max_height_accel
        lv = self.leveller
        lv.kp, lv.ki, lv.kd, lv.max_dl = lc.roll_kp, lc.roll_ki, lc.roll_kd, lc.max_roll_dl
        self.levelling = lc.roll_kp > 0.0 or lc.roll_ki > 0.0

    def replies(self):
        """Return the hips' (position, velocity, torque) in the motor frame (None: no reply)."""
        return [None if m.feedback is None else m.feedback[1:4] for m in self.motors.motors]

    def read(self) -> LegState:
        """Update and return the legs' state from the newest replies."""
        # replies(), with the reply of a motor kept as it was while its feedback is the same
        # object, or a new one of the same position and velocity (the state reads those two
        # alone: the controller keeps a leg's state, and the whole one, while its replies are
        # the same objects).
        replies, seen = self._replies, self._feedback
        for i, m in enumerate(self.motors.motors):
            fb = m.feedback
            if fb is not seen[i]:
                seen[i] = fb
                r = replies[i]
                if fb is None or r is None or r[0] != fb[1] or r[1] != fb[2]:
                    replies[i] = None if fb is None else fb[1:4]
        self.state = self.controller.state(replies)
        return self.state

    def load(self) -> float:
        """Return the legs' mean load f_l [N] from the hip torques (NaN: not known)."""
        st = self.state
        if st is None or not st.valid:
            return math.nan
        tau = []
        for m in self.motors.motors:
            fb = m.feedback
            tau.append(math.nan if fb is None else fb[3])   # MotorFeedback.torque
        return self.controller.load(tau)

    def due(self, tick: int) -> Tuple[int, ...]:
        """
        Return the legs whose hips are commanded in this tick while balancing.

        Each leg every ``legs.command_divider``-th tick; with a divider of 2 or more the two
        legs take turns, so every tick carries the same number of frames (the right leg half a
        cycle after the left: 2 hip frames per tick at 250 Hz, not 4 and 0).
        """
        return self._due[tick % self.divider]

    def frames(self, commands) -> List[Frame]:
        """MIT frames of impedance commands."""
        cf = self.protocol.command_frame
        out = []
        for c in commands:   # (motor_id, position, velocity, kp, kd, torque): cf's arguments
            out.append(cf(*c))
        return out


class LegTask(NoLegs):
    """The leg task with driven legs (see the module docstring)."""

    driven = True

    def __init__(self, cfg: BalanceConfig, hips: MotorSet):
        self.legs = Legs(cfg, hips)
        self.height_min, self.height_max = cfg.model.height_min, cfg.model.height_max
        self.raised_since: Optional[float] = None
        self.raise_integral = 0.0
        self.hold_height: Optional[float] = None   # the length held on the tail (sit-down)
        #: The planned rise's run-up: the robot still rests on its tail while balancing (the tick
        #: sets it from BalanceCore.rise_on_tail); the legs then hold as while raised on it.
        self.tail_hold = False
        self.lift_hold: Optional[Tuple[float, float]] = None   # the heights when lifted
        super().__init__(cfg)

    def configure(self, cfg: BalanceConfig) -> None:
        """Take the live settings of ``cfg``."""
        super().configure(cfg)
        self.legs.configure(cfg)

    def read(self) -> Optional[float]:
        """Read the legs' state; return the height l for the snapshot [m]."""
        state = self.legs.read()
        if self.legs.controller.homed:
            return state.l   # NaN for a leg out of reach or a hip that never replied
        # Before homing the hip angles are known only modulo a rotor turn: l is not known,
        # and not needed (nothing balances); the lowest height stands in.
        return self.height_min

    def ready(self) -> bool:
        """Return True when the legs are homed and at height_min or above (ready to balance)."""
        st = self.legs.state
        return self.legs.controller.homed and st is not None and st.valid and \
            st.l >= self.height_min - RAISED_TOLERANCE

    @property
    def l_ref(self) -> float:
        """Return the shaped height reference [m]."""
        return self.legs.shaper.l_ref

    @property
    def target(self) -> float:
        """Return the height the legs go to [m]: the commanded one."""
        return self.commanded

    def load(self) -> float:
        """Return the legs' mean load f_l [N] from the hip torques (NaN: not known)."""
        return self.legs.load()

    def homing_plan(self) -> str:
        """Return what an arm that homes and raises the legs will do (the reply's text)."""
        return '%sraising the legs to %.2f m, then balancing' % (
            '' if self.legs.controller.homed else 'homing the legs, ', self.height_min)

    def start_homing(self) -> None:
        """Prepare homing (where the angles are not known) and raising."""
        legs = self.legs
        homed = legs.controller.homed
        legs.homing = None if homed else HipHoming(legs.controller.motors, legs.homing_config)
        self.raised_since = None
        self.raise_integral = 0.0
        legs.shaper.height_min = self.height_min   # a sit-down folded below it
        if homed:
            state = legs.read()
            legs.shaper.reset(state.l if state.valid else self.height_min)

    def start_balancing(self) -> None:
        """Balancing begins: the height shaping starts from where the legs are."""
        legs = self.legs
        state = legs.read()
        legs.shaper.height_min = self.height_min
        legs.shaper.reset(state.l if state.valid else self.height_min)
        legs.leveller.reset()

    def _on_sit_down(self) -> None:
        self.raise_integral = 0.0
        self.hold_height = None

    def lifted(self) -> None:
        """Keep the heights the legs have now: the robot was lifted."""
        state = self.legs.state
        self.lift_hold = tuple(state.heights) if state is not None and state.valid else None

    def enable_frames(self) -> List[Frame]:
        """Return the hips' enter-motor-mode frames."""
        return self.legs.motors.enable_frames()

    def stop_frames(self) -> List[Frame]:
        """Return the hips' zero torque and exit frames."""
        return self.legs.motors.stop_frames()

    def poll_frames(self) -> List[Frame]:
        """Return the exit frames that keep resting hips answering."""
        return self.legs.protocol.disable_frames(self.legs.motors.ids)

    # ---------------------------------------------------------------------------- per tick

    def step(self, mode: Mode, now: float, s: SensorSnapshot, dt: float, theta: float,
             rising: bool, tick: int, lifted: bool, gyro_x: float) -> Tuple[List[Frame], list]:
        """
        Return this tick's hip frames and events for ``mode``.

        theta: theta~ - d_hat [rad]; rising: still rising from the tail (the legs stay at
        height_min); tick: the tick's count (the legs take turns); lifted: FAULT for a lift;
        gyro_x: the roll rate [rad/s]. Events: (RAISED, ''), (LEG_FAULT, why), ('info', text).
        """
        frames, events = [], []
        sit = self.sit
        if mode is HOMING:
            self._prepare(now, dt, theta, frames, events)
        elif mode is SITTING and sit is not None and sit.phase in (FOLD, DONE):
            self._fold(dt, theta, frames)
        elif mode is BALANCING or mode is SITTING:
            self._balance(mode, now, s, dt, theta, rising, tick, gyro_x, frames, events)
        elif mode is FAULT:
            legs = self.legs
            if self.lift_hold is not None and lifted:
                # Lifted: the legs keep their length, without the weight's share (the weight
                # is on the hand), so they neither drop nor push out.
                frames += legs.frames(legs.controller.commands(*self.lift_hold, load=0.0))
            else:
                frames += legs.frames(legs.controller.damping_commands(legs.state))
        return frames, events

    def _prepare(self, now, dt, theta, frames, events) -> None:
        """HOMING: home the hips where needed, then raise the legs on the tail to height_min."""
        legs = self.legs
        homing = legs.homing
        if homing is not None and homing.status == 'running':
            frames += legs.frames(homing.step(legs.replies(), now))
            if homing.status == 'done':
                legs.controller.set_offsets(homing.offsets)
                events.append(('info', 'legs homed: offsets %s rad' % ', '.join(
                    '%.4f' % o for o in homing.offsets)))
                state = legs.read()
                legs.shaper.reset(state.l if state.valid else self.height_min)
            elif homing.status == 'failed':
                events.append((LEG_FAULT, 'homing failed: %s' % homing.reason))
            return
        state = legs.state
        if not state.valid:
            events.append((LEG_FAULT, 'legs: ' + '; '.join(state.problems)))
            return
        sh = legs.shaper
        sh.command(self.height_min)
        l_ref, l_dot = sh.step(dt)
        l_cmd = self._tail_height(l_ref, state, dt)
        frames += legs.frames(legs.controller.commands(l_cmd, l_cmd, l_dot, l_dot,
                                                       pitch=theta, load=TAIL_LOAD))
        if l_ref == self.height_min and abs(state.l - l_ref) < RAISED_TOLERANCE:
            self.raised_since = now if self.raised_since is None else self.raised_since
            if now - self.raised_since >= RAISED_TIME:
                events.append((RAISED, ''))
        else:
            self.raised_since = None

    def _fold(self, dt, theta, frames) -> None:
        """Sit-down's last phase: fold the legs down to their stops, resting on the tail."""
        legs = self.legs
        sh, state = legs.shaper, legs.state
        if self.hold_height is not None:   # from holding at contact to folding
            sh.reset(self.hold_height)
            self.hold_height = None
            self.raise_integral = 0.0
        folded = legs.folded_height + FOLD_MARGIN
        sh.height_min = min(sh.height_min, folded)   # the shaper may go below height_min now
        sh.command(folded)
        l_ref, l_dot = sh.step(dt)
        l_cmd = self._tail_height(l_ref, state, dt)
        frames += legs.frames(legs.controller.commands(
            l_cmd, l_cmd, l_dot, l_dot, pitch=theta, load=TAIL_LOAD))
        if state.valid and l_ref == folded and state.l <= folded + RAISED_TOLERANCE:
            self.sit.folded()

    def _balance(self, mode, now, s, dt, theta, rising, tick, gyro_x, frames, events) -> None:
        """BALANCING and SITTING: the shaped height with levelling, or holding on the tail."""
        legs = self.legs
        sh = legs.shaper
        if mode is SITTING:
            sh.command(self.height_min)
        elif not rising:
            sh.command(self.commanded)
        l_ref, l_dot = sh.step(dt)
        if rising and self.tail_hold and mode is BALANCING:
            # The whole weight's share pushed the legs open and tipped the robot over its tail
            # wheel during the planned rise's run-up (MuJoCo, 2026-12-07): as in _prepare.
            l_cmd = self._tail_height(l_ref, legs.state, dt)
            frames += legs.frames(legs.controller.commands(l_cmd, l_cmd, l_dot, l_dot,
                                                           pitch=theta, load=TAIL_LOAD))
            return
        if self.sit is not None and self.sit.phase == BRAKE:
            # On the tail: the legs hold the length they had at contact, so the tail stops the
            # body's rotation (legs that give way, or push with the whole weight's share, let
            # the body roll on over the tail), carrying what the tail leaves. The weight's
            # share goes over with the brake: dropped at once, it lets the body fall onto the
            # tail.
            if self.hold_height is None:
                self.hold_height = legs.state.l if legs.state.valid else l_ref
            load = 1.0 - (1.0 - TAIL_LOAD) * self.sit.brake_blend(now)
            frames += legs.frames(legs.controller.commands(
                self.hold_height, self.hold_height, pitch=theta, load=load))
            return
        dl = legs.leveller.update(s.roll, gyro_x, dt) if legs.levelling else 0.0
        l_left, l_right = split_heights(l_ref, dl, self.height_min, self.height_max)
        due = legs._due[tick % legs.divider]   # legs.due(tick)
        if due:
            frames += legs.frames(legs.controller.commands(
                l_left, l_right, l_dot, l_dot, pitch=theta, legs=due))
        if not legs.state.valid:
            events.append((LEG_FAULT, 'legs: ' + '; '.join(legs.state.problems)))

    def _tail_height(self, l_ref: float, state: LegState, dt: float) -> float:
        """
        Return the legs' commanded height for l_ref [m] while the robot rests on its tail.

        The tail carries part of the weight: feeding the whole share forward pushed the legs
        4 cm past the reference and tipped the robot over the tail. How much the tail carries
        changes with the pitch: an integral on the height error takes the rest (it left
        1.4 cm without).
        """
        if state.valid:
            self.raise_integral += RAISE_KI * (l_ref - state.l) * dt
            self.raise_integral = min(max(self.raise_integral, -RAISE_LIMIT), RAISE_LIMIT)
        return l_ref + self.raise_integral

    # -------------------------------------------------------------------------- publishing

    def joint_values(self) -> Tuple[list, list, list]:
        """Return the hips' and the knees' (positions, velocities, efforts) (NaN: unknown)."""
        legs, nan = self.legs, math.nan
        st = legs.state if legs.state is not None else legs.read()
        dirs = legs.controller.motors.directions
        eff = [d * (m.feedback.torque if m.feedback is not None else nan)
               for d, m in zip(dirs, legs.motors.motors)]
        return list(st.q) + list(st.knees), list(st.q_dot) + [nan] * 4, eff + [nan] * 4

    def status(self) -> Optional[dict]:
        """Return the legs' part of /diagnostics."""
        legs = self.legs
        st = legs.state
        return {'homed': legs.controller.homed,
                'homing': None if legs.homing is None else legs.homing.status,
                'l_ref': legs.shaper.l_ref, 'target': self.commanded,
                'problems': list(st.problems) if st is not None else ['no state']}
