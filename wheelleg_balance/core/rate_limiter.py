"""
The one rate limiter of the package: references that ramp instead of stepping.

Used by teleop (x_dot* and yaw rate* from the stick, with jerk limits), by the reference shaping
of balance_node (core/reference.py) and by the height command. Same order as ros2_controllers'
diff_drive_controller SpeedLimiter: jerk, then acceleration, then the value's bound.
"""
import math


def finite_or_zero(v) -> float:
    """``v`` as a float, or 0.0 when it is not a finite number (or not a number at all)."""
    try:
        f = float(v)
    except (TypeError, ValueError, OverflowError):
        return 0.0
    return f if math.isfinite(f) else 0.0


def limit_rate(target: float, previous: float, max_rate: float, dt: float) -> float:
    """Move from ``previous`` towards ``target`` by at most ``max_rate * dt``."""
    step = max_rate * dt
    return min(max(target, previous - step), previous + step)


class RateLimiter:
    """
    Shapes one reference so that |d/dt| <= max_accel and |d^2/dt^2| <= max_jerk.

    Without a jerk limit this is a ramp: each step moves towards the target by at most
    max_accel * dt and lands on it exactly. With a jerk limit the acceleration itself ramps by at
    most max_jerk * dt per step, and the acceleration towards the target is capped at the largest
    from which it can still ramp down to zero by the time the error does (about
    sqrt(2 max_jerk |error|)), so a held target is approached without overshoot beyond
    max_jerk * dt^2. A limit of 0 (or less) means unlimited.
    """

    def __init__(self, max_accel: float = 0.0, max_jerk: float = 0.0):
        self.max_accel = max_accel
        self.max_jerk = max_jerk
        self.value = 0.0
        self.accel = 0.0

    def reset(self, value: float = 0.0) -> None:
        """Jump to ``value`` at rest (zero acceleration)."""
        self.value = finite_or_zero(value)
        self.accel = 0.0

    def step(self, target: float, dt: float, bound: float = math.inf) -> float:
        """
        Advance ``dt`` [s] towards ``target`` (non-finite: 0) and return the new value.

        The value never leaves [-bound, bound] (the jerk-limited approach can pass a target at
        full scale by up to max_jerk * dt^2: it stops at the bound instead).
        """
        target = finite_or_zero(target)
        dt = finite_or_zero(dt)
        if self.max_accel <= 0.0 and self.max_jerk <= 0.0:
            self.value, self.accel = min(max(target, -bound), bound), 0.0
            return self.value
        if dt <= 0.0:
            return self.value
        a_max = self.max_accel if self.max_accel > 0.0 else math.inf
        error = target - self.value
        # Largest acceleration towards the target: within the limit, and not past the target
        # in this very step.
        a_lim = min(a_max, abs(error) / dt)
        if self.max_jerk > 0.0:
            j = self.max_jerk
            # ... and not past it while the acceleration then ramps down to 0 at j: the value
            # still moves by a^2 / (2 j) + a dt / 2 (the discrete sum of that ramp).
            a_lim = min(a_lim, j * (math.sqrt(0.25 * dt * dt + 2.0 * abs(error) / j) - 0.5 * dt))
            toward = 1.0 if error >= 0.0 else -1.0
            a_rel = self.accel * toward   # current acceleration, positive towards the target
            a_rel = min(max(a_lim, a_rel - j * dt), a_rel + j * dt)
            accel = min(max(toward * a_rel, -a_max), a_max)
        else:
            accel = math.copysign(a_lim, error)
            if a_lim * dt >= abs(error):  # lands on the target exactly, not a rounding off it
                self.value, self.accel = min(max(target, -bound), bound), accel
                return self.value
        self.accel = accel
        self.value += accel * dt
        if abs(self.value) > bound:
            self.value, self.accel = math.copysign(bound, self.value), 0.0
        return self.value
