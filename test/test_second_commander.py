"""
A second commander on the bus: command frames to our motors that this node did not send.

Another balance_node, a test script, a second computer: the motors obey every command frame on
their ID, so two senders make two masters. A frame counts as a command when the protocol
decodes it as one and it is no reply (core/protocols: ``command_motor_ids``): FAULT
``input_conflict`` at the tick that reads it while armed (zero torque), arming refused while
such frames come (core/balance_loop.py, FOREIGN_COMMAND_HOLD). At the tick level on the fault
suite's bench (validation/faults/bench.LoopBench, a virtual clock), and at the node level
with balance_node as a process and a second python-can sender on its bus
(validation/faults/scenarios.py ``scenario_second_commander``).
"""
import pytest

from wheelleg_balance.core.protocols.base import Frame
from wheelleg_balance.core.protocols.dji import DjiC620Protocol
from wheelleg_balance.core.protocols.mit import ENTER_MOTOR_MODE, EXIT_MOTOR_MODE, \
    MitProtocol, SET_ZERO_POSITION
from wheelleg_balance.sim.motor_emulator import DjiC620Emulator
from wheelleg_balance.validation.faults import bench as bench_module
from wheelleg_balance.validation.faults.bench import is_zero_torque, LoopBench, make_joints, \
    MODE

MIT = MitProtocol()
DJI = DjiC620Protocol()
SENDER = 'another sender on the bus'


def balancing(bench: LoopBench, ticks: int = 25) -> LoopBench:
    """Arm the bench (upright, still) and let it balance for ``ticks``."""
    req = bench.arm_from_rest()
    assert req.success, req.message
    run(bench, ticks)
    assert bench.mode == MODE['BALANCING'], bench.loop.supervisor.faults
    return bench


def run(bench: LoopBench, ticks: int, foreign=None, every: int = 1):
    """Tick ``ticks`` times; ``foreign``: a frame of another sender every ``every`` ticks."""
    sent = []
    for k in range(ticks):
        bench.feed()
        if foreign is not None and k % every == 0:
            bench.inputs.frames.append((bench.t + bench.period, foreign))
        sent.append(bench.tick())
    return sent


def own_id_replies(bench: LoopBench) -> None:
    """Make each wheel motor reply on its own ID with 8 bytes (MIT master_id = motor ID)."""
    for motor_id in bench.loop.motors.ids:
        e = bench.motors.motor(motor_id)
        e.protocol = MitProtocol(master_id=motor_id)
        e.reply_temperature = True


def fault_reasons(bench: LoopBench):
    return [(f.code, f.message) for f in bench.loop.supervisor.faults]


def assert_conflict_now(bench: LoopBench, frames, motor: str):
    """FAULT input_conflict at this tick, naming the motor and another sender; zero torque."""
    assert bench.mode == MODE['FAULT']
    assert frames and all(is_zero_torque(cmd) for _, cmd in frames), frames
    (reason,) = [m for c, m in fault_reasons(bench) if c == 'input_conflict']
    assert motor in reason and SENDER in reason


def test_protocols_tell_commands_from_replies():
    cmd = MIT.torque_frames({1: 3.0})[0]
    assert MIT.command_motor_ids(cmd) == (1,)
    for special in (ENTER_MOTOR_MODE, EXIT_MOTOR_MODE, SET_ZERO_POSITION):
        assert MIT.command_motor_ids(Frame(2, special)) == (2,)
    # Replies: 6 or 8 bytes on the master ID, 8 bytes on the motor's own ID (byte 0 = ID).
    own = MitProtocol(master_id=1).encode_reply(1, 0.3, 1.0, 0.5, temperature=30.0)
    assert own.arbitration_id == 1 and len(own.data) == 8
    for reply in (own, MIT.encode_reply(1, 0.3, 1.0, 0.5),
                  MIT.encode_reply(2, 0.3, 1.0, 0.5, temperature=30.0)):
        assert MIT.command_motor_ids(reply) == ()
    assert MIT.command_motor_ids(Frame(1, bytes(6))) == ()
    assert MIT.command_motor_ids(Frame(1, bytes(8), True)) == ()
    # C620: either command ID carries four ESCs; feedback is none.
    assert DJI.command_motor_ids(DJI.torque_frames({3: 1.0})[0]) == (1, 2, 3, 4)
    assert DJI.command_motor_ids(DJI.torque_frames({6: 1.0})[0]) == (5, 6, 7, 8)
    assert DJI.command_motor_ids(DJI.encode_feedback(1, 100, 10, 5, 30)) == ()


def test_mit_replies_on_the_motors_own_id_are_no_conflict_another_senders_command_is():
    """
    master_id = the motor ID: 8-byte replies on ID 1 and 2, like commands by ID and length.

    Balancing on them raises nothing; a torque command to motor 1 from another sender is a
    FAULT at the tick that reads it; arming is refused while such frames come and accepted
    FOREIGN_COMMAND_HOLD after the last. Commands to IDs that are not ours (another robot's
    motors on the bus) are ignored.
    """
    bench = LoopBench()
    own_id_replies(bench)
    balancing(bench, ticks=250)   # 0.5 s of 8-byte replies on the motors' own IDs
    assert bench.loop.motors.by_id[1].replies > 200
    run(bench, 50, MIT.torque_frames({7: 3.0})[0])
    run(bench, 10, Frame(0x3, ENTER_MOTOR_MODE))
    assert bench.mode == MODE['BALANCING'] and not fault_reasons(bench)
    foreign = MIT.torque_frames({1: 3.0})[0]
    (frames,) = run(bench, 1, foreign)
    assert_conflict_now(bench, frames, 'motor 1 (left_wheel)')
    from wheelleg_balance.core.balance_loop import FOREIGN_COMMAND_HOLD
    # Arming refused while they come (every 20 ms), with the reason.
    run(bench, 100, foreign, every=10)
    req = bench.request(True)
    run(bench, 1)
    assert not req.success
    assert 'motor 1 (left_wheel)' in req.message and SENDER in req.message
    assert bench.loop.status(bench.t)['foreign_command_reason']
    # Refused until none came for FOREIGN_COMMAND_HOLD, then accepted.
    run(bench, int(0.5 * FOREIGN_COMMAND_HOLD / bench.period))
    req = bench.request(True)
    run(bench, 1)
    assert not req.success and SENDER in req.message
    run(bench, int(0.6 * FOREIGN_COMMAND_HOLD / bench.period))
    req = bench.request(True)
    run(bench, 1)
    assert req.success, req.message
    assert bench.loop.status(bench.t)['foreign_command_reason'] == ''


@pytest.mark.parametrize('special', [ENTER_MOTOR_MODE, EXIT_MOTOR_MODE, SET_ZERO_POSITION],
                         ids=['enter', 'exit', 'zero'])
def test_special_frames_from_another_sender_are_commands(special):
    bench = balancing(LoopBench())
    (frames,) = run(bench, 1, Frame(2, special))
    assert_conflict_now(bench, frames, 'motor 2 (right_wheel)')


@pytest.fixture
def dji_bench(monkeypatch):
    """Return a maker of benches with two C620 ESCs (IDs 1, 2) for wheel motors."""
    monkeypatch.setattr(bench_module, 'wheel_motors',
                        lambda loop: DjiC620Emulator(loop.motors.ids))
    # max_wheel_torque: the C620's 20 A are 6 N m (a larger limit is a configuration problem).
    return lambda: LoopBench(**{'can.protocol': 'dji_c620', 'max_wheel_torque': 6.0,
                                'wheel_state_source': 'joint_states'})


@pytest.mark.parametrize('escs', [{1: 0.0}, {3: 2.0, 4: -2.0}], ids=['ours', 'others'])
def test_dji_any_command_frame_carrying_our_slots_is_a_conflict(dji_bench, escs):
    """
    A 0x200 frame sets ESCs 1-4 whoever it was meant for: ours (1, 2) are in it.

    A 0x1FF frame (ESCs 5-8) does not carry ours.
    """
    bench = dji_bench()
    for _ in range(12):
        bench.feed(joints=make_joints())
        bench.tick()
    req = bench.request(True)
    bench.feed()
    bench.tick()
    assert req.success, req.message
    run(bench, 50, DJI.torque_frames({6: 1.0})[0])
    assert bench.mode == MODE['BALANCING'] and not fault_reasons(bench)
    run(bench, 1, DJI.torque_frames(escs)[0])
    assert bench.mode == MODE['FAULT']
    (reason,) = [m for c, m in fault_reasons(bench) if c == 'input_conflict']
    assert 'motor 1 (left_wheel), motor 2 (right_wheel)' in reason and SENDER in reason
    # The next frame to the ESCs is zero current for both (the FAULT's zero torque).
    (cmd,) = bench.sent
    assert cmd.arbitration_id == 0x200 and bytes(cmd.data)[:4] == bytes(4)


# ---------------------------------------------------------------- the test buses' echoes

def test_a_late_echo_of_our_own_frame_is_no_other_senders_frame():
    """
    udp_multicast hands the sender its frames back; on a loaded machine after the next poll.

    An echo within ECHO_WINDOW of the send is ours (dropped, counted), any copy beyond the
    echoes, and any copy after the window, is another sender's frame.
    """
    import uuid
    from can import Message
    from can.interfaces.virtual import VirtualBus
    from wheelleg_balance.nodes.can_io import CanIo
    channel = 'wlb-%s' % uuid.uuid4().hex
    now = [10.0]
    ours, peer = VirtualBus(channel=channel, receive_own_messages=True), \
        VirtualBus(channel=channel)
    io = CanIo(ours, clock=lambda: now[0])

    def copy(frame):   # what a late echo is on the bus: the same frame once more
        peer.send(Message(arbitration_id=frame.arbitration_id, data=frame.data,
                          is_extended_id=False))
    try:
        cmd = MIT.torque_frames({1: 0.5})[0]
        assert io.send([cmd]) is None
        assert ours.recv(0.0) is not None    # its echo, held back past the next poll
        now[0] += 0.002
        frames = []
        assert io.poll(frames) == 0
        now[0] += 0.002
        copy(cmd)                            # the late echo
        assert io.poll(frames) == 1 and frames == [] and io.rx_echoes == 1
        copy(cmd)                            # one copy more: another sender's
        assert io.poll(frames) == 1 and [f for _, f in frames] == [cmd]
        from wheelleg_balance.nodes.can_io import ECHO_WINDOW
        other = MIT.torque_frames({1: -0.5})[0]
        assert io.send([other]) is None
        assert ours.recv(0.0) is not None
        now[0] += ECHO_WINDOW + 0.01         # its echo never came: forgotten
        frames = []
        io.poll(frames)
        copy(other)
        assert io.poll(frames) == 1 and [f for _, f in frames] == [other]
        assert io.rx_echoes == 1
    finally:
        io.close()
        peer.shutdown()


# ------------------------------------------------------------- balance_node as a process

@pytest.mark.ros
def test_a_second_python_can_sender_faults_the_running_node_and_blocks_arming(context):
    """
    A second python-can bus sends commands to motor 1 while balance_node balances.

    balance_node as its own process on udp_multicast: zero torque within 50 ms of the first
    frame, arming refused while it sends (validation/faults/scenarios.py
    scenario_second_commander).
    """
    from wheelleg_balance.validation.faults.suite import run_measured
    out = run_measured('second_commander', context)
    print('second_commander: time to zero torque %s s, figures %s'
          % (out.time_to_zero, out.figures))
    assert out.handled, '; '.join(out.failures)
