"""
balance_node's control loop: the tick every 2 ms on the CAN bus, in a process without rclpy.

The loop is nodes/control_runner.py's ``ControlRunner`` (or, on a simulator's IMU stamps,
nodes/lockstep_runner.py's ``LockstepRunner``: ``make_runner``); this module is its process.

balance_node starts it as a child process (``python -P -m
wheelleg_balance.nodes.control_process --fd N`` on the parent's sys.path: processes.Child),
so the executor, the parameter and service machinery and DDS discovery share no interpreter
with the tick; a bus that does not open is one line to balance_node, which ends with it;
tests that hand the node an in-process python-can bus run the same runner in a thread. The
child ends with zero torque and exit-motor-mode frames when told to
(STOP), when the ROS side goes away (end-of-file on the link: the parent died, even by
SIGKILL; the kernel also sends it SIGTERM then: PR_SET_PDEATHSIG) and on SIGINT, SIGTERM,
SIGHUP or SIGQUIT. The sensor samples come from the sensor intake process over a socket pair
of their own (nodes/sensor_intake.py). At every pass the loop writes a heartbeat (the time,
whether it commands the motors) into memory it shares with the watchdog process
(nodes/watchdog.py), which stops the motors if the loop stalls or dies; no arm before the
watchdog watches.
"""
import argparse
import signal
import sys
import time

from . import control_link as L
from .can_io import open_bus_or_fail
from .control_runner import ControlRunner, MAX_CATCH_UP  # noqa: F401 (MAX_CATCH_UP)
from .lockstep_runner import LockstepRunner
from .sensor_intake import die_with_parent
from .watchdog import Heartbeat
from ..core import table_cache
from ..core.config import BalanceConfig
from ..core.schema import from_flat
from ..processes import run_child, StartError


def make_runner(cfg: BalanceConfig, *args, **kwargs) -> ControlRunner:
    """Return the runner of ``cfg``'s clock_source: ControlRunner, or the lockstep runner."""
    if cfg.loop.clock_source == 'imu_stamp':
        return LockstepRunner(cfg, *args, **kwargs)
    return ControlRunner(cfg, *args, **kwargs)


def _stop_on_signals(runner: ControlRunner) -> None:
    def handler(signum, frame):
        runner.stop()
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT):
        signal.signal(signum, handler)


def main(argv=None) -> int:
    """Run the control loop of the balance_node that started this process."""
    parser = argparse.ArgumentParser(description='balance_node control loop (started by '
                                     'balance_node, not by hand)')
    parser.add_argument('--fd', type=int, required=True, help='inherited link socket')
    parser.add_argument('--sensor-fd', type=int, help='inherited socket of the sensor intake')
    parser.add_argument('--heartbeat-fd', type=int, help="inherited memfd of the watchdog's "
                        'heartbeat')
    args = parser.parse_args(argv)
    die_with_parent()
    link = L.Link.from_fd(args.fd)
    sensor_link = None if args.sensor_fd is None else L.Link.from_fd(args.sensor_fd)
    params = None
    deadline = time.monotonic() + 30.0
    while params is None and time.monotonic() < deadline and not link.closed:
        link.wait_readable(0.5)
        for tag, payload in link.receive(1):
            if tag == L.PARAMS:
                params = payload
    if params is None:
        raise StartError('the control process', 'no configuration from balance_node within '
                         '30 s', 'balance_node starts it; it is not run by hand')
    cfg = from_flat(BalanceConfig, params)
    # Tables of a configuration the package has none for (a robot's own model): solved at the
    # first start, then read from the user's cache folder (core/table_cache.py).
    table_cache.keep_in(table_cache.default_folder())
    # A bus that does not open is one line to balance_node (processes.run_child), which ends.
    bus = open_bus_or_fail(cfg.can.interface, cfg.can.channel, cfg.can.udp_port)
    leg_bus = None
    if cfg.legs.driven and cfg.legs.channel and cfg.legs.channel != cfg.can.channel:
        try:
            leg_bus = open_bus_or_fail(cfg.can.interface, cfg.legs.channel, cfg.can.udp_port,
                                       "the legs' CAN bus")
        except StartError:
            bus.shutdown()
            raise
    heartbeat = None if args.heartbeat_fd is None else Heartbeat(args.heartbeat_fd)
    runner = make_runner(cfg, bus, link, sensor_link, leg_bus=leg_bus, heartbeat=heartbeat)
    _stop_on_signals(runner)
    runner.run()
    link.close()
    return 0


if __name__ == '__main__':
    sys.exit(run_child('the control process', main))
