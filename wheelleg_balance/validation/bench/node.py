"""
balance_node under load, measured from outside: its CAN frames, its CPU time, its latency.

Set-up (one session, every process on localhost, ROS isolated by the caller's ROS_DOMAIN_ID and
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST plus a namespace of its own):

- balance_node as its own process (``python -m wheelleg_balance.nodes.balance_node``, or the
  same module of another source tree: ``NodeUnderTest.tree``) on a ``udp_multicast`` CAN bus
  with a group and port of its own, or on a ``socketcan_hub`` bus with a hub of its own
  (nodes/socketcan_hub.py: python-can's SocketcanBus, the robot's code path), ``auto_arm`` true,
  with its six motors (``legs.driven``) or, for a tree from before the legs, its two wheel
  motors;
- a sensor process (``python -m wheelleg_balance.validation.bench.node publisher``) publishing
  ``imu`` at 500 Hz (and, for a node that reads its wheel speeds from them, the wheels'
  ``joint_states``) from core/deadline.DeadlineLoop, with sensor-data QoS. It is publisher-only
  (no services, no rosout) and its participant UDP-only (nodes/dds.py): a publish then never
  waits for other processes, so the plant does not stall when participants come and go
  (docs/benchmarks.md, "The 0.33 s stall");
- a motor process (``python -m wheelleg_balance.validation.bench.node motors``) that is the
  motors: it records every frame on the bus with its kernel receive time (SO_TIMESTAMPNS) and
  answers each MIT frame as the firmware does (sim/motor_emulator.py): the wheels still, the
  hips at the angles of l = 0.37 m.

Latency probe: the robot stands upright (pitch 0), still until the node balances (it arms only
from a still pose: Session.start then sends SIGUSR1), then every ``TOGGLE_TICKS`` samples the
sensor process flips the sign of the IMU's pitch rate (+-PITCH_RATE): the torque on both
wheels steps with it (about 0.7 N m with ida_pbc). The latency of a probe is the time from
publishing the first sample of the new sign (time.time_ns just before publish) to the kernel
receive time of the first frame (per wheel) whose torque has crossed half-way to its new value;
a probe counts when both wheels have it. Both clocks are CLOCK_REALTIME on the same machine.
The sensor period is 2.0004 ms (499.9 Hz) on purpose: the sensor and control loops then slide
past each other by one whole period every 10 s, so the probes see every phase between a
sample's arrival and the next control tick, instead of one arbitrary phase for the whole run.
A controller whose torque does not follow theta_dot (output_regulation saturates here) leaves
the latency unmeasured (NaN), not wrong.

The CPU figure is the node's whole process tree: the ROS shell, the control process and the
sensor intake (``processes``), each also given alone.
"""
import argparse
from dataclasses import dataclass
import math
import os
import signal
import subprocess
import sys
import threading
import time
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from .stats import (cpu_percent, period_stats, proc_cpu_seconds, summary_us,
                    thread_cpu_percent, thread_cpu_seconds)
from ...core import realtime
from ...core.deadline import DeadlineLoop
from ...core.kinematics import FiveBarLeg
from ...core.protocols.base import Frame
from ...nodes import socketcan_hub
from ...processes import end_process
from ...sim.motor_emulator import MitMotorBank

SENSOR_PERIOD_NS = 2_000_400
TOGGLE_TICKS = 10
PITCH_RATE = 0.5            # [rad/s] the probe's pitch rate step
WHEEL_IDS = (1, 2)
HIP_IDS = (3, 4, 5, 6)
#: Motor shaft relative to the joint: balance_node's defaults (the right wheel is mirrored).
DIRECTIONS = {1: 1, 2: -1}
LEFT_ID, RIGHT_ID = WHEEL_IDS
LEFT_JOINT, RIGHT_JOINT = 'left_wheel_joint', 'right_wheel_joint'
#: The hips' joint angle [rad] (FiveBarLeg convention, the node's zero offsets): l = 0.37 m.
HIP_ANGLE = FiveBarLeg().inverse(0.37)[0]
NODE_MODULE = 'wheelleg_balance.nodes.balance_node'
#: Sensor and motor timeouts of the node under test [s]. The sensor and motor processes are test
#: infrastructure on a shared machine: a stall of theirs must not fault the node and end the
#: measurement (test/test_balance_node.py does the same). A fault is still reported.
TIMEOUT = 0.25
#: Seconds from the start of the probing to the measurement window. The motors never move and
#: the IMU reads upright, so the controller's state drifts to a steady torque (about -2.2 N m
#: on the left wheel with ida_pbc, +-0.4 N m with the probe), crossing zero about 1 s after the
#: probing starts and settled after about 2 s: a window opened before then counts those ticks
#: as not balancing (one run on a loaded host did, with a 2 s warm-up, 2026-12-06).
WARMUP = 4.0
#: Receive buffer of the recorder's socket [bytes] (SO_RCVBUFFORCE needs CAP_NET_ADMIN; else
#: SO_RCVBUF, capped by net.core.rmem_max).
RECEIVE_BUFFER = 16 * 1024 * 1024
SO_RCVBUFFORCE = 33   # <asm-generic/socket.h>; not in Python's socket module


@dataclass
class NodeUnderTest:
    """
    Which balance_node is measured and how it is wired.

    motors: 6 (two wheels, four hips: ``legs.driven``, wheel speeds from the wheel motors'
    replies) or 2 (the wheels only); joint_states: the sensor process also publishes the
    wheels' joint_states (a node from before ``wheel_state_source``); tree: a source tree whose
    wheelleg_balance package runs the node (None: this one); label: its name in reports;
    params: ``NAME:=VALUE`` parameters of this node.
    """

    motors: int = 6
    joint_states: bool = False
    tree: Optional[str] = None
    label: str = 'this tree'
    params: Tuple[str, ...] = ()

    def node_args(self) -> List[str]:
        """Return the parameters that wire this node to the session's motors, and its own."""
        return (['-p', 'legs.driven:=true'] if self.motors == 6 else []) + param_args(
            self.params)

    def env(self, env: Dict[str, str]) -> Dict[str, str]:
        """Return the environment of the node's process (its tree first on the path)."""
        if self.tree is None:
            return env
        out = dict(env)
        out['PYTHONPATH'] = os.pathsep.join(p for p in (self.tree, env.get('PYTHONPATH')) if p)
        return out


def param_args(params: Sequence[str]) -> List[str]:
    """Return the ROS arguments that set ``NAME:=VALUE`` parameters (-p NAME:=VALUE ...)."""
    return [a for p in params for a in ('-p', p)]


# ------------------------------------------------------------------------ sensor process

def run_publisher(namespace: str, output: str, max_duration: float,
                  joint_states: bool = False, period_ns: int = SENSOR_PERIOD_NS,
                  toggle_ticks: int = TOGGLE_TICKS, pitch_rate: float = PITCH_RATE,
                  priority: int = 0) -> None:
    """
    Publish imu (and joint_states) until SIGINT/SIGTERM or max_duration; write an .npz.

    priority: SCHED_FIFO priority of the publishing thread (0: none; refused: printed).
    """
    from ...nodes.dds import apply_udp_only
    apply_udp_only()   # before rclpy: the participant is made UDP-only
    import rclpy
    from rclpy.qos import qos_profile_sensor_data
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import Imu, JointState

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('bench_sensors', namespace=namespace, enable_rosout=False,
                             start_parameter_services=False)
    imu_pub = node.create_publisher(Imu, 'imu', qos_profile_sensor_data)
    js_pub = node.create_publisher(JointState, 'joint_states', qos_profile_sensor_data) \
        if joint_states else None
    imu = Imu()
    imu.header.frame_id = 'imu_link'
    imu.orientation.w = 1.0        # pitch 0: the robot stands upright and still
    imu.linear_acceleration.z = 9.81
    js = JointState(name=[LEFT_JOINT, RIGHT_JOINT], position=[0.0, 0.0], velocity=[0.0, 0.0])
    imu_ns: List[int] = []
    toggle_ns: List[int] = []
    toggle_level: List[int] = []
    wall = time.time_ns
    level = [1]
    loop = DeadlineLoop(period_ns * 1e-9, max_catch_up=0)   # a late sample is not sent twice
    # Still (pitch rate 0) until SIGUSR1: a node arms only from an upright pose that is still.
    probing = [False]
    signal.signal(signal.SIGUSR1, lambda *_: probing.__setitem__(0, True))

    def tick(now_ns: int) -> None:
        k = loop.ticks
        toggled = probing[0] and k % toggle_ticks == 0
        if toggled:
            level[0] = -level[0]
            imu.angular_velocity.y = level[0] * pitch_rate
        t = wall()
        imu.header.stamp.sec, imu.header.stamp.nanosec = divmod(t, 1_000_000_000)
        imu_pub.publish(imu)
        imu_ns.append(t)
        if toggled:
            toggle_ns.append(t)
            toggle_level.append(level[0])
        if js_pub is not None:
            js.header.stamp = imu.header.stamp
            js_pub.publish(js)

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: loop.stop())
    threading.Timer(max_duration, loop.stop).start()
    _plant_priority(priority, 'sensors')
    loop.run(tick)
    # Saved first: what comes after may hang on a busy machine until the parent's SIGKILL.
    np.savez(output, imu_ns=np.asarray(imu_ns, dtype=np.int64),
             toggle_ns=np.asarray(toggle_ns, dtype=np.int64),
             toggle_level=np.asarray(toggle_level, dtype=np.int64),
             overruns=loop.overruns, stalls=loop.stalls, longest_stall=loop.longest_stall)
    node.destroy_node()
    rclpy.try_shutdown()


def _plant_priority(priority: int, what: str) -> None:
    """Give the calling thread SCHED_FIFO ``priority`` (0: nothing); print the outcome."""
    if priority > 0:
        ok, message = realtime.set_fifo_priority(priority)
        print('%s: %s' % (what, message), flush=True)


# --------------------------------------------------------------------- motors + recorder

class MotorBus(threading.Thread):
    """
    The robot's motors on the bus: record every frame, answer each as the firmware does.

    The motors are sim/motor_emulator.py's (a MitMotorBank): the wheels still, the hips at
    HIP_ANGLE. The bus is ``interface``'s ``channel`` (the udp_multicast group, on ``port``;
    the socketcan_hub hub's address), or ``bus`` when given (a test's virtual bus). motor_ids:
    the wheels' IDs, then the hips' if any.
    """

    def __init__(self, channel: Optional[str] = None, port: int = 43113,
                 motor_ids: Sequence[int] = WHEEL_IDS, bus=None, priority: int = 0,
                 interface: str = 'udp_multicast'):
        super().__init__(name='bench_motors', daemon=True)
        import can
        from ...nodes.can_io import open_bus
        self._can = can
        self.priority = priority
        self.bus = bus if bus is not None else open_bus(interface, channel, port)
        self._inode = self._grow_receive_buffer()
        self._drops = -1
        self.motors = MitMotorBank(motor_ids, DIRECTIONS)
        for motor_id in motor_ids:
            if motor_id in HIP_IDS:
                self.motors.joints[motor_id] = (HIP_ANGLE, 0.0)
        self.protocol = self.motors.protocol
        self.motor_ids = set(motor_ids)
        self.t_ns: List[int] = []       # commands: kernel receive time [ns, realtime]
        self.ids: List[int] = []
        self.torque: List[float] = []   # motor torque decoded [N m] (tau_ff for the hips)
        self.events: List[tuple] = []   # (t_ns, motor id, 'enter' | 'exit' | 'zero')
        self.reply_errors = 0
        self._halt = threading.Event()

    def _grow_receive_buffer(self) -> Optional[int]:
        """
        Give the bus socket a receive buffer of RECEIVE_BUFFER; return its inode (None: none).

        A recording that loses frames while this process waits for the CPU would show gaps the
        node never made; the kernel counts such losses (``receive_drops``).
        """
        import socket
        try:
            sock = socket.socket(fileno=os.dup(self.bus.fileno()))
        except (AttributeError, OSError, ValueError, NotImplementedError):
            return None
        try:
            for option in (SO_RCVBUFFORCE, socket.SO_RCVBUF):
                try:
                    sock.setsockopt(socket.SOL_SOCKET, option, RECEIVE_BUFFER)
                    break
                except OSError:
                    continue
            return os.fstat(sock.fileno()).st_ino
        finally:
            sock.close()

    def receive_drops(self) -> int:
        """Return the datagrams the kernel dropped on the bus socket (-1: unknown)."""
        return udp_drops(self._inode)

    def run(self) -> None:
        """Record and answer frames until stop()."""
        can, protocol = self._can, self.protocol
        _plant_priority(self.priority, 'motors')
        while not self._halt.is_set():
            try:
                msg = self.bus.recv(0.1)
            except can.CanError:
                continue
            if msg is None or msg.arbitration_id not in self.motor_ids or msg.dlc != 8:
                continue  # our own replies (ID 0) come back through multicast loopback
            t_ns = int(round(msg.timestamp * 1e9))
            motor_id = msg.arbitration_id
            frame = Frame(motor_id, bytes(msg.data), msg.is_extended_id)
            cmd = protocol.decode_command(frame)
            if isinstance(cmd, str):
                self.events.append((t_ns, motor_id, cmd))
            elif cmd is None:
                continue
            else:
                self.t_ns.append(t_ns)
                self.ids.append(motor_id)
                self.torque.append(cmd.torque)
            for reply in self.motors.handle(frame, time.monotonic()):
                try:
                    self.bus.send(can.Message(arbitration_id=reply.arbitration_id,
                                              data=reply.data, is_extended_id=False))
                except can.CanError:
                    self.reply_errors += 1

    def stop(self) -> None:
        """Stop the thread and close the bus."""
        self._halt.set()
        self.join(timeout=2.0)
        self._drops = self.receive_drops()   # while the socket is open
        self.bus.shutdown()

    def save(self, output: str) -> None:
        """Write the recording: t_ns, ids, torque and the events (t_ns, id, kind code)."""
        kinds = ('enter', 'exit', 'zero')
        np.savez(output, t_ns=np.asarray(self.t_ns, dtype=np.int64),
                 ids=np.asarray(self.ids, dtype=np.int64), torque=np.asarray(self.torque),
                 events=np.asarray([(t, i, kinds.index(k)) for t, i, k in self.events],
                                   dtype=np.int64).reshape(-1, 3),
                 reply_errors=self.reply_errors, receive_drops=self._drops)

    def armed_ns(self) -> Optional[int]:
        """Receive time of the first wheel torque command after every motor entered motor mode."""
        entered = {}
        for t, motor_id, kind in list(self.events):
            if kind == 'enter':
                entered.setdefault(motor_id, t)
        if set(entered) != self.motor_ids:
            return None
        since = max(entered.values())
        for t, motor_id in zip(list(self.t_ns), list(self.ids)):
            if t > since and motor_id == LEFT_ID:
                return t
        return None


def udp_drops(inode: Optional[int]) -> int:
    """Return the drops column of /proc/net/udp for the socket ``inode`` (-1: not found)."""
    if inode is None:
        return -1
    for table in ('/proc/net/udp', '/proc/net/udp6'):
        try:
            with open(table) as f:
                next(f)
                for line in f:
                    fields = line.split()
                    if len(fields) >= 13 and fields[9] == str(inode):
                        return int(fields[-1])
        except (OSError, StopIteration, ValueError):
            continue
    return -1


def run_motors(channel: str, port: int, output: str, motors: int = 2,
               priority: int = 0, interface: str = 'udp_multicast') -> None:
    """
    Be the motors until SIGINT/SIGTERM, then write the recording to output (.npz).

    Prints 'armed <t_ns>' once balance_node has put every motor in motor mode and commands
    torque (the parent starts measuring from there). A process of its own, so the parent's
    work (reading /diagnostics) never delays a reply.
    """
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    bus = MotorBus(channel, port, (WHEEL_IDS + HIP_IDS)[:motors], priority=priority,
                   interface=interface)
    bus.start()
    armed = None
    while not stop.wait(0.02):
        if armed is None:
            armed = bus.armed_ns()
            if armed is not None:
                print('armed %d' % armed, flush=True)
    bus.stop()
    bus.save(output)


class Recording:
    """What the motor process recorded (see MotorBus.save)."""

    def __init__(self, path: str):
        data = np.load(path)
        self.t_ns, self.ids, self.torque = data['t_ns'], data['ids'], data['torque']
        kinds = ('enter', 'exit', 'zero')
        self.events = [(int(t), int(i), kinds[k]) for t, i, k in data['events']]
        self.reply_errors = int(data['reply_errors'])
        self.receive_drops = int(data['receive_drops']) if 'receive_drops' in data else -1

    def commands(self, motor_id: int, t0_ns: int, t1_ns: int):
        """Commands to ``motor_id`` received in [t0_ns, t1_ns] -> (t_ns, torque)."""
        keep = (self.ids == motor_id) & (self.t_ns >= t0_ns) & (self.t_ns <= t1_ns)
        return self.t_ns[keep], self.torque[keep]


# ------------------------------------------------------------------------------ analysis

def probe_latencies(toggle_ns, toggle_level, frame_ns, frame_tau,
                    settle_ns: int = 6_000_000, min_step: float = 0.2) -> np.ndarray:
    """
    Latency of each probe [ns] for one motor's frames: NaN when unmeasured, inf when lost.

    The torque each probe level (toggle_level +-1) gives is learnt from the whole run (median
    of the frames from settle_ns after a toggle to the next toggle); a probe's latency is the
    delay from its toggle to the first frame past the half-way torque towards its level. A probe
    whose level never shows before the next toggle (the node stalled through it) is lost (inf).
    All NaN when the two levels differ by less than min_step [N m].
    """
    toggles = np.asarray(toggle_ns, dtype=np.int64)
    levels = np.asarray(toggle_level)
    t = np.asarray(frame_ns, dtype=np.int64)
    tau = np.asarray(frame_tau, dtype=np.float64)
    n = max(toggles.size - 1, 0)
    out = np.full(n, np.nan)
    if n == 0 or t.size == 0:
        return out
    # The probe each frame belongs to: the last toggle at or before it (-1: before the first).
    probe = np.searchsorted(toggles, t, side='right') - 1
    inside = (probe >= 0) & (probe < n)
    settled = inside & (t >= toggles[np.clip(probe, 0, n - 1)] + settle_ns)
    frame_level = np.where(inside, levels[np.clip(probe, 0, n - 1)], 0)
    value = {}
    for level in (1, -1):
        sel = settled & (frame_level == level)
        if not sel.any():
            return out
        value[level] = float(np.median(tau[sel]))
    if abs(value[1] - value[-1]) < min_step:
        return out
    middle = 0.5 * (value[1] + value[-1])
    side = {k: np.sign(v - middle) for k, v in value.items()}
    want = np.where(frame_level == 1, side[1], side[-1])
    hits = np.flatnonzero(inside & (np.sign(tau - middle) == want))
    out[:] = np.inf
    if hits.size == 0:
        return out
    first = np.searchsorted(t, toggles[:n])          # first frame of each probe's span
    end = np.searchsorted(t, toggles[1:n + 1])       # first frame of the next span
    k = np.searchsorted(hits, first)                 # first frame past half-way from there
    hit = hits[np.minimum(k, hits.size - 1)]
    ok = (k < hits.size) & (hit < end)
    out[ok] = t[hit[ok]] - toggles[:n][ok]
    return out


def frame_gaps(t_ns) -> Dict[str, float]:
    """Longest gap between consecutive frames [ms] and how many exceed 10, 100 and 250 ms."""
    d = np.diff(np.asarray(t_ns, dtype=np.int64)) / 1e6
    if d.size == 0:
        return {'max_ms': math.nan, 'over_10ms': 0, 'over_100ms': 0, 'over_250ms': 0}
    return {'max_ms': float(d.max()), 'over_10ms': int(np.sum(d > 10.0)),
            'over_100ms': int(np.sum(d > 100.0)), 'over_250ms': int(np.sum(d > 250.0))}


def _tail(path: str, lines: int = 15) -> str:
    try:
        with open(path, errors='replace') as f:
            return ''.join(f.readlines()[-lines:])
    except OSError:
        return ''


def stop_process(proc: subprocess.Popen, timeout: float = 10.0) -> Optional[int]:
    """SIGINT, then SIGTERM, then SIGKILL, to this one process; returns its exit code."""
    end_process(proc, signal.SIGINT, timeout, then=(signal.SIGTERM,))
    return proc.returncode


def descendants(pid: int) -> List[int]:
    """Return pid and every process below it (from /proc/<pid>/task/*/children)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            for tid in os.listdir('/proc/%d/task' % p):
                with open('/proc/%d/task/%s/children' % (p, tid)) as f:
                    todo.extend(int(c) for c in f.read().split())
        except OSError:
            continue   # it ended meanwhile
    return out


def process_name(pid: int) -> str:
    """Return a process's short name: the module it runs (python -m), else its command."""
    try:
        with open('/proc/%d/cmdline' % pid, 'rb') as f:
            argv = f.read().split(b'\0')
    except OSError:
        return str(pid)
    args = [a.decode(errors='replace') for a in argv if a]
    if '-m' in args[:-1]:
        return args[args.index('-m') + 1].rsplit('.', 1)[-1]
    return os.path.basename(args[0]) if args else str(pid)


def tree_cpu_seconds(pid: int) -> Dict[int, tuple]:
    """{pid: (name, CPU seconds)} of a process and its descendants."""
    out = {}
    for p in descendants(pid):
        try:
            out[p] = (process_name(p), proc_cpu_seconds(p))
        except (OSError, ValueError, IndexError):
            pass
    return out


def read_node_diagnostics(hardware_id: str, timeout: float = 5.0,
                          names: Sequence[str] = ()) -> Dict[str, Dict[str, str]]:
    """
    Read a node's /diagnostics: {status name: {key: value, 'message': ...}} ({} if none).

    Waits for every status of ``names`` (default: any two statuses) or the timeout.
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from diagnostic_msgs.msg import DiagnosticArray

    context = Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    found: Dict[str, Dict[str, str]] = {}
    try:
        node = rclpy.create_node('bench_diagnostics', context=context)

        def on_diag(msg):
            for status in msg.status:
                if status.hardware_id == hardware_id:
                    values = {kv.key: kv.value for kv in status.values}
                    values['message'] = status.message
                    found[status.name] = values

        def done():
            return all(n in found for n in names) if names else len(found) >= 2

        node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 10)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        end = time.monotonic() + timeout
        while not done() and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.1)
        executor.shutdown()
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    return found


#: The socketcan_hub channel in a Session's commands until its hub runs and tells its address.
HUB_ADDRESS = '<hub address>'
LOOP_STATUS = 'balance_node: control loop'
SAFETY_STATUS = 'balance_node: safety'


class Session:
    """
    One balance_node with its sensor and motor processes (see the module docstring).

    ``start`` returns once the node commands torque to every motor (or raises RuntimeError
    with the logs); ``stop`` ends the processes (the node first, with its exit frames);
    ``analyse(t0_ns, t1_ns)`` reads the recordings of a window of wall-clock time.
    """

    def __init__(self, workdir: str, env: Dict[str, str], group: str, port: int,
                 nut: NodeUnderTest = NodeUnderTest(), controller: str = 'ida_pbc',
                 realtime_priority: int = 0, extra_node_args: Sequence[str] = (),
                 node_module: str = NODE_MODULE, tag: str = '', namespace: str = '',
                 max_duration: float = 3600.0, plant_priority: int = 0,
                 interface: str = 'udp_multicast'):
        self.nut = nut
        self.env = env
        self.interface = interface
        self.hub: Optional[subprocess.Popen] = None
        if interface == socketcan_hub.INTERFACE:   # its channel: the hub's, once it runs
            group = HUB_ADDRESS
        self.group = group
        self.namespace = namespace or '/bench_%d%s' % (os.getpid(), tag)
        self.hardware_id = '%s:%s' % (interface, group)
        self.sensors_npz = os.path.join(workdir, 'sensors%s.npz' % tag)
        self.node_log = os.path.join(workdir, 'balance_node%s.log' % tag)
        self.pub_log = os.path.join(workdir, 'sensors%s.log' % tag)
        self.frames_npz = os.path.join(workdir, 'frames%s.npz' % tag)
        self.node_cmd = [
            sys.executable, '-m', node_module, '--ros-args', '-r', '__ns:=' + self.namespace,
            '-p', 'can.interface:=' + interface, '-p', 'can.channel:=' + group] + (
                ['-p', 'can.udp_port:=%d' % port] if interface == 'udp_multicast' else []) + [
            '-p', 'auto_arm:=true',
            '-p', 'controller:=' + controller, '-p', 'imu_timeout:=%g' % TIMEOUT,
            '-p', 'joint_state_timeout:=%g' % TIMEOUT, '-p', 'motor_timeout:=%g' % TIMEOUT,
            '-p', 'watchdog_timeout:=%g' % TIMEOUT,
            '-p', 'realtime_priority:=%d' % realtime_priority] + nut.node_args() + list(
                extra_node_args)
        self.motors_cmd = [sys.executable, '-m', 'wheelleg_balance.validation.bench.node',
                           'motors', '--interface', interface, '--channel', group,
                           '--port', str(port), '--output',
                           self.frames_npz, '--motors', str(nut.motors),
                           '--priority', str(plant_priority)]
        self.pub_cmd = [sys.executable, '-m', 'wheelleg_balance.validation.bench.node',
                        'publisher', '--namespace', self.namespace, '--output',
                        self.sensors_npz, '--max-duration', str(max_duration),
                        '--priority', str(plant_priority)] + (
                            ['--joint-states'] if nut.joint_states else [])
        self.node: Optional[subprocess.Popen] = None
        self.motors: Optional[subprocess.Popen] = None
        self.pub: Optional[subprocess.Popen] = None
        self.motor_lines: List[str] = []
        self.result: Dict = {'controller': controller, 'realtime_priority': realtime_priority,
                             'tree': nut.label, 'motor_count': nut.motors,
                             'interface': interface,
                             'command': ' '.join(['python'] + self.node_cmd[1:])}
        self.shutdown_ns: Optional[int] = None

    def start(self, timeout: float = 60.0) -> None:
        """Start the motors, the sensors and the node; wait until it commands torque."""
        if self.interface == socketcan_hub.INTERFACE:
            self._start_hub()
        self.motors = subprocess.Popen(self.motors_cmd, env=self.env, stdout=subprocess.PIPE,
                                       stderr=subprocess.STDOUT, text=True)

        def read_motor_output():
            for line in self.motors.stdout:
                self.motor_lines.append(line)

        threading.Thread(target=read_motor_output, daemon=True).start()
        with open(self.pub_log, 'w') as log:
            self.pub = subprocess.Popen(self.pub_cmd, env=self.env, stdout=log,
                                        stderr=subprocess.STDOUT)
        with open(self.node_log, 'w') as log:
            # In the tree's folder: ``python -m`` puts the working folder first on the path.
            self.node = subprocess.Popen(self.node_cmd, env=self.nut.env(self.env), stdout=log,
                                         stderr=subprocess.STDOUT, cwd=self.nut.tree)
        end = time.monotonic() + timeout
        while not any(line.startswith('armed') for line in self.motor_lines):
            if self.node.poll() is not None or self.pub.poll() is not None or \
                    self.motors.poll() is not None or time.monotonic() > end:
                raise RuntimeError(
                    'balance_node (%s) did not start balancing (node exit %s, sensors exit %s, '
                    'motors exit %s):\n%s%s%s' % (
                        self.nut.label, self.node.poll(), self.pub.poll(), self.motors.poll(),
                        _tail(self.node_log), _tail(self.pub_log),
                        ''.join(self.motor_lines[-10:])))
            time.sleep(0.05)
        # The node arms from a still pose, then homes and raises the legs (if it drives them):
        # the probes start once it balances.
        while time.monotonic() < end and self.alive:
            if self.diagnostics().get(SAFETY_STATUS, {}).get('mode') in ('BALANCING', 'FAULT'):
                break
        self.pub.send_signal(signal.SIGUSR1)

    def _start_hub(self) -> None:
        # The hub picks a free port and prints it ('ready 127.0.0.1:PORT'): the channel of
        # the node and the motors.
        self.hub = subprocess.Popen(socketcan_hub.hub_command(), env=self.env,
                                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        words = self.hub.stdout.readline().split()
        if len(words) != 2 or words[0] != 'ready':
            raise RuntimeError('the socketcan_hub hub did not start (exit %s): %s'
                               % (self.hub.poll(), ' '.join(words)))
        address = words[1]
        self.node_cmd = [a.replace(HUB_ADDRESS, address) for a in self.node_cmd]
        self.motors_cmd = [a.replace(HUB_ADDRESS, address) for a in self.motors_cmd]
        self.group = address
        self.hardware_id = '%s:%s' % (self.interface, address)
        self.result['command'] = ' '.join(['python'] + self.node_cmd[1:])

    @property
    def alive(self) -> bool:
        """Return True while the node, sensor and motor processes all run."""
        return all(p is not None and p.poll() is None
                   for p in (self.node, self.pub, self.motors))

    def cpu(self) -> Dict[int, tuple]:
        """{pid: (name, CPU seconds)} of the node's process tree now."""
        return tree_cpu_seconds(self.node.pid)

    def hub_cpu(self) -> float:
        """CPU seconds of the socketcan_hub hub now (NaN: no hub)."""
        if self.hub is None:
            return math.nan
        try:
            return proc_cpu_seconds(self.hub.pid)
        except OSError:
            return math.nan

    def diagnostics(self) -> Dict[str, Dict[str, str]]:
        """Read the node's /diagnostics now."""
        return read_node_diagnostics(self.hardware_id, names=(LOOP_STATUS, SAFETY_STATUS))

    def stop(self) -> None:
        """End the node (its exit frames reach the motors), then the motors and sensors."""
        self.shutdown_ns = time.time_ns()
        if self.node is not None:
            self.result['node_exit_code'] = stop_process(self.node)
        time.sleep(0.3)
        for proc in (self.motors, self.pub, self.hub):
            if proc is not None:
                stop_process(proc)
        if self.hub is not None:   # 'relayed N frames, dropped M'
            self.result['hub'] = self.hub.stdout.read().strip()

    def recording(self) -> Recording:
        """Return what the motor process recorded (after ``stop``)."""
        return Recording(self.frames_npz)

    def sensors(self):
        """Return what the sensor process recorded (after ``stop``)."""
        return np.load(self.sensors_npz)

    def analyse(self, t0_ns: int, t1_ns: int) -> Dict:
        """Return the frame, latency and sensor figures of [t0_ns, t1_ns] (after stop)."""
        rec = self.recording()
        result = dict(self.result)
        exits = sorted(i for t, i, kind in rec.events
                       if kind == 'exit' and t >= (self.shutdown_ns or 0))
        result['clean_shutdown'] = exits == sorted((WHEEL_IDS + HIP_IDS)[:self.nut.motors])
        # Motor-mode changes inside the window mean the node did not balance throughout.
        result['mode_changes_in_window'] = sum(
            1 for t, _, _ in rec.events if t0_ns <= t <= t1_ns)
        result['reply_errors'] = rec.reply_errors
        result['recorder_receive_drops'] = rec.receive_drops
        result['window_ns'] = [t0_ns, t1_ns]
        sensors = self.sensors()
        in_window = (sensors['toggle_ns'] >= t0_ns) & (sensors['toggle_ns'] <= t1_ns)
        toggles, levels = sensors['toggle_ns'][in_window], sensors['toggle_level'][in_window]
        per_motor, latencies = {}, []
        for motor_id in (WHEEL_IDS + HIP_IDS)[:self.nut.motors]:
            t, tau = rec.commands(motor_id, t0_ns, t1_ns)
            stats = period_stats(t)
            entry = {'frames': int(t.size), 'rate_hz': stats['rate_hz'],
                     'gaps': frame_gaps(t)}
            if motor_id in WHEEL_IDS:
                # While balancing, the probe keeps |tau| well above 0.3 N m; in FAULT the node
                # sends zero torque: the share of such commands is the share balanced.
                entry['balancing_share'] = float(np.mean(np.abs(tau) > 0.3))
                latencies.append(probe_latencies(toggles, levels, t, tau))
            if motor_id == LEFT_ID:
                result['timing'] = stats
            per_motor[str(motor_id)] = entry
        # A probe is done when both wheels have the new command (NaN, unmeasured, stays NaN).
        both = np.max(latencies, axis=0)
        valid = both[np.isfinite(both)]
        result['motors'] = per_motor
        latency = summary_us(valid)
        latency['lost'] = int(np.sum(np.isinf(both)))
        latency['p999_us'] = float(np.percentile(valid, 99.9)) / 1e3 if valid.size else math.nan
        latency['min_us'] = float(valid.min()) / 1e3 if valid.size else math.nan
        latency['probes'] = int(both.size)
        result['latency'] = latency
        imu = sensors['imu_ns']
        imu = imu[(imu >= t0_ns) & (imu <= t1_ns)]
        keys = ('rate_hz', 'period_p99_ms', 'period_max_ms')
        if imu.size >= 3:
            sensor_stats = period_stats(imu, SENSOR_PERIOD_NS)
            result['sensors'] = {k: sensor_stats[k] for k in keys}
        else:   # the sensor process did not save its recording of this window
            result['sensors'] = dict.fromkeys(keys, math.nan)
        return result


def cpu_figures(before: Dict[int, tuple], after: Dict[int, tuple], wall_s: float) -> Dict:
    """CPU of a process tree between two ``tree_cpu_seconds`` samples: total and per process."""
    per = {}
    for pid, (name, cpu1) in after.items():
        if pid in before:
            per['%s/%d' % (name, pid)] = cpu_percent(before[pid][1], cpu1, wall_s)
    return {'cpu_percent': sum(per.values()), 'processes': per}


def _number(values: Dict[str, str], key: str) -> float:
    try:
        return float(values.get(key, 'nan'))
    except ValueError:
        return math.nan


def run(duration: float, workdir: str, env: Dict[str, str], group: str, port: int,
        controller: str = 'ida_pbc', warmup: float = WARMUP, start_timeout: float = 60.0,
        realtime_priority: int = 0, extra_node_args=(), node_module: str = NODE_MODULE,
        on_window: Optional[Callable[[int, float], None]] = None, tag: str = '',
        nut: NodeUnderTest = NodeUnderTest(), interface: str = 'udp_multicast') -> Dict:
    """
    Run balance_node with sensors and fake motors, measure ``duration`` s after ``warmup``.

    Returns the node section of the report (see docs/benchmarks.md); raises RuntimeError with
    the node's output when it does not start balancing within start_timeout. on_window(pid,
    duration) is called with the control process's pid when the measurement starts (e.g. to
    attach a profiler); node_module lets a variant of the node be measured the same way; tag
    is appended to the names of the raw files written to workdir; nut: which node, wired how;
    interface: the bus, udp_multicast (group, port) or socketcan_hub (a hub of its own).
    """
    session = Session(workdir, env, group, port, nut, controller, realtime_priority,
                      extra_node_args, node_module, tag,
                      max_duration=start_timeout + warmup + duration + 30.0,
                      interface=interface)
    try:
        session.start(start_timeout)
        time.sleep(warmup)
        diag0 = session.diagnostics()
        hub0 = session.hub_cpu()
        t0_ns, cpu0 = time.time_ns(), session.cpu()
        threads0 = {p: thread_cpu_seconds(p) for p in cpu0}
        if on_window is not None:
            children = [p for p, (name, _) in cpu0.items() if name == 'control_process']
            on_window(children[0] if children else session.node.pid, duration)
        time.sleep(duration)
        t1_ns, cpu1 = time.time_ns(), session.cpu()
        wall = (t1_ns - t0_ns) * 1e-9
        hub_cpu = cpu_percent(hub0, session.hub_cpu(), wall)
        threads = []
        for p in cpu0:
            try:
                rows = thread_cpu_percent(p, threads0[p], thread_cpu_seconds(p), wall, top=3)
            except OSError:
                continue
            threads += [dict(r, process=cpu0[p][0]) for r in rows]
        if not session.alive:
            raise RuntimeError('a process died during the run:\n' + _tail(session.node_log))
        diag = session.diagnostics()
    finally:
        session.stop()
    result = session.analyse(t0_ns, t1_ns)
    result.update(cpu_figures(cpu0, cpu1, wall))
    if session.hub is not None:   # the bus's stand-in for the kernel: not the node's
        result['hub_cpu_percent'] = hub_cpu
    result['threads'] = sorted(threads, key=lambda r: -r['cpu_percent'])[:8]
    result['node_loop'] = diag.get(LOOP_STATUS, {})
    loop0, loop1 = diag0.get(LOOP_STATUS, {}), diag.get(LOOP_STATUS, {})
    result['overruns_in_window'] = _number(loop1, 'overruns') - _number(loop0, 'overruns')
    # Every tick of the window, not the last 1024 the node's percentiles cover: the ticks that
    # computed longer than the budget (half the period). Both counts come from statuses read
    # just before and just after the window (published at 1 Hz: up to about 1 s off).
    ticks = _number(loop1, 'ticks') - _number(loop0, 'ticks')
    over = _number(loop1, 'over_budget') - _number(loop0, 'over_budget')
    result['ticks_counted'] = ticks
    result['over_budget_in_window'] = over
    result['over_budget_share'] = over / ticks if ticks > 0 else math.nan
    safety = diag.get(SAFETY_STATUS, {})
    result['node_mode'] = safety.get('mode', 'unknown')
    result['node_faults'] = safety.get('fault_reasons', '')
    return result


def main(argv=None):
    """Entry of the helper processes: ``publisher`` (sensors) or ``motors``."""
    parser = argparse.ArgumentParser(description='benchmark helper process')
    parser.add_argument('role', choices=('publisher', 'motors'))
    parser.add_argument('--output', required=True)
    parser.add_argument('--namespace', help='publisher: ROS namespace of the node under test')
    parser.add_argument('--max-duration', type=float, default=600.0, help='publisher: [s]')
    parser.add_argument('--joint-states', action='store_true',
                        help="publisher: the wheels' joint_states too")
    parser.add_argument('--interface', default='udp_multicast',
                        choices=('udp_multicast', socketcan_hub.INTERFACE),
                        help='motors: the bus')
    parser.add_argument('--channel', help="motors: udp_multicast group or the hub's address")
    parser.add_argument('--port', type=int, default=43113, help='motors: UDP port')
    parser.add_argument('--motors', type=int, default=2, choices=(2, 6),
                        help='motors: 2 wheels, or 2 wheels and 4 hips')
    parser.add_argument('--priority', type=int, default=0,
                        help='SCHED_FIFO priority of the publishing / recording thread')
    args = parser.parse_args(argv)
    if args.role == 'publisher':
        run_publisher(args.namespace, args.output, args.max_duration, args.joint_states,
                      priority=args.priority)
    else:
        run_motors(args.channel, args.port, args.output, args.motors, args.priority,
                   args.interface)


if __name__ == '__main__':
    main()
