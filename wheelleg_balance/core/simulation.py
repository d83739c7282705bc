"""
Closed-loop simulation: the nonlinear model (1) of the paper driven by ``BalanceCore``.

The plant is the inverted pendulum on a cart of Sec. II-B, model (1), with the robot's extras:

- integration: fixed-step RK4 (``substeps`` per control period, 4 x 0.5 ms by default), wheel
  torques held constant over each 2 ms tick (zero-order hold), optional extra ticks of delay;
- height l(t): a smooth schedule (cubic smoothstep between waypoints). Model (1) treats l as a
  constant; for a moving l the plant adds the terms a point mass on a leg of prescribed length
  l(t) gets from its Lagrangian (core/model.py ipc_accel_moving; they vanish for l_dot =
  l_ddot = 0, leaving (1) exactly);
- the tail: the body cannot lean forward past ``tail_angle`` (+36 deg). Resting on it, the tail's
  passive wheel pushes only vertically, i.e. a generalized force on theta alone, so the robot
  rolls as one rigid body ((M + m) x_ddot = u - m l_ddot s) until the wheels accelerate forward
  enough to lift the body (the free theta_ddot turns negative). Hitting the tail is a plastic
  impact that keeps the horizontal momentum (M + m) x_dot + m l c theta_dot;
- mass error: the plant's m and M are scaled by ``mass_factor``; the controller keeps nominal;
- yaw: a rigid yaw inertia driven by the wheel torque difference (only for the wheel speeds and
  the yaw-rate loop of Sec. V-A; it does not couple into the pitch plane, as in the paper).

The controller side sees what the robot's sensors give: IMU pitch theta~ = theta + d (IMU offset
d), IMU pitch rate, the wheel angular velocities relative to the leg (forward positive)
w_l,r = (x_dot -/+ yaw_rate d_w / 2) / r_w - theta_dot, and the height l; Gaussian noise from a
seeded generator (so runs are deterministic) can be added to pitch, pitch rate and wheel speeds.

A run ends early with ``fell`` when |theta| > ``fall_angle`` (45 deg), or when the body touches
the tail again after having risen ``rise_margin`` below it (a failed start-up or a forward fall).
"""
from bisect import bisect_right
import copy
from dataclasses import dataclass, field
import math
import time
from typing import Optional, Sequence, Tuple

import numpy as np

from .model import ipc_accel_moving
from .params import CONTROL_PERIOD, IdaPbcGains, RobotParams
from .pipeline import BalanceCore, CoreConfig, Measurement, Reference

#: Angle at which the body rests on its tail [rad] (theta > 0 leans forward).
TAIL_ANGLE = math.radians(36.0)
#: Pitch beyond which the robot counts as fallen [rad].
FALL_ANGLE = math.radians(45.0)


class SmoothSchedule:
    """
    A scalar reference through waypoints ((t0, v0), (t1, v1), ...) with t in [s].

    Between consecutive waypoints the value follows a cubic smoothstep
    v = v_i + (v_{i+1} - v_i) (3 tau^2 - 2 tau^3), tau = (t - t_i) / (t_{i+1} - t_i), so it has
    a continuous first derivative; before t0 it is v0, after the last waypoint the last value.
    """

    def __init__(self, points):
        if isinstance(points, (int, float)):
            points = ((0.0, float(points)),)
        pts = [(float(t), float(v)) for t, v in points]
        if not pts:
            raise ValueError('a schedule needs at least one waypoint')
        if any(b[0] <= a[0] for a, b in zip(pts, pts[1:])):
            raise ValueError('schedule times must increase strictly')
        self._t = [t for t, _ in pts]
        self._v = [v for _, v in pts]
        self.constant = all(v == self._v[0] for v in self._v)

    def __call__(self, t: float) -> Tuple[float, float, float]:
        """Return (value, first derivative, second derivative) at time t [s]."""
        ts, vs = self._t, self._v
        if self.constant or t <= ts[0]:
            return vs[0], 0.0, 0.0
        if t >= ts[-1]:
            return vs[-1], 0.0, 0.0
        i = bisect_right(ts, t) - 1
        span = ts[i + 1] - ts[i]
        dv = vs[i + 1] - vs[i]
        tau = (t - ts[i]) / span
        return (vs[i] + dv * tau * tau * (3.0 - 2.0 * tau),
                dv * 6.0 * tau * (1.0 - tau) / span,
                dv * (6.0 - 12.0 * tau) / (span * span))

    def value(self, t: float) -> float:
        """Return the value at time t [s]."""
        return self(t)[0]


@dataclass
class Scenario:
    """
    One closed-loop run. Angles in rad, lengths in m, times in s (SI throughout).

    controller: BalanceCore controller name ('ida_pbc', 'output_regulation', 'lqr').
    theta0, theta_dot0, x_dot0: true initial state (theta0 = TAIL_ANGLE: resting on the tail).
    imu_offset: d, the IMU reads theta~ = theta + d. d_hat0: the observer's initial d_hat.
    height, x_dot_ref, yaw_rate_ref: waypoints ((t, value), ...) of SmoothSchedule (or a number).
    noise_std: standard deviations of (pitch [rad], pitch rate [rad/s], wheel speed [rad/s]).
    seed: seed of the noise generator. max_wheel_torque: per-wheel limit of BalanceCore [N m].
    motor_torque_limit: per-wheel limit of the motors the controller does not know about
    (None: none) [N m]; the plant clips silently, so the observer sees the unclipped force.
    delay_ticks: extra control periods between a command and its application.
    mass_factor: the plant's m and M are the nominal ones times this (controller: nominal).
    ida_pbc_gains: IDA-PBC parameters (None: the defaults, IdaPbcGains()). compensate_offset:
    IDA-PBC uses theta~ - d_hat. linear_gain: if set, the 'lqr' controller uses this fixed k_x
    [N/rad, N s/rad, N/m, N s/m] instead of the LQR schedule (e.g. Table I's k_x).
    """

    name: str = 'scenario'
    controller: str = 'ida_pbc'
    duration: float = 10.0
    dt: float = CONTROL_PERIOD
    substeps: int = 4
    theta0: float = TAIL_ANGLE
    theta_dot0: float = 0.0
    x_dot0: float = 0.0
    imu_offset: float = 0.0
    d_hat0: float = 0.0
    height: object = 0.37
    x_dot_ref: object = 0.0
    yaw_rate_ref: object = 0.0
    noise_std: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    seed: int = 0
    max_wheel_torque: float = 12.0
    motor_torque_limit: Optional[float] = None
    delay_ticks: int = 0
    mass_factor: float = 1.0
    ida_pbc_gains: Optional[IdaPbcGains] = None
    compensate_offset: bool = True
    linear_gain: Optional[Sequence[float]] = None
    yaw_rate_gain: float = 0.3
    tail_angle: float = TAIL_ANGLE
    fall_angle: float = FALL_ANGLE
    rise_margin: float = math.radians(5.0)
    yaw_inertia: float = 0.33  # [kg m^2], body box plus wheels about the vertical axis
    params: RobotParams = field(default_factory=RobotParams)


@dataclass
class SimResult:
    """
    Time series of a run (one sample per control tick, taken when the sensors are read).

    theta, theta_dot, x, x_dot: true plant state [rad, rad/s, m, m/s]; theta_meas: IMU pitch
    [rad]; x_dot_est: the core's odometry speed [m/s]; u: force applied over the tick [N];
    tau_left, tau_right: wheel torques applied over the tick [N m]; d_hat: observer estimate
    [rad]; l: height [m]; x_dot_ref: velocity reference [m/s]; yaw_rate: true yaw rate [rad/s].
    fell / fall_time: whether and when [s] the robot fell. cpu_time: process time of the run [s].
    The figures of a run (overshoot, settling time, peak torque, tracking errors) are computed
    from these arrays by validation/paper/metrics.py (validation/paper/experiments.run_metrics).
    """

    scenario: Scenario
    t: np.ndarray
    theta: np.ndarray
    theta_dot: np.ndarray
    x: np.ndarray
    x_dot: np.ndarray
    theta_meas: np.ndarray
    x_dot_est: np.ndarray
    u: np.ndarray
    tau_left: np.ndarray
    tau_right: np.ndarray
    d_hat: np.ndarray
    l: np.ndarray
    x_dot_ref: np.ndarray
    yaw_rate: np.ndarray
    fell: bool
    fall_time: Optional[float]
    cpu_time: float


#: The plant is model (1) with the moving-height terms (core/model.py, the one copy).
plant_accel = ipc_accel_moving


class Plant:
    """
    The simulated robot of scenario ``sc``: model (1) with the tail, height schedule and yaw.

    State: theta, theta_dot, x, x_dot, yaw_rate (true values, SI). ``sensors`` gives what the
    robot's IMU and wheel encoders report; ``advance`` integrates one control period under
    constant wheel torques. ``risen``: the body has left the tail; ``fell``: see the module
    docstring.
    """

    def __init__(self, sc: Scenario):
        p = sc.params
        self.sc = sc
        self.m = p.body_mass * sc.mass_factor
        self.M = p.wheel_mass * sc.mass_factor
        self.g = p.gravity
        self.r_w = p.wheel_radius
        self.half_track = 0.5 * p.wheel_separation
        self.height = SmoothSchedule(sc.height)
        self.theta = min(sc.theta0, sc.tail_angle)
        self.theta_dot = sc.theta_dot0
        self.x = 0.0
        self.x_dot = sc.x_dot0
        self.yaw_rate = 0.0
        self._rise_level = sc.tail_angle - sc.rise_margin
        self.risen = self.theta < self._rise_level
        self.fell = False

    def energy(self, t: float = 0.0) -> float:
        """Kinetic plus potential energy of model (1) at height l(t) [J] (zero at the axle)."""
        l = self.height(t)[0]
        c = math.cos(self.theta)
        return (0.5 * (self.M + self.m) * self.x_dot ** 2
                + self.m * l * c * self.x_dot * self.theta_dot
                + 0.5 * self.m * (l * self.theta_dot) ** 2 + self.m * self.g * l * c)

    def sensors(self, t: float, noise=(0.0, 0.0, 0.0, 0.0)) -> Measurement:
        """
        Return the robot's readings at time t [s].

        IMU pitch theta + d, pitch rate, wheel speeds relative to the leg (forward positive),
        height l(t); ``noise`` is added to (pitch, pitch rate, left wheel, right wheel).
        """
        w_base = self.x_dot / self.r_w - self.theta_dot
        w_yaw = self.yaw_rate * self.half_track / self.r_w
        return Measurement(
            theta_meas=self.theta + self.sc.imu_offset + noise[0],
            theta_dot=self.theta_dot + noise[1],
            wheel_vel_left=w_base - w_yaw + noise[2],
            wheel_vel_right=w_base + w_yaw + noise[3],
            l=self.height(t)[0])

    def _accel(self, th, thd, u, l, ld, ldd):
        # Contact with the tail (one contact, so complementarity is a sign test): it pushes
        # only while the free motion would lean the body further forward.
        th_dd, x_dd = plant_accel(th, thd, u, l, ld, ldd, self.m, self.M, self.g)
        if th >= self.sc.tail_angle and thd >= 0.0 and th_dd > 0.0:
            return 0.0, (u - self.m * ldd * math.sin(th)) / (self.M + self.m)
        return th_dd, x_dd

    def advance(self, tau_left: float, tau_right: float, t: float) -> None:
        """Integrate from t over one control period with the wheel torques held [N m]."""
        sc = self.sc
        dt = sc.dt
        h = dt / sc.substeps
        u = (tau_left + tau_right) / self.r_w
        tail = sc.tail_angle
        accel = self._accel
        # Yaw: constant torque over the tick, so the rate update is exact.
        self.yaw_rate += dt * (tau_right - tau_left) / self.r_w * self.half_track / sc.yaw_inertia
        th, thd, x, xd = self.theta, self.theta_dot, self.x, self.x_dot
        height = self.height
        for j in range(sc.substeps):
            t0 = t + j * h
            if height.constant:
                s0 = s1 = s2 = height(t0)
            else:
                s0, s1, s2 = height(t0), height(t0 + 0.5 * h), height(t0 + h)
            a1, b1 = accel(th, thd, u, *s0)
            a2, b2 = accel(th + 0.5 * h * thd, thd + 0.5 * h * a1, u, *s1)
            a3, b3 = accel(th + 0.5 * h * (thd + 0.5 * h * a1), thd + 0.5 * h * a2, u, *s1)
            a4, b4 = accel(th + h * (thd + 0.5 * h * a2), thd + h * a3, u, *s2)
            th_n = th + h * (thd + h / 6.0 * (a1 + a2 + a3))
            thd = thd + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
            x += h * (xd + h / 6.0 * (b1 + b2 + b3))
            xd += h / 6.0 * (b1 + 2.0 * b2 + 2.0 * b3 + b4)
            th = th_n
            if th >= tail:
                if thd > 0.0:
                    # Plastic impact on the tail: vertical impulse, horizontal momentum kept.
                    xd += self.m * s2[0] * math.cos(tail) * thd / (self.M + self.m)
                th, thd = tail, 0.0
                if self.risen:
                    self.fell = True
            elif th < self._rise_level:
                self.risen = True
            if abs(th) > sc.fall_angle:
                self.fell = True
        self.theta, self.theta_dot, self.x, self.x_dot = th, thd, x, xd

    @property
    def on_tail(self) -> bool:
        """Return True while the body rests on the tail."""
        return self.theta >= self.sc.tail_angle


#: Built cores by model: building one places the observer poles and solves the LQR on a grid of
#: heights (0.3 to 1 s); a deep copy of a built one takes a millisecond.
_CORE_CACHE = {}


def _build_core(sc: Scenario) -> BalanceCore:
    """
    Return a BalanceCore configured for ``sc``, ready for ``reset``.

    The expensive part (observer and LQR schedule, which depend only on the model) is built once
    per (params, dt) and deep-copied; the tuning is then set through the core's public surface:
    ``config`` (read every tick), ``set_ida_pbc_gains``, ``select`` (applied by ``reset``).
    """
    key = repr((sc.params, sc.dt))
    if key not in _CORE_CACHE:
        if len(_CORE_CACHE) > 8:
            _CORE_CACHE.clear()
        _CORE_CACHE[key] = BalanceCore(sc.params, CoreConfig(), sc.dt)
    core = copy.deepcopy(_CORE_CACHE[key])
    core.config = CoreConfig(
        controller=sc.controller,
        ida_pbc=sc.ida_pbc_gains if sc.ida_pbc_gains is not None else IdaPbcGains(),
        compensate_offset=sc.compensate_offset,
        d_hat0=sc.d_hat0,
        yaw_rate_gain=sc.yaw_rate_gain,
        max_wheel_torque=sc.max_wheel_torque)
    core.set_ida_pbc_gains(core.config.ida_pbc)
    core.select(sc.controller)
    if sc.linear_gain is not None:
        from .lqr import FixedGain
        from .output_regulation import LqrController
        core.controllers['lqr'] = LqrController(sc.params, FixedGain(sc.linear_gain))
    return core


def simulate(sc: Scenario, core: Optional[BalanceCore] = None) -> SimResult:
    """
    Run scenario ``sc`` in closed loop with BalanceCore; deterministic for a given seed.

    core: a BalanceCore to use as it is (its tuning, not the scenario's controller fields);
    None builds one from the scenario.
    """
    cpu0 = time.process_time()
    dt = sc.dt
    n = int(round(sc.duration / dt))
    plant = Plant(sc)
    v_ref = SmoothSchedule(sc.x_dot_ref)
    yaw_ref = SmoothSchedule(sc.yaw_rate_ref)
    std = sc.noise_std
    noise = (np.random.default_rng(sc.seed).standard_normal((n, 4))
             * np.array([std[0], std[1], std[2], std[2]])).tolist()
    if core is None:
        core = _build_core(sc)
    pending = [(0.0, 0.0)] * sc.delay_ticks  # commands waiting for the extra delay
    limit = sc.motor_torque_limit

    rec = np.full((n, 14), np.nan)
    k_end = n
    for k in range(n):
        t = k * dt
        meas = plant.sensors(t, noise[k])
        if k == 0:
            core.reset(meas)
        ref = Reference(x_dot_ref=v_ref(t)[0], yaw_rate_ref=yaw_ref(t)[0])
        out = core.step(meas, ref, dt)
        pending.append((out.tau_left, out.tau_right))
        tau_l, tau_r = pending.pop(0)
        if limit is not None:
            tau_l = min(limit, max(-limit, tau_l))
            tau_r = min(limit, max(-limit, tau_r))
        rec[k] = (t, plant.theta, plant.theta_dot, plant.x, plant.x_dot, meas.theta_meas,
                  out.x_dot, (tau_l + tau_r) / plant.r_w, tau_l, tau_r, out.d_hat, meas.l,
                  ref.x_dot_ref, plant.yaw_rate)
        plant.advance(tau_l, tau_r, t)
        if plant.fell:
            k_end = k + 1
            break

    cols = rec[:k_end].T
    return SimResult(
        scenario=sc, t=cols[0], theta=cols[1], theta_dot=cols[2], x=cols[3], x_dot=cols[4],
        theta_meas=cols[5], x_dot_est=cols[6], u=cols[7], tau_left=cols[8], tau_right=cols[9],
        d_hat=cols[10], l=cols[11], x_dot_ref=cols[12], yaw_rate=cols[13], fell=plant.fell,
        fall_time=k_end * dt if plant.fell else None, cpu_time=time.process_time() - cpu0)
