"""
balance_node end to end: real rclpy and DDS on localhost, wheel motors faked on a python-can bus.

In-process tests use a ``virtual`` bus (a fresh channel per test); the node's control process
and the signal tests' node process (`python -m wheelleg_balance.nodes.balance_node`) use a
``udp_multicast`` bus with a group and port unique to the test. The wheel motors on the bus are
the package's firmware emulators (sim/motor_emulator.py: MIT motors, or DJI C620 ESCs): they act
on and answer the frames. What the node sends is logged here, and its torque frames are decoded
by hand from the MIT layout of docs/interface.md (not with the package's codec), so the encoding
is checked independently of both the node and the emulator.
"""
import math
import os
import pathlib
import signal
import struct
import subprocess
import sys
import threading
import time
import uuid

import can
from can.interfaces.virtual import VirtualBus
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TwistStamped
from nav_msgs.msg import Odometry
import pytest
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import SetBool, Trigger

from wheelleg_balance.core.balance_loop import STATE_FIELDS
from wheelleg_balance.core.can_budget import frame_bits
from wheelleg_balance.core.kinematics import FiveBarLeg
from wheelleg_balance.core.protocols.base import Frame
from wheelleg_balance.nodes.balance_node import BalanceNode
from wheelleg_balance.nodes.can_io import open_bus
from wheelleg_balance.nodes.control_process import MAX_CATCH_UP
from wheelleg_balance.sim.motor_emulator import DjiC620Emulator, MitMotorBank
# Test plumbing only (polling, spinning); frames are still decoded here, independently.
from wheelleg_balance.validation.faults.rig import Spinning, wait_for

pytestmark = pytest.mark.ros

REPO = pathlib.Path(__file__).resolve().parents[1]
ENTER = bytes.fromhex('FFFFFFFFFFFFFFFC')
EXIT = bytes.fromhex('FFFFFFFFFFFFFFFD')
# Torque-only MIT command (DESIGN.md): p = 0 -> 0x7FFF, v = 0 -> 0x7FF, kp = kd = 0.
TORQUE_PREFIX = bytes.fromhex('7FFF7FF00000')
T_MAX = 18.0
TORQUE_LSB = 2 * T_MAX / 4095
MODE = {'DISARMED': 0, 'BALANCING': 1, 'FAULT': 2}
IDX = {name: i for i, name in enumerate(STATE_FIELDS)}

# Generous sensor/motor timeouts keep a loaded 2-core machine from tripping them by accident;
# the fault tests stop the data for far longer than these.
BASE_PARAMS = {
    'imu_timeout': 0.25, 'joint_state_timeout': 0.25, 'motor_timeout': 0.25,
    'max_wheel_torque': 1.0, 'state_publish_rate': 100.0, 'diagnostics_rate': 2.0,
}


def decode_torque_command(data):
    """Torque [N m] of a torque-only MIT command, or None if the frame is not one."""
    if len(data) != 8 or bytes(data[:6]) != TORQUE_PREFIX or data[6] >> 4:
        return None
    t = ((data[6] & 0x0F) << 8) | data[7]
    return t * (2 * T_MAX) / 4095 - T_MAX


class WheelMotors:
    """
    The two wheel motors, emulated: MIT motors (IDs 1, 2) or, ``protocol='dji'``, two C620 ESCs.

    ``answer(msg, t)`` hands a frame on the bus, received at ``t`` [s], to the motors' firmware
    and returns their replies as can.Message; the frames the node sent them are logged in
    ``frames`` (t, arbitration_id, bytes): MIT frames to the motors' IDs, 0x200 current frames
    of the ESCs.
    Motor IDs in ``silent`` do not answer (they still act on the frames).
    """

    def __init__(self, ids=(1, 2), protocol='mit'):
        self.ids = ids
        self.protocol = protocol
        self.emulator = DjiC620Emulator(ids) if protocol == 'dji' else MitMotorBank(ids)
        self.silent = self.emulator.silent
        self.frames = []

    def answer(self, msg, t):
        data = bytes(msg.data)
        to_motors = msg.arbitration_id == 0x200 if self.protocol == 'dji' else \
            msg.arbitration_id in self.ids
        if to_motors and len(data) == 8:   # not our own replies (udp_multicast loops them
            self.frames.append((t, msg.arbitration_id, data))   # back) nor strangers
        replies = self.emulator.handle(Frame(msg.arbitration_id, data, msg.is_extended_id),
                                       time.monotonic())
        return [can.Message(arbitration_id=r.arbitration_id, data=r.data, is_extended_id=False,
                            timestamp=time.time()) for r in replies]

    def torques(self, motor_id, since=0.0):
        return [decode_torque_command(d) for t, i, d in list(self.frames)
                if i == motor_id and t >= since and decode_torque_command(d) is not None]


class FakeMotors(WheelMotors):
    """The wheel motors on a bus between processes (WheelMotors), in a thread of their own."""

    def __init__(self, bus, ids=(1, 2), protocol='mit'):
        super().__init__(ids, protocol)
        self.bus = bus
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop.is_set():
            try:
                msg = self.bus.recv(0.05)
            except can.CanError:
                continue
            if msg is None:
                continue
            for reply in self.answer(msg, msg.timestamp):
                self.bus.send(reply)

    def caught_up(self, t, timeout=2.0):
        """Wait until a frame received at or after ``t`` [s] is logged (the thread may lag)."""
        return wait_for(lambda: bool(self.frames) and self.frames[-1][0] >= t, timeout)

    def close(self):
        self._stop.set()
        self._thread.join(1.0)
        self.bus.shutdown()


def udp_address():
    """Return a multicast group and port of this test's own (other runs stay apart)."""
    n = uuid.uuid4().int
    return '239.74.163.%d' % (100 + n % 100), 46000 + (n >> 8) % 3000


class MotorBus(VirtualBus):
    """
    The node's in-process virtual bus with the two wheel motors (WheelMotors) on it.

    Every frame the node sends is logged and answered at once (no extra thread, so a loaded
    machine times the node, not the motors); while ``fail`` is set, send raises
    CanOperationError like a full socketcan TX queue.
    """

    def __init__(self, channel, protocol='mit', ids=(1, 2)):
        super().__init__(channel=channel)
        self.motors = WheelMotors(ids, protocol)
        self.silent = self.motors.silent
        self.frames = self.motors.frames   # (send time [s], arbitration_id, bytes)
        self.fail = False

    def send(self, msg, timeout=None):
        if self.fail:
            raise can.CanOperationError('injected: Transmit buffer full')
        super().send(msg, timeout)
        for reply in self.motors.answer(msg, time.time()):
            self.queue.put(reply)

    def torques(self, motor_id, since=0.0):
        return self.motors.torques(motor_id, since)


class Robot(Node):
    """The test's side of ROS: sensor publishers, state/diagnostics listeners, service clients."""

    def __init__(self, context):
        super().__init__('fake_robot_%s' % uuid.uuid4().hex[:8], context=context)
        self.imu_pub = self.create_publisher(Imu, 'imu', qos_profile_sensor_data)
        # Another driver's joint states (wheel_state_source: joint_states, or the hips).
        self.joint_pub = self.create_publisher(JointState, 'joint_states_in',
                                               qos_profile_sensor_data)
        self.cmd_pub = self.create_publisher(TwistStamped, 'cmd_vel', qos_profile_sensor_data)
        self.states = []   # (receipt time, list of values)
        self.diagnostics = []
        self.create_subscription(Float64MultiArray, '/balance_node/state', self._on_state, 10)
        self.create_subscription(DiagnosticArray, '/diagnostics', self.diagnostics.append, 10)
        self.arm_client = self.create_client(SetBool, '/balance_node/arm')
        self.set_client = self.create_client(SetParameters, '/balance_node/set_parameters')
        self.get_client = self.create_client(GetParameters, '/balance_node/get_parameters')
        # What the sensor timer publishes.
        self.theta = 0.05
        self.imu_nan = False
        self.imu_on = True
        self.joints_on = True
        self.cmd = None   # (x_dot*, yaw_rate*) or None: not published
        self.wheel_vel = (0.0, 0.0)
        self.leg_q = None  # (q_front, q_rear) of both legs, or None: no leg joints
        self._timer = None
        self._publishing = True
        self._imu = Imu()
        self._joints = JointState(name=['left_wheel_joint', 'right_wheel_joint'],
                                  position=[0.0, 0.0], velocity=[0.0, 0.0])
        self._twist = TwistStamped()
        self._k = 0

    def _on_state(self, msg):
        self.states.append((time.monotonic(), list(msg.data)))

    def start(self):
        """Publish the sensors at 200 Hz (cmd_vel at 25 Hz) from a timer of the executor."""
        self._timer = self.create_timer(0.005, self._publish)

    def _publish(self):
        if not self._publishing:
            return
        imu, joints = self._imu, self._joints
        if self.imu_on:
            half = 0.5 * self.theta
            imu.orientation.y = math.nan if self.imu_nan else math.sin(half)
            imu.orientation.w = math.cos(half)
            self.imu_pub.publish(imu)
        if self.joints_on:
            joints.velocity = list(self.wheel_vel)
            if self.leg_q is not None:
                joints.name = ['left_wheel_joint', 'right_wheel_joint', 'lf', 'lr', 'rf', 'rr']
                joints.position = [0.0, 0.0] + list(self.leg_q) * 2
                joints.velocity = list(self.wheel_vel) + [0.0] * 4
            self.joint_pub.publish(joints)
        if self.cmd is not None and self._k % 8 == 0:
            self._twist.twist.linear.x, self._twist.twist.angular.z = self.cmd
            self.cmd_pub.publish(self._twist)
        self._k += 1

    def stop(self):
        """
        Stop publishing; the timer itself goes with the node (destroy_node, after the spin).

        Cancelling it while the executor spins raced the executor's take of a timer already
        ready ("timer is canceled" in the spin thread, seen at teardown).
        """
        self._publishing = False

    def call(self, client, request, timeout=5.0):
        assert client.wait_for_service(timeout_sec=timeout)
        future = client.call_async(request)
        assert wait_for(future.done, timeout), 'service call timed out'
        return future.result()

    def arm(self, on=True):
        return self.call(self.arm_client, SetBool.Request(data=on))

    def set_params(self, **values):
        req = SetParameters.Request(parameters=[
            Parameter(name, value=value).to_parameter_msg() for name, value in values.items()])
        return self.call(self.set_client, req).results

    def get_param(self, name):
        (value,) = self.call(self.get_client, GetParameters.Request(names=[name])).values
        return parameter_value_to_python(value)

    def last_state(self):
        return self.states[-1][1] if self.states else None

    def wait_state(self, predicate, timeout=3.0):
        return wait_for(lambda: bool(self.states) and predicate(self.states[-1][1]), timeout)

    def diagnostic_values(self, status_name):
        for array in reversed(self.diagnostics):
            for status in array.status:
                if status.name == status_name:
                    return {kv.key: kv.value for kv in status.values}, status
        return None, None


class Rig:
    """
    balance_node + fake motors + fake sensors, each node spun by its own executor thread.

    The node runs as on the robot: its control loop in a process of its own, the fake motors
    in this one, on a udp_multicast bus. ``in_process``: the loop in a thread of this process on
    a virtual bus whose sends can be made to fail (``node_bus.fail``).
    """

    def __init__(self, context, motor_protocol='mit', in_process=False, **overrides):
        params = dict(BASE_PARAMS, **overrides)
        if in_process:
            self.node_bus = bus = MotorBus('wlb-%s' % uuid.uuid4().hex, motor_protocol)
            self.motors = self.node_bus
        else:
            group, port = udp_address()
            bus = None
            self.motors = FakeMotors(open_bus('udp_multicast', group, port),
                                     protocol=motor_protocol)
            params.update({'can.interface': 'udp_multicast', 'can.channel': group,
                           'can.udp_port': port})
        self.node = BalanceNode(bus=bus, context=context, parameter_overrides=[
            Parameter(k, value=v) for k, v in params.items()])
        self.robot = Robot(context)
        self._spinning = Spinning(context, (self.node, self.robot))
        self.robot.start()

    def wait_ready(self, timeout=10.0):
        """
        Wait for balance_node's first state: its processes started and discovered.

        A check that counts from the rig's creation also counts the start of the control and
        sensor processes and DDS discovery, which on a loaded CI machine took over 3 s once
        (2026-12-07: test_joint_states_give_height_and_odometry); they are timed elsewhere
        (benchmark --parts start).
        """
        assert self.robot.wait_state(lambda s: True, timeout), 'no state topic'

    def wait_sensors(self, timeout=10.0):
        """
        Wait until the robot's joint states have reached the node's tick (the intake's samples).

        DDS discovery between this process and the intake process sometimes missed the first
        announcements and matched only at the next one, about 3 s later: in 10 runs here
        (2026-12-07) one had no sample in the 3 s after the ready state, two waited about 3 s.
        A check of what the samples do counts from their arrival, not from the discovery.
        """
        self.wait_ready(timeout)
        assert wait_for(lambda: math.isfinite(
            (self.node.status.get('sensors') or {}).get('joint_age_s', math.inf)), timeout), \
            'no joint states reached the tick in %.0f s' % timeout

    def arm_and_balance(self):
        assert wait_for(lambda: self.robot.arm_client.service_is_ready(), 5.0)
        self.wait_ready()
        # Sensors must have reached the node before arming can succeed.
        assert wait_for(lambda: self.robot.arm().success, 5.0, step=0.1)
        assert self.robot.wait_state(lambda s: s[IDX['mode']] == MODE['BALANCING'], 2.0)

    def close(self):
        self.robot.stop()
        self.node.shutdown()
        self._spinning.stop()
        self.node.destroy_node()
        self.robot.destroy_node()
        if isinstance(self.motors, FakeMotors):
            self.motors.close()


@pytest.fixture
def make_rig(context):
    rigs = []

    def make(**kwargs):
        rigs.append(Rig(context, **kwargs))
        return rigs[-1]
    yield make
    for r in rigs:
        r.close()


@pytest.fixture
def rig(make_rig):
    return make_rig()


def _fresh_status(rig):
    """
    Return (time [s], skipped deadlines) of a loop status sent after this call (10 per s).

    The time is the tick's own (CLOCK_MONOTONIC) at which the loop took the status.
    """
    t = time.monotonic()
    assert wait_for(lambda: rig.node.status['time'] > t, 1.0)
    status = rig.node.status
    return status['time'], status['timing']['overruns']


def test_armed_node_sends_encoded_torque_frames_at_500_hz(rig):
    # Leaning forward by 0.2 rad, the wheels must push with at least (M + m) g tan(theta) =
    # 28 N to catch the body: any balance controller saturates at max_wheel_torque (1 N m per
    # wheel, 20 N in total).
    rig.robot.theta = 0.2
    rig.arm_and_balance()
    time.sleep(0.3)
    # The window runs from one status's tick to a later one's: the deadlines the loop skipped
    # between them and the frames it sent are of the same ticks. (A window on the test's own
    # clock ended up to 0.1 s before the second status: a stall in between was counted as
    # skipped while its frames fell outside, CI of 2026-12-04: 499 frames + 20 skipped.)
    t0, overruns0 = _fresh_status(rig)
    time.sleep(1.0)
    t1, overruns1 = _fresh_status(rig)
    wall = time.time() - time.monotonic()   # the frames are stamped on the wall clock
    start, end = t0 + wall, t1 + wall
    assert rig.motors.caught_up(end)
    skipped = overruns1 - overruns0
    deadlines = round((t1 - t0) / rig.node.status['period_target'])
    frames = [f for f in list(rig.motors.frames) if start <= f[0] < end]
    for motor_id in (1, 2):
        mine = [d for _, i, d in frames if i == motor_id]
        assert all(decode_torque_command(d) is not None for d in mine)
        # One frame per motor on every 2 ms deadline less the deadlines the loop skipped
        # (stalls longer than MAX_CATCH_UP periods, counted as overruns). A
        # shorter stall is caught up, so a window's edge can cut a catch-up burst: up to
        # MAX_CATCH_UP frames of deadlines before the window come after its start (and as
        # many of its own after its end). The floor leaves room for a loaded machine but
        # fails a loop that overruns systematically (a tick longer than 2 ms would give 250).
        edge = 3 + MAX_CATCH_UP
        assert 0.8 * deadlines <= len(mine) <= deadlines + edge, (motor_id, len(mine), skipped)
        assert abs(len(mine) + skipped - deadlines) <= edge, (motor_id, len(mine), skipped,
                                                              deadlines)
    # Both wheels push forward; the right motor is mounted mirrored (can.right_direction -1),
    # so its command is negative. Every frame carries the saturated torque.
    left = rig.motors.torques(1, since=start)
    right = rig.motors.torques(2, since=start)
    assert all(t == pytest.approx(1.0, abs=TORQUE_LSB) for t in left)
    assert all(t == pytest.approx(-1.0, abs=TORQUE_LSB) for t in right)
    state = rig.robot.last_state()
    assert state[IDX['tau_left']] == pytest.approx(1.0) and state[IDX['tau_right']] == \
        pytest.approx(1.0)
    # The fake motors answered: the node counts them alive.
    assert wait_for(lambda: rig.robot.diagnostic_values('balance_node: CAN')[0] is not None, 2.0)
    values, status = rig.robot.diagnostic_values('balance_node: CAN')
    assert values['motor_1_alive'] == 'True' and values['motor_2_alive'] == 'True'
    assert int(values['motor_1_replies']) > 400 and int(values['tx_errors']) == 0
    # The bus load: two commands (8 bytes) and two replies (6 or 8) a tick at <= 500 Hz, with
    # worst-case stuffing (core/can_budget.py), over the 0.1 s between status messages. The
    # udp_multicast bus hands the node its own commands back (SocketCAN does not): they are
    # dropped as echoes, not counted twice, so the load is what the wire would carry.
    low, high = (500 * 2 * (frame_bits(8) + frame_bits(n)) / 1e4 for n in (6, 8))
    assert 0.7 * low <= float(values['bus_load_pct']) <= 1.1 * high, values['bus_load_pct']
    assert int(values['rx_echoes']) > 400   # each command came back once: not a reply
    assert int(values['rx_frames']) < 1.5 * int(values['rx_replies'])
    loop, _ = rig.robot.diagnostic_values('balance_node: control loop')
    # Never faster than the 2 ms grid (no catch-up); slower only by the skipped deadlines.
    assert 1.95 < float(loop['period_mean_ms']) < 3.0
    assert float(loop['period_p99_ms']) < 20.0 and int(loop['tick_errors']) == 0
    # BalanceLoop.tick is timed apart from the bus and link work around it: part of each tick.
    for figure in ('mean', 'p99', 'max'):
        core, whole = (float(loop['%s_%s_ms' % (k, figure)]) for k in ('core_compute', 'compute'))
        assert 0.0 < core <= whole, (figure, core, whole)
    # Ticks over the compute budget (half the period), counted over the whole run: none if the
    # slowest tick of the window was within it, and never more than the ticks run.
    assert float(loop['compute_budget_ms']) == pytest.approx(1.0)
    over, ticks = int(loop['over_budget']), int(loop['ticks'])
    assert 0 <= over < ticks
    if float(loop['compute_max_ms']) <= 1.0 and ticks <= 1024:
        assert over == 0


def _resting(data):
    """Tell whether a frame leaves an MIT motor at rest: exit, or a zero-torque command."""
    if data == EXIT:
        return True
    tau = decode_torque_command(data)
    return tau is not None and abs(tau) <= TORQUE_LSB


def test_arm_sends_enter_frames_and_disarm_zero_torque_then_exit(rig):
    t0 = time.time()
    rig.arm_and_balance()
    time.sleep(0.1)
    frames = [f for f in list(rig.motors.frames) if f[0] >= t0]
    for motor_id in (1, 2):
        mine = [d for _, i, d in frames if i == motor_id]
        # Disarmed, the node polls the resting motors (exit frames keep their replies coming);
        # the first frame that is not a resting one enters motor mode, torque follows.
        assert ENTER in mine, 'arming must enter motor mode'
        k = mine.index(ENTER)
        assert all(_resting(d) for d in mine[:k]), 'nothing but rest before arming'
        assert decode_torque_command(mine[k + 1]) is not None
    t1 = time.time()
    response = rig.robot.arm(False)
    # Balancing, a disarm sits the robot down (core/sit_down.py); on this rig's motionless
    # sensors the lean cannot reach the tail and ends at its timeout (3 s) with the same cut.
    assert response.success, response.message
    assert rig.robot.wait_state(lambda s: s[IDX['mode']] == MODE['DISARMED'], 6.0)
    time.sleep(0.2)
    frames = [f for f in list(rig.motors.frames) if f[0] >= t1]
    for motor_id in (1, 2):
        mine = [d for _, i, d in frames if i == motor_id]
        assert EXIT in mine
        k = mine.index(EXIT)
        assert decode_torque_command(mine[k - 1]) == pytest.approx(0.0, abs=TORQUE_LSB)
        assert mine[k + 1:] and all(_resting(d) for d in mine[k + 1:]), \
            'disarmed, only resting frames follow the exit frame (the motors keep answering)'
        assert ENTER not in mine[k + 1:]


def test_stop_service_cuts_at_once(rig):
    rig.arm_and_balance()
    time.sleep(0.1)
    client = rig.robot.create_client(Trigger, '/balance_node/stop')
    t1 = time.time()
    response = rig.robot.call(client, Trigger.Request())
    assert response.success, response.message
    # ~/stop is the emergency stop: no sit-down, DISARMED at the next tick.
    assert rig.robot.wait_state(lambda s: s[IDX['mode']] == MODE['DISARMED'], 0.5)
    time.sleep(0.1)
    for motor_id in (1, 2):
        mine = [d for t, i, d in list(rig.motors.frames) if i == motor_id and t >= t1]
        k = mine.index(EXIT)
        assert all(_resting(d) for d in mine[k:])


def test_controller_switch_and_refused_parameters(rig):
    rig.arm_and_balance()
    assert rig.robot.wait_state(lambda s: s[IDX['controller']] == 0)  # ida_pbc
    (result,) = rig.robot.set_params(controller='lqr')
    assert result.successful, result.reason
    assert rig.robot.wait_state(lambda s: s[IDX['controller']] == 2)
    (result,) = rig.robot.set_params(controller='output_regulation')
    assert result.successful
    assert rig.robot.wait_state(lambda s: s[IDX['controller']] == 1)
    assert rig.robot.last_state()[IDX['mode']] == MODE['BALANCING']
    assert wait_for(lambda: (rig.robot.diagnostic_values('balance_node: safety')[0] or {})
                    .get('controller') == 'output_regulation', 2.0)

    (result,) = rig.robot.set_params(controller='pid')
    assert not result.successful and 'unknown controller' in result.reason
    (result,) = rig.robot.set_params(yaw_rate_gain=50.0)
    assert not result.successful and 'out of range' in result.reason
    (result,) = rig.robot.set_params(height=0.9)
    assert not result.successful and 'height_max' in result.reason
    (result,) = rig.robot.set_params(wheel_radius=0.2)
    assert not result.successful and 'read-only' in result.reason
    # Nothing changed.
    assert rig.robot.get_param('controller') == 'output_regulation'
    assert rig.robot.get_param('yaw_rate_gain') == 0.3
    time.sleep(0.1)
    assert rig.robot.last_state()[IDX['controller']] == 1


def test_joint_states_give_height_and_odometry(make_rig, context):
    r = make_rig(left_leg_front_joint='lf', left_leg_rear_joint='lr', right_leg_front_joint='rf',
                 right_leg_rear_joint='rr', right_wheel_direction=-1,
                 wheel_state_source='joint_states')
    odoms = []
    r.robot.create_subscription(Odometry, 'odom', odoms.append, 10)
    q_front, q_rear = FiveBarLeg().inverse(0.55)
    r.robot.theta = 0.0
    r.robot.leg_q = (q_front, q_rear)
    # Right joint velocity negative with right_wheel_direction -1: both wheels roll forward.
    r.robot.wheel_vel = (2.0, -2.0)
    r.wait_sensors()
    assert r.robot.wait_state(lambda s: s[IDX['l']] == pytest.approx(0.55, abs=1e-6), 3.0), \
        'l %s after %d states; sensors %s; intake %s' % (
            r.robot.last_state()[IDX['l']], len(r.robot.states), r.node.status.get('sensors'),
            r.node.status.get('intake_ready'))
    assert wait_for(lambda: len(odoms) > 10 and odoms[-1].pose.pose.position.x > 0.05, 5.0)
    odom = odoms[-1]
    # REP 105: odom -> base_footprint (base_link sits above it, pitched).
    assert odom.header.frame_id == 'odom' and odom.child_frame_id == 'base_footprint'
    # x_dot = r_w ((w_l + w_r) / 2 + theta_dot) = 0.1 * 2.0; straight ahead, no yaw.
    assert odom.twist.twist.linear.x == pytest.approx(0.2, abs=1e-9)
    assert odom.twist.twist.angular.z == pytest.approx(0.0, abs=1e-9)
    assert abs(odom.pose.pose.position.y) < 1e-9 and odom.pose.pose.orientation.w == 1.0
    assert odom.pose.covariance[0] == 0.001 and odom.twist.covariance[35] == 0.01
    # Disarmed all along: odometry runs whatever the mode.
    assert r.robot.last_state()[IDX['mode']] == MODE['DISARMED']


def test_dji_c620_protocol_plugs_in(make_rig):
    # The C620's feedback is read for liveness; the wheel speeds come from joint states.
    r = make_rig(motor_protocol='dji', wheel_state_source='joint_states',
                 **{'can.protocol': 'dji_c620'})
    r.robot.theta = 0.2   # saturates any controller (see the 500 Hz test)
    r.arm_and_balance()   # the C620 has no motor mode: arming sends nothing special
    time.sleep(0.3)
    start = time.time()
    time.sleep(0.5)
    assert r.motors.caught_up(start + 0.5)
    window = [struct.unpack('>4h', d)[:2] for t, i, d in list(r.motors.frames)
              if i == 0x200 and start <= t < start + 0.5]
    assert 200 <= len(window) <= 252   # one 0x200 frame per tick for both ESCs
    # Forward torque at max_wheel_torque, the right ESC mirrored (can.right_direction -1):
    # 1 N m at 0.3 N m/A is 3.33 A, i.e. code 3.33 * 16384 / 20 = 2731.
    assert all(codes == (2731, -2731) for codes in window), window[:5]
    assert wait_for(lambda: (r.robot.diagnostic_values('balance_node: CAN')[0] or {})
                    .get('motor_2_alive') == 'True', 2.0)
    assert r.robot.last_state()[IDX['mode']] == MODE['BALANCING']


def _stale_imu(r):
    r.robot.imu_on = False


def _stale_joints(r):
    r.robot.joints_on = False


def _nan_imu(r):
    r.robot.imu_nan = True


def _fall(r):
    r.robot.theta = math.radians(50.0)


def _silent_motor(r):
    r.motors.silent.add(2)


def _send_failure(r):
    r.node_bus.fail = True


def _heal(r):
    r.robot.imu_on = r.robot.joints_on = True
    r.robot.imu_nan = False
    r.robot.theta = 0.05
    r.motors.silent.clear()
    if hasattr(r, 'node_bus'):
        r.node_bus.fail = False


@pytest.mark.parametrize('inject,code', [
    (_stale_imu, 'imu_stale'), (_stale_joints, 'joint_states_stale'), (_nan_imu, 'non_finite'),
    (_fall, 'fall'), (_silent_motor, 'motor_silent'), (_send_failure, 'can_send')])
def test_fault_gives_zero_torque_and_a_diagnostic_and_the_node_lives_on(make_rig, inject,
                                                                        code):
    # A send failure needs a bus the test controls: the loop in a thread on a virtual bus.
    # Stale joint states matter where the wheels come from them (else from the replies).
    extra = {'wheel_state_source': 'joint_states'} if code == 'joint_states_stale' else {}
    r = make_rig(in_process=code == 'can_send', **extra)
    r.arm_and_balance()
    time.sleep(0.2)
    assert abs(r.motors.torques(1)[-1]) > 0.1
    inject(r)
    assert r.robot.wait_state(lambda s: s[IDX['mode']] == MODE['FAULT'], 2.0)
    state = r.robot.last_state()
    assert state[IDX['tau_left']] == 0.0 and state[IDX['tau_right']] == 0.0
    if code == 'can_send':
        time.sleep(0.1)
        r.node_bus.fail = False  # the bus recovers: the FAULT's zero torque gets through
    t_fault = time.time()
    time.sleep(0.2)
    if isinstance(r.motors, FakeMotors):
        assert r.motors.caught_up(t_fault + 0.2)
    for motor_id in (1, 2):
        after = r.motors.torques(motor_id, since=t_fault)
        assert len(after) > 20, 'FAULT keeps commanding zero torque every tick'
        assert all(abs(t) <= TORQUE_LSB for t in after)
    assert wait_for(lambda: code in ((r.robot.diagnostic_values('balance_node: safety')[0]
                                      or {}).get('faults', '')), 2.0)
    values, status = r.robot.diagnostic_values('balance_node: safety')
    assert status.level == b'\x02' and values['mode'] == 'FAULT'
    assert values['fault_reasons']
    # FAULT is never left by itself ...
    _heal(r)
    time.sleep(0.3)
    assert r.robot.last_state()[IDX['mode']] == MODE['FAULT']
    # ... but the node is alive and an explicit re-arm balances again.
    assert wait_for(lambda: r.robot.arm().success, 3.0, step=0.1)
    assert r.robot.wait_state(lambda s: s[IDX['mode']] == MODE['BALANCING'], 2.0)


def test_cmd_vel_timeout_ramps_the_reference_to_zero_while_balancing(make_rig):
    rig = make_rig(cmd_vel_timeout=0.3, **{'reference.max_acceleration': 2.0})
    rig.arm_and_balance()
    rig.robot.cmd = (0.4, 0.5)
    assert rig.robot.wait_state(lambda s: s[IDX['x_dot_ref']] == pytest.approx(0.4), 2.0)
    assert rig.robot.last_state()[IDX['yaw_rate_ref']] == pytest.approx(0.5)
    t_stop = time.monotonic()
    rig.robot.cmd = None
    assert rig.robot.wait_state(lambda s: s[IDX['x_dot_ref']] == 0.0, 3.0)
    history = [(t, s) for t, s in list(rig.robot.states) if t >= t_stop]
    refs = [s[IDX['x_dot_ref']] for _, s in history]
    assert all(b <= a for a, b in zip(refs, refs[1:])), 'the reference only ramps down'
    t_first_drop = next(t for t, s in history if s[IDX['x_dot_ref']] < 0.4 - 1e-9)
    # Held while the last command is younger than cmd_vel_timeout (0.3 s; the sensor thread
    # republished it at most ~40 ms before t_stop) ...
    assert 0.2 <= t_first_drop - t_stop <= 1.0
    # ... then a ramp at 2 m/s^2: 0.4 m/s takes 0.2 s, i.e. about 19 samples of ~/state
    # (every 5 ticks) strictly between 0.4 and 0, each about 2 m/s^2 * 10 ms = 0.02 m/s below
    # the previous one (more when a loaded machine made the loop skip ticks). A step has none;
    # a limit several times higher leaves fewer than 5.
    ramp = [r for r in refs if 0.0 < r < 0.4 - 1e-9]
    assert len(ramp) >= 5, refs
    drops = [a - b for a, b in zip(refs, refs[1:]) if a != b]
    assert max(drops) <= 0.1, drops
    assert rig.robot.last_state()[IDX['yaw_rate_ref']] == 0.0
    assert all(s[IDX['mode']] == MODE['BALANCING'] for _, s in history)


def _udp_frames(bus, frames, stop):
    while not stop.is_set():
        msg = bus.recv(0.05)
        if msg is not None and msg.arbitration_id in (1, 2) and len(msg.data) == 8:
            frames.append((time.monotonic(), msg.arbitration_id, bytes(msg.data)))


@pytest.mark.parametrize('signum', [signal.SIGTERM, signal.SIGINT])
def test_signal_sends_zero_torque_then_exit_frames(context, signum):
    group = '239.74.163.%d' % (100 + os.getpid() % 150)
    port = 47000 + os.getpid() % 2000 + 2 * int(signum)
    motor_bus = open_bus('udp_multicast', group, port)
    motors = FakeMotors(motor_bus)
    robot = Robot(context)
    spinning = Spinning(context, (robot,))
    robot.start()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(REPO)] + [p for p in [os.environ.get('PYTHONPATH')] if p]))
    args = [sys.executable, '-m', 'wheelleg_balance.nodes.balance_node', '--ros-args',
            '-p', 'can.interface:=udp_multicast', '-p', 'can.channel:=%s' % group,
            '-p', 'can.udp_port:=%d' % port, '-p', 'auto_arm:=true',
            '-p', 'imu_timeout:=0.5', '-p', 'joint_state_timeout:=0.5',
            '-p', 'motor_timeout:=0.5', '-p', 'max_wheel_torque:=2.0']
    proc = subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        # auto_arm: balancing (non-zero torque frames) as soon as the sensors reach the node.
        assert wait_for(lambda: any(abs(t) > 0.1 for t in motors.torques(1)[-5:]), 30.0), \
            'the node never balanced: %s' % (proc.poll(),)
        proc.send_signal(signum)
        out, err = proc.communicate(timeout=15.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        robot.stop()
        spinning.stop()
        robot.destroy_node()
        time.sleep(0.1)
        motors.close()
    assert proc.returncode == 0, err
    assert 'Traceback' not in err and 'Traceback' not in out, err
    for motor_id in (1, 2):
        mine = [d for _, i, d in motors.frames if i == motor_id]
        assert mine[-1] == EXIT, 'the last frame to each motor exits motor mode'
        last_push = max(k for k, d in enumerate(mine)
                        if decode_torque_command(d) is not None
                        and abs(decode_torque_command(d)) > 0.1)
        tail = mine[last_push + 1:]
        assert tail.index(EXIT) > 0, 'zero torque comes before the exit frame'
        assert all(abs(decode_torque_command(d)) <= TORQUE_LSB for d in tail[:tail.index(EXIT)])


def _flatten(d, prefix=''):
    for key, value in d.items():
        if isinstance(value, dict):
            yield from _flatten(value, prefix + key + '.')
        else:
            yield prefix + key, value


def test_config_file_loads_with_the_design_defaults(context):
    import yaml
    path = REPO / 'config' / 'balance.yaml'
    values = dict(_flatten(yaml.safe_load(path.read_text())['balance_node']['ros__parameters']))
    bus = VirtualBus(channel='wlb-%s' % uuid.uuid4().hex)
    node = BalanceNode(bus=bus, context=context,
                       cli_args=['--ros-args', '--params-file', str(path)])
    try:
        for name, value in values.items():
            assert node.has_parameter(name), 'unknown parameter %s in balance.yaml' % name
            assert node.get_parameter(name).value == value, name
        # DESIGN.md section 2 and Table I; the issue "control that beats the paper" (newer than
        # DESIGN.md) makes `auto` the default and IDA-PBC's m22_0, k_v, P the tuning command's
        # best point: test_config checks this file against the defaults and paper_table_i.yaml
        # against Table I, test_tuning the defaults against docs/tuning_report.json.
        design = {
            'controller': 'auto', 'body_mass': 11.0, 'wheel_mass': 3.0, 'gravity': 9.81,
            'wheel_radius': 0.1, 'wheel_separation': 0.47, 'height_min': 0.37,
            'height_max': 0.70, 'ida_pbc.k': 0.015, 'yaw_rate_gain': 0.3,
            'max_wheel_torque': 12.0, 'fall_angle': pytest.approx(math.radians(45.0)),
            'cmd_vel_timeout': 0.5, 'auto_arm': False, 'can.interface': 'socketcan',
            'can.channel': 'can0', 'can.protocol': 'mit', 'can.left_motor_id': 1,
            'can.right_motor_id': 2, 'can.left_direction': 1, 'can.right_direction': -1,
            'can.mit.p_max': 12.5, 'can.mit.v_max': 50.0, 'can.mit.t_max': 18.0,
        }
        for name, value in design.items():
            assert node.get_parameter(name).value == value, name
            assert values[name] == value, name
        described = node.describe_parameters(['wheel_radius', 'controller', 'can.channel'])
        assert [d.read_only for d in described] == [True, False, True]
        assert all(d.description for d in node.describe_parameters(list(values)))
    finally:
        node.shutdown()
        node.destroy_node()
