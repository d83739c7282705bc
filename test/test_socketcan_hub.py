"""
The socketcan_hub test bus (nodes/socketcan_hub.py): python-can's SocketcanBus through a hub.

A frame one member sends reaches every other member and never comes back to its sender, as on
a CAN bus with raw sockets; members come and go; a hub process starts, serves and ends cleanly.
"""
import os
import signal
import subprocess
import sys
import threading

import can
import pytest

from wheelleg_balance.core.protocols.base import Frame
from wheelleg_balance.core.protocols.mit import MitProtocol
from wheelleg_balance.nodes.can_io import CanIo, open_bus
from wheelleg_balance.nodes.socketcan_hub import Hub, hub_command, HubSocketcanBus, INTERFACE

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture
def hub():
    hub = Hub()
    thread = threading.Thread(target=hub.serve, daemon=True)
    thread.start()
    yield hub
    hub.stop()
    thread.join(5.0)
    assert not thread.is_alive()


def test_every_other_member_gets_each_frame_and_the_sender_none(hub):
    a, b, c = (CanIo(open_bus(INTERFACE, hub.address)) for _ in range(3))
    try:
        assert isinstance(a.bus, HubSocketcanBus) and a.raw is a.bus.socket
        frames = MitProtocol().torque_frames({1: 0.5, 2: -0.5}) + [
            Frame(0x1ABCDEF, b'\x01', True)]
        assert a.send(frames) is None
        for member in (b, c):
            got = [member.bus.recv(2.0) for _ in frames]   # python-can's SocketCAN receive
            assert [(m.arbitration_id, bytes(m.data), m.is_extended_id) for m in got] == [
                (f.arbitration_id, f.data, f.is_extended_id) for f in frames]
        assert a.poll([]) == 0 and a.bus.recv(0.05) is None   # no echo
        # A member leaves: the others go on.
        c.close()
        assert b.send([Frame(0x7, bytes(8), False)]) is None
        msg = a.bus.recv(2.0)
        assert msg is not None and msg.arbitration_id == 0x7
        assert hub.frames == 4
    finally:
        a.close()
        b.close()
        c.close()


def test_no_hub_is_a_clear_initialization_error():
    import socket
    free = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    free.bind(('127.0.0.1', 0))
    port = free.getsockname()[1]
    free.close()   # nobody on that port
    with pytest.raises(can.CanInitializationError, match='no socketcan_hub hub'):
        open_bus(INTERFACE, '127.0.0.1:%d' % port)
    with pytest.raises(can.CanInitializationError, match='no socketcan_hub hub'):
        open_bus(INTERFACE, 'can0')


def udp_drops_of(bus) -> int:
    from wheelleg_balance.validation.bench.node import udp_drops
    return udp_drops(os.fstat(bus.socket.fileno()).st_ino)


def test_a_member_that_never_reads_loses_frames_the_others_still_get(hub):
    sender, deaf, reader = (open_bus(INTERFACE, hub.address) for _ in range(3))
    try:
        n = 2000   # far more than a socket buffer of frames
        for k in range(n):
            sender.send(can.Message(arbitration_id=k % 0x7FF, data=bytes(8),
                                    is_extended_id=False))
            assert reader.recv(2.0).arbitration_id == k % 0x7FF
        # The deaf member's buffer filled: the kernel dropped the rest, the reader got all.
        assert udp_drops_of(deaf) > 0
    finally:
        for bus in (sender, deaf, reader):
            bus.shutdown()


def test_the_hub_process_serves_and_ends_on_sigterm():
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join(p for p in (REPO, env.get('PYTHONPATH')) if p)
    proc = subprocess.Popen(hub_command(), env=env, stdout=subprocess.PIPE, text=True)
    try:
        ready, address = proc.stdout.readline().split()
        assert ready == 'ready' and address.startswith('127.0.0.1:')
        a, b = open_bus(INTERFACE, address), open_bus(INTERFACE, address)
        a.send(can.Message(arbitration_id=0x10, data=b'\x02', is_extended_id=False))
        assert b.recv(5.0).arbitration_id == 0x10
        a.shutdown()
        b.shutdown()
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=10)
        assert proc.returncode == 0 and 'relayed 1 frames' in out
    finally:
        if proc.poll() is None:
            proc.kill()
    assert hub_command(5)[:4] == [sys.executable, '-m', 'wheelleg_balance.nodes.socketcan_hub',
                                  '5']


def test_balance_node_balances_on_the_robots_can_code_path(tmp_path):
    """The whole node (control process, watchdog) on python-can's SocketcanBus via a hub."""
    from wheelleg_balance.validation import child_env
    from wheelleg_balance.validation.bench import node as bench_node
    env = child_env()   # this package first; this run's ROS_DOMAIN_ID (conftest)
    result = bench_node.run(2.0, str(tmp_path), env, '', 0, warmup=1.0, tag='_unix',
                            interface=INTERFACE)
    assert result['interface'] == INTERFACE and result['node_mode'] == 'BALANCING'
    motors = result['motors']
    # Every motor commanded through the hub: the wheels every tick, the hips in turns.
    assert len(motors) == 6 and all(m['frames'] > 0 for m in motors.values())
    assert motors['1']['frames'] > 1.5 * motors['3']['frames']
    # Every motor got its exit frame through the hub when the node ended.
    assert result['clean_shutdown'] and result['node_exit_code'] == 0
    assert result['hub'].startswith('relayed ')
    assert result['hub_cpu_percent'] >= 0.0
