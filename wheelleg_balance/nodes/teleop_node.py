"""
teleop_node: joystick (sensor_msgs/Joy on ``joy``) -> ``cmd_vel``, ``cmd_height``, arming.

A thin shell around core/teleop.py (docs/interface.md): the subscription stores each sample,
a timer at ``publish_rate`` publishes the rate-limited command while motion is enabled, then one
zero command when it is released or the joystick has been silent for ``joy_timeout``. The same
timer publishes the height target on ``cmd_height`` (std_msgs/Float64 [m]) when the pad changes
it, and calls ``balance_node/arm`` (std_srvs/SetBool; remap it for another name) with true or
false when the arm or disarm combination has been held with the deadman; the answer is logged.
``cmd_vel`` is geometry_msgs/TwistStamped (header.stamp = now, frame_id = ``frame``) or Twist
when ``publish_stamped_twist`` is false: linear.x = x_dot* [m/s], angular.z = yaw rate* [rad/s],
positive turns left (REP 103).

Parameters (``TeleopNodeConfig``, core/schema.py) carry descriptors with ranges (see
``ros2 param describe /teleop_node <name>``);
``publish_rate`` and ``publish_stamped_twist`` are read-only, every other one can change live:
a bad value is rejected with a reason and nothing changes. config/teleop_xbox.yaml and
config/teleop_ps4.yaml hold the values for the pads under the joy package's SDL mapping.
"""
from dataclasses import dataclass
import signal
import sys
import threading

from geometry_msgs.msg import Twist, TwistStamped
import rclpy
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import Joy
from std_msgs.msg import Float64
from std_srvs.srv import SetBool

from . import clock
from .params import load, ParameterGuard
from ..core.schema import param, section
from ..core.teleop import Teleop, TeleopConfig


@dataclass
class TeleopNodeConfig:
    """teleop_node's parameters: the core's (core/teleop.py) and the node's own."""

    teleop: TeleopConfig = section(TeleopConfig)
    frame: str = param('base_link', 'header.frame_id of the TwistStamped commands')
    publish_stamped_twist: bool = param(True, 'publish geometry_msgs/TwistStamped (false: '
                                        'Twist)', read_only=True)
    publish_rate: float = param(50.0, 'rate of cmd_vel while motion is enabled [Hz]', 1.0,
                                500.0, read_only=True)


class TeleopNode(Node):
    """Joy -> cmd_vel with teleop_twist_joy's parameters, deadzone, timeout and rate limits."""

    def __init__(self, **kwargs):
        super().__init__('teleop_node', **kwargs)
        cfg = load(self, TeleopNodeConfig)   # ValueError with every problem
        self._lock = threading.Lock()
        self.teleop = Teleop(cfg.teleop)
        self.config = cfg
        self._now = clock.seconds(self)   # simulated seconds under use_sim_time
        self.add_on_set_parameters_callback(ParameterGuard(cfg, self._apply))
        self._pub = self.create_publisher(TwistStamped if cfg.publish_stamped_twist else Twist,
                                          'cmd_vel', 10)
        self._height_pub = self.create_publisher(Float64, 'cmd_height', 10)
        self._arm_client = self.create_client(SetBool, 'balance_node/arm')
        self.create_subscription(Joy, 'joy', self._on_joy, qos_profile_sensor_data)
        self.create_timer(1.0 / cfg.publish_rate, self._tick)
        t = cfg.teleop
        self.get_logger().info(
            'enable button %d%s, turbo button %d; x_dot* on axis %d (%.2f / %.2f m/s), '
            'yaw rate* on axis %d (%.2f / %.2f rad/s); cmd_vel at %.0f Hz as %s; height: '
            'buttons %s -> %s m, axis %d (%.2f m/s); arm %s, disarm %s with the enable '
            'button held %.1f s' % (
                t.enable_button, '' if t.require_enable_button else ' (not required)',
                t.enable_turbo_button, t.axis_linear_x, t.scale_linear_x,
                t.scale_linear_turbo_x, t.axis_angular_yaw, t.scale_angular_yaw,
                t.scale_angular_turbo_yaw, cfg.publish_rate,
                'TwistStamped' if cfg.publish_stamped_twist else 'Twist', t.height_buttons,
                t.heights, t.axis_height, t.scale_height, t.arm_buttons, t.disarm_buttons,
                t.arm_hold_time))

    def _on_joy(self, msg: Joy) -> None:
        with self._lock:
            self.teleop.on_joy(msg.axes, msg.buttons, self._now())

    def _tick(self) -> None:
        with self._lock:
            cmd = self.teleop.tick(self._now())
            height = self.teleop.take_height()
            arm = self.teleop.take_arm()
        if cmd is not None:
            self._publish(*cmd)
        if height is not None:
            self._height_pub.publish(Float64(data=float(height)))
        if arm is not None:
            self._request_arm(arm)

    def _request_arm(self, on: bool) -> None:
        what = 'arm' if on else 'disarm'
        if not self._arm_client.service_is_ready():
            self.get_logger().warning('%s: no balance_node/arm service' % what)
            return
        self.get_logger().info('%s requested from the pad' % what)
        future = self._arm_client.call_async(SetBool.Request(data=on))

        def answered(f):
            r = f.result()
            if r is not None:
                log = self.get_logger().info if r.success else self.get_logger().warning
                log('%s: %s' % (what, r.message))
        future.add_done_callback(answered)

    def stop(self) -> None:
        """Send the one zero command if the robot was last told to move (on shutdown)."""
        with self._lock:
            cmd = self.teleop.stop()
        if cmd is not None and self.context.ok():
            self._publish(*cmd)
            # The process exits next: give the reliable publisher a moment to have the last
            # word delivered (without this it was lost about one exit in three).
            self._pub.wait_for_all_acked(Duration(seconds=0.5))

    def _publish(self, x_dot: float, yaw_rate: float) -> None:
        twist = Twist()
        twist.linear.x = float(x_dot)
        twist.angular.z = float(yaw_rate)
        if not self.config.publish_stamped_twist:
            self._pub.publish(twist)
            return
        msg = TwistStamped()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.config.frame
        msg.twist = twist
        self._pub.publish(msg)

    def _apply(self, changes, new_config: TeleopNodeConfig) -> None:
        """Apply an accepted change (ParameterGuard checked it as a whole) at once."""
        with self._lock:
            self.config = new_config
            self.teleop.configure(new_config.teleop)


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
