"""
Optional dependencies: what only the simulator and the validation tools import.

The robot runs balance_node and teleop_node with run-time keys only (package.xml exec_depend).
MuJoCo (sim_node, main_job, the fault suite's MuJoCo plant), matplotlib (the figures of
main_job and experiments) and mcap (main_job's MCAP recordings) are imported through this module
where they are needed, so a robot without them never imports them and a tool that needs one says
in one line what to install (docs/robot_setup.md, "Installing").
"""
import importlib
import importlib.util
from typing import Iterable, List

#: Module -> (rosdep key, how to install it on Ubuntu 24.04).
OPTIONAL = {
    'mujoco': ('python3-mujoco-pip', 'pip install mujoco in the Python that runs ROS (a venv '
               'with --system-site-packages; Ubuntu 24.04 refuses pip outside one), or '
               'WHEELLEG_BALANCE_SIM=1 PIP_BREAK_SYSTEM_PACKAGES=1 rosdep install ...'),
    'matplotlib': ('python3-matplotlib', 'sudo apt install python3-matplotlib'),
    # main_job's MCAP recordings (validation/recording.py); no rosdep key resolves to it.
    'mcap': ('none (PyPI mcap)', 'pip install mcap mcap-ros2-support in the Python that runs '
             'ROS (a venv with --system-site-packages on Ubuntu 24.04)'),
}


class MissingDependency(ImportError):
    """An optional dependency is not installed; the message says what needs it and the fix."""


def _message(module: str, needed_by: str) -> str:
    key, how = OPTIONAL.get(module.split('.')[0], (module, 'install the Python module %s'
                                                   % module))
    return '%s needs the Python module %r (rosdep key %s), which is not installed: %s' % (
        needed_by, module, key, how)


def require(module: str, needed_by: str):
    """Import and return module; raise MissingDependency saying who needs it and how to fix."""
    try:
        return importlib.import_module(module)
    except ImportError as e:
        if e.name is not None and e.name.split('.')[0] != module.split('.')[0]:
            raise  # the module is there but one of its own imports failed: show that
        raise MissingDependency(_message(module, needed_by), name=module) from e


def missing(modules: Iterable[str], needed_by: str) -> List[str]:
    """Return one message per module of modules that is not installed (nothing is imported)."""
    return [_message(m, needed_by) for m in modules if importlib.util.find_spec(m) is None]


def pyplot(needed_by: str = 'the figures'):
    """Return matplotlib.pyplot on the non-interactive Agg backend (else MissingDependency)."""
    matplotlib = require('matplotlib', needed_by)
    matplotlib.use('Agg')
    return importlib.import_module('matplotlib.pyplot')
