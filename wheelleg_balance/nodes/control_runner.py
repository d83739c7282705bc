"""
The control loop of balance_node's control process: ``ControlRunner`` (no rclpy).

A DeadlineLoop (core/deadline.py) that, every period, drains the link to the ROS side
(nodes/control_link.py: sensor samples, cmd_vel, arm requests, parameter changes), polls the
CAN bus, runs ``BalanceLoop.tick`` (core/balance_loop.py), sends its frames, and sends back the
state frame (at the publication rates, those with a subscription on the ROS side), arm replies,
log lines and, five times a second or on a mode change, a status for /diagnostics. At every
pass it writes a heartbeat (the time, whether it commands the motors) into memory it shares
with the watchdog process (nodes/watchdog.py); no arm before the watchdog watches. It ends
with zero torque and exit-motor-mode frames.

nodes/control_process.py runs it as a process of its own; tests that hand balance_node an
in-process python-can bus run it in a thread. On a simulator's IMU stamps the loop is
nodes/lockstep_runner.py's ``LockstepRunner``.
"""
from array import array
import gc
import select
import time
from typing import Optional

from . import control_link as L
from .can_io import CanIo
from .watchdog import Heartbeat, WATCHING
from ..core import realtime
from ..core.balance_loop import BalanceLoop
from ..core.can_budget import BusLoad, max_catch_up
from ..core.config import BalanceConfig
from ..core.deadline import DeadlineLoop, TIMING_WINDOW, window_stats
from ..core.safety import COMMANDING, Mode
from ..core.sensing import build_protocol
from ..core.tick_io import PUBLISH_ODOM, PUBLISH_STATE, state_frame, TickInputs

#: Missed deadlines served late, back to back, before a stall is skipped. Catching up keeps the
#: rate at 500 Hz and the observer's 2 ms time base (it is discretized per update); a longer
#: stall is skipped rather than answered by a long burst of frames.
MAX_CATCH_UP = 5
#: Period of the status messages for /diagnostics [s] (a mode change sends one at once):
#: balance_node judges the loop alive by their age (balance_node.ALIVE_LIMIT, 0.5 s) and
#: publishes /diagnostics once a second by default; a status costs about 0.4 ms of the
#: control process (docs/benchmarks.md), so five a second, not ten.
STATUS_PERIOD = 0.2
#: With clock_source imu_stamp: how long the loop waits for a sample before it serves the link
#: alone (commands, the intake's readiness, a status for /diagnostics) [s, wall clock].
IDLE_WAKE = 0.02


def decimation(rate: float, period: float) -> int:
    """Ticks between publications at ``rate`` [Hz]; 0 = never."""
    return 0 if rate <= 0.0 else max(1, int(round(1.0 / (rate * period))))


class ControlRunner:
    """The control loop around a BalanceLoop (see the module docstring)."""

    def __init__(self, cfg: BalanceConfig, bus, link: L.Link,
                 sensor_link: Optional[L.Link] = None, realtime_options: bool = True,
                 leg_bus=None, heartbeat: Optional[Heartbeat] = None):
        """
        Build the runner.

        bus: the wheels' python-can bus (and the hips', unless leg_bus is given); link: to
        balance_node's ROS side (commands in; state, status, replies out); sensor_link: from
        the sensor intake (nodes/sensor_intake.py), None when the samples come over ``link``;
        heartbeat: shared with the watchdog (nodes/watchdog.py), written at every pass.
        """
        self.cfg = cfg
        self.loop = BalanceLoop(cfg)
        #: The time of the newest tick [s]: CLOCK_MONOTONIC (the lockstep runner: a stamp).
        self.now = 0.0
        #: Ticks run so far (the timer's count is the wall-clock loop's only).
        self.ticks = 0
        clock = self._receipt_clock()
        self.can = CanIo(bus, cfg.can.send_timeout, clock, cfg.can.raw_frames)
        self.leg_can = CanIo(leg_bus, cfg.can.send_timeout, clock, cfg.can.raw_frames) \
            if leg_bus is not None else None
        self.link = link
        self.sensor_link = sensor_link
        #: The links to drain, the intake's first; one poll tells which have messages, so an
        #: empty link costs no recv that fails (an exception each).
        self._links = tuple((x.fileno(), x) for x in (sensor_link, link) if x is not None)
        self._readable = select.poll()
        for fd, _ in self._links:
            self._readable.register(fd, select.POLLIN)
        self.timer = DeadlineLoop(cfg.loop.control_period,
                                  max_catch_up=self.catch_up_limit(cfg, leg_bus is not None),
                                  on_stall=self._on_stall, on_error=self._on_error)
        self._load = BusLoad(cfg.can.bitrate)
        self._leg_load = BusLoad(cfg.can.bitrate)
        self.inputs = TickInputs()
        #: BalanceLoop.tick's own time [s] per tick (the ring of the timer's compute times holds
        #: the whole tick: the link, the bus I/O and the tick), to tell the two apart.
        self._core_times = array('d', [0.0] * TIMING_WINDOW)
        self._arm_ids = []
        self._state_every = decimation(cfg.publish.state_publish_rate, self.timer.period)
        self._odom_every = decimation(cfg.publish.odom_publish_rate, self.timer.period)
        #: The publications the ROS side has subscribers for (L.WANTED): a frame nobody reads
        #: is neither built nor sent (nor woken up for on the ROS side).
        self._wanted = PUBLISH_STATE | PUBLISH_ODOM
        self._realtime_options = realtime_options
        self.realtime = ''
        self._status_due = 0.0
        self._last_mode: Optional[Mode] = None
        self._shut_down = False
        self.intake_ready = sensor_link is None
        self.heartbeat = heartbeat
        # No arming before the watchdog watches (it starts after this process).
        self.inputs.guarded = heartbeat is None

    def _receipt_clock(self):
        """Return the clock that stamps the frames' receipt (CLOCK_MONOTONIC)."""
        return time.monotonic

    @staticmethod
    def catch_up_limit(cfg: BalanceConfig, legs_own_bus: bool) -> int:
        """Return the ticks a catch-up may serve: MAX_CATCH_UP, fewer with a short TX queue."""
        can = cfg.can   # the protocol knows (the C620: one frame for both wheels)
        per_tick = build_protocol(cfg).frames_per_tick((can.left_motor_id, can.right_motor_id))
        if cfg.legs.driven and not legs_own_bus:
            per_tick += 4 if cfg.legs.command_divider == 1 else 2   # the legs take turns
        return max_catch_up(cfg.can.tx_queue_len, per_tick, MAX_CATCH_UP)

    # ------------------------------------------------------------------------- lifecycle

    def run(self) -> None:
        """Run until stopped; always end with zero torque and the motors out of motor mode."""
        try:
            # Start from a known state: a crashed run may have left the motors in motor mode.
            self.loop.report_send(time.monotonic(), self._send(*self.loop.stop_frames()))
            if self._realtime_options:
                self._apply_realtime()
            gc.collect()
            gc.freeze()  # a full collection of the start-up objects took 30 ms (15 ticks)
            self.link.send_object(L.READY, 'control loop %.1f ms, %s' % (
                1e3 * self.timer.period, self.realtime or 'no real-time options'))
            self._loop()
        finally:
            self.shutdown()

    def _loop(self) -> None:
        """Tick every control_period until stopped (core/deadline.py)."""
        self.timer.run(self._tick)

    def stop(self) -> None:
        """End the loop after the tick in progress (any thread, a signal handler)."""
        self.timer.stop()

    def shutdown(self) -> None:
        """Zero torque, exit motor mode, close the bus (idempotent)."""
        self.timer.stop()
        if self._shut_down:
            return
        self._shut_down = True
        self._send(*self.loop.stop_frames())
        if self.heartbeat is not None:
            self.heartbeat.end()   # stop frames sent: the watchdog has nothing left to guard
        self.can.close()
        if self.leg_can is not None:
            self.leg_can.close()

    def _send(self, frames, leg_frames) -> Optional[str]:
        """Send the wheels' frames, then the hips' (on their own bus if they have one)."""
        if not leg_frames:
            return self.can.send(frames)
        error = self.can.send(frames)
        leg_error = (self.leg_can or self.can).send(leg_frames)
        return error or leg_error

    def _apply_realtime(self) -> None:
        lc = self.cfg.loop
        results = {'thread_name': realtime.name_thread('balance_control')}
        cpus = () if lc.realtime_cpu < 0 else (lc.realtime_cpu,)
        results.update(realtime.apply(lc.realtime_priority, cpus, lc.lock_memory))
        self.realtime = '; '.join(message for _, message in results.values())
        for name in ('priority', 'affinity', 'memory_lock'):
            ok, message = results[name]
            if not ok:
                self.link.send_object(L.EVENT, ('warn', 'real-time option refused: %s'
                                                % message))

    # ------------------------------------------------------------------------------ tick

    def _beat(self) -> None:
        hb = self.heartbeat
        if hb is not None:
            hb.beat(time.monotonic(), self.loop.mode in COMMANDING)
            self.inputs.guarded = hb.state()[0] == WATCHING

    def _drain_link(self) -> None:
        self._beat()
        # The intake's samples first, then the ROS side's messages (it may carry samples too).
        # An end-of-file or a closed socket polls as ready too (POLLHUP, POLLNVAL): receive
        # then marks the link closed.
        ready = self._readable.poll(0)
        if ready:
            fds = [fd for fd, _ in ready]
            for fd, link in self._links:
                if fd in fds:
                    for tag, payload in link.receive():
                        self._take(tag, payload)
        if self.link.closed:
            self.timer.stop()  # the ROS side is gone: end with zero torque

    def _take(self, tag: bytes, payload) -> None:
        """Put one message of a link into the tick's inputs (or act on it)."""
        inputs = self.inputs
        if tag == L.IMU:
            inputs.imu.append(payload)
        elif tag == L.JOINTS:
            inputs.joints.append(payload)
        elif tag == L.CMD_VEL:
            inputs.cmd_vel = payload
        elif tag == L.CMD_HEIGHT:
            inputs.cmd_height = payload
        elif tag == L.ESTOP:
            inputs.estop = True
        elif tag == L.ARM:   # an arm, a disarm, or an identification phase by its name
            request_id, arm = payload
            self._arm_ids.append(request_id)
            if isinstance(arm, str):
                inputs.excite = arm
            else:
                inputs.arm = bool(arm)
        elif tag == L.PARAMS:
            inputs.params = {**inputs.params, **payload}
        elif tag == L.CONFLICTS:
            inputs.conflicts = payload   # a state: it stays until the next verdict
        elif tag == L.WANTED:
            self._wanted = payload
        elif tag == L.STOP:
            self.timer.stop()
        elif tag == L.READY:
            self.intake_ready = True
            self._status_due = self._first_status()   # balance_node's start waits for it
            self.link.send_object(L.EVENT, ('info', '%s ready' % payload))

    def _tick(self, now_ns: int) -> None:
        self._drain_link()
        self._step(now_ns * 1e-9)

    def _step(self, now: float) -> None:
        """One tick at ``now`` [s] on what the link brought: CAN in, BalanceLoop, CAN out."""
        self.now = now
        inputs = self.inputs
        self.can.poll(inputs.frames)
        if self.leg_can is not None:
            self.leg_can.poll(inputs.frames)
        try:
            t0 = time.perf_counter()
            result = self.loop.tick(now, inputs)
            self._core_times[self.ticks % TIMING_WINDOW] = time.perf_counter() - t0
            self.ticks += 1
            self.loop.report_send(now, self._send(result.frames, result.leg_frames))
        finally:
            inputs.clear()
        self._beat()   # after the send: an arm in this tick is guarded from its first torque
        self._answer_arm(result.arm_reply)
        for event in result.events:
            self.link.send_object(L.EVENT, event)
        self._send_state(result, now)
        mode = self.loop.mode
        if now >= self._status_due or mode is not self._last_mode:
            self._last_mode = mode
            self._status_due = self._next_status(now)
            self.link.send_object(L.STATUS, self.status(now))

    def _first_status(self) -> float:
        """Return when the status after the intake's readiness is due: at once."""
        return 0.0

    def _next_status(self, now: float) -> float:
        """Return when the next status is due after one sent at ``now`` [s]."""
        return now + STATUS_PERIOD

    def _answer_arm(self, reply) -> None:
        if reply is None or not self._arm_ids:
            return
        *superseded, last = self._arm_ids
        self._arm_ids = []
        for request_id in superseded:
            self.link.send_object(L.ARM_REPLY, (request_id, False, 'superseded by a later '
                                                'request'))
        self.link.send_object(L.ARM_REPLY, (last, reply[0], reply[1]))

    def _send_state(self, result, now: float) -> None:
        n = self.ticks - 1
        flags = 0
        if self._state_every and n % self._state_every == 0:
            flags |= PUBLISH_STATE
        if self._odom_every and n % self._odom_every == 0:
            flags |= PUBLISH_ODOM
        flags &= self._wanted
        if flags:
            joints = ()
            if flags & PUBLISH_STATE:
                pos, vel, eff = self.loop.joint_values(now)
                joints = pos + vel + eff
            self.link.send_state(state_frame(result.state, result.odom, flags), joints)

    def _on_stall(self, lateness: float) -> None:
        self.link.send_object(L.EVENT, ('warn', 'control loop: a tick came %.1f ms late'
                                        % (1e3 * lateness)))

    def _on_error(self, now_ns: int, exc: BaseException) -> None:
        """Take a bug in the tick: FAULT (zero torque), reported; the loop lives on."""
        self._answer_arm(self.loop.report_internal_error(now_ns * 1e-9, repr(exc)))
        self.link.send_object(L.EVENT, ('error', 'control tick failed: %r' % (exc,)))

    def status(self, now: float) -> dict:
        """Return the loop's status, its timing and the bus counters (for /diagnostics)."""
        out = self.loop.status(now)
        out['timing'] = self.timer.stats()
        out['clock_source'] = self.cfg.loop.clock_source
        n = min(self.ticks, TIMING_WINDOW)
        out['timing'].update(window_stats('core', self._core_times[:n]))
        out['period_target'] = self.timer.period
        out['can'] = self.can.counters()
        out['can']['load_pct'] = self._load.update(now, out['can']['bits'])
        if self.leg_can is not None:
            out['leg_can'] = self.leg_can.counters()
            out['leg_can']['load_pct'] = self._leg_load.update(now, out['leg_can']['bits'])
        out['max_catch_up'] = self.timer.max_catch_up
        out['link_dropped'] = self.link.dropped
        out['realtime'] = self.realtime
        out['intake_ready'] = self.intake_ready
        out['time'] = now
        return out
