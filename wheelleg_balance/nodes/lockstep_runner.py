"""
The lockstep runner: the control loop paced by a simulator's IMU stamps, never a robot's.

With ``clock_source: imu_stamp`` (sim_node's ``lockstep``) the loop is paced by the simulated
sensor instead of the wall clock: one tick per IMU sample, at the sample's header stamp, and
every receipt time of that tick (samples, CAN replies, commands) is that stamp, so every
timeout runs on simulated time. sim_node steps its physics once it has the frames of the
tick, so the closed loop is the same on an idle machine and on a loaded one, only slower
(docs/simulation.md). ``LockstepRunner`` is nodes/control_runner.py's ``ControlRunner`` with
that clock; the robot's runner has none of it.

Never on a robot: a silent IMU would stop the clock. The configuration allows it only on the
test buses (core/config.py). Here only a tick writes the heartbeat, and while the motors are
commanded a wall-clock guard stands in for the stopped clock: no new sample for
``lockstep_wall_timeout`` (1 s) of wall time runs one more tick, a period after the last, told
that the IMU is silent (``TickInputs.imu_silent``): FAULT imu_stale, zero torque. Should the
loop itself hang, the watchdog fires on the heartbeat that no tick renewed (its limit there is
that timeout plus ``watchdog_timeout``, nodes/watchdog.py ``stall_limit``).
"""
import math
import time
from typing import Optional

from . import control_link as L
from .control_runner import ControlRunner, IDLE_WAKE, STATUS_PERIOD
from .watchdog import WATCHING
from ..core.safety import COMMANDING


class LockstepRunner(ControlRunner):
    """The control loop on IMU stamps (see the module docstring)."""

    def __init__(self, *args, **kwargs):
        #: Samples whose stamp did not advance the clock (no tick ran on them).
        self.stamps_not_advancing = 0
        super().__init__(*args, **kwargs)

    def _receipt_clock(self):
        """Return the clock that stamps the frames' receipt: the tick's IMU stamp."""
        return lambda: self.now

    def _loop(self) -> None:
        self._run_on_stamps()

    def _run_on_stamps(self) -> None:
        """Tick at the stamp of each newest IMU sample (clock_source imu_stamp)."""
        link = self.sensor_link if self.sensor_link is not None else self.link
        # The status goes out on the wall clock here (the ROS side judges the loop alive by
        # its age), also before the first sample; _step adds one on a mode change.
        self._status_due = math.inf
        status_due = time.monotonic()
        silent_limit = self.cfg.loop.lockstep_wall_timeout
        last_tick = time.monotonic()
        while not self.timer.stopped:
            link.wait_readable(IDLE_WAKE)
            self._drain_link()
            if time.monotonic() >= status_due:
                status_due = time.monotonic() + STATUS_PERIOD
                self.link.send_object(L.STATUS, self.status(self.now))
            inputs = self.inputs
            now = self._newest_stamp()
            silent = time.monotonic() - last_tick
            if now is None and silent > silent_limit and self.loop.mode in COMMANDING:
                # The clock stopped with torque in the motors: one tick, a period on, faults.
                inputs.imu_silent = (
                    'no IMU sample for %.2f s of wall time on IMU stamps (lockstep_wall_timeout '
                    '%.2f s): the simulator or the IMU stopped' % (silent, silent_limit))
                now = self.now + self.timer.period
            if now is None:
                continue
            last_tick = time.monotonic()
            # Every receipt time of this tick is its stamp: the timeouts run on sim time.
            inputs.imu[:] = [s._replace(t=s.stamp_sec + 1e-9 * s.stamp_nanosec)
                             for s in inputs.imu]
            inputs.joints[:] = [s._replace(t=now) for s in inputs.joints]
            if inputs.cmd_vel is not None:
                inputs.cmd_vel = inputs.cmd_vel._replace(t=now)
            if inputs.cmd_height is not None:
                inputs.cmd_height = inputs.cmd_height._replace(t=now)
            try:
                self._step(now)
            except Exception as exc:  # noqa: B902 -- as DeadlineLoop: the loop lives on
                self._on_error(int(now * 1e9), exc)

    def _newest_stamp(self) -> Optional[float]:
        """Return the newest sample's stamp [s] if it advances the clock, else None."""
        imu = self.inputs.imu
        if not imu:
            return None
        newest = imu[-1]
        now = newest.stamp_sec + 1e-9 * newest.stamp_nanosec
        if now <= self.now:
            self.stamps_not_advancing += 1   # a repeated or older stamp: time stands
            imu.clear()
            return None
        return now

    def _beat(self) -> None:
        # Only a tick beats (``_step``, after its send): no sample, no tick, a heartbeat that
        # goes stale. Draining the link only reads whether the watchdog watches.
        if self.heartbeat is not None:
            self.inputs.guarded = self.heartbeat.state()[0] == WATCHING

    def _step(self, now: float) -> None:
        super()._step(now)
        hb = self.heartbeat
        if hb is not None:
            hb.beat(time.monotonic(), self.loop.mode in COMMANDING)

    def _send(self, frames, leg_frames) -> Optional[str]:
        """
        Send the hips' frames first, then the wheels'.

        The wheels, commanded every tick, close the tick for sim_node (sim/robot_motors.py
        ``commanded``), whichever hips the tick commanded.
        """
        if not leg_frames:
            return self.can.send(frames)
        leg_error = (self.leg_can or self.can).send(leg_frames)
        return self.can.send(frames) or leg_error

    def _first_status(self) -> float:
        # The wall clock times the statuses here (_run_on_stamps); a tick sends one only on a
        # mode change.
        return math.inf

    def _next_status(self, now: float) -> float:
        return math.inf

    def status(self, now: float) -> dict:
        """Return the runner's status; the ticks run on the IMU's stamps, not deadlines."""
        out = super().status(now)
        out['timing']['ticks'] = self.ticks
        out['timing']['stamps_not_advancing'] = self.stamps_not_advancing
        return out
