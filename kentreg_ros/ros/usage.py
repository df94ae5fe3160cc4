"""``kentreg_node --help``: the console script's own options and where the ROS ones go."""

from __future__ import annotations

import argparse

from kentreg_ros import __version__
from kentreg_ros.cli.common import ArgumentParser
from kentreg_ros.io.params import NODE_NAME


def build_parser() -> argparse.ArgumentParser:
    """The console script's own options (``--help``, ``--version``); ROS arguments are not
    its business: rclpy reads them after ``--ros-args``."""
    parser = ArgumentParser(
        prog=NODE_NAME,
        usage=f'{NODE_NAME} [-h] [--version] [--ros-args ...]',
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=(
            'LiDAR odometry by Kent mixture registration: subscribes to sensor_msgs/PointCloud2\n'
            'on `points`; publishes kentreg/odometry, kentreg/pose, kentreg/path,\n'
            'kentreg/cloud_registered, kentreg/map, /diagnostics and /tf; services ~/save_map\n'
            'and ~/reset; `initialpose` sets the pose.'
        ),
        epilog=(
            'ROS arguments follow --ros-args, e.g.\n'
            f'  {NODE_NAME} --ros-args -p name:=value --params-file FILE '
            '-r points:=/velodyne_points\n'
            '  ros2 run kentreg_ros kentreg_node --ros-args --params-file config/kentreg.yaml\n'
            '\n'
            'Parameters: every one, with its type, default, range and reason, in\n'
            'docs/configuration.md (the parameter tables); the file with every default:\n'
            '  python3 -m kentreg_ros.docs --parameter-file > kentreg.yaml\n'
            'At run time: ros2 param describe /kentreg_node <name>.'
        ),
    )
    parser.add_argument('--version', action='version', version=f'%(prog)s {__version__}')
    return parser
