"""
Test doubles on the CAN side: a bus that fails on send, the motors on a bus, an error-frame storm.

Times are wall-clock seconds (``time.time``), the clock python-can stamps frames with.
"""
import math
import threading
import time
from typing import Dict, List, Optional, Tuple

import can
from can.interfaces.virtual import VirtualBus

from .bench import emulated_motors, MIT, TORQUE_LSB
from ...core.config import DEFAULTS
from ...core.protocols.base import Frame, MotorProtocol
from ...core.protocols.emulation import EmulatedMotor

#: The wheel motors' IDs and directions of the default configuration.
MOTOR_IDS = (DEFAULTS.can.left_motor_id, DEFAULTS.can.right_motor_id)
MOTOR_DIRECTIONS = {DEFAULTS.can.left_motor_id: DEFAULTS.can.left_direction,
                    DEFAULTS.can.right_motor_id: DEFAULTS.can.right_direction}


class FlakyBus(VirtualBus):
    """
    A virtual bus whose ``send`` raises ``fail_with`` (an exception instance) while set.

    ``first_failure`` is the wall-clock time [s] of the first send that raised (None before):
    a send already past the check when ``fail_with`` was set still reaches the bus, so "nothing
    got out while sends failed" is measured from here, not from when the fault was set.
    """

    fail_with: Optional[BaseException] = None
    first_failure: Optional[float] = None

    def send(self, msg, timeout=None):
        error = self.fail_with
        if error is not None:
            if self.first_failure is None:
                self.first_failure = time.time()
            raise error
        super().send(msg, timeout)


def tx_queue_full() -> can.CanOperationError:
    """Return what python-can's socketcan send raises on a full TX queue (ENOBUFS)."""
    return can.CanOperationError('Failed to transmit: [Errno 105] No buffer space available',
                                 105)


def bus_off() -> can.CanOperationError:
    """Return what python-can's socketcan send raises when bus-off (ENETDOWN)."""
    return can.CanOperationError('Failed to transmit: [Errno 100] Network is down', 100)


class FakeMotors:
    """
    Two wheel motors on a bus: every frame they act on is logged, their firmware answers.

    The motors are ``protocol``'s emulated firmware (``motors``: bench.emulated_motors, the
    protocol's make_emulator; MIT by default; ``directions`` those of the default configuration,
    the joints still): each acts on its frames and answers as its firmware does. ``log`` holds
    (time [s], motor id, kind, torque [N m]) per frame a motor acted on, read off the motor's state
    after it (``frame_kind``): kind 'torque' (a torque-only command in its torque mode), 'command'
    (any other impedance command), 'enter' (torque mode, no command yet), 'exit' (out of its torque
    mode). Motors in ``silent`` do not answer (they still act on the frames); ``answer=False``
    makes a passive recorder (another device answers, e.g. sim_node); ``motor(id)`` is one motor's
    emulator, for its fault flags (``reply_id``: replies that carry another ID).
    ``wheel_torques()`` gives the torques the motors apply, as forward-positive wheel torques.
    """

    def __init__(self, bus: can.BusABC, ids=MOTOR_IDS, answer: bool = True,
                 protocol: MotorProtocol = MIT, directions=None):
        self.bus = bus
        self.ids = tuple(ids)
        self.answer = answer
        self.motors = emulated_motors(protocol, self.ids, directions or MOTOR_DIRECTIONS)
        self.silent = self.motors.silent
        self.last_reply: Dict[int, Optional[float]] = dict.fromkeys(self.ids)   # send time [s]
        self.log: List[Tuple[float, int, str, float]] = []
        self._lock = threading.Lock()   # the plant's thread reads the torques
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='fake_motors', daemon=True)
        self._thread.start()

    def motor(self, motor_id: int) -> EmulatedMotor:
        """Return the emulator of one motor."""
        return self.motors.motor(motor_id)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self.bus.recv(0.05)
            except (can.CanError, OSError):
                continue
            if msg is None or msg.is_error_frame:
                continue
            t = msg.timestamp or time.time()
            frame = Frame(msg.arbitration_id, bytes(msg.data), msg.is_extended_id)
            emulators = self.motors.emulators
            with self._lock:
                before = {i: (e.frames, e.command) for i, e in emulators.items()}
                replies = self.motors.handle(frame, time.monotonic())
                acted = [i for i, e in emulators.items() if e.frames != before[i][0]]
                self.log.extend((t, i) + frame_kind(emulators[i], before[i][1])
                                for i in acted)
            if not self.answer:
                continue
            for reply in replies:
                try:
                    t_send = time.time()   # before the send: the node may take it at once
                    self.bus.send(can.Message(arbitration_id=reply.arbitration_id,
                                              data=reply.data,
                                              is_extended_id=reply.is_extended_id))
                    self.last_reply.update((i, t_send) for i in acted
                                           if i not in self.silent)
                except (can.CanError, OSError):
                    pass

    def wheel_torques(self) -> Tuple[float, float]:
        """Forward-positive (left, right) wheel torques being applied [N m]."""
        left, right = self.ids
        now = time.monotonic()
        with self._lock:
            return self.motors.torque(left, now), self.motors.torque(right, now)

    def frames(self, motor: int, since: float = 0.0, until: float = math.inf):
        """Return the logged (time, kind, torque) of one motor within [since, until)."""
        return [(t, kind, tau) for t, i, kind, tau in list(self.log)
                if i == motor and since <= t < until]

    def torques(self, motor: int, since: float = 0.0, until: float = math.inf) -> List[float]:
        """Torques [N m] of the torque-only commands to ``motor`` within [since, until)."""
        return [tau for _, kind, tau in self.frames(motor, since, until) if kind == 'torque']

    def zero_since(self, since: float,
                   kinds: Tuple[str, ...] = ('torque', 'exit', 'command')) -> Optional[float]:
        """
        Time from which the motors get only zero torque or exit frames (latest over motors).

        Frames before ``since`` are ignored, and frames of other ``kinds`` (of ``log``). None
        when a motor got no zero frame after its last non-zero torque (torque was never brought
        to zero).
        """
        t_zero = since
        for motor in self.ids:
            frames = [(t, tau) for t, kind, tau in self.frames(motor, since) if kind in kinds]
            bad = [k for k, (_, tau) in enumerate(frames) if abs(tau) > TORQUE_LSB]
            first = bad[-1] + 1 if bad else 0
            if first >= len(frames):
                return None
            t_zero = max(t_zero, frames[first][0])
        return t_zero

    def close(self) -> None:
        """Stop answering and close the bus."""
        self._stop.set()
        self._thread.join(1.0)
        self.bus.shutdown()


def frame_kind(motor: EmulatedMotor, command_before) -> Tuple[str, float]:
    """
    Return what a frame a motor just acted on was: (kind, torque [N m]), any protocol.

    Read off the emulator's state (``command_before``: its command before the frame): a new
    command is 'torque' (kp = kd = 0) or 'command' (any other impedance command) with its
    feed-forward torque, in the torque mode or not; else 'exit' outside the torque mode (a
    disable, a set-zero in rest) and 'enter' in it (an enable).
    """
    cmd = motor.command
    if cmd is not None and cmd is not command_before:
        return ('torque' if cmd.kp == 0.0 and cmd.kd == 0.0 else 'command'), cmd.torque
    return ('enter' if motor.enabled else 'exit'), 0.0


class ErrorFrameStorm:
    """
    CAN error frames at ``rate`` [frames/s] in the node's receive queue (a VirtualBus), while on.

    The storm lives in the node's reads: while on, each read of the node's bus first returns
    the error frames due by the clock since the storm came on (one shared Message, no copy),
    then the real frames. So the node pays what a storm on socketcan costs it, each frame read
    and dropped in its bounded poll (about 1.4 us), and the test pays nothing. Earlier versions
    cost the test: sent with ``VirtualBus.send`` every frame was deep-copied for every receiver
    and woke the fake motors' reader thread (14 us of the sender per frame; the node's torque
    frames fell from 469/s to 285/s on a loaded machine); put into the queue by a thread of its
    own, that thread's wake-ups took the GIL from the node's loop in the same process (the rig's
    loop, bound by the GIL at about 300 ticks/s, kept 86 to 99 % of its rate). On the robot the
    motors' CAN controllers drop error frames in hardware and socketcan delivers none to a socket
    without ``CAN_RAW_ERR_FILTER``.
    """

    def __init__(self, receiver: VirtualBus, rate: float = 4000.0):
        self._receiver = receiver
        self._queue = receiver.queue   # the senders' channel keeps putting the real frames here
        self._queue_get = self._queue.get
        self.rate = rate
        #: Error frames the node has read.
        self.sent = 0
        self._on_since: Optional[float] = None
        self._given = 0
        # Error class "bus error" + "protocol violation" (linux/can/error.h), as socketcan
        # delivers them with the error filter open.
        self._msg = can.Message(arbitration_id=0x088, is_error_frame=True, dlc=8,
                                data=bytes(8), is_extended_id=False, is_rx=True)

    def start(self) -> 'ErrorFrameStorm':
        """Stand between the node's bus and its queue (the storm off until ``set_on``)."""
        # The queue's own get is replaced, not the queue: VirtualBus.send tells the sender's
        # queue by identity, and a bus whose queue were another object would get its own
        # frames back (its torque commands, then, from another sender: input_conflict).
        self._queue.get = self.get
        return self

    def set_on(self, on: bool) -> None:
        """Start (True) or end the storm; frames come due from the moment it starts."""
        if on and self._on_since is None:
            self._given = 0
            self._on_since = time.monotonic()
        elif not on:
            self._on_since = None

    def get(self, block: bool = True, timeout: Optional[float] = None):
        """Read as the node does (queue.Queue.get): a due error frame, else a real one."""
        since = self._on_since
        if since is not None and int((time.monotonic() - since) * self.rate) > self._given:
            self._given += 1
            self.sent += 1
            return self._msg
        return self._queue_get(block, timeout)

    def stop(self) -> None:
        """End the storm and give the node's queue its own get back."""
        self._on_since = None
        self._queue.__dict__.pop('get', None)
