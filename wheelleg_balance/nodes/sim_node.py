"""
sim_node: the simulated robot (sim/robot_sim.py) in real time, with the robot's ROS and CAN faces.

- publishes ``imu`` (sensor_msgs/Imu, frame imu_link) and ``joint_states`` (both wheels and the
  four hips) every tick, ``publish_rate`` Hz (500), sensor-data QoS; ``~/ground_truth``
  (std_msgs/Float64MultiArray, field names in ``layout.dim[0].label``) at ``ground_truth_rate``;
- answers MIT-mode frames on the CAN bus (``can.*``) like the two wheel motors: enter / exit /
  zero and commands tau = kp (p - q) + kd (v - q_dot) + t evaluated every physics step, applied
  only between 'enter' and 'exit', clamped to +-can.mit.t_max; one reply per received frame.

Conventions (docs/simulation.md): joint_states reports each joint in its own axis convention, as
a joint_state_broadcaster would. A wheel joint's axis is its motor's shaft, so its position,
velocity and effort are the motor's (the same numbers as the CAN replies, apart from the motor's
settable zero): a positive value of the left wheel (can.left_direction = +1) rolls the robot
forward, of the right wheel (can.right_direction = -1, mirrored motor) backward. The hips are in
core/kinematics.py FiveBarLeg's convention (direction +1, offset 0). balance_node therefore needs
left_wheel_direction = can.left_direction and right_wheel_direction = can.right_direction.

A dedicated thread runs the loop: it sleeps to absolute deadlines (start + k period), advances the
simulation by exactly one period per tick and publishes; ROS spins in the main thread, CAN frames
are served by a receive thread.
"""
import math
import sys
import threading
import time
from typing import Dict, List, Optional

import can
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
import rclpy
from rclpy.exceptions import ParameterUninitializedException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from .can_io import open_bus
from ..core.protocols.base import Frame
from ..core.protocols.mit import MitCommand, MitProtocol
from ..sim.robot_sim import GROUND_TRUTH_FIELDS, LEG_JOINTS, Push, RobotSim, Slope


class MotorEmulator:
    """
    One MIT-mode wheel motor (pure Python): its mode, last command and zero offset.

    Positions and velocities passed in are the motor's (direction applied, before the zero).
    """

    def __init__(self, motor_id: int, torque_limit: float):
        self.motor_id = motor_id
        self.torque_limit = torque_limit
        self.enabled = False
        self.command: Optional[MitCommand] = None
        self.zero = 0.0          # motor position that reads as 0 [rad]
        self.torque = 0.0        # last torque applied [N m]
        self.frames = 0

    def handle(self, decoded, position: float) -> None:
        """Act on a decoded frame ('enter', 'exit', 'zero' or a MitCommand)."""
        self.frames += 1
        if decoded == 'enter':
            self.enabled = True
            self.command = None     # start from zero torque, not a stale command
        elif decoded == 'exit':
            self.enabled = False
            self.command = None
            self.torque = 0.0
        elif decoded == 'zero':
            self.zero = position
        elif isinstance(decoded, MitCommand):
            self.command = decoded

    def torque_for(self, position: float, velocity: float) -> float:
        """Return the motor torque [N m] for the present state (0 outside motor mode), clamped."""
        cmd = self.command
        if not self.enabled or cmd is None:
            self.torque = 0.0
            return 0.0
        tau = (cmd.kp * (cmd.position - (position - self.zero))
               + cmd.kd * (cmd.velocity - velocity) + cmd.torque)
        lim = self.torque_limit
        self.torque = min(max(tau, -lim), lim)
        return self.torque


def _f(lo, hi, description, read_only=True):
    return ParameterDescriptor(description=description, read_only=read_only,
                               floating_point_range=[FloatingPointRange(from_value=float(lo),
                                                                        to_value=float(hi))])


def _i(lo, hi, description, step=0):
    return ParameterDescriptor(description=description, read_only=True,
                               integer_range=[IntegerRange(from_value=lo, to_value=hi,
                                                           step=step)])


def _s(description):
    return ParameterDescriptor(description=description, read_only=True)


#: name -> (default, descriptor); list parameters without a default are in LIST_PARAMS.
PARAMS = {
    'publish_rate': (500.0, _f(10.0, 2000.0, 'loop and imu/joint_states rate [Hz]')),
    'ground_truth_rate': (100.0, _f(0.0, 1000.0, '~/ground_truth rate [Hz] (0: off)')),
    'imu_frame_id': ('imu_link', _s('frame_id of imu')),
    'imu_pitch_offset': (math.radians(2.2), _f(-0.5, 0.5, 'IMU pitch mounting offset d [rad]: '
                                               'the IMU reads theta + d (the paper: ~2.2 deg)')),
    'initial_pose': ('tail', _s("'tail': rest on the tail; 'pitch': wheels on the floor, body "
                                'at initial_pitch (falls unless balanced at once)')),
    'initial_pitch': (0.0, _f(-1.5, 1.5, 'body pitch for initial_pose pitch [rad]')),
    'height': (0.37, _f(0.37, 0.70, 'body height l [m] when no height_schedule is given')),
    'bump_height': (0.02, _f(0.001, 0.1, 'height of the bumps [m]')),
    'slope.enabled': (False, _s('put a ramp under one wheel (paper experiment 8)')),
    'slope.start_x': (1.0, _f(-100.0, 100.0, 'x where the ramp leaves the floor [m]')),
    'slope.length': (1.2, _f(0.1, 10.0, 'ramp length [m]')),
    'slope.angle': (math.radians(7.0), _f(0.0, 0.5, 'ramp angle [rad]')),
    'slope.side': ('left', _s("wheel track of the ramp: 'left' or 'right'")),
    'left_wheel_joint': ('left_wheel_joint', _s('joint_states name of the left wheel')),
    'right_wheel_joint': ('right_wheel_joint', _s('joint_states name of the right wheel')),
    'leg_joints': (list(LEG_JOINTS), _s('joint_states names of the hips: left front, left '
                                        'rear, right front, right rear')),
    'can.interface': ('virtual', _s('python-can interface: virtual (one process), '
                                    'udp_multicast (between processes) or socketcan')),
    'can.channel': ('wheelleg_sim', _s('python-can channel (udp_multicast: the group)')),
    'can.udp_port': (43113, _i(1, 65535, 'UDP port of the udp_multicast interface')),
    'can.protocol': ('mit', _s('motor protocol; only mit is simulated')),
    'can.left_motor_id': (1, _i(1, 2047, 'CAN ID of the left wheel motor')),
    'can.right_motor_id': (2, _i(1, 2047, 'CAN ID of the right wheel motor')),
    'can.left_direction': (1, _i(-1, 1, '+1 when a positive torque of the left motor drives '
                                 'the wheel forward, else -1', step=2)),
    'can.right_direction': (-1, _i(-1, 1, '+1 when a positive torque of the right motor '
                                   'drives the wheel forward, else -1', step=2)),
    'can.master_id': (0, _i(0, 2047, 'standard ID the motors reply on')),
    'can.mit.p_max': (12.5, _f(0.1, 1000.0, 'MIT position range +-p_max [rad]')),
    'can.mit.v_max': (50.0, _f(0.1, 1000.0, 'MIT velocity range +-v_max [rad/s]')),
    'can.mit.kp_max': (500.0, _f(0.1, 10000.0, 'MIT kp range 0..kp_max [N m/rad]')),
    'can.mit.kd_max': (5.0, _f(0.01, 1000.0, 'MIT kd range 0..kd_max [N m s/rad]')),
    'can.mit.t_max': (18.0, _f(0.1, 18.0, 'MIT torque range and motor limit +-t_max [N m] '
                               "(the model's actuators stop at 18)")),
}
LIST_PARAMS = {
    'height_schedule': 'flat [t0, l0, t1, l1, ...]: height l [m] at simulated time t [s], '
                       'linear in between; unset: constant height',
    'pushes': 'flat [start, duration, force_x, force_y, ...]: pushes on the body [s, s, N, N] '
              'in world axes; unset: none',
    'bumps': 'x positions of bumps across the floor [m]; unset: none',
}


class SimNode(Node):
    """The simulated robot as a ROS node (see the module docstring); start() runs it."""

    def __init__(self, **kwargs):
        super().__init__('sim_node', **kwargs)
        p = {}
        for name, (default, desc) in PARAMS.items():
            p[name] = self.declare_parameter(name, default, desc).value
        for name, text in LIST_PARAMS.items():
            self.declare_parameter(name, Parameter.Type.DOUBLE_ARRAY, _s(text))
            try:
                p[name] = list(self.get_parameter(name).value)
            except ParameterUninitializedException:
                p[name] = []
        self.params = p
        if p['can.protocol'] != 'mit':
            raise ValueError('sim_node simulates MIT-mode motors only (can.protocol: mit)')
        if p['can.left_motor_id'] == p['can.right_motor_id']:
            raise ValueError('the two motors need different CAN IDs')
        sched = p['height_schedule']
        pushes = p['pushes']
        if len(sched) % 2 or len(pushes) % 4 or len(p['leg_joints']) != 4:
            raise ValueError('height_schedule needs pairs, pushes groups of 4, leg_joints 4 '
                             'names')
        slope = None
        if p['slope.enabled']:
            slope = Slope(p['slope.start_x'], p['slope.length'], p['slope.angle'],
                          p['slope.side'])
        self.sim = RobotSim(
            d_offset=p['imu_pitch_offset'], height=p['height'],
            height_schedule=list(zip(sched[0::2], sched[1::2])),
            pushes=[Push(*pushes[i:i + 4]) for i in range(0, len(pushes), 4)],
            bumps=p['bumps'], bump_height=p['bump_height'], slope=slope)
        self.sim.reset(p['initial_pose'], pitch=p['initial_pitch'])

        t_max = p['can.mit.t_max']
        self.protocol = MitProtocol(
            p_min=-p['can.mit.p_max'], p_max=p['can.mit.p_max'], v_min=-p['can.mit.v_max'],
            v_max=p['can.mit.v_max'], kp_max=p['can.mit.kp_max'], kd_max=p['can.mit.kd_max'],
            t_min=-t_max, t_max=t_max, master_id=p['can.master_id'])
        # Index 0 = left wheel, 1 = right wheel.
        self.motors = [MotorEmulator(p['can.left_motor_id'], t_max),
                       MotorEmulator(p['can.right_motor_id'], t_max)]
        self.directions = (p['can.left_direction'], p['can.right_direction'])
        self._motor_by_id: Dict[int, int] = {m.motor_id: i for i, m in enumerate(self.motors)}
        # Motor-side state (position, velocity) per wheel, refreshed every physics step.
        self._motor_state = [(0.0, 0.0), (0.0, 0.0)]

        self.period = 1.0 / p['publish_rate']
        self.substeps = max(1, int(round(self.period / self.sim.timestep)))
        self.period = self.substeps * self.sim.timestep  # whole physics steps per tick
        gt_rate = p['ground_truth_rate']
        self._gt_every = max(1, int(round(1.0 / (gt_rate * self.period)))) if gt_rate else 0

        self.imu_pub = self.create_publisher(Imu, 'imu', qos_profile_sensor_data)
        self.joint_pub = self.create_publisher(JointState, 'joint_states',
                                               qos_profile_sensor_data)
        self.gt_pub = self.create_publisher(Float64MultiArray, '~/ground_truth', 10)
        self._imu = Imu()
        self._imu.header.frame_id = p['imu_frame_id']
        self._joints = JointState()
        self._joints.name = [p['left_wheel_joint'], p['right_wheel_joint']] + list(
            p['leg_joints'])
        self._gt = Float64MultiArray()
        self._gt.layout.dim = [MultiArrayDimension(label=','.join(GROUND_TRUTH_FIELDS),
                                                   size=len(GROUND_TRUTH_FIELDS),
                                                   stride=len(GROUND_TRUTH_FIELDS))]

        self.bus: Optional[can.BusABC] = None
        self._stop = threading.Event()
        self._threads: List[threading.Thread] = []
        # Loop statistics.
        self.ticks = 0
        self.late_ticks = 0      # ticks that started after their deadline + one period
        self.resyncs = 0         # times the loop gave up catching up
        self.can_frames = 0
        self.can_replies = 0
        self.can_errors = 0

    # ---- lifecycle --------------------------------------------------------------------------

    def start(self) -> None:
        """Open the CAN bus and start the loop and CAN threads."""
        p = self.params
        self.bus = open_bus(p['can.interface'], p['can.channel'], p['can.udp_port'])
        self._update_motor_state()
        self._threads = [threading.Thread(target=self._loop, name='sim_loop', daemon=True),
                         threading.Thread(target=self._can_loop, name='sim_can', daemon=True)]
        for t in self._threads:
            t.start()
        self.get_logger().info(
            'simulating at %.0f Hz (%d x %.1f ms physics steps), CAN %s %s, motors %d/%d' % (
                1.0 / self.period, self.substeps, 1e3 * self.sim.timestep, p['can.interface'],
                p['can.channel'], self.motors[0].motor_id, self.motors[1].motor_id))

    def stop(self) -> None:
        """Stop the threads and close the bus (idempotent)."""
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads = []
        if self.bus is not None:
            try:
                self.bus.shutdown()
            except Exception:  # noqa: B902 -- closing must not fail the shutdown path
                pass
            self.bus = None

    # ---- simulation loop --------------------------------------------------------------------

    def _update_motor_state(self) -> None:
        wheel_q = self.sim.wheel_angles()
        wheel_v = self.sim.wheel_velocities()
        dirs = self.directions
        self._motor_state = [(dirs[0] * wheel_q[0], dirs[0] * wheel_v[0]),
                             (dirs[1] * wheel_q[1], dirs[1] * wheel_v[1])]

    def _physics_tick(self) -> None:
        sim, motors, dirs = self.sim, self.motors, self.directions
        dt = sim.timestep
        for _ in range(self.substeps):
            (ql, vl), (qr, vr) = self._motor_state
            tau_l = dirs[0] * motors[0].torque_for(ql, vl)
            tau_r = dirs[1] * motors[1].torque_for(qr, vr)
            sim.step(tau_l, tau_r, dt)
            self._update_motor_state()

    def _publish(self) -> None:
        stamp = self.get_clock().now().to_msg()
        (qx, qy, qz, qw), gyro, acc = self.sim.imu()
        imu = self._imu
        imu.header.stamp = stamp
        o = imu.orientation
        o.x, o.y, o.z, o.w = qx, qy, qz, qw
        w = imu.angular_velocity
        w.x, w.y, w.z = gyro
        a = imu.linear_acceleration
        a.x, a.y, a.z = acc
        self.imu_pub.publish(imu)

        js = self._joints
        js.header.stamp = stamp
        (ql, vl), (qr, vr) = self._motor_state
        js.position = [ql, qr] + list(self.sim.leg_angles())
        js.velocity = [vl, vr] + list(self.sim.leg_velocities())
        js.effort = [self.motors[0].torque, self.motors[1].torque] + list(
            self.sim.leg_torques())
        self.joint_pub.publish(js)

        if self._gt_every and self.ticks % self._gt_every == 0:
            gt = self.sim.ground_truth()
            self._gt.data = [gt[k] for k in GROUND_TRUTH_FIELDS]
            self.gt_pub.publish(self._gt)

    def _loop(self) -> None:
        period = self.period
        deadline = time.monotonic()
        while not self._stop.is_set():
            try:
                self._physics_tick()
                self._publish()
            except Exception as exc:  # noqa: B902 -- keep the robot alive; report it
                if self._stop.is_set() or not rclpy.ok(context=self.context):
                    return
                self.get_logger().error('sim tick failed: %r' % exc)
            self.ticks += 1
            deadline += period
            delay = deadline - time.monotonic()
            if delay > 0.0:
                time.sleep(delay)
            elif delay < -period:
                self.late_ticks += 1
                if delay < -20.0 * period:  # far behind: restart the schedule from now
                    self.resyncs += 1
                    deadline = time.monotonic()

    # ---- CAN --------------------------------------------------------------------------------

    def _can_loop(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self.bus.recv(timeout=0.05)
            except (can.CanError, OSError, ValueError):
                self.can_errors += 1
                time.sleep(0.01)
                continue
            if msg is None or msg.is_error_frame or msg.is_remote_frame:
                continue
            index = self._motor_by_id.get(msg.arbitration_id)
            if index is None or msg.is_extended_id:
                continue  # another node's frame, or our own reply
            decoded = self.protocol.decode_command(
                Frame(msg.arbitration_id, bytes(msg.data), msg.is_extended_id))
            if decoded is None:
                continue
            self.can_frames += 1
            motor = self.motors[index]
            position, velocity = self._motor_state[index]
            motor.handle(decoded, position)
            torque = motor.torque_for(position, velocity)
            reply = self.protocol.encode_reply(motor.motor_id, position - motor.zero, velocity,
                                               torque)
            try:
                self.bus.send(can.Message(arbitration_id=reply.arbitration_id,
                                          data=reply.data, is_extended_id=False), timeout=0.01)
                self.can_replies += 1
            except (can.CanError, OSError, ValueError):
                self.can_errors += 1


def main(args=None) -> None:
    """Run sim_node until Ctrl-C."""
    # The CAN thread answers ~1000 frames/s: hand the GIL over sooner than the default 5 ms so
    # the loop thread wakes at its deadlines.
    sys.setswitchinterval(0.0005)
    rclpy.init(args=args)
    node = None
    try:
        node = SimNode()
        node.start()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.stop()
            # The context may be gone (SIGTERM): write to stderr, not through rosout.
            print('[sim_node] stopped after %d ticks (%d late, %d resyncs), %d CAN frames'
                  % (node.ticks, node.late_ticks, node.resyncs, node.can_frames),
                  file=sys.stderr)
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


if __name__ == '__main__':
    main()
