"""
balance_node's watchdog: zero torque and exit frames when the control process stalls or dies.

The control process (nodes/control_process.py) sends the motors their torque every 2 ms and,
when it ends in an orderly way (STOP, a signal, the ROS side gone), zero torque and the
exit-motor-mode frames. Two things it cannot do itself: send those frames when it is killed
(SIGKILL, the OOM killer, a crash in C code) and when it hangs (a deadlock, a stopped process,
a stall that never ends). The MIT motors then hold the last torque (up to 12 N m) for as long
as their own command timeout allows, which is "forever" unless it was set by hand
(docs/robot_setup.md). The watchdog is a third process, without rclpy (so the DDS stalls of
docs/benchmarks.md cannot reach it) and without the control thread's code paths: it reads a
heartbeat the loop writes into shared memory at every pass of its loop, and when the loop is
commanding the motors and

- its heartbeat is older than ``watchdog_timeout`` (a stall), or
- its process has ended without clearing the commanding flag (killed),

it kills the control process (so a stalled loop cannot resume with a stale torque), sends zero
torque and then exit-motor-mode to every motor on its own CAN socket, and records why in the
shared memory for /diagnostics (nodes/diagnostics.py). balance_node starts it beside the
control process and arms only once it runs; it ends with its parent (PR_SET_PDEATHSIG), after
giving a commanding control process the same time to end cleanly.

With ``clock_source: imu_stamp`` (lockstep with a simulator, which may take longer than
``watchdog_timeout`` between two ticks on a loaded machine) only a tick writes the heartbeat,
and the limit is ``lockstep_wall_timeout`` + ``watchdog_timeout`` (``stall_limit``): the loop's
own guard (FAULT imu_stale after ``lockstep_wall_timeout`` without a sample) comes first, the
watchdog catches a loop that hangs.

The heartbeat (``Heartbeat``): 24 bytes in a memfd both processes map: the loop's monotonic
time [s, float64] and flags [uint32] (written by the control process only), the watchdog's
state [uint32] and the stall it saw [s, float64] (written by the watchdog only).
"""
import argparse
import mmap
import os
import signal
import struct
import sys
import time
from typing import Callable, Optional, Tuple

from ..processes import Child, end_process, run_child, StartError

#: Written by the control process: the time of its loop's newest pass [s], flags.
_LOOP = struct.Struct('<dI')
#: Written by the watchdog at offset 12: its state, the heartbeat age that made it fire [s].
_DOG = struct.Struct('<Id')
_DOG_OFFSET = 12
SIZE = 24

#: Loop flags: the motors are commanded (BALANCING, HOMING, SITTING: a torque that is not zero
#: may be in the motors); the loop has ended after its stop frames.
COMMANDING = 1
ENDED = 2
#: Watchdog states.
STARTING, WATCHING, FIRED_STALL, FIRED_DIED, ENDED_CLEAN = 0, 1, 2, 3, 4
#: Not a state in the shared memory: the heartbeat is unmapped (balance_node shutting down).
CLOSED = 5
STATE_TEXT = {STARTING: 'starting', WATCHING: 'watching',
              FIRED_STALL: 'fired: the control loop stalled',
              FIRED_DIED: 'fired: the control process died while commanding',
              ENDED_CLEAN: 'ended', CLOSED: 'closed (node shutting down)'}
#: Polls per watchdog_timeout (the reaction is the timeout plus at most one poll).
POLLS_PER_TIMEOUT = 10
#: A stale heartbeat is read again this much later before the watchdog fires [s]: two reads
#: that agree, so a torn read of the 8-byte time cannot fire it.
CONFIRM_DELAY = 0.001


class Heartbeat:
    """The shared memory of the loop and the watchdog (see the module docstring)."""

    def __init__(self, fd: Optional[int] = None):
        """Create it (fd None: a new memfd) or map the one inherited as ``fd``."""
        if fd is None:
            fd = os.memfd_create('wheelleg_balance_heartbeat', 0)
            os.ftruncate(fd, SIZE)
        self.fd = fd
        self._map = mmap.mmap(fd, SIZE)

    def beat(self, now: float, commanding: bool) -> None:
        """Record a pass of the control loop at ``now`` [s, CLOCK_MONOTONIC]."""
        _LOOP.pack_into(self._map, 0, now, COMMANDING if commanding else 0)

    def end(self) -> None:
        """Record that the loop sent its stop frames and ends: nothing left to guard."""
        _LOOP.pack_into(self._map, 0, time.monotonic(), ENDED)

    def loop(self) -> Tuple[float, int]:
        """Return (time of the loop's newest pass [s], flags)."""
        return _LOOP.unpack_from(self._map, 0)

    def set_state(self, state: int, stall: float = 0.0) -> None:
        """Record the watchdog's state (and the heartbeat age [s] it fired at)."""
        _DOG.pack_into(self._map, _DOG_OFFSET, state, stall)

    def state(self) -> Tuple[int, float]:
        """Return (the watchdog's state, the heartbeat age [s] it fired at); CLOSED once closed."""
        try:
            return _DOG.unpack_from(self._map, _DOG_OFFSET)
        except ValueError:   # unmapped by close() in another thread (a diagnostics timer)
            return CLOSED, 0.0

    def describe(self) -> dict:
        """Return the watchdog's state for /diagnostics."""
        state, stall = self.state()
        return {'state': state, 'text': STATE_TEXT.get(state, 'unknown state %d' % state),
                'fired': state in (FIRED_STALL, FIRED_DIED), 'stall': stall}

    def close(self) -> None:
        """Unmap it (the fd stays open for the caller to close)."""
        self._map.close()


class Watchdog:
    """
    The decision: fire when the commanding loop's heartbeat is stale or its process is gone.

    heartbeat: the shared Heartbeat; timeout: watchdog_timeout [s]; alive(): True while the
    control process runs; fire(state, age): kill it and send the stop frames; clock: monotonic;
    sleep(dt): wait up to dt [s] (the process: until the control process ends, at the latest).
    """

    def __init__(self, heartbeat: Heartbeat, timeout: float, alive: Callable[[], bool],
                 fire: Callable[[int, float], None],
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep):
        self.heartbeat = heartbeat
        self.timeout = timeout
        self.alive = alive
        self._fire = fire
        self.clock = clock
        self.sleep = sleep
        self.fired = False

    def check(self) -> bool:
        """Look once; fire if due. Return True while there is something left to watch."""
        t, flags = self.heartbeat.loop()
        if flags & ENDED:
            self.heartbeat.set_state(ENDED_CLEAN)
            return False
        if not self.alive():
            if flags & COMMANDING:
                self._trigger(FIRED_DIED, self.clock() - t)
            else:
                self.heartbeat.set_state(ENDED_CLEAN)
            return False
        if flags & COMMANDING and self.clock() - t > self.timeout:
            self.sleep(CONFIRM_DELAY)
            t2, flags2 = self.heartbeat.loop()
            if t2 == t and flags2 & COMMANDING:
                self._trigger(FIRED_STALL, self.clock() - t)
                return False
        return True

    def _trigger(self, state: int, age: float) -> None:
        self.fired = True
        self._fire(state, age)
        self.heartbeat.set_state(state, age)

    def run(self, stopping: Callable[[], bool]) -> None:
        """Check every timeout / POLLS_PER_TIMEOUT until done; once ``stopping()``, one timeout."""
        self.heartbeat.set_state(WATCHING)
        poll = self.timeout / POLLS_PER_TIMEOUT
        give_up = None
        while self.check():
            if give_up is None and stopping():
                # balance_node is ending: the control process got its signal too. Give it the
                # timeout to send its own stop frames; still commanding after that: fire.
                give_up = self.clock() + self.timeout
            if give_up is not None and self.clock() >= give_up:
                t, flags = self.heartbeat.loop()
                if flags & COMMANDING:
                    self._trigger(FIRED_STALL, self.clock() - t)
                break
            self.sleep(poll)


def stall_limit(cfg) -> float:
    """Return the heartbeat age [s] that is a stall for configuration ``cfg`` (the docstring)."""
    timeout = cfg.safety.watchdog_timeout
    if cfg.loop.clock_source == 'imu_stamp':
        return cfg.loop.lockstep_wall_timeout + timeout
    return timeout


#: The watchdog's module (started by balance_node as processes.Child).
MODULE = 'wheelleg_balance.nodes.watchdog'


def plan(params: dict) -> dict:
    """
    Return what the watchdog needs of the flat configuration ``params``.

    Its buses (channel, the frames that stop their motors: zero torque, exit motor mode), the
    stall limit [s], the real-time priority. Worked out in balance_node's process, which has the
    configuration's modules loaded anyway: the watchdog process then starts on python-can alone,
    without numpy or the control core (docs/benchmarks.md, "Start-up").
    """
    from ..core.sensing import all_stop_frames
    from ..core.config import BalanceConfig
    from ..core.schema import from_flat
    cfg = from_flat(BalanceConfig, params)
    wheel_frames, leg_frames = all_stop_frames(cfg)
    buses = [(cfg.can.channel, wheel_frames)]
    if leg_frames:
        if cfg.legs.channel and cfg.legs.channel != cfg.can.channel:
            buses.append((cfg.legs.channel, leg_frames))
        else:
            buses[0] = (cfg.can.channel, wheel_frames + leg_frames)
    return {'interface': cfg.can.interface, 'udp_port': cfg.can.udp_port,
            'raw_frames': cfg.can.raw_frames, 'limit': stall_limit(cfg),
            'realtime_priority': cfg.loop.realtime_priority,
            'buses': [[channel, [[f.arbitration_id, f.data.hex(), f.is_extended_id]
                                 for f in frames]] for channel, frames in buses]}


def arguments(heartbeat_fd: int, pid: int, params: dict):
    """Return the arguments of the watchdog of control process ``pid`` (flat ``params``)."""
    import json
    return ['--heartbeat-fd', str(heartbeat_fd), '--pid', str(pid), '--plan',
            json.dumps(plan(params))]


class WatchdogProcess:
    """
    balance_node's side of the watchdog: its heartbeat, its process, its state.

    ``heartbeat.fd`` goes to the control process (``--heartbeat-fd``); ``start`` then starts the
    watchdog for that process's pid; ``wait`` returns once it watches (no arming before).
    """

    def __init__(self, timeout: float):
        self.heartbeat = Heartbeat()
        self.timeout = timeout
        self.process = None
        self.child = None

    def start(self, pid: int, params: dict) -> None:
        """Start the watchdog of control process ``pid`` (``params``: flat configuration)."""
        self.child = Child('the watchdog', MODULE, arguments(self.heartbeat.fd, pid, params),
                           pass_fds=(self.heartbeat.fd,))
        self.process = self.child.process

    def wait(self, until: float) -> None:
        """
        Wait until it has started, at most until ``until`` [s, monotonic]; StartError if not.

        Started is any state past STARTING: on a loaded machine the loop may arm (it arms only
        once the watchdog watches), fault and be fired on before this polls, and a watchdog
        that fired is one that works (/diagnostics reports its firing).
        """
        while self.heartbeat.state()[0] == STARTING and time.monotonic() < until \
                and self.process.poll() is None:
            time.sleep(0.02)
        if self.heartbeat.state()[0] == STARTING:
            line = self.child.failure(wait=1.0) if self.child is not None else None
            raise StartError(line or 'the watchdog did not start (exit code %s)'
                             % self.process.poll())
        if self.child is not None:
            self.child.started()

    def state(self) -> dict:
        """Return its state for /diagnostics (Heartbeat.describe, running, timeout)."""
        out = self.heartbeat.describe()
        out['running'] = self.process is not None and self.process.poll() is None
        out['timeout'] = self.timeout
        return out

    def close(self) -> None:
        """End it (it ends by itself once the loop has ended) and free the shared memory."""
        if self.process is not None:
            end_process(self.process, timeout=1.0)
        if self.child is not None:
            self.child.started()   # closes the report pipe
        self.heartbeat.close()
        os.close(self.heartbeat.fd)


def _process_watch(pid: int) -> Tuple[Callable[[], bool], Callable[[float], None]]:
    """
    Return (alive(), wait(dt)) for process ``pid``, on a pidfd (no confusion with a reused pid).

    A pidfd turns readable when the process ends: wait(dt) sleeps dt [s] or until then, so a
    killed control process is noticed at once, not at the next poll.
    """
    import select
    try:
        pidfd = os.pidfd_open(pid)
    except OSError:
        return (lambda: False), time.sleep

    def alive() -> bool:
        try:
            return not select.select([pidfd], [], [], 0)[0]
        except OSError:
            return False

    def wait(dt: float) -> None:
        try:
            select.select([pidfd], [], [], dt)
        except OSError:
            time.sleep(dt)
    return alive, wait


def main(argv=None) -> int:
    """Watch the control process of the balance_node that started this process."""
    import json
    from .can_io import CanIo, open_bus_or_fail
    from .sensor_intake import die_with_parent
    from ..core import realtime
    from ..core.protocols.base import Frame

    parser = argparse.ArgumentParser(description='balance_node watchdog (started by '
                                     'balance_node, not by hand)')
    parser.add_argument('--heartbeat-fd', type=int, required=True)
    parser.add_argument('--pid', type=int, required=True, help='the control process')
    parser.add_argument('--plan', required=True, help='its buses and frames as JSON (plan)')
    args = parser.parse_args(argv)
    die_with_parent()
    stopping = []
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT):
        signal.signal(signum, lambda s, f: stopping.append(s))
    todo = json.loads(args.plan)
    heartbeat = Heartbeat(args.heartbeat_fd)
    send_timeout = 0.01
    buses = []
    for channel, frames in todo['buses']:
        buses.append((CanIo(open_bus_or_fail(todo['interface'], channel, todo['udp_port'],
                                             "the watchdog's CAN bus"), send_timeout,
                            raw_frames=todo['raw_frames']),
                      [Frame(i, bytes.fromhex(data), ext) for i, data, ext in frames]))
    # Above the loop: the watchdog sleeps nearly always, and must run when the loop spins.
    if todo['realtime_priority'] > 0:
        realtime.set_fifo_priority(min(99, todo['realtime_priority'] + 1))
    alive, wait = _process_watch(args.pid)

    def fire(state: int, age: float) -> None:
        if state == FIRED_STALL:
            try:
                os.kill(args.pid, signal.SIGKILL)   # a stalled loop must not come back
            except OSError:
                pass
        for io, frames in buses:
            for f in frames:   # one by one: a failed send must not keep the others back
                io.send([f])
        print('balance_node watchdog: %s (heartbeat %.0f ms old): zero torque and exit '
              'motor mode sent to every motor; restart balance_node'
              % (STATE_TEXT[state], 1e3 * age), file=sys.stderr, flush=True)

    dog = Watchdog(heartbeat, todo['limit'], alive, fire, sleep=wait)
    try:
        dog.run(lambda: bool(stopping))
    finally:
        for io, _ in buses:
            io.close()
        heartbeat.close()
    return 0


if __name__ == '__main__':
    sys.exit(run_child('the watchdog', main))
