"""
One control tick of the paper's loop (Sec. V-A): estimate, control, actuate.

``BalanceCore`` is what balance_node, the closed-loop simulation, the experiments and the
benchmark all run, so the code that is proven in simulation is the code on the robot.

Per tick (2 ms):

1. wheel odometry: x_dot = r_w ((w_l + w_r)/2 + theta_dot), x_k = x_{k-1} + T_s x_dot_{k-1},
   yaw rate = r_w (w_r - w_l) / d_w  (core/estimation.py);
2. the Luenberger observer (8) on [theta~, theta_dot, x, x_dot, d] runs whatever controller is
   selected, so d_hat is always warm and a controller switch hands over the estimator state
   (core/observer.py);
3. the selected controller gives the force u [N] (core/output_regulation.py, core/ida_pbc.py);
   a switch is bumpless: the jump between the old and the new controller's u is blended out
   linearly over ``switch_blend_time``;
4. u becomes two wheel torques with the yaw-rate loop, saturated so balance comes before yaw
   (core/actuation.py). The force actually applied feeds the observer at the next tick.
"""
from dataclasses import dataclass, field, fields
import math
from typing import Optional

import numpy as np

from .actuation import wheel_torques, YawLoop
from .auto_mode import AutoRules, AutoSelector, brake_step, HOLD, RISE
from .controller_base import ControlInput
from .estimation import WheelOdometry
from .ida_pbc import IdaPbcController
from .lqr import linear_gains
from .observer import DisturbanceObserver
from .output_regulation import HoldShape, LqrController, OutputRegulationController
from .params import CONTROL_PERIOD, IdaPbcGains, RobotParams
from .rise import PlannedRise, RiseSpec

#: The controllers (``TickOutput.controller``, the index in ~/state).
CONTROLLER_NAMES = ('ida_pbc', 'output_regulation', 'lqr')
#: Names accepted by ``BalanceCore.select`` and the node's ``controller`` parameter: a
#: controller, or ``auto`` (core/auto_mode.py chooses one every tick).
MODES = CONTROLLER_NAMES + ('auto',)


@dataclass(frozen=True)
class Measurement:
    """
    Sensor readings of one tick.

    theta_meas: IMU pitch theta~ = theta + d [rad]; theta_dot: IMU pitch rate [rad/s];
    wheel_vel_left / wheel_vel_right: wheel angular velocity relative to the leg, forward
    positive [rad/s]; l: height of the body above the wheel axle [m]; yaw_rate_gyro: the IMU's
    yaw rate about the vertical [rad/s] (NaN: none; the yaw loop then uses the wheels').
    """

    theta_meas: float
    theta_dot: float
    wheel_vel_left: float
    wheel_vel_right: float
    l: float
    yaw_rate_gyro: float = math.nan


@dataclass(frozen=True)
class Reference:
    """References from the operator: x_dot* [m/s] and yaw rate* [rad/s, positive turns left]."""

    x_dot_ref: float = 0.0
    yaw_rate_ref: float = 0.0


@dataclass
class CoreConfig:
    """
    Tuning of the control core.

    controller: initial controller, one of MODES ('auto': core/auto_mode.py chooses).
    auto: the auto mode's thresholds.
    ida_pbc: IDA-PBC parameters (the defaults: Table I's and damping near upright rest).
    compensate_offset: IDA-PBC uses theta~ - d_hat (removes the velocity bias an IMU offset
    causes; the paper leaves the offset in).
    d_hat0: initial estimate of the IMU pitch offset d [rad].
    yaw_rate_gain: Sec. V-A yaw torque gain [N m s/rad] (tau_gamma = gain (yaw rate - yaw rate*)).
    yaw_rate_ki [N m/rad], yaw_rate_ff [N m s/rad], yaw_integral_limit [N m]: the yaw loop's
    integral and feed-forward terms (core/actuation.py YawLoop; 0: the paper's loop).
    yaw_rate_source: the yaw rate the integral acts on: 'imu' (the gyro, where the
    measurement has it) or 'wheels' (the odometry's); the proportional term is the wheels'.
    max_wheel_torque: per-wheel torque limit [N m].
    switch_blend_time: time over which a controller switch blends out the jump in u [s].
    lqr_Q, lqr_R: LQR weights (None: core/lqr.py defaults).
    linear_gain_source: the linear controllers' k_x(l): 'lqr' (from lqr_Q, lqr_R) or
    'table_i' (Table I's k_x at every height; core/lqr.py linear_gains).
    hold: how output regulation holds and moves the robot (core/output_regulation.py).
    tail_pitch: the pitch of the tail rest, where the planned rise starts [rad].
    """

    controller: str = 'ida_pbc'
    ida_pbc: IdaPbcGains = field(default_factory=IdaPbcGains)
    compensate_offset: bool = True
    d_hat0: float = 0.0
    yaw_rate_gain: float = 0.3
    yaw_rate_ki: float = 0.0
    yaw_rate_ff: float = 0.0
    yaw_integral_limit: float = 4.0
    yaw_rate_source: str = 'imu'
    max_wheel_torque: float = 12.0
    switch_blend_time: float = 0.1
    lqr_Q: Optional[np.ndarray] = None
    lqr_R: Optional[np.ndarray] = None
    linear_gain_source: str = 'lqr'
    auto: AutoRules = field(default_factory=AutoRules)
    hold: HoldShape = field(default_factory=HoldShape)
    tail_pitch: float = RiseSpec.theta_0


@dataclass(frozen=True)
class TickOutput:
    """
    Result of one tick.

    tau_left / tau_right: wheel torques [N m], forward positive, before motor directions.
    u: force actually applied [N] (after saturation); u_cmd: force the controller asked for [N].
    theta: measured pitch [rad]; theta_dot [rad/s]; x [m]; x_dot [m/s]; yaw_rate [rad/s];
    d_hat: IMU offset estimate [rad]; l: height used [m]; controller: name of the active one;
    saturated: True when a torque limit cut the command.
    """

    tau_left: float
    tau_right: float
    u: float
    u_cmd: float
    theta: float
    theta_dot: float
    x: float
    x_dot: float
    yaw_rate: float
    d_hat: float
    l: float
    controller: str
    saturated: bool


class TickValues:
    """
    TickOutput's fields in one mutable object that ``BalanceCore.advance`` rewrites every tick.

    The tick's path reads its output here instead of building a TickOutput per tick; keep a
    value, not the object, across ticks.
    """

    __slots__ = tuple(f.name for f in fields(TickOutput))

    def __init__(self):
        for name in self.__slots__:
            setattr(self, name, 0.0)
        self.controller, self.saturated = '', False


class BalanceCore:
    """The control tick shared by balance_node, the simulation and the benchmark."""

    def __init__(self, p: RobotParams = RobotParams(), config: Optional[CoreConfig] = None,
                 dt: float = CONTROL_PERIOD, odometry: Optional[WheelOdometry] = None):
        """
        Build the core for robot ``p`` at control period ``dt`` [s].

        odometry: the wheel odometry to update while balancing (the tick's own, so its odom
        pose is one; None: a private one).
        """
        self.p = p
        self.config = config if config is not None else CoreConfig()
        if self.config.controller not in MODES:
            raise ValueError('unknown controller %r (one of %s)'
                             % (self.config.controller, ', '.join(MODES)))
        self.dt = dt
        self.schedule = linear_gains(p, self.config.linear_gain_source, self.config.lqr_Q,
                                     self.config.lqr_R)
        self.controllers = {
            'ida_pbc': IdaPbcController(p, self.config.ida_pbc, self.config.compensate_offset),
            'output_regulation': OutputRegulationController(
                p, self.schedule, shape=self.config.hold),
            'lqr': LqrController(p, self.schedule),
        }
        self.observer = DisturbanceObserver(p, dt)
        # Solved (or read from the cache) only when asked for: a robot's own model would
        # otherwise solve it at every start (2.5-4.5 s) for a rise it does not use.
        self.rise = _planned_rise(p, self.config, dt) if self.config.auto.planned_rise else None
        self.odometry = odometry if odometry is not None else WheelOdometry(p)
        self._auto: Optional[AutoSelector] = None
        self._takeover_speed = 0.0   # [m/s], fading out after the hold's take-over
        self.yaw = YawLoop()
        self._active = self.config.controller
        if self._active == 'auto':
            self._auto, self._active = AutoSelector(self.config.auto), RISE
        self._requested: Optional[str] = None
        self._input = ControlInput(l=p.height_min)
        self._l = p.height_min  # last valid height [m]
        self._u_applied = 0.0
        self._u_cmd = 0.0
        self._blend_offset = 0.0
        self._blend_step = 0.0
        self.out = TickValues()   # the newest tick's output (advance)

    @property
    def active_controller(self) -> str:
        """Name of the controller that computed the last tick."""
        return self._active

    @property
    def auto(self) -> Optional[AutoSelector]:
        """Return the auto mode's selector (None unless the controller is 'auto')."""
        return self._auto

    @property
    def mode(self) -> str:
        """Return what was selected: a controller's name or 'auto'."""
        return 'auto' if self._auto is not None else (self._requested or self._active)

    def select(self, name: str) -> None:
        """Switch to ``name`` (MODES) at the next tick (bumpless). Raises ValueError."""
        if name not in MODES:
            raise ValueError('unknown controller %r (one of %s)' % (name, ', '.join(MODES)))
        if name == 'auto':
            if self._auto is None:   # it goes on from the controller that runs
                self._auto = AutoSelector(self.config.auto, choice=self._active
                                          if self._active in (RISE, HOLD) else RISE)
            return
        self._auto = None
        if self.rise is not None:
            self.rise.stop()
        if name != self._active:
            self._requested = name

    def set_auto_rules(self, rules: AutoRules) -> None:
        """Replace the auto mode's thresholds (from the next tick)."""
        self.config.auto = rules
        if self._auto is not None:
            self._auto.rules = rules
        if rules.planned_rise and self.rise is None:
            # Offline users only (simulations, tests): balance_node's auto.planned_rise is
            # read-only, so the control loop never waits for a solve.
            self.rise = _planned_rise(self.p, self.config, self.dt)

    def set_hold_shape(self, shape: HoldShape) -> None:
        """Replace output regulation's hold shape (lean limits, roll-out); from the next tick."""
        self.config.hold = shape
        self.controllers['output_regulation'].shape = shape

    def set_ida_pbc_gains(self, gains: IdaPbcGains) -> None:
        """Replace the IDA-PBC parameters (k, m22_0, k_v, P); applies from the next tick."""
        self.config.ida_pbc = gains
        self.controllers['ida_pbc'] = IdaPbcController(
            self.p, gains, self.config.compensate_offset)

    def reset(self, meas: Measurement) -> None:
        """Start balancing from ``meas`` (on arm): x = 0, observer at the measured pitch."""
        self.odometry.reset_travel()
        theta_dot = meas.theta_dot if math.isfinite(meas.theta_dot) else 0.0
        self.observer.reset(np.array([meas.theta_meas, theta_dot, 0.0, 0.0, self.config.d_hat0]))
        self._u_applied = 0.0
        self._u_cmd = 0.0
        self._blend_offset = 0.0
        self._blend_step = 0.0
        self.yaw.reset()
        self._takeover_speed = 0.0
        if self._requested is not None:
            self._active, self._requested = self._requested, None
        if self._auto is not None:
            self._auto.reset()
            self._active = self._auto.choice
        rise = self.rise
        if rise is not None:
            rise.stop()
            c = self.config
            if self._auto is not None and c.auto.planned_rise and rise.applies(
                    meas.theta_meas - c.d_hat0, theta_dot, meas.l, c.max_wheel_torque):
                rise.start(c.d_hat0)
        s = self._control_input(meas.theta_meas, meas.theta_dot, 0.0, 0.0,
                                self._height(meas.l), 0.0, self.observer.xi_hat)
        for controller in self.controllers.values():
            controller.reset(s)

    @property
    def planned_rise(self) -> bool:
        """Return True while the planned rise (core/rise.py) computes the force."""
        return self.rise is not None and self.rise.running

    @property
    def rise_on_tail(self) -> bool:
        """Return True while the planned rise's run-up has the robot on its tail (core/rise.py)."""
        return self.rise is not None and self.rise.on_tail

    def _rise_handover(self, theta_meas: float, tilt: float, theta_dot: float,
                       dt: float) -> Optional[str]:
        """
        Return the controller that takes over from the planned rise now, None: not yet.

        IDA-PBC when the pitch leaves the plan, or the body is far from upright after it (the
        auto mode's leave rule); the hold once the plan has ended and the auto mode's enter
        rule holds (its dwell counted from the plan's end). tilt: theta~ - d_hat [rad].
        """
        auto, r = self._auto, self.config.auto
        if self.rise.off_plan(theta_meas):
            auto.reset()
            return RISE
        if not self.rise.finished:
            return None
        if not (abs(tilt) <= r.leave_angle and abs(theta_dot) <= r.leave_rate):
            auto.reset()
            return RISE
        return HOLD if auto.choose(tilt, theta_dot, dt) == HOLD else None

    def coast(self, w_left: float, w_right: float, theta_dot: float, dt: float) -> None:
        """
        Advance the odometry while not balancing (the robot may be pushed or rolled).

        The wheel speeds relative to the leg and the pitch rate [rad/s], over dt [s]: the
        odometry has this one owner, ``step`` moves it while balancing.
        """
        self.odometry.update(w_left, w_right, theta_dot, dt)

    def _height(self, l: float) -> float:
        """Clamp l into the leg's range; a non-finite l (legs out of reach) keeps the last."""
        if math.isfinite(l):
            self._l = self.p.clamp_height(l)
        return self._l

    def _control_input(self, theta_meas, theta_dot, x, x_dot, l, x_dot_ref, z) -> ControlInput:
        """Fill the ControlInput (switches, and controllers without ``compute_floats``)."""
        s = self._input
        s.theta, s.theta_dot, s.x, s.x_dot, s.l = theta_meas, theta_dot, x, x_dot, l
        s.x_dot_ref, s.xi_hat = x_dot_ref, np.array(z)
        return s

    def step(self, meas: Measurement, ref: Reference, dt: Optional[float] = None) -> TickOutput:
        """Run one tick: returns the wheel torques to send and the estimated state."""
        o = self.advance(meas.theta_meas, meas.theta_dot, meas.wheel_vel_left,
                         meas.wheel_vel_right, meas.l, meas.yaw_rate_gyro, ref.x_dot_ref,
                         ref.yaw_rate_ref, self.dt if dt is None else dt)
        return TickOutput(
            tau_left=o.tau_left, tau_right=o.tau_right, u=o.u, u_cmd=o.u_cmd, theta=o.theta,
            theta_dot=o.theta_dot, x=o.x, x_dot=o.x_dot, yaw_rate=o.yaw_rate, d_hat=o.d_hat,
            l=o.l, controller=o.controller, saturated=o.saturated)

    def advance(self, theta_meas: float, theta_dot: float, w_left: float, w_right: float,
                l_meas: float, yaw_rate_gyro: float, x_dot_ref: float, yaw_rate_ref: float,
                dt: float) -> TickValues:
        """
        ``step`` on plain floats, the tick's path: Measurement's and Reference's fields in.

        Returns ``self.out``, TickOutput's fields rewritten in place by every tick (nothing is
        built per tick: no Measurement, Reference, TickOutput or numpy array).
        """
        x, x_dot, yaw_rate = self.odometry.update(w_left, w_right, theta_dot, dt)
        if math.isfinite(l_meas):
            # p.clamp_height(l) (min(max(l, lo), hi)) without its call; a non-finite l (legs
            # out of reach) keeps the last
            p = self.p
            lo, hi = p.height_min, p.height_max
            l = lo if lo > l_meas else l_meas
            self._l = hi if hi < l else l
        l = self._l
        z = self.observer.update_floats(theta_meas, x, self._u_applied, l)
        d_hat = z[4]
        rise = self.rise
        planned = rise is not None and rise.running
        if planned:
            handover = self._rise_handover(theta_meas, theta_meas - d_hat, theta_dot, dt)
            if handover is not None:
                rise.stop()
                planned = False
                self._requested = handover
        elif self._auto is not None:
            choice = self._auto.choose(theta_meas - d_hat, theta_dot, dt)
            if choice != self._active:
                self._requested = choice
        requested = self._requested
        x_dot_ref_c = x_dot_ref   # the x_dot* the controller tracks
        if requested is not None:
            # Taking over a moving robot (auto's rule or a parameter set): the hold starts at
            # its speed and brakes at auto.stop_deceleration, instead of pulling it back to
            # where it took over or braking at its small lean limit.
            self._takeover_speed = x_dot - x_dot_ref if requested == HOLD else 0.0
        if self._takeover_speed:
            x_dot_ref_c = x_dot_ref + self._takeover_speed
            self._takeover_speed = brake_step(self._takeover_speed,
                                              self.config.auto.stop_deceleration, dt)

        if planned:
            u_cmd = rise.step(theta_meas, theta_dot, x, x_dot)
        elif requested is not None:
            # Bumpless transfer: the new controller starts from the current estimate, and the
            # difference to the last command fades out instead of stepping the torque.
            s = self._control_input(theta_meas, theta_dot, x, x_dot, l, x_dot_ref_c, z)
            new = self.controllers[requested]
            new.reset(s)
            u_new = new.compute(s)
            self._active, self._requested = requested, None
            jump = self._u_cmd - u_new if math.isfinite(u_new) else 0.0
            ticks = max(1, int(round(self.config.switch_blend_time / dt)))
            self._blend_offset = jump
            self._blend_step = jump / ticks
            u_cmd = u_new
        else:
            controller = self.controllers[self._active]
            try:   # an attribute, not a getattr call: the tick's controllers all have it
                fast = controller.compute_floats
            except AttributeError:
                u_cmd = controller.compute(self._control_input(
                    theta_meas, theta_dot, x, x_dot, l, x_dot_ref_c, z))
            else:
                u_cmd = fast(theta_meas, theta_dot, x, x_dot, l, x_dot_ref_c, z)

        blend = self._blend_offset
        if blend != 0.0:
            u_cmd += blend
            if abs(blend) <= abs(self._blend_step):
                self._blend_offset = 0.0
            else:
                self._blend_offset = blend - self._blend_step
        if not math.isfinite(u_cmd):
            u_cmd = 0.0  # never pass a non-finite command on; the supervisor sees theta itself
        self._u_cmd = u_cmd

        c, yaw = self.config, self.yaw
        yaw.ki, yaw.ff, yaw.limit = c.yaw_rate_ki, c.yaw_rate_ff, c.yaw_integral_limit
        # The proportional term acts on the wheels' yaw rate: it damps the wheels' speed
        # difference, which keeps a wheel in the air from running free (with it on the gyro, a
        # wheel dropping off MuJoCo's ramp spun up into the lifted fault). The integral acts on
        # the gyro's: the wheels overstate a turn on the spot (their tyres scrub: 165 deg/s by
        # the wheels was 136 deg/s of true yaw), so only the gyro's error brings the true rate.
        r_int = yaw_rate_gyro if c.yaw_rate_source == 'imu' \
            and math.isfinite(yaw_rate_gyro) else yaw_rate
        tau_left, tau_right, saturated = wheel_torques(
            u_cmd, yaw_rate, yaw_rate_ref, self.p, c.yaw_rate_gain, c.max_wheel_torque,
            yaw.extra(yaw_rate_ref))
        yaw.update(r_int, yaw_rate_ref, dt, saturated)
        # The force really applied (after the torque limit) is what the observer must see.
        u = self._u_applied = (tau_left + tau_right) / self.p.wheel_radius
        o = self.out
        o.tau_left, o.tau_right, o.u, o.u_cmd = tau_left, tau_right, u, u_cmd
        o.theta, o.theta_dot, o.x, o.x_dot = theta_meas, theta_dot, x, x_dot
        o.yaw_rate, o.d_hat, o.l = yaw_rate, d_hat, l
        o.controller, o.saturated = self._active, saturated
        return o


def _planned_rise(p: RobotParams, c: CoreConfig, dt: float) -> Optional[PlannedRise]:
    """Return the planned rise of this robot (core/rise.py), None when it cannot be solved."""
    try:
        return PlannedRise(p, RiseSpec(l=p.height_min, theta_0=c.tail_pitch - c.d_hat0,
                                       max_wheel_torque=c.max_wheel_torque, dt=dt))
    except RuntimeError:
        return None   # IDA-PBC rises, as without the plan
