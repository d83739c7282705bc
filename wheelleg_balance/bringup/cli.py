"""
The ``bringup`` command (``ros2 run wheelleg_balance bringup``): see docs/robot_setup.md.

    bringup --config my_robot.yaml --output my_robot_checked.yaml    # the robot on its stand
    bringup --sim [--sim-param fault.miswired_motor_id=1]            # against sim_node
    bringup --sim --sim-config config/sim_lk_damiao.yaml             # another simulated robot

Reads the robot's balance_node params file, runs the checks of session.py on its CAN buses
with the builder at the terminal, reads the IMU on ``imu`` (remappable: ``--ros-args -r
imu:=/my_imu/data``), and writes the filled config to ``--output`` (also when a check failed:
the corrections are in it, and the header lists what failed). ``--sim`` starts sim_node on a
udp_multicast bus of its own and lets its hand do the builder's part (sim.py); ``--sim-config``
lays a sim_node params file over its defaults (the motors of another robot), ``--sim-param``
single parameters over both. Exit status: 0
every check passed, 1 a check failed, 2 bring-up refused to run (a balance_node drives the bus)
or could not start.
"""
import argparse
import datetime
import os
import pathlib
import signal
import subprocess
import sys
import tempfile
import threading
import time
from typing import List, Optional

import yaml

from . import robot_config, sim as simmod
from .imu_check import ImuSample
from .iplink import check_link, ip_link_json
from .motor_checks import channels
from .report import Check, FAIL, Report
from .session import BringUp, ConsoleOperator, Refused
from ..core.protocols import import_protocol
from ..core.schema import from_flat, nest
from ..processes import end_process
from ..sim.config import SimConfig
from ..validation import child_env

#: How long sim_node may take to publish its first IMU sample [s], and the legs to hang still.
SIM_START_TIMEOUT = 60.0
SIM_SETTLE = 2.0
#: How long bring-up lets DDS discovery find the other nodes before it looks [s].
DISCOVERY = 1.5


def default_config() -> pathlib.Path:
    """Return the installed config/balance.yaml (or the source tree's)."""
    try:
        from ament_index_python.packages import get_package_share_directory
        return pathlib.Path(get_package_share_directory('wheelleg_balance')) / 'config' / \
            'balance.yaml'
    except (ImportError, LookupError, ValueError):
        return pathlib.Path(__file__).resolve().parents[2] / 'config' / 'balance.yaml'


class RosSide:
    """bring-up's ROS node: the IMU, the graph (who else runs), sim_node's hand and clock."""

    def __init__(self, args: Optional[List[str]] = None):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import Imu, JointState
        self._rclpy = rclpy
        rclpy.init(args=args)
        self.node = rclpy.create_node('bringup')
        self._JointState = JointState
        self._lock = threading.Lock()
        self._samples: List[ImuSample] = []
        self.imu_count = 0
        self.node.create_subscription(Imu, 'imu', self._on_imu, qos_profile_sensor_data)
        self.imu_topic = self.node.resolve_topic_name('imu')
        self._hand = self.node.create_publisher(JointState, 'sim_node/hand', 10)
        from rosgraph_msgs.msg import Clock
        self.sim_time: Optional[float] = None    # sim_node's /clock [s], None before one came
        self.node.create_subscription(Clock, '/clock', self._on_clock, 10)
        self._executor = SingleThreadedExecutor()
        self._executor.add_node(self.node)
        self._thread = threading.Thread(target=self._executor.spin, daemon=True)
        self._thread.start()
        self._started = time.monotonic()

    def _on_imu(self, msg) -> None:
        o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
        sample = ImuSample((o.x, o.y, o.z, o.w), float(msg.orientation_covariance[0]),
                           (w.x, w.y, w.z), (a.x, a.y, a.z))
        with self._lock:
            self.imu_count += 1
            self._samples.append(sample)
            del self._samples[:-2000]

    def _on_clock(self, msg) -> None:
        self.sim_time = msg.clock.sec + 1e-9 * msg.clock.nanosec

    def wait_sim(self, duration: float) -> None:
        """
        Wait ``duration`` seconds of sim_node's time (--sim: the hand's moves and the settling).

        A loaded machine runs the simulation slower than the wall clock; the procedure's waits
        are the simulated robot's, so they follow its clock (at most 30 times as long in wall
        time; without a /clock at all, the wall clock's).
        """
        start = self.sim_time
        if start is None:
            time.sleep(duration)
            return
        give_up = time.monotonic() + 30.0 * duration + 5.0
        while self.sim_time < start + duration and time.monotonic() < give_up:
            time.sleep(0.01)

    def imu(self, duration: float) -> List[ImuSample]:
        """Return the IMU samples of the next ``duration`` seconds."""
        with self._lock:
            self._samples = []
        time.sleep(duration)
        with self._lock:
            return list(self._samples)

    def owners(self) -> List[str]:
        """Return the balance_nodes in the graph (by name, or by their ~/arm service)."""
        time.sleep(max(0.0, DISCOVERY - (time.monotonic() - self._started)))
        found = set()
        for name, ns in self.node.get_node_names_and_namespaces():
            if name == 'balance_node':
                found.add('%s/%s' % (ns.rstrip('/'), name))
        for srv, types in self.node.get_service_names_and_types():
            if srv.endswith('/arm') and 'std_srvs/srv/SetBool' in types:
                found.add('a node with the service %s' % srv)
        return sorted(found)

    def hand(self, names, positions, efforts) -> None:
        """Publish sim_node's hand command."""
        self._hand.publish(self._JointState(name=list(names), position=list(positions),
                                            effort=list(efforts)))

    def close(self) -> None:
        """Stop spinning and shut rclpy down."""
        self._executor.shutdown()
        self._thread.join(timeout=5.0)
        self.node.destroy_node()
        if self._rclpy.ok():
            self._rclpy.shutdown()


def _parse_overrides(items: List[str]) -> dict:
    out = {}
    for item in items:
        name, sep, value = item.partition('=')
        if not sep:
            raise ValueError('--sim-param needs NAME=VALUE, got %r' % item)
        out[name.strip()] = yaml.safe_load(value)
    return out


def _start_sim(params: dict, folder: pathlib.Path, protocols: List[str]) -> subprocess.Popen:
    path = folder / 'sim.yaml'
    path.write_text(yaml.safe_dump({'sim_node': {'ros__parameters': nest(params)}},
                                   default_flow_style=None))
    log = open(folder / 'sim_node.log', 'w')
    loads = [arg for spec in protocols for arg in ('--protocol', spec)]
    return subprocess.Popen([sys.executable, '-m', 'wheelleg_balance.nodes.sim_node'] + loads
                            + ['--ros-args', '--params-file', str(path)], stdout=log,
                            stderr=subprocess.STDOUT,
                            env=child_env(dict(os.environ, PYTHONUNBUFFERED='1')))


def _open(cfg) -> List:
    from ..nodes.can_io import CanIo, open_bus
    return [CanIo(open_bus(cfg.can.interface, ch, cfg.can.udp_port), send_timeout=0.01)
            for ch in channels(cfg)]


def main(argv: Optional[List[str]] = None) -> int:
    """Run bring-up; return the exit status (see the module docstring)."""
    from rclpy.utilities import remove_ros_args
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = argparse.ArgumentParser(prog='bringup', description=__doc__.split('\n\n')[0])
    parser.add_argument('--config', type=pathlib.Path, default=None,
                        help="the robot's balance_node params file (default: the package's "
                        'config/balance.yaml)')
    parser.add_argument('--output', type=pathlib.Path, default=pathlib.Path('robot.yaml'),
                        help='where the filled config is written (default robot.yaml)')
    parser.add_argument('--sim', action='store_true', help='run against a sim_node of its '
                        "own, whose hand does the builder's part")
    parser.add_argument('--sim-param', action='append', default=[], metavar='NAME=VALUE',
                        help='a sim_node parameter, e.g. fault.miswired_motor_id=1')
    parser.add_argument('--sim-config', type=pathlib.Path, default=None,
                        help='--sim: a sim_node params file laid over its defaults, e.g. '
                        "the package's config/sim_lk_damiao.yaml")
    parser.add_argument('--protocol', action='append', default=[], metavar='MODULE:CLASS',
                        help='register a protocol defined outside the package (its module '
                        'on the path; --sim: sim_node loads it too)')
    parser.add_argument('--can-group', default=None, help='--sim: the udp_multicast group')
    parser.add_argument('--udp-port', type=int, default=None, help='--sim: the UDP port')
    args = parser.parse_args(remove_ros_args(['bringup'] + argv)[1:])
    report = Report()
    sim_proc = None
    tmp = None
    ros = None
    ios: List = []
    try:
        for spec in args.protocol:
            import_protocol(spec)
        if args.sim:
            pid = os.getpid()
            group = args.can_group or '239.74.%d.%d' % ((pid >> 8) % 256, pid % 256 or 1)
            port = args.udp_port or 40000 + pid % 20000
            robot = robot_config.read_params(args.sim_config, 'sim_node') \
                if args.sim_config else {}
            overrides = _parse_overrides(args.sim_param)
            params = simmod.sim_params(group, port, dict(robot, **overrides))
            sim_cfg = from_flat(SimConfig, params)
            cfg = simmod.balance_config(sim_cfg)
            faults = ', '.join('%s=%s' % kv for kv in overrides.items())
            base = 'sim_node on its stand (%s%s)' % (
                '%s, ' % args.sim_config if args.sim_config else '',
                faults or 'no sim_node parameter overrides')
        else:
            path = args.config or default_config()
            cfg = robot_config.build(robot_config.read_params(path))
            base = str(path)
    except (ValueError, OSError) as exc:
        print('bringup: %s' % exc, file=sys.stderr)
        return 2
    report.say('bringup of %s, %s' % (base, datetime.datetime.now().isoformat(timespec='seconds')))
    try:
        ros = RosSide(['bringup', '--ros-args'] + _ros_args(argv))
        if args.sim:
            tmp = tempfile.TemporaryDirectory(prefix='bringup_sim_')
            sim_proc = _start_sim(params, pathlib.Path(tmp.name), args.protocol)
            end = time.monotonic() + SIM_START_TIMEOUT
            while ros.imu_count == 0 and time.monotonic() < end and sim_proc.poll() is None:
                time.sleep(0.05)
            if ros.imu_count == 0:
                print('bringup: sim_node did not come up: %s' % (
                    pathlib.Path(tmp.name, 'sim_node.log').read_text()[-2000:]), file=sys.stderr)
                return 2
            report.say('sim_node is up (CAN udp_multicast %s:%d); the legs hang free for %.0f s'
                       % (group, port, SIM_SETTLE))
            ros.wait_sim(SIM_SETTLE)
            operator = simmod.SimOperator(sim_cfg, ros.hand, report.say, wait=ros.wait_sim)
        else:
            operator = ConsoleOperator(report.say)
        links = (lambda: [c for ch in channels(cfg) for c in check_link(ip_link_json(ch), ch)]) \
            if cfg.can.interface == 'socketcan' else (lambda: [])
        try:
            ios = _open(cfg)
        except Exception as exc:  # noqa: B902 -- python-can raises many kinds here
            report.extend(links())
            report.add(Check(FAIL, ', '.join(channels(cfg)), 'cannot open the bus: %s' % exc))
            return 2
        session = BringUp(cfg, ios, operator, ros.imu, report, owners=ros.owners, links=links,
                          imu_topic=ros.imu_topic,
                          wait=ros.wait_sim if args.sim else time.sleep)
        try:
            changes = session.run()
        except Refused as exc:
            report.add(Check(FAIL, 'bringup', 'refused: %s' % exc))
            return 2
        return _write(cfg, changes, report, args.output)
    except KeyboardInterrupt:
        report.say('interrupted: the motors were sent zero torque and exit')
        return 130
    finally:
        for io in ios:
            io.close()
        if sim_proc is not None:
            end_process(sim_proc, signal.SIGINT, 10.0)
        if tmp is not None:
            tmp.cleanup()
        if ros is not None:
            ros.close()


def _ros_args(argv: List[str]) -> List[str]:
    # The --ros-args part of the command line (remappings such as -r imu:=/my_imu/data).
    if '--ros-args' not in argv:
        return []
    rest = argv[argv.index('--ros-args') + 1:]
    return rest[:rest.index('--')] if '--' in rest else rest


def _write(cfg, changes: dict, report: Report, output: pathlib.Path) -> int:
    report.say("== 6. The robot's config")
    try:
        filled, _ = robot_config.filled_config(cfg, changes)
    except ValueError as exc:
        report.add(Check(FAIL, str(output), 'the corrected configuration is not valid: %s' % exc))
        return 1
    failed = report.failed
    header = ['balance_node parameters written by `bringup` on %s.'
              % datetime.datetime.now().isoformat(timespec='seconds'),
              report.summary() + '.']
    header += ['FAIL %s: %s' % (c.item, c.text[:160]) for c in failed]
    header += ['changed by the checks: %s' % ', '.join(sorted(changes)) if changes else
               'no parameter changed by the checks']
    robot_config.write_params(output, filled, header)
    report.say('wrote %s (%s)' % (output, 'changed: %s' % ', '.join(sorted(changes))
                                  if changes else 'no changes'))
    report.say(report.summary())
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
