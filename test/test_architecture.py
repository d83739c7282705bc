"""
The package's shape: the math core stays free of ROS and the bus, the docs cite what exists.

- core/ (model, controllers, estimators, kinematics, codecs, the tick) imports neither rclpy,
  the ROS message packages, python-can nor the package's nodes or validation code, so it is
  tested and benchmarked alone and runs in a process without rclpy (the control loop's);
- the control process (nodes/control_process.py) imports no rclpy, directly or through the
  modules it imports: nothing of the ROS side shares its interpreter;
- no module or page cites a DESIGN.md (it is not part of the repository: docs/interface.md is).
"""
import ast
import pathlib
import subprocess
import sys

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
PACKAGE = REPO / 'wheelleg_balance'
#: Top-level modules the core may not import.
FORBIDDEN_IN_CORE = {'rclpy', 'can', 'sensor_msgs', 'geometry_msgs', 'nav_msgs', 'std_msgs',
                     'std_srvs', 'diagnostic_msgs', 'rcl_interfaces', 'builtin_interfaces',
                     'rosgraph_msgs', 'mujoco', 'matplotlib'}


def _imports(path: pathlib.Path):
    """Yield (absolute module name, line) of every import in ``path``."""
    package = '.'.join(path.relative_to(REPO).with_suffix('').parts[:-1])
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split('.')
                base = base[:len(base) - node.level + 1]
                module = '.'.join(base + ([node.module] if node.module else []))
            else:
                module = node.module
            yield module, node.lineno


@pytest.mark.parametrize('path', sorted((PACKAGE / 'core').rglob('*.py')),
                         ids=lambda p: str(p.relative_to(PACKAGE)))
def test_core_imports_neither_ros_nor_the_bus_nor_the_shell(path):
    for module, line in _imports(path):
        top = module.split('.')[0]
        assert top not in FORBIDDEN_IN_CORE, '%s:%d imports %s' % (path.name, line, module)
        if top == 'wheelleg_balance':
            assert module.startswith('wheelleg_balance.core'), \
                '%s:%d imports %s' % (path.name, line, module)


def test_the_control_process_runs_without_rclpy():
    code = ('import sys, wheelleg_balance.nodes.control_process; '
            'print(sorted(m for m in sys.modules if m.split(".")[0] in %r))'
            % sorted(FORBIDDEN_IN_CORE - {'can'}))
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         cwd=REPO, check=True, timeout=60).stdout.strip()
    assert out == '[]', 'the control process imports %s' % out


def test_nothing_cites_a_design_md_outside_the_repository():
    assert not (REPO / 'DESIGN.md').exists()
    offenders = []
    for path in list(PACKAGE.rglob('*.py')) + list((REPO / 'docs').glob('*.md')) + \
            [REPO / 'README.md']:
        if 'DESIGN.md' in path.read_text():
            offenders.append(str(path.relative_to(REPO)))
    assert not offenders, offenders
