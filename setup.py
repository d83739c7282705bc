"""ament_python build of wheelleg_balance (see package.xml for dependencies)."""
from glob import glob
import os

from setuptools import find_packages, setup

package_name = 'wheelleg_balance'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    package_data={package_name: ['sim/*.xml']},
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
        ],
    },
)
