"""
The control tick of balance_node as one object over its parts (no rclpy, no python-can).

``BalanceLoop.tick(now, inputs)`` takes the time and everything that arrived since the last tick
(IMU and joint samples, the motors' CAN replies, the newest cmd_vel and cmd_height, an arm or
disarm request, parameter changes) and returns the CAN frames to send and the state to publish
(core/tick_io.py). The node is a shell around it: it collects the inputs, calls ``tick`` every
2 ms, sends the frames, reports the send's outcome back (``report_send``) and publishes. Given
the same inputs the tick does the same thing, so a fault test, a fuzz case, a benchmark, a
replay and an offline run drive this very object with a fake clock.

The tick is a short sequence over parts that own their state, each configured by one
``configure(cfg)`` at build and on every parameter change:

1. ``Sensing`` (core/sensing.py): the IMU, the motors' replies, the joint states -> the
   ``SensorSnapshot``;
2. ``ArmingSupervisor`` (core/arming.py, beside core/safety.py): an arm, a disarm, auto_arm,
   an emergency stop decided; the motors' health; every check that faults;
3. ``Balancing`` (core/balancing.py): the references and ``BalanceCore`` (observer (8), the
   controller, the torque split of Sec. V-A), the one owner of the odometry;
4. the leg task (core/leg_task.py): homing, raising, the height and roll, the sit-down, folding,
   reported as events; ``NoLegs`` where the legs are not driven;
5. ``Actuation`` (core/actuation.py): the frames to the motors;

and, asked for (``TickInputs.excite``), ``Excitation`` (core/excitation.py): an identification
phase, its wheel torques (EXCITING) or its references (while balancing).

Per mode (core/safety.py): HOMING zero wheel torque while the legs home and rise on the tail;
BALANCING and SITTING the controller's (or the sit-down's) torques; FAULT zero wheel torque
every tick, the hips damping (or, lifted, holding); DISARMED nothing but, every 20 ms, exit
frames that keep the motors' replies coming while they rest. docs/architecture.md draws it.
"""
from math import isfinite
from typing import Any, Dict, List, Mapping, Optional, Tuple

from .actuation import Actuation
from .arming import Action, ArmingSupervisor, AUTO_ARM_STEADY, BALANCE, HOME, safety_limits, \
    SENSOR_INPUTS, SIT, STOP  # noqa: F401 (AUTO_ARM_STEADY, SENSOR_INPUTS, safety_limits)
from .balancing import Balancing, core_config  # noqa: F401 (core_config: its old home)
from .config import BalanceConfig
from .excitation import BALANCE as BALANCE_PHASE
from .excitation_task import ExcitationTask
from .leg_task import LEG_FAULT, LegTask, NoLegs, RAISED
from .protocols.base import Frame
from .safety import BALANCING, COMMANDING, DISARMED, EXCITING, FAULT, HOMING, LEGS, LIFTED, \
    Mode, SensorSnapshot, SITTING
from .schema import with_changes
# The names below had their home here; importers of older code find them still.
from .sensing import all_stop_frames, build_protocol, five_bar, FOREIGN_COMMAND_HOLD, \
    joint_names, joint_state_reader, joint_states_used, LEFT_WHEEL, RIGHT_WHEEL, \
    Sensing  # noqa: F401
from .tick_io import CmdHeight, CmdVel, LoopState, Odom, STATE_FIELDS, TickInputs, \
    TickResult  # noqa: F401


class BalanceLoop:
    """The control tick (see the module docstring)."""

    def __init__(self, cfg: BalanceConfig):
        self.cfg = cfg
        self.period = cfg.loop.control_period
        self.p = cfg.model
        self.sensing = Sensing(cfg)
        self.legs_task = LegTask(cfg, self.sensing.hips) if cfg.legs.driven else NoLegs(cfg)
        self.arming = ArmingSupervisor(cfg, self.sensing, self.legs_task)
        self.balancing = Balancing(cfg)
        self.actuation = Actuation(self.sensing.motors, self.legs_task, self.sensing.from_can,
                                   self.period)
        self.excite = ExcitationTask(cfg, self.arming, self.actuation, self.balancing,
                                     self.legs_task, self._act)
        self.excitation = self.excite.excitation
        self.joint_names = joint_names(cfg)
        # The parts' objects that callers (tests, the fault suite) reach through the loop.
        self.supervisor = self.arming.safety
        self.motors, self.protocol = self.sensing.motors, self.sensing.protocol
        self.wheel_states = self.sensing.wheel_states
        self.legs = self.legs_task.legs
        self.imu = self.sensing.imu
        self.core = self.balancing.core
        self.shaper = self.balancing.shaper
        self._result = TickResult()
        self._last_now: Optional[float] = None
        self._ticks = 0

    def apply_parameters(self, changes: Mapping[str, Any]) -> None:
        """Apply validated parameter changes {name: value} (at the start of a tick)."""
        self.cfg = cfg = with_changes(self.cfg, changes)
        for part in (self.sensing, self.legs_task, self.arming, self.balancing,
                     self.excitation):
            part.configure(cfg)

    @property
    def mode(self) -> Mode:
        """Return the supervisor's mode."""
        return self.supervisor.mode

    @property
    def last_result(self) -> TickResult:
        """Return what the newest tick produced (the object is reused by the next tick)."""
        return self._result

    # ---------------------------------------------------------------------------- the tick

    def tick(self, now: float, inputs: TickInputs) -> TickResult:
        """Run one control tick at monotonic time ``now`` [s] (see the module docstring)."""
        r, arming, ctl, legs = self._begin(now, inputs)
        last, self._last_now = self._last_now, now
        dt = now - last if last is not None else self.period
        stall_limit = arming.begin(now, dt)
        self.sensing.take(inputs.imu, inputs.joints, inputs.frames, ctl.accel, r.events)
        ctl.take(inputs.cmd_vel, inputs.cmd_height, inputs.conflicts, legs)
        s = self.sensing.read(now, legs.read(), legs.height)
        sup = arming.safety   # its _mode read directly: the properties cost a call a use
        mode = sup._mode
        commanded = mode in COMMANDING   # since the previous tick
        if not (mode is BALANCING or mode is SITTING) and s.imu_time is not None \
                and s.joint_time is not None and sup.limits.plausible(s):
            ctl.coast(s, dt)
        ctl.estimate_acceleration(dt)
        self._motor_health(now, r)
        self._request(now, inputs, s)
        st = r.state   # still the last tick's torques: applied since
        mode = arming.check(now, s, dt, stall_limit, commanded, inputs.imu_silent,
                            st.tau_left, st.tau_right, ctl.d_hat, ctl.rising, r.events)
        mode = self.excite.step(mode, now, s, r, self._ticks) if self.excitation.phase else mode
        if mode is BALANCING or mode is SITTING:
            self._balance(mode, now, s, dt)
        else:
            if mode is FAULT or mode is HOMING:
                self.actuation.zero(r)
            elif mode is DISARMED:
                self.actuation.poll(r, self._ticks)
            ctl.idle(st)
            if mode is EXCITING:
                self.excite.publish(st)
        self._step_legs(mode, now, s, dt)
        if mode is SITTING and legs.sat_down:
            r.events.append(('info', legs.finish_sit_down()))
            self._act(arming.disarm(), now, s)
        r.state.time = now
        self._publish(s)
        return r

    def _begin(self, now: float, inputs: TickInputs):
        r = self._result
        r.frames, r.leg_frames, r.arm_reply, r.events = [], [], None, []
        self._ticks += 1
        if inputs.params:
            self.apply_parameters(inputs.params)
        if self.excitation.phase == BALANCE_PHASE:   # its references, not the operator's
            inputs.cmd_vel, inputs.cmd_height = self.excitation.references(now)
        return r, self.arming, self.balancing, self.legs_task

    def _request(self, now: float, inputs: TickInputs, s: SensorSnapshot) -> None:
        """Decide an operator's request (arming's, core/arming.py) or start an excitation."""
        action = self.arming.request(now, inputs, s, self._result.events)
        if action is not None:
            self._act(action, now, s)
        elif inputs.excite:
            self.excite.start(now, inputs.excite, s, inputs.guarded, self._result)

    def _motor_health(self, now: float, r: TickResult) -> None:
        """Judge the motors' health: the wheels' torque derated; too hot, the sit-down."""
        scale, hot = self.arming.motor_health(now)
        self.balancing.derate(scale)
        if hot is not None and self.arming.safety._mode is BALANCING and self.arming.sit_down():
            self.legs_task.start_sit_down()
            r.events.append(('warn', 'over-temperature, sitting down: ' + hot))

    def _act(self, action: Optional[Action], now: float, s: SensorSnapshot) -> None:
        """Carry out the supervisor's decision (core/arming.py) with the parts."""
        if action is None:
            return
        r, legs = self._result, self.legs_task
        if action.kind == STOP:
            legs.end()
            self.actuation.stop(r)
        elif action.kind == SIT:
            legs.start_sit_down()
        elif action.kind == HOME:
            legs.start_homing()
            self.actuation.enable(r)
        elif action.kind == BALANCE:
            self.balancing.start(s, self.imu.yaw_rate)
            if not action.enabled:
                self.actuation.enable(r)
            legs.start_balancing()

    def _balance(self, mode: Mode, now: float, s: SensorSnapshot, dt: float) -> None:
        """Run the controller (or the sit-down's lean and brake); command the wheels."""
        r, ctl, legs = self._result, self.balancing, self.legs_task
        sitting = mode is SITTING and legs.sit is not None
        out, x_ref, w_ref = ctl.step(now, s, dt, self.imu.yaw_rate, sitting)
        tau_l, tau_r, u = out.tau_left, out.tau_right, out.u
        if sitting:
            sit = legs.sit_wheels(now, s, out.x_dot, out.d_hat, ctl.max_wheel_torque)
            if sit is not None:
                tau_l, tau_r, u = sit
        self.actuation.torques(r, tau_l, tau_r)
        st = r.state
        st.x, st.x_dot, st.yaw_rate = out.x, out.x_dot, out.yaw_rate
        st.u, st.tau_left, st.tau_right = u, tau_l, tau_r
        st.x_dot_ref, st.yaw_rate_ref = x_ref, w_ref
        ctl.rise(now, s.theta, legs.commanded, r.events)

    def _step_legs(self, mode: Mode, now: float, s: SensorSnapshot, dt: float) -> None:
        """Add the leg task's frames; act on its events (raised, a leg fault, a line)."""
        r, arming = self._result, self.arming
        faults = arming.safety._faults   # empty but in FAULT
        lifted = any(f.code == LIFTED for f in faults) if faults else False
        self.legs_task.tail_hold = self.balancing.core.rise_on_tail
        frames, events = self.legs_task.step(mode, now, s, dt, s.theta - self.balancing.d_hat,
                                             self.balancing.rising, self._ticks, lifted,
                                             self.imu.gyro[0])
        r.leg_frames += frames
        for kind, text in events:
            if kind == RAISED:
                self._act(arming.start_balancing(now, s, reply_needed=False), now, s)
            elif kind == LEG_FAULT:
                arming.safety.report_fault(now, LEGS, text)
            else:
                r.events.append((kind, text))

    # ------------------------------------------------------------------ sending, stopping

    def report_send(self, now: float, error: Optional[str]) -> None:
        """
        Tell the loop how sending this tick's frames went (None: all sent, else the error).

        A failed send while commanding is a fault; it completes a pending arm/disarm reply.
        """
        r = self._result
        reply = self.arming.reply(now, bool(r.frames or r.leg_frames), error, r.events)
        if reply is not None:
            r.arm_reply = reply

    def report_internal_error(self, now: float,
                              message: str) -> Optional[Tuple[bool, str]]:
        """
        Report an exception that escaped a tick (a bug): a commanded mode goes to FAULT.

        Returns the failed reply of an arm/disarm request the tick was handling, else None.
        """
        reply = self.arming.internal_error(now, message)
        if reply is not None:
            self._result.arm_reply = reply
        return reply

    def stop_frames(self) -> Tuple[List[Frame], List[Frame]]:
        """
        Disarm; return zero torque + exit motor mode for every motor (start, shutdown).

        (the wheels' frames, the hips' frames): the hips may be on a bus of their own.
        """
        self.supervisor.disarm()
        self.legs_task.end()
        return all_stop_frames(self.cfg)

    # ------------------------------------------------------------------------- publishing

    def _publish(self, s: SensorSnapshot) -> None:
        r, ctl, legs = self._result, self.balancing, self.legs_task
        state = r.state
        state.theta, state.theta_dot, state.d_hat, state.l = s.theta, s.theta_dot, \
            ctl.d_hat, s.l
        state.roll = s.roll
        state.l_ref = legs.l_ref
        state.l_target = legs.target
        state.controller = ctl.controller_index
        state.mode = self.supervisor._mode._value_   # int(mode) without the call
        state.excitation = self.excitation.index
        odom, o = r.odom, ctl.core.odometry   # ctl.odometry without its property's call
        odom.x, odom.y, odom.yaw = o.pose
        x_dot, yaw_rate = o.x_dot, o.yaw_rate
        odom.x_dot = x_dot if isfinite(x_dot) else 0.0
        odom.yaw_rate = yaw_rate if isfinite(yaw_rate) else 0.0

    def joint_values(self, now: float) -> Tuple[List[float], List[float], List[float]]:
        """
        Return (position, velocity, effort) of ``joint_names``, each in its joint's convention.

        Wheels: forward positive, relative to the leg (angle unwrapped from the replies, or the
        joint states' velocity); hips: the FiveBarLeg angles; knees: the passive angles of the
        five-bar kinematics (position only). NaN where unknown.
        """
        pos, vel, eff = self.sensing.wheel_joint_values(now)
        leg_pos, leg_vel, leg_eff = self.legs_task.joint_values()
        return pos + leg_pos, vel + leg_vel, eff + leg_eff

    def status(self, now: float) -> Dict[str, Any]:
        """
        Everything /diagnostics shows about the tick, as plain values (picklable).

        mode, faults and conditions as (code, message) pairs, the controller, the references,
        input counters, per motor: alive, reply age [s], replies and the last feedback; the
        newest samples; the legs (homed, height, problems).
        """
        out = self.arming.status()
        out.update(self.balancing.status())
        out.update(self.sensing.status(now, self.supervisor.limits.motor_timeout))
        legs = self.legs_task.status()
        if legs is not None:
            out['legs'] = legs
        if self.legs_task.sit is not None:
            out['sit_down'] = self.legs_task.sit.phase
        out.update(self.excitation.status(now))
        return out
