"""
Packaging: package.xml stays true, colcon sees an ament_python package, `ros2 run` finds us.

`ros2 run wheelleg_balance balance_node` looks for an executable file named balance_node in
<prefix>/lib/wheelleg_balance, where <prefix> is the package's prefix in the ament index
(ros2run uses ament_index_python.get_package_prefix); these tests check exactly that.
"""
import ast
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
               'main_job', 'fault_report']

# Third-party import name -> the package.xml key that provides it on Ubuntu 24.04 / Jazzy.
IMPORT_TO_KEY = {
    'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'can': 'python3-can',
    'msgpack': 'python3-msgpack', 'yaml': 'python3-yaml', 'matplotlib': 'python3-matplotlib',
    'mujoco': 'python3-mujoco-pip', 'rclpy': 'rclpy', 'sensor_msgs': 'sensor_msgs',
    'geometry_msgs': 'geometry_msgs', 'nav_msgs': 'nav_msgs', 'std_msgs': 'std_msgs',
    'std_srvs': 'std_srvs', 'diagnostic_msgs': 'diagnostic_msgs',
    'builtin_interfaces': 'builtin_interfaces', 'rcl_interfaces': 'rcl_interfaces',
    'ament_index_python': 'ament_index_python', 'launch': 'launch', 'launch_ros': 'launch_ros',
    'sympy': 'python3-sympy', 'hypothesis': 'python3-hypothesis', 'pytest': 'python3-pytest',
    'ament_flake8': 'ament_flake8', 'ament_pep257': 'ament_pep257',
}


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
    (PACKAGE, ('exec_depend', 'depend')),
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
