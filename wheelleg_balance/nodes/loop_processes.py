"""
balance_node's children: the control loop, the sensor intake and the watchdog.

The control process (nodes/control_process.py) owns the CAN bus and the 2 ms loop, the sensor
intake (nodes/sensor_intake.py) has nothing but the sensor subscriptions, the watchdog
(nodes/watchdog.py) stops the motors if the control process stalls or dies. Each runs on this
process's sys.path, never the working directory's (processes.py ``Child``); a child that
fails to start is one line (``StartError``). With a python-can bus passed in (tests), the
control loop runs in a thread of this process instead, and there is no watchdog.
"""
import subprocess
import sys
import threading
import time
from typing import Callable, Optional

from . import control_link as L, sensor_intake, watchdog
from ..core.config import BalanceConfig
from ..core.schema import to_flat
from ..processes import Child, end_process, StartError

#: How long balance_node waits for the control loop to start [s] (solving a configuration's
#: height tables takes a few seconds the first time: core/table_cache.py).
START_TIMEOUT = 30.0
#: The control process's module (nodes/control_process.py).
CONTROL_MODULE = 'wheelleg_balance.nodes.control_process'


class LoopProcesses:
    """The control loop, the sensor intake and the watchdog of a balance_node."""

    def __init__(self):
        """Make the link to the control loop (``link``); ``start`` starts the children."""
        ros_end, self._loop_end = L.socket_pair()
        self._intake_end, self._loop_sensor_end = L.socket_pair()
        self.link = L.Link(ros_end)
        self.control: Optional[Child] = None
        self.intake: Optional[Child] = None
        self.watchdog: Optional[watchdog.WatchdogProcess] = None
        self.runner = None
        self.runner_thread: Optional[threading.Thread] = None

    def start(self, node, cfg: BalanceConfig, bus) -> None:
        """
        Start the control loop (on ``bus`` in a thread, None: a process), then the intake.

        What started before a failure is ended by ``end_children`` and ``close``.
        """
        self._start_control(cfg, bus, self._loop_end, self._loop_sensor_end)
        self._start_intake(node, cfg, self._intake_end)

    def _start_control(self, cfg: BalanceConfig, bus, loop_end, sensor_end) -> None:
        if bus is not None:
            from .control_process import make_runner   # python-can: only with a bus here
            self.runner = make_runner(cfg, bus, L.Link(loop_end), L.Link(sensor_end))
            self.runner_thread = threading.Thread(target=self.runner.run,
                                                  name='balance_control', daemon=True)
            self.runner_thread.start()
            return
        self.watchdog = watchdog.WatchdogProcess(watchdog.stall_limit(cfg))
        fds = (L.inheritable(loop_end), L.inheritable(sensor_end), self.watchdog.heartbeat.fd)
        self.control = Child('the control process', CONTROL_MODULE, [
            '--fd', str(fds[0]), '--sensor-fd', str(fds[1]), '--heartbeat-fd', str(fds[2])],
            pass_fds=fds)
        # The child has its copies; ours would hide the child's end-of-file.
        loop_end.close()
        sensor_end.close()
        self.link.send_object(L.PARAMS, to_flat(cfg))
        self.watchdog.start(self.control.process.pid, to_flat(cfg))

    def _start_intake(self, node, cfg: BalanceConfig, intake_end) -> None:
        fd = L.inheritable(intake_end)
        # joint_states_in, never the joint_states balance_node publishes (docs/interface.md).
        self.intake = Child('the sensor intake', sensor_intake.MODULE, sensor_intake.arguments(
            fd, node.get_name(), node.get_namespace(), node.resolve_topic_name('imu'),
            node.resolve_topic_name('joint_states_in'), to_flat(cfg),
            sensor_intake.enclave_argument(sys.argv)), pass_fds=(fd,))
        intake_end.close()

    def wait_started(self, ready: threading.Event, status: Callable[[], Optional[dict]],
                     error: Callable[[], str]) -> None:
        """
        Wait until the loop runs, the intake subscribes and the watchdog watches.

        ready: set by the reader of the link on the loop's READY (or its end); status: the
        newest status the loop sent; error: a line the loop logged while starting. Raises
        StartError with the one line of what failed.
        """
        if not ready.wait(START_TIMEOUT) or self.link.closed:
            raise StartError(_failure(self.control) or error() or 'control loop did not start')
        # The loop reports the intake's subscriptions (a process of its own) in its status.
        end = time.monotonic() + START_TIMEOUT
        intake = self.intake.process

        def intake_ready():
            return (status() or {}).get('intake_ready')
        while not intake_ready() and time.monotonic() < end and not self.link.closed \
                and intake.poll() is None:
            time.sleep(0.02)
        if not intake_ready():
            if self.link.closed:   # the control process ended first
                raise StartError(_failure(self.control) or error() or 'control loop ended')
            raise StartError(_failure(self.intake) or 'sensor intake did not start (exit '
                             'code %s)' % intake.poll())
        if self.watchdog is not None:   # none with an in-process bus
            self.watchdog.wait(end)
        for child in (self.control, self.intake):
            if child is not None:
                child.started()   # a later failure goes to stderr, traceback and all

    @property
    def control_task_id(self) -> Optional[int]:
        """Return the Linux task the control loop runs in: its process's pid or thread id."""
        if self.control is not None:
            return self.control.process.pid
        return None if self.runner_thread is None else self.runner_thread.native_id

    def end_children(self) -> None:
        """End the intake and the loop (told to stop before: its zero torque, exit frames)."""
        if self.intake is not None:
            end_process(self.intake.process)
        if self.runner is not None:
            self.runner.stop()
            if self.runner_thread is not None:
                self.runner_thread.join(timeout=2.0)
            self.runner.shutdown()
        if self.control is not None:
            _end_child(self.control.process, self.link)

    def close(self) -> None:
        """Close the link and the watchdog (after ``end_children``)."""
        self.link.close()
        if self.watchdog is not None:
            self.watchdog.close()
        for child in (self.control, self.intake):
            if child is not None:
                child.started()   # closes its report pipe


def _failure(child: Optional[Child]) -> Optional[str]:
    """Return a child's line (a failed start) or exit code, else None (still running)."""
    # Its link closes as it ends: the line, written before, or its exit follows at once.
    return None if child is None else child.failure(wait=2.0)


def _end_child(child: subprocess.Popen, link: L.Link) -> None:
    """Let the control process end with its stop frames; kill it only if it hangs."""
    try:
        child.wait(timeout=1.0)
        return
    except subprocess.TimeoutExpired:
        pass
    link.close()  # end-of-file: the loop stops even if the STOP message was dropped
    try:
        child.wait(timeout=2.0)
    except subprocess.TimeoutExpired:
        child.kill()
        child.wait()
