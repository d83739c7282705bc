"""
What the fit reads: a phase's recording as the MCAP recordings hold it (validation/recording.py).

A ``Record`` is one phase (``stand``, ``tail`` or ``balance``): per topic a ``Series`` of time
[s] and named columns, under the topics' names in a recording:

- ``imu`` (sensor_msgs/Imu): ``qx, qy, qz, qw`` (orientation), ``wx, wy, wz``
  (angular velocity [rad/s]) and ``ax, ay, az`` (specific force [m/s^2]) in the IMU frame;
- ``joint_states`` (balance_node's): ``<joint>.position``, ``.velocity``,
  ``.effort`` per joint name; the wheels forward positive relative to the leg, the hips in
  FiveBarLeg's convention, as balance_node publishes them;
- ``balance_node/state`` (std_msgs/Float64MultiArray): the columns of
  core/tick_io.py STATE_FIELDS, of which the fit uses ``tau_left``, ``tau_right`` (the wheel
  torques commanded, forward positive [N m]), ``l`` [m] and ``mode``.

``read_mcap`` reads such a file (the ``mcap`` and ``mcap-ros2-support`` packages, optional)
and ``write_mcap`` writes one (the ``identify --sim`` phases, so ``--recording`` refits them),
into one Record, every topic on the recording's log time (the state has no stamp; one clock
for all, so the fitted delay includes what the transport adds); ``excite.py`` builds the same
layout from the simulator in-process.
"""
from dataclasses import dataclass, field
from typing import Dict, Iterable, List, Optional

import numpy as np

from ..core.tick_io import STATE_FIELDS

#: The topics a phase's fit reads.
IMU, JOINTS, STATE = 'imu', 'joint_states', 'balance_node/state'
IMU_COLUMNS = ('qx', 'qy', 'qz', 'qw', 'wx', 'wy', 'wz', 'ax', 'ay', 'az')
#: The phases, in the order they are played and fitted.
PHASES = ('stand', 'tail', 'balance')


@dataclass
class Series:
    """Samples of one topic: time t [s] (increasing) and columns of the same length."""

    t: np.ndarray
    columns: Dict[str, np.ndarray]

    def __getitem__(self, name: str) -> np.ndarray:
        """Return the column ``name`` (KeyError names what there is)."""
        try:
            return self.columns[name]
        except KeyError:
            raise KeyError('no column %r (there are %s)' % (name, ', '.join(self.columns))) \
                from None

    def ordered(self) -> 'Series':
        """Return the samples by time, a repeated time once (as received, they may not be)."""
        k = np.argsort(self.t, kind='stable')
        keep = k[np.concatenate([[True], np.diff(self.t[k]) > 0])] if len(k) else k
        return Series(self.t[keep], {n: c[keep] for n, c in self.columns.items()})

    def at(self, t: np.ndarray, name: str) -> np.ndarray:
        """Return the column ``name`` linearly interpolated at times t [s]."""
        return np.interp(t, self.t, self[name])


@dataclass
class Record:
    """One phase's recording: {topic: Series} (see the module docstring)."""

    phase: str
    topics: Dict[str, Series] = field(default_factory=dict)

    def __getitem__(self, topic: str) -> Series:
        """Return the topic's Series (KeyError names the phase and the topic)."""
        try:
            return self.topics[topic]
        except KeyError:
            raise KeyError('the %s recording has no %r topic' % (self.phase, topic)) from None


class SeriesBuilder:
    """Rows appended one sample at a time, then ``series()`` (the in-process recorder)."""

    def __init__(self, names: Iterable[str]):
        self.names = list(names)
        self._t: List[float] = []
        self._rows: List[List[float]] = []

    def add(self, t: float, values: Iterable[float]) -> None:
        """Append one sample at time t [s], values in ``names`` order."""
        self._t.append(t)
        self._rows.append(list(values))

    def series(self) -> Series:
        """Return the samples as a Series."""
        data = np.array(self._rows, dtype=float).reshape(len(self._rows), len(self.names))
        return Series(np.array(self._t), {n: data[:, k] for k, n in enumerate(self.names)})


def joint_columns(names: Iterable[str]) -> List[str]:
    """Return the joint_states columns of joints ``names``: positions, velocities, efforts."""
    names = list(names)
    return ['%s.%s' % (n, q) for q in ('position', 'velocity', 'effort') for n in names]


def read_mcap(path, phase: str, start: float = -np.inf, end: float = np.inf,
              state_topic: str = '/balance_node/state') -> Record:
    """
    Read a phase's Record from an MCAP recording (validation/recording.py's layout).

    start, end: the part of the recording [s of log time since its first message] that is
    the phase. Raises MissingDependency without the mcap packages, KeyError for a missing
    topic.
    """
    from ..optional import require
    reader_mod = require('mcap.reader', 'reading MCAP recordings')
    decoder_mod = require('mcap_ros2.decoder', 'reading MCAP recordings')
    imu = SeriesBuilder(IMU_COLUMNS)
    state = SeriesBuilder(STATE_FIELDS)
    joints: Optional[SeriesBuilder] = None
    t0 = None
    with open(path, 'rb') as f:
        reader = reader_mod.make_reader(f, decoder_factories=[decoder_mod.DecoderFactory()])
        for _, channel, message, msg in reader.iter_decoded_messages(
                topics=['/imu', '/joint_states', state_topic]):
            t_log = 1e-9 * message.log_time
            t0 = t_log if t0 is None else t0
            if not start <= t_log - t0 <= end:
                continue
            if channel.topic == '/imu':
                o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
                imu.add(t_log, (o.x, o.y, o.z, o.w, w.x, w.y, w.z, a.x, a.y, a.z))
            elif channel.topic == '/joint_states':
                if joints is None:
                    joints = SeriesBuilder(joint_columns(msg.name))
                if len(msg.name) * 3 == len(joints.names):
                    joints.add(t_log, list(msg.position) + list(msg.velocity)
                               + list(msg.effort))
            elif len(msg.data) == len(STATE_FIELDS):
                state.add(t_log, msg.data)
            elif len(msg.data) == len(STATE_FIELDS) - 1:   # before ~/state's ``time``
                state.add(t_log, list(msg.data) + [t_log])
            elif len(msg.data) == len(STATE_FIELDS) - 2:   # before ~/state's ``excitation``
                state.add(t_log, list(msg.data) + [0.0, t_log])
    if joints is None:
        raise KeyError('%s has no joint_states' % path)
    return Record(phase, {IMU: imu.series(), JOINTS: joints.series(), STATE: state.series()})


def write_mcap(path, rec: Record, t0: float = 100.0) -> None:
    """
    Write a Record as balance_node's recording holds it (validation/recording.py's schemas).

    Each sample on the log time t0 + its time [s]; the imu and joint states stamped with it.
    Needs the ``mcap-ros2-support`` package and the ROS message packages (MissingDependency).
    """
    from ..optional import require
    writer_mod = require('mcap_ros2.writer', 'writing MCAP recordings')
    from sensor_msgs.msg import Imu, JointState
    from std_msgs.msg import Float64MultiArray
    from ..validation.recording import message_definition
    imu, js, st = rec[IMU], rec[JOINTS], rec[STATE]
    names = [c[:-len('.position')] for c in js.columns if c.endswith('.position')]
    with open(path, 'wb') as f:
        writer = writer_mod.Writer(f)
        schemas = {cls: writer.register_msgdef('%s/msg/%s' % (cls.__module__.split('.')[0],
                                                              cls.__name__),
                                               message_definition(cls))
                   for cls in (Imu, JointState, Float64MultiArray)}
        for k, t in enumerate(imu.t):
            ns = int(round((t0 + t) * 1e9))
            stamp = {'sec': ns // 1000000000, 'nanosec': ns % 1000000000}
            c = {n: float(imu[n][k]) for n in imu.columns}
            writer.write_message('/imu', schemas[Imu], {
                'header': {'stamp': stamp, 'frame_id': 'imu_link'},
                'orientation': {'x': c['qx'], 'y': c['qy'], 'z': c['qz'], 'w': c['qw']},
                'angular_velocity': {'x': c['wx'], 'y': c['wy'], 'z': c['wz']},
                'linear_acceleration': {'x': c['ax'], 'y': c['ay'], 'z': c['az']}},
                log_time=ns, publish_time=ns)
        for k, t in enumerate(js.t):
            ns = int(round((t0 + t) * 1e9))
            stamp = {'sec': ns // 1000000000, 'nanosec': ns % 1000000000}
            writer.write_message('/joint_states', schemas[JointState], {
                'header': {'stamp': stamp, 'frame_id': ''}, 'name': names,
                'position': [float(js[n + '.position'][k]) for n in names],
                'velocity': [float(js[n + '.velocity'][k]) for n in names],
                'effort': [float(js[n + '.effort'][k]) for n in names]},
                log_time=ns, publish_time=ns)
        for k, t in enumerate(st.t):
            ns = int(round((t0 + t) * 1e9))
            writer.write_message('/balance_node/state', schemas[Float64MultiArray], {
                'layout': {'dim': [], 'data_offset': 0},
                'data': [float(st[n][k]) for n in st.columns]}, log_time=ns, publish_time=ns)
        writer.finish()
