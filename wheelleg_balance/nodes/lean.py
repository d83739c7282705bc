"""
rclpy entities without the default QoS event handlers.

rclpy gives every subscription and publisher default handlers for the "incompatible QoS" and
"incompatible type" events. Each is a waitable that a SingleThreadedExecutor takes out, checks
and adds back to its wait set at every wake-up, whether it fires or not. A process that wakes
500 times a second on a sensor topic pays for all of them each time: main_job's recorder (13
subscriptions, the IMU at 500 Hz) used 28 to 46 % of a core with them and 18 to 19 % without
(docs/benchmarks.md, 2026-12-02). The events only log a warning that ``ros2 topic info
--verbose`` also shows; the nodes that wake often go without them.

rclpy is imported when the callbacks are made, not with this module: the sensor intake and the
control process import it before rclpy may be loaded (nodes/dds.py must come first; the
control process never loads rclpy).
"""


def subscription_events():
    """Return event callbacks (SubscriptionEventCallbacks) without the default handlers."""
    from rclpy.event_handler import SubscriptionEventCallbacks
    return SubscriptionEventCallbacks(use_default_callbacks=False)


def publisher_events(matched=None):
    """
    Return event callbacks (PublisherEventCallbacks) without the default handlers.

    matched: called with the rmw_matched_status_t (``current_count``: the subscriptions now
    matched) when a subscription comes or goes.
    """
    from rclpy.event_handler import PublisherEventCallbacks
    return PublisherEventCallbacks(matched=matched, use_default_callbacks=False)
