"""
Who publishes balance_node's inputs: a second or unknown publisher is refused, with a reason.

A second IMU on ``imu`` (a forgotten bag replay, a ``ros2 topic pub`` from a laptop, a second
driver after a restart) mixes two attitudes in one stream; a second ``cmd_vel`` source makes
two operators steer at once. A message does not say which publisher sent it (rclpy's message
info has no publisher id), so balance_node looks at the ROS graph instead: twice a second it
asks for the publishers of each input (``Node.get_publishers_info_by_topic``) and judges them
here. The robot's own driver can be named by parameter (``imu_publisher``, ...); unnamed, any
single publisher is accepted. The verdict goes to the tick as ``TickInputs.conflicts``
(core/balance_loop.py): a sensor conflict refuses arming and faults a commanding robot, a
command conflict drops that command until the intruder is gone.
"""
from typing import Callable, Dict, Optional, Sequence, Tuple

from ..core.config import BalanceConfig
from ..core.schema import to_flat
from ..core.sensing import joint_states_used

#: How often balance_node looks at the publishers [s].
CHECK_PERIOD = 0.5

#: input (TickInputs.conflicts key) -> (topic name balance_node subscribes, its parameter).
INPUTS = {'imu': ('imu', 'imu_publisher'),
          'joint_states': ('joint_states_in', 'joint_state_publisher'),
          'cmd_vel': ('cmd_vel', 'cmd_vel_publisher'),
          'cmd_height': ('cmd_height', 'cmd_height_publisher')}


def full_name(namespace: str, name: str) -> str:
    """Return /namespace/name (a node's fully qualified name)."""
    return '/' + '/'.join(p for p in (namespace.strip('/'), name) if p)


def _matches(allowed: str, namespace: str, name: str) -> bool:
    # A bare name matches in any namespace; one with a slash must match the whole name.
    return full_name(namespace, name) == '/' + allowed.strip('/') if '/' in allowed \
        else name == allowed


def judge(topic: str, publishers: Sequence[Tuple[str, str]], allowed: str = '') -> Optional[str]:
    """
    Return why the publishers of ``topic`` are refused, or None when they are fine.

    publishers: (namespace, node name) per publisher (one node may publish twice);
    allowed: the one node allowed ('' = any single node).
    """
    nodes = sorted({full_name(ns, n) for ns, n in publishers})
    if allowed:
        strangers = sorted({full_name(ns, n) for ns, n in publishers
                            if not _matches(allowed, ns, n)})
        if strangers:
            return '%s has publishers other than %s: %s' % (topic, allowed, ', '.join(strangers))
        return None
    if len(nodes) > 1:
        return '%s has %d publishers (%s); one is allowed: name the driver in the parameter' % (
            topic, len(nodes), ', '.join(nodes))
    return None


def conflicts(publishers_of, topics: Dict[str, str], allowed: Dict[str, str]) -> Dict[str, str]:
    """
    Return {input: why} for every watched input whose publishers are refused.

    publishers_of(topic) -> [(namespace, node name)]; topics: {input: resolved topic};
    allowed: {input: allowed node ('' = any single one)}.
    """
    out = {}
    for key, topic in topics.items():
        why = judge(topic, publishers_of(topic), allowed.get(key, ''))
        if why is not None:
            out[key] = why
    return out


class InputGuard:
    """
    balance_node's check of its inputs' publishers; ``check`` runs on a timer.

    node: the rclpy node (its graph and topic names); on_change({input: why}): called when the
    verdict changes (the node sends it to the loop).
    """

    def __init__(self, node, cfg: BalanceConfig, on_change: Callable[[Dict[str, str]], None]):
        used = {'imu', 'cmd_vel', 'cmd_height'}
        if joint_states_used(cfg):
            used.add('joint_states')
        self.node = node
        self.topics = {key: node.resolve_topic_name(topic)
                       for key, (topic, _) in INPUTS.items() if key in used}
        flat = to_flat(cfg)   # the names are read-only parameters: fixed at start
        self.allowed = {key: flat[name] for key, (_, name) in INPUTS.items()}
        self.on_change = on_change
        self.found: Dict[str, str] = {}

    def _publishers(self, topic: str):
        return [(i.node_namespace, i.node_name)
                for i in self.node.get_publishers_info_by_topic(topic)]

    def check(self) -> None:
        """Judge the publishers of every watched input; report a changed verdict."""
        found = conflicts(self._publishers, self.topics, self.allowed)
        if found == self.found:
            return
        log = self.node.get_logger()
        for key in sorted(set(found) | set(self.found)):
            if key in found:
                log.error('refusing %s: %s' % (key, found[key]))
            else:
                log.info('%s: its publishers are accepted again' % key)
        self.found = found
        self.on_change(found)
