# SPDX-License-Identifier: Apache-2.0
"""Install script: works for both `colcon build` (ament_python) and a plain `pip install .`.

The data_files put the ament index marker, package.xml, config/ and launch/ files under
share/gp_ground_segmentation so that `ros2 run` / `ros2 pkg` find the package; setup.cfg puts the
console scripts in lib/gp_ground_segmentation, where `ros2 run` looks for executables.
"""

import glob
import os

from setuptools import find_packages, setup

package_name = 'gp_ground_segmentation'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*', 'scenes', 'scenes.*', 'benchmarks']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob.glob(os.path.join('config', '*.yaml'))
         + glob.glob(os.path.join('config', '*.xml'))
         + glob.glob(os.path.join('config', '*.rviz'))),
        ('share/' + package_name + '/launch', glob.glob(os.path.join('launch', '*.launch.py'))),
    ],
    python_requires='>=3.10',
    # ROS 2 Jazzy comes from PyPI here (rclpy with Fast DDS, the message packages); colcon users
    # who source a ROS installation already have these, and pip sees them satisfied.
    install_requires=[
        'setuptools',
        'numpy',
        'scipy',
        'threadpoolctl',  # segmenter.py caps BLAS threads per call
        'numba',  # the compiled stages (core/compiled.py), the GP each segment at its own size
        'PyYAML',  # config.load_params_file
        'rosbags',
        'ros-jazzy-rclpy[fastrtps]',
        'ros-jazzy-common-interfaces',
    ],
    extras_require={
        # matplotlib so that CI also runs the plotting tests instead of skipping them; Dask and
        # Optuna so that the batch/tune tests run on a real LocalCluster there; velodyne-decoder
        # for the packet bag and pcap tests
        'test': ['pytest', 'hypothesis', 'matplotlib', 'flake8', 'dask[distributed]', 'optuna',
                 'velodyne-decoder>=3.1', 'dpkt'],
        'plot': ['matplotlib'],
        'scale': ['dask[distributed]'],  # gp-ground-seg batch/tune --jobs/--scheduler
        'tune': ['optuna'],  # gp-ground-seg tune
        # replay/eval/batch of Velodyne packet bags and .pcap captures (tools/packets.py);
        # dpkt (its pcap reader) is also read directly
        'packets': ['velodyne-decoder>=3.1', 'dpkt'],
        'bench': ['pypatchworkpp', 'linefit'],
    },
    zip_safe=True,
    maintainer='gp_ground_segmentation maintainers',
    maintainer_email='maintainers@gp-ground-segmentation.invalid',
    description='Gaussian-process ground segmentation of LiDAR point clouds (ROS 2 Jazzy node '
                'and numpy/scipy core)',
    license='Apache License 2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'ground_segmentation_node = gp_ground_segmentation.ros.node:main',
            'ground_segmentation_lifecycle_node = gp_ground_segmentation.ros.lifecycle:main',
            'gp-ground-seg = gp_ground_segmentation.tools.cli:main',
        ],
    },
)
