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

from .bench import decode, MIT, TORQUE_LSB
from ...core.config import DEFAULTS
from ...core.protocols.base import Frame
from ...core.protocols.mit import MitCommand
from ...sim.motor_emulator import MitMotorBank, MitMotorEmulator

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
    Two MIT wheel motors on a bus: every frame to them is logged, their firmware answers.

    The motors are sim/motor_emulator.py's (``motors``, a MitMotorBank with the default
    configuration's directions, the joints still): each acts on its frames and answers every
    one with a reply on ID 0, as the firmware does. ``log`` holds (time [s], motor id, kind,
    torque [N m]) per frame, decoded as the firmware decodes it: kind 'torque' (torque-only
    command), 'command' (any other MIT command), 'enter', 'exit', 'zero'. Motors in ``silent``
    do not answer (they still act on the frames); ``answer=False`` makes a passive recorder
    (another device answers, e.g. sim_node); ``motor(id)`` is one motor's emulator, for its
    fault flags (``reply_id``: replies that carry another ID). ``wheel_torques()`` gives the
    torques the motors apply, as forward-positive wheel torques.
    """

    def __init__(self, bus: can.BusABC, ids=MOTOR_IDS, answer: bool = True):
        self.bus = bus
        self.ids = tuple(ids)
        self.answer = answer
        self.motors = MitMotorBank(self.ids, MOTOR_DIRECTIONS, MIT)
        self.silent = self.motors.silent
        self.last_reply: Dict[int, Optional[float]] = dict.fromkeys(self.ids)   # send time [s]
        self.log: List[Tuple[float, int, str, float]] = []
        self._lock = threading.Lock()   # the plant's thread reads the torques
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='fake_motors', daemon=True)
        self._thread.start()

    def motor(self, motor_id: int) -> MitMotorEmulator:
        """Return the emulator of one motor."""
        return self.motors.motor(motor_id)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self.bus.recv(0.05)
            except (can.CanError, OSError):
                continue
            if msg is None or msg.is_error_frame or msg.arbitration_id not in self.ids:
                continue
            t = msg.timestamp or time.time()
            motor = msg.arbitration_id
            frame = Frame(motor, bytes(msg.data), msg.is_extended_id)
            cmd = decode(motor, frame.data)
            if cmd is None:
                continue
            if isinstance(cmd, MitCommand):
                torque_only = cmd.kp == 0.0 and cmd.kd == 0.0
                self.log.append((t, motor, 'torque' if torque_only else 'command', cmd.torque))
            else:
                self.log.append((t, motor, cmd, 0.0))
            with self._lock:
                replies = self.motors.handle(frame, time.monotonic())
            if not self.answer:
                continue
            for reply in replies:
                try:
                    t_send = time.time()   # before the send: the node may take it at once
                    self.bus.send(can.Message(arbitration_id=reply.arbitration_id,
                                              data=reply.data, is_extended_id=False))
                    self.last_reply[motor] = t_send
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

    def zero_since(self, since: float) -> Optional[float]:
        """
        Time from which the motors get only zero torque or exit frames (latest over motors).

        Frames before ``since`` are ignored. None when a motor got no zero frame after its last
        non-zero torque (torque was never brought to zero).
        """
        t_zero = since
        for motor in self.ids:
            frames = [(t, tau) for t, kind, tau in self.frames(motor, since)
                      if kind in ('torque', 'exit', 'command')]
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


class ErrorFrameStorm:
    """
    CAN error frames at ``rate`` [frames/s] into the node's receive queue (a VirtualBus).

    Only the node's reader gets them, one shared Message object, no copy: on the robot the
    motors' CAN controllers drop error frames in hardware, and the storm must load the system
    under test, not the test. Sent with ``VirtualBus.send`` instead, every frame was deep-copied
    for every receiver on the channel (14 us of the sender per frame on the idle VM, more under
    load) and woke the fake motors' reader thread, all in the node's process and under its GIL:
    on a loaded 2-core machine the node's torque frames fell from 469/s to 285/s. The node's
    own share, a bounded poll that drops error frames, is about 1.4 us per frame.

    The frames go in bursts every ``BURST`` s (20 at 4000/s): the thread wakes 200 times a
    second, not 1000, each wake a GIL hand-over in the node's process. ``on`` gates it: cleared,
    the thread sends nothing (windows with and without the storm on one rig).
    """

    #: Seconds between two bursts.
    BURST = 0.005

    def __init__(self, receiver: VirtualBus, rate: float = 4000.0):
        self.queue = receiver.queue
        self.rate = rate
        self.sent = 0
        self.on = threading.Event()
        self.on.set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='error_storm', daemon=True)

    def start(self) -> 'ErrorFrameStorm':
        self._thread.start()
        return self

    def _run(self) -> None:
        # Error class "bus error" + "protocol violation" (linux/can/error.h), as socketcan
        # delivers them with the error filter open.
        msg = can.Message(arbitration_id=0x088, is_error_frame=True, dlc=8,
                          data=bytes(8), is_extended_id=False, is_rx=True)
        batch = max(1, int(round(self.rate * self.BURST)))
        put = self.queue.put_nowait
        t_next = time.monotonic()
        while not self._stop.is_set():
            if not self.on.is_set():
                self.on.wait(0.05)
                t_next = time.monotonic()
                continue
            for _ in range(batch):
                put(msg)
            self.sent += batch
            t_next += batch / self.rate
            delay = t_next - time.monotonic()
            if delay > 0.0:
                time.sleep(delay)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
