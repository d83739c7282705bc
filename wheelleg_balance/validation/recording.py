"""
Recordings as MCAP files of standard ROS 2 messages, for Foxglove and PlotJuggler.

``McapRecording`` subscribes to topics on a node with ``raw=True`` (the serialized CDR bytes,
as DDS delivered them: no decoding and re-encoding) and writes each message into an MCAP file
(profile ros2, message encoding cdr, schema encoding ros2msg) as rosbag2's MCAP storage does;
``ros2 bag info``, Foxglove and PlotJuggler open it. The schemas are the messages' complete
definitions (``message_definition``: the type's fields, then every nested type after a line of
80 '=' and ``MSG: pkg/msg/Type``, the concatenation of ros2/rosbag2
docs/message_definition_encoding.md), generated from the Python message classes, so no .msg
file needs to be installed.

Named fields: a Float64MultiArray whose ``layout.dim[0].label`` lists its fields comma-separated
(balance_node's ``~/state``, sim_node's ``~/ground_truth``) shows in a viewer as data[0] ..
data[16]. For such a topic the recording also writes ``<topic>_named``, one float64 field per
label (schema ``wheelleg_balance/msg/<Name>``, defined in the file itself: both viewers decode
it from the embedded schema, no package needed), so the viewers list theta, x_dot, d_hat ...;
the original topic stays as published. Diagnostics likewise: their values are strings, which
no plot takes, so for ``/diagnostics`` the recording also writes ``/diagnostics_named`` with
balance_node's numeric figures (DIAGNOSTIC_FIELDS, NaN where a message lacks one). The layouts in
docs/layouts/ use them.

The ``mcap`` package (PyPI ``mcap``; ``mcap-ros2-support`` reads the files back in the tests)
is optional: ``start`` returns None and says why when it is not installed.
"""
import re
import struct
import threading
import time
from typing import Dict, List, Optional, Sequence, Tuple

from ..optional import MissingDependency, require

#: ROS IDL primitive type names (a message class's _fields_and_field_types) -> .msg names.
_PRIMITIVES = {'boolean': 'bool', 'octet': 'byte', 'char': 'char', 'float': 'float32',
               'double': 'float64', 'int8': 'int8', 'uint8': 'uint8', 'int16': 'int16',
               'uint16': 'uint16', 'int32': 'int32', 'uint32': 'uint32', 'int64': 'int64',
               'uint64': 'uint64', 'string': 'string', 'wstring': 'wstring'}
_SEPARATOR = '=' * 80
#: The CDR encapsulation header of a little-endian plain CDR payload.
_CDR_LE = b'\x00\x01\x00\x00'


def type_name(msg_class) -> str:
    """Return 'sensor_msgs/msg/Imu' for a message class."""
    module = msg_class.__module__.split('.')
    return '%s/%s/%s' % (module[0], module[1], msg_class.__name__)


def _msg_type(idl: str) -> Tuple[str, Optional[str]]:
    """Return (.msg field type, nested 'pkg/msg/Type' or None) of an IDL field type."""
    m = re.fullmatch(r'sequence<(.+?)(?:, (\d+))?>', idl)
    if m:
        inner, nested = _msg_type(m.group(1))
        return inner + ('[<=%s]' % m.group(2) if m.group(2) else '[]'), nested
    m = re.fullmatch(r'(.+)\[(\d+)\]', idl)
    if m:
        inner, nested = _msg_type(m.group(1))
        return '%s[%s]' % (inner, m.group(2)), nested
    m = re.fullmatch(r'(w?string)<(\d+)>', idl)
    if m:
        return '%s<=%s' % (m.group(1), m.group(2)), None
    if idl in _PRIMITIVES:
        return _PRIMITIVES[idl], None
    pkg, name = idl.split('/')
    return '%s/%s' % (pkg, name), '%s/msg/%s' % (pkg, name)


def _fields(msg_class) -> Tuple[List[str], List[str]]:
    lines, nested = [], []
    for field, idl in msg_class.get_fields_and_field_types().items():
        t, dep = _msg_type(idl)
        lines.append('%s %s' % (t, field))
        if dep:
            nested.append(dep)
    return lines, nested


def _class(full: str):
    import importlib
    pkg, sub, name = full.split('/')
    return getattr(importlib.import_module('%s.%s' % (pkg, sub)), name)


def message_definition(msg_class) -> str:
    """Return the complete ros2msg definition of a message class (see the module docstring)."""
    lines, todo = _fields(msg_class)
    text = ['\n'.join(lines)]
    done = set()
    while todo:
        dep = todo.pop(0)
        if dep in done:
            continue
        done.add(dep)
        dep_lines, more = _fields(_class(dep))
        text.append('%s\nMSG: %s\n%s' % (_SEPARATOR, dep, '\n'.join(dep_lines)))
        todo += more
    return '\n'.join(text) + '\n'


def named_definition(labels: Sequence[str]) -> str:
    """Return the ros2msg definition of one float64 field per label."""
    return ''.join('float64 %s\n' % label for label in labels)


def named_payload(values: Sequence[float]) -> bytes:
    """Return the CDR bytes of a message of float64 fields (the encapsulation, then 8-byte LE)."""
    return _CDR_LE + struct.pack('<%dd' % len(values), *values)


#: balance_node's diagnostic values written as numbers to ``/diagnostics_named`` (the keys of
#: nodes/diagnostics.py; booleans as 0/1).
DIAGNOSTIC_FIELDS = ('mode_index', 'period_mean_ms', 'period_p99_ms', 'period_max_ms',
                     'compute_mean_ms', 'compute_p99_ms', 'compute_max_ms', 'overruns',
                     'caught_up', 'late_share', 'stalls', 'longest_stall_ms', 'tick_errors',
                     'tx_frames', 'tx_errors', 'rx_frames', 'rx_replies', 'rx_errors')
DIAGNOSTICS_SCHEMA = 'wheelleg_balance/msg/BalanceDiagnostics'


def diagnostic_values(msg, fields: Sequence[str] = DIAGNOSTIC_FIELDS) -> List[float]:
    """Return the fields' numbers from balance_node's statuses in a DiagnosticArray (NaN: none)."""
    found: Dict[str, float] = {}
    for status in msg.status:
        if not status.name.startswith('balance_node'):
            continue
        for kv in status.values:
            if kv.key in fields:
                v = {'True': '1', 'False': '0'}.get(kv.value, kv.value)
                try:
                    found[kv.key] = float(v)
                except ValueError:
                    pass
    return [found.get(f, float('nan')) for f in fields]


def _valid_labels(label: str) -> Optional[List[str]]:
    labels = [s.strip() for s in label.split(',')]
    ok = labels and all(re.fullmatch(r'[a-z][a-z0-9_]*', s) for s in labels) \
        and len(set(labels)) == len(labels)
    return labels if ok else None


class McapRecording:
    """
    Write topics of a node into an MCAP file as they arrive (see the module docstring).

    node: an rclpy node (its executor runs the callbacks); path: the file; topics: (name,
    message class) pairs; named: {topic name: schema name} of Float64MultiArray topics to write
    a ``<topic>_named`` channel for. ``messages`` counts what was written per topic.
    """

    def __init__(self, node, path, topics: Sequence[Tuple[str, type]],
                 named: Optional[Dict[str, str]] = None):
        # Optional and without a rosdep key: imported here, where it is needed (optional.py).
        mcap_writer = require('mcap.writer', 'the MCAP recordings')
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rclpy.serialization import deserialize_message
        from ..nodes import lean
        self._deserialize = deserialize_message
        self._file = open(path, 'wb')
        self._writer = mcap_writer.Writer(self._file)
        self._writer.start(profile='ros2', library='wheelleg_balance recording')
        self._lock = threading.Lock()
        self._closed = False
        self.path = path
        self.messages: Dict[str, int] = {}
        self._node = node
        self._subs = []
        self._named: Dict[str, Tuple[str, Optional[int], Optional[List[str]]]] = {}
        named = named or {}
        self._diag_topic: Optional[str] = None
        self._diag_channel: Optional[int] = None
        # Best effort matches reliable and best-effort publishers alike.
        qos = QoSProfile(depth=500, reliability=ReliabilityPolicy.BEST_EFFORT)
        for topic, cls in topics:
            resolved = node.resolve_topic_name(topic)
            schema = self._writer.register_schema(type_name(cls), 'ros2msg',
                                                  message_definition(cls).encode())
            channel = self._writer.register_channel(resolved, 'cdr', schema)
            self.messages[resolved] = 0
            if type_name(cls) == 'diagnostic_msgs/msg/DiagnosticArray':
                self._diag_topic = resolved
            if topic in named or resolved in named:
                self._named[resolved] = (named.get(topic, named.get(resolved)), None, None)
            self._subs.append(node.create_subscription(
                cls, topic, self._callback(resolved, channel, cls), qos, raw=True,
                event_callbacks=lean.subscription_events()))

    def _callback(self, topic: str, channel: int, cls):
        def write(data: bytes) -> None:
            now = time.time_ns()
            with self._lock:
                if self._closed:
                    return
                self._writer.add_message(channel, log_time=now, data=bytes(data),
                                         publish_time=now, sequence=self.messages[topic])
                self.messages[topic] += 1
                if topic in self._named:
                    self._write_named(topic, cls, data, now)
                if topic == self._diag_topic:
                    self._write_diagnostics(cls, data, now)
        return write

    def _write_diagnostics(self, cls, data: bytes, now: int) -> None:
        msg = self._deserialize(bytes(data), cls)
        if not any(st.name.startswith('balance_node') for st in msg.status):
            return
        topic = self._diag_topic + '_named'
        if self._diag_channel is None:
            schema = self._writer.register_schema(
                DIAGNOSTICS_SCHEMA, 'ros2msg', named_definition(DIAGNOSTIC_FIELDS).encode())
            self._diag_channel = self._writer.register_channel(topic, 'cdr', schema)
            self.messages[topic] = 0
        self._writer.add_message(self._diag_channel, log_time=now,
                                 data=named_payload(diagnostic_values(msg)), publish_time=now,
                                 sequence=self.messages[topic])
        self.messages[topic] += 1

    def _write_named(self, topic: str, cls, data: bytes, now: int) -> None:
        schema_name, channel, labels = self._named[topic]
        msg = self._deserialize(bytes(data), cls)
        if channel is None:
            labels = _valid_labels(msg.layout.dim[0].label) if msg.layout.dim else None
            if labels is None:
                self._named.pop(topic)   # no usable field names: the topic alone
                return
            schema = self._writer.register_schema(schema_name, 'ros2msg',
                                                  named_definition(labels).encode())
            channel = self._writer.register_channel(topic + '_named', 'cdr', schema)
            self._named[topic] = (schema_name, channel, labels)
            self.messages[topic + '_named'] = 0
        if len(msg.data) != len(labels):
            return
        self._writer.add_message(channel, log_time=now, data=named_payload(msg.data),
                                 publish_time=now, sequence=self.messages[topic + '_named'])
        self.messages[topic + '_named'] += 1

    def close(self) -> None:
        """Stop recording and finish the file (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._writer.finish()
            self._file.close()
        for sub in self._subs:
            self._node.destroy_subscription(sub)


def default_topics() -> List[Tuple[str, type]]:
    """Return what a main_job run records: the robot's topics, balance_node's, the truth."""
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import TwistStamped
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Imu, JointState
    from std_msgs.msg import Float64, Float64MultiArray
    topics = [('imu', Imu), ('joint_states', JointState), ('odom', Odometry),
              ('cmd_vel', TwistStamped), ('cmd_height', Float64),
              ('balance_node/state', Float64MultiArray), ('/diagnostics', DiagnosticArray),
              ('sim_node/ground_truth', Float64MultiArray)]
    try:
        from tf2_msgs.msg import TFMessage
        topics += [('/tf', TFMessage), ('/tf_static', TFMessage)]
    except ImportError:
        pass   # not installed (the PyPI ROS wheels): no TF in the recording
    return topics


#: The named channels of a main_job recording.
NAMED = {'balance_node/state': 'wheelleg_balance/msg/BalanceState',
         'sim_node/ground_truth': 'wheelleg_balance/msg/GroundTruth'}


def start(node, path, log=print) -> Optional[McapRecording]:
    """Start recording default_topics() into path; None (said through log) without mcap."""
    try:
        return McapRecording(node, path, default_topics(), NAMED)
    except MissingDependency as exc:
        log('no MCAP recording: %s' % exc)
        return None
