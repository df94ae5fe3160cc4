"""Start ``kentreg_node`` with a parameter file, an input topic and optional simulated time.

Examples::

    ros2 launch kentreg_ros kentreg.launch.py
    ros2 launch kentreg_ros kentreg.launch.py topic:=/velodyne_points
    ros2 launch kentreg_ros kentreg.launch.py config_file:=/path/to/my.yaml use_sim_time:=true

Arguments
---------
topic
    PointCloud2 topic the node subscribes to (its ``points`` input is remapped to it).
config_file
    Parameter file in the ``/**: ros__parameters:`` form (default: the installed
    ``share/kentreg_ros/config/kentreg.yaml``, which holds every default).
use_sim_time
    ``true`` to follow ``/clock`` (a bag played with ``kentreg_play --clock`` or
    ``ros2 bag play --clock``).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument
from launch.launch_description import LaunchDescription
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

PACKAGE = 'kentreg_ros'


def generate_launch_description() -> LaunchDescription:
    """The launch description: three arguments and the node."""
    default_config = os.path.join(get_package_share_directory(PACKAGE), 'config', 'kentreg.yaml')
    topic = LaunchConfiguration('topic')
    config_file = LaunchConfiguration('config_file')
    use_sim_time = LaunchConfiguration('use_sim_time')
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                'topic',
                default_value='points',
                description='PointCloud2 input topic (remaps the node input `points`).',
            ),
            DeclareLaunchArgument(
                'config_file',
                default_value=default_config,
                description='Parameter file (/**: ros__parameters: ...).',
            ),
            DeclareLaunchArgument(
                'use_sim_time',
                default_value='false',
                choices=['true', 'false'],
                description='Use /clock (simulated or bag time) instead of the system clock.',
            ),
            Node(
                package=PACKAGE,
                executable='kentreg_node',
                name='kentreg_node',
                output='screen',
                emulate_tty=True,
                parameters=[
                    config_file,
                    {'use_sim_time': ParameterValue(use_sim_time, value_type=bool)},
                ],
                remappings=[('points', topic)],
            ),
        ]
    )
