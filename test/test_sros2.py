"""
config/sros2/policy.xml: SROS2's documented schema, and the robot's real endpoints.

The policy (docs/robot_setup.md, "SROS2") is read with xml.etree as sros2's tools read it:
its shape is that of sros2's policy.xsd (version 0.2.0), and its names are resolved and mapped
to DDS topics as sros2's permissions.xsl does (rt<topic>, rq<service>Request,
rr<service>Reply; ``~`` under ns/node, a relative name under ns). The checks:

- only the operator's enclave may call balance_node's ``~/arm``, ``~/stop`` and parameter
  services (the pad's ``~/arm`` from teleop_node on the robot being the one exception), and
  only balance_node may answer them;
- the robot's profiles of balance_node, its sensor intake (a process and node of its own) and
  teleop_node allow exactly what those nodes publish, subscribe, serve and call: read from the
  running nodes' graph (so a topic the node gains and the policy lacks fails here) and from
  docs/interface.md (so a documented one does too, e.g. /tf where tf2_msgs is not installed);
- every service in the policy exists: served by our nodes, or a standard service of the node
  whose profile names it.
"""
import fnmatch
import pathlib
import re
import uuid
import xml.etree.ElementTree as ET

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
POLICY = REPO / 'config' / 'sros2' / 'policy.xml'
INTERFACE = REPO / 'docs' / 'interface.md'
ROBOT, OPERATOR = '/wheelleg/robot', '/wheelleg/operator'
#: Services every rclpy / rclcpp node of Jazzy serves by default under its own name (checked
#: against the running nodes below).
PARAMETER_SERVICES = ('describe_parameters', 'get_parameter_types', 'get_parameters',
                      'list_parameters', 'set_parameters', 'set_parameters_atomically')
NODE_SERVICES = PARAMETER_SERVICES + ('get_type_description',)
#: What only the operator's station may call.
PROTECTED = {'/balance_node/arm', '/balance_node/stop'} | {
    '/balance_node/' + s for s in PARAMETER_SERVICES}
#: The pad's arm and disarm (teleop_node's arm_buttons, disarm_buttons): the one request the
#: robot's own enclave makes.
PAD_REQUEST = (ROBOT, 'teleop_node', '/balance_node/arm')
#: The ros2 command line's hidden nodes on the operator's station (ros2cli NODE_NAME_PREFIX).
ROS2CLI = '/_ros2cli_*'
#: DDS topics of a policy rule, as sros2's permissions.xsl writes them: (publish, subscribe).
DDS = {
    'publish': lambda n: ({'rt' + n}, set()),
    'subscribe': lambda n: (set(), {'rt' + n}),
    'request': lambda n: ({'rq%sRequest' % n}, {'rr%sReply' % n}),
    'reply': lambda n: ({'rr%sReply' % n}, {'rq%sRequest' % n}),
}
NAME = re.compile(r'^(/[A-Za-z_][A-Za-z0-9_]*)+$')
VERBS = {'topics': ('topic', {'publish', 'subscribe'}),
         'services': ('service', {'reply', 'request'})}


def load_policy():
    """Return the policy's root element, comments kept (sros2 reads them with lxml)."""
    parser = ET.XMLParser(target=ET.TreeBuilder(insert_comments=True))
    return ET.parse(POLICY, parser).getroot()


def elements(parent):
    """Return the child elements of ``parent``, without comments."""
    return [child for child in parent if isinstance(child.tag, str)]


def resolve(name: str, ns: str, node: str) -> str:
    """Return the fully qualified name, as sros2's permissions.xsl resolves it."""
    if name.startswith('/'):
        return name
    prefix = ns if ns.endswith('/') else ns + '/'
    if name.startswith('~'):
        return prefix + node + name[1:]
    return prefix + name


def rules(root=None):
    """Return {(enclave, node, verb, qualifier, name)}: every rule, names resolved."""
    out = set()
    for enclave in (root if root is not None else load_policy()).iter('enclave'):
        for profile in enclave.iter('profile'):
            ns, node = profile.get('ns'), profile.get('node')
            for group in elements(profile):
                item = VERBS[group.tag][0]
                for verb, qualifier in group.attrib.items():
                    for e in group.findall(item):
                        out.add((enclave.get('path'), node, verb, qualifier,
                                 resolve(e.text.strip(), ns, node)))
    return out


def allowed(verb: str, enclave: str = None, node: str = None) -> set:
    """Return the names the policy ALLOWs for ``verb`` (to one enclave, one node's profile)."""
    return {n for e, p, v, q, n in rules() if v == verb and q == 'ALLOW'
            and enclave in (None, e) and node in (None, p)}


def dds_matches(pattern: str, topic: str) -> bool:
    """Fast DDS matches a permission and a topic with fnmatch both ways (* spans '/')."""
    return fnmatch.fnmatchcase(topic, pattern) or fnmatch.fnmatchcase(pattern, topic)


def may_write(enclave: str, dds_topic: str) -> bool:
    """Return whether the enclave's grant lets it write ``dds_topic``."""
    return any(dds_matches(pattern, dds_topic) for e, _, v, q, n in rules()
               if e == enclave and q == 'ALLOW' for pattern in DDS[v](n)[0])


def interface_table(node: str) -> dict:
    """Return {'pub'|'sub'|'srv': {resolved names}} from docs/interface.md's table of node."""
    section = INTERFACE.read_text().split('\n## %s\n' % node, 1)[1].split('\n## ', 1)[0]
    out = {'pub': set(), 'sub': set(), 'srv': set()}
    for direction, name in re.findall(r'^\| (sub|pub|srv) \| `([^`]+)` \|', section, re.M):
        out[direction].add(resolve(name, '/', node))
    return out


# ---- the documented schema ----------------------------------------------------------------

def test_the_policy_has_the_shape_of_sros2s_schema():
    root = load_policy()
    # policy.xsd: <policy version="0.2.0"> holding one <enclaves>.
    assert root.tag == 'policy' and root.get('version') == '0.2.0'
    assert [e.tag for e in elements(root)] == ['enclaves']
    enclaves = root.find('enclaves')
    # sros2's generate_artifacts takes every child of <enclaves> for an enclave, comments too
    # (lxml keeps them): one there would be an enclave without a path.
    assert all(child.tag == 'enclave' for child in enclaves), 'only <enclave> in <enclaves>'
    assert [e.get('path') for e in enclaves] == [ROBOT, OPERATOR]
    profiles = set()
    for enclave in enclaves:
        assert NAME.match(enclave.get('path'))
        assert [e.tag for e in elements(enclave)] == ['profiles']
        for profile in elements(enclave.find('profiles')):
            assert profile.tag == 'profile'
            assert set(profile.attrib) == {'ns', 'node'}, profile.attrib
            assert profile.get('ns') == '/' and NAME.match('/' + profile.get('node'))
            key = (enclave.get('path'), profile.get('node'))
            assert key not in profiles, 'two profiles of %s in %s' % key[::-1]
            profiles.add(key)
            for group in elements(profile):
                assert group.tag in VERBS, group.tag
                item, verbs = VERBS[group.tag]
                assert group.attrib and set(group.attrib) <= verbs, group.attrib
                # Only ALLOW here: the generated grant's default is DENY.
                assert set(group.attrib.values()) == {'ALLOW'}, group.attrib
                names = elements(group)
                assert names and all(e.tag == item and e.text.strip() for e in names)
    assert {(ROBOT, n) for n in ('balance_node', 'balance_node_sensors', 'teleop_node',
                                 'game_controller_node', 'robot_state_publisher')} <= profiles
    for _, node, verb, _, name in rules(root):
        # Plain ROS names; the one pattern is the operator's for the command line's own nodes.
        assert NAME.match(name) or (node == 'operator' and name == ROS2CLI), name


# ---- who may call what --------------------------------------------------------------------

def test_only_the_operator_may_call_arm_stop_and_the_parameter_services():
    requests = {(e, p, n) for e, p, v, q, n in rules() if v == 'request'}
    assert {(OPERATOR, 'operator', s) for s in PROTECTED} <= requests
    # On the robot, only the pad's arming.
    assert {r for r in requests if r[0] != OPERATOR} == {PAD_REQUEST}
    for service in PROTECTED:
        # At the DDS level, wildcards included: who may write the request topic.
        writers = {e for e in (ROBOT, OPERATOR) if may_write(e, 'rq%sRequest' % service)}
        expected = {OPERATOR, ROBOT} if service == PAD_REQUEST[2] else {OPERATOR}
        assert writers == expected, (service, writers)
        # Only balance_node answers them (no impostor server in the robot's enclave).
        assert {(e, p) for e, p, v, _, n in rules() if v == 'reply' and n == service} == \
            {(ROBOT, 'balance_node')}, service


def test_the_operator_reads_state_and_diagnostics_and_commands_nothing():
    assert {'/balance_node/state', '/diagnostics'} <= allowed('subscribe', OPERATOR)
    # It publishes only its own nodes' log and parameter events: no cmd_vel, no imu.
    assert allowed('publish', OPERATOR) == {'/rosout', '/parameter_events'}
    # It answers only the services of the command line's hidden nodes, not the robot's.
    assert allowed('reply', OPERATOR) == {ROS2CLI}
    assert fnmatch.fnmatchcase('/_ros2cli_requester_std_srvs_SetBool/get_parameters', ROS2CLI)
    assert not any(fnmatch.fnmatchcase(n, ROS2CLI) for n in allowed('reply', ROBOT))


# ---- the running nodes --------------------------------------------------------------------

@pytest.fixture(scope='module')
def graph(context):
    """Return {node: {'pub'|'sub'|'srv'|'cli': {names}}} of the running robot's own nodes."""
    from can.interfaces.virtual import VirtualBus
    from rclpy.node import Node

    from wheelleg_balance.core.balance_loop import joint_states_used
    from wheelleg_balance.nodes.balance_node import BalanceNode
    from wheelleg_balance.nodes.teleop_node import TeleopNode
    from wheelleg_balance.validation.faults.rig import wait_for

    # The control loop in a thread on a virtual bus; the sensor intake in its own process.
    node = BalanceNode(bus=VirtualBus(channel='wlb-%s' % uuid.uuid4().hex), context=context)
    teleop = TeleopNode(context=context)
    probe = Node('sros2_probe', context=context)
    queries = {'pub': probe.get_publisher_names_and_types_by_node,
               'sub': probe.get_subscriber_names_and_types_by_node,
               'srv': probe.get_service_names_and_types_by_node,
               'cli': probe.get_client_names_and_types_by_node}

    def endpoints(name):
        try:
            return {k: {n for n, _ in q(name, '/')} for k, q in queries.items()}
        except Exception:  # noqa: B902 -- not discovered yet (NodeNameNonExistentError)
            return None
    names = ('balance_node', 'balance_node_sensors', 'teleop_node')
    # imu, and joint_states_in only where the tick reads it (not with the defaults' motors).
    intake_subs = 1 + joint_states_used(node.config)
    try:
        # The intake is another participant: wait until discovery shows its subscriptions.
        assert wait_for(lambda: all(endpoints(n) for n in names) and len(
            endpoints('balance_node_sensors')['sub']) == intake_subs, 20.0, step=0.1)
        yield {n: endpoints(n) for n in names}
    finally:
        node.shutdown()
        node.destroy_node()
        teleop.destroy_node()
        probe.destroy_node()


@pytest.mark.ros
def test_balance_node_and_its_intake_get_exactly_what_they_use(graph):
    doc = interface_table('balance_node')
    nodes = ('balance_node', 'balance_node_sensors')
    verbs = (('pub', 'publish'), ('sub', 'subscribe'), ('srv', 'reply'), ('cli', 'request'))
    for node in nodes:
        for direction, verb in verbs:
            missing = graph[node][direction] - allowed(verb, ROBOT, node)
            assert not missing, '%s %s %s, the policy does not allow it' % (
                node, verb, sorted(missing))
    # Together (the intake takes balance_node's documented imu and joint_states_in): exactly
    # the running nodes' endpoints plus the documented ones, nothing more.
    for direction, verb in verbs:
        used = set().union(*(graph[n][direction] for n in nodes))
        documented = doc.get(direction, set())
        granted = set().union(*(allowed(verb, ROBOT, n) for n in nodes))
        assert granted == used | documented, (verb, granted ^ (used | documented))
    assert doc['srv'] <= allowed('reply', ROBOT, 'balance_node')
    assert not allowed('reply', ROBOT, 'balance_node_sensors')


@pytest.mark.ros
def test_teleop_node_gets_exactly_what_it_uses(graph):
    used = graph['teleop_node']
    for direction, verb in (('pub', 'publish'), ('sub', 'subscribe'), ('srv', 'reply'),
                            ('cli', 'request')):
        assert allowed(verb, ROBOT, 'teleop_node') == used[direction], verb
    # Its one client is the pad's arming, the exception above.
    assert used['cli'] == {PAD_REQUEST[2]}


@pytest.mark.ros
def test_every_service_in_the_policy_exists(graph):
    # The standard services of a node are what ours serve besides their own.
    own = graph['teleop_node']['srv']
    assert own == {'/teleop_node/' + s for s in NODE_SERVICES}
    served = graph['balance_node']['srv'] | own | interface_table('balance_node')['srv']
    services = {(p, v, n) for _, p, v, _, n in rules() if v in ('reply', 'request')}
    assert len(services) > len(PROTECTED)
    for node, verb, name in services:
        if name == ROS2CLI:
            continue   # checked above: the command line's nodes, none of the robot's
        standard = {'/%s/%s' % (node, s) for s in NODE_SERVICES}
        if verb == 'request':
            assert name in served, '%s calls %s, which nobody serves' % (node, name)
        else:
            assert name in served | standard, '%s serves %s?' % (node, name)


def test_balance_node_hands_its_enclave_to_its_sensor_intake():
    """The intake is a participant of its own: it must join balance_node's enclave."""
    from wheelleg_balance.nodes.sensor_intake import arguments, enclave_argument
    assert enclave_argument(['balance_node', '--ros-args', '-r', '__ns:=/r', '--enclave',
                             '/wheelleg/robot']) == '/wheelleg/robot'
    assert enclave_argument(['balance_node', '--ros-args', '-e', '/wheelleg/robot']) == \
        '/wheelleg/robot'
    assert enclave_argument(['balance_node', '--enclave', '/x']) == ''   # not a ROS argument
    assert enclave_argument(['balance_node', '--ros-args', '--', '--enclave', '/x']) == ''
    assert enclave_argument(['balance_node']) == ''
    cmd = arguments(3, 'balance_node', '/', '/imu', '/joint_states_in', {}, '/wheelleg/robot')
    assert cmd[cmd.index('--enclave') + 1] == '/wheelleg/robot'
