"""
From the force u to the two wheel torques, and from wheel to motor directions (paper Sec. V-A).

Sec. V-A: each wheel gets tau = r_w u / 2 (so the two together push with u), and the yaw torque
tau_gamma = gain (yaw_rate - yaw_rate*) is added to the left wheel and subtracted from the right.
That is a negative feedback on the yaw rate: turning left faster than asked (yaw_rate > yaw_rate*)
speeds the left wheel up and slows the right one, which turns the robot right. The pair sums to
r_w u whatever tau_gamma is, so yaw does not disturb balance -- until a wheel hits its torque
limit. Then balance comes first: the common torque is clipped to +-max, and tau_gamma only gets
the headroom that is left, so the two wheels still sum to the (clipped) balance torque and the
turn is what gives way.
"""
import math
from typing import Tuple

from .params import RobotParams


def wheel_torques(u: float, yaw_rate: float, yaw_rate_ref: float, p: RobotParams,
                  yaw_rate_gain: float = 0.3, max_torque: float = 12.0,
                  yaw_extra: float = 0.0) -> Tuple[float, float, bool]:
    """
    Wheel torques (tau_left, tau_right, saturated) for force u (Sec. V-A).

    u: force on the cart [N], forward positive; yaw_rate, yaw_rate_ref: measured and wanted yaw
    rate [rad/s], positive turns left; yaw_rate_gain [N m s/rad]; max_torque: per-wheel limit
    [N m]; yaw_extra: the yaw loop's integral and feed-forward torque [N m], positive turns
    left (YawLoop). tau_gamma = yaw_rate_gain (yaw rate - yaw rate*) - yaw_extra, the paper's
    with yaw_extra = 0. Returns wheel torques [N m], forward positive, before motor directions,
    and whether a limit cut the command. The outputs are always finite and within +-max_torque:
    a NaN term counts as zero, and a max_torque that is not a positive finite number means zero
    torque. The balance comes first: the yaw torque gets only the headroom u leaves.
    """
    limit = max_torque if 0.0 < max_torque < math.inf else 0.0  # NaN fails the comparison
    saturated = False
    tau = 0.5 * p.wheel_radius * u
    if tau != tau:  # NaN
        tau = 0.0
    if tau > limit:
        tau, saturated = limit, True
    elif tau < -limit:
        tau, saturated = -limit, True
    tau_gamma = yaw_rate_gain * (yaw_rate - yaw_rate_ref) - yaw_extra
    if tau_gamma != tau_gamma:
        tau_gamma = 0.0
    headroom = limit - abs(tau)
    if tau_gamma > headroom:
        tau_gamma, saturated = headroom, True
    elif tau_gamma < -headroom:
        tau_gamma, saturated = -headroom, True
    # The final clip only removes floating-point rounding (|tau| + headroom == limit).
    # (Comparisons, not min/max calls: the same result, NaN included, for a tenth the cost.)
    tau_left = tau + tau_gamma
    if not -limit <= tau_left <= limit:
        tau_left = limit if tau_left > limit else -limit
    tau_right = tau - tau_gamma
    if not -limit <= tau_right <= limit:
        tau_right = limit if tau_right > limit else -limit
    return tau_left, tau_right, saturated


class YawLoop:
    """
    The yaw loop's integral and feed-forward terms (the proportional one is the paper's, Sec. V-A).

    A turn on the spot needs a steady torque against the tyres' scrub (about 2 N m per wheel at
    2.5 rad/s in MuJoCo): the paper's proportional term alone reached 43 of 165 deg/s.
    yaw_extra = ff yaw rate* + ki integral of (yaw rate* - yaw rate) dt, the integral kept within
    +-limit [N m] and held while a torque limit cuts the command (no wind-up).
    ki [N m/rad], ff [N m s/rad], limit [N m].
    """

    def __init__(self, ki: float = 0.0, ff: float = 0.0, limit: float = 4.0):
        self.ki, self.ff, self.limit = ki, ff, limit
        self.integral = 0.0   # [N m]

    def reset(self) -> None:
        """Arming: no torque carried over."""
        self.integral = 0.0

    def extra(self, yaw_rate_ref: float) -> float:
        """Return yaw_extra [N m] for this tick (NaN terms count as zero)."""
        ff = self.ff * yaw_rate_ref
        return self.integral + (ff if ff == ff else 0.0)

    def update(self, yaw_rate: float, yaw_rate_ref: float, dt: float, saturated: bool) -> None:
        """Integrate this tick's error [rad/s] over dt [s], unless the command was cut."""
        step = self.ki * (yaw_rate_ref - yaw_rate) * dt
        if saturated or step != step:
            return
        # min(limit, max(-limit, integral)) as comparisons, the same result (a tenth the cost)
        limit, integral = self.limit, self.integral + step
        integral = integral if integral > -limit else -limit
        self.integral = integral if integral < limit else limit


def check_direction(direction: int) -> int:
    """Return a motor mounting direction (+1 or -1) as int; raise ValueError for other values."""
    if direction not in (1, -1):
        raise ValueError('motor direction must be 1 or -1, not %r' % (direction,))
    return int(direction)


def motor_torque(wheel_torque: float, direction: int) -> float:
    """
    Motor torque [N m] that gives ``wheel_torque`` (forward positive) on the wheel.

    direction is +1 when the motor's positive rotation drives the wheel forward, -1 when the
    motor is mounted mirrored (typically one side of the robot).
    """
    return direction * wheel_torque


def wheel_velocity(motor_velocity: float, direction: int) -> float:
    """
    Wheel angular velocity [rad/s], forward positive, from the motor's velocity.

    direction as for motor_torque; the same mapping turns a motor position into a wheel angle.
    """
    return direction * motor_velocity


#: Ticks between the exit frames that keep resting motors answering (DISARMED): 20 ms.
POLL_TICKS = 10


class Actuation:
    """
    The last part of the tick: its frames to the motors (no CAN here: core/motors.py's codecs).

    wheels: the wheel motors (a core/motors.py MotorSet); legs: the leg task
    (core/leg_task.py), whose hip frames go beside the wheels'; poll_wheels: the wheels' replies
    are read while they rest (``wheel_state_source: can``). Frames go into a TickResult's
    ``frames`` (the wheels' bus) and ``leg_frames`` (the hips').
    """

    def __init__(self, wheels, legs, poll_wheels: bool, period: float = 0.002):
        self.wheels, self.legs, self.poll_wheels = wheels, legs, poll_wheels
        self._names = [m.name for m in wheels.motors]
        # The left and the right wheel's motor (``wheels.torque_frames`` looks them up by
        # name for every command: the same {motor ID: direction tau} map, built here).
        self._left, self._right = wheels.motors
        # A protocol whose torque replies lack the error code asks one wheel every
        # health_interval [s] (the others' ticks pay nothing: torques stays as it is).
        interval = wheels.protocol.health_interval
        self._health_every = max(1, round(interval / period)) if interval > 0.0 else 0
        self._health_ticks = 0
        if self._health_every:
            self.torques = self._torques_and_health

    def torques(self, r, tau_left: float, tau_right: float) -> None:
        """Command the wheel torques [N m] (forward positive; the directions applied here)."""
        left, right = self._left, self._right
        r.frames += self.wheels.protocol.torque_frames({
            left.motor_id: left.direction * tau_left, right.motor_id: right.direction * tau_right})

    def _torques_and_health(self, r, tau_left: float, tau_right: float) -> None:
        """Torques, and every _health_every ticks a health query to the next wheel in turn."""
        Actuation.torques(self, r, tau_left, tau_right)
        n, every = self._health_ticks, self._health_every
        self._health_ticks = n + 1
        if not n % every:
            ids = self.wheels.ids
            r.frames += self.wheels.protocol.health_frames(ids[n // every % len(ids)])

    def excite(self, r, tau_left: float, tau_right: float, tick: int) -> None:
        """EXCITING: the wheel torques [N m]; resting hips polled as in DISARMED."""
        self.torques(r, tau_left, tau_right)
        if self.legs.driven and not tick % POLL_TICKS:
            r.leg_frames += self.legs.poll_frames()

    def enable_wheels(self, r) -> None:
        """Enter motor mode, the wheels only (EXCITING: the hips rest)."""
        r.frames += self.wheels.enable_frames()

    def zero(self, r) -> None:
        """Zero torque to the wheels, staying in motor mode (FAULT, HOMING)."""
        r.frames += self.wheels.zero_torque_frames()

    def enable(self, r) -> None:
        """Enter motor mode, every motor."""
        r.frames += self.wheels.enable_frames()
        r.leg_frames += self.legs.enable_frames()

    def stop(self, r) -> None:
        """Zero torque and exit motor mode, every motor."""
        r.frames += self.wheels.stop_frames()
        r.leg_frames += self.legs.stop_frames()

    def poll(self, r, tick: int) -> None:
        """
        DISARMED: every POLL_TICKS ticks, exit frames to resting motors that are read.

        Resting motors answer every frame: exit frames keep them resting and their replies
        (liveness, wheel and hip readings) coming.
        """
        if tick % POLL_TICKS or not (self.poll_wheels or self.legs.driven) or r.frames:
            return
        if self.poll_wheels:
            r.frames += self.wheels.protocol.disable_frames(self.wheels.ids)
        r.leg_frames += self.legs.poll_frames()
