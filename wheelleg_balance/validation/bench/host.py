"""The machine the benchmark's figures come from, and the environment of its child processes."""
import os
import platform
import random
from typing import Dict

from .. import child_env
from ...core.realtime import kernel_is_preempt_rt


def package_env() -> Dict[str, str]:
    """Environment for the child processes: this package importable, ROS isolated per run."""
    env = child_env()
    env['ROS_DOMAIN_ID'] = str(random.randint(1, 101))
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['PYTHONUNBUFFERED'] = '1'
    return env


def machine() -> Dict:
    """Describe the machine the figures are measured on."""
    return {'cpus': os.cpu_count(), 'cpus_allowed': len(os.sched_getaffinity(0)),
            'kernel': platform.release(), 'preempt_rt': kernel_is_preempt_rt(),
            'python': platform.python_version(), 'processor': platform.machine(),
            'load_average': [round(v, 2) for v in os.getloadavg()]}
