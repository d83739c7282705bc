"""
The ``socketcan_hub`` test bus: SocketCAN's code path between processes, without SocketCAN.

python-can's ``SocketcanBus`` runs on a loopback UDP socket (``HubSocketcanBus``) connected to a
hub process (``python -m wheelleg_balance.nodes.socketcan_hub PORT``) that hands every frame
to every other member, as a CAN bus does, and never back to its sender, as a raw CAN socket
does by default. So the node, its watchdog and a test's motors exchange ``struct can_frame``
through python-can's own SocketCAN send and receive, and CanIo takes its SocketCAN path
(nodes/can_io.py): what runs on the robot, but for the kernel's CAN stack (driver, TX queue,
bit timing), which the hub's relaying stands in for. ``can.interface: socketcan_hub``,
``can.channel``: the hub's address, ``127.0.0.1:PORT``. For benchmarks and tests; on the
robot, ``socketcan``.

Why: these kernels have no CAN (no AF_CAN sockets, no vcan), and python-can's bus between
processes, udp_multicast, sends msgpack datagrams and hands each sender its own frames back,
which costs the node more than SocketCAN does (docs/benchmarks.md, "CAN I/O on SocketCAN").
UDP, not a Unix socket: a Unix datagram or packet socket queues at most
net.unix.max_dgram_qlen (10) frames, which a member preempted for three ticks overflows; a UDP
socket queues as many as its buffer holds, as a CAN socket does.

A member joins with an empty datagram, which the hub answers with one (``HubSocketcanBus``
waits for it: no hub is a clear error). The hub's socket is not connected, so a member that
went away costs it nothing; a member that never reads loses the frames its buffer cannot hold.
"""
import argparse
import selectors
import signal
import socket
import sys
import threading
from typing import List, Optional, Tuple

import can
from can.interfaces.socketcan import constants as sc_constants
from can.interfaces.socketcan.socketcan import SocketcanBus

#: The interface name of this bus in ``can.interface`` (nodes/can_io.py ``open_bus``).
INTERFACE = 'socketcan_hub'
HOST = '127.0.0.1'
#: The largest frame a member may send: struct canfd_frame (a classic frame is 16 bytes).
MAX_FRAME = 72
#: How long joining waits for the hub's answer [s].
JOIN_TIMEOUT = 2.0


class HubSocketcanBus(SocketcanBus):
    """
    python-can's SocketcanBus on a connected UDP socket (no CAN in this kernel).

    Its send and receive are SocketcanBus's own: select, then ``capture_message`` (recvmsg
    with the SO_TIMESTAMPNS time, the 16-byte frame dissected into a Message) to receive;
    ``build_can_frame``, select for room, send to send. Only the constructor differs, which
    opens and binds an AF_CAN socket; and the kernel's CAN filter, which passes every frame
    when none is set, is taken as set.
    """

    def __init__(self, sock: socket.socket, channel: str = 'pair'):
        # The attributes SocketcanBus.__init__ sets, on the given socket.
        self.socket = sock
        self.channel = channel
        self.channel_info = 'python-can SocketcanBus on loopback UDP (%s)' % channel
        self._bcm_sockets = {}
        self._is_filtered = False
        self._task_id = 0
        self._task_id_guard = threading.Lock()
        self._can_protocol = can.CanProtocol.CAN_20
        sock.setsockopt(socket.SOL_SOCKET, sc_constants.SO_TIMESTAMPNS, 1)
        can.BusABC.__init__(self, channel=channel)

    @classmethod
    def join(cls, channel: str) -> 'HubSocketcanBus':
        """Join the bus of the hub at ``channel`` ('HOST:PORT'; can.CanInitializationError)."""
        host, _, port = channel.rpartition(':')
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((HOST, 0))
            sock.connect((host or HOST, int(port)))
            sock.settimeout(JOIN_TIMEOUT)
            sock.send(b'')
            if sock.recv(MAX_FRAME) != b'':
                raise OSError("the answer was not the hub's")
            sock.settimeout(None)
        except (OSError, ValueError) as exc:
            sock.close()
            raise can.CanInitializationError('no socketcan_hub hub at %s: %s' % (channel, exc))
        return cls(sock, channel)

    def _apply_filters(self, filters) -> None:
        # CAN_RAW_FILTER does not exist on a UDP socket; a raw CAN socket with no filter set
        # passes every frame in the kernel, so python-can filters nothing in Python either.
        self._is_filtered = True


def socketcan_pair() -> Tuple[HubSocketcanBus, HubSocketcanBus]:
    """Return two HubSocketcanBus connected to each other (a bus of two, no hub)."""
    a, b = (socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2))
    for s in (a, b):
        s.bind((HOST, 0))
    a.connect(b.getsockname())
    b.connect(a.getsockname())
    return HubSocketcanBus(a), HubSocketcanBus(b)


class Hub:
    """
    The bus: every frame a member sends goes to every other member, in order.

    ``serve`` runs until ``stop`` (any thread, a signal handler). ``frames``: frames relayed;
    ``dropped``: copies a member's full buffer refused (the kernel usually drops them silently,
    as a CAN socket's full receive queue does).
    """

    def __init__(self, port: int = 0):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((HOST, port))
        self.sock.setblocking(False)
        self.address = '%s:%d' % self.sock.getsockname()
        self.members: List[tuple] = []
        self.frames = 0
        self.dropped = 0
        self._selector = selectors.DefaultSelector()
        self._selector.register(self.sock, selectors.EVENT_READ)
        self._wake_r, self._wake_w = socket.socketpair()
        self._selector.register(self._wake_r, selectors.EVENT_READ)
        self._stop = False

    def stop(self) -> None:
        """Make ``serve`` return."""
        self._stop = True
        try:
            self._wake_w.send(b'\0')
        except OSError:
            pass

    def serve(self) -> None:
        """Relay frames until ``stop``; then close the sockets."""
        try:
            while not self._stop:
                for key, _ in self._selector.select(timeout=1.0):
                    if key.fileobj is self.sock:
                        self._relay()
        finally:
            self.close()

    def _relay(self) -> None:
        sock = self.sock
        while True:
            try:
                frame, sender = sock.recvfrom(MAX_FRAME)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                continue   # an error queued on the socket: read on
            if not frame:   # a member joins: answer it
                if sender not in self.members:
                    self.members.append(sender)
                self._send(b'', sender)
                continue
            self.frames += 1
            for member in self.members:
                if member != sender:
                    self._send(frame, member)

    def _send(self, data: bytes, member: tuple) -> None:
        try:
            self.sock.sendto(data, member)
        except (BlockingIOError, InterruptedError):
            self.dropped += 1
        except OSError:
            pass   # a member that went away

    def close(self) -> None:
        """Close the sockets (idempotent)."""
        for s in (self.sock, self._wake_r, self._wake_w):
            s.close()


def hub_command(port: int = 0) -> List[str]:
    """Return the command that runs a hub as a process of its own (0: any free port)."""
    return [sys.executable, '-m', 'wheelleg_balance.nodes.socketcan_hub', str(port)]


def main(argv: Optional[List[str]] = None) -> int:
    """Run a hub until SIGINT or SIGTERM; print its address ('ready HOST:PORT') first."""
    parser = argparse.ArgumentParser(description='the socketcan_hub test bus (module doc)')
    parser.add_argument('port', type=int, nargs='?', default=0,
                        help='UDP port on 127.0.0.1 (default 0: any free one)')
    args = parser.parse_args(argv)
    hub = Hub(args.port)
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: hub.stop())
    print('ready %s' % hub.address, flush=True)
    hub.serve()
    print('relayed %d frames, dropped %d' % (hub.frames, hub.dropped), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
