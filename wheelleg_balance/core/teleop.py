"""
Joystick teleoperation: a Joy sample (axes, buttons) -> x_dot* [m/s], yaw rate*, height, arm.

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
- a rate limiter per axis (core/rate_limiter.py) with acceleration limits
  (``max_linear_accel`` m/s^2, ``max_angular_accel`` rad/s^2) and optional jerk limits (m/s^3,
  rad/s^3) while enabled.

Beyond driving (balance_node's ``cmd_height`` and ``~/arm``):

- the height target l* [m] for ``cmd_height``: a press of one of ``height_buttons`` sets it to
  the ``heights`` entry at the same position (the paper's 0.70 / 0.52 / 0.37 m on Y, X, A), and
  ``axis_height`` moves it at up to ``scale_height`` m/s, within [height_min, height_max]; only
  while motion is enabled. It starts at height_min, where the robot stands up. The target is a
  step: balance_node shapes it with its own rate and acceleration limits;
- arm and disarm by button combinations with the deadman: ``enable_button`` held together with
  every one of ``arm_buttons`` (``disarm_buttons``) for ``arm_hold_time`` asks once for
  ``~/arm`` true (false: balance_node sits the robot down); the combination must be released
  before it asks again, and a joystick gone silent cancels it.

Malformed samples never raise: missing entries, NaN/Inf and non-numbers read as 0 (axes) or not
pressed (buttons), and axes are clamped to [-1, 1], so outputs stay within the scales.
No rclpy here: nodes/teleop_node.py feeds monotonic times and samples.
"""
from dataclasses import dataclass, fields
import math
from typing import List, Optional, Sequence, Tuple

from .rate_limiter import finite_or_zero as _finite, RateLimiter
from .schema import param

__all__ = ['apply_deadzone', 'button_pressed', 'map_joy', 'MAX_TICK_DT', 'read_axis', 'Teleop',
           'TeleopConfig', 'pad_combo']

#: Largest time step [s] the rate limiters integrate in one tick: after a stall (a busy executor)
#: the reference keeps ramping at no more than this step, never jumps.
MAX_TICK_DT = 0.1


_BUTTON = (-1, 127)
_AXIS = (-1, 63)


def _index(default: int, description: str, limits, name: str):
    return param(default, description, limits[0], limits[1], step=1, name=name)


@dataclass
class TeleopConfig:
    """
    Teleop parameters: teleop_twist_joy's names (the ROS name where it has a '.').

    Indices are 0-based into sensor_msgs/Joy buttons and axes (-1 = unused). A limit of 0 means
    "no limit" for the accelerations and jerks. Defaults: an Xbox pad under the joy package's
    SDL game controller mapping (config/teleop_xbox.yaml).
    """

    enable_button: int = _index(9, 'button that enables motion at the normal scales (Joy '
                                'buttons index; SDL LEFTSHOULDER, LB / L1)', _BUTTON,
                                'enable_button')
    enable_turbo_button: int = _index(10, 'button that enables motion at the turbo scales, '
                                      'even without the enable button; -1 = none (SDL '
                                      'RIGHTSHOULDER, RB / R1)', _BUTTON, 'enable_turbo_button')
    require_enable_button: bool = param(True, 'false: move at the normal scales without '
                                        'holding the enable button')
    axis_linear_x: int = _index(1, 'axis for x_dot* (Joy axes index; -1 = unused; SDL LEFTY, up '
                                '= +1 under the joy package)', _AXIS, 'axis_linear.x')
    scale_linear_x: float = param(0.5, 'x_dot* at full deflection [m/s] (negative inverts the '
                                  'axis)', -5.0, 5.0, name='scale_linear.x')
    scale_linear_turbo_x: float = param(1.0, 'x_dot* at full deflection with turbo [m/s]', -5.0,
                                        5.0, name='scale_linear_turbo.x')
    axis_angular_yaw: int = _index(2, 'axis for yaw rate* (Joy axes index; -1 = unused; SDL '
                                   'RIGHTX, left = +1 under the joy package)', _AXIS,
                                   'axis_angular.yaw')
    scale_angular_yaw: float = param(1.5, 'yaw rate* at full deflection [rad/s], positive turns '
                                     'left', -10.0, 10.0, name='scale_angular.yaw')
    scale_angular_turbo_yaw: float = param(2.88, 'yaw rate* at full deflection with turbo '
                                           "[rad/s] (2.88: 165 deg/s, the paper's rotation)",
                                           -10.0, 10.0, name='scale_angular_turbo.yaw')
    inverted_reverse: bool = param(False, 'negate the yaw rate while x_dot* < 0 (turn like a '
                                   'reversing car)')
    deadzone: float = param(0.1, 'axis deadzone, fraction of full deflection; rescaled so the '
                            'command is continuous at its edge', 0.0, 0.95)
    joy_timeout: float = param(0.5, 'joystick silence after which motion stops (one zero '
                               'command) [s]', 0.01, 10.0)
    max_linear_accel: float = param(1.0, 'acceleration limit of x_dot* [m/s^2]; 0 = unlimited',
                                    0.0, 50.0)
    max_angular_accel: float = param(6.0, 'acceleration limit of yaw rate* [rad/s^2]; 0 = '
                                     'unlimited', 0.0, 200.0)
    max_linear_jerk: float = param(0.0, 'jerk limit of x_dot* [m/s^3]; 0 = unlimited', 0.0,
                                   1000.0)
    max_angular_jerk: float = param(0.0, 'jerk limit of yaw rate* [rad/s^3]; 0 = unlimited',
                                    0.0, 5000.0)
    height_buttons: List[int] = param([3, 2, 0], 'buttons that set the height target to the '
                                      'heights entry at the same position, while motion is '
                                      'enabled (SDL Y, X, A); empty: none', 0, 127, item=int)
    heights: List[float] = param([0.70, 0.52, 0.37], 'height target [m] of each height_buttons '
                                 "entry (the paper's 0.70 / 0.52 / 0.37 m)", 0.0, 3.0,
                                 item=float)
    axis_height: int = _index(3, 'axis that moves the height target, up = taller, while motion '
                              'is enabled (Joy axes index; -1 = unused; SDL RIGHTY)', _AXIS,
                              'axis_height')
    scale_height: float = param(0.1, 'rate of the height target at full deflection of '
                                'axis_height [m/s] (negative inverts the axis)', -1.0, 1.0)
    height_min: float = param(0.37, "lowest height target [m] (balance_node's height_min; the "
                              'target starts here, where the robot stands up)', 0.0, 3.0)
    height_max: float = param(0.70, "highest height target [m] (balance_node's height_max)",
                              0.0, 3.0)
    arm_buttons: List[int] = param([6], 'held together with enable_button (the deadman) for '
                                   "arm_hold_time: call balance_node's ~/arm true (SDL START); "
                                   'empty: no arming from the pad', 0, 127, item=int)
    disarm_buttons: List[int] = param([4], 'held together with enable_button for '
                                      'arm_hold_time: call ~/arm false, balance_node sits the '
                                      'robot down (SDL BACK); empty: none', 0, 127, item=int)
    arm_hold_time: float = param(0.5, 'how long an arm or disarm combination must be held [s]',
                                 0.0, 5.0)

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
        return out + self._pad_problems()

    def _pad_problems(self) -> List[str]:
        """Check the height and arming buttons: one job per button, the heights in range."""
        out = []
        if len(self.height_buttons) != len(self.heights):
            out.append('height_buttons (%d) and heights (%d) need one entry each' % (
                len(self.height_buttons), len(self.heights)))
        if not self.height_min < self.height_max:
            out.append('height_min %g must be below height_max %g'
                       % (self.height_min, self.height_max))
        out += ['heights entry %g outside height_min..height_max' % h for h in self.heights
                if not self.height_min <= h <= self.height_max]
        if (self.arm_buttons or self.disarm_buttons) and self.enable_button < 0:
            out.append('arm_buttons and disarm_buttons need enable_button (the deadman)')
        roles = [('enable_button', [self.enable_button]),
                 ('enable_turbo_button', [self.enable_turbo_button]),
                 ('height_buttons', self.height_buttons), ('arm_buttons', self.arm_buttons),
                 ('disarm_buttons', self.disarm_buttons)]
        for i, (name, used) in enumerate(roles):
            for other, theirs in roles[i + 1:]:
                if (name, other) == ('enable_button', 'enable_turbo_button'):
                    continue   # checked above
                both = sorted({b for b in used if b >= 0} & {b for b in theirs if b >= 0})
                if both:
                    out.append('%s and %s share button(s) %s' % (name, other, both))
        if len(set(self.height_buttons)) != len(self.height_buttons):
            out.append('height_buttons lists a button twice')
        if self.axis_height >= 0 and self.axis_height in (self.axis_linear_x,
                                                          self.axis_angular_yaw):
            out.append('axis_height %d is also a driving axis' % self.axis_height)
        return out


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


def pad_combo(buttons: Sequence, cfg: TeleopConfig) -> Optional[bool]:
    """
    Return True while the arm combination is held with the deadman, False for the disarm one.

    None when neither (or both) is held in full: enable_button and every button of the
    combination pressed; an empty combination is never held.
    """
    if not button_pressed(buttons, cfg.enable_button):
        return None
    arm = bool(cfg.arm_buttons) and all(button_pressed(buttons, b) for b in cfg.arm_buttons)
    disarm = bool(cfg.disarm_buttons) and all(button_pressed(buttons, b)
                                              for b in cfg.disarm_buttons)
    return arm if arm != disarm else None


class Teleop:
    """
    Stateful teleop: call ``on_joy`` for every Joy sample and ``tick`` at the publish rate.

    ``tick(now)`` returns the command to publish, (x_dot* [m/s], yaw rate* [rad/s]), or None when
    nothing is to be published: every tick while enabled (rate limited), then one (0.0, 0.0) when
    the buttons release motion or the joystick has been silent longer than ``joy_timeout``, then
    None until enabled again. Nothing is published before the first Joy sample. After each tick,
    ``take_height()`` returns a new height target [m] to send on cmd_height (None: unchanged)
    and ``take_arm()`` an arm (True) or disarm (False) request to send to ~/arm (None: none).
    Times are monotonic seconds.
    """

    def __init__(self, cfg: Optional[TeleopConfig] = None):
        self.cfg = cfg or TeleopConfig()
        self.linear = RateLimiter()
        self.angular = RateLimiter()
        self._target: Optional[Tuple[float, float]] = None
        self._joy_time: Optional[float] = None
        self._last_tick: Optional[float] = None
        self._zero_sent = False
        self.timed_out = False
        #: The height target l* [m]; sent on cmd_height only once it changes.
        self.height = self._height_sent = self.cfg.height_min
        self._height_rate = 0.0                 # from axis_height [m/s]
        self._pressed: Tuple[bool, ...] = ()    # height_buttons held in the last sample
        self._combo: Optional[bool] = None      # the arm / disarm combination held
        self._combo_since = 0.0
        self._combo_done = False
        self._arm: Optional[bool] = None
        self.configure(self.cfg)

    def configure(self, cfg: TeleopConfig) -> None:
        """Take a new configuration; the references continue from their current values."""
        self.cfg = cfg
        self.linear.max_accel, self.linear.max_jerk = cfg.max_linear_accel, cfg.max_linear_jerk
        self.angular.max_accel, self.angular.max_jerk = (cfg.max_angular_accel,
                                                         cfg.max_angular_jerk)
        self.height = self._clamp_height(self.height)

    def on_joy(self, axes: Sequence, buttons: Sequence, now: float) -> None:
        """Take a Joy sample received at monotonic time ``now`` [s]."""
        self._joy_time = now
        try:
            self._target = map_joy(axes, buttons, self.cfg)
            self._on_pad(axes, buttons, now)
        except Exception:  # noqa: B902 -- a sample the readers did not foresee: not enabled
            self._target = None
            self._height_rate = 0.0
            self._combo = None

    def _on_pad(self, axes: Sequence, buttons: Sequence, now: float) -> None:
        """Read the height buttons (on a press), the height axis and the arm combinations."""
        cfg = self.cfg
        pressed = tuple(button_pressed(buttons, b) for b in cfg.height_buttons)
        if self._target is not None:
            for k, down in enumerate(pressed):
                if down and not (k < len(self._pressed) and self._pressed[k]):
                    self.height = self._clamp_height(cfg.heights[k])
                    break
            self._height_rate = apply_deadzone(read_axis(axes, cfg.axis_height),
                                               cfg.deadzone) * cfg.scale_height
        else:
            self._height_rate = 0.0
        self._pressed = pressed
        combo = pad_combo(buttons, cfg)
        if combo != self._combo:
            self._combo, self._combo_since, self._combo_done = combo, now, False

    def _clamp_height(self, l: float) -> float:
        return min(max(l, self.cfg.height_min), self.cfg.height_max)

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
        self._tick_pad(now, dt)
        if self._target is not None and not self.timed_out:
            self._zero_sent = False
            cfg = self.cfg
            x_max = max(abs(cfg.scale_linear_x), abs(cfg.scale_linear_turbo_x))
            w_max = max(abs(cfg.scale_angular_yaw), abs(cfg.scale_angular_turbo_yaw))
            return (self.linear.step(self._target[0], dt, x_max),
                    self.angular.step(self._target[1], dt, w_max))
        return self.stop()

    def _tick_pad(self, now: float, dt: float) -> None:
        if self.timed_out:
            self._height_rate, self._combo, self._pressed = 0.0, None, ()
            return
        if self._height_rate:
            self.height = self._clamp_height(self.height + self._height_rate * dt)
        if self._combo is not None and not self._combo_done and \
                now - self._combo_since >= self.cfg.arm_hold_time:
            self._combo_done = True
            self._arm = self._combo

    def take_height(self) -> Optional[float]:
        """Return the height target [m] if it changed since it was last taken, else None."""
        if self.height == self._height_sent:
            return None
        self._height_sent = self.height
        return self.height

    def take_arm(self) -> Optional[bool]:
        """Return a pending arm (True) or disarm (False) request once, else None."""
        request, self._arm = self._arm, None
        return request

    def stop(self) -> Optional[Tuple[float, float]]:
        """Rest the references; return the one (0.0, 0.0) to send, or None if it was sent."""
        self.linear.reset()
        self.angular.reset()
        if self._zero_sent:
            return None
        self._zero_sent = True
        return 0.0, 0.0
