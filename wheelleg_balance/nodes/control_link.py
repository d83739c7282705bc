"""
The link between balance_node's ROS side and its control loop: one socket pair, never blocking.

The control loop runs in a process of its own (nodes/control_process.py) so nothing the rclpy
executor, the parameter and service machinery or DDS discovery does can delay a tick
(docs/benchmarks.md, "The 0.33 s stall"). The two sides talk over an AF_UNIX SOCK_SEQPACKET
socket pair: message boundaries are kept, a message is delivered whole or not at all, the kernel
does the synchronization (no shared-memory ordering questions on ARM), and when one side dies
the other reads end-of-file at once.

Every message is a tag byte and a payload. The frequent ones (sensor samples to the loop, the
state from it) are fixed struct layouts; the rare ones (arm requests and replies, parameter
changes, status for /diagnostics, log lines) are pickled. Both ends are non-blocking: a sender
that finds the socket full drops the message and counts it (``dropped``), since waiting would
let a stalled reader stall the writer.
"""
from array import array
import os
import pickle
import socket
import struct
import sys
from typing import Any, Callable, Iterator, Optional, Tuple

from ..core.sensors import ImuSample, JointSample
from ..core.tick_io import CmdHeight, CmdVel, FRAME_FIELDS

# Tags: ROS side -> control loop.
IMU = b'I'
JOINTS = b'J'
CMD_VEL = b'C'
CMD_HEIGHT = b'H'
ESTOP = b'X'        # emergency stop: zero torque, exit motor mode, no sit-down
ARM = b'A'          # (request id, bool, or an identification phase's name)
PARAMS = b'P'       # {name: value}
STOP = b'S'         # shut down: zero torque, exit motor mode, end
CONFLICTS = b'K'    # {input: why} inputs refused for their publishers (nodes/input_guard.py)
WANTED = b'W'       # the state frame's publication flags that have subscribers (tick_io.py)
# Tags: control loop -> ROS side.
STATE = b's'        # ~/state values, the odometry, the tick's time (and the joints' values)
ARM_REPLY = b'a'    # (request id, success, message)
STATUS = b'd'       # the loop's status dict (core/balance_loop.BalanceLoop.status + timing)
EVENT = b'e'        # (level, text) to log
READY = b'r'        # the loop runs (payload: a text for the log)

_IMU = struct.Struct('<dqq4d?7d')
_JOINTS = struct.Struct('<d?dd?d')
_CMD = struct.Struct('<3d')
_CMD_HEIGHT = struct.Struct('<2d')
#: STATE payload: the state frame (core/tick_io.py: the state, the odometry, the tick's time,
#: the publication flags); then, when the joint_states are due, the published joints'
#: positions, velocities and efforts.
_STATE = struct.Struct('<%dd' % len(FRAME_FIELDS))

#: Largest message [bytes]: a status dict of many motors stays below this.
MAX_MESSAGE = 65536


def socket_pair() -> Tuple[socket.socket, socket.socket]:
    """Return (ROS side, control side), both non-blocking and close-on-exec."""
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    for s in (a, b):
        s.setblocking(False)
    return a, b


class Link:
    """
    One end of the link: ``send_*`` never block, ``receive`` drains what arrived.

    closed: the other end was seen to close (end-of-file) or the socket failed.
    """

    def __init__(self, sock: socket.socket):
        self.sock = sock
        self.sent = 0
        self.dropped = 0
        self.closed = False

    @classmethod
    def from_fd(cls, fd: int) -> 'Link':
        """Adopt an inherited socket file descriptor (the control process's end)."""
        sock = socket.socket(fileno=fd)
        sock.setblocking(False)
        return cls(sock)

    def fileno(self) -> int:
        """Return the socket's file descriptor."""
        return self.sock.fileno()

    def _send(self, message: bytes) -> bool:
        if self.closed:
            return False
        try:
            self.sock.send(message)
        except (BlockingIOError, InterruptedError):
            self.dropped += 1
            return False
        except OSError:
            self.closed = True
            return False
        self.sent += 1
        return True

    def send_imu(self, s: ImuSample) -> bool:
        """Send one IMU sample."""
        return self._send(IMU + _IMU.pack(*s))

    def send_joints(self, s: JointSample) -> bool:
        """Send one joint sample."""
        return self._send(JOINTS + _JOINTS.pack(*s))

    def send_cmd_vel(self, c: CmdVel) -> bool:
        """Send the newest cmd_vel."""
        return self._send(CMD_VEL + _CMD.pack(*c))

    def send_cmd_height(self, c: CmdHeight) -> bool:
        """Send the newest cmd_height."""
        return self._send(CMD_HEIGHT + _CMD_HEIGHT.pack(*c))

    def send_state(self, values, joints=()) -> bool:
        """
        Send a state frame (core/tick_io.py ``state_frame``).

        joints: positions + velocities + efforts of the published joints (floats), in the same
        message (one wake-up of the ROS side, not two); received as the pair (state, joints).
        """
        return self._send(STATE + _STATE.pack(*values)
                          + struct.pack('<%dd' % len(joints), *joints))

    def send_object(self, tag: bytes, obj: Any) -> bool:
        """Send a rare message with a pickled payload (arm, params, status, events)."""
        return self._send(tag + pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL))

    def receive(self, limit: int = 256) -> Iterator[Tuple[bytes, Any]]:
        """
        Yield (tag, payload) for each message waiting, at most ``limit``, without blocking.

        Payloads: ImuSample, JointSample, CmdVel, the state and joint values (a pair of
        array('d')), or the unpickled object.
        An end-of-file or a socket error sets ``closed`` and ends the iteration.
        """
        for _ in range(limit):
            try:
                data = self.sock.recv(MAX_MESSAGE)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self.closed = True
                return
            if not data:
                self.closed = True
                return
            yield decode(data)

    def wait_readable(self, timeout: float) -> bool:
        """Block up to ``timeout`` [s] until a message (or end-of-file) is waiting."""
        import select
        try:
            readable, _, _ = select.select([self.sock], [], [], timeout)
        except (OSError, ValueError):
            self.closed = True
            return True
        return bool(readable)

    def close(self) -> None:
        """Close this end (idempotent)."""
        self.closed = True
        try:
            self.sock.close()
        except OSError:
            pass


_DECODERS: dict = {
    IMU: lambda p: ImuSample(*_IMU.unpack(p)),
    JOINTS: lambda p: JointSample(*_JOINTS.unpack(p)),
    CMD_VEL: lambda p: CmdVel(*_CMD.unpack(p)),
    CMD_HEIGHT: lambda p: CmdHeight(*_CMD_HEIGHT.unpack(p)),
    STATE: lambda p: (_doubles(p[:_STATE.size]), _doubles(p[_STATE.size:])),
}


def _doubles(data: bytes) -> array:
    """Little-endian float64s as an array('d'): what ROS messages' float64[] take unchecked."""
    out = array('d', data)
    if sys.byteorder != 'little':
        out.byteswap()
    return out


def decode(data: bytes) -> Tuple[bytes, Any]:
    """(tag, payload) of one message (see ``Link.receive``)."""
    tag, payload = data[:1], data[1:]
    decoder: Optional[Callable] = _DECODERS.get(tag)
    if decoder is not None:
        return tag, decoder(payload)
    return tag, pickle.loads(payload)


def inheritable(sock: socket.socket) -> int:
    """Mark a socket inheritable for a child process; return its file descriptor."""
    fd = sock.fileno()
    os.set_inheritable(fd, True)
    return fd
