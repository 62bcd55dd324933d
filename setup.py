"""
ament_python packaging for dgp_ros.

The same file serves two installs:
- ``colcon build`` in a ROS 2 Jazzy workspace (setup.cfg puts the executables in
  ``lib/dgp_ros`` where ``ros2 run dgp_ros estimator`` finds them);
- ``pip install -e .`` into the PyPI-based ``.venv`` (console scripts on PATH).
"""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'dgp_ros'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(include=['dgp_ros', 'dgp_ros.*', 'sim_bridge', 'sim_bridge.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml')),
        ('share/' + PACKAGE + '/launch', glob('launch/*.py')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='dgp_ros maintainers',
    maintainer_email='maintainers@dgp-ros.org',
    description=('Dissipative Gaussian Processes for passive online damping identification '
                 '(ROS 2).'),
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'estimator = dgp_ros.nodes.estimator:main',
            'sim_bridge = sim_bridge.node:main',
            'dgp-arm-sim = dgp_ros.nodes.arm_sim:main',
            'dgp-arm-loop = dgp_ros.nodes.arm_loop:main',
            'dgp-controller = dgp_ros.nodes.controller:main',
            'dgp-demo = dgp_ros.apps.demo:main',
            'dgp-replay = dgp_ros.apps.replay:main',
            'dgp-export = dgp_ros.apps.export:main',
            'dgp-record = dgp_ros.bags.cli:record_main',
            'dgp-play = dgp_ros.bags.cli:play_main',
        ],
        # what a saved model may carry besides its damping force, rebuilt by kind when
        # dgp_ros.gp evaluates it (gp/persistence.py: gp imports no layer above it)
        'dgp_ros.corrections': [
            'conservative = dgp_ros.dynamics.conservative:Correction.from_dict',
        ],
    },
)
