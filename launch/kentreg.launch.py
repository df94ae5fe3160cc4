"""Start ``kentreg_node`` with a parameter file, an input topic, its frames, and optionally RViz
and a bag to play.

Examples::

    ros2 launch kentreg_ros kentreg.launch.py
    ros2 launch kentreg_ros kentreg.launch.py topic:=/velodyne_points base_frame:=base_link
    ros2 launch kentreg_ros kentreg.launch.py bag:=bags/balm_50 use_sim_time:=true rviz:=true

Arguments
---------
topic
    PointCloud2 topic the node subscribes to (its ``points`` input is remapped to it).
config_file
    Parameter file in the ``/**: ros__parameters:`` form (default: the installed
    ``share/kentreg_ros/config/kentreg.yaml``, which holds every default).
use_sim_time
    ``true`` to follow ``/clock`` (a bag played with ``--clock``, as ``bag:=`` does).
rviz
    ``true`` to start rviz2 with the installed ``share/kentreg_ros/rviz/kentreg.rviz``.
bag
    A bag to play into the node (``ros2 bag play --clock``; ``kentreg_play --clock`` where
    ros2cli is missing); empty: none.
odom_frame, base_frame
    The node's frames; empty (the default): as ``config_file`` says (its default base_frame
    is empty too: the cloud's own frame moves).
"""

import os
import shutil

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, ExecuteProcess, LogInfo, OpaqueFunction
from launch.conditions import IfCondition
from launch.launch_context import LaunchContext
from launch.launch_description import LaunchDescription
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

PACKAGE = 'kentreg_ros'


def _node_and_bag(context: LaunchContext) -> list:
    """The node with the frames given on the command line (only those: the others stay the
    parameter file's), and the bag player when ``bag:=`` names one."""
    frames = {
        name: LaunchConfiguration(name).perform(context) for name in ('odom_frame', 'base_frame')
    }
    overrides = {name: value for name, value in frames.items() if value}
    use_sim_time = LaunchConfiguration('use_sim_time')
    actions = [
        Node(
            package=PACKAGE,
            executable='kentreg_node',
            name='kentreg_node',
            output='screen',
            emulate_tty=True,
            parameters=[
                LaunchConfiguration('config_file'),
                {'use_sim_time': ParameterValue(use_sim_time, value_type=bool), **overrides},
            ],
            remappings=[('points', LaunchConfiguration('topic'))],
        )
    ]
    bag = LaunchConfiguration('bag').perform(context)
    if bag:
        if shutil.which('ros2'):
            cmd = ['ros2', 'bag', 'play', bag, '--clock']
        else:
            cmd = ['kentreg_play', bag, '--clock', '--wait-subscribers', '10']
            note = 'ros2 (ros2cli) not found: playing the bag with kentreg_play.'
            actions.append(LogInfo(msg=note))
        actions.append(ExecuteProcess(cmd=cmd, output='screen'))
    return actions


def generate_launch_description() -> LaunchDescription:
    """The launch description: the arguments, the node, RViz and the bag player."""
    default_config = os.path.join(get_package_share_directory(PACKAGE), 'config', 'kentreg.yaml')
    rviz_config = os.path.join(get_package_share_directory(PACKAGE), 'rviz', 'kentreg.rviz')
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
            DeclareLaunchArgument(
                'rviz',
                default_value='false',
                choices=['true', 'false'],
                description='Start rviz2 with the package configuration (rviz/kentreg.rviz).',
            ),
            DeclareLaunchArgument(
                'bag',
                default_value='',
                description='Bag to play into the node with --clock (empty: none).',
            ),
            DeclareLaunchArgument(
                'odom_frame',
                default_value='',
                description='Odometry frame (empty: as config_file says).',
            ),
            DeclareLaunchArgument(
                'base_frame',
                default_value='',
                description='Moving frame (empty: as config_file says; its default is the '
                "cloud's own frame).",
            ),
            OpaqueFunction(function=_node_and_bag),
            Node(
                package='rviz2',
                executable='rviz2',
                name='rviz2',
                arguments=['-d', rviz_config],
                parameters=[{'use_sim_time': ParameterValue(use_sim_time, value_type=bool)}],
                condition=IfCondition(LaunchConfiguration('rviz')),
                output='screen',
            ),
        ]
    )
