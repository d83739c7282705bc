"""
Joystick teleoperation: a Joy sample (axes, buttons) -> the references x_dot* [m/s], yaw rate*.

Semantics and parameter names follow ros2/teleop_twist_joy (rolling, src/teleop_twist_joy.cpp):

- the turbo button (``enable_turbo_button``, -1 = none) enables motion at the turbo scales, even
  without the enable button; otherwise the enable button (or ``require_enable_button`` false)
  enables motion at the normal scales;
- x_dot* = axis[axis_linear.x] * scale_linear.x, yaw rate* = axis[axis_angular.yaw] *
  scale_angular.yaw (positive turns left, REP 103); an axis index of -1 or beyond the sample's
  axes reads 0;
- ``inverted_reverse``: while x_dot* < 0 the yaw rate is negated, so the robot turns like a car
  reversing;
- when motion stops being enabled, exactly one zero command is sent, then nothing while it stays
  disabled.

Beyond teleop_twist_joy (the paper's S-turn, Sec. V-B 5, oscillated in x_dot and yaw rate because
the operator's reference was jerky):

- a deadzone on both axes, rescaled so the command is continuous at the deadzone edge and still
  reaches full scale at full deflection (``apply_deadzone``);
- ``joy_timeout``: a joystick that has gone silent counts as released (one zero command);
- a rate limiter per axis (``RateLimiter``) with acceleration limits (``max_linear_accel`` m/s^2,
  ``max_angular_accel`` rad/s^2) and optional jerk limits (m/s^3, rad/s^3) while enabled.

Malformed samples never raise: missing entries, NaN/Inf and non-numbers read as 0 (axes) or not
pressed (buttons), and axes are clamped to [-1, 1], so outputs stay within the scales.
No rclpy here: nodes/teleop_node.py feeds monotonic times and samples.
"""
from dataclasses import dataclass, fields
import math
from typing import List, Optional, Sequence, Tuple

#: Largest time step [s] the rate limiters integrate in one tick: after a stall (a busy executor)
#: the reference keeps ramping at no more than this step, never jumps.
MAX_TICK_DT = 0.1


@dataclass
class TeleopConfig:
    """
    Teleop parameters; field names are teleop_twist_joy's with '.' replaced by '_'.

    Indices are 0-based into sensor_msgs/Joy buttons and axes (-1 = unused). A limit of 0 means
    "no limit" for the accelerations and jerks.
    """

    enable_button: int = 9                 # SDL game controller LEFTSHOULDER (LB / L1)
    enable_turbo_button: int = 10          # SDL game controller RIGHTSHOULDER (RB / R1)
    require_enable_button: bool = True
    axis_linear_x: int = 1                 # SDL LEFTY (up = +1 under the joy package)
    scale_linear_x: float = 0.5            # x_dot* at full deflection [m/s]
    scale_linear_turbo_x: float = 1.0      # [m/s]
    axis_angular_yaw: int = 2              # SDL RIGHTX (left = +1 under the joy package)
    scale_angular_yaw: float = 1.5         # yaw rate* at full deflection [rad/s]
    scale_angular_turbo_yaw: float = 2.88  # 165 deg/s, the paper's rotation experiment [rad/s]
    inverted_reverse: bool = False
    deadzone: float = 0.1                  # fraction of the axis range, [0, 1)
    joy_timeout: float = 0.5               # [s]
    max_linear_accel: float = 1.0          # [m/s^2], 0 = unlimited
    max_angular_accel: float = 6.0         # [rad/s^2], 0 = unlimited
    max_linear_jerk: float = 0.0           # [m/s^3], 0 = unlimited
    max_angular_jerk: float = 0.0          # [rad/s^3], 0 = unlimited

    def problems(self) -> List[str]:
        """Return why this configuration is unusable (empty list: it is fine)."""
        out = []
        for f in fields(self):
            v = getattr(self, f.name)
            if f.type is int and (isinstance(v, bool) or not isinstance(v, int) or v < -1):
                out.append('%s must be an integer >= -1 (-1 = unused), got %r' % (f.name, v))
            elif f.type is float and (isinstance(v, bool) or not isinstance(v, (int, float))
                                      or not math.isfinite(v)):
                out.append('%s must be a finite number, got %r' % (f.name, v))
            elif f.type is bool and not isinstance(v, bool):
                out.append('%s must be a bool, got %r' % (f.name, v))
        if out:
            return out
        if not 0.0 <= self.deadzone < 1.0:
            out.append('deadzone must be in [0, 1), got %r' % self.deadzone)
        if self.joy_timeout <= 0.0:
            out.append('joy_timeout must be > 0 s, got %r' % self.joy_timeout)
        for name in ('max_linear_accel', 'max_angular_accel', 'max_linear_jerk',
                     'max_angular_jerk'):
            if getattr(self, name) < 0.0:
                out.append('%s must be >= 0 (0 = unlimited), got %r' % (name, getattr(self, name)))
        if self.enable_turbo_button >= 0 and self.enable_turbo_button == self.enable_button:
            out.append('enable_button and enable_turbo_button are both %d: turbo would always '
                       'be on' % self.enable_button)
        if self.require_enable_button and self.enable_button < 0 and self.enable_turbo_button < 0:
            out.append('require_enable_button is true but enable_button and enable_turbo_button '
                       'are both -1: motion could never be enabled')
        return out


def _finite(v) -> float:
    """``v`` as a float, or 0.0 when it is not a finite number."""
    try:
        f = float(v)
    except (TypeError, ValueError, OverflowError):
        return 0.0
    return f if math.isfinite(f) else 0.0


def read_axis(axes: Sequence, index: int) -> float:
    """Axis ``index`` of a Joy sample in [-1, 1]; 0 when unused (-1), missing or not finite."""
    if index < 0:
        return 0.0
    try:
        v = axes[index]
    except (IndexError, TypeError, KeyError):
        return 0.0
    return min(max(_finite(v), -1.0), 1.0)


def button_pressed(buttons: Sequence, index: int) -> bool:
    """Return whether button ``index`` exists and holds a finite non-zero value."""
    if index < 0:
        return False
    try:
        v = buttons[index]
    except (IndexError, TypeError, KeyError):
        return False
    return _finite(v) != 0.0


def apply_deadzone(value: float, deadzone: float) -> float:
    """
    Zero inside |value| <= deadzone, then rescale linearly so +-1 still maps to +-1.

    Continuous at the deadzone edge (the output leaves 0 there), unlike a plain cut-off that
    would step to +-deadzone. ``value`` is clamped to [-1, 1] first.
    """
    v = min(max(_finite(value), -1.0), 1.0)
    a = abs(v)
    if a <= deadzone:
        return 0.0
    return math.copysign((a - deadzone) / (1.0 - deadzone), v)


def map_joy(axes: Sequence, buttons: Sequence,
            cfg: TeleopConfig) -> Optional[Tuple[float, float]]:
    """
    Map one Joy sample to the target (x_dot* [m/s], yaw rate* [rad/s]), before rate limiting.

    Returns None when motion is not enabled (neither turbo nor enable button, and the enable
    button is required).
    """
    if cfg.enable_turbo_button >= 0 and button_pressed(buttons, cfg.enable_turbo_button):
        scale_x, scale_yaw = cfg.scale_linear_turbo_x, cfg.scale_angular_turbo_yaw
    elif not cfg.require_enable_button or button_pressed(buttons, cfg.enable_button):
        scale_x, scale_yaw = cfg.scale_linear_x, cfg.scale_angular_yaw
    else:
        return None
    x_dot = apply_deadzone(read_axis(axes, cfg.axis_linear_x), cfg.deadzone) * scale_x
    yaw_rate = apply_deadzone(read_axis(axes, cfg.axis_angular_yaw), cfg.deadzone) * scale_yaw
    if cfg.inverted_reverse and x_dot < 0.0:
        yaw_rate = -yaw_rate
    return x_dot + 0.0, yaw_rate + 0.0  # + 0.0 turns -0.0 into 0.0


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
        self.value = _finite(value)
        self.accel = 0.0

    def step(self, target: float, dt: float, bound: float = math.inf) -> float:
        """
        Advance ``dt`` [s] towards ``target`` (non-finite: 0) and return the new value.

        The value never leaves [-bound, bound] (the jerk-limited approach can pass a target at
        full scale by up to max_jerk * dt^2: it stops at the bound instead).
        """
        target = _finite(target)
        dt = _finite(dt)
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
        self.accel = accel
        self.value += accel * dt
        if abs(self.value) > bound:
            self.value, self.accel = math.copysign(bound, self.value), 0.0
        return self.value


class Teleop:
    """
    Stateful teleop: call ``on_joy`` for every Joy sample and ``tick`` at the publish rate.

    ``tick(now)`` returns the command to publish, (x_dot* [m/s], yaw rate* [rad/s]), or None when
    nothing is to be published: every tick while enabled (rate limited), then one (0.0, 0.0) when
    the buttons release motion or the joystick has been silent longer than ``joy_timeout``, then
    None until enabled again. Nothing is published before the first Joy sample. Times are
    monotonic seconds.
    """

    def __init__(self, cfg: Optional[TeleopConfig] = None):
        self.cfg = cfg or TeleopConfig()
        self.linear = RateLimiter()
        self.angular = RateLimiter()
        self.configure(self.cfg)
        self._target: Optional[Tuple[float, float]] = None
        self._joy_time: Optional[float] = None
        self._last_tick: Optional[float] = None
        self._zero_sent = False
        self.timed_out = False

    def configure(self, cfg: TeleopConfig) -> None:
        """Take a new configuration; the references continue from their current values."""
        self.cfg = cfg
        self.linear.max_accel, self.linear.max_jerk = cfg.max_linear_accel, cfg.max_linear_jerk
        self.angular.max_accel, self.angular.max_jerk = (cfg.max_angular_accel,
                                                         cfg.max_angular_jerk)

    def on_joy(self, axes: Sequence, buttons: Sequence, now: float) -> None:
        """Take a Joy sample received at monotonic time ``now`` [s]."""
        self._joy_time = now
        try:
            self._target = map_joy(axes, buttons, self.cfg)
        except Exception:  # noqa: B902 -- a sample the readers did not foresee: not enabled
            self._target = None

    @property
    def enabled(self) -> bool:
        """Whether the newest sample enables motion (the timeout is not considered)."""
        return self._target is not None

    def tick(self, now: float) -> Optional[Tuple[float, float]]:
        """Advance to monotonic time ``now`` [s]; return the command to publish or None."""
        dt = 0.0 if self._last_tick is None else min(max(now - self._last_tick, 0.0),
                                                     MAX_TICK_DT)
        self._last_tick = now
        if self._joy_time is None:
            return None
        self.timed_out = now - self._joy_time > self.cfg.joy_timeout
        if self._target is not None and not self.timed_out:
            self._zero_sent = False
            cfg = self.cfg
            x_max = max(abs(cfg.scale_linear_x), abs(cfg.scale_linear_turbo_x))
            w_max = max(abs(cfg.scale_angular_yaw), abs(cfg.scale_angular_turbo_yaw))
            return (self.linear.step(self._target[0], dt, x_max),
                    self.angular.step(self._target[1], dt, w_max))
        return self.stop()

    def stop(self) -> Optional[Tuple[float, float]]:
        """Rest the references; return the one (0.0, 0.0) to send, or None if it was sent."""
        self.linear.reset()
        self.angular.reset()
        if self._zero_sent:
            return None
        self._zero_sent = True
        return 0.0, 0.0
