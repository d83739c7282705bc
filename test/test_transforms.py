"""
balance_node's TF publisher (nodes/transforms.py) without a running node.

tf2_msgs is a run-time key of the robot's install but is not installed here (the PyPI ROS
wheels lack it): with the import blocked, the publisher must say so once and publish nothing;
with a stand-in tf2_msgs.msg.TFMessage it must publish base_footprint -> base_link (the body's
pitch theta~ - d_hat, its height from l) and odom -> base_footprint only with enable_odom_tf.
"""
import math
import sys
import types

import pytest

from wheelleg_balance.core.balance_loop import STATE_FIELDS
from wheelleg_balance.core.config import BalanceConfig
from wheelleg_balance.core.schema import with_changes
from wheelleg_balance.nodes.transforms import TfPublisher


class Logger:
    def __init__(self):
        self.warnings = []

    def warning(self, text):
        self.warnings.append(text)


class Node:
    """What TfPublisher uses of an rclpy node."""

    def __init__(self):
        self.logger = Logger()
        self.published = []

    def get_logger(self):
        return self.logger

    def create_publisher(self, msg_type, topic, qos):
        self.topic = topic
        return types.SimpleNamespace(publish=self.published.append)


def _state(theta, d_hat, l):
    s = [0.0] * len(STATE_FIELDS)
    s[STATE_FIELDS.index('theta')] = theta
    s[STATE_FIELDS.index('d_hat')] = d_hat
    s[STATE_FIELDS.index('l')] = l
    return s


def test_without_tf2_msgs_it_says_so_once_and_publishes_nothing(monkeypatch):
    monkeypatch.setitem(sys.modules, 'tf2_msgs', None)   # import fails as if not installed
    monkeypatch.setitem(sys.modules, 'tf2_msgs.msg', None)
    node = Node()
    tf = TfPublisher(node, BalanceConfig())
    for _ in range(3):
        tf.publish(None, _state(0.1, 0.0, 0.4), (0.0, 0.0, 0.0))
    assert len(node.logger.warnings) == 1 and 'tf2_msgs' in node.logger.warnings[0]
    assert node.published == []


@pytest.fixture
def fake_tf2(monkeypatch):
    msg = types.ModuleType('tf2_msgs.msg')

    class TFMessage:
        def __init__(self, transforms=()):
            self.transforms = list(transforms)
    msg.TFMessage = TFMessage
    pkg = types.ModuleType('tf2_msgs')
    pkg.msg = msg
    monkeypatch.setitem(sys.modules, 'tf2_msgs', pkg)
    monkeypatch.setitem(sys.modules, 'tf2_msgs.msg', msg)


@pytest.mark.parametrize('odom_tf', [True, False])
def test_the_transforms_and_their_frames(fake_tf2, odom_tf):
    node = Node()
    cfg = with_changes(BalanceConfig(), {'enable_odom_tf': odom_tf})
    tf = TfPublisher(node, cfg)
    assert node.topic == '/tf' and node.logger.warnings == []
    theta, d_hat = math.radians(12.0), math.radians(2.0)
    tf.publish('stamp', _state(theta, d_hat, 0.5), (1.0, 2.0, 0.5))
    tf.publish('stamp', _state(math.nan, 0.0, 0.5), (1.0, 2.0, 0.5))   # no attitude: nothing
    assert len(node.published) == 1
    ts = node.published[0].transforms
    assert [(t.header.frame_id, t.child_frame_id) for t in ts] == \
        [('base_footprint', 'base_link')] + ([('odom', 'base_footprint')] if odom_tf else [])
    body = ts[0].transform
    # The body's pitch, the IMU's offset removed: a rotation by 10 deg about y.
    assert 2.0 * math.asin(body.rotation.y) == pytest.approx(math.radians(10.0))
    # base_link above the floor: r_w plus the axle's depth below the hips, cos-projected.
    axle_z = cfg.leg.com_height - 0.5
    assert body.translation.z == pytest.approx(
        0.1 + math.sin(math.radians(10.0)) * cfg.leg.com_x - math.cos(math.radians(10.0)) * axle_z)
    if odom_tf:
        odom = ts[1].transform
        assert (odom.translation.x, odom.translation.y) == (1.0, 2.0)
        assert 2.0 * math.atan2(odom.rotation.z, odom.rotation.w) == pytest.approx(0.5)
