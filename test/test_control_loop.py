"""
balance_node's control loop mechanics: what makes the 2 ms loop hold in Python.

- the sensor intake takes imu / joint_states as they arrive, so no executor has to run for
  the robot to balance, and the node's remappings still apply to those topics;
- CAN frames are read by ``CanIo.poll`` in the tick (no receive thread), bounded and never
  raising, and decoded by the tick's ``MotorSet``;
- missed deadlines (core/deadline.py): up to MAX_CATCH_UP are served late (the rate holds), a
  longer stall is skipped (no burst), checked on a simulated clock so the result does not
  depend on the load; a tick later than 10 ms is counted and reported as a stall;
- the real-time options are tried from the control loop and reported, refused or not.
"""
import errno
import os
import time
import uuid

import can
from can.interfaces.virtual import VirtualBus
import numpy as np
import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Imu, JointState

from wheelleg_balance.core.deadline import DeadlineLoop, window_stats
from wheelleg_balance.core.motors import MotorSet
from wheelleg_balance.core.protocols.mit import MitProtocol
from wheelleg_balance.nodes.balance_node import BalanceNode
from wheelleg_balance.nodes.can_io import CanIo
from wheelleg_balance.nodes.control_process import MAX_CATCH_UP
from wheelleg_balance.validation.faults.rig import wait_for

pytestmark = pytest.mark.ros

PERIOD_NS = 2_000_000


@pytest.fixture
def make_node(context):
    nodes = []

    def make(cli_args=None, **params):
        node = BalanceNode(bus=VirtualBus(channel='wlb-%s' % uuid.uuid4().hex),
                           context=context, namespace='/loop_%s' % uuid.uuid4().hex[:8],
                           cli_args=cli_args,
                           parameter_overrides=[Parameter(k, value=v)
                                                for k, v in params.items()])
        nodes.append(node)
        return node
    yield make
    for node in nodes:
        node.destroy_node()


def _publish_sensors(context, namespace, imu_topic='imu', seconds=1.0, until=None):
    """Publish Imu and JointState at about 200 Hz from a node nobody spins (``until()``)."""
    pub_node = Node('fake_sensors_%s' % uuid.uuid4().hex[:8], context=context,
                    namespace=namespace)
    try:
        imu_pub = pub_node.create_publisher(Imu, imu_topic, qos_profile_sensor_data)
        # Another driver's joint states (wheel_state_source: joint_states).
        joint_pub = pub_node.create_publisher(JointState, 'joint_states_in',
                                              qos_profile_sensor_data)
        imu, joints = Imu(), JointState()
        imu.orientation.w = 1.0
        joints.name = ['left_wheel_joint', 'right_wheel_joint']
        joints.position, joints.velocity = [0.0, 0.0], [1.0, 2.0]
        end = time.monotonic() + seconds
        k = 0
        while time.monotonic() < end and not (until is not None and until()):
            k += 1
            imu.header.stamp.nanosec = k  # a new stamp each time: not a frozen IMU
            imu_pub.publish(imu)
            joint_pub.publish(joints)
            time.sleep(0.005)
    finally:
        pub_node.destroy_node()


def _sensors(node):
    """Return the control loop's view of its newest samples (its status), or None."""
    st = node.status
    return None if st is None else st['sensors']


def _fresh(node, key, age=0.5):
    s = _sensors(node)
    return s is not None and s[key] < age


def test_the_loop_takes_sensor_samples_without_any_executor(make_node, context):
    node = make_node(wheel_state_source='joint_states')
    # No executor spins `node`: only its sensor intake can take the samples. Published until
    # both arrive (discovery of a new publisher takes a moment on a loaded machine).
    _publish_sensors(context, node.get_namespace(), seconds=5.0, until=lambda: _fresh(
        node, 'imu_age_s', 0.1) and _fresh(node, 'joint_age_s', 0.1))
    assert _fresh(node, 'imu_age_s'), 'imu never reached the control loop'
    assert _fresh(node, 'joint_age_s'), 'joint_states never reached the control loop'
    s = _sensors(node)
    assert (s['wheel_vel_left'], s['wheel_vel_right']) == (1.0, 2.0)
    assert node.status['timing']['tick_errors'] == 0


def test_remapping_the_node_remaps_its_sensor_topics(make_node, context):
    node = make_node(cli_args=['--ros-args', '-r', 'imu:=imu_remapped'])
    _publish_sensors(context, node.get_namespace(), imu_topic='imu', seconds=1.5)
    time.sleep(0.2)
    assert _sensors(node)['imu_age_s'] == float('inf'), \
        'the original topic must no longer feed the node'
    _publish_sensors(context, node.get_namespace(), imu_topic='imu_remapped', seconds=5.0,
                     until=lambda: _fresh(node, 'imu_age_s', 0.1))
    assert _fresh(node, 'imu_age_s')


def test_the_state_and_the_joints_cross_the_link_in_one_message():
    from wheelleg_balance.core import tick_io
    from wheelleg_balance.nodes import control_link as L
    ros_end, loop_end = (L.Link(s) for s in L.socket_pair())
    state = tick_io.LoopState(**{f: 0.5 * k for k, f in enumerate(tick_io.STATE_FIELDS)})
    state.time = 12.5
    odom = tick_io.Odom(x=2.0, yaw_rate=-0.5)
    values = tick_io.state_frame(state, odom, tick_io.PUBLISH_ODOM)
    assert len(values) == len(tick_io.FRAME_FIELDS)
    assert values[tick_io.MODE] == 0.5 * tick_io.MODE and values[tick_io.TIME] == 12.5
    assert values[tick_io.ODOM] == [2.0, 0.0, 0.0, 0.0, -0.5]
    assert values[tick_io.FLAGS] == tick_io.PUBLISH_ODOM
    joints = [float(k) for k in range(30)]   # six motors and four knees: 3 x 10 values
    assert loop_end.send_state(values, joints) and loop_end.send_state(values)
    received = [(tag, [list(part) for part in payload]) for tag, payload in ros_end.receive()]
    assert received == [(L.STATE, [values, joints]), (L.STATE, [values, []])]


# ----------------------------------------------------------------- CanIo.poll, MotorSet


def _reply(motor_id):
    f = MitProtocol().encode_reply(motor_id, 0.5, -1.0, 0.25)
    return can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=False)


def _poll_into(io, motors):
    frames = []
    n = io.poll(frames)
    for t, frame in frames:
        motors.on_frame(t, frame)
    return n


def test_poll_decodes_the_replies_received_since_the_last_tick():
    channel = 'wlb-%s' % uuid.uuid4().hex
    peer = VirtualBus(channel=channel)
    io = CanIo(VirtualBus(channel=channel), clock=lambda: 42.0)
    motors = MotorSet(MitProtocol(), (('left', 1, 1), ('right', 2, -1)))
    try:
        assert _poll_into(io, motors) == 0 and motors.reply_times == {1: None, 2: None}
        peer.send(_reply(1))
        peer.send(_reply(7))  # a motor that is not ours: read, not taken as a reply
        assert _poll_into(io, motors) == 2
        assert motors.reply_times == {1: 42.0, 2: None}
        assert motors.by_id[1].feedback.velocity == pytest.approx(-1.0, abs=0.05)
        assert (io.rx_frames, motors.rx_replies) == (2, 1)
        assert _poll_into(io, motors) == 0
    finally:
        io.close()
        peer.shutdown()


def test_poll_drops_the_echoes_of_extended_frames_too():
    """The echoes of 29-bit ID frames (CyberGear commands) are dropped like standard ones."""
    from wheelleg_balance.core.protocols import CybergearProtocol
    channel = 'wlb-%s' % uuid.uuid4().hex
    peer = VirtualBus(channel=channel)
    io = CanIo(VirtualBus(channel=channel, receive_own_messages=True), clock=lambda: 7.0)
    command = CybergearProtocol().torque_frames({1: 0.5})[0]
    assert command.is_extended_id
    try:
        assert io.send([command]) is None
        # Another node sending the very same command: one copy is the echo, this one is not.
        peer.send(can.Message(arbitration_id=command.arbitration_id, data=command.data,
                              is_extended_id=True))
        frames = []
        assert io.poll(frames) == 2
        assert [f for _, f in frames] == [command]
        assert (io.rx_echoes, io.rx_frames) == (1, 1)
    finally:
        io.close()
        peer.shutdown()


def test_poll_drops_the_echoes_of_its_own_frames_once_each():
    """A bus that hands the sender its frames back (udp_multicast): not decoded, not counted."""
    from wheelleg_balance.core.protocols.base import Frame
    channel = 'wlb-%s' % uuid.uuid4().hex
    peer = VirtualBus(channel=channel)
    io = CanIo(VirtualBus(channel=channel, receive_own_messages=True), clock=lambda: 7.0)
    command = MitProtocol().torque_frames({1: 0.5})[0]
    try:
        assert io.send([command, MitProtocol().torque_frames({2: 0.5})[0]]) is None
        peer.send(_reply(1))
        # Another node sending the very same command: one copy is the echo, this one is not.
        peer.send(can.Message(arbitration_id=command.arbitration_id, data=command.data,
                              is_extended_id=False))
        frames = []
        assert io.poll(frames) == 4
        assert [f for _, f in frames] == [Frame(0, _reply(1).data), command]
        assert (io.rx_echoes, io.rx_frames, io.tx_frames) == (2, 2, 2)
        # Only frames sent since the previous poll are echoes.
        peer.send(can.Message(arbitration_id=command.arbitration_id, data=command.data,
                              is_extended_id=False))
        frames = []
        assert io.poll(frames) == 1 and [f for _, f in frames] == [command]
        assert io.counters()['rx_echoes'] == 2
    finally:
        io.close()
        peer.shutdown()
    # A bus that makes no echoes (SocketCAN's default): another node's copy of a frame just
    # sent is a received frame like any other.
    channel = 'wlb-%s' % uuid.uuid4().hex
    peer = VirtualBus(channel=channel)
    io = CanIo(VirtualBus(channel=channel))
    try:
        assert io.send([command]) is None
        peer.send(can.Message(arbitration_id=command.arbitration_id, data=command.data,
                              is_extended_id=False))
        frames = []
        assert io.poll(frames) == 1 and [f for _, f in frames] == [command]
        assert (io.rx_echoes, io.rx_frames) == (0, 1)
    finally:
        io.close()
        peer.shutdown()


def test_poll_reads_a_bounded_number_of_frames_per_tick():
    channel = 'wlb-%s' % uuid.uuid4().hex
    peer = VirtualBus(channel=channel)
    io = CanIo(VirtualBus(channel=channel))
    motors = MotorSet(MitProtocol(), (('left', 1, 1), ('right', 2, -1)))
    try:
        for _ in range(10):
            peer.send(_reply(2))
        frames = []
        assert io.poll(frames, max_frames=4) == 4
        assert io.poll(frames, max_frames=4) == 4
        assert io.poll(frames, max_frames=4) == 2
        for t, frame in frames:
            motors.on_frame(t, frame)
        assert motors.by_id[2].replies == 10
    finally:
        io.close()
        peer.shutdown()


# On SocketCAN CanIo reads and writes struct can_frame on python-can's socket itself. No
# SocketCAN in these kernels: python-can's SocketcanBus on another socket stands in
# (nodes/socketcan_hub.py), and the other end runs python-can's own frame code.

def _packet_pair():
    """Return SocketcanBus ends of a Unix packet socket pair (a buffer that fills, EPIPE)."""
    import socket
    from wheelleg_balance.nodes.socketcan_hub import HubSocketcanBus
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    return HubSocketcanBus(a), HubSocketcanBus(b)


def test_on_socketcan_frames_go_straight_on_the_socket_as_python_can_writes_and_reads_them():
    from wheelleg_balance.core.protocols.base import Frame
    from wheelleg_balance.nodes.socketcan_hub import socketcan_pair
    ours, theirs = socketcan_pair()
    io = CanIo(ours, clock=lambda: 5.0)
    assert io.raw is ours.socket
    frames = [Frame(0x7FF, bytes(range(8)), False), Frame(0x1ABCDEF, b'\x01\x02\x03', True),
              Frame(0x000, b'', False)] + MitProtocol().torque_frames({1: 0.5, 2: -0.5})
    try:
        assert io.send(frames) is None
        for f in frames:   # python-can's capture_message reads what CanIo wrote
            msg = theirs.recv(1.0)
            assert (msg.arbitration_id, bytes(msg.data), msg.is_extended_id) == \
                (f.arbitration_id, f.data, f.is_extended_id)
            assert not (msg.is_error_frame or msg.is_remote_frame)
        for f in frames:   # ... and CanIo reads what python-can's build_can_frame wrote
            theirs.send(can.Message(arbitration_id=f.arbitration_id, data=f.data,
                                    is_extended_id=f.is_extended_id))
        got = []
        assert io.poll(got) == len(frames)
        assert got == [(5.0, f) for f in frames]
        assert (io.tx_frames, io.rx_frames, io.rx_echoes, io.tx_errors) == (5, 5, 0, 0)
        # The bus load counts the same bits as on python-can's path.
        plain = CanIo(VirtualBus(channel='wlb-%s' % uuid.uuid4().hex))
        assert plain.raw is None
        plain.send(frames)
        assert io.bits == 2 * plain.bits
        plain.close()
        # Error and remote frames: counted, dropped, as python-can's path does.
        theirs.send(can.Message(arbitration_id=0x4, is_error_frame=True, data=bytes(8)))
        theirs.send(can.Message(arbitration_id=0x5, is_remote_frame=True, dlc=8))
        got = []
        assert io.poll(got) == 2 and got == [] and io.rx_frames == 7
        assert io.poll(got, max_frames=0) == 0
    finally:
        io.close()
        theirs.shutdown()


def test_on_socketcan_a_bad_read_or_a_failed_send_is_an_error_text_never_an_exception():
    from wheelleg_balance.core.protocols.base import Frame
    ours, theirs = _packet_pair()
    io = CanIo(ours)
    try:
        theirs.socket.send(b'\x01\x02\x03')   # no struct can_frame
        theirs.send(can.Message(arbitration_id=0x10, data=b'\x01', is_extended_id=False))
        got = []
        assert io.poll(got) == 1 and got == [] and io.rx_errors == 1
        assert 'no CAN frame' in io.last_rx_error
        assert io.poll(got) == 1 and got[0][1].arbitration_id == 0x10   # the next one is read
        assert 'classic CAN' in io.send([Frame(0x1, bytes(9), False)])
        theirs.shutdown()   # the other end gone: every send fails, as on a bus that is down
        error = io.send([Frame(0x1, bytes(8), False), Frame(0x2, bytes(8), False)])
        assert error.startswith('CanOperationError: Failed to transmit: [Errno')
        assert (io.tx_errors, io.tx_frames) == (2, 0)
    finally:
        io.close()
    assert io.send([Frame(0x1, bytes(8), False)]) == 'bus closed' and io.poll([]) == 0


def test_on_socketcan_a_full_socket_buffer_waits_send_timeout_then_is_a_send_error():
    from wheelleg_balance.core.protocols.base import Frame
    ours, theirs = _packet_pair()
    io = CanIo(ours, send_timeout=0.001)
    frame = Frame(0x1, bytes(8), False)
    try:
        sent = 0
        while io.send([frame]) is None and sent < 100000:   # nobody reads: the buffer fills
            sent += 1
        assert 0 < sent < 100000 and io.tx_frames == sent and io.tx_errors == 1
        assert io.last_tx_error.startswith('CanOperationError: Failed to transmit: [Errno %d]'
                                           % errno.EAGAIN)
        assert theirs.recv(1.0) is not None   # room for one frame again
        assert io.send([frame]) is None and io.tx_frames == sent + 1
    finally:
        io.close()
        theirs.shutdown()


def test_python_cans_own_path_stays_where_it_is_asked_for_or_filters_run_in_python():
    from wheelleg_balance.nodes.socketcan_hub import socketcan_pair
    ours, theirs = socketcan_pair()
    try:
        assert CanIo(ours, raw_frames=False).raw is None
        ours.set_filters([{'can_id': 0x10, 'can_mask': 0x7FF}])
        assert CanIo(ours).raw is None
    finally:
        ours.shutdown()
        theirs.shutdown()


class _FailingBus(can.BusABC):
    def __init__(self):
        super().__init__(channel='failing')

    def send(self, msg, timeout=None):
        pass

    def _recv_internal(self, timeout):
        raise can.CanOperationError('bus-off')


def test_poll_counts_a_receive_error_and_does_not_raise():
    io = CanIo(_FailingBus())
    assert io.poll([]) == 0
    assert io.poll([]) == 0
    assert io.rx_errors == 2 and 'bus-off' in io.last_rx_error
    io.close()
    assert io.poll([]) == 0  # closed: nothing read, nothing raised


# --------------------------------------------------------------------- deadline policy


class _SimTime:
    """A clock that moves only when slept on (or when a tick says it took time)."""

    def __init__(self):
        self.ns = 1_000_000_000

    def monotonic_ns(self):
        return self.ns

    def sleep(self, seconds):
        self.ns += max(0, int(round(seconds * 1e9)))


def _run_loop(ticks, stall_at, stall_ns, **loop_args):
    """Run a DeadlineLoop on simulated time; tick ``stall_at`` takes ``stall_ns``."""
    clock = _SimTime()
    stalls = []
    loop = DeadlineLoop(PERIOD_NS * 1e-9, clock_ns=clock.monotonic_ns, sleep=clock.sleep,
                        on_stall=stalls.append, **loop_args)
    times = []

    def tick(now_ns):
        times.append(now_ns)
        clock.ns += 100_000 + (stall_ns if len(times) == stall_at else 0)
        if len(times) == ticks:
            loop.stop()
    loop.run(tick)
    return [t - times[0] for t in times], loop, stalls


def test_a_short_stall_is_caught_up_and_the_schedule_kept():
    stall = 3 * PERIOD_NS + 500_000   # 3.5 periods: 4 deadlines pass during it
    t, loop, stalls = _run_loop(ticks=100, stall_at=10, stall_ns=stall,
                                max_catch_up=MAX_CATCH_UP)
    # Deadlines 10..13 are served late, back to back; from then on every tick is on its own
    # 2 ms deadline again: 100 ticks in 99 periods, nothing skipped.
    assert t[-1] == 99 * PERIOD_NS
    assert all(t[k] == k * PERIOD_NS for k in range(10))
    assert all(t[k] == k * PERIOD_NS for k in range(14, 100))
    assert all(t[k] > k * PERIOD_NS for k in range(10, 13))
    stats = loop.stats()
    assert stats['overruns'] == 0
    assert stats['caught_up'] == 3
    assert stats['ticks'] == 100
    assert stalls == [] and stats['stalls'] == 0   # 5.6 ms late at most: not a stall


def test_a_long_stall_is_skipped_not_answered_with_a_burst():
    stall = (MAX_CATCH_UP + 5) * PERIOD_NS  # longer than the catch-up bound
    t, loop, stalls = _run_loop(ticks=40, stall_at=10, stall_ns=stall,
                                max_catch_up=MAX_CATCH_UP)
    gaps = [b - a for a, b in zip(t, t[1:])]
    # After the stall the loop goes straight back to the 2 ms grid: no tick runs early.
    assert all(g >= PERIOD_NS for g in gaps)
    assert all(x % PERIOD_NS == 0 for x in t)
    assert loop.stats()['overruns'] == MAX_CATCH_UP + 5
    assert loop.stats()['caught_up'] == 0


def test_a_tick_later_than_10_ms_is_a_stall_with_its_length():
    stall = 15 * PERIOD_NS + 100_000   # the next deadline is served 28.2 ms late
    t, loop, stalls = _run_loop(ticks=40, stall_at=10, stall_ns=stall,
                                max_catch_up=MAX_CATCH_UP)
    # Skipped (more than MAX_CATCH_UP missed): the next tick is on the grid, 28.2 ms after
    # the deadline it should have had... reported once, with its length.
    assert len(stalls) == 1 and loop.stats()['stalls'] == 1
    assert stalls[0] == pytest.approx(loop.stats()['longest_stall'])
    assert 0.010 < stalls[0] < 0.040


def test_resync_policy_serves_every_deadline_until_far_behind():
    stall = 10 * PERIOD_NS
    t, loop, _ = _run_loop(ticks=60, stall_at=10, stall_ns=stall, max_catch_up=None,
                           resync_after=20)
    # sim_node's policy: all 10 missed deadlines are served (simulated time keeps up).
    assert t[-1] == 59 * PERIOD_NS
    assert loop.stats()['resyncs'] == 0 and loop.stats()['overruns'] == 0
    t, loop, _ = _run_loop(ticks=60, stall_at=10, stall_ns=30 * PERIOD_NS, max_catch_up=None,
                           resync_after=20)
    assert loop.stats()['resyncs'] == 1   # far behind: the schedule restarts from now


@pytest.mark.parametrize('late_after', [None, PERIOD_NS * 1e-9])
def test_late_ticks_are_those_past_late_after(late_after):
    # sim_node counts a tick late when it starts more than a period after its deadline; the
    # default is a quarter period. After a 10-period stall the catch-up ticks run back to back,
    # each 0.1 ms long, so their lateness falls by 1.9 ms per tick.
    t, loop, _ = _run_loop(ticks=60, stall_at=10, stall_ns=10 * PERIOD_NS, max_catch_up=None,
                           resync_after=20, late_after=late_after)
    lateness = [t[k] - k * PERIOD_NS for k in range(len(t))]
    threshold = PERIOD_NS // 4 if late_after is None else PERIOD_NS
    assert loop.late == sum(x > threshold for x in lateness) > 0
    assert loop.stats()['late_share'] == loop.late / 60


@pytest.mark.parametrize('budget', [None, 0.0003])
def test_ticks_over_the_compute_budget_are_counted_over_the_whole_run(budget):
    # Ticks take 0.1 ms, then every 7th 1.2 ms, for 3000 ticks: more than the 1024 of the
    # percentile rings, so only the counter sees the whole run. Default budget: half the period.
    clock = _SimTime()
    loop = DeadlineLoop(PERIOD_NS * 1e-9, clock_ns=clock.monotonic_ns, sleep=clock.sleep,
                        max_catch_up=MAX_CATCH_UP, budget=budget)

    def tick(now_ns):
        k = loop.ticks
        clock.ns += 1_200_000 if k % 7 == 0 else 100_000
        if k == 2999:
            loop.stop()
    loop.run(tick)
    stats = loop.stats()
    assert stats['ticks'] == 3000
    assert stats['budget'] == pytest.approx(PERIOD_NS * 0.5e-9 if budget is None else budget)
    assert stats['over_budget'] == len(range(0, 3000, 7))   # 0.1 ms is within either budget
    # Exactly the budget is within it.
    clock = _SimTime()
    loop = DeadlineLoop(PERIOD_NS * 1e-9, clock_ns=clock.monotonic_ns, sleep=clock.sleep)

    def exact(now_ns):
        clock.ns += PERIOD_NS // 2
        if loop.ticks == 9:
            loop.stop()
    loop.run(exact)
    assert loop.stats()['over_budget'] == 0


@pytest.mark.parametrize('n', [1, 2, 3, 100, 1023, 1024])
def test_window_stats_are_numpys_mean_p99_and_max(n):
    values = np.random.default_rng(n).exponential(0.0005, n)
    stats = window_stats('compute', values)
    assert stats['compute_mean'] == pytest.approx(np.mean(values), rel=1e-12)
    assert stats['compute_p99'] == pytest.approx(np.percentile(values, 99), rel=1e-12)
    assert stats['compute_max'] == np.max(values)
    assert all(np.isnan(v) for v in window_stats('period', []).values())


def test_an_exception_in_the_tick_is_counted_and_the_loop_goes_on():
    clock = _SimTime()
    errors = []
    loop = DeadlineLoop(0.002, clock_ns=clock.monotonic_ns, sleep=clock.sleep,
                        on_error=lambda now, exc: errors.append(exc))
    n = []

    def tick(now_ns):
        n.append(now_ns)
        if len(n) == 3:
            raise RuntimeError('a bug')
        if len(n) == 10:
            loop.stop()
    loop.run(tick)
    assert len(n) == 10 and loop.stats()['tick_errors'] == 1
    assert isinstance(errors[0], RuntimeError)


# ------------------------------------------------------------------- real-time options


def test_refused_realtime_options_are_reported_and_the_loop_runs(make_node):
    node = make_node(realtime_cpu=1023)
    assert wait_for(lambda: node.status is not None, 2.0)
    realtime = node.status['realtime']
    assert 'not allowed' in realtime and "thread named 'balance_control'" in realtime
    ticks = node.status['timing']['ticks']
    assert wait_for(lambda: node.status['timing']['ticks'] > ticks + 50, 3.0)
    loop = [s for s in node.diagnostics(time.monotonic()).status
            if s.name == 'balance_node: control loop'][0]
    assert 'not allowed' in {kv.key: kv.value for kv in loop.values}['realtime']


def test_the_control_loop_is_pinned_when_allowed(make_node):
    cpu = min(os.sched_getaffinity(0))
    node = make_node(realtime_cpu=cpu)
    assert wait_for(lambda: node.status is not None, 2.0)
    assert 'pinned to CPU %d' % cpu in node.status['realtime']
    assert os.sched_getaffinity(node.control_task_id) == {cpu}


# ------------------------------------------------------- clock_source imu_stamp (lockstep)

def test_on_imu_stamps_the_loop_ticks_once_per_sample_at_its_stamp():
    """A tick per new IMU stamp, at the stamp; the sample's receipt time is its stamp."""
    import threading
    from wheelleg_balance.core.config import BalanceConfig
    from wheelleg_balance.core.schema import with_changes
    from wheelleg_balance.core.sensors import ImuSample
    from wheelleg_balance.nodes import control_link as L
    from wheelleg_balance.nodes.control_process import make_runner

    cfg = with_changes(BalanceConfig(), {'clock_source': 'imu_stamp'})
    ros_end, loop_end = L.socket_pair()
    intake_end, loop_sensor_end = L.socket_pair()
    runner = make_runner(cfg, VirtualBus(channel='wlb-%s' % uuid.uuid4().hex),
                         L.Link(loop_end), L.Link(loop_sensor_end), realtime_options=False)
    thread = threading.Thread(target=runner.run, daemon=True)
    thread.start()
    sensors = L.Link(intake_end)

    def sample(k):
        # Receipt time 0 (the intake's monotonic clock): the loop must not use it.
        return ImuSample(0.0, 1000, k * PERIOD_NS, 0.0, 0.0, 0.0, 1.0, True, 0.0, 0.0, 0.0,
                         0.0, 0.0, 9.81)
    try:
        for k in range(1, 31):
            sensors.send_imu(sample(k))
            assert wait_for(lambda: runner.ticks >= k, 5.0), k   # one at a time, as lockstep
        assert runner.now == pytest.approx(1000.06)
        assert runner.loop.imu.time == pytest.approx(1000.06)
        sensors.send_imu(sample(30))          # the same stamp again: time stands, no tick
        assert wait_for(lambda: runner.stamps_not_advancing == 1, 5.0)
        time.sleep(0.1)                       # wall time passes: no tick without a sample
        assert runner.ticks == 30
    finally:
        runner.stop()
        thread.join(5.0)
        L.Link(ros_end).close()
    assert not thread.is_alive()


def test_the_udp_multicast_test_bus_never_leaves_the_machine():
    """TTL 0: the frames reach this host's sockets only, and they do reach them."""
    import socket
    from wheelleg_balance.nodes.can_io import open_bus
    group, port = '239.74.250.%d' % (1 + os.getpid() % 200), 46000 + os.getpid() % 2000
    a, b = open_bus('udp_multicast', group, port), open_bus('udp_multicast', group, port)
    try:
        ttl = a._multicast._socket.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL)
        assert ttl == 0
        a.send(can.Message(arbitration_id=7, data=b'\x01' * 8, is_extended_id=False))
        got = b.recv(2.0)
        assert got is not None and got.arbitration_id == 7
    finally:
        a.shutdown()
        b.shutdown()


def test_on_the_udp_multicast_test_bus_sends_never_wait():
    """No socket timeout mode there (a poll before each recvmsg and sendto); socketcan keeps it."""
    from wheelleg_balance.nodes.can_io import open_bus
    group, port = '239.74.251.%d' % (1 + os.getpid() % 200), 46000 + os.getpid() % 2000
    a, b = open_bus('udp_multicast', group, port), open_bus('udp_multicast', group, port)
    io, peer = CanIo(a, send_timeout=0.0005), CanIo(b, send_timeout=0.0005)
    try:
        assert io.send_timeout == 0.0
        assert io.send(MitProtocol().torque_frames({1: 0.5})) is None
        assert a._multicast._socket.gettimeout() == 0.0   # non-blocking, not timeout mode
        assert wait_for(lambda: peer.poll([]) == 1, 2.0)
        assert io.poll([]) == 1 and io.rx_echoes == 1     # its own frame, handed back
    finally:
        io.close()
        peer.close()
    virtual = CanIo(VirtualBus(channel='wlb-%s' % uuid.uuid4().hex), send_timeout=0.0005)
    assert virtual.send_timeout == 0.0005
    virtual.close()
