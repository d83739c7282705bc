"""
balance_node as it runs on the robot, driven from outside over DDS and CAN: the fault rig.

``Rig``: the node (its control loop on a python-can ``virtual`` channel shared with
``FakeMotors``, in a thread of this process so the fakes can share the channel), its rclpy
executor, real DDS on localhost, and ``FakeRobot``, a ROS node publishing ``imu`` /
``joint_states`` / ``cmd_vel`` from a plant (validation/faults/plants.py) driven by the torques
the fake motors receive. Every fault is injected at the outside of the node (messages, CAN
frames, services, signals), and every reaction is read off the bus, decoded as the fake
motors' firmware decodes it: MIT, the default configuration's protocol (FakeMotors; the other
protocols' motor faults run at the tick level, test/test_protocols_on_the_tick.py).

Times are wall-clock seconds (``time.time``), the clock python-can stamps frames with.
"""
import os
import threading
import time
from typing import Callable, Dict, List, Optional, Tuple
import uuid

import can
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TwistStamped
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.qos import qos_profile_sensor_data
from rclpy.time import Time
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import SetBool

from .bench import IDX, make_joints, MODE
from .doubles import FakeMotors, FlakyBus
from .plants import StaticPlant
from ...core.config import BalanceConfig, DEFAULTS
from ...core.estimation import pitch_from_quaternion
from ...core.schema import from_flat
from ...core.sensing import wheel_motors
from ...nodes.balance_node import BalanceNode

#: Control period of balance_node [s].
PERIOD = DEFAULTS.loop.control_period
#: The robot's fall angle [rad].
FALL_ANGLE = DEFAULTS.safety.fall_angle


def isolate_ros() -> None:
    """
    Keep this process's ROS traffic to itself: a domain from the pid, localhost discovery.

    Must run before rclpy.init (setdefault: a domain chosen by the caller is kept). Domains
    200..231: the package's other tests use 10..99 and the main job 100..199 (under pytest,
    test/conftest.py has chosen the domain before this module is imported). Each rig also puts
    its nodes in a namespace of its own (``unique_namespace``).
    """
    os.environ.setdefault('ROS_DOMAIN_ID', str(200 + os.getpid() % 32))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'


# At import, so that importing this module before rclpy.init is enough.
isolate_ros()


def unique_namespace() -> str:
    """Return a ROS namespace no other rig uses ('/fault_<hex>')."""
    return '/fault_%s' % uuid.uuid4().hex[:10]


#: Timeouts of the rigs [s]: twice the robot's 50 ms, so a loaded 2-core machine does not trip
#: them by accident; the faults below last far longer.
RIG_PARAMS = {'imu_timeout': 0.1, 'joint_state_timeout': 0.1, 'motor_timeout': 0.1,
              'diagnostics_rate': 2.0, 'state_publish_rate': 250.0}
#: Slack for delivery and scheduling on top of a timeout [s] (DDS hop, executor, one tick).
SLACK = 0.06
#: Start of the name of the reaction-time check (zero torque within the bound): the one check
#: that depends on how fast the machine schedules the node, DDS and the rig.
REACTION_TIME_CHECK = 'zero torque on the bus within'
#: Name of the check that the sit-down began (~/state SITTING) within its bound.
SITTING_TIME_CHECK = 'SITTING within'


def wait_for(predicate: Callable[[], bool], timeout: float, step: float = 0.005) -> bool:
    """Poll ``predicate`` until it is true or ``timeout`` [s] passed; return its last value."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(step)
    return bool(predicate())

# ---------------------------------------------------------------------------- the ROS side


class FakeRobot(Node):
    """
    The test's ROS side of the robot: sensors out, the node's state and diagnostics in.

    It publishes the plant's IMU and joint states at 500 Hz and cmd_vel at 50 Hz while ``cmd``
    is set, listens to ~/state and /diagnostics and calls the node's services.

    Injection hooks: ``imu_on`` / ``joints_on`` (publish or not), ``imu_hook(msg)`` /
    ``joint_hook(msg)`` (edit each message before it goes out), ``freeze_imu`` (republish the
    last IMU message unchanged, stamp included), ``cmd_stamp_offset`` [s] (cmd_vel stamped
    that far from now).
    """

    def __init__(self, context, plant, motors: FakeMotors, namespace: str):
        super().__init__('fake_robot', namespace=namespace, context=context)
        node = '%s/balance_node' % namespace
        self.plant = plant
        self.motors = motors
        self.imu_pub = self.create_publisher(Imu, 'imu', qos_profile_sensor_data)
        # Another driver's joint states (wheel_state_source: joint_states) come in here.
        self.joint_pub = self.create_publisher(JointState, 'joint_states_in',
                                               qos_profile_sensor_data)
        self.cmd_pub = self.create_publisher(TwistStamped, 'cmd_vel', qos_profile_sensor_data)
        self.states: List[Tuple[float, List[float]]] = []
        self.diagnostics: List[Tuple[float, DiagnosticArray]] = []
        self.create_subscription(Float64MultiArray, node + '/state',
                                 lambda m: self.states.append((time.time(), list(m.data))), 10)
        self.create_subscription(DiagnosticArray, 'diagnostics',
                                 lambda m: self.diagnostics.append((time.time(), m)), 10)
        self.arm_client = self.create_client(SetBool, node + '/arm')
        self.set_client = self.create_client(SetParameters, node + '/set_parameters')
        self.get_client = self.create_client(GetParameters, node + '/get_parameters')
        self.imu_on = True
        self.joints_on = True
        self.freeze_imu = False
        self.imu_hook: Optional[Callable[[Imu], None]] = None
        self.joint_hook: Optional[Callable[[JointState], None]] = None
        self.cmd: Optional[Tuple[float, float]] = None
        self.cmd_hook: Optional[Callable[[TwistStamped], None]] = None
        self.cmd_stamp_offset = 0.0
        # Send times [s] of the newest IMU sample, of the newest with a new stamp, and of the
        # newest joint state that went out unedited.
        self.last_imu_time: Optional[float] = None
        self.last_new_imu_time: Optional[float] = None
        self.last_clean_joint_time: Optional[float] = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name='fake_robot', daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _loop(self) -> None:
        imu = Imu()
        cmd = TwistStamped()
        k = 0
        last = t_next = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            # Real elapsed time, capped so a stalled thread does not make one huge step.
            self.plant.advance(*self.motors.wheel_torques(), min(now - last, 0.01))
            last = now
            q, gyro, accel, wheels, legs = self.plant.sense()
            stamp = self.get_clock().now().to_msg()
            if self.imu_on:
                if not self.freeze_imu:
                    imu = Imu()
                    imu.header.stamp = stamp
                    imu.header.frame_id = 'imu_link'
                    o = imu.orientation
                    o.x, o.y, o.z, o.w = q
                    v = imu.angular_velocity
                    v.x, v.y, v.z = gyro
                    a = imu.linear_acceleration
                    a.x, a.y, a.z = accel
                    if self.imu_hook is not None:
                        self.imu_hook(imu)
                # Taken before the publish: the node may receive the sample before publish()
                # returns, and a timeout counts from its receipt.
                t_pub = time.time()
                self.imu_pub.publish(imu)
                self.last_imu_time = t_pub
                if not self.freeze_imu:
                    self.last_new_imu_time = self.last_imu_time
            if self.joints_on:
                js = make_joints(wheels[0], wheels[1], legs)
                js.header.stamp = stamp
                hook = self.joint_hook
                if hook is not None:
                    hook(js)
                t_pub = time.time()   # before the publish, as the imu's
                self.joint_pub.publish(js)
                if hook is None:
                    self.last_clean_joint_time = t_pub
            if self.cmd is not None and k % 10 == 0:
                now_ns = self.get_clock().now().nanoseconds
                cmd.header.stamp = Time(
                    nanoseconds=now_ns + int(self.cmd_stamp_offset * 1e9)).to_msg()
                cmd.twist.linear.x, cmd.twist.angular.z = self.cmd
                if self.cmd_hook is not None:
                    self.cmd_hook(cmd)
                self.cmd_pub.publish(cmd)
            k += 1
            t_next += PERIOD
            delay = t_next - time.monotonic()
            if delay > 0.0:
                time.sleep(delay)
            elif delay < -0.05:
                t_next = time.monotonic()   # fell far behind: do not burst to catch up

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(1.0)

    # ---- what the node says --------------------------------------------------------------

    def last_state(self) -> Optional[List[float]]:
        return self.states[-1][1] if self.states else None

    def mode(self) -> Optional[int]:
        s = self.last_state()
        return None if s is None else int(s[IDX['mode']])

    def wait_mode(self, mode: str, timeout: float = 2.0) -> Optional[float]:
        """Wait for ~/state to report ``mode``; return the receipt time [s] or None."""
        want = MODE[mode]
        n0 = len(self.states)

        def seen():
            return any(int(s[IDX['mode']]) == want for _, s in self.states[max(0, n0 - 1):])
        if not wait_for(seen, timeout):
            return None
        return next(t for t, s in self.states[max(0, n0 - 1):] if int(s[IDX['mode']]) == want)

    def modes_since(self, since: float) -> List[int]:
        return [int(s[IDX['mode']]) for t, s in list(self.states) if t >= since]

    def status_values(self, name: str) -> Dict[str, str]:
        """Key/values of the newest diagnostic status 'balance_node: <name>' ({} if none)."""
        for _, diagnostics in reversed(list(self.diagnostics)):
            for status in diagnostics.status:
                if status.name == 'balance_node: ' + name:
                    return {kv.key: kv.value for kv in status.values}
        return {}

    def safety(self) -> Dict[str, str]:
        return self.status_values('safety')

    def can_status(self) -> Dict[str, str]:
        return self.status_values('CAN')

    def loop_status(self) -> Dict[str, str]:
        return self.status_values('control loop')

    def wait_fault_code(self, code: str, timeout: float = 2.0) -> bool:
        return wait_for(lambda: code in self.safety().get('faults', '').split(','), timeout)

    # ---- services -------------------------------------------------------------------------

    def call(self, client, request, timeout: float = 5.0):
        if not client.wait_for_service(timeout_sec=timeout):
            raise TimeoutError('service %s not available' % client.srv_name)
        future = client.call_async(request)
        if not wait_for(future.done, timeout):
            raise TimeoutError('service %s did not answer' % client.srv_name)
        return future.result()

    def arm(self, on: bool = True):
        return self.call(self.arm_client, SetBool.Request(data=on))

    def set_params(self, **values):
        req = SetParameters.Request(parameters=[
            Parameter(name, value=value).to_parameter_msg() for name, value in values.items()])
        return self.call(self.set_client, req).results

    def get_param(self, name: str):
        (value,) = self.call(self.get_client, GetParameters.Request(names=[name])).values
        return parameter_value_to_python(value)


class Spinning:
    """Each node spun by an executor of its own on a daemon thread, until ``stop()``."""

    #: How long ``stop`` waits for a callback still running to end [s] (the 2 s join it had
    #: could return during a callback slowed by a loaded machine, the nodes then destroyed
    #: under it).
    STOP_TIMEOUT_S = 30.0

    def __init__(self, context, nodes):
        self._running = True
        self._executors = []
        self._threads = []
        for node in nodes:
            ex = SingleThreadedExecutor(context=context)
            ex.add_node(node)
            th = threading.Thread(target=self._spin, args=(ex,), daemon=True)
            self._executors.append(ex)
            self._threads.append(th)
            th.start()

    def _spin(self, executor) -> None:
        while self._running:
            executor.spin_once(timeout_sec=0.05)

    def stop(self, timeout: float = STOP_TIMEOUT_S) -> None:
        """
        Let the threads finish their last spin, then shut the executors down.

        Returns only when every thread has ended, so the nodes can be destroyed after it;
        raises RuntimeError if one is still in a callback after ``timeout`` [s].
        """
        self._running = False
        deadline = time.monotonic() + timeout
        for th in self._threads:
            th.join(max(0.0, deadline - time.monotonic()))
        alive = sum(th.is_alive() for th in self._threads)
        if alive:
            raise RuntimeError('%d spin thread(s) still in a callback after %.0f s: the '
                               'nodes must not be destroyed under them' % (alive, timeout))
        for ex in self._executors:
            ex.shutdown()


class Rig:
    """
    balance_node + FakeMotors on a virtual bus + FakeRobot over DDS (see the module docstring).

    ``params`` override the node's parameters (RIG_PARAMS first); the fake motors speak the
    wheels' protocol they configure (``can.protocol``, MIT by default) with their IDs and
    directions; ``motor_angles``: {motor ID: joint angle [rad]} the fake motors stand at from
    the first reply on. Use as a context manager.
    """

    def __init__(self, context, plant=None, motor_angles=None, **params):
        channel = 'wlb-faults-%s' % uuid.uuid4().hex
        self.channel = channel
        self.node_bus = FlakyBus(channel=channel)
        self.params = dict(RIG_PARAMS, **params)
        wheels = wheel_motors(from_flat(BalanceConfig, self.params))
        self.motors = FakeMotors(can.Bus(interface='virtual', channel=channel), wheels.ids,
                                 protocol=wheels.protocol,
                                 directions={m.motor_id: m.direction for m in wheels.motors})
        for motor_id, angle in (motor_angles or {}).items():
            self.motors.motors.joints[motor_id] = (float(angle), 0.0)
        self.plant = plant if plant is not None else StaticPlant()
        namespace = unique_namespace()
        overrides = [Parameter(k, value=v) for k, v in self.params.items()]
        # /diagnostics is absolute: remapped into the namespace, away from other rigs' nodes.
        self.node = BalanceNode(bus=self.node_bus, context=context, namespace=namespace,
                                parameter_overrides=overrides, cli_args=[
                                    '--ros-args', '-r', '/diagnostics:=diagnostics'])
        self.robot = FakeRobot(context, self.plant, self.motors, namespace)
        self._spinning = Spinning(context, (self.node, self.robot))
        self.robot.start()

    def __enter__(self) -> 'Rig':
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def arm(self, timeout: float = 10.0) -> bool:
        """Arm (retrying until the sensors reached the node); True once BALANCING."""
        robot = self.robot
        if not wait_for(lambda: robot.arm_client.service_is_ready()
                        and robot.last_state() is not None, timeout):
            return False
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if robot.arm().success:
                return robot.wait_mode('BALANCING', 2.0) is not None
            time.sleep(0.1)
        return False

    def close(self) -> None:
        self.robot.stop()
        self.node.shutdown()
        self._spinning.stop()
        self.node.destroy_node()
        self.robot.destroy_node()
        self.motors.close()


# ------------------------------------------------------------------------ against sim_node


class ImuWatch(Node):
    """
    Notes the first Imu whose |pitch| exceeds ``angle`` [rad]: receipt time and header stamp.

    first_time: its receipt time [s, time.time()]; first_stamp: its header stamp [s] (sim_node's
    simulated time in lockstep). ``ground_truth=True`` also records sim_node's ~/ground_truth
    (same namespace) as rows of (sim time [s], tau_left, tau_right [N m], the applied torques).
    """

    def __init__(self, context, namespace: str, angle: float = FALL_ANGLE,
                 ground_truth: bool = False):
        super().__init__('imu_watch', namespace=namespace, context=context)
        self.angle = angle
        self.first_time: Optional[float] = None
        self.first_stamp: Optional[float] = None
        self.truth: List[Tuple[float, float, float]] = []
        self.create_subscription(Imu, 'imu', self._on_imu, qos_profile_sensor_data)
        if ground_truth:
            self.create_subscription(Float64MultiArray, 'sim_node/ground_truth', self._on_truth,
                                     100)

    def _on_imu(self, msg: Imu) -> None:
        o = msg.orientation
        if self.first_time is None and abs(pitch_from_quaternion(o.x, o.y, o.z, o.w)) > \
                self.angle:
            self.first_time = time.time()
            self.first_stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec

    def _on_truth(self, msg: Float64MultiArray) -> None:
        labels = msg.layout.dim[0].label.split(',')
        row = dict(zip(labels, msg.data))
        self.truth.append((row['time'], row['tau_left'], row['tau_right']))
