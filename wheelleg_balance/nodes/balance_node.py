"""
balance_node: the 2 ms balance loop of the real robot (interface: DESIGN.md section 2).

Threads:

- the control thread ("balance_control"): sleeps to absolute deadlines (time.monotonic_ns; a late
  tick does not push later ones: up to MAX_CATCH_UP missed deadlines are served at once, a
  longer stall is skipped and counted as overruns). At each tick it takes the newest ``imu`` and
  ``joint_states`` samples straight from their subscriptions, reads the motors' CAN replies,
  runs the safety supervisor and BalanceCore.step, sends one torque command per wheel motor and
  publishes ~/state and odom at decimated rates. Mode changes (arm, disarm, fault) and parameter
  changes are applied by this thread at the start of a tick, so the core is never shared;
- the ROS executor (main thread): ``cmd_vel`` (its callback stores one tuple), the ~/arm
  service, parameter validation and /diagnostics.

Why the sensors are not read by the executor: rclpy's executor costs about 0.25 ms of Python per
wake-up, 1000 wake-ups a second for two 500 Hz topics; the control thread then waits for the GIL
and misses deadlines (docs/benchmarks.md). Their subscriptions live on a second node,
``<name>_sensors``, that no executor spins; topic names are resolved by this node first, so its
remappings apply.

Modes (core/safety.py): DISARMED sends no frames (the motors were left in rest mode by the exit
frames), BALANCING sends the controller's torques, FAULT sends zero torque every tick until an
explicit re-arm or disarm. See docs/balance_node.md.
"""
from array import array
import gc
import math
import signal
import sys
import threading
import time
from typing import Optional

import can
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import TwistStamped
from nav_msgs.msg import Odometry
import numpy as np
from rcl_interfaces.msg import SetParametersResult
import rclpy
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension
from std_srvs.srv import SetBool

from . import params as P
from .can_io import CanIo, open_bus
from ..core import realtime
from ..core.actuation import check_direction, motor_torque
from ..core.estimation import pitch_from_quaternion, pitch_rate_from_gyro, WheelOdometry
from ..core.kinematics import FiveBarLeg
from ..core.params import IdaPbcGains, RobotParams
from ..core.pipeline import BalanceCore, CONTROLLER_NAMES, CoreConfig, Measurement, Reference
from ..core.protocols.dji import DjiC620Protocol
from ..core.protocols.mit import MitProtocol
from ..core.safety import Mode, ReferenceShaper, SafetyLimits, SafetySupervisor, SensorSnapshot

#: Layout of ~/state (std_msgs/Float64MultiArray), documented in docs/balance_node.md.
STATE_FIELDS = ('theta', 'theta_dot', 'x', 'x_dot', 'yaw_rate', 'd_hat', 'l', 'u', 'tau_left',
                'tau_right', 'controller', 'mode', 'x_dot_ref', 'yaw_rate_ref')
_S = {name: i for i, name in enumerate(STATE_FIELDS)}

#: Samples of the period statistics ring (about 2 s at 500 Hz).
TIMING_WINDOW = 1024

#: Missed deadlines the loop serves late, back to back, before it gives up and skips a stall.
#: Catching up keeps the rate at 500 Hz and the observer's 2 ms time base (it is discretized
#: per update); a stall longer than this is skipped rather than answered by a long burst.
MAX_CATCH_UP = 5

#: Messages taken from one sensor subscription per tick at most (its queue holds 5).
MAX_TAKES = 16

_IDA_PBC_PARAMS = ('ida_pbc.k', 'ida_pbc.m22_0', 'ida_pbc.k_v', 'ida_pbc.P')


def make_protocol(v):
    """Build the wheel motors' CAN protocol from the parameter values ``v``."""
    if v['can.protocol'] == 'mit':
        return MitProtocol(p_min=-v['can.mit.p_max'], p_max=v['can.mit.p_max'],
                           v_min=-v['can.mit.v_max'], v_max=v['can.mit.v_max'],
                           kp_max=v['can.mit.kp_max'], kd_max=v['can.mit.kd_max'],
                           t_min=-v['can.mit.t_max'], t_max=v['can.mit.t_max'])
    return DjiC620Protocol(torque_constant=v['can.dji.torque_constant'],
                           gear_ratio=v['can.dji.gear_ratio'],
                           current_limit=v['can.dji.current_limit'])


class _ArmRequest:
    """An ~/arm call handed from the service callback to the control thread."""

    def __init__(self, arm: bool):
        self.arm = arm
        self.done = threading.Event()
        self.success = False
        self.message = 'not handled'


class BalanceNode(Node):
    """The balance controller node (see the module docstring)."""

    def __init__(self, bus=None, **kwargs):
        """
        Build the node, open the CAN bus and start the control thread.

        bus: an already open python-can bus to use instead of opening ``can.interface`` /
        ``can.channel`` (tests); the node owns it and shuts it down. kwargs go to rclpy's Node
        (e.g. parameter_overrides).
        """
        super().__init__('balance_node', **kwargs)
        v = P.declare_all(self)
        ok, reason = P.validate({}, v)
        if not ok:
            raise ValueError(reason)
        self._values = v
        self.p = RobotParams(body_mass=v['body_mass'], wheel_mass=v['wheel_mass'],
                             gravity=v['gravity'], wheel_radius=v['wheel_radius'],
                             wheel_separation=v['wheel_separation'],
                             height_min=v['height_min'], height_max=v['height_max'])
        self.period = v['control_period']
        self.core = BalanceCore(self.p, CoreConfig(
            controller=v['controller'], ida_pbc=self._ida_pbc_gains(v),
            compensate_offset=v['ida_pbc.compensate_offset'], d_hat0=v['d_hat0'],
            yaw_rate_gain=v['yaw_rate_gain'], max_wheel_torque=v['max_wheel_torque'],
            switch_blend_time=v['switch_blend_time'],
            lqr_Q=np.diag(v['output_regulation.q_diag']), lqr_R=v['output_regulation.r']),
            dt=self.period)
        self.left_id = v['can.left_motor_id']
        self.right_id = v['can.right_motor_id']
        if self.left_id == self.right_id:
            raise ValueError('can.left_motor_id and can.right_motor_id must differ')
        self.motor_ids = (self.left_id, self.right_id)
        self.left_dir = check_direction(v['can.left_direction'])
        self.right_dir = check_direction(v['can.right_direction'])
        self.supervisor = SafetySupervisor(SafetyLimits(
            fall_angle=v['fall_angle'], imu_timeout=v['imu_timeout'],
            joint_state_timeout=v['joint_state_timeout'], motor_timeout=v['motor_timeout'],
            max_pitch_rate=v['max_pitch_rate'], max_wheel_velocity=v['max_wheel_velocity']),
            self.motor_ids)
        self.shaper = ReferenceShaper(
            v['reference.max_velocity'], v['reference.max_acceleration'],
            v['reference.max_yaw_rate'], v['reference.max_yaw_acceleration'],
            v['cmd_vel_timeout'])
        self.odometry = WheelOdometry(self.p)
        self._setup_joints(v)
        self._height = v['height']

        self.protocol = make_protocol(v)
        self._hardware_id = '%s:%s' % (v['can.interface'], v['can.channel'])

        # Newest samples, written by the executor thread (one tuple assignment each).
        self._imu = None        # (t, theta~, theta_dot)
        self._wheels = None     # (t, w_left, w_right), forward positive
        self._legs = None       # (t, l)
        self._cmd = None        # (t, x_dot*, yaw_rate*)
        self.rejected_cmd_vel = 0
        self._imu_stamp = None  # header stamp of the newest IMU sample
        self.frozen_imu = 0     # IMU samples dropped for repeating the previous stamp
        self._snapshot = SensorSnapshot()

        self._pending = {}
        self._pending_lock = threading.Lock()
        self._arm_request: Optional[_ArmRequest] = None
        self._auto_arm = v['auto_arm']
        self._armed_once = False
        self._x = self._d_hat = 0.0
        self._last_tick_ns: Optional[int] = None
        self._tick_count = 0
        self._realtime = ''
        self._init_timing()

        self._state_every = self._decimation(v['state_publish_rate'])
        self._odom_every = self._decimation(v['odom_publish_rate'])
        self._state_pub = self._publisher(Float64MultiArray, '~/state')
        self._state_msg = Float64MultiArray()
        self._state_msg.layout.dim = [MultiArrayDimension(
            label=','.join(STATE_FIELDS), size=len(STATE_FIELDS), stride=len(STATE_FIELDS))]
        self._state = array('d', [0.0] * len(STATE_FIELDS))
        self._odom_pub = self._publisher(Odometry, 'odom')
        self._odom_msg = self._make_odom(v)
        self._diag_pub = self._publisher(DiagnosticArray, '/diagnostics')
        self.create_subscription(TwistStamped, 'cmd_vel', self._on_cmd_vel,
                                 qos_profile_sensor_data, event_callbacks=_no_sub_events())
        self._sensor_node = Node(self.get_name() + '_sensors', context=self.context,
                                 namespace=self.get_namespace(), use_global_arguments=False,
                                 enable_rosout=False, start_parameter_services=False)
        self._sensor_subs = [
            (self._sensor_node.create_subscription(
                msg_type, self.resolve_topic_name(topic), callback, qos_profile_sensor_data,
                event_callbacks=_no_sub_events()), callback)
            for msg_type, topic, callback in ((Imu, 'imu', self._on_imu),
                                              (JointState, 'joint_states',
                                               self._on_joint_states))]
        self.create_service(SetBool, '~/arm', self._on_arm)
        self._diag_period = 1.0 / v['diagnostics_rate']
        self._diag_last = -math.inf
        self._diag_key = None
        self.create_timer(0.05, self._on_diagnostics_timer)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self._stop = threading.Event()
        self._shut_down = False
        self._thread: Optional[threading.Thread] = None
        if bus is None:
            try:
                bus = open_bus(v['can.interface'], v['can.channel'], v['can.udp_port'])
            except (can.CanError, OSError, ValueError, ImportError) as exc:
                self._sensor_node.destroy_node()
                raise RuntimeError('cannot open CAN bus %s: %s' % (self._hardware_id, exc))
        self.can = CanIo(bus, self.protocol, self.motor_ids, v['can.send_timeout'])
        try:
            # Start from a known state: a crashed run may have left the motors in motor mode.
            self._send_stop_frames(time.monotonic())
            # The GIL is handed over every 5 ms by default: far too late for a 2 ms loop when
            # the executor thread is busy in Python.
            sys.setswitchinterval(min(sys.getswitchinterval(), 0.0002))
            self._thread = threading.Thread(target=self._run, name='balance_control',
                                            daemon=True)
            self._thread.start()
            self.get_logger().info(
                'balance_node: controller %s, CAN %s (%s, motors %d/%d), %.1f ms loop, %s' % (
                    v['controller'], self._hardware_id, v['can.protocol'], self.left_id,
                    self.right_id, 1e3 * self.period,
                    'auto_arm' if self._auto_arm else 'call ~/arm to balance'))
        except BaseException:
            # Whatever stopped the start (an error, a signal), the motors end at zero torque.
            self.shutdown()
            self._sensor_node.destroy_node()
            raise

    # ------------------------------------------------------------------------------- set-up

    @staticmethod
    def _ida_pbc_gains(v) -> IdaPbcGains:
        return IdaPbcGains(k=v['ida_pbc.k'], m22_0=v['ida_pbc.m22_0'], k_v=v['ida_pbc.k_v'],
                           P=v['ida_pbc.P'])

    def _publisher(self, msg_type, topic: str):
        # Without the default QoS event handlers: each is a waitable the executor re-adds to its
        # wait set at every wake-up (docs/benchmarks.md).
        return self.create_publisher(
            msg_type, topic, 10,
            event_callbacks=PublisherEventCallbacks(use_default_callbacks=False))

    def _decimation(self, rate: float) -> int:
        """Ticks between publications at ``rate`` [Hz]; 0 = never."""
        return 0 if rate <= 0.0 else max(1, int(round(1.0 / (rate * self.period))))

    def _setup_joints(self, v) -> None:
        self._left_wheel = v['left_wheel_joint']
        self._right_wheel = v['right_wheel_joint']
        self._wheel_dir = (check_direction(v['left_wheel_direction']),
                           check_direction(v['right_wheel_direction']))
        names = (v['left_leg_front_joint'], v['left_leg_rear_joint'],
                 v['right_leg_front_joint'], v['right_leg_rear_joint'])
        self._leg = FiveBarLeg(thigh=v['leg.thigh'], shank=v['leg.shank'],
                               hip_spacing=v['leg.hip_spacing'],
                               com_height=v['leg.com_height'], com_x=v['leg.com_x'])
        # Each leg as (front name, rear name, front dir, rear dir, front offset, rear offset).
        self._legs_cfg = []
        dirs, offs = v['leg_joint_directions'], v['leg_joint_offsets']
        for k in (0, 2):
            if names[k] and names[k + 1]:
                self._legs_cfg.append((names[k], names[k + 1], dirs[k], dirs[k + 1],
                                       offs[k], offs[k + 1]))
            elif names[k] or names[k + 1]:
                raise ValueError('a leg needs both its front and rear joint names')

    def _make_odom(self, v) -> Odometry:
        msg = Odometry()
        msg.header.frame_id = v['odom_frame_id']
        msg.child_frame_id = v['base_frame_id']
        for k, c in enumerate(v['pose_covariance_diagonal']):
            msg.pose.covariance[7 * k] = c
        for k, c in enumerate(v['twist_covariance_diagonal']):
            msg.twist.covariance[7 * k] = c
        return msg

    # ---------------------------------------------- subscription callbacks (either thread)

    def _on_imu(self, msg: Imu) -> None:
        o = msg.orientation
        if msg.orientation_covariance[0] == -1.0:  # sensor_msgs: "no orientation estimate"
            theta = math.nan
        else:
            theta = pitch_from_quaternion(o.x, o.y, o.z, o.w)
        stamp = (msg.header.stamp.sec, msg.header.stamp.nanosec)
        if stamp == self._imu_stamp and stamp != (0, 0):
            # A driver republishing one sample: keep its receipt time so it goes stale.
            self.frozen_imu += 1
            return
        self._imu_stamp = stamp
        self._imu = (time.monotonic(), theta, pitch_rate_from_gyro(msg.angular_velocity.y))

    def _on_joint_states(self, msg: JointState) -> None:
        now = time.monotonic()
        names = msg.name
        try:
            i_l = names.index(self._left_wheel)
            i_r = names.index(self._right_wheel)
            self._wheels = (now, self._wheel_dir[0] * msg.velocity[i_l],
                            self._wheel_dir[1] * msg.velocity[i_r])
        except (ValueError, IndexError):
            pass  # a message without our wheels (e.g. from another publisher)
        if not self._legs_cfg:
            return
        try:
            total = 0.0
            for front, rear, d_f, d_r, o_f, o_r in self._legs_cfg:
                q_front = o_f + d_f * msg.position[names.index(front)]
                q_rear = o_r + d_r * msg.position[names.index(rear)]
                total += self._leg.height(q_front, q_rear)
            self._legs = (now, total / len(self._legs_cfg))
        except (ValueError, IndexError):
            pass

    def _on_cmd_vel(self, msg: TwistStamped) -> None:
        x, w = msg.twist.linear.x, msg.twist.angular.z
        if math.isfinite(x) and math.isfinite(w):
            self._cmd = (time.monotonic(), x, w)
        else:
            self.rejected_cmd_vel += 1

    def _on_arm(self, request, response):
        req = _ArmRequest(bool(request.data))
        with self._pending_lock:
            self._arm_request = req
        if req.done.wait(1.0):
            response.success, response.message = req.success, req.message
        else:
            response.success, response.message = False, 'control loop did not answer'
        self.get_logger().info('~/arm %s: %s (%s)' % (
            request.data, 'ok' if response.success else 'refused', response.message))
        return response

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        changes = {p.name: p.value for p in parameters}
        ok, reason = P.validate(changes, self._values)
        if not ok:
            return SetParametersResult(successful=False, reason=reason)
        self._values.update(changes)
        with self._pending_lock:
            self._pending.update(changes)
        return SetParametersResult(successful=True)

    # ---------------------------------------------------------------------- control thread

    def _init_timing(self) -> None:
        self._periods = array('d', [0.0] * TIMING_WINDOW)
        self._computes = array('d', [0.0] * TIMING_WINDOW)
        self._overruns = 0      # deadlines skipped (never served)
        self._caught_up = 0     # deadlines served late by catching up
        self._late = 0
        self._tick_errors = 0

    def _apply_realtime(self) -> None:
        """Apply the real-time options from the control thread; refusals are logged, not fatal."""
        v = self._values
        results = {'thread_name': realtime.name_thread('balance_control')}
        cpu = v['realtime_cpu']
        results.update(realtime.apply(v['realtime_priority'], () if cpu < 0 else (cpu,),
                                      v['lock_memory']))
        self._realtime = '; '.join(message for _, message in results.values())
        for name in ('priority', 'affinity', 'memory_lock'):
            ok, message = results[name]
            if not ok:
                self.get_logger().warning('real-time option refused: %s' % message)

    def _take_samples(self) -> None:
        """Hand every imu / joint_states message received since the last tick to its callback."""
        for sub, callback in self._sensor_subs:
            handle, msg_type = sub.handle, sub.msg_type
            with handle:  # what rclpy's executor does to take a message
                for _ in range(MAX_TAKES):
                    taken = handle.take_message(msg_type, False)
                    if taken is None:
                        break
                    callback(taken[0])

    def _run(self) -> None:
        self._apply_realtime()
        period_ns = int(round(self.period * 1e9))
        late_ns = period_ns // 4
        deadline = time.monotonic_ns() + period_ns
        prev_start = None
        while not self._stop.is_set():
            now = time.monotonic_ns()
            if now < deadline:
                time.sleep((deadline - now) * 1e-9)
                now = time.monotonic_ns()
            k = self._tick_count % TIMING_WINDOW
            if prev_start is not None:
                self._periods[k] = (now - prev_start) * 1e-9
            prev_start = now
            if now - deadline > late_ns:
                self._late += 1
            try:
                if self.context.ok():  # after SIGINT/SIGTERM the subscriptions are gone
                    self._take_samples()
                self.can.poll()
                self._tick(now)
            except Exception as exc:  # noqa: B902 -- a bug must not kill the loop: zero torque
                self._tick_errors += 1
                self.supervisor.report_internal_error(now * 1e-9, repr(exc))
                self.get_logger().error('control tick failed: %r' % (exc,),
                                        throttle_duration_sec=1.0)
            if self.context.ok():  # publishing fails once SIGINT/SIGTERM shut rclpy down
                try:
                    self._publish()
                except Exception as exc:  # noqa: B902 -- a lost message is not a fault
                    if self.context.ok():  # else a signal shut rclpy down meanwhile
                        self.get_logger().warning('publishing failed: %r' % (exc,),
                                                  throttle_duration_sec=1.0)
            end = time.monotonic_ns()
            self._computes[k] = (end - now) * 1e-9
            self._tick_count += 1
            deadline += period_ns
            if end > deadline:
                missed = (end - deadline) // period_ns + 1  # deadlines already passed
                if missed > MAX_CATCH_UP:
                    self._overruns += missed
                    deadline += missed * period_ns
                else:
                    self._caught_up += 1  # the next tick runs at once, on its own deadline

    def _read_samples(self, now: float) -> SensorSnapshot:
        s = self._snapshot
        imu, wheels, legs = self._imu, self._wheels, self._legs
        if imu is None:
            s.imu_time, s.theta, s.theta_dot = None, math.nan, math.nan
        else:
            s.imu_time, s.theta, s.theta_dot = imu
        if wheels is None:
            s.joint_time, s.wheel_vel_left, s.wheel_vel_right = None, math.nan, math.nan
        else:
            s.joint_time, s.wheel_vel_left, s.wheel_vel_right = wheels
        if not self._legs_cfg:
            s.l = self._height
        elif legs is None:
            s.joint_time, s.l = None, math.nan
        else:
            s.l = legs[1]
            if s.joint_time is not None:
                s.joint_time = min(s.joint_time, legs[0])
        return s

    def _tick(self, now_ns: int) -> None:
        now = now_ns * 1e-9
        dt = self.period if self._last_tick_ns is None else (now_ns - self._last_tick_ns) * 1e-9
        self._last_tick_ns = now_ns
        if self._pending:
            self._apply_parameters()
        s = self._read_samples(now)
        if s.imu_time is not None and s.joint_time is not None and \
                self.supervisor.limits.plausible(s):
            self.odometry.update(s.wheel_vel_left, s.wheel_vel_right, s.theta_dot, dt)
        if self._arm_request is not None:
            with self._pending_lock:
                request, self._arm_request = self._arm_request, None
            self._handle_arm(request, now, s)
        elif self._auto_arm and not self._armed_once and self.supervisor.mode is Mode.DISARMED:
            if self.supervisor.check(now, s, self.can.reply_times) == ():
                self._handle_arm(_ArmRequest(True), now, s)
        mode = self.supervisor.update(now, s, self.can.reply_times)
        state = self._state
        if mode is Mode.BALANCING:
            cmd = self._cmd
            if cmd is None:
                x_ref, w_ref = self.shaper.update(now, None, 0.0, 0.0, dt)
            else:
                x_ref, w_ref = self.shaper.update(now, cmd[0], cmd[1], cmd[2], dt)
            out = self.core.step(Measurement(s.theta, s.theta_dot, s.wheel_vel_left,
                                             s.wheel_vel_right, s.l),
                                 Reference(x_ref, w_ref), dt)
            error = self.can.send(self.protocol.torque_frames({
                self.left_id: motor_torque(out.tau_left, self.left_dir),
                self.right_id: motor_torque(out.tau_right, self.right_dir)}))
            self.supervisor.report_send(now, error is None, error)
            self._x, self._d_hat = out.x, out.d_hat
            state[2], state[3], state[4] = out.x, out.x_dot, out.yaw_rate
            state[7], state[8], state[9] = out.u, out.tau_left, out.tau_right
            state[12], state[13] = x_ref, w_ref
        else:
            if mode is Mode.FAULT:
                error = self.can.send(self.protocol.zero_torque_frames(self.motor_ids))
                self.supervisor.report_send(now, error is None, error)
            state[2], state[3], state[4] = self._x, self.odometry.x_dot, self.odometry.yaw_rate
            state[7] = state[8] = state[9] = state[12] = state[13] = 0.0
        state[0], state[1], state[5], state[6] = s.theta, s.theta_dot, self._d_hat, s.l
        state[11] = int(mode)  # the mode these commands were made in

    def _publish(self) -> None:
        """Publish ~/state and odom when their decimation counters say so."""
        n = self._tick_count
        if self._state_every and n % self._state_every == 0:
            state = self._state
            state[10] = CONTROLLER_NAMES.index(self.core.active_controller)
            self._state_msg.data = state
            self._state_pub.publish(self._state_msg)
        if self._odom_every and n % self._odom_every == 0:
            self._publish_odom()

    def _handle_arm(self, req: _ArmRequest, now: float, s: SensorSnapshot) -> None:
        if not req.arm:
            self.supervisor.disarm()
            error = self._send_stop_frames(now)
            req.success = error is None
            req.message = 'disarmed' if error is None else 'disarmed, but %s' % error
        elif self.supervisor.mode is Mode.BALANCING:
            req.success, req.message = True, 'already balancing'
        else:
            ok, reason = self.supervisor.arm(now, s, self.can.reply_times)
            if ok:
                self.core.reset(Measurement(s.theta, s.theta_dot, s.wheel_vel_left,
                                            s.wheel_vel_right, s.l))
                self.shaper.reset()
                error = self.can.send(self.protocol.enable_frames(self.motor_ids))
                self.supervisor.report_send(now, error is None, error)
                if error is not None:
                    ok, reason = False, 'enter motor mode failed: %s' % error
                else:
                    self._armed_once = True
            req.success, req.message = ok, reason
        req.done.set()

    def _send_stop_frames(self, now: float) -> Optional[str]:
        """Zero torque, then exit motor mode, for both motors (disarm, start-up, shutdown)."""
        ids = self.motor_ids
        error = self.can.send(self.protocol.zero_torque_frames(ids)
                              + self.protocol.disable_frames(ids))
        self.supervisor.report_send(now, error is None, error)
        return error

    def _apply_parameters(self) -> None:
        with self._pending_lock:
            changes, self._pending = self._pending, {}
        v = self._values
        core, sup, shaper = self.core, self.supervisor, self.shaper
        for name, value in changes.items():
            if name == 'controller':
                core.select(value)
            elif name == 'height':
                self._height = value
            elif name in _IDA_PBC_PARAMS:
                core.set_ida_pbc_gains(self._ida_pbc_gains(v))
            elif name in ('d_hat0', 'yaw_rate_gain', 'max_wheel_torque', 'switch_blend_time'):
                setattr(core.config, name, value)
            elif name in ('fall_angle', 'imu_timeout', 'joint_state_timeout', 'motor_timeout',
                          'max_pitch_rate', 'max_wheel_velocity'):
                setattr(sup.limits, name, value)
            elif name == 'cmd_vel_timeout':
                shaper.cmd_vel_timeout = value
            elif name.startswith('reference.'):
                setattr(shaper, name[len('reference.'):], value)

    def _publish_odom(self) -> None:
        msg = self._odom_msg
        x, y, yaw = self.odometry.pose
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.pose.pose.position.x = x
        msg.pose.pose.position.y = y
        msg.pose.pose.orientation.z = math.sin(0.5 * yaw)
        msg.pose.pose.orientation.w = math.cos(0.5 * yaw)
        x_dot, yaw_rate = self.odometry.x_dot, self.odometry.yaw_rate
        msg.twist.twist.linear.x = x_dot if math.isfinite(x_dot) else 0.0
        msg.twist.twist.angular.z = yaw_rate if math.isfinite(yaw_rate) else 0.0
        self._odom_pub.publish(msg)

    # ---------------------------------------------------------------------------- diagnostics

    def timing(self) -> dict:
        """Loop statistics over the last TIMING_WINDOW ticks (periods and compute times [s])."""
        n = min(self._tick_count, TIMING_WINDOW)
        periods = np.frombuffer(self._periods, dtype=float)[:n].copy()
        computes = np.frombuffer(self._computes, dtype=float)[:n].copy()
        periods = periods[periods > 0.0]
        if periods.size == 0:
            periods = np.array([math.nan])
        if computes.size == 0:
            computes = np.array([math.nan])
        ticks = max(self._tick_count, 1)
        return {
            'ticks': self._tick_count, 'overruns': self._overruns,
            'caught_up': self._caught_up,
            'late_share': self._late / ticks, 'tick_errors': self._tick_errors,
            'period_mean': float(np.mean(periods)),
            'period_p99': float(np.percentile(periods, 99)),
            'period_max': float(np.max(periods)),
            'compute_mean': float(np.mean(computes)),
            'compute_p99': float(np.percentile(computes, 99)),
            'compute_max': float(np.max(computes)),
        }

    def _on_diagnostics_timer(self) -> None:
        sup = self.supervisor
        key = (sup.mode, sup.faults)
        now = time.monotonic()
        if key == self._diag_key and now - self._diag_last < self._diag_period:
            return
        self._diag_key, self._diag_last = key, now
        self._diag_pub.publish(self.diagnostics(now))

    def diagnostics(self, now: float) -> DiagnosticArray:
        """Build the DiagnosticArray: safety, control loop, CAN."""
        sup = self.supervisor
        mode = sup.mode
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()

        safety = DiagnosticStatus(name='balance_node: safety', hardware_id=self._hardware_id)
        conditions = sup.conditions
        if mode is Mode.FAULT:
            safety.level = DiagnosticStatus.ERROR
            safety.message = 'FAULT: ' + '; '.join(f.message for f in sup.faults)
        elif mode is Mode.BALANCING:
            safety.level = DiagnosticStatus.OK
            safety.message = 'BALANCING with %s' % self.core.active_controller
        else:
            safety.level = DiagnosticStatus.WARN if conditions else DiagnosticStatus.OK
            safety.message = 'DISARMED' + (
                ' (cannot arm: %s)' % '; '.join(f.message for f in conditions)
                if conditions else '')
        safety.values = _kv(
            mode=mode.name, mode_index=int(mode),
            faults=','.join(f.code for f in sup.faults),
            fault_reasons='; '.join(f.message for f in sup.faults),
            conditions=','.join(f.code for f in conditions),
            controller=self.core.active_controller,
            controller_parameter=self._values['controller'],
            x_dot_ref=self.shaper.x_dot_ref, yaw_rate_ref=self.shaper.yaw_rate_ref,
            cmd_vel_timed_out=self.shaper.timed_out,
            rejected_cmd_vel=self.rejected_cmd_vel, frozen_imu_samples=self.frozen_imu)

        t = self.timing()
        loop = DiagnosticStatus(name='balance_node: control loop', hardware_id=self._hardware_id)
        loop.level = DiagnosticStatus.OK if t['late_share'] < 0.05 and not t['tick_errors'] \
            else DiagnosticStatus.WARN
        loop.message = ('period mean %.3f ms, p99 %.3f ms, max %.3f ms, %d deadlines skipped, '
                        '%d caught up' % (1e3 * t['period_mean'], 1e3 * t['period_p99'],
                                          1e3 * t['period_max'], t['overruns'],
                                          t['caught_up']))
        loop.values = _kv(
            period_target_ms=1e3 * self.period,
            period_mean_ms=1e3 * t['period_mean'], period_p99_ms=1e3 * t['period_p99'],
            period_max_ms=1e3 * t['period_max'], overruns=t['overruns'],
            caught_up=t['caught_up'],
            late_share=t['late_share'], ticks=t['ticks'],
            compute_mean_ms=1e3 * t['compute_mean'], compute_p99_ms=1e3 * t['compute_p99'],
            compute_max_ms=1e3 * t['compute_max'], tick_errors=t['tick_errors'],
            realtime=self._realtime)

        io = self.can
        bus = DiagnosticStatus(name='balance_node: CAN', hardware_id=self._hardware_id)
        values = {'protocol': self.protocol.name, 'tx_frames': io.tx_frames,
                  'tx_errors': io.tx_errors, 'last_tx_error': io.last_tx_error,
                  'rx_frames': io.rx_frames, 'rx_replies': io.rx_replies,
                  'rx_errors': io.rx_errors, 'last_rx_error': io.last_rx_error}
        all_alive = True
        for motor_id, status in io.motors.items():
            age = math.inf if status.last_reply is None else now - status.last_reply
            alive = age <= sup.limits.motor_timeout
            all_alive = all_alive and alive
            prefix = 'motor_%d_' % motor_id
            values[prefix + 'alive'] = alive
            values[prefix + 'reply_age_s'] = age
            values[prefix + 'replies'] = status.replies
            fb = status.feedback
            if fb is not None:
                values[prefix + 'position'] = fb.position
                values[prefix + 'velocity'] = fb.velocity
                values[prefix + 'torque'] = fb.torque
                values[prefix + 'temperature'] = fb.temperature
                values[prefix + 'error'] = fb.error
        bus.values = _kv(**values)
        if mode is not Mode.DISARMED and not all_alive:
            bus.level, bus.message = DiagnosticStatus.ERROR, 'motor not answering'
        elif io.tx_errors:
            bus.level = DiagnosticStatus.WARN
            bus.message = '%d send errors, last: %s' % (io.tx_errors, io.last_tx_error)
        else:
            bus.level, bus.message = DiagnosticStatus.OK, 'ok'
        msg.status = [safety, loop, bus]
        return msg

    # ------------------------------------------------------------------------------ shutdown

    def shutdown(self) -> None:
        """Stop the loop, then zero torque, exit motor mode, close the bus (idempotent)."""
        if self._shut_down:
            return
        self._shut_down = True
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.supervisor.disarm()
        self._send_stop_frames(time.monotonic())
        self.can.close()

    def destroy_node(self):
        """Shut down (stop the loop, zero torque, close the bus), then destroy both nodes."""
        self.shutdown()
        self._sensor_node.destroy_node()
        return super().destroy_node()


def _no_sub_events() -> SubscriptionEventCallbacks:
    # Without the default QoS event handlers (see BalanceNode._publisher).
    return SubscriptionEventCallbacks(use_default_callbacks=False)


def _kv(**values):
    return [KeyValue(key=k, value=_fmt(v)) for k, v in values.items()]


def _fmt(v) -> str:
    if isinstance(v, float):
        return '%.6g' % v
    return str(v)


def _ignore_signal(signum, frame) -> None:
    """Let a signal do nothing in Python; rclpy's own handler has shut the context down."""


def main(args=None) -> int:
    """Run balance_node until SIGINT/SIGTERM; exit with zero torque and the motors disabled."""
    # SIGINT and SIGTERM only shut rclpy down (its handlers chain to these): no
    # KeyboardInterrupt may land in the constructor or the stop path and skip the exit frames.
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, _ignore_signal)
    rclpy.init(args=args)
    # Made before the node: the control thread balances from the start, so a signal can come
    # before spinning begins, and an executor cannot be created on a context already shut down.
    executor = SingleThreadedExecutor()
    node = None
    rc = 0
    try:
        node = BalanceNode()
        # Python's full garbage collection scans every live object: with rclpy, numpy and scipy
        # loaded that is ~90,000 objects and took 30 ms (15 control ticks) on the 2-core test
        # machine. Objects alive now live as long as the node: move them out of the collector's
        # sight (0.2 ms per full collection after this). docs/benchmarks.md.
        gc.collect()
        gc.freeze()
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as exc:  # noqa: B902 -- one clear line, no traceback
        if rclpy.ok():  # else a signal shut rclpy down while we started or spun: not an error
            print('balance_node: %s: %s' % (type(exc).__name__, exc), file=sys.stderr)
            rc = 1
    finally:
        if node is not None:
            node.destroy_node()  # stops the loop, zero torque, exit frames, closes the bus
        executor.shutdown()
        rclpy.try_shutdown()
    return rc


if __name__ == '__main__':
    sys.exit(main())
