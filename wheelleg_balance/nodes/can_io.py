"""
The CAN bus of the control loop: python-can on one side, core Frames on the other.

Sending is synchronous from the control loop, one send with a short timeout per frame (never
the kernel's periodic send: it would keep sending the last torque if Python stalled).
A failed send (``can.CanError``, e.g. the ``CanOperationError`` of a full socketcan TX queue, or
an OSError) is returned as a message for the safety supervisor, never raised.
Replies are read by the control loop too: ``poll()`` at the start of each tick drains the
bus without waiting into (receipt time, Frame) pairs for core/balance_loop.py, which decodes
them. No receive thread: a python-can Notifier woke 1000-2000 times a second and competed with
the control thread for the GIL (docs/benchmarks.md). A reply is thus known to one tick (2 ms),
well inside ``motor_timeout``.

A raw SocketCAN socket does not receive its own frames (``CAN_RAW_RECV_OWN_MSGS`` is off by
default), and python-can's ``receive_own_messages`` is off; its udp_multicast test bus hands
them back all the same (every member of the group, the sender too, gets each datagram). Such an
echo of a frame sent within ECHO_WINDOW is dropped here, before it is decoded, counted or
added to the bus load: on the test bus four of a tick's eight received frames were echoes. Not
only those of the frames since the previous poll: on a loaded machine an echo can come after
it, and would pass for another sender's command to our motors (a FAULT, core/balance_loop.py).

On SocketCAN python-can opens, binds and configures the raw socket (error frames, its kernel
filter), and the frames of the loop are read and written on that socket directly, one
``struct can_frame`` of <linux/can.h> each (``raw_socket_of``): python-can's recv and send
cost three times as much per frame, 6 % of a core at the six-motor node's 500 Hz traffic
(the benchmark's bus part, docs/benchmarks.md). Every other interface goes through python-can.
"""
import select
import socket
import struct
import threading
import time
from typing import Callable, Iterable, List, Optional, Tuple

import can
from can.interfaces.socketcan import SocketcanBus
from can.interfaces.socketcan.constants import CAN_EFF_FLAG, CAN_ERR_FLAG, CAN_RTR_FLAG
from can.interfaces.udp_multicast import UdpMulticastBus

from . import socketcan_hub
from ..core.can_budget import frame_bits
from ..core.protocols.base import Frame
from ..processes import StartError


def hands_back_own_frames(bus: can.BusABC) -> bool:
    """
    Tell whether the bus gives the sender its own frames back (echoes; see the module docstring).

    udp_multicast always does; python-can's virtual bus when asked to (receive_own_messages);
    SocketCAN's raw sockets do not by default.
    """
    return isinstance(bus, UdpMulticastBus) or bool(getattr(bus, 'receive_own_messages', False))


#: struct can_frame of <linux/can.h>: can_id with the EFF/RTR/ERR flags (python-can's
#: socketcan constants), len, two pad bytes and len8_dlc, data[8] (the layout of python-can's
#: build_can_frame and capture_message).
CAN_FRAME = struct.Struct('=IB3x8s')
#: The identifier bits of an extended and of a standard can_id (<linux/can.h>).
CAN_EFF_MASK = 0x1FFFFFFF
CAN_SFF_MASK = 0x7FF
#: Error and remote frames carry no data for the loop: counted and dropped.
_NO_DATA_FLAGS = CAN_ERR_FLAG | CAN_RTR_FLAG
#: frame_bits (core/can_budget.py) of 0..8 data bytes, standard and extended: looked up per
#: frame instead of called (a call with its min and max cost more than the rest of a frame's
#: bookkeeping).
_STANDARD_BITS = tuple(frame_bits(n, False) for n in range(9))
_EXTENDED_BITS = tuple(frame_bits(n, True) for n in range(9))


def raw_socket_of(bus: can.BusABC) -> Optional[socket.socket]:
    """
    Return the raw CAN socket under ``bus`` when frames may go on it directly, else None.

    That is a python-can SocketcanBus of classic CAN frames with no filter of its own: a
    filter python-can runs in Python, or CAN FD frames (72 bytes), keep python-can's path.
    """
    if isinstance(bus, SocketcanBus) and bus.protocol is can.CanProtocol.CAN_20 \
            and not bus.filters:
        return getattr(bus, 'socket', None)
    return None


def _os_error_text(action: str, exc: OSError) -> str:
    # The text python-can's SocketcanBus gives the same failure.
    return 'CanOperationError: Failed to %s: [Errno %s] %s' % (action, exc.errno, exc.strerror)


#: IP_MULTICAST_TTL of the udp_multicast test bus: 0, this host only.
UDP_HOP_LIMIT = 0


def open_bus(interface: str, channel: str, udp_port: int = 43113) -> can.BusABC:
    """
    Open the bus with python-can.

    socketcan on the robot (bitrate is set with `ip link`, 1 Mbit/s), ``virtual`` in one
    process, ``udp_multicast`` between processes (channel = multicast group; udp_port keeps
    concurrent test runs apart, since a socket bound to the port sees every joined group).
    The udp_multicast test bus never leaves the machine: hop limit (TTL) 0, so its frames
    reach only this host's sockets (python-can's default, 1, would put them on the LAN).
    ``socketcan_hub`` (channel = the hub's '127.0.0.1:PORT'): python-can's SocketcanBus
    between processes without SocketCAN, for benchmarks and tests (nodes/socketcan_hub.py).
    """
    if interface == socketcan_hub.INTERFACE:
        return socketcan_hub.HubSocketcanBus.join(channel)
    if interface == 'udp_multicast':
        return can.Bus(interface=interface, channel=channel, port=udp_port,
                       hop_limit=UDP_HOP_LIMIT)
    return can.Bus(interface=interface, channel=channel)


def open_bus_or_fail(interface: str, channel: str, udp_port: int = 43113,
                     what: str = 'the CAN bus') -> can.BusABC:
    """open_bus; a bus that does not open is a StartError: which, why, what to check."""
    try:
        return open_bus(interface, channel, udp_port)
    except Exception as exc:  # noqa: B902 -- python-can raises what its back-end raises
        if interface == 'socketcan':
            fix = ('is %s there and up? (ip link show %s; ip link set %s up type can bitrate '
                   '1000000); else set can.interface / can.channel' % ((channel,) * 3))
        else:
            fix = 'check can.interface, can.channel and can.udp_port'
        raise StartError('cannot open %s %s:%s' % (what, interface, channel),
                         '%s: %s' % (type(exc).__name__, exc), fix) from exc


#: How long a sent frame's echo is waited for [s] (buses that hand them back).
ECHO_WINDOW = 0.1
#: Frames one poll reads at most. A 1 Mbit/s bus carries at most about 18 frames per 2 ms tick;
#: udp_multicast also loops the node's own frames back.
MAX_FRAMES_PER_POLL = 64


class CanIo:
    """
    Send frames and collect received ones on one bus.

    Counters: tx_frames, tx_errors, rx_frames, rx_errors, rx_echoes (own frames the bus handed
    back, dropped); last_tx_error / last_rx_error hold the newest error text; bits: the bit
    times of the data frames sent and received (core/can_budget.py, worst-case stuffing), for
    the bus load. raw_frames: False keeps python-can's recv and send on SocketCAN too (the
    benchmark's comparison); ``raw`` is the socket the frames go on directly (None: python-can).
    """

    def __init__(self, bus: can.BusABC, send_timeout: float = 0.0005,
                 clock: Callable[[], float] = time.monotonic, raw_frames: bool = True):
        self.bus = bus
        self.raw = raw_socket_of(bus) if raw_frames else None
        # The udp_multicast test bus sends without waiting: for a send timeout python-can puts
        # its one socket in timeout mode, and CPython then polls before every recvmsg and
        # sendto (three system calls per reply instead of two); a full socket buffer is a
        # send error at once, as a full SocketCAN TX queue is.
        self.send_timeout = 0.0 if isinstance(bus, UdpMulticastBus) else send_timeout
        self._clock = clock
        self.tx_frames = 0
        self.tx_errors = 0
        self.rx_frames = 0
        self.rx_errors = 0
        self.rx_echoes = 0
        self.bits = 0
        # Echoes are looked for only where the bus makes them: the robot's sends pay nothing.
        self._track_echoes = hands_back_own_frames(bus)
        #: (arbitration ID, data, extended) of the frames sent whose echo has not come -> send
        #: times [s], oldest first (forgotten after ECHO_WINDOW).
        self._sent = {}
        self.last_tx_error = ''
        self.last_rx_error = ''
        self._lock = threading.Lock()
        self._closed = False

    def poll(self, into: List[Tuple[float, Frame]],
             max_frames: int = MAX_FRAMES_PER_POLL) -> int:
        """
        Append the data frames received since the last call to ``into``; return how many.

        Never blocks and never raises: a receive error is counted (rx_errors, last_rx_error)
        and ends this poll. At most ``max_frames`` are read, so an error-frame storm cannot
        hold the tick; the rest wait for the next one. Error and remote frames are counted
        and dropped.
        """
        if self.raw is not None:
            return self._poll_raw(into, max_frames)
        n = frames = echoes = bits = 0
        with self._lock:
            if self._closed:
                return 0
            # One receipt time for the poll: the frames waited in the socket until now.
            now = self._clock()
            recv = self.bus.recv
            sent = self._sent
            try:
                while n < max_frames:
                    msg = recv(timeout=0.0)
                    if msg is None:
                        break
                    n += 1
                    if msg.is_error_frame or msg.is_remote_frame:
                        frames += 1
                        continue
                    data = bytes(msg.data)
                    extended = msg.is_extended_id
                    if sent:   # standard and extended IDs (CyberGear) alike
                        key = (msg.arbitration_id, data, extended)
                        times = sent.get(key)
                        if times:   # our own frame, handed back by the bus
                            del times[0]
                            if not times:
                                del sent[key]
                            echoes += 1
                            continue
                    frames += 1
                    bits += frame_bits(len(data), extended)
                    into.append((now, Frame(msg.arbitration_id, data, extended)))
            except (can.CanError, OSError, ValueError) as exc:
                self.rx_errors += 1
                self.last_rx_error = '%s: %s' % (type(exc).__name__, exc)
            if sent:   # echoes that never came (a full socket buffer drops them)
                old = now - ECHO_WINDOW
                for key in [k for k, times in sent.items() if times[0] < old]:
                    times = [t for t in sent[key] if t >= old]
                    if times:
                        sent[key] = times
                    else:
                        del sent[key]
            self.rx_frames += frames
            self.rx_echoes += echoes
            self.bits += bits
        return n

    def _poll_raw(self, into: List[Tuple[float, Frame]], max_frames: int) -> int:
        # poll() on the raw CAN socket: one recv and one struct per frame, never blocking.
        n = frames = bits = 0
        with self._lock:
            if self._closed:
                return 0
            now = self._clock()
            recv, unpack, size = self.raw.recv, CAN_FRAME.unpack, CAN_FRAME.size
            dontwait = socket.MSG_DONTWAIT
            try:
                while n < max_frames:
                    try:
                        cf = recv(size, dontwait)
                    except (BlockingIOError, InterruptedError):
                        break
                    n += 1
                    if len(cf) != size:
                        raise ValueError('a %d-byte read is no CAN frame' % len(cf))
                    can_id, length, data = unpack(cf)
                    frames += 1
                    if can_id & _NO_DATA_FLAGS:
                        continue   # counted and dropped, as on python-can's path
                    if length > 8:
                        length = 8
                    if can_id & CAN_EFF_FLAG:
                        bits += _EXTENDED_BITS[length]
                        into.append((now, Frame(can_id & CAN_EFF_MASK, data[:length], True)))
                    else:
                        bits += _STANDARD_BITS[length]
                        into.append((now, Frame(can_id & CAN_SFF_MASK, data[:length], False)))
            except OSError as exc:
                self.rx_errors += 1
                self.last_rx_error = _os_error_text('receive', exc)
            except ValueError as exc:
                self.rx_errors += 1
                self.last_rx_error = 'ValueError: %s' % exc
            self.rx_frames += frames
            self.bits += bits
        return n

    def send(self, frames: Iterable[Frame]) -> Optional[str]:
        """Send the frames in order; stop at the first failure and return its text (else None)."""
        with self._lock:  # the control loop and shutdown may both send
            if self._closed:
                return 'bus closed'
            if self.raw is not None:
                return self._send_raw(frames)
            now = self._clock() if self._track_echoes else 0.0
            for f in frames:
                msg = can.Message(arbitration_id=f.arbitration_id, data=f.data,
                                  is_extended_id=f.is_extended_id)
                try:
                    self.bus.send(msg, timeout=self.send_timeout)
                except (can.CanError, OSError, ValueError) as exc:
                    self.tx_errors += 1
                    self.last_tx_error = '%s: %s' % (type(exc).__name__, exc)
                    return self.last_tx_error
                self.tx_frames += 1
                self.bits += frame_bits(len(f.data), f.is_extended_id)
                if self._track_echoes:   # the loop's frames
                    key = (f.arbitration_id, bytes(f.data), f.is_extended_id)
                    self._sent.setdefault(key, []).append(now)
            return None

    def _send_raw(self, frames: Iterable[Frame]) -> Optional[str]:
        # send() on the raw CAN socket (the lock held). A full TX queue is ENOBUFS at once, as
        # through python-can; a full socket buffer waits up to send_timeout for room, as
        # python-can's select before each send does.
        send, pack, size = self.raw.send, CAN_FRAME.pack, CAN_FRAME.size
        dontwait = socket.MSG_DONTWAIT
        bits = sent_frames = 0
        error = None
        for f in frames:
            data = f.data
            length = len(data)
            try:
                if length > 8:
                    raise ValueError('%d data bytes in a classic CAN frame' % length)
                if f.is_extended_id:
                    cf = pack(f.arbitration_id | CAN_EFF_FLAG, length, data)
                    frame_bits_ = _EXTENDED_BITS[length]
                else:
                    cf = pack(f.arbitration_id, length, data)
                    frame_bits_ = _STANDARD_BITS[length]
                try:
                    sent = send(cf, dontwait)
                except BlockingIOError:
                    select.select([], [self.raw], [], self.send_timeout)
                    sent = send(cf, dontwait)
                if sent != size:
                    raise ValueError('sent %d of %d bytes' % (sent, size))
            except OSError as exc:
                error = self.last_tx_error = _os_error_text('transmit', exc)
            except (ValueError, struct.error) as exc:
                error = self.last_tx_error = '%s: %s' % (type(exc).__name__, exc)
            else:
                sent_frames += 1
                bits += frame_bits_
                continue
            self.tx_errors += 1
            break
        self.tx_frames += sent_frames
        self.bits += bits
        return error

    def counters(self) -> dict:
        """Return the counters and last errors, as plain values."""
        return {'tx_frames': self.tx_frames, 'tx_errors': self.tx_errors,
                'last_tx_error': self.last_tx_error, 'rx_frames': self.rx_frames,
                'rx_errors': self.rx_errors, 'last_rx_error': self.last_rx_error,
                'rx_echoes': self.rx_echoes,
                'bits': self.bits}

    def close(self) -> None:
        """Shut the bus down (idempotent, never raises)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        try:
            self.bus.shutdown()
        except Exception:  # noqa: B902 -- closing must not fail the shutdown path
            pass
