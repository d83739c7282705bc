"""
Shaping of the operator's command into the references x_dot* [m/s] and yaw rate* [rad/s].

Per axis, as ros2_controllers' diff_drive_controller SpeedLimiter: first the acceleration limit
(relative to the previous reference), then the velocity limit (core/rate_limiter.py). A command
older than ``cmd_vel_timeout`` [s] counts as zero, so the references ramp down to zero at the
acceleration limits while the robot keeps balancing: a missing command is not a fault.
"""
from typing import Optional, Tuple

from .rate_limiter import RateLimiter


class ReferenceShaper:
    """Rate- and value-limited x_dot* and yaw rate* from cmd_vel (see the module docstring)."""

    def __init__(self, max_velocity: float = 1.0, max_acceleration: float = 1.0,
                 max_yaw_rate: float = 3.0, max_yaw_acceleration: float = 6.0,
                 cmd_vel_timeout: float = 0.5):
        self._x = RateLimiter(max_acceleration)
        self._w = RateLimiter(max_yaw_acceleration)
        self.max_velocity = max_velocity
        self.max_yaw_rate = max_yaw_rate
        self.cmd_vel_timeout = cmd_vel_timeout
        self.timed_out = True

    @property
    def max_acceleration(self) -> float:
        """Limit of the rate of change of x_dot* [m/s^2]."""
        return self._x.max_accel

    @max_acceleration.setter
    def max_acceleration(self, value: float) -> None:
        self._x.max_accel = value

    @property
    def max_yaw_acceleration(self) -> float:
        """Limit of the rate of change of yaw rate* [rad/s^2]."""
        return self._w.max_accel

    @max_yaw_acceleration.setter
    def max_yaw_acceleration(self, value: float) -> None:
        self._w.max_accel = value

    @property
    def x_dot_ref(self) -> float:
        """Return the present x_dot* [m/s]."""
        return self._x.value

    @property
    def yaw_rate_ref(self) -> float:
        """Return the present yaw rate* [rad/s]."""
        return self._w.value

    def reset(self) -> None:
        """Start from rest (on arm)."""
        self._x.reset()
        self._w.reset()

    def update(self, now: float, cmd_time: Optional[float], x_dot_cmd: float,
               yaw_rate_cmd: float, dt: float) -> Tuple[float, float]:
        """
        Advance one tick of ``dt`` [s] towards the newest command.

        cmd_time is the monotonic receipt time of the command [s] (None: none yet).
        Returns (x_dot*, yaw rate*).
        """
        self.timed_out = cmd_time is None or now - cmd_time > self.cmd_vel_timeout
        if self.timed_out:
            x_dot_cmd = yaw_rate_cmd = 0.0
        return (self._x.step(x_dot_cmd, dt, self.max_velocity),
                self._w.step(yaw_rate_cmd, dt, self.max_yaw_rate))
