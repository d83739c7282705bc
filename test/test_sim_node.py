"""
sim_node in-process: real rclpy DDS on localhost and a python-can virtual bus.

One node serves all tests (module fixture): the rates are measured over one second of wall
clock, and the CAN tests talk to the motors like balance_node does.
"""
import os
import sys
import threading
import time

import can
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray

from wheelleg_balance.core.protocols.mit import MitProtocol
from wheelleg_balance.nodes.sim_node import SimNode
# The polling helper of all the ROS tests (test/conftest.py says why it lives there).
from wheelleg_balance.tools.fault_suite import wait_for

pytestmark = pytest.mark.ros

CHANNEL = 'test_sim_node_%d' % os.getpid()
PROTOCOL = MitProtocol()


class Listener:
    """A subscriber node spun in a background thread, keeping the newest messages."""

    def __init__(self, context):
        self.node = rclpy.create_node('sim_node_listener', context=context)
        self.imu_times = []
        self.joint_times = []
        self.joints = None
        self.ground_truth = None
        # Best effort like the publisher; a deep queue so that a busy executor drops nothing.
        qos = QoSProfile(depth=500, reliability=ReliabilityPolicy.BEST_EFFORT)
        self.node.create_subscription(Imu, 'imu', self._imu, qos)
        self.node.create_subscription(JointState, 'joint_states', self._joint, qos)
        self.node.create_subscription(Float64MultiArray, 'sim_node/ground_truth',
                                      self._gt, 10)

    def _imu(self, msg):
        self.imu_times.append(time.monotonic())

    def _joint(self, msg):
        self.joint_times.append(time.monotonic())
        self.joints = msg

    def _gt(self, msg):
        self.ground_truth = msg


@pytest.fixture(scope='module')
def system(context):
    # The listener shares this interpreter with the node (in its own process, sim_node's loop
    # thread has the GIL to itself): hand the GIL over sooner than the default 5 ms so the
    # loop thread is not held up by the listener's callbacks.
    switch_interval = sys.getswitchinterval()
    sys.setswitchinterval(0.0005)
    node = SimNode(context=context, parameter_overrides=[
        Parameter('can.interface', value='virtual'),
        Parameter('can.channel', value=CHANNEL),
        Parameter('ground_truth_rate', value=50.0),
    ])
    listener = Listener(context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.add_node(listener.node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    node.start()
    bus = can.Bus(interface='virtual', channel=CHANNEL)
    try:
        yield node, listener, bus
    finally:
        bus.shutdown()
        node.stop()
        executor.shutdown()
        listener.node.destroy_node()
        node.destroy_node()
        spinner.join(timeout=2.0)
        sys.setswitchinterval(switch_interval)


def _exchange(bus, frame, timeout=0.5):
    """Send one frame and return the decoded reply of that motor (or None)."""
    bus.send(can.Message(arbitration_id=frame.arbitration_id, data=frame.data,
                         is_extended_id=False))
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        msg = bus.recv(timeout=0.05)
        if msg is None:
            continue
        fb = PROTOCOL.decode_feedback(
            type(frame)(msg.arbitration_id, bytes(msg.data), msg.is_extended_id))
        if fb is not None and fb.motor_id == frame.arbitration_id:
            return fb
    return None


def test_publishes_imu_and_joint_states_at_500_hz(system):
    node, listener, _ = system
    assert wait_for(lambda: len(listener.imu_times) > 50 and len(listener.joint_times) > 50,
                    5.0)
    time.sleep(0.3)  # past discovery and start-up
    t0 = time.monotonic()
    k0 = node.ticks
    time.sleep(1.0)
    t1 = time.monotonic()
    imu_rate = sum(t0 <= t < t1 for t in list(listener.imu_times)) / (t1 - t0)
    joint_rate = sum(t0 <= t < t1 for t in list(listener.joint_times)) / (t1 - t0)
    ticks = node.ticks - k0
    assert imu_rate >= 450.0, (imu_rate, ticks, node.late_ticks, node.resyncs)
    assert joint_rate >= 450.0, (joint_rate, ticks, node.late_ticks, node.resyncs)
    js = listener.joints
    assert js.name[:2] == ['left_wheel_joint', 'right_wheel_joint']
    assert len(js.name) == len(js.position) == len(js.velocity) == len(js.effort) == 6
    gt = listener.ground_truth
    assert gt is not None
    labels = gt.layout.dim[0].label.split(',')
    theta = gt.data[labels.index('theta')]
    assert 0.55 < theta < 0.70  # resting on the tail at about 36 deg


def test_torque_only_after_enter(system):
    node, listener, bus = system
    right = node.params['can.right_motor_id']
    # Not in motor mode: the motor answers, but applies nothing.
    fb = _exchange(bus, PROTOCOL.torque_frames({right: 6.0})[0])
    assert fb is not None and fb.motor_id == right
    assert abs(fb.torque) < 0.01
    time.sleep(0.1)
    assert node.motors[1].torque == 0.0
    assert node.sim.wheel_torques()[1] == 0.0


def test_enter_then_torque_gets_reply_and_drives_the_wheel(system):
    node, listener, bus = system
    left = node.params['can.left_motor_id']
    fb = _exchange(bus, PROTOCOL.enable_frames([left])[0])
    assert fb is not None and fb.motor_id == left and abs(fb.torque) < 0.01
    v0 = node.sim.wheel_velocities()[0]
    fb = _exchange(bus, PROTOCOL.torque_frames({left: 3.0})[0])
    assert fb is not None and fb.motor_id == left
    assert fb.torque == pytest.approx(3.0, abs=0.02)
    time.sleep(0.2)
    # can.left_direction = +1: positive motor torque rolls the left wheel forward.
    assert node.sim.wheel_torques()[0] == pytest.approx(3.0, abs=0.02)
    assert node.sim.wheel_velocities()[0] > v0 + 1.0
    fb = _exchange(bus, PROTOCOL.torque_frames({left: 3.0})[0])
    assert fb.velocity > 1.0   # the reply reports the motion in the motor's convention
    # Exit: torque off again.
    fb = _exchange(bus, PROTOCOL.disable_frames([left])[-1])
    assert fb is not None and abs(fb.torque) < 0.01
    time.sleep(0.05)
    assert node.sim.wheel_torques()[0] == 0.0


def test_torque_is_limited_to_the_motor_limit(system):
    node, _, bus = system
    left = node.params['can.left_motor_id']
    assert _exchange(bus, PROTOCOL.enable_frames([left])[0]) is not None
    # A full MIT command whose PD term asks for far more than 18 N m.
    fb = _exchange(bus, PROTOCOL.command_frame(left, 12.0, 0.0, 500.0, 0.0, 18.0))
    assert fb is not None
    assert fb.torque == pytest.approx(18.0, abs=0.02)
    assert abs(node.sim.wheel_torques()[0]) <= 18.0
    assert _exchange(bus, PROTOCOL.disable_frames([left])[-1]) is not None
