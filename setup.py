"""ament_python build of wheelleg_balance (see package.xml for dependencies)."""
import compileall
from glob import glob
import os
import py_compile
import subprocess
import sys

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py

package_name = 'wheelleg_balance'


class BuildPyWithTables(build_py):
    """build_py, then the bytecode and the default configuration's height tables (start-up)."""

    def run(self):
        super().run()
        # Bytecode whatever PYTHONDONTWRITEBYTECODE says (set in many containers: then nothing
        # ever caches it, and every start of every process compiled the package: 0.1 s each).
        # Checked against the source's hash, so an edited source is never shadowed.
        compileall.compile_dir(os.path.join(self.build_lib, package_name), quiet=1,
                               invalidation_mode=py_compile.PycInvalidationMode.CHECKED_HASH)
        # core/table_cache.py: balance_node then starts without solving them (1.4 s at load 1).
        folder = os.path.join(self.build_lib, package_name, 'core', 'tables')
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(
            p for p in (os.path.abspath(self.build_lib), os.environ.get('PYTHONPATH')) if p))
        code = ('from wheelleg_balance.core.default_tables import write_defaults; '
                'write_defaults(%r)' % os.path.abspath(folder))
        if subprocess.call([sys.executable, '-P', '-c', code], env=env) != 0:
            self.warn('height tables not solved: balance_node solves them at its start')


setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    cmdclass={'build_py': BuildPyWithTables},
    package_data={package_name: ['sim/*.xml', 'validation/bench/data/*.msgpack.xz']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        (os.path.join('share', package_name, 'config'),
         glob('config/*.yaml') + glob('config/*.xml')),
        (os.path.join('share', package_name, 'config', 'sros2'), glob('config/sros2/*.xml')),
        (os.path.join('share', package_name, 'launch'), glob('launch/*.launch.py')),
        (os.path.join('share', package_name, 'urdf'), glob('urdf/*.urdf')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='wheelleg_balance maintainers',
    maintainer_email='maintainers@wheelleg-balance.org',
    description='Balance control of a wheel-legged robot (output regulation and IDA-PBC).',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'balance_node = wheelleg_balance.nodes.balance_node:main',
            'teleop_node = wheelleg_balance.nodes.teleop_node:main',
            'sim_node = wheelleg_balance.nodes.sim_node:main',
            'experiments = wheelleg_balance.validation.paper.experiments:main',
            'benchmark = wheelleg_balance.validation.bench.benchmark:main',
            'soak = wheelleg_balance.validation.bench.soak:main',
            'main_job = wheelleg_balance.validation.paper.main_job.cli:main',
            'fault_report = wheelleg_balance.validation.faults.report:main',
            'margins_report = wheelleg_balance.validation.paper.margins_report:main',
            'tuning = wheelleg_balance.validation.paper.tuning:main',
            'bringup = wheelleg_balance.bringup.cli:main',
            'identify = wheelleg_balance.identification.cli:main',
        ],
    },
)
