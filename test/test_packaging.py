"""
Packaging: package.xml stays true, colcon sees an ament_python package, `ros2 run` finds us.

`ros2 run wheelleg_balance balance_node` looks for an executable file named balance_node in
<prefix>/lib/wheelleg_balance, where <prefix> is the package's prefix in the ament index
(ros2run uses ament_index_python.get_package_prefix); these tests check exactly that.
"""
import ast
import importlib.util
import os
import pathlib
import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
PACKAGE = 'wheelleg_balance'
EXECUTABLES = ['balance_node', 'teleop_node', 'sim_node', 'experiments', 'benchmark',
               'main_job', 'fault_report', 'bringup', 'soak']

# Third-party import name -> the package.xml key that provides it on Ubuntu 24.04 / Jazzy.
IMPORT_TO_KEY = {
    'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'can': 'python3-can',
    'msgpack': 'python3-msgpack', 'yaml': 'python3-yaml', 'matplotlib': 'python3-matplotlib',
    'mujoco': 'python3-mujoco-pip', 'rclpy': 'rclpy', 'sensor_msgs': 'sensor_msgs',
    'geometry_msgs': 'geometry_msgs', 'nav_msgs': 'nav_msgs', 'std_msgs': 'std_msgs',
    'std_srvs': 'std_srvs', 'diagnostic_msgs': 'diagnostic_msgs',
    'builtin_interfaces': 'builtin_interfaces', 'rcl_interfaces': 'rcl_interfaces',
    'rosgraph_msgs': 'rosgraph_msgs',
    'ament_index_python': 'ament_index_python', 'launch': 'launch', 'launch_ros': 'launch_ros',
    'sympy': 'python3-sympy', 'hypothesis': 'python3-hypothesis', 'pytest': 'python3-pytest',
    'ament_flake8': 'ament_flake8', 'ament_pep257': 'ament_pep257', 'tf2_msgs': 'tf2_msgs',
}
ROSDEP_TABLE = REPO / 'test' / 'rosdep_noble.yaml'
DEPEND_TAGS = ('depend', 'build_depend', 'buildtool_depend', 'build_export_depend',
               'buildtool_export_depend', 'exec_depend', 'test_depend', 'doc_depend')


def _manifest():
    return ET.parse(REPO / 'package.xml').getroot()


def _third_party_imports(folder):
    stdlib = set(sys.stdlib_module_names)
    found = {}
    for path in sorted((REPO / folder).rglob('*.py')):
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split('.')[0]
                local = (path.parent / (top + '.py')).is_file()  # a helper module beside it
                if top not in stdlib and top != PACKAGE and not local:
                    found.setdefault(top, str(path.relative_to(REPO)))
    return found


def test_manifest_is_format_3_with_a_valid_maintainer():
    root = _manifest()
    assert root.get('format') == '3'
    assert root.findtext('name') == PACKAGE
    assert root.find('export/build_type').text == 'ament_python'
    email = root.find('maintainer').get('email')
    # colcon treats a package with an invalid maintainer e-mail as plain Python.
    assert re.fullmatch(r'[^@\s]+@[^@\s]+\.[A-Za-z]{2,}', email), email


@pytest.mark.parametrize('folder,tags', [
    # The package holds the simulator and the validation tools too: their test (and optional)
    # dependencies are allowed here; test_product_code_imports_run_time_keys_only keeps them
    # out of what the robot runs.
    (PACKAGE, ('exec_depend', 'depend', 'test_depend')),
    ('test', ('test_depend', 'exec_depend', 'depend')),
    ('launch', ('exec_depend', 'depend')),
])
def test_every_import_is_declared_in_package_xml(folder, tags):
    root = _manifest()
    declared = {e.text for tag in tags for e in root.findall(tag)}
    missing = {}
    for module, where in _third_party_imports(folder).items():
        key = IMPORT_TO_KEY.get(module)
        assert key is not None, 'import %r in %s has no known rosdep key' % (module, where)
        if key not in declared:
            missing[module] = (key, where)
    assert not missing, 'package.xml lacks: %s' % missing


def test_colcon_sees_an_ament_python_package():
    colcon = shutil.which('colcon')
    if colcon is None:
        pytest.skip('colcon is not installed in this environment')
    out = subprocess.run([colcon, 'list', '--base-paths', str(REPO)], capture_output=True,
                         text=True, check=True, cwd=REPO).stdout
    assert re.search(r'^%s\s+\S+\s+\(ros\.ament_python\)$' % PACKAGE, out, re.M), out


def test_executables_are_where_ros2_run_looks(tmp_path):
    try:
        from ament_index_python.packages import get_package_prefix, PackageNotFoundError
        prefix = get_package_prefix(PACKAGE)
    except (ImportError, LookupError, EnvironmentError, PackageNotFoundError):
        colcon = shutil.which('colcon')
        if colcon is None:
            pytest.skip('neither a built workspace nor colcon to build one')
        subprocess.run([colcon, '--log-base', str(tmp_path / 'log'), 'build', '--base-paths',
                        str(REPO), '--build-base', str(tmp_path / 'build'), '--install-base',
                        str(tmp_path / 'install')], check=True, cwd=REPO, capture_output=True)
        prefix = str(tmp_path / 'install' / PACKAGE)
    lib = pathlib.Path(prefix) / 'lib' / PACKAGE
    for name in EXECUTABLES:
        exe = lib / name
        assert exe.is_file() and os.access(exe, os.X_OK), 'missing executable %s' % exe
    share = pathlib.Path(prefix) / 'share' / PACKAGE
    assert (share / 'package.xml').is_file()
    assert (share / 'config' / 'balance.yaml').is_file()
    assert (share / 'config' / 'fastdds_no_shm.xml').is_file()   # nodes/dds.py


@pytest.mark.skipif(not (REPO / '.venv').is_dir() or not (REPO / '.colcon' / 'install').is_dir(),
                    reason='no scripts/setup.sh build in this checkout (e.g. a colcon workspace)')
def test_env_sh_puts_every_command_on_the_path():
    # README: `source scripts/env.sh`, then the commands by name; scripts/main_job.sh runs
    # `main_job` this way.
    names = ' '.join(EXECUTABLES)
    out = subprocess.run(['bash', '-c', 'source scripts/env.sh && for n in %s; do '
                          'command -v "$n" || echo "missing $n"; done' % names],
                         cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    found = out.stdout.split()
    assert 'missing' not in found, out.stdout
    for name, path in zip(EXECUTABLES, found):
        assert path.endswith('/lib/%s/%s' % (PACKAGE, name)), (name, path)
        # The executable runs the interpreter of the venv the package was built with.
        assert 'python' in pathlib.Path(path).read_text().splitlines()[0]


def test_robot_launch_imports_without_launch_and_starts_robot_state_publisher():
    path = REPO / 'launch' / 'robot.launch.py'
    tree = ast.parse(path.read_text())
    # Module level: the standard library only (launch, launch_ros come in the function).
    top = {a.name.split('.')[0] for n in tree.body if isinstance(n, ast.Import) for a in n.names}
    top |= {n.module.split('.')[0] for n in tree.body if isinstance(n, ast.ImportFrom)}
    assert top <= set(sys.stdlib_module_names), top
    spec = importlib.util.spec_from_file_location('robot_launch', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    # robot_description is the URDF that setup.py installs to share/.
    urdf = module.robot_description(str(REPO))
    assert ET.fromstring(urdf).get('name') == PACKAGE
    assert "glob('urdf/*.urdf')" in (REPO / 'setup.py').read_text()
    strings = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant)
               and isinstance(n.value, str)}
    assert {'robot_state_publisher', 'robot_description'} <= strings
    assert 'robot_state_publisher' in {e.text for e in _manifest().findall('exec_depend')}


# ---- an install that works on a stock Ubuntu 24.04 -----------------------------------------

def _dependencies():
    """(key, tag, condition) of every dependency in package.xml."""
    return [(e.text, e.tag, e.get('condition')) for tag in DEPEND_TAGS
            for e in _manifest().findall(tag)]


def test_every_rosdep_key_resolves_on_noble_as_pinned():
    import yaml
    table = yaml.safe_load(ROSDEP_TABLE.read_text())['keys']
    keys = {key for key, _, _ in _dependencies()}
    assert keys == set(table), 'not pinned: %s; stale: %s' % (keys - set(table),
                                                              set(table) - keys)
    for key, tag, condition in _dependencies():
        entry = table[key]
        assert entry['installer'] in ('apt', 'pip'), key
        if entry['source'] == 'jazzy/distribution.yaml':
            # A ROS package: rosdep installs ros-jazzy-<name> from the ROS apt repository.
            assert entry['packages'] == ['ros-jazzy-' + key.replace('_', '-')], key
            assert entry['installer'] == 'apt', key
        else:
            assert entry['source'] in ('rosdep/python.yaml', 'rosdep/base.yaml'), key
            rule = yaml.safe_load(entry['rule']) if isinstance(entry['rule'], str) \
                else entry['rule']
            if entry['installer'] == 'pip':
                assert rule == {'pip': {'packages': entry['packages']}}, key
            else:
                # A list for every Ubuntu release, or a map by release where noble or '*'.
                apt = rule if isinstance(rule, list) else rule.get('noble', rule.get('*'))
                assert apt == entry['packages'], key
        # rosdep installs every type but doc and skips a dependency whose condition is false:
        # what a plain `rosdep install` gets must come from apt (pip fails under PEP 668).
        if condition is None and tag != 'doc_depend':
            assert entry['installer'] == 'apt', '%s (%s) would need pip' % (key, tag)
    # The conditional key is off unless asked for (catkin_pkg: an unset variable is '').
    conditional = [(k, c) for k, _, c in _dependencies() if c is not None]
    assert conditional == [('python3-mujoco-pip', '$WHEELLEG_BALANCE_SIM == 1')]


def test_run_time_keys_are_what_the_robot_needs():
    run_time = {k for k, tag, c in _dependencies() if tag in ('exec_depend', 'depend')}
    assert {'rclpy', 'python3-numpy', 'python3-scipy', 'python3-can', 'sensor_msgs',
            'robot_state_publisher'} <= run_time
    # The simulator's and the tools' dependencies are not run-time dependencies of the robot.
    assert not run_time & {'python3-mujoco-pip', 'python3-matplotlib', 'python3-msgpack',
                           'python3-sympy', 'python3-hypothesis', 'python3-pytest'}


def _product_modules():
    """Modules the robot runs: the core, and the nodes but the simulator."""
    root = REPO / PACKAGE
    paths = sorted((root / 'core').rglob('*.py')) + sorted((root / 'nodes').glob('*.py'))
    paths.append(root / 'optional.py')
    names = []
    for path in paths:
        if path.name == 'sim_node.py':
            continue
        parts = path.relative_to(REPO).with_suffix('').parts
        names.append('.'.join(parts[:-1] if parts[-1] == '__init__' else parts))
    return names


def _run_without(modules, code):
    """Run Python code in a child where importing any of modules fails as if not installed."""
    prelude = 'import sys\nfor m in %r:\n    sys.modules[m] = None\n' % (sorted(modules),)
    return subprocess.run([sys.executable, '-c', prelude + code], capture_output=True,
                          text=True, cwd=REPO, timeout=120)


def test_product_code_imports_run_time_keys_only():
    run_time = {k for k, tag, c in _dependencies() if tag in ('exec_depend', 'depend')
                and c is None}
    blocked = {m for m, key in IMPORT_TO_KEY.items() if key not in run_time}
    assert {'mujoco', 'matplotlib', 'msgpack', 'sympy', 'hypothesis', 'pytest'} <= blocked
    modules = _product_modules()
    assert 'wheelleg_balance.nodes.balance_node' in modules
    assert 'wheelleg_balance.core.attitude' in modules
    out = _run_without(blocked, 'import importlib\nfor name in %r:\n'
                       '    importlib.import_module(name)\n' % (modules,))
    assert out.returncode == 0, out.stderr


def test_sim_node_without_mujoco_says_what_to_install():
    out = _run_without({'mujoco'}, 'import wheelleg_balance.nodes.sim_node')
    assert out.returncode == 1
    assert 'Traceback' not in out.stderr, out.stderr
    assert out.stderr.startswith('sim_node: ') and 'python3-mujoco-pip' in out.stderr, \
        out.stderr


def test_sim_config_and_the_motor_emulators_need_no_mujoco():
    # config/sim.yaml is checked, and the fake motors of the tests run, without the simulator.
    out = _run_without({'mujoco'}, 'from wheelleg_balance.sim.config import SimConfig\n'
                       'from wheelleg_balance.sim.motor_emulator import MitMotorBank\n'
                       'from wheelleg_balance.core.schema import check\n'
                       'assert check(SimConfig()) == [] and MitMotorBank((1, 2)).ids\n')
    assert out.returncode == 0, out.stderr


#: Where each tool's main() lives.
TOOL_MODULES = {'main_job': 'wheelleg_balance.validation.paper.main_job.cli',
                'experiments': 'wheelleg_balance.validation.paper.experiments'}


@pytest.mark.parametrize('tool,module', [('main_job', 'mujoco'), ('main_job', 'matplotlib'),
                                         ('experiments', 'matplotlib')])
def test_tools_without_their_optional_dependency_stop_at_once(tmp_path, tool, module):
    output = tmp_path / 'out'
    out = _run_without({module}, 'import importlib\n'
                       'sys.exit(importlib.import_module(%r).main(["--output", %r]))'
                       % (TOOL_MODULES[tool], str(output)))
    assert out.returncode == 2, out.stderr
    assert 'Traceback' not in out.stderr, out.stderr
    assert repr(module) in out.stderr and tool in out.stderr
    assert not output.exists()  # nothing was started


def test_optional_require_names_what_is_missing_and_passes_real_errors_on():
    from wheelleg_balance.optional import MissingDependency, require
    with pytest.raises(MissingDependency, match='the test needs the Python module .no_such_'):
        require('no_such_module_xyz', 'the test')
    assert require('json', 'the test').dumps([1]) == '[1]'


def test_license_file_is_the_license_package_xml_names():
    text = (REPO / 'LICENSE').read_text()
    assert _manifest().findtext('license') == 'Apache-2.0'
    assert "license='Apache-2.0'" in (REPO / 'setup.py').read_text()
    head = ' '.join(text.split()[:4])
    assert head == 'Apache License Version 2.0,', head
    assert 'END OF TERMS AND CONDITIONS' in text and len(text.splitlines()) == 202
