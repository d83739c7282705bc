"""
balance_node's TF: base_footprint -> base_link always, odom -> base_footprint when asked.

The transforms themselves are core/frames.py's; this module only puts them into
geometry_msgs/TransformStamped on /tf (as ros2_controllers' diff_drive_controller does with
``enable_odom_tf``). Where tf2_msgs is not installed (it is a run-time key of the robot's
install, but not of every test environment) the node says so once and goes on without TF.
"""
from geometry_msgs.msg import TransformStamped
from rclpy.qos import QoSDurabilityPolicy, QoSHistoryPolicy, QoSProfile

from ..core.config import BalanceConfig
from ..core.frames import base_footprint_to_base_link, odom_to_base_footprint
from ..core.tick_io import STATE_FIELDS

_THETA, _D_HAT, _L = (STATE_FIELDS.index(n) for n in ('theta', 'd_hat', 'l'))


class TfPublisher:
    """Publishes the robot's two transforms from the loop's state (see the module docstring)."""

    def __init__(self, node, cfg: BalanceConfig, create=None):
        """
        Make the /tf publisher (with tf2_msgs installed).

        create(msg_type, topic, qos): makes it (nodes/state_publisher.py's counts its
        subscriptions); None: ``node.create_publisher``.
        """
        self.node = node
        pub, leg = cfg.publish, cfg.leg
        self.odom_tf = pub.enable_odom_tf
        self.wheel_radius = cfg.model.wheel_radius
        self.com = (leg.com_x, leg.com_height)
        self._frames = (pub.odom_frame_id, pub.footprint_frame_id, pub.base_frame_id)
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError:
            node.get_logger().warning('tf2_msgs is not installed: no TF published (install '
                                      'ros-jazzy-tf2-msgs)')
            self._pub = None
            return
        odom, footprint, base = self._frames
        # Made once and refilled (as nodes/state_publisher.py's messages): the transforms'
        # frames never change, and building the messages cost more than publishing them.
        self._base = _stamped(footprint, base)
        self._odom = _stamped(odom, footprint) if self.odom_tf else None
        self._msg = TFMessage(transforms=[t for t in (self._base, self._odom) if t is not None])
        qos = QoSProfile(depth=100, history=QoSHistoryPolicy.KEEP_LAST,
                         durability=QoSDurabilityPolicy.VOLATILE)
        self._pub = (create or node.create_publisher)(TFMessage, '/tf', qos)

    def publish(self, stamp, state, pose) -> None:
        """Publish for ~/state values ``state`` and the odometry ``pose`` (x, y, yaw)."""
        if self._pub is None:
            return
        theta = state[_THETA] - state[_D_HAT]   # the body's pitch: the IMU's less its offset
        l = state[_L]
        if not (theta == theta and l == l):
            return
        _fill(self._base, stamp, base_footprint_to_base_link(
            theta, self.com[0], self.com[1] - l, self.wheel_radius))
        if self._odom is not None:
            _fill(self._odom, stamp, odom_to_base_footprint(*pose))
        self._pub.publish(self._msg)


def _stamped(parent: str, child: str) -> TransformStamped:
    t = TransformStamped()
    t.header.frame_id, t.child_frame_id = parent, child
    return t


def _fill(t: TransformStamped, stamp, transform) -> None:
    (x, y, z), (qx, qy, qz, qw) = transform
    t.header.stamp = stamp
    tr, r = t.transform.translation, t.transform.rotation
    tr.x, tr.y, tr.z = x, y, z
    r.x, r.y, r.z, r.w = qx, qy, qz, qw
