"""ament_python / pip package definition for kentreg_ros."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'kentreg_ros'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*', 'benchmarks', 'benchmarks.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        # config/*.xml: DDS profiles (the shared-memory Fast DDS profile for large clouds).
        ('share/' + PACKAGE + '/config', glob('config/*.yaml') + glob('config/*.xml')),
        ('share/' + PACKAGE + '/launch', glob('launch/*.py')),
        ('share/' + PACKAGE + '/rviz', glob('rviz/*.rviz')),
    ],
    python_requires='>=3.11',
    install_requires=['numpy>=1.24', 'scipy>=1.10', 'pyyaml>=6', 'setuptools'],
    extras_require={
        'io': ['rosbags>=0.11', 'mcap>=1.1', 'tqdm>=4.60', 'python-lzf>=0.2.4', 'matplotlib>=3.7'],
        # small_gicp's C++ KD-tree: exact neighbour queries about twice as fast as scipy's
        # (kentreg_ros.core.neighbors); numba compiles the per-point loops of preparing a scan
        # (kentreg_ros.core.kernels). benchmarks/per_scan.py measures both; without them the
        # same results come from scipy and numpy, slower.
        'fast': ['small-gicp>=1.0', 'numba>=0.60'],
        'test': [
            'pytest>=7',
            'small-gicp>=1.0',
            'numba>=0.60',
            'ruff>=0.5',
            'mypy>=1.8',
            'rosbags>=0.11',
            'mcap>=1.1',
            'tqdm>=4.60',
            'python-lzf>=0.2.4',
            'plyfile>=1.0',
            'matplotlib>=3.7',
            'types-PyYAML',
        ],
        'ros': ['ros-jazzy-rclpy[fastrtps]', 'ros-jazzy-common-interfaces'],
        # kentreg_batch over several cores or machines: Dask's distributed scheduler (chosen
        # over Ray for its start-up, memory and install size; benchmarks/README.md, section 6)
        # and threadpoolctl, which holds each worker's BLAS to one thread.
        'cluster': ['distributed>=2024.1', 'threadpoolctl>=3.1'],
        'bench': ['open3d-cpu', 'small-gicp', 'kiss-icp', 'matplotlib>=3.7'],
    },
    zip_safe=True,
    maintainer='kentreg maintainers',
    maintainer_email='kentreg@example.com',
    description='LiDAR odometry with Kent (FB5) mixture registration for ROS 2 Jazzy.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'kentreg = kentreg_ros.cli.__main__:main',
            'kentreg_register = kentreg_ros.cli.register:main',
            'kentreg_convert = kentreg_ros.cli.convert:main',
            'kentreg_replay = kentreg_ros.cli.replay:main',
            'kentreg_localize = kentreg_ros.cli.localize:main',
            'kentreg_batch = kentreg_ros.cli.batch:main',
            'kentreg_node = kentreg_ros.ros.node:main',
            'kentreg_play = kentreg_ros.ros.play:main',
        ],
    },
)
