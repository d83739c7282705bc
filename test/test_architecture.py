"""
The package's shape: the math core stays free of ROS and the bus, the docs cite what exists.

- core/ (model, controllers, estimators, kinematics, codecs, the tick) imports neither rclpy,
  the ROS message packages, python-can nor the package's nodes or validation code, so it is
  tested and benchmarked alone and runs in a process without rclpy (the control loop's);
- the control process (nodes/control_process.py) imports no rclpy, directly or through the
  modules it imports: nothing of the ROS side shares its interpreter;
- no module or page cites a DESIGN.md (it is not part of the repository: docs/interface.md is);
- the tick stays a short sequence over parts (issue "The tick in parts"): in core/ and nodes/
  no file over MAX_FILE_LINES, no class over MAX_CLASS_LINES, ``BalanceLoop.tick`` at most
  MAX_TICK_LINES, nodes/balance_node.py at most MAX_NODE_LINES.
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


#: The size limits of core/ and nodes/ [lines] (validation/ and sim/ are not held to them).
MAX_FILE_LINES = 600
MAX_CLASS_LINES = 300
MAX_TICK_LINES = 40
MAX_NODE_LINES = 400


def _sizes(path: pathlib.Path):
    """Return (lines of the file, {class name: lines}, {qualified function: lines})."""
    text = path.read_text()
    tree = ast.parse(text, str(path))
    classes, functions = {}, {}
    for node in tree.body:
        if isinstance(node, ast.ClassDef):
            classes[node.name] = node.end_lineno - node.lineno + 1
            for item in node.body:
                if isinstance(item, ast.FunctionDef):
                    functions['%s.%s' % (node.name, item.name)] = \
                        item.end_lineno - item.lineno + 1
    return text.count('\n'), classes, functions


@pytest.mark.parametrize('path', sorted((PACKAGE / 'core').rglob('*.py'))
                         + sorted((PACKAGE / 'nodes').glob('*.py')),
                         ids=lambda p: str(p.relative_to(PACKAGE)))
def test_files_and_classes_of_the_core_and_the_nodes_stay_small(path):
    lines, classes, _ = _sizes(path)
    assert lines <= MAX_FILE_LINES, '%s: %d lines' % (path.name, lines)
    big = {name: n for name, n in classes.items() if n > MAX_CLASS_LINES}
    assert not big, big
    if path.name == 'balance_node.py':
        assert lines <= MAX_NODE_LINES, lines


def test_the_tick_is_a_short_sequence_over_parts():
    _, classes, functions = _sizes(PACKAGE / 'core' / 'balance_loop.py')
    assert functions['BalanceLoop.tick'] <= MAX_TICK_LINES, functions['BalanceLoop.tick']
    assert classes['BalanceLoop'] <= MAX_CLASS_LINES


def test_the_size_checks_can_fail(tmp_path):
    big = tmp_path / 'big.py'
    big.write_text('class Big:\n' + ''.join('    x%d = %d\n' % (k, k) for k in range(400)))
    lines, classes, _ = _sizes(big)
    assert lines == 401 and classes['Big'] == 401 > MAX_CLASS_LINES
