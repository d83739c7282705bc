"""
balance_node's sensor intake: imu and joint_states to the control loop, from a bare process.

The intake runs in a process of its own that does nothing else.

The intake is a node with subscriptions and nothing more (imu; joint_states_in only where the
tick reads it: wheel speeds from another driver, or undriven legs' hip angles): no publisher, no
service (not even the parameter, logger or type-description services), no rosout, no executor.
Its main thread blocks in an rcl wait set on the subscriptions (the GIL released), takes each
message the moment it arrives (the IMU's serialized: nodes/imu_cdr.py), reduces it to a small
sample (core/sensors.py) stamped with its monotonic receipt time, and sends it straight to the
control process over their own socket pair (nodes/control_link.py). A process of its own
because what stalls an rclpy process when other participants come and go (docs/benchmarks.md)
is the executor, service and publisher side of rclpy: balance_node's ROS side may stall, the
samples do not (and if the intake ever did, the samples would go stale and the loop fault,
never freeze). Its participant is UDP-only (nodes/dds.py): Fast DDS's shared-memory
transport made even this subscription-only participant's discovery wait 0.33 s for other
processes, and the samples with it. With ``realtime_priority`` set, the intake runs
SCHED_FIFO one below the loop.

balance_node starts it (``python -P -m wheelleg_balance.nodes.sensor_intake --fd N ...`` on
its own sys.path: processes.Child) with the topic names it has resolved, so its remappings
apply; a failed start is one line to balance_node, which ends with it. The intake ends when
the control process goes away (the link closes), when balance_node dies (the kernel sends it
SIGTERM: PR_SET_PDEATHSIG) and on SIGINT/SIGTERM/SIGHUP/SIGQUIT.
"""
import argparse
import contextlib
import ctypes
import math
import signal
import sys
import time
from typing import Optional

from .control_link import Link, READY
from .dds import apply_udp_only
from .imu_cdr import imu_sample_from_cdr
from ..core import realtime
from ..core.sensors import ImuSample, JointStateReader
from ..processes import run_child

#: Messages taken from one subscription per wake-up at most (its queue holds 5).
MAX_TAKES = 16
#: Longest wait [s] before the loop looks at its stop flag again.
WAIT_TIMEOUT = 0.1
_PR_SET_PDEATHSIG = 1   # linux/prctl.h


def imu_sample(msg, t: float, clock: float = math.nan) -> ImuSample:
    """
    Reduce a sensor_msgs/Imu to an ImuSample received at monotonic time ``t`` [s].

    clock: the node's clock (ROS time) at receipt [s], which the stamp is compared with.
    """
    o, w, a, stamp = msg.orientation, msg.angular_velocity, msg.linear_acceleration, \
        msg.header.stamp
    # sensor_msgs: orientation_covariance[0] == -1 means "no orientation estimate".
    return ImuSample(t, stamp.sec, stamp.nanosec, o.x, o.y, o.z, o.w,
                     msg.orientation_covariance[0] != -1.0, w.x, w.y, w.z, a.x, a.y, a.z,
                     clock)


def die_with_parent(signum: int = signal.SIGTERM) -> bool:
    """Ask Linux to send ``signum`` to this process when its parent dies; False elsewhere."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(_PR_SET_PDEATHSIG, int(signum), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


class SensorIntake:
    """
    The intake's node and loop (see the module docstring); ``run`` blocks until ``stop``.

    context: an initialized rclpy Context of this process; name, namespace: of balance_node
    (the intake's node is ``<name>_sensors``); imu_topic, joint_topic: resolved names
    (joint_topic None: the tick reads no joint_states_in, nothing subscribes it).
    """

    def __init__(self, context, link: Link, reader: JointStateReader, name: str,
                 namespace: str, imu_topic: str, joint_topic: Optional[str]):
        from rclpy.event_handler import SubscriptionEventCallbacks
        from rclpy.guard_condition import GuardCondition
        from rclpy.node import Node
        from rclpy.parameter import Parameter
        from rclpy.qos import qos_profile_sensor_data
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import Imu, JointState

        self.context = context
        self.link = link
        self.reader = reader
        self.node = Node(name + '_sensors', context=context, namespace=namespace,
                         use_global_arguments=False, enable_rosout=False,
                         start_parameter_services=False, parameter_overrides=[
                             Parameter('start_type_description_service', value=False)])
        no_events = SubscriptionEventCallbacks(use_default_callbacks=False)
        self._subs = [self.node.create_subscription(msg_type, topic, lambda _: None,
                                                    qos_profile_sensor_data,
                                                    event_callbacks=no_events)
                      for msg_type, topic in ((Imu, imu_topic), (JointState, joint_topic))
                      if topic is not None]
        self._imu_type = Imu
        self._deserialize = deserialize_message
        self._wake = GuardCondition(None, None, context=context)
        self._stopped = False
        self.taken = 0
        self.errors = 0
        self.realtime = ''   # the outcome of its real-time priority, if one was asked for

    def stop(self) -> None:
        """Make ``run`` return (any thread, a signal handler)."""
        self._stopped = True
        try:
            self._wake.trigger()
        except Exception:  # noqa: B902 -- the context may be gone already
            pass

    def run(self) -> None:
        """Wait for samples and forward them until stopped or the link closes."""
        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
        extra = ' (%s)' % self.realtime if self.realtime else ''
        self.link.send_object(READY, 'sensor intake %s%s' % (
            self.node.get_fully_qualified_name(), extra))
        context = self.context
        timeout_ns = int(WAIT_TIMEOUT * 1e9)
        handles = [sub.handle for sub in self._subs]
        imu, joints = handles[0], handles[1] if len(handles) > 1 else None
        wake = self._wake.handle
        # One wait set for the whole run, its entities held for as long (what rclpy's executor
        # builds anew at every wake-up was a sixth of the intake's time at 500 Hz).
        with contextlib.ExitStack() as held:
            for handle in handles + [wake, context.handle]:
                held.enter_context(handle)
            wait_set = _rclpy.WaitSet(len(handles), 1, 0, 0, 0, 0, context.handle)
            while not self._stopped and not self.link.closed:
                try:
                    wait_set.clear_entities()
                    for handle in handles:
                        wait_set.add_subscription(handle)
                    wait_set.add_guard_condition(wake)
                    wait_set.wait(timeout_ns)
                    if wait_set.is_ready('subscription', 0):
                        self._take_imu(imu)
                    if joints is not None and wait_set.is_ready('subscription', 1):
                        self._take_joints(joints, self._subs[1].msg_type)
                except Exception:  # noqa: B902 -- shutting down, or a bad message: go on
                    if self._stopped or not context.ok():
                        return
                    self.errors += 1

    def _take_imu(self, handle) -> None:
        # Serialized (nodes/imu_cdr.py): the tick needs 13 numbers of the message.
        for _ in range(MAX_TAKES):
            taken = handle.take_message(self._imu_type, True)
            if taken is None:
                return
            self.taken += 1
            t = time.monotonic()
            # The intake's node runs on ROS time without sim time: its clock is the system
            # clock, read here without building a Time.
            clock = time.time()
            sample = imu_sample_from_cdr(taken[0], t, clock)
            if sample is None:   # not plain CDR: rclpy's deserializer
                sample = imu_sample(self._deserialize(taken[0], self._imu_type), t, clock)
            self.link.send_imu(sample)

    def _take_joints(self, handle, msg_type) -> None:
        for _ in range(MAX_TAKES):
            taken = handle.take_message(msg_type, False)
            if taken is None:
                return
            self.taken += 1
            msg = taken[0]
            sample = self.reader.reduce(time.monotonic(), msg.name, msg.position, msg.velocity)
            if sample is not None:
                self.link.send_joints(sample)

    def destroy(self) -> None:
        """Destroy the node."""
        self.node.destroy_node()


def enclave_argument(argv) -> str:
    """Return the SROS2 enclave given as ``--enclave`` / ``-e`` among ROS arguments ('' none)."""
    in_ros = False
    for k, arg in enumerate(argv):
        if arg == '--ros-args':
            in_ros = True
        elif arg == '--':
            in_ros = False
        elif in_ros and arg in ('--enclave', '-e') and k + 1 < len(argv):
            return argv[k + 1]
    return ''


#: The intake's module (started by balance_node as processes.Child).
MODULE = 'wheelleg_balance.nodes.sensor_intake'


def arguments(fd: int, name: str, namespace: str, imu_topic: str, joint_topic: str,
              params: dict, enclave: str = ''):
    """
    Return the arguments of the intake process (``params``: flat configuration).

    enclave: balance_node's SROS2 enclave, for the intake's own participant ('' = none given).
    """
    import json
    return ['--fd', str(fd), '--name', name, '--namespace', namespace, '--imu', imu_topic,
            '--joint-states', joint_topic, '--params', json.dumps(params),
            '--enclave', enclave]


def main(argv=None) -> int:
    """Run the sensor intake of the balance_node that started this process."""
    import json
    import rclpy
    from rclpy.context import Context
    from rclpy.signals import SignalHandlerOptions
    # Here, not above: the control process and the watchdog import die_with_parent only.
    from ..core.sensing import joint_state_reader, joint_states_used
    from ..core.config import BalanceConfig
    from ..core.schema import from_flat

    parser = argparse.ArgumentParser(description='balance_node sensor intake (started by '
                                     'balance_node, not by hand)')
    parser.add_argument('--fd', type=int, required=True, help='inherited link socket')
    parser.add_argument('--name', required=True)
    parser.add_argument('--namespace', required=True)
    parser.add_argument('--imu', required=True)
    parser.add_argument('--joint-states', required=True)
    parser.add_argument('--params', required=True, help='the configuration as JSON')
    parser.add_argument('--enclave', default='', help="balance_node's SROS2 enclave")
    args = parser.parse_args(argv)
    die_with_parent()
    link = Link.from_fd(args.fd)
    cfg = from_flat(BalanceConfig, json.loads(args.params))
    # With realtime_priority, the intake is one below the loop: a sample starved by machine
    # load would fault the robot as surely as a stalled tick. Set before rclpy.init, so that
    # the DDS threads that receive the samples inherit it.
    priority = ''
    if cfg.loop.realtime_priority > 0:
        priority = realtime.set_fifo_priority(max(1, cfg.loop.realtime_priority - 1))[1]
    # Without shared memory its participant's DDS threads never wait for other processes
    # (nodes/dds.py): with it, the samples stopped for 0.25 s while participants came and went
    # (the soak benchmark, docs/benchmarks.md).
    apply_udp_only()
    context = Context()
    ros_args = ['--ros-args', '--enclave', args.enclave] if args.enclave else []
    rclpy.init(args=ros_args, context=context, signal_handler_options=SignalHandlerOptions.NO)
    intake = SensorIntake(context, link, joint_state_reader(cfg), args.name, args.namespace,
                          args.imu, args.joint_states if joint_states_used(cfg) else None)
    intake.realtime = priority

    def handler(signum, frame):
        intake.stop()
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT):
        signal.signal(signum, handler)
    try:
        intake.run()
    finally:
        intake.destroy()
        rclpy.try_shutdown(context=context)
        link.close()
    return 0


if __name__ == '__main__':
    sys.exit(run_child('the sensor intake', main))
