"""
main_job's ROS side and its recordings: the ``Recorder`` node and a run's ``Trace``.

The Recorder subscribes to sim_node's ``~/ground_truth``, balance_node's ``~/state``, ``cmd_vel``,
``cmd_height`` and ``/diagnostics``, and calls balance_node's arm, stop and parameter services
and the joystick script's start (docs/main_job.md). A Trace is one run's recordings as numpy
arrays on one time axis, seconds since the start of balancing.
"""
import csv
import threading
import time
from typing import Dict, List, Optional

import numpy as np

from ..metrics import window


class Recorder:
    """This process's ROS side: recordings, the arm and start services, parameter calls."""

    def __init__(self):
        import rclpy
        from geometry_msgs.msg import TwistStamped
        from rcl_interfaces.srv import SetParameters
        from rclpy.executors import SingleThreadedExecutor
        from diagnostic_msgs.msg import DiagnosticArray
        from std_msgs.msg import Float64, Float64MultiArray
        from std_srvs.srv import SetBool, Trigger
        from ....nodes import lean
        # No parameter services and no QoS event handlers: fewer entities in the wait set that
        # the executor rebuilds at each of the IMU's 500 wake-ups a second (nodes/lean.py).
        self.node = rclpy.create_node('main_job', start_parameter_services=False)
        no_events = lean.subscription_events()
        self.gt: List[tuple] = []      # (receipt time, data...)
        self.state: List[tuple] = []
        self.cmd: List[tuple] = []     # (receipt time, x_dot*, yaw rate*)
        self.height: List[tuple] = []  # (receipt time, cmd_height [m])
        self.gt_labels: List[str] = []
        self.state_labels: List[str] = []
        self.node.create_subscription(Float64MultiArray, 'sim_node/ground_truth',
                                      self._on_gt, 100, event_callbacks=no_events)
        self.node.create_subscription(Float64MultiArray, 'balance_node/state',
                                      self._on_state, 100, event_callbacks=no_events)
        self.node.create_subscription(TwistStamped, 'cmd_vel', self._on_cmd, 100,
                                      event_callbacks=no_events)
        self.node.create_subscription(Float64, 'cmd_height', self._on_height, 10,
                                      event_callbacks=no_events)
        self.faults: List[str] = []    # balance_node's fault reasons (/diagnostics)
        self.fault_times: Dict[str, float] = {}   # reason: receipt time it was first seen
        self.loop: Dict[str, str] = {}  # balance_node's newest control-loop statistics
        #: The loads [%] balance_node's CAN status reported of each bus (bus_load_pct,
        #: leg_bus_load_pct with the hips on their own), and the wheels' protocol.
        self.bus_load: Dict[str, object] = {}
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10,
                                      event_callbacks=no_events)
        self.arm_client = self.node.create_client(SetBool, 'balance_node/arm')
        self.stop_client = self.node.create_client(Trigger, 'balance_node/stop')
        self.param_client = self.node.create_client(SetParameters,
                                                    'balance_node/set_parameters')
        self.start_client = self.node.create_client(Trigger, 'joy_script/start')
        self._SetBool, self._Trigger, self._SetParameters = SetBool, Trigger, SetParameters
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self.executor.spin, daemon=True)
        self._thread.start()

    def _on_gt(self, msg):
        if not self.gt_labels and msg.layout.dim:
            self.gt_labels = msg.layout.dim[0].label.split(',')
        self.gt.append((time.monotonic(),) + tuple(msg.data))

    def _on_state(self, msg):
        if not self.state_labels and msg.layout.dim:
            self.state_labels = msg.layout.dim[0].label.split(',')
        self.state.append((time.monotonic(),) + tuple(msg.data))

    def _on_cmd(self, msg):
        self.cmd.append((time.monotonic(), msg.twist.linear.x, msg.twist.angular.z))

    def _on_height(self, msg):
        self.height.append((time.monotonic(), msg.data))

    def _on_diag(self, msg):
        for st in msg.status:
            level = st.level[0] if isinstance(st.level, bytes) else int(st.level)  # a byte
            if st.name == 'balance_node: safety' and level >= 2 and \
                    st.message not in self.faults:
                self.faults.append(st.message)
                self.fault_times[st.message] = time.monotonic()
            elif st.name == 'balance_node: CAN':
                self._take_bus_load(st.values)
            elif st.name == 'balance_node: control loop':
                self.loop = {kv.key: kv.value for kv in st.values
                             if kv.key in ('overruns', 'late_share', 'period_p99_ms',
                                           'period_max_ms', 'ticks')}

    def _take_bus_load(self, values) -> None:
        for kv in values:
            if kv.key == 'protocol':
                self.bus_load['protocol'] = kv.value
            elif kv.key in ('bus_load_pct', 'leg_bus_load_pct'):
                try:
                    load = float(kv.value)
                except ValueError:
                    continue
                if load == load:   # not NaN (before a second status)
                    self.bus_load.setdefault(kv.key, []).append(load)

    def bus_load_summary(self) -> Dict[str, object]:
        """
        Return the wheels' protocol and each bus's median and highest load [%].

        The median is the budget's figure; the highest can be one status window that a stall
        of the simulated clock (lockstep) made short.
        """
        out: Dict[str, object] = {}
        for key, value in self.bus_load.items():
            if isinstance(value, list):
                ordered = sorted(value)
                out[key.replace('_pct', '_median_pct')] = ordered[len(ordered) // 2]
                out[key.replace('_pct', '_max_pct')] = ordered[-1]
            else:
                out[key] = value
        return out

    def start_mcap(self, path):
        """Also write every topic of the run into an MCAP file (validation/recording.py)."""
        from ...recording import start
        self.mcap = start(self.node, path)
        return self.mcap

    def stop_mcap(self):
        """Finish the MCAP file, if one is being written."""
        if getattr(self, 'mcap', None) is not None:
            self.mcap.close()
            self.mcap = None

    def clear(self):
        """Forget the previous run's recordings, faults and loop statistics."""
        self.gt, self.state, self.cmd, self.faults, self.loop = [], [], [], [], {}
        self.bus_load = {}
        self.fault_times = {}
        self.height = []

    def sim_time(self) -> Optional[float]:
        """Newest sim time seen on ~/ground_truth [s]."""
        if not self.gt or 'time' not in self.gt_labels:
            return None
        return self.gt[-1][1 + self.gt_labels.index('time')]

    def call(self, client, request, timeout=3.0):
        """Call a service; the response or None."""
        if not client.wait_for_service(timeout_sec=timeout):
            return None
        future = client.call_async(request)
        end = time.monotonic() + timeout
        while not future.done() and time.monotonic() < end:
            time.sleep(0.005)
        return future.result() if future.done() else None

    def arm(self, on: bool):
        """Arm (True) or disarm balance_node; the response or None."""
        return self.call(self.arm_client, self._SetBool.Request(data=on))

    def stop(self):
        """Cut the torque with balance_node's emergency stop service; the response or None."""
        return self.call(self.stop_client, self._Trigger.Request())

    def start_joystick(self):
        """Start the joystick script (``joy_script/start``); the response or None."""
        return self.call(self.start_client, self._Trigger.Request())

    def set_param(self, name: str, value):
        """Set one balance_node parameter; the response or None."""
        from rclpy.parameter import Parameter
        req = self._SetParameters.Request()
        req.parameters = [Parameter(name, value=value).to_parameter_msg()]
        return self.call(self.param_client, req)

    def save_csv(self, folder) -> None:
        """Write ground_truth, state, cmd_vel and cmd_height CSVs (receipt time first)."""
        save_csv(folder / 'ground_truth.csv', self.gt, self.gt_labels)
        save_csv(folder / 'state.csv', self.state, self.state_labels)
        save_csv(folder / 'cmd_vel.csv', self.cmd, ['x_dot_ref', 'yaw_rate_ref'])
        save_csv(folder / 'cmd_height.csv', self.height, ['height'])

    def close(self):
        """Stop spinning and destroy the node (before rclpy shuts down)."""
        self.executor.shutdown()
        # Join the spin thread before rclpy shuts down: a thread left inside rcl_wait at exit
        # ended the process with "terminate called without an active exception" (rc 134).
        self._thread.join(timeout=5.0)
        self.node.destroy_node()


def save_csv(path, rows, labels) -> None:
    """Write rows with a header: receipt_time, then the labels."""
    with open(path, 'w', newline='') as f:
        w = csv.writer(f)
        w.writerow(['receipt_time'] + list(labels))
        w.writerows(rows)


class Trace:
    """
    The recordings of one run as arrays, on one time axis: simulated seconds since time 0.

    Time 0 is the first ~/state in BALANCING after the arm; t0 and t_arm (the arm; None: the
    same) are receipt times. Every recording is put on sim_node's clock (the ground truth's
    'time'), the others through the receipt times of the ground truth around them: the
    physics' own time, whether sim_node ran in real time or slower (lockstep on a loaded
    machine). g: ground truth (sim_node's GROUND_TRUTH_FIELDS); s: balance_node's ~/state
    fields; c: cmd_vel (x_dot_ref, yaw_rate_ref); h: cmd_height (height). Data from 1 s before
    the arm to ``duration`` after time 0.
    """

    def __init__(self, rec: Recorder, t0: float, duration: float,
                 t_arm: Optional[float] = None):
        self.duration = duration
        gt = np.array(rec.gt, dtype=float).reshape(-1, len(rec.gt_labels) + 1)
        receipt, sim = gt[:, 0], gt[:, 1 + rec.gt_labels.index('time')]

        def to_sim(t):
            return np.interp(t, receipt, sim)
        t0_sim = float(to_sim(t0))
        #: The arm, in seconds before time 0 (negative: homing and raising the legs).
        self.t_arm = float(to_sim(t_arm if t_arm is not None else t0)) - t0_sim
        first = self.t_arm - 1.0

        def arrays(rows, labels, times=None):
            a = np.array(rows, dtype=float).reshape(-1, len(labels) + 1)
            t = (to_sim(a[:, 0]) if times is None else times) - t0_sim
            keep = (t >= first) & (t <= duration)
            return t[keep], {n: a[keep, i + 1] for i, n in enumerate(labels)}, a[keep, 0]

        self.tg, self.g, self._gt_receipt = arrays(rec.gt, rec.gt_labels, sim)
        self.ts, self.s, _ = arrays(rec.state, rec.state_labels)
        self.tc, self.c, _ = arrays(rec.cmd, ['x_dot_ref', 'yaw_rate_ref'])
        self.th, self.h, _ = arrays(getattr(rec, 'height', []), ['height'])
        #: Sim time at time 0 [s].
        self.start_sim_time = t0_sim

    def sim_to_rel(self, t_sim: float) -> float:
        """Time since time 0 [s] of a sim time [s]."""
        return t_sim - self.start_sim_time

    def sim_lag(self) -> float:
        """How far sim time fell behind the wall clock over the run [s]."""
        if self.tg.size < 2:
            return 0.0
        return float((self._gt_receipt[-1] - self._gt_receipt[0]) - (self.tg[-1] - self.tg[0]))

    def win(self, t0: float, t1: float) -> np.ndarray:
        """Mask of ground-truth samples in [t0, t1)."""
        return window(self.tg, t0, t1)

    def state_on_gt(self, name: str) -> np.ndarray:
        """Return a ~/state field at the ground-truth times (linear interpolation)."""
        return np.interp(self.tg, self.ts, self.s[name])

    def deg(self, name: str) -> np.ndarray:
        """Return a ground-truth angle in degrees."""
        return np.degrees(self.g[name])
