"""
sim_node: the simulated robot (sim/robot_sim.py) in real time, with the robot's ROS and CAN faces.

- publishes ``imu`` (sensor_msgs/Imu, frame imu_link) every tick, ``publish_rate`` Hz (500),
  sensor-data QoS, and ``joint_states`` (both wheels and the four hips) only when asked
  (``publish_joint_states``, off by default: on the robot nothing publishes them, balance_node
  reads the motors' replies); ``~/ground_truth`` (std_msgs/Float64MultiArray, field names in
  ``layout.dim[0].label``) at ``ground_truth_rate``;
- answers the motors' frames on the CAN bus (``can.*``) like the motors do, through one
  firmware emulator per motor (sim/robot_motors.py: each its protocol's ``make_emulator``):
  the two wheel motors (``can.protocol``) and the four hip motors (``legs.*``,
  ``legs.can.protocol``, on the wheels' bus or on a second one, ``legs.can.channel``), any
  registered protocol on either. The MIT motors: enter / exit / zero (zero in rest mode only)
  and commands tau = kp (p - q) + kd (v - q_dot) + t evaluated every physics step, applied
  only in motor mode, clamped to the motor's t_max; one reply per received frame with the
  true state (the other protocols as their modules say; a C620 group frame is answered by
  each ESC it carries, CyberGear frames are extended). Until
  balance_node drives them the hips are limp: the robot starts as after power-up
  (``initial_pose: folded``), legs folded onto their stops, resting on its tail;
- publishes ``/clock`` (rosgraph_msgs/Clock, the simulated time, 100 Hz) for nodes with
  ``use_sim_time`` and for ``bringup --sim``, which time themselves on the simulation;
- subscribes ``~/hand`` (sensor_msgs/JointState): the builder's hand of the bring-up checks
  (``bringup --sim``; sim/hand.py). Each named joint (the joint_states names) is pulled from
  where it is when the message arrives by ``position`` [rad] (its joint convention: wheels
  forward positive, hips FiveBarLeg's), with at most ``effort`` [N m] (empty: ``hand.max_torque``)
  and held there; a message without names lets go. With ``initial_pose: stand`` the body sits
  on a stand at the tail pitch with its wheels free (the bring-up pose).

Conventions (docs/simulation.md): joint_states reports each joint in its own axis convention, as
a joint_state_broadcaster would. A wheel joint's axis is its motor's shaft, so its position,
velocity and effort are the motor's (the same numbers as the CAN replies, apart from the motor's
settable zero and the replies' wrap at +-p_max): a positive value of the left wheel
(can.left_direction = +1) rolls the robot forward, of the right wheel (can.right_direction = -1,
mirrored motor) backward. The hips are in core/kinematics.py FiveBarLeg's convention.
balance_node therefore needs left_wheel_direction = can.left_direction and
right_wheel_direction = can.right_direction. A hip motor reads legs.directions[i] (q - offset)
(legs.offsets[i]: the joint angle at its zero), or, with legs.power_up, that only modulo one
rotor turn, as a real motor after power-up (homing resolves it).

Parameters: ``SimConfig`` (sim/config.py; ``ros2 param describe /sim_node <name>`` shows each
one's description and range), all read-only; a wrong value stops the node at start with every
problem named. A dedicated thread runs the loop on core/deadline.DeadlineLoop: it sleeps to
absolute deadlines (start + k period), advances the simulation by exactly one period per tick
and publishes; a late tick is followed at once by the ones it missed until the loop is
RESYNC_AFTER periods behind, when it restarts its schedule from now (simulated time follows the
wall clock; late ticks and resyncs are counted). ROS spins in the main thread, CAN frames are
served by a receive thread per bus. Its participant is UDP-only (nodes/dds.py): a publish
through Fast DDS's shared memory could hold the loop thread 0.33 s or more while other
processes come and go (docs/benchmarks.md, "The 0.33 s stall").

``lockstep`` (with balance_node's ``clock_source: imu_stamp``): imu is stamped with the
simulated time, and each tick first waits (at most ``lockstep_timeout``, wall clock) until the
commands balance_node computed from that sample are in (sim/robot_motors.py ``commanded``: the
wheels' frames close a tick, the hips' are sent before them). The loop never catches up in
bursts: when the wait or the CPU makes it late it simply runs slower than real time
(``real_time_factor``). The closed loop is then the same on a loaded machine as on an idle one
(docs/simulation.md).
"""
import argparse
from collections import Counter
import sys
import threading
import time
from typing import List, Optional

import can
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from rclpy.time import Time
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from . import lean
from .can_io import hands_back_own_frames, open_bus
from .dds import apply_udp_only
from .params import load
from ..core.deadline import DeadlineLoop
from ..core.protocols.base import Frame
from ..core.schema import to_flat
from ..optional import MissingDependency
from ..sim.config import motor_protocol, SimConfig
from ..sim.layout import WHEEL_JOINTS

try:
    from ..sim.hand import Hand
    from ..sim.robot_motors import default_specs, JOINTS, RobotMotors
    from ..sim.robot_sim import GROUND_TRUTH_FIELDS, Push, RobotSim, Slope
except MissingDependency as missing:
    # The executable's module: without MuJoCo there is nothing it can do but say so.
    raise SystemExit('sim_node: %s' % missing) from None

#: The loop serves every missed deadline until this many periods behind, then restarts its
#: schedule from now (simulated time follows the wall clock; a resync is counted).
RESYNC_AFTER = 20
#: /clock every this many ticks (100 Hz at 500 Hz).
CLOCK_EVERY = 5


class SimNode(Node):
    """The simulated robot as a ROS node (see the module docstring); start() runs it."""

    def __init__(self, **kwargs):
        super().__init__('sim_node', **kwargs)
        self.config = cfg = load(self, SimConfig)   # ValueError with every problem
        #: {parameter name: value} of the configuration (what the tests and logs read).
        self.params = to_flat(cfg)
        pushes = cfg.pushes
        slope = None
        if cfg.slope.enabled:
            sl = cfg.slope
            slope = Slope(sl.start_x, sl.length, sl.angle, sl.side)
        self.sim = RobotSim(
            d_offset=cfg.imu_pitch_offset, height=cfg.height,
            pushes=[Push(*pushes[i:i + 4]) for i in range(0, len(pushes), 4)],
            bumps=cfg.bumps, bump_height=cfg.bump_height, slope=slope, legs='motors',
            body=cfg.robot)
        self.sim.reset(cfg.initial_pose, pitch=cfg.initial_pitch, lift=cfg.stand_lift)

        c, legs, fw = cfg.can, cfg.legs, cfg.can.firmware
        self.protocol = motor_protocol(c, c.master_id)
        self.directions = (c.left_direction, c.right_direction)
        specs = default_specs(
            (c.left_motor_id, c.right_motor_id), self.directions, tuple(legs.motor_ids),
            tuple(legs.directions), tuple(legs.offsets), hip_bus=1 if cfg.second_bus else 0)
        self.motors = RobotMotors(
            self.sim, specs, self.protocol, motor_protocol(legs, c.master_id),
            gear_ratio=legs.gear_ratio, command_timeout=fw.command_timeout,
            timeout_action=fw.timeout_action, wrap=fw.wrap,
            reply_temperature=fw.reply_temperature, power_up=legs.power_up)
        for e in self.motors.emulators.values():
            e.miswired = e.motor_id == cfg.fault.miswired_motor_id
            if e.motor_id == cfg.fault.wrong_mode_motor_id:   # SimConfig checked it has one
                e.set_control_mode(cfg.fault.wrong_mode)
        h = cfg.hand
        self.motors.hand = Hand(len(JOINTS), h.kp, h.kd, h.max_torque)
        self._hand_joints = {name: k for k, name in enumerate(
            [cfg.left_wheel_joint, cfg.right_wheel_joint] + list(cfg.leg_joints))}
        self._channels = cfg.channels

        self.substeps = max(1, int(round((1.0 / cfg.publish_rate) / self.sim.timestep)))
        self.period = self.substeps * self.sim.timestep  # whole physics steps per tick
        gt_rate = cfg.ground_truth_rate
        self._gt_every = max(1, int(round(1.0 / (gt_rate * self.period)))) if gt_rate else 0
        # A tick that starts more than a period after its deadline is late. In lockstep a late
        # tick restarts the schedule: simulated time slows down instead of bursting.
        self.loop = DeadlineLoop(self.period, max_catch_up=None,
                                 resync_after=0 if cfg.lockstep else RESYNC_AFTER,
                                 late_after=self.period, on_error=self._on_tick_error)
        self._commands = threading.Condition()
        self._marks: Optional[dict] = None
        #: lockstep: ticks whose commands did not come within lockstep_timeout.
        self.lockstep_timeouts = 0
        self._wall_start: Optional[float] = None

        self.imu_pub = self.create_publisher(Imu, 'imu', qos_profile_sensor_data,
                                             event_callbacks=lean.publisher_events())
        self.joint_pub = self.create_publisher(JointState, 'joint_states',
                                               qos_profile_sensor_data,
                                               event_callbacks=lean.publisher_events())
        self.gt_pub = self.create_publisher(Float64MultiArray, '~/ground_truth', 10,
                                            event_callbacks=lean.publisher_events())
        # /clock, the simulated time, every CLOCK_EVERY ticks: nodes with use_sim_time (the
        # scripted joystick, teleop_node in lockstep) and bringup --sim time themselves on it.
        self.clock_pub = self.create_publisher(Clock, '/clock', 10,
                                               event_callbacks=lean.publisher_events())
        self._clock_msg = Clock()
        self.create_subscription(JointState, '~/hand', self._on_hand, 10,
                                 event_callbacks=lean.subscription_events())
        self._imu = Imu()
        self._imu.header.frame_id = cfg.imu_frame_id
        self._joints = JointState()
        self._joints.name = [cfg.left_wheel_joint, cfg.right_wheel_joint] + list(
            cfg.leg_joints)
        self._wheel_emulators = [self.motors.motor(j) for j in WHEEL_JOINTS]
        self._gt = Float64MultiArray()
        self._gt.layout.dim = [MultiArrayDimension(label=','.join(GROUND_TRUTH_FIELDS),
                                                   size=len(GROUND_TRUTH_FIELDS),
                                                   stride=len(GROUND_TRUTH_FIELDS))]

        self.buses: List[can.BusABC] = []
        self._stop = threading.Event()
        self._threads: List[threading.Thread] = []
        self.can_frames = 0
        self.can_replies = 0
        self.can_errors = 0

    # ---- loop statistics --------------------------------------------------------------------

    @property
    def ticks(self) -> int:
        """Return the ticks run so far."""
        return self.loop.ticks

    @property
    def late_ticks(self) -> int:
        """Return the ticks that started more than one period after their deadline."""
        return self.loop.late

    @property
    def real_time_factor(self) -> float:
        """Return simulated time over wall time since the loop started (1.0: real time)."""
        if self._wall_start is None:
            return float('nan')
        return self.motors.time / max(time.monotonic() - self._wall_start, 1e-9)

    @property
    def resyncs(self) -> int:
        """Return how often the loop gave up catching up (RESYNC_AFTER periods behind)."""
        return self.loop.resyncs

    # ---- lifecycle --------------------------------------------------------------------------

    @property
    def bus(self) -> Optional[can.BusABC]:
        """Return the bus of the wheel motors (None before start)."""
        return self.buses[0] if self.buses else None

    def start(self) -> None:
        """Open the CAN bus(es) and start the loop and CAN threads."""
        c = self.config.can
        self.buses = [open_bus(c.interface, channel, c.udp_port) for channel in self._channels]
        self._threads = [threading.Thread(target=self.loop.run, args=(self._tick,),
                                          name='sim_loop', daemon=True)]
        self._threads += [threading.Thread(target=self._can_loop, args=(k,),
                                           name='sim_can%d' % k, daemon=True)
                          for k in range(len(self.buses))]
        for t in self._threads:
            t.start()
        motors = ', '.join('%s %d' % (s.joint, s.motor_id) for s in self.motors.specs)
        self.get_logger().info(
            'simulating at %.0f Hz (%d x %.1f ms physics steps), pose %s, CAN %s %s, motors: %s'
            % (1.0 / self.period, self.substeps, 1e3 * self.sim.timestep,
               self.config.initial_pose, c.interface, ' + '.join(self._channels), motors))

    def stop(self) -> None:
        """Stop the threads and close the buses (idempotent)."""
        self._stop.set()
        self.loop.stop()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads = []
        for bus in self.buses:
            try:
                bus.shutdown()
            except Exception:  # noqa: B902 -- closing must not fail the shutdown path
                pass
        self.buses = []

    # ---- simulation loop --------------------------------------------------------------------

    def _publish(self) -> None:
        sim_stamp = Time(nanoseconds=int(round(self.motors.time * 1e9))).to_msg()
        if self.ticks % CLOCK_EVERY == 0:
            self._clock_msg.clock = sim_stamp
            self.clock_pub.publish(self._clock_msg)
        stamp = sim_stamp if self.config.lockstep else self.get_clock().now().to_msg()
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

        if self.config.publish_joint_states:
            js = self._joints
            js.header.stamp = stamp
            # Wheels in their motor's convention (direction applied, no zero), hips in
            # FiveBarLeg's.
            d = self.directions
            wq, wv = self.sim.wheel_angles(), self.sim.wheel_velocities()
            js.position = [d[0] * wq[0], d[1] * wq[1]] + list(self.sim.leg_angles())
            js.velocity = [d[0] * wv[0], d[1] * wv[1]] + list(self.sim.leg_velocities())
            js.effort = [e.motor_torque for e in self._wheel_emulators] + list(
                self.sim.leg_torques())
            self.joint_pub.publish(js)

        if self._gt_every and self.ticks % self._gt_every == 0:
            gt = self.sim.ground_truth()
            self._gt.data = [gt[k] for k in GROUND_TRUTH_FIELDS]
            self.gt_pub.publish(self._gt)

    def _on_hand(self, msg: JointState) -> None:
        # The builder's hand (bring-up): displacements from where the joints are now.
        moves, limits = {}, {}
        for i, name in enumerate(msg.name):
            k = self._hand_joints.get(name)
            if k is None or i >= len(msg.position):
                self.get_logger().warning('~/hand: no joint %r with a position' % name)
                continue
            moves[k] = float(msg.position[i])
            if i < len(msg.effort):
                limits[k] = float(msg.effort[i])
        if moves:
            self.motors.hand.grab(moves, self.motors.joint_angles(), limits)
        else:
            self.motors.hand.release()

    def _tick(self, now_ns: int) -> None:
        if self._wall_start is None:
            self._wall_start = time.monotonic()
        if self.config.lockstep and self._marks is not None:
            self._wait_for_commands()
        # Exactly one period of simulated time per tick, whenever the tick runs.
        self.motors.step(self.period)
        if self.config.lockstep:
            with self._commands:
                self._marks = self.motors.command_marks()
        self._publish()

    def _wait_for_commands(self) -> None:
        """Lockstep: wait until the motors in motor mode have the tick's commands."""
        with self._commands:
            if not self._commands.wait_for(lambda: self.motors.commanded(self._marks),
                                           self.config.lockstep_timeout):
                if not self._stop.is_set():
                    self.lockstep_timeouts += 1

    def _on_tick_error(self, now_ns: int, exc: BaseException) -> None:
        if self._stop.is_set() or not rclpy.ok(context=self.context):
            self.loop.stop()   # shutting down: the publishers are gone
            return
        self.get_logger().error('sim tick failed: %r' % exc)

    # ---- CAN --------------------------------------------------------------------------------

    def _can_loop(self, index: int) -> None:
        bus = self.buses[index]
        # Our own replies, where the bus hands them back (udp_multicast): a motor never hears
        # its own frames, and an LK motor's echo of run (0x88) is that command again.
        own: Optional[Counter] = Counter() if hands_back_own_frames(bus) else None
        while not self._stop.is_set():
            try:
                msg = bus.recv(timeout=0.05)
            except (can.CanError, OSError, ValueError):
                self.can_errors += 1
                time.sleep(0.01)
                continue
            if msg is None or msg.is_error_frame or msg.is_remote_frame:
                continue
            if own:
                key = (msg.arbitration_id, bytes(msg.data), msg.is_extended_id)
                if own[key] > 0:
                    own[key] -= 1
                    if not own[key]:
                        del own[key]
                    continue
            # None: another node's frame, our own reply, or not a command frame.
            with self._commands:
                replies = self.motors.replies(
                    Frame(msg.arbitration_id, bytes(msg.data), msg.is_extended_id), index)
                self._commands.notify()
            if not replies:
                continue
            self.can_frames += 1
            for reply in replies:   # a C620 group frame: one per ESC it carries
                try:
                    bus.send(can.Message(arbitration_id=reply.arbitration_id, data=reply.data,
                                         is_extended_id=reply.is_extended_id), timeout=0.01)
                    self.can_replies += 1
                    if own is not None:
                        own[(reply.arbitration_id, bytes(reply.data), reply.is_extended_id)] += 1
                except (can.CanError, OSError, ValueError):
                    self.can_errors += 1


def load_protocols(argv) -> None:
    """
    Register the protocols named by ``--protocol module:Class`` (before the parameters).

    A protocol defined outside the package (a test's, a builder's) whose module is on the
    path; its name is then a value of ``can.protocol`` / ``legs.can.protocol``.
    """
    from rclpy.utilities import remove_ros_args
    from ..core.protocols import import_protocol
    parser = argparse.ArgumentParser(prog='sim_node')
    parser.add_argument('--protocol', action='append', default=[], metavar='MODULE:CLASS')
    for spec in parser.parse_args(remove_ros_args(['sim_node'] + list(argv))[1:]).protocol:
        import_protocol(spec)


def main(args=None) -> None:
    """Run sim_node until Ctrl-C."""
    # The CAN thread answers ~1000 frames/s: hand the GIL over sooner than the default 5 ms so
    # the loop thread wakes at its deadlines.
    sys.setswitchinterval(0.0005)
    # Its publishes hold the GIL; through Fast DDS's shared memory one could wait 0.33 s or
    # more for another process and freeze the simulation with it (docs/benchmarks.md).
    apply_udp_only()
    rclpy.init(args=args)
    node = None
    try:
        load_protocols(sys.argv[1:] if args is None else args)
        node = SimNode()
        node.start()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.stop()
            # The context may be gone (SIGTERM): write to stderr, not through rosout.
            print('[sim_node] stopped after %d ticks (%d late, %d resyncs), %d CAN frames, '
                  'real-time factor %.2f, %d lockstep timeouts'
                  % (node.ticks, node.late_ticks, node.resyncs, node.can_frames,
                     node.real_time_factor, node.lockstep_timeouts), file=sys.stderr)
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


if __name__ == '__main__':
    main()
