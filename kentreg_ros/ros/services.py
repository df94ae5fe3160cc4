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
from the scans). With a ``map_file`` it means something else: the pose of the moving frame in
``map_frame``, where the localization searches the map, within the window its covariance gives
(:func:`search_window`); the odometry is left alone.
"""

from __future__ import annotations

import datetime
import os
from pathlib import Path
from typing import Any

import numpy as np

from kentreg_ros.core import InvalidInputError, Window
from kentreg_ros.io.params import NodeSettings
from kentreg_ros.io.runmap import SavedRun, save_run
from kentreg_ros.ros.frames import Frames
from kentreg_ros.ros.messages import covariance_from_msg, pose_from_msg

FloatArray = np.ndarray
#: Standard deviations of an initial pose's covariance the map search covers: 3 holds 99.7 %
#: of a normal error along one axis.
WINDOW_SIGMAS = 3.0
#: The least window of an initial pose (m, deg): a click in RViz's 2D Pose Estimate is rarely
#: better than a metre and ten degrees, and RViz sends no covariance of its own choice; a
#: window below the odometry's drift over the search's few scans would refuse the right place.
MIN_WINDOW_DISTANCE = 1.0
MIN_WINDOW_ANGLE_DEG = 10.0


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


def initial_pose(
    msg: Any, settings: NodeSettings, frames: Frames, *, fixed: str | None = None
) -> FloatArray | str:
    """The pose of an ``initialpose`` message in the frame ``fixed`` (default ``odom_frame``:
    ``T_odom_moving``; with a ``map_file`` the node asks for ``map_frame``), or why it cannot be
    used."""
    target = settings.odom_frame if fixed is None else fixed
    try:
        T = pose_from_msg(msg.pose.pose)
    except ValueError as exc:  # scipy: a zero or non-finite quaternion
        return f'its orientation is no rotation ({exc})'
    if not np.isfinite(T).all():
        return 'its position is not finite'
    frame = msg.header.frame_id.lstrip('/')
    if frame in ('', target):
        return T
    T_target_frame = frames.lookup(target, frame)
    if T_target_frame is None:
        return (
            f'it is in frame {frame!r}, and tf2 has no {target} <- {frame} '
            f'(give it in {target!r}, the fixed frame to set in RViz)'
        )
    return T_target_frame @ T


def search_window(covariance: Any) -> Window | str:
    """The window an ``initialpose`` gives the map search: :data:`WINDOW_SIGMAS` standard
    deviations of its position (the largest over x and y; z is the map's to find) and of its
    rotation (the largest over the three axes), at least :data:`MIN_WINDOW_DISTANCE` m and
    :data:`MIN_WINDOW_ANGLE_DEG`; or why the covariance cannot give one.

    Parameters
    ----------
    covariance : sequence of float, 36 values
        The message's row-major 6x6 covariance (x, y, z, rotation about X, Y, Z).
    """
    try:
        C = covariance_from_msg(covariance)
    except InvalidInputError as exc:
        return str(exc)
    if not np.isfinite(C).all():
        return 'its covariance is not finite'
    xy = float(np.linalg.eigvalsh(0.5 * (C[:2, :2] + C[:2, :2].T))[-1])
    rot = float(np.linalg.eigvalsh(0.5 * (C[3:, 3:] + C[3:, 3:].T))[-1])
    distance = WINDOW_SIGMAS * np.sqrt(max(xy, 0.0))
    angle = np.degrees(WINDOW_SIGMAS * np.sqrt(max(rot, 0.0)))
    return Window(
        distance=float(max(distance, MIN_WINDOW_DISTANCE)),
        angle_deg=float(np.clip(angle, MIN_WINDOW_ANGLE_DEG, 180.0)),
    )
