"""
balance_node under load, measured from outside: its CAN frames, its CPU time, its latency.

Set-up (one run, every process on localhost, ROS isolated by the caller's ROS_DOMAIN_ID and
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST plus a namespace of its own):

- balance_node as its own process (``python -m wheelleg_balance.nodes.balance_node``) on a
  ``udp_multicast`` CAN bus with a group and port of its own, ``auto_arm`` true;
- a sensor process (``python -m wheelleg_balance.tools.bench_node publisher``) publishing
  ``imu`` and ``joint_states`` from a loop sleeping to absolute deadlines (sensor-data QoS);
- a motor process (``python -m wheelleg_balance.tools.bench_node motors``) that is the two
  wheel motors: it records every frame on the bus with its kernel receive time
  (SO_TIMESTAMPNS) and answers each MIT command as the firmware does.

Latency probe: the robot stands still (pitch 0) and every ``TOGGLE_TICKS`` samples the sensor
process reverses the wheels' spin (w_left = -w_right = +-WHEEL_SPEED). That is a pure turn: the
ground speed stays 0, so u does not move, while the Sec. V-A yaw term flips the torque
difference between the wheels, whatever controller runs. The latency of a probe is the time
from publishing the first joint_states sample of the new spin (time.time_ns just before
publish) to the kernel receive time of the first frame (per motor) whose torque has crossed
half-way to its new value; a probe counts when both motors have it. Both clocks are
CLOCK_REALTIME on the same machine. The sensor period is 2.0004 ms (499.9 Hz) on purpose: the
sensor and control loops then slide past each other by one whole period every 10 s, so the
probes see every phase between a sample's arrival and the next control tick, instead of one
arbitrary phase for the whole run.
"""
import argparse
import math
import os
import signal
import subprocess
import sys
import threading
import time
from typing import Callable, Dict, List, Optional

import numpy as np

from .bench_stats import (cpu_percent, period_stats, proc_cpu_seconds, summary_us,
                          thread_cpu_percent, thread_cpu_seconds)
from ..core.protocols.base import Frame
from ..core.protocols.mit import MitProtocol

SENSOR_PERIOD_NS = 2_000_400
TOGGLE_TICKS = 10
WHEEL_SPEED = 5.0           # [rad/s]: yaw rate 2.1 rad/s, +-0.64 N m of yaw torque per wheel
LEFT_ID, RIGHT_ID = 1, 2
LEFT_JOINT, RIGHT_JOINT = 'left_wheel_joint', 'right_wheel_joint'
NODE_MODULE = 'wheelleg_balance.nodes.balance_node'
#: Sensor and motor timeouts of the node under test [s]. The sensor and motor processes are test
#: infrastructure on a shared machine: a stall of theirs must not fault the node and end the
#: measurement (test/test_balance_node.py does the same). A fault is still reported.
TIMEOUT = 0.25


# ------------------------------------------------------------------------ sensor process

def run_publisher(namespace: str, output: str, max_duration: float,
                  period_ns: int = SENSOR_PERIOD_NS, toggle_ticks: int = TOGGLE_TICKS,
                  wheel_speed: float = WHEEL_SPEED) -> None:
    """Publish imu and joint_states until SIGINT/SIGTERM or max_duration; write an .npz."""
    import rclpy
    from rclpy.qos import qos_profile_sensor_data
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import Imu, JointState

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('bench_sensors', namespace=namespace)
    imu_pub = node.create_publisher(Imu, 'imu', qos_profile_sensor_data)
    js_pub = node.create_publisher(JointState, 'joint_states', qos_profile_sensor_data)
    imu = Imu()
    imu.header.frame_id = 'imu_link'
    imu.orientation.w = 1.0        # pitch 0: the robot stands upright and still
    js = JointState()
    js.name = [LEFT_JOINT, RIGHT_JOINT]
    js.position = [0.0, 0.0]
    imu_ns: List[int] = []
    js_ns: List[int] = []
    toggle_ns: List[int] = []
    toggle_level: List[int] = []
    clock, wall = time.monotonic_ns, time.time_ns
    level = 1
    end = clock() + int(max_duration * 1e9)
    deadline = clock() + period_ns
    k = 0
    while not stop.is_set() and deadline < end:
        now = clock()
        if deadline > now:
            time.sleep((deadline - now) * 1e-9)
        toggled = k % toggle_ticks == 0
        if toggled:
            level = -level
            js.velocity = [-level * wheel_speed, level * wheel_speed]
        t = wall()
        imu.header.stamp.sec, imu.header.stamp.nanosec = divmod(t, 1_000_000_000)
        imu_pub.publish(imu)
        imu_ns.append(t)
        t = wall()
        js.header.stamp.sec, js.header.stamp.nanosec = divmod(t, 1_000_000_000)
        js_pub.publish(js)
        js_ns.append(t)
        if toggled:
            toggle_ns.append(t)
            toggle_level.append(level)
        deadline += period_ns
        k += 1
    node.destroy_node()
    rclpy.try_shutdown()
    np.savez(output, imu_ns=np.asarray(imu_ns, dtype=np.int64),
             js_ns=np.asarray(js_ns, dtype=np.int64),
             toggle_ns=np.asarray(toggle_ns, dtype=np.int64),
             toggle_level=np.asarray(toggle_level, dtype=np.int64))


# ----------------------------------------------------------------- fake motors + recorder

class MotorBus(threading.Thread):
    """The two wheel motors on the udp_multicast bus: record every frame, answer every command."""

    def __init__(self, channel: str, port: int, motor_ids=(LEFT_ID, RIGHT_ID)):
        super().__init__(name='bench_motors', daemon=True)
        import can
        self._can = can
        self.bus = can.Bus(interface='udp_multicast', channel=channel, port=port)
        self.protocol = MitProtocol()
        self.motor_ids = set(motor_ids)
        self.t_ns: List[int] = []       # torque commands: kernel receive time [ns, realtime]
        self.ids: List[int] = []
        self.torque: List[float] = []   # motor torque decoded [N m]
        self.events: List[tuple] = []   # (t_ns, motor id, 'enter' | 'exit' | 'zero')
        self.reply_errors = 0
        self._halt = threading.Event()

    def run(self) -> None:
        """Record and answer frames until stop()."""
        can, protocol = self._can, self.protocol
        while not self._halt.is_set():
            try:
                msg = self.bus.recv(0.1)
            except can.CanError:
                continue
            if msg is None or msg.arbitration_id not in self.motor_ids or msg.dlc != 8:
                continue  # our own replies (ID 0) come back through multicast loopback
            t_ns = int(round(msg.timestamp * 1e9))
            motor_id = msg.arbitration_id
            cmd = protocol.decode_command(Frame(motor_id, bytes(msg.data)))
            if isinstance(cmd, str):
                self.events.append((t_ns, motor_id, cmd))
                torque = 0.0
            elif cmd is None:
                continue
            else:
                self.t_ns.append(t_ns)
                self.ids.append(motor_id)
                self.torque.append(cmd.torque)
                torque = cmd.torque
            reply = protocol.encode_reply(motor_id, 0.0, 0.0, torque)
            try:
                self.bus.send(can.Message(arbitration_id=reply.arbitration_id, data=reply.data,
                                          is_extended_id=False))
            except can.CanError:
                self.reply_errors += 1

    def stop(self) -> None:
        """Stop the thread and close the bus."""
        self._halt.set()
        self.join(timeout=2.0)
        self.bus.shutdown()

    def save(self, output: str) -> None:
        """Write the recording: t_ns, ids, torque and the events (t_ns, id, kind code)."""
        kinds = ('enter', 'exit', 'zero')
        np.savez(output, t_ns=np.asarray(self.t_ns, dtype=np.int64),
                 ids=np.asarray(self.ids, dtype=np.int64), torque=np.asarray(self.torque),
                 events=np.asarray([(t, i, kinds.index(k)) for t, i, k in self.events],
                                   dtype=np.int64).reshape(-1, 3),
                 reply_errors=self.reply_errors)

    def armed_ns(self) -> Optional[int]:
        """Receive time of the first torque command after both motors entered motor mode."""
        entered = {}
        for t, motor_id, kind in list(self.events):
            if kind == 'enter':
                entered.setdefault(motor_id, t)
        if set(entered) != self.motor_ids:
            return None
        since = max(entered.values())
        for t in list(self.t_ns):
            if t > since:
                return t
        return None


def run_motors(channel: str, port: int, output: str) -> None:
    """
    Be the wheel motors until SIGINT/SIGTERM, then write the recording to output (.npz).

    Prints 'armed <t_ns>' once balance_node has put both motors in motor mode and commands
    torque (the parent starts measuring from there). A process of its own, so the parent's
    work (reading /diagnostics) never delays a reply.
    """
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    motors = MotorBus(channel, port)
    motors.start()
    armed = None
    while not stop.wait(0.02):
        if armed is None:
            armed = motors.armed_ns()
            if armed is not None:
                print('armed %d' % armed, flush=True)
    motors.stop()
    motors.save(output)


class Recording:
    """What the motor process recorded (see MotorBus.save)."""

    def __init__(self, path: str):
        data = np.load(path)
        self.t_ns, self.ids, self.torque = data['t_ns'], data['ids'], data['torque']
        kinds = ('enter', 'exit', 'zero')
        self.events = [(int(t), int(i), kinds[k]) for t, i, k in data['events']]
        self.reply_errors = int(data['reply_errors'])

    def commands(self, motor_id: int, t0_ns: int, t1_ns: int):
        """Torque commands to ``motor_id`` received in [t0_ns, t1_ns] -> (t_ns, torque)."""
        keep = (self.ids == motor_id) & (self.t_ns >= t0_ns) & (self.t_ns <= t1_ns)
        return self.t_ns[keep], self.torque[keep]


# ------------------------------------------------------------------------------ analysis

def probe_latencies(toggle_ns, toggle_level, frame_ns, frame_tau,
                    settle_ns: int = 6_000_000, min_step: float = 0.2) -> np.ndarray:
    """
    Latency of each probe [ns] for one motor's frames: NaN when unmeasured, inf when lost.

    The torque each spin direction (toggle_level +-1) gives is learnt from the whole run (median
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
    steady = {1: [], -1: []}
    for i in range(n):
        sel = (t >= toggles[i] + settle_ns) & (t < toggles[i + 1])
        steady[int(levels[i])].append(tau[sel])
    if not all(len(v) and np.concatenate(v).size for v in steady.values()):
        return out
    value = {k: float(np.median(np.concatenate(v))) for k, v in steady.items()}
    if abs(value[1] - value[-1]) < min_step:
        return out
    middle = 0.5 * (value[1] + value[-1])
    for i in range(n):
        side = np.sign(value[int(levels[i])] - middle)
        span = (t >= toggles[i]) & (t < toggles[i + 1])
        crossed = np.nonzero(np.sign(tau[span] - middle) == side)[0]
        out[i] = t[span][crossed[0]] - toggles[i] if crossed.size else np.inf
    return out


# --------------------------------------------------------------------------- orchestration

def _tail(path: str, lines: int = 15) -> str:
    try:
        with open(path, errors='replace') as f:
            return ''.join(f.readlines()[-lines:])
    except OSError:
        return ''


def stop_process(proc: subprocess.Popen, timeout: float = 10.0) -> Optional[int]:
    """SIGINT, then SIGTERM, then SIGKILL, to this one process; returns its exit code."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
        if proc.poll() is not None:
            break
        proc.send_signal(sig)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            continue
    return proc.poll()


def read_node_diagnostics(hardware_id: str, timeout: float = 5.0) -> Dict[str, Dict[str, str]]:
    """Read the node's /diagnostics: {status name: {key: value, 'message': ...}} ({} if none)."""
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

        node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 10)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        end = time.monotonic() + timeout
        while len(found) < 2 and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.1)
        executor.shutdown()
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    return found


def run(duration: float, workdir: str, env: Dict[str, str], group: str, port: int,
        controller: str = 'ida_pbc', warmup: float = 2.0, start_timeout: float = 60.0,
        realtime_priority: int = 0, extra_node_args=(), node_module: str = NODE_MODULE,
        on_window: Optional[Callable[[int, float], None]] = None, tag: str = '') -> Dict:
    """
    Run balance_node with sensors and fake motors, measure ``duration`` s after ``warmup``.

    Returns the node section of the report (see docs/benchmarks.md); raises RuntimeError with
    the node's output when it does not start balancing within start_timeout. on_window(pid,
    duration) is called when the measurement starts (e.g. to attach a profiler); node_module
    lets a variant of the node be measured the same way; tag is appended to the names of the
    raw files written to workdir.
    """
    namespace = '/bench_%d' % os.getpid()
    sensors_npz = os.path.join(workdir, 'sensors%s.npz' % tag)
    node_log = os.path.join(workdir, 'balance_node%s.log' % tag)
    pub_log = os.path.join(workdir, 'sensors%s.log' % tag)
    frames_npz = os.path.join(workdir, 'frames%s.npz' % tag)
    motors = subprocess.Popen(
        [sys.executable, '-m', 'wheelleg_balance.tools.bench_node', 'motors', '--channel', group,
         '--port', str(port), '--output', frames_npz],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    motor_lines: List[str] = []

    def read_motor_output():
        for line in motors.stdout:
            motor_lines.append(line)

    threading.Thread(target=read_motor_output, daemon=True).start()
    total = start_timeout + warmup + duration + 30.0
    with open(pub_log, 'w') as log:
        pub = subprocess.Popen(
            [sys.executable, '-m', 'wheelleg_balance.tools.bench_node', 'publisher',
             '--namespace', namespace, '--output', sensors_npz, '--max-duration', str(total)],
            env=env, stdout=log, stderr=subprocess.STDOUT)
    node_cmd = [sys.executable, '-m', node_module, '--ros-args', '-r', '__ns:=' + namespace,
                '-p', 'can.interface:=udp_multicast', '-p', 'can.channel:=' + group,
                '-p', 'can.udp_port:=%d' % port, '-p', 'auto_arm:=true',
                '-p', 'controller:=' + controller, '-p', 'imu_timeout:=%g' % TIMEOUT,
                '-p', 'joint_state_timeout:=%g' % TIMEOUT, '-p', 'motor_timeout:=%g' % TIMEOUT,
                '-p', 'realtime_priority:=%d' % realtime_priority] + list(extra_node_args)
    with open(node_log, 'w') as log:
        node = subprocess.Popen(node_cmd, env=env, stdout=log, stderr=subprocess.STDOUT)
    result: Dict = {'controller': controller, 'realtime_priority': realtime_priority,
                    'command': ' '.join(['python'] + node_cmd[1:])}
    try:
        end = time.monotonic() + start_timeout
        while not any(line.startswith('armed') for line in motor_lines):
            if node.poll() is not None or pub.poll() is not None or \
                    motors.poll() is not None or time.monotonic() > end:
                raise RuntimeError('balance_node did not start balancing (node exit %s, '
                                   'sensors exit %s, motors exit %s):\n%s%s%s' % (
                                       node.poll(), pub.poll(), motors.poll(), _tail(node_log),
                                       _tail(pub_log), ''.join(motor_lines[-10:])))
            time.sleep(0.05)
        time.sleep(warmup)
        t0_ns, cpu0 = time.time_ns(), proc_cpu_seconds(node.pid)
        threads0 = thread_cpu_seconds(node.pid)
        if on_window is not None:
            on_window(node.pid, duration)
        time.sleep(duration)
        t1_ns, cpu1 = time.time_ns(), proc_cpu_seconds(node.pid)
        result['threads'] = thread_cpu_percent(node.pid, threads0, thread_cpu_seconds(node.pid),
                                               (t1_ns - t0_ns) * 1e-9)
        if node.poll() is not None:
            raise RuntimeError('balance_node died during the run:\n' + _tail(node_log))
        diag = read_node_diagnostics('udp_multicast:' + group)
        result['node_loop'] = diag.get('balance_node: control loop', {})
        safety = diag.get('balance_node: safety', {})
        result['node_mode'] = safety.get('mode', 'unknown')
        result['node_faults'] = safety.get('fault_reasons', '')
    finally:
        shutdown_ns = time.time_ns()
        result['node_exit_code'] = stop_process(node)
        time.sleep(0.3)
        stop_process(motors)
        stop_process(pub)
    rec = Recording(frames_npz)
    result['cpu_percent'] = cpu_percent(cpu0, cpu1, (t1_ns - t0_ns) * 1e-9)
    exits = sorted(i for t, i, kind in rec.events if kind == 'exit' and t >= shutdown_ns)
    result['clean_shutdown'] = exits == [LEFT_ID, RIGHT_ID]
    # Motor-mode changes inside the window mean the node did not balance throughout.
    result['mode_changes_in_window'] = sum(
        1 for t, _, _ in rec.events if t0_ns <= t <= t1_ns)
    result['reply_errors'] = rec.reply_errors
    result['window_ns'] = [t0_ns, t1_ns]

    sensors = np.load(sensors_npz)
    in_window = (sensors['toggle_ns'] >= t0_ns) & (sensors['toggle_ns'] <= t1_ns)
    toggles, levels = sensors['toggle_ns'][in_window], sensors['toggle_level'][in_window]
    per_motor, latencies = {}, []
    for motor_id in (LEFT_ID, RIGHT_ID):
        t, tau = rec.commands(motor_id, t0_ns, t1_ns)
        stats = period_stats(t)
        # While balancing, the probe's yaw torque keeps |tau| near 0.64 N m; in FAULT the node
        # sends zero torque: the share of non-zero commands is the share of the run balanced.
        per_motor[str(motor_id)] = {'frames': int(t.size), 'rate_hz': stats['rate_hz'],
                                    'balancing_share': float(np.mean(np.abs(tau) > 0.3))}
        if motor_id == LEFT_ID:
            result['timing'] = stats
        latencies.append(probe_latencies(toggles, levels, t, tau))
    # A probe is done when both motors have the new command (NaN, unmeasured, stays NaN).
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
    sensor_stats = period_stats(imu, SENSOR_PERIOD_NS)
    result['sensors'] = {k: sensor_stats[k] for k in ('rate_hz', 'period_p99_ms',
                                                      'period_max_ms')}
    return result


def main(argv=None):
    """Entry of the helper processes: ``publisher`` (sensors) or ``motors``."""
    parser = argparse.ArgumentParser(description='benchmark helper process')
    parser.add_argument('role', choices=('publisher', 'motors'))
    parser.add_argument('--output', required=True)
    parser.add_argument('--namespace', help='publisher: ROS namespace of the node under test')
    parser.add_argument('--max-duration', type=float, default=600.0, help='publisher: [s]')
    parser.add_argument('--channel', help='motors: udp_multicast group')
    parser.add_argument('--port', type=int, default=43113, help='motors: UDP port')
    args = parser.parse_args(argv)
    if args.role == 'publisher':
        run_publisher(args.namespace, args.output, args.max_duration)
    else:
        run_motors(args.channel, args.port, args.output)


if __name__ == '__main__':
    main()
