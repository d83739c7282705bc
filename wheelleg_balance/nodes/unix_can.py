"""
The ``unix_socketcan`` test bus: SocketCAN's code path between processes, without SocketCAN.

python-can's ``SocketcanBus`` runs on a Unix packet socket (``UnixSocketcanBus``) connected to a
hub process (``python -m wheelleg_balance.nodes.unix_can hub PATH``) that hands every frame to
every other member, as a CAN bus does, and never back to its sender, as a raw CAN socket does
by default. So the node, its watchdog and a test's motors exchange ``struct can_frame`` through
python-can's own SocketCAN send and receive, and CanIo takes its SocketCAN path
(nodes/can_io.py): what runs on the robot, but for the kernel's CAN stack (driver, TX queue,
bit timing), which the hub's relaying stands in for. ``can.interface: unix_socketcan``,
``can.channel``: the hub's socket path. For benchmarks and tests; on the robot, ``socketcan``.

No CAN in these kernels (no AF_CAN sockets, no vcan): udp_multicast, python-can's bus between
processes, sends msgpack datagrams and hands each sender its own frames back, which costs the
node more than SocketCAN does (docs/benchmarks.md, "CAN I/O on SocketCAN").
"""
import argparse
import os
import selectors
import signal
import socket
import sys
import threading
from typing import List, Optional

import can
from can.interfaces.socketcan import constants as sc_constants
from can.interfaces.socketcan.socketcan import SocketcanBus

#: The interface name of this bus in ``can.interface`` (nodes/can_io.py ``open_bus``).
INTERFACE = 'unix_socketcan'
#: The largest frame a member may send: struct canfd_frame (a classic frame is 16 bytes).
MAX_FRAME = 72


class UnixSocketcanBus(SocketcanBus):
    """
    python-can's SocketcanBus on a Unix packet socket (no CAN in this kernel).

    Its send and receive are SocketcanBus's own: select, then ``capture_message`` (recvmsg
    with the SO_TIMESTAMPNS time, the 16-byte frame dissected into a Message) to receive;
    ``build_can_frame``, select for room, send to send. Only the constructor differs, which
    opens and binds an AF_CAN socket; and the kernel's CAN filter, which passes every frame
    when none is set, is taken as set. Like a raw CAN socket it never hands back its own frames.
    """

    def __init__(self, sock: socket.socket, channel: str = 'unix'):
        # The attributes SocketcanBus.__init__ sets, on the given socket.
        self.socket = sock
        self.channel = channel
        self.channel_info = 'python-can SocketcanBus on a Unix packet socket (%s)' % channel
        self._bcm_sockets = {}
        self._is_filtered = False
        self._task_id = 0
        self._task_id_guard = threading.Lock()
        self._can_protocol = can.CanProtocol.CAN_20
        sock.setsockopt(socket.SOL_SOCKET, sc_constants.SO_TIMESTAMPNS, 1)
        can.BusABC.__init__(self, channel=channel)

    @classmethod
    def connect(cls, path: str) -> 'UnixSocketcanBus':
        """Join the bus of the hub listening at ``path`` (can.CanInitializationError if none)."""
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            sock.connect(path)
        except OSError as exc:
            sock.close()
            raise can.CanInitializationError('no unix_socketcan hub at %s: %s' % (path, exc))
        return cls(sock, path)

    def _apply_filters(self, filters) -> None:
        # CAN_RAW_FILTER does not exist on a Unix socket; a raw CAN socket with no filter set
        # passes every frame in the kernel, so python-can filters nothing in Python either.
        self._is_filtered = True


def socketcan_pair():
    """Return two UnixSocketcanBus ends of one socket pair (a bus of two, no hub)."""
    # SEQPACKET, not DGRAM: a datagram pair queues only net.unix.max_dgram_qlen (10) frames,
    # which a peer preempted for three ticks would overflow; this one queues by its buffer.
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    return UnixSocketcanBus(a), UnixSocketcanBus(b)


class Hub:
    """
    The bus: every frame a member sends goes to every other member, in order.

    ``serve`` runs until ``stop`` (any thread, a signal handler). A member whose socket is full
    loses the frame (counted in ``dropped``), as a CAN controller whose receive FIFO is full
    does; a member that hangs up leaves the bus.
    """

    def __init__(self, path: str):
        self.path = path
        if os.path.exists(path):
            os.unlink(path)
        self.listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self.listener.bind(path)
        self.listener.listen(16)
        self.listener.setblocking(False)
        self.members: List[socket.socket] = []
        self.frames = 0
        self.dropped = 0
        self._selector = selectors.DefaultSelector()
        self._selector.register(self.listener, selectors.EVENT_READ)
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
        """Relay frames until ``stop``; then close every socket and remove the path."""
        try:
            while not self._stop:
                ready = [key.fileobj for key, _ in self._selector.select(timeout=1.0)]
                # Who joined first: a member whose connect returned before a frame was sent
                # gets that frame (the listener is readable from the connect on).
                if self.listener in ready:
                    self._accept()
                for sock in ready:
                    if sock is not self.listener and sock is not self._wake_r:
                        self._relay(sock)
        finally:
            self.close()

    def _accept(self) -> None:
        while True:
            try:
                member, _ = self.listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            member.setblocking(False)
            self.members.append(member)
            self._selector.register(member, selectors.EVENT_READ)

    def _relay(self, sender: socket.socket) -> None:
        while True:
            try:
                frame = sender.recv(MAX_FRAME)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                frame = b''
            if not frame:   # hung up
                self._leave(sender)
                return
            self.frames += 1
            for member in self.members:
                if member is not sender:
                    try:
                        member.send(frame)
                    except (BlockingIOError, InterruptedError):
                        self.dropped += 1
                    except OSError:
                        pass   # leaving: its hang-up is read next

    def _leave(self, member: socket.socket) -> None:
        self._selector.unregister(member)
        self.members.remove(member)
        member.close()

    def close(self) -> None:
        """Close every socket and remove the path (idempotent)."""
        for member in list(self.members):
            self._leave(member)
        for sock in (self.listener, self._wake_r, self._wake_w):
            sock.close()
        try:
            os.unlink(self.path)
        except OSError:
            pass


def hub_command(path: str) -> List[str]:
    """Return the command that runs a hub at ``path`` as a process of its own."""
    return [sys.executable, '-m', 'wheelleg_balance.nodes.unix_can', 'hub', path]


def main(argv: Optional[List[str]] = None) -> int:
    """Run a hub until SIGINT or SIGTERM (prints 'ready' once members may connect)."""
    parser = argparse.ArgumentParser(description='the unix_socketcan test bus (module doc)')
    parser.add_argument('role', choices=('hub',))
    parser.add_argument('path', help="the hub's socket path (can.channel of the members)")
    args = parser.parse_args(argv)
    hub = Hub(args.path)
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: hub.stop())
    print('ready', flush=True)
    hub.serve()
    print('relayed %d frames, dropped %d' % (hub.frames, hub.dropped), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
