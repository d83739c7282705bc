"""
teleop_node: joystick (sensor_msgs/Joy on ``joy``) -> ``cmd_vel`` for balance_node.

A thin shell around core/teleop.py (DESIGN.md section 2): the subscription stores each sample,
a timer at ``publish_rate`` publishes the rate-limited command while motion is enabled, then one
zero command when it is released or the joystick has been silent for ``joy_timeout``.
``cmd_vel`` is geometry_msgs/TwistStamped (header.stamp = now, frame_id = ``frame``) or Twist
when ``publish_stamped_twist`` is false: linear.x = x_dot* [m/s], angular.z = yaw rate* [rad/s],
positive turns left (REP 103).

Parameters carry descriptors with ranges (see ``ros2 param describe /teleop_node <name>``);
``publish_rate`` and ``publish_stamped_twist`` are read-only, every other one can change live:
a bad value is rejected with a reason and nothing changes. config/teleop_xbox.yaml and
config/teleop_ps4.yaml hold the values for the pads under the joy package's SDL mapping.
"""
from dataclasses import asdict, fields, replace
import signal
import sys
import threading
import time

from geometry_msgs.msg import Twist, TwistStamped
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
import rclpy
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import Joy

from ..core.teleop import Teleop, TeleopConfig

_BUTTON = (-1, 127)
_AXIS = (-1, 63)
# ROS name -> (description, range or None). Defaults come from core.teleop.TeleopConfig.
_CORE_PARAMS = {
    'enable_button': ('button that enables motion at the normal scales (Joy buttons index)',
                      _BUTTON),
    'enable_turbo_button': ('button that enables motion at the turbo scales, even without the '
                            'enable button; -1 = none', _BUTTON),
    'require_enable_button': ('false: move at the normal scales without holding the enable '
                              'button', None),
    'axis_linear.x': ('axis for x_dot* (Joy axes index; -1 = unused)', _AXIS),
    'scale_linear.x': ('x_dot* at full deflection [m/s] (negative inverts the axis)',
                       (-5.0, 5.0)),
    'scale_linear_turbo.x': ('x_dot* at full deflection with turbo [m/s]', (-5.0, 5.0)),
    'axis_angular.yaw': ('axis for yaw rate* (Joy axes index; -1 = unused)', _AXIS),
    'scale_angular.yaw': ('yaw rate* at full deflection [rad/s], positive turns left',
                          (-10.0, 10.0)),
    'scale_angular_turbo.yaw': ('yaw rate* at full deflection with turbo [rad/s]',
                                (-10.0, 10.0)),
    'inverted_reverse': ('negate the yaw rate while x_dot* < 0 (turn like a reversing car)',
                         None),
    'deadzone': ('axis deadzone, fraction of full deflection; rescaled so the command is '
                 'continuous at its edge', (0.0, 0.95)),
    'joy_timeout': ('joystick silence after which motion stops (one zero command) [s]',
                    (0.01, 10.0)),
    'max_linear_accel': ('acceleration limit of x_dot* [m/s^2]; 0 = unlimited', (0.0, 50.0)),
    'max_angular_accel': ('acceleration limit of yaw rate* [rad/s^2]; 0 = unlimited',
                          (0.0, 200.0)),
    'max_linear_jerk': ('jerk limit of x_dot* [m/s^3]; 0 = unlimited', (0.0, 1000.0)),
    'max_angular_jerk': ('jerk limit of yaw rate* [rad/s^3]; 0 = unlimited', (0.0, 5000.0)),
}
# Node-only parameters: name -> (default, description, range or None, read_only).
_NODE_PARAMS = {
    'frame': ('base_link', 'header.frame_id of the TwistStamped commands', None, False),
    'publish_stamped_twist': (True, 'publish geometry_msgs/TwistStamped (false: Twist)', None,
                              True),
    'publish_rate': (50.0, 'rate of cmd_vel while motion is enabled [Hz]', (1.0, 500.0), True),
}


def field_name(ros_name: str) -> str:
    """Return the TeleopConfig field of a ROS parameter ('axis_linear.x' -> 'axis_linear_x')."""
    return ros_name.replace('.', '_')


def _descriptor(description, limits, default, read_only=False) -> ParameterDescriptor:
    d = ParameterDescriptor(description=description, read_only=read_only)
    if limits is not None and isinstance(default, int) and not isinstance(default, bool):
        d.integer_range = [IntegerRange(from_value=limits[0], to_value=limits[1], step=1)]
    elif limits is not None and isinstance(default, float):
        d.floating_point_range = [FloatingPointRange(from_value=limits[0], to_value=limits[1])]
    return d


class TeleopNode(Node):
    """Joy -> cmd_vel with teleop_twist_joy's parameters, deadzone, timeout and rate limits."""

    def __init__(self, **kwargs):
        super().__init__('teleop_node', **kwargs)
        defaults = asdict(TeleopConfig())
        names = {field_name(n) for n in _CORE_PARAMS}
        assert names == {f.name for f in fields(TeleopConfig)}, 'parameter table out of date'
        for name, (description, limits) in _CORE_PARAMS.items():
            default = defaults[field_name(name)]
            self.declare_parameter(name, default, _descriptor(description, limits, default))
        for name, (default, description, limits, read_only) in _NODE_PARAMS.items():
            self.declare_parameter(name, default,
                                   _descriptor(description, limits, default, read_only))

        cfg = TeleopConfig(**{field_name(n): self.get_parameter(n).value for n in _CORE_PARAMS})
        problems = cfg.problems()
        if problems:
            raise ValueError('invalid parameters: ' + '; '.join(problems))
        self._lock = threading.Lock()
        self._teleop = Teleop(cfg)
        self._frame = self.get_parameter('frame').value
        self._stamped = self.get_parameter('publish_stamped_twist').value
        rate = self.get_parameter('publish_rate').value
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self._pub = self.create_publisher(TwistStamped if self._stamped else Twist, 'cmd_vel', 10)
        self.create_subscription(Joy, 'joy', self._on_joy, qos_profile_sensor_data)
        self.create_timer(1.0 / rate, self._tick)
        self.get_logger().info(
            'enable button %d%s, turbo button %d; x_dot* on axis %d (%.2f / %.2f m/s), '
            'yaw rate* on axis %d (%.2f / %.2f rad/s); cmd_vel at %.0f Hz as %s' % (
                cfg.enable_button, '' if cfg.require_enable_button else ' (not required)',
                cfg.enable_turbo_button, cfg.axis_linear_x, cfg.scale_linear_x,
                cfg.scale_linear_turbo_x, cfg.axis_angular_yaw, cfg.scale_angular_yaw,
                cfg.scale_angular_turbo_yaw, rate, 'TwistStamped' if self._stamped else 'Twist'))

    def _on_joy(self, msg: Joy) -> None:
        with self._lock:
            self._teleop.on_joy(msg.axes, msg.buttons, time.monotonic())

    def _tick(self) -> None:
        with self._lock:
            cmd = self._teleop.tick(time.monotonic())
        if cmd is not None:
            self._publish(*cmd)

    def stop(self) -> None:
        """Send the one zero command if the robot was last told to move (on shutdown)."""
        with self._lock:
            cmd = self._teleop.stop()
        if cmd is not None and self.context.ok():
            self._publish(*cmd)
            # The process exits next: give the reliable publisher a moment to have the last
            # word delivered (without this it was lost about one exit in three).
            self._pub.wait_for_all_acked(Duration(seconds=0.5))

    def _publish(self, x_dot: float, yaw_rate: float) -> None:
        twist = Twist()
        twist.linear.x = float(x_dot)
        twist.angular.z = float(yaw_rate)
        if not self._stamped:
            self._pub.publish(twist)
            return
        msg = TwistStamped()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self._frame
        msg.twist = twist
        self._pub.publish(msg)

    def _on_set_parameters(self, params) -> SetParametersResult:
        """Validate a change as a whole (rclpy has checked types and ranges); apply it if good."""
        core = {}
        frame = None
        for p in params:
            if p.name in _CORE_PARAMS:
                core[field_name(p.name)] = p.value
            elif p.name == 'frame':
                frame = p.value
        if not core:
            if frame is not None:
                self._frame = frame
            return SetParametersResult(successful=True)
        with self._lock:
            cfg = replace(self._teleop.cfg, **core)
            problems = cfg.problems()
            if problems:
                return SetParametersResult(successful=False, reason='; '.join(problems))
            self._teleop.configure(cfg)
            if frame is not None:
                self._frame = frame
        return SetParametersResult(successful=True)


def main(args=None) -> int:
    """Run teleop_node until SIGINT/SIGTERM; send the one zero command if moving, then exit."""
    # Own signal handlers: rclpy's would shut the context down before the final zero is sent.
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    node = None
    rc = 0
    try:
        node = TeleopNode()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as exc:  # noqa: B902 -- start-up errors: one clear line, no traceback
        print('teleop_node: %s: %s' % (type(exc).__name__, exc), file=sys.stderr)
        rc = 1
    finally:
        if node is not None:
            node.stop()
            node.destroy_node()
        rclpy.try_shutdown()
    return rc


if __name__ == '__main__':
    sys.exit(main())
