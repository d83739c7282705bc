"""
MCAP recordings (validation/recording.py) read back as Foxglove and PlotJuggler read them.

Messages published over DDS on localhost are recorded by McapRecording and decoded again with
mcap-ros2-support from the schemas embedded in the file alone (what the viewers do): every
field must come back as published, and ~/state's named channel must carry the labels as field
names with the values in order. The layouts of docs/layouts/ must name only channels and fields
that a main_job recording holds. Needs the PyPI packages mcap and mcap-ros2-support (skipped
without them: they are optional, validation/recording.py).
"""
import json
import pathlib
import threading
import time
import xml.etree.ElementTree as ET

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import Odometry
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import Imu
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from wheelleg_balance.core.balance_loop import STATE_FIELDS
from wheelleg_balance.validation import recording

REPO = pathlib.Path(__file__).resolve().parents[1]
LAYOUTS = REPO / 'docs' / 'layouts'


def test_definitions_are_complete_and_in_rosbag2s_form():
    text = recording.message_definition(Imu)
    head = text.split('=' * 80)[0]
    assert head.splitlines() == [
        'std_msgs/Header header', 'geometry_msgs/Quaternion orientation',
        'float64[9] orientation_covariance', 'geometry_msgs/Vector3 angular_velocity',
        'float64[9] angular_velocity_covariance', 'geometry_msgs/Vector3 linear_acceleration',
        'float64[9] linear_acceleration_covariance']
    for dep in ('std_msgs/msg/Header', 'builtin_interfaces/msg/Time',
                'geometry_msgs/msg/Quaternion', 'geometry_msgs/msg/Vector3'):
        assert ('%s\nMSG: %s\n' % ('=' * 80, dep)) in text
    assert text.count('MSG: ') == 4   # each nested type once
    assert recording.type_name(DiagnosticArray) == 'diagnostic_msgs/msg/DiagnosticArray'
    assert 'diagnostic_msgs/KeyValue[] values' in recording.message_definition(DiagnosticArray)
    assert recording.named_payload([1.0]) == b'\x00\x01\x00\x00' + b'\x00' * 6 + b'\xf0?'


@pytest.mark.ros
def test_a_recording_decodes_to_what_was_published(tmp_path, context):
    pytest.importorskip('mcap')
    reader_mod = pytest.importorskip('mcap.reader')
    decoder = pytest.importorskip('mcap_ros2.decoder')
    pub_node = rclpy.create_node('recording_pub', context=context)
    rec_node = rclpy.create_node('recording_rec', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(pub_node)
    executor.add_node(rec_node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    path = tmp_path / 'run.mcap'
    rec = recording.McapRecording(
        rec_node, str(path), [('imu', Imu), ('balance_node/state', Float64MultiArray),
                              ('/diagnostics', DiagnosticArray), ('odom', Odometry)],
        recording.NAMED)
    pubs = {'imu': pub_node.create_publisher(Imu, 'imu', 10),
            'state': pub_node.create_publisher(Float64MultiArray, 'balance_node/state', 10),
            'diag': pub_node.create_publisher(DiagnosticArray, '/diagnostics', 10),
            'odom': pub_node.create_publisher(Odometry, 'odom', 10)}
    end = time.monotonic() + 10.0
    while time.monotonic() < end and not all(p.get_subscription_count() for p in pubs.values()):
        time.sleep(0.05)
    n = 20
    for i in range(n):
        imu = Imu()
        imu.header.frame_id = 'imu_link'
        imu.header.stamp.sec = i
        imu.orientation.y = 0.1 * i
        imu.orientation.w = 1.0
        imu.linear_acceleration.z = 9.81
        pubs['imu'].publish(imu)
        state = Float64MultiArray(data=[float(i * 100 + k) for k in range(len(STATE_FIELDS))])
        state.layout.dim = [MultiArrayDimension(label=','.join(STATE_FIELDS),
                                                size=len(STATE_FIELDS),
                                                stride=len(STATE_FIELDS))]
        pubs['state'].publish(state)
        pubs['diag'].publish(DiagnosticArray(status=[DiagnosticStatus(
            level=DiagnosticStatus.WARN, name='balance_node: safety', message='m%d' % i,
            values=[KeyValue(key='mode', value='BALANCING'),
                    KeyValue(key='mode_index', value='%d' % (i % 3)),
                    KeyValue(key='period_p99_ms', value='2.0%d' % i)])]))
        odom = Odometry()
        odom.pose.pose.position.x = 0.5 * i
        odom.twist.covariance[35] = 0.01
        pubs['odom'].publish(odom)
        time.sleep(0.02)
    end = time.monotonic() + 5.0
    while time.monotonic() < end and min(rec.messages.values()) < n:
        time.sleep(0.05)
    rec.close()
    executor.shutdown()
    spinner.join(timeout=5.0)
    pub_node.destroy_node()
    rec_node.destroy_node()
    assert rec.messages == {'/imu': n, '/balance_node/state': n, '/diagnostics': n, '/odom': n,
                            '/balance_node/state_named': n, '/diagnostics_named': n}

    got = {}
    with open(path, 'rb') as f:
        reader = reader_mod.make_reader(f, decoder_factories=[decoder.DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == 6 * n
        schemas = {c.topic: summary.schemas[c.schema_id].name
                   for c in summary.channels.values()}
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            got.setdefault(channel.topic, []).append(decoded)
    assert schemas['/imu'] == 'sensor_msgs/msg/Imu'
    assert schemas['/balance_node/state_named'] == 'wheelleg_balance/msg/BalanceState'
    imu = got['/imu']
    assert [m.header.stamp.sec for m in imu] == list(range(n))
    assert imu[7].orientation.y == pytest.approx(0.7) and imu[7].header.frame_id == 'imu_link'
    assert list(imu[0].orientation_covariance) == [0.0] * 9
    assert [m.data for m in got['/balance_node/state']][3] == [
        300.0 + k for k in range(len(STATE_FIELDS))]
    named = got['/balance_node/state_named'][3]
    assert [getattr(named, f) for f in STATE_FIELDS] == [300.0 + k for k in
                                                         range(len(STATE_FIELDS))]
    diag = got['/diagnostics'][5].status[0]
    assert (diag.name, diag.message, diag.values[0].value) == (
        'balance_node: safety', 'm5', 'BALANCING')
    diag = got['/diagnostics_named'][5]
    assert (diag.mode_index, diag.period_p99_ms) == (2.0, 2.05)
    assert diag.overruns != diag.overruns   # NaN: not in these messages
    assert got['/odom'][4].pose.pose.position.x == 2.0
    assert got['/odom'][4].twist.covariance[35] == 0.01


def test_the_foxglove_layout_plots_state_odom_and_diagnostics():
    layout = json.loads((LAYOUTS / 'foxglove.json').read_text())
    paths = [p['value'] for cfg in layout['configById'].values() for p in cfg.get('paths', [])]
    labels = {p['value']: p.get('label') for cfg in layout['configById'].values()
              for p in cfg.get('paths', [])}
    state = [p for p in paths if p.startswith('/balance_node/state.data[')]
    assert state, paths
    for p in state:   # each ~/state index labelled with its field's name
        index = int(p.split('[')[1].rstrip(']'))
        assert labels[p] == STATE_FIELDS[index], p
    assert any(p.startswith('/odom.') for p in paths)
    topics = {cfg.get('topicToRender') for cfg in layout['configById'].values()}
    assert '/diagnostics' in topics
    # Every panel of the layout is placed in its tree.
    placed = json.dumps(layout['layout'])
    assert all(key in placed for key in layout['configById'])


def test_the_plotjuggler_layout_names_fields_of_the_recording():
    root = ET.parse(LAYOUTS / 'plotjuggler.xml').getroot()
    curves = [c.get('name') for c in root.iter('curve')]
    named = [c for c in curves if c.startswith('/balance_node/state_named/')]
    assert named and all(c.split('/')[-1] in STATE_FIELDS for c in named), curves
    assert any(c.startswith('/odom/') for c in curves)
    assert any(c.split('/')[-1] in recording.DIAGNOSTIC_FIELDS and
               c.startswith('/diagnostics_named/') for c in curves)
    assert any(c.startswith('/sim_node/ground_truth_named/') for c in curves)
