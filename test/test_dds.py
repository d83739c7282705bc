"""
nodes/dds.py: a UDP-only Fast DDS participant for each discovery range, and that it works.

The environment rules are pure; the ROS test starts a publisher process with them under this
run's LOCALHOST range and checks, from /proc, that its participant has no shared-memory thread
while a LOCALHOST subscriber here still gets its messages.
"""
import os
import subprocess
import sys
import textwrap
import time

import pytest
from std_msgs.msg import Int32

from wheelleg_balance.nodes.dds import profile_path, udp_only_env
from wheelleg_balance.validation import child_env


def test_localhost_gets_the_loopback_profile_and_the_system_default_range():
    changes = udp_only_env({'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'})
    assert changes['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'SYSTEM_DEFAULT'
    assert changes['FASTRTPS_DEFAULT_PROFILES_FILE'] == profile_path()
    assert profile_path().endswith('config/fastdds_no_shm.xml') and os.path.isfile(
        profile_path())
    # The deprecated switch means the same.
    assert udp_only_env({'ROS_LOCALHOST_ONLY': '1'})['ROS_LOCALHOST_ONLY'] == '0'


@pytest.mark.parametrize('scope', ['', 'SUBNET', 'SYSTEM_DEFAULT', 'subnet'])
def test_other_ranges_get_udp_as_the_only_builtin_transport(scope):
    assert udp_only_env({'ROS_AUTOMATIC_DISCOVERY_RANGE': scope}) == {
        'FASTDDS_BUILTIN_TRANSPORTS': 'UDPv4'}


@pytest.mark.parametrize('env', [
    {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'OFF'},
    {'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'},
    {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST', 'FASTRTPS_DEFAULT_PROFILES_FILE': '/my.xml'},
    {'FASTDDS_BUILTIN_TRANSPORTS': 'SHM'},
])
def test_the_users_own_choice_is_left_alone(env):
    assert udp_only_env(env) == {}


PUBLISHER = textwrap.dedent("""
    import os, sys, time
    from wheelleg_balance.nodes.dds import apply_udp_only
    if sys.argv[2] == 'udp':
        apply_udp_only()
    import rclpy
    from std_msgs.msg import Int32
    rclpy.init()
    node = rclpy.create_node('dds_probe_%d' % os.getpid())
    pub = node.create_publisher(Int32, sys.argv[1], 10)
    for k in range(400):
        if k == 100:
            threads = sorted(open('/proc/self/task/%s/comm' % t).read().strip()
                             for t in os.listdir('/proc/self/task'))
            print('threads', ' '.join(threads), flush=True)
        pub.publish(Int32(data=k))
        time.sleep(0.01)
""")


@pytest.mark.ros
@pytest.mark.parametrize('udp_only', [True, False])
def test_a_udp_only_publisher_reaches_a_localhost_subscriber(context, udp_only):
    import rclpy
    topic = 'dds_probe_%d_%d' % (os.getpid(), udp_only)
    node = rclpy.create_node('dds_probe_listener', context=context)
    got = []
    node.create_subscription(Int32, topic, lambda m: got.append(m.data), 10)
    env = child_env()
    assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'   # test/conftest.py
    proc = subprocess.Popen([sys.executable, '-c', PUBLISHER, topic,
                             'udp' if udp_only else 'default'], env=env,
                            stdout=subprocess.PIPE, text=True)
    from rclpy.executors import SingleThreadedExecutor
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        end = time.monotonic() + 20.0
        while len(got) < 20 and time.monotonic() < end and proc.poll() is None:
            executor.spin_once(timeout_sec=0.05)
        threads = proc.stdout.readline().split()
    finally:
        proc.kill()
        proc.wait()
        executor.shutdown()
        node.destroy_node()
    assert len(got) >= 20, got
    assert threads[0] == 'threads'
    # Fast DDS names its shared-memory threads dds.shm.<port> and dds.shm.wdog; the default
    # participant (the control case) has them.
    shm = [t for t in threads if t.startswith('dds.shm')]
    assert not shm if udp_only else shm, threads
