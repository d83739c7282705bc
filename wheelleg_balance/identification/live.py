"""
A phase played by the running balance_node and recorded: ``identify --phase`` on a robot.

``record_phase`` asks balance_node for the phase (its ``~/excite/<phase>`` service,
core/excitation.py) and records what the fit reads (records.py: ``imu``, ``joint_states``,
``<node>/state``) from the call until ~/state's ``excitation`` has gone back to 0 and
``TAIL`` s more (the wheels coasting), every message on the time it carries: ~/state on its
``time`` (the ROS time of its tick), joint_states and imu on their stamps (balance_node stamps
joint_states with its tick's ROS time; the IMU stamps its samples): one clock, which a lagging
simulator or a busy recorder does not stretch as it does receipt times (in lockstep 7.5 s of
receipt time for a 3.1 s phase). balance_node must publish ~/state (and with it
joint_states) at the control rate, ``state_publish_rate: 500``: the fit holds each commanded
torque until the next sample, and the programs change it every tick.
"""
import math
import time
from typing import List, Optional

from .records import IMU, IMU_COLUMNS, joint_columns, JOINTS, Record, SeriesBuilder, STATE
from ..core.excitation import PHASE_INDEX
from ..core.tick_io import STATE_FIELDS

#: Recorded after the phase ended [s].
TAIL = 0.3
#: The longest a phase may take from the call to its end [s] (balance: about 16 s).
PHASE_TIMEOUT = 60.0
#: Each subscription's queue [messages]: 4 s of the control rate.
QUEUE = 2000
#: How long the node's service may take to appear [s] (DDS discovery).
DISCOVERY_TIMEOUT = 20.0
_EXCITATION = STATE_FIELDS.index('excitation')
_TIME = STATE_FIELDS.index('time')


class PhaseError(RuntimeError):
    """The phase was refused, or it did not end in time (the message says which)."""


def record_phase(phase: str, node: str = '/balance_node', context=None) -> Record:
    """
    Play ``phase`` on the running balance_node ``node`` and return its Record.

    context: an initialized rclpy Context (None: one of its own, initialized and shut down
    here). Raises PhaseError with balance_node's reason when it refused the phase, or when
    the phase did not end within PHASE_TIMEOUT.
    """
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Imu, JointState
    from std_msgs.msg import Float64MultiArray
    from std_srvs.srv import Trigger
    own = context is None
    if own:
        from rclpy.context import Context
        context = Context()
        rclpy.init(context=context)
    imu, state = SeriesBuilder(IMU_COLUMNS), SeriesBuilder(STATE_FIELDS)
    joints: List[Optional[SeriesBuilder]] = [None]

    def on_imu(msg):
        o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
        imu.add(_seconds(msg.header.stamp), (o.x, o.y, o.z, o.w, w.x, w.y, w.z, a.x, a.y, a.z))

    def on_joints(msg):
        if joints[0] is None:
            joints[0] = SeriesBuilder(joint_columns(msg.name))
        if len(msg.name) * 3 == len(joints[0].names):
            joints[0].add(_seconds(msg.header.stamp), list(msg.position) + list(msg.velocity)
                          + list(msg.effort))

    index = PHASE_INDEX[phase]
    # The phase's index seen on ~/state; its end and the newest state [s, the ticks' times].
    marks = {'seen': False, 'ended': None, 'newest': -math.inf}

    def on_state(msg):
        if len(msg.data) == len(STATE_FIELDS):
            t = msg.data[_TIME]
            state.add(t, msg.data)
            marks['newest'] = max(marks['newest'], t)
            if msg.data[_EXCITATION] == index:
                marks['seen'] = True
            elif marks['seen'] and marks['ended'] is None:
                marks['ended'] = t

    ros = rclpy.create_node('identify_phase', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(ros)
    try:
        # Queues of QUEUE samples: DDS takes every message in at once and Python drains them
        # at its pace (at depth 5 and 100 a busy machine lost 1 in 10 of the phase's states).
        # balance_node's publishers are reliable, an IMU's may be best effort.
        best_effort = QoSProfile(depth=QUEUE, reliability=ReliabilityPolicy.BEST_EFFORT)
        reliable = QoSProfile(depth=QUEUE, reliability=ReliabilityPolicy.RELIABLE)
        ros.create_subscription(Imu, 'imu', on_imu, best_effort)
        ros.create_subscription(JointState, 'joint_states', on_joints, reliable)
        ros.create_subscription(Float64MultiArray, node.rstrip('/') + '/state', on_state,
                                reliable)
        client = ros.create_client(Trigger, '%s/excite/%s' % (node.rstrip('/'), phase))
        if not client.wait_for_service(timeout_sec=DISCOVERY_TIMEOUT):
            raise PhaseError('%s/excite/%s not found: is balance_node running?'
                             % (node, phase))
        future = client.call_async(Trigger.Request())
        executor.spin_until_future_complete(future, timeout_sec=5.0)
        answer = future.result()
        if answer is None or not answer.success:
            raise PhaseError('%s: %s' % (phase, answer.message if answer is not None else
                                         'balance_node did not answer'))
        deadline = time.monotonic() + PHASE_TIMEOUT
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.01)
            if marks['ended'] is not None and marks['newest'] > marks['ended'] + TAIL:
                break
        else:
            raise PhaseError('%s did not end within %.0f s' % (phase, PHASE_TIMEOUT))
    finally:
        executor.shutdown()
        ros.destroy_node()
        if own:
            rclpy.try_shutdown(context=context)
    if joints[0] is None:
        raise PhaseError('no joint_states from balance_node during %s' % phase)
    return Record(phase, {IMU: imu.series().ordered(), JOINTS: joints[0].series().ordered(),
                          STATE: state.series().ordered()})


def _seconds(stamp) -> float:
    """Return a builtin_interfaces/Time as seconds."""
    return stamp.sec + 1e-9 * stamp.nanosec
