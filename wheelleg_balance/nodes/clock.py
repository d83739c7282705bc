"""
The seconds a node times its own work by: CLOCK_MONOTONIC, or ROS time under ``use_sim_time``.

A node that rate-limits or times out on its own (teleop_node, the validation tools' scripted
joystick) keeps the monotonic clock on a robot, where ROS time is the system clock and may jump.
With ``use_sim_time`` (rclpy's standard parameter: ROS time follows ``/clock``, which sim_node
publishes in lockstep) it follows the simulation instead, so its limits and scripts hold in
simulated seconds however fast the simulation runs.
"""
import time
from typing import Callable

from rclpy.node import Node


def seconds(node: Node) -> Callable[[], float]:
    """Return the node's clock in seconds: ROS time with use_sim_time, else monotonic."""
    if node.get_parameter('use_sim_time').value:
        clock = node.get_clock()
        return lambda: clock.now().nanoseconds * 1e-9
    return time.monotonic
