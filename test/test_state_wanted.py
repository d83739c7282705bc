"""
The state frame only where someone reads it.

The publishers' subscription counts (nodes/state_publisher.py) decide which publication flags
the control process builds and sends (control_link.WANTED).
"""
import threading
import time
import types
import uuid

from can.interfaces.virtual import VirtualBus

from wheelleg_balance.core.config import BalanceConfig
from wheelleg_balance.core.tick_io import FLAGS, FRAME_FIELDS, PUBLISH_ODOM, PUBLISH_STATE
from wheelleg_balance.nodes import control_link as L
from wheelleg_balance.nodes.control_runner import ControlRunner
from wheelleg_balance.nodes.state_publisher import StatePublisher
from wheelleg_balance.validation.faults.rig import wait_for


def _frames(ros: L.Link, seconds: float):
    """Return the flags of the state frames the ROS end receives in ``seconds``."""
    flags = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        ros.wait_readable(0.05)
        flags += [int(p[0][FLAGS]) for tag, p in ros.receive() if tag == L.STATE]
    return flags


def test_the_runner_sends_only_the_publications_that_are_wanted():
    ros_end, loop_end = L.socket_pair()
    runner = ControlRunner(BalanceConfig(), VirtualBus(channel='wlb-%s' % uuid.uuid4().hex),
                           L.Link(loop_end), realtime_options=False)
    ros = L.Link(ros_end)
    thread = threading.Thread(target=runner.run, daemon=True)
    thread.start()
    try:
        assert wait_for(lambda: runner.ticks > 0, 5.0)
        # Until told otherwise: every publication (100 Hz state, 50 Hz odometry by default).
        flags = _frames(ros, 0.3)
        assert any(f & PUBLISH_STATE for f in flags) and any(f & PUBLISH_ODOM for f in flags)
        ros.send_object(L.WANTED, 0)
        _frames(ros, 0.05)   # what was on its way
        assert _frames(ros, 0.3) == []
        ros.send_object(L.WANTED, PUBLISH_ODOM)
        _frames(ros, 0.05)
        flags = _frames(ros, 0.3)
        assert flags and all(f == PUBLISH_ODOM for f in flags)
    finally:
        runner.stop()
        thread.join(5.0)
        ros.close()
    assert not thread.is_alive()


class _Publisher:
    def __init__(self, topic, events):
        self.topic, self.events, self.published = topic, events, []

    def publish(self, msg):
        self.published.append(msg)

    def get_subscription_count(self):
        return 0


class _Node:
    """What StatePublisher uses of an rclpy node; ``unsupported``: no matched events."""

    def __init__(self, unsupported=False):
        self.publishers = {}
        self.unsupported = unsupported
        self.logger = types.SimpleNamespace(warning=lambda text: None)

    def get_logger(self):
        return self.logger

    def get_clock(self):
        # The ROS clock the tick's times are taken to (state_publisher._tick_stamp).
        return types.SimpleNamespace(
            now=lambda: types.SimpleNamespace(nanoseconds=time.time_ns()))

    def create_publisher(self, msg_type, topic, qos, event_callbacks=None):
        if self.unsupported and event_callbacks.matched is not None:
            from rclpy.event_handler import UnsupportedEventTypeError
            raise UnsupportedEventTypeError(0)
        self.publishers[topic] = _Publisher(topic, event_callbacks)
        return self.publishers[topic]


def _frame(flags):
    values = [0.0] * len(FRAME_FIELDS)
    values[FLAGS] = float(flags)
    return values


def test_the_publisher_counts_subscriptions_and_publishes_only_to_them():
    node, wanted = _Node(), []
    pub = StatePublisher(node, BalanceConfig(), wanted.append)
    pub.report_wanted()
    assert wanted == [0]   # nobody subscribes yet
    joints = [0.0] * 3 * len(pub._joint_msg.name)
    pub.publish(_frame(PUBLISH_STATE | PUBLISH_ODOM), joints)
    assert all(p.published == [] for p in node.publishers.values())

    def matched(topic, count):
        node.publishers[topic].events.matched(types.SimpleNamespace(current_count=count))
    matched('odom', 1)
    assert wanted == [0, PUBLISH_ODOM]
    matched('joint_states', 2)   # the joints come with the state frame
    assert wanted == [0, PUBLISH_ODOM, PUBLISH_ODOM | PUBLISH_STATE]
    matched('odom', 1)           # no change: nothing sent
    assert len(wanted) == 3
    pub.publish(_frame(PUBLISH_STATE | PUBLISH_ODOM), joints)
    assert [len(node.publishers[t].published) for t in ('~/state', 'odom', 'joint_states')] \
        == [0, 1, 1]
    matched('odom', 0)
    matched('joint_states', 0)
    assert wanted[-1] == 0


def test_without_matched_events_everything_is_published():
    node, wanted = _Node(unsupported=True), []
    pub = StatePublisher(node, BalanceConfig(), wanted.append)
    pub.report_wanted()
    assert wanted == [PUBLISH_STATE | PUBLISH_ODOM]
    pub.publish(_frame(PUBLISH_STATE | PUBLISH_ODOM), ())
    assert [len(node.publishers[t].published) for t in ('~/state', 'odom')] == [1, 1]
