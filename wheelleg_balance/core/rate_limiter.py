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
        # finite_or_zero's result; its call only for what is not a finite plain float
        if type(target) is not float or target - target != 0.0:
            target = finite_or_zero(target)
        if type(dt) is not float or dt - dt != 0.0:
            dt = finite_or_zero(dt)
        # min(a, b) is written b if b < a else a, max(a, b) b if b > a else a: the same result
        # (NaN included) without the builtins' calls, on the tick's path.
        max_accel, max_jerk = self.max_accel, self.max_jerk
        if max_jerk <= 0.0 and max_accel > 0.0 and dt > 0.0:
            # The ramp (the reference shaper's): the general steps below, shortened.
            error = target - self.value
            if error == 0.0:   # held at the target: a_lim = 0, which lands on it
                v = -bound if -bound > target else target
                v = bound if bound < v else v
                self.value, self.accel = v, math.copysign(0.0, error)
                return v
            abs_error = abs(error)
            a_lim = abs_error / dt
            a_lim = a_lim if a_lim < max_accel else max_accel
            accel = math.copysign(a_lim, error)
            if a_lim * dt >= abs_error:  # lands on the target exactly
                v = -bound if -bound > target else target
                v = bound if bound < v else v
                self.value, self.accel = v, accel
                return v
            self.accel = accel
            value = self.value = self.value + accel * dt
            if abs(value) > bound:
                self.value, self.accel = math.copysign(bound, value), 0.0
            return self.value
        if max_accel <= 0.0 and max_jerk <= 0.0:
            v = -bound if -bound > target else target
            self.value, self.accel = bound if bound < v else v, 0.0
            return self.value
        if dt <= 0.0:
            return self.value
        a_max = max_accel if max_accel > 0.0 else math.inf
        error = target - self.value
        # Largest acceleration towards the target: within the limit, and not past the target
        # in this very step.
        a_lim = abs(error) / dt
        a_lim = a_lim if a_lim < a_max else a_max
        if max_jerk > 0.0:
            j = max_jerk
            # ... and not past it while the acceleration then ramps down to 0 at j: the value
            # still moves by a^2 / (2 j) + a dt / 2 (the discrete sum of that ramp).
            a_ramp = j * (math.sqrt(0.25 * dt * dt + 2.0 * abs(error) / j) - 0.5 * dt)
            a_lim = a_ramp if a_ramp < a_lim else a_lim
            toward = 1.0 if error >= 0.0 else -1.0
            a_rel = self.accel * toward   # current acceleration, positive towards the target
            lo = a_rel - j * dt
            lo = lo if lo > a_lim else a_lim
            hi = a_rel + j * dt
            a_rel = hi if hi < lo else lo
            accel = toward * a_rel
            accel = -a_max if -a_max > accel else accel
            accel = a_max if a_max < accel else accel
        else:
            accel = math.copysign(a_lim, error)
            if a_lim * dt >= abs(error):  # lands on the target exactly, not a rounding off it
                v = -bound if -bound > target else target
                self.value, self.accel = bound if bound < v else v, accel
                return self.value
        self.accel = accel
        self.value += accel * dt
        if abs(self.value) > bound:
            self.value, self.accel = math.copysign(bound, self.value), 0.0
        return self.value
