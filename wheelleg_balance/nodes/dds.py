"""
Fast DDS without its shared-memory transport, for the processes whose writes must not block.

A publish (or a service reply) that goes through Fast DDS's shared-memory transport can block
the writing thread for 333 ms, 1 s or 2 s when other processes come and go, and rclpy holds
the GIL through it, so every Python thread of the process stops (docs/benchmarks.md, "The
0.33 s stall"). Over UDP a write never waits for another process. ``udp_only_env`` returns
the environment changes that make a process's participant UDP-only, for the discovery range
the environment asks for:

- ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` (or ``ROS_LOCALHOST_ONLY=1``): rmw_fastrtps 8.4
  adds shared memory to whatever is configured there (``FASTDDS_BUILTIN_TRANSPORTS`` is
  ignored, measured), so the range becomes SYSTEM_DEFAULT and the installed profile
  ``config/fastdds_no_shm.xml`` keeps the participant on 127.0.0.1, as LOCALHOST did;
- SUBNET, SYSTEM_DEFAULT or unset: ``FASTDDS_BUILTIN_TRANSPORTS=UDPv4`` (honoured there);
- OFF, another RMW than Fast DDS, or a Fast DDS profile or transport the user set: nothing
  changes.

Set before rclpy is initialized (rmw reads the environment when the participant is created):
for a child process in its environment, for this process with ``apply_udp_only`` first thing
in ``main``. Participants configured this way talk to shared-memory ones over UDP.
"""
import os
import pathlib
from typing import Dict, Mapping, MutableMapping, Optional

PROFILE_NAME = 'fastdds_no_shm.xml'
_FAST_DDS = ('', 'rmw_fastrtps_cpp', 'rmw_fastrtps_dynamic_cpp')
#: Set by the user: their Fast DDS configuration wins.
_USER_VARIABLES = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE',
                   'FASTDDS_BUILTIN_TRANSPORTS')


def profile_path() -> Optional[str]:
    """Return the no-shared-memory profile: next to the sources, else the installed share/."""
    # This file is <repo>/wheelleg_balance/nodes/dds.py.
    here = pathlib.Path(__file__).resolve().parents[2] / 'config' / PROFILE_NAME
    if here.is_file():
        return str(here)
    try:
        from ament_index_python.packages import get_package_share_directory
        path = pathlib.Path(get_package_share_directory('wheelleg_balance')) / 'config' / \
            PROFILE_NAME
    except (ImportError, LookupError, ValueError):
        return None
    return str(path) if path.is_file() else None


def udp_only_env(env: Mapping[str, str], profile: Optional[str] = None) -> Dict[str, str]:
    """Return the variables to set in ``env`` for a UDP-only participant ({} if none)."""
    if env.get('RMW_IMPLEMENTATION', '') not in _FAST_DDS or \
            any(env.get(k) for k in _USER_VARIABLES):
        return {}
    scope = env.get('ROS_AUTOMATIC_DISCOVERY_RANGE', '').strip().upper()
    if scope == 'OFF':
        return {}
    if scope == 'LOCALHOST' or (not scope and env.get('ROS_LOCALHOST_ONLY', '') == '1'):
        profile = profile or profile_path()
        if profile is None:
            return {}
        return {'FASTRTPS_DEFAULT_PROFILES_FILE': profile,
                'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SYSTEM_DEFAULT', 'ROS_LOCALHOST_ONLY': '0'}
    return {'FASTDDS_BUILTIN_TRANSPORTS': 'UDPv4'}


def apply_udp_only(env: Optional[MutableMapping[str, str]] = None) -> Dict[str, str]:
    """Make ``env`` (default: this process's, before rclpy.init) UDP-only; return the changes."""
    env = os.environ if env is None else env
    changes = udp_only_env(env)
    env.update(changes)
    return changes
