"""
The control core as a part of the tick: the operator's commands, the references, BalanceCore.

``Balancing`` takes cmd_vel (and hands cmd_height to the legs), shapes the references
(core/reference.py: cmd_vel timeout, acceleration and velocity limits), runs ``BalanceCore``
(core/pipeline.py: observer (8), the controller, the torque split of Sec. V-A) while the
wheels are commanded, and tells when the robot has risen from its tail (the legs then go to the
commanded height). ``BalanceCore`` is the one owner of the wheel odometry: it moves it in
``step`` while balancing and in ``coast`` while not. No rclpy, no CAN.
"""
import math
from typing import Optional, Tuple

import numpy as np

from .config import BalanceConfig
from .estimation import WheelOdometry
from .pipeline import BalanceCore, CONTROLLER_NAMES, CoreConfig, Measurement, TickValues
from .reference import ReferenceShaper
from .safety import SensorSnapshot
from .tick_io import CmdVel, LoopState

#: |theta~ - d_hat| [rad] below which, for RISE_TIME [s], the robot counts as risen (the legs
#: then go to the commanded height).
RISEN_ANGLE = math.radians(5.0)
RISE_TIME = 0.5


def core_config(cfg: BalanceConfig) -> CoreConfig:
    """Return the control core's tuning from the configuration (the tick's, the margins')."""
    c = cfg.control
    return CoreConfig(controller=c.controller, ida_pbc=cfg.ida_pbc,
                      compensate_offset=c.compensate_offset, d_hat0=c.d_hat0,
                      yaw_rate_gain=c.yaw_rate_gain, yaw_rate_ki=c.yaw_rate_ki,
                      yaw_rate_ff=c.yaw_rate_ff, yaw_integral_limit=c.yaw_integral_limit,
                      yaw_rate_source=c.yaw_rate_source,
                      max_wheel_torque=cfg.safety.max_wheel_torque,
                      switch_blend_time=c.switch_blend_time,
                      lqr_Q=np.diag(cfg.output_regulation.q_diag),
                      lqr_R=cfg.output_regulation.r,
                      linear_gain_source=cfg.output_regulation.gain_source, auto=cfg.auto,
                      hold=cfg.output_regulation, tail_pitch=cfg.safety.tail_pitch)


class Balancing:
    """The control core of the tick (see the module docstring)."""

    def __init__(self, cfg: BalanceConfig):
        self.cfg = cfg
        self.p = cfg.model
        self.core = BalanceCore(self.p, core_config(cfg), dt=cfg.loop.control_period,
                                odometry=WheelOdometry(self.p))
        self.shaper = ReferenceShaper()
        self._cmd: Optional[CmdVel] = None
        self.rejected_cmd_vel = 0
        self.rejected_cmd_height = 0
        self.x = 0.0       # travel since arming [m]
        self.d_hat = 0.0   # the observer's IMU offset estimate [rad]
        self._x_dot_prev = 0.0
        self.accel = 0.0   # forward acceleration estimate [m/s^2] (the IMU's gravity fallback)
        self.rising = False
        self._risen_since: Optional[float] = None
        self.configure(cfg)

    @property
    def odometry(self) -> WheelOdometry:
        """Return BalanceCore's wheel odometry."""
        return self.core.odometry

    def configure(self, cfg: BalanceConfig) -> None:
        """Take the settings of ``cfg`` that may change live (at build and on every change)."""
        old, self.cfg = self.cfg, cfg
        core = self.core
        if cfg.control.controller != old.control.controller:
            core.select(cfg.control.controller)
        if cfg.ida_pbc != old.ida_pbc:
            core.set_ida_pbc_gains(cfg.ida_pbc)
        if cfg.output_regulation != old.output_regulation:
            core.set_hold_shape(cfg.output_regulation)
        c, k = cfg.control, core.config
        k.d_hat0, k.yaw_rate_gain, k.yaw_rate_ki = c.d_hat0, c.yaw_rate_gain, c.yaw_rate_ki
        k.yaw_rate_ff, k.yaw_integral_limit = c.yaw_rate_ff, c.yaw_integral_limit
        k.yaw_rate_source, k.switch_blend_time = c.yaw_rate_source, c.switch_blend_time
        k.max_wheel_torque = cfg.safety.max_wheel_torque
        core.set_auto_rules(cfg.auto)
        sh, ref = self.shaper, cfg.reference
        sh.max_velocity, sh.max_acceleration = ref.max_velocity, ref.max_acceleration
        sh.max_yaw_rate, sh.max_yaw_acceleration = ref.max_yaw_rate, ref.max_yaw_acceleration
        sh.cmd_vel_timeout = cfg.safety.cmd_vel_timeout

    def take(self, cmd_vel: Optional[CmdVel], cmd_height, conflicts, legs) -> None:
        """Take the newest commands; a non-finite one, or one of a conflict, is dropped."""
        if cmd_vel is not None:
            if 'cmd_vel' not in conflicts and math.isfinite(cmd_vel.x_dot) \
                    and math.isfinite(cmd_vel.yaw_rate):
                self._cmd = cmd_vel
            else:
                self.rejected_cmd_vel += 1
        if cmd_height is not None:
            h = cmd_height.height
            if 'cmd_height' not in conflicts and isinstance(h, (int, float)) \
                    and math.isfinite(h):
                legs.command_height(h)
            else:
                self.rejected_cmd_height += 1

    def derate(self, scale: float) -> None:
        """Scale the wheels' torque limit (a hot wheel motor: core/motor_health.py)."""
        self.core.config.max_wheel_torque = self.cfg.safety.max_wheel_torque * scale

    @property
    def max_wheel_torque(self) -> float:
        """Return the wheels' torque limit now [N m] (derated when a wheel motor is hot)."""
        return self.core.config.max_wheel_torque

    def coast(self, s: SensorSnapshot, dt: float) -> None:
        """Not balancing: the odometry follows the wheels all the same (a plausible ``s``)."""
        self.core.coast(s.wheel_vel_left, s.wheel_vel_right, s.theta_dot, dt)

    def estimate_acceleration(self, dt: float) -> None:
        """Estimate the forward acceleration, low-passed (50 ms), for the gravity fallback."""
        x_dot = self.core.odometry.x_dot
        if math.isfinite(x_dot) and dt > 0.0:
            a = (x_dot - self._x_dot_prev) / dt
            gain = dt / 0.05
            self.accel += (1.0 if 1.0 < gain else gain) * (a - self.accel)   # min(1, gain)
            self._x_dot_prev = x_dot
        if not math.isfinite(self.accel):
            self.accel = 0.0

    def start(self, s: SensorSnapshot, yaw_rate: float) -> None:
        """Balancing begins: x = 0, the observer at the measured pitch, the references at 0."""
        self.core.reset(_measurement(s, yaw_rate))
        self.shaper.reset()
        self.rising = True
        self._risen_since = None

    def step(self, now: float, s: SensorSnapshot, dt: float, yaw_rate: float,
             sitting: bool) -> Tuple[TickValues, float, float]:
        """
        Run the controller; return its output and the shaped x_dot* [m/s], yaw rate* [rad/s].

        sitting: the sit-down runs (the references go to zero). The output has TickOutput's
        fields; it is BalanceCore's one TickValues, rewritten by the next tick.
        """
        cmd = self._cmd
        if cmd is None or sitting:
            x_ref, w_ref = self.shaper.update(now, None, 0.0, 0.0, dt)
        else:
            x_ref, w_ref = self.shaper.update(now, cmd.t, cmd.x_dot, cmd.yaw_rate, dt)
        # BalanceCore.step's fields passed as they are (no Measurement, Reference, TickOutput)
        out = self.core.advance(s.theta, s.theta_dot, s.wheel_vel_left, s.wheel_vel_right, s.l,
                                yaw_rate, x_ref, w_ref, dt)
        self.x, self.d_hat = out.x, out.d_hat
        return out, x_ref, w_ref

    def rise(self, now: float, theta: float, target: float, events: list) -> None:
        """While rising: risen once |theta~ - d_hat| stays within RISEN_ANGLE for RISE_TIME."""
        if not self.rising:
            return
        if abs(theta - self.d_hat) < RISEN_ANGLE:
            self._risen_since = now if self._risen_since is None else self._risen_since
            if now - self._risen_since >= RISE_TIME:
                self.rising = False
                events.append(('info', 'risen: the legs go to %.3f m' % target))
        else:
            self._risen_since = None

    def idle(self, state: LoopState) -> None:
        """Fill ``state`` for a tick that did not balance: the odometry, no torque."""
        odometry = self.core.odometry
        state.x, state.x_dot, state.yaw_rate = self.x, odometry.x_dot, odometry.yaw_rate
        state.u = state.tau_left = state.tau_right = 0.0
        state.x_dot_ref = state.yaw_rate_ref = 0.0

    @property
    def controller_index(self) -> int:
        """Return the active controller's index in CONTROLLER_NAMES."""
        return CONTROLLER_NAMES.index(self.core.active_controller)

    def status(self) -> dict:
        """Return the control core's part of /diagnostics."""
        sh = self.shaper
        return {'controller': self.core.active_controller,
                'controller_parameter': self.cfg.control.controller,
                'x_dot_ref': sh.x_dot_ref, 'yaw_rate_ref': sh.yaw_rate_ref,
                'cmd_vel_timed_out': sh.timed_out,
                'rejected_cmd_vel': self.rejected_cmd_vel,
                'rejected_cmd_height': self.rejected_cmd_height}


def _measurement(s: SensorSnapshot, yaw_rate: float) -> Measurement:
    return Measurement(s.theta, s.theta_dot, s.wheel_vel_left, s.wheel_vel_right, s.l, yaw_rate)
