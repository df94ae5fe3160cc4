"""What the node answers besides its topics: ``~/save_map`` and the ``initialpose`` topic.

``~/save_map`` (std_srvs/Trigger) writes the map of the whole run so far (not only the part
published around the sensor) as ``map.ply`` and the trajectory of the moving frame as
``trajectory_tum.txt`` (``evo_traj tum``), both in ``odom_frame``, into a new folder under
``map_directory`` per call (named by the wall-clock time, so a second save never overwrites
the first); it answers with the paths, or with the reason it could not write them. Saving
copies the map under its lock, then writes outside it: the worker goes on meanwhile.

``initialpose`` (geometry_msgs/PoseWithCovarianceStamped, what RViz's "2D Pose Estimate"
publishes) sets the pose of the moving frame: its pose in ``odom_frame`` directly, or in
another frame through tf2 (``odom_frame <- that frame``); without tf2, a pose in another frame
is refused with a warning. The covariance of the message is not used (the odometry's own grows
from the scans).
"""

from __future__ import annotations

import datetime
import os
from pathlib import Path
from typing import Any

import numpy as np

from kentreg_ros.io.params import NodeSettings
from kentreg_ros.io.runmap import SavedRun, save_run
from kentreg_ros.ros.frames import Frames
from kentreg_ros.ros.messages import pose_from_msg

FloatArray = np.ndarray


def map_directory(settings: NodeSettings) -> Path:
    """Where ``~/save_map`` writes: ``map_directory`` (``~`` expanded), or
    ``$ROS_HOME/kentreg_maps`` (``~/.ros/kentreg_maps``, where ROS keeps its logs)."""
    if settings.map_directory.strip():
        return Path(settings.map_directory).expanduser()
    ros_home = os.environ.get('ROS_HOME', '').strip()
    home = Path(ros_home).expanduser() if ros_home else Path.home() / '.ros'
    return home / 'kentreg_maps'


def _new_folder(root: Path) -> Path:
    stamp = datetime.datetime.now().strftime('%Y%m%d-%H%M%S')
    folder, n = root / stamp, 2
    while folder.exists():
        folder, n = root / f'{stamp}-{n}', n + 1
    return folder


def save_map(outputs: Any, settings: NodeSettings) -> tuple[bool, str, SavedRun | None]:
    """Write the run's map and trajectory (see the module docstring); return
    ``(success, message, what was written)``."""
    points, stamps, poses, voxel = outputs.run_snapshot()
    if not len(stamps):
        return False, 'Nothing to save yet: no scan has been processed.', None
    folder = _new_folder(map_directory(settings))
    try:
        saved = save_run(folder, points, stamps, poses, voxel_size=voxel)
    except OSError as exc:
        return False, f'Cannot write the map into {folder}: {exc}', None
    message = (
        f'Saved the map ({saved.n_points} points, {voxel:g} m voxels, {settings.odom_frame}) '
        f'to {saved.map_path} and the trajectory ({saved.n_poses} poses, TUM) to '
        f'{saved.trajectory_path}'
    )
    return True, message, saved


def initial_pose(msg: Any, settings: NodeSettings, frames: Frames) -> FloatArray | str:
    """``T_odom_moving`` of an ``initialpose`` message, or why it cannot be used."""
    try:
        T = pose_from_msg(msg.pose.pose)
    except ValueError as exc:  # scipy: a zero or non-finite quaternion
        return f'its orientation is no rotation ({exc})'
    if not np.isfinite(T).all():
        return 'its position is not finite'
    frame = msg.header.frame_id.lstrip('/')
    if frame in ('', settings.odom_frame):
        return T
    T_odom_frame = frames.lookup(settings.odom_frame, frame)
    if T_odom_frame is None:
        return (
            f'it is in frame {frame!r}, and tf2 has no {settings.odom_frame} <- {frame} '
            f'(give it in {settings.odom_frame!r}, the fixed frame of rviz/kentreg.rviz)'
        )
    return T_odom_frame @ T
