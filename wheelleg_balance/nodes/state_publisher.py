"""
balance_node's publishers of what the loop sends back: ~/state, odom, joint_states and TF.

Each state frame (core/tick_io.py) carries its publication flags: the ~/state values and TF
(base_footprint -> base_link, and odom -> base_footprint with ``enable_odom_tf``:
nodes/transforms.py) when ``PUBLISH_STATE`` is set, the odometry when ``PUBLISH_ODOM`` is; the
joints' values come with the state. Messages are made once and refilled.

A topic without a subscription is not published, and the control process is told which
publications have any (``wanted``, sent as control_link.WANTED), so that it builds and sends no
frame nobody reads: the ROS side wakes for nothing, and rclpy's publish with its clock read
costs some 0.3 ms a frame here after a sleep, when its code is out of the caches
(docs/benchmarks.md). The counts follow each publisher's "matched" event; an rmw without that
event counts as subscribed, always.

Every message of a frame is stamped with the ROS time of its tick, and ~/state's ``time`` is
that stamp [s]: the tick's time on the loop's clock (core/tick_io.py) taken to ROS time, the
offset between the clocks read at publication (CLOCK_MONOTONIC against the node's clock); in
lockstep (``clock_source: imu_stamp``) the loop's clock is already the simulator's ROS
stamps. So a recording of a phase is on the ticks' times, which a lagging simulator or a busy
ROS side does not stretch (identification/live.py).
"""
import math
import time
from typing import Callable, Optional

from nav_msgs.msg import Odometry
from rclpy.time import Time
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from . import lean
from .transforms import TfPublisher
from ..core.config import BalanceConfig
from ..core.sensing import joint_names
from ..core.tick_io import FLAGS, N_STATE, ODOM, PUBLISH_ODOM, PUBLISH_STATE, STATE_FIELDS, \
    TIME


class StatePublisher:
    """The publishers of a balance_node (see the module docstring)."""

    def __init__(self, node, cfg: BalanceConfig,
                 on_wanted: Optional[Callable[[int], None]] = None):
        """
        Make the publishers.

        on_wanted(flags): called (from the executor) when the publication flags that have
        subscriptions change (``wanted``).
        """
        self._node = node
        self._on_wanted = on_wanted
        #: Subscriptions matched per publisher: 'state', 'odom', 'joints', 'tf' (math.inf: the
        #: rmw does not say).
        self.matched = {}
        self._wanted_sent: Optional[int] = None

        def publisher(msg_type, topic, key):
            return self._create(msg_type, topic, 10, key)
        self._state_msg = Float64MultiArray()
        self._state_msg.layout.dim = [MultiArrayDimension(
            label=','.join(STATE_FIELDS), size=N_STATE, stride=N_STATE)]
        self._state_pub = publisher(Float64MultiArray, '~/state', 'state')
        self._odom_msg = _odometry(cfg)
        self._odom_pub = publisher(Odometry, 'odom', 'odom')
        self._joint_msg = JointState(name=joint_names(cfg))
        self._joint_pub = publisher(JointState, 'joint_states', 'joints')
        self.matched.setdefault('tf', 0)   # no tf2_msgs: no /tf publisher
        self._tf = TfPublisher(node, cfg, lambda msg_type, topic, qos: self._create(
            msg_type, topic, qos, 'tf'))
        self._clock = node.get_clock()
        self._on_stamps = cfg.loop.clock_source == 'imu_stamp'

    def _create(self, msg_type, topic: str, qos, key: str):
        """Create a publisher whose subscriptions are counted in ``matched[key]``."""
        from rclpy.event_handler import UnsupportedEventTypeError

        def on_matched(status):
            self.matched[key] = status.current_count
            self.report_wanted()
        try:
            pub = self._node.create_publisher(
                msg_type, topic, qos, event_callbacks=lean.publisher_events(on_matched))
        except UnsupportedEventTypeError:
            self.matched[key] = math.inf
            return self._node.create_publisher(msg_type, topic, qos,
                                               event_callbacks=lean.publisher_events())
        self.matched[key] = pub.get_subscription_count()
        return pub

    def wanted(self) -> int:
        """Return the state frame's flags (PUBLISH_STATE, PUBLISH_ODOM) someone subscribes to."""
        m = self.matched
        return (PUBLISH_STATE if m['state'] or m['joints'] or m['tf'] else 0) | (
            PUBLISH_ODOM if m['odom'] else 0)

    def report_wanted(self) -> None:
        """Call on_wanted with ``wanted()`` if it changed since the last call."""
        wanted = self.wanted()
        if wanted != self._wanted_sent and self._on_wanted is not None:
            self._wanted_sent = wanted
            self._on_wanted(wanted)

    def _tick_stamp(self, tick: float) -> float:
        """Return the ROS time [s] of a tick at ``tick`` on the loop's clock."""
        if self._on_stamps and math.isfinite(tick):
            return tick
        now = self._clock.now().nanoseconds * 1e-9
        return now - (time.monotonic() - tick) if math.isfinite(tick) else now

    def publish(self, values, joints) -> None:
        """Publish a state frame (an array('d'): float64[] fields take it unchecked)."""
        values[TIME] = t = self._tick_stamp(values[TIME])
        stamp = Time(nanoseconds=int(round(t * 1e9))).to_msg()
        flags = int(values[FLAGS])
        x, y, yaw, x_dot, yaw_rate = values[ODOM]
        m = self.matched
        if flags & PUBLISH_STATE:
            if m['state']:
                self._state_msg.data = values[:N_STATE]
                self._state_pub.publish(self._state_msg)
            if m['tf']:
                self._tf.publish(stamp, values, (x, y, yaw))
        if flags & PUBLISH_ODOM and m['odom']:
            msg = self._odom_msg
            msg.header.stamp = stamp
            msg.pose.pose.position.x, msg.pose.pose.position.y = x, y
            msg.pose.pose.orientation.z = math.sin(0.5 * yaw)
            msg.pose.pose.orientation.w = math.cos(0.5 * yaw)
            msg.twist.twist.linear.x, msg.twist.twist.angular.z = x_dot, yaw_rate
            self._odom_pub.publish(msg)
        if joints and m['joints']:
            msg, n = self._joint_msg, len(self._joint_msg.name)
            msg.header.stamp = stamp
            msg.position, msg.velocity, msg.effort = joints[0:n], joints[n:2 * n], joints[2 * n:]
            self._joint_pub.publish(msg)


def _odometry(cfg: BalanceConfig) -> Odometry:
    pub = cfg.publish
    msg = Odometry()
    msg.header.frame_id = pub.odom_frame_id
    msg.child_frame_id = pub.footprint_frame_id   # the odometry's pose is the footprint's
    for k, c in enumerate(pub.pose_covariance_diagonal):
        msg.pose.covariance[7 * k] = c
    for k, c in enumerate(pub.twist_covariance_diagonal):
        msg.twist.covariance[7 * k] = c
    return msg
