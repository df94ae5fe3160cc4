"""A recording: the scans of a bag or a folder together with their reference poses (a pose file
beside them, or a topic of the bag)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from kentreg_ros.core import KentRegError
from kentreg_ros.io.bags import ODOMETRY, PATH, POSESTAMPED, _Bag, bag_topics, is_bag
from kentreg_ros.io.errors import BagError, ScanFileError, describe_error
from kentreg_ros.io.pointcloud2 import (
    stamp_to_ns,
)
from kentreg_ros.io.poses import Trajectory, pose_file_beside, read_poses
from kentreg_ros.io.scanfiles import list_scans
from kentreg_ros.io.sources import ScanSource, open_scan_source

logger = logging.getLogger(__name__)

#: Message types :func:`read_ground_truth` accepts.
POSE_MSGTYPES = (
    POSESTAMPED,
    ODOMETRY,
    'geometry_msgs/msg/PoseWithCovarianceStamped',
    'geometry_msgs/msg/TransformStamped',
    PATH,
)


#: Topic of the reference poses :func:`read_ground_truth` and :func:`open_recording` read.
GROUND_TRUTH_TOPIC = '/ground_truth'


def _matrix(translation: Any, rotation: Any) -> NDArray[np.float64]:
    """4x4 from a geometry_msgs Point/Vector3 and Quaternion."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([rotation.x, rotation.y, rotation.z, rotation.w]).as_matrix()
    T[:3, 3] = (translation.x, translation.y, translation.z)
    return T


def read_ground_truth(path: str | Path, *, topic: str = GROUND_TRUTH_TOPIC) -> Trajectory:
    """Poses of a bag topic as a :class:`~kentreg_ros.io.poses.Trajectory`.

    Parameters
    ----------
    path : str or Path
        A bag.
    topic : str
        A topic of PoseStamped, Odometry, PoseWithCovarianceStamped or TransformStamped (one
        pose per message, header stamps), or Path (the last message's poses).

    Returns
    -------
    Trajectory
        ``stamps_ns`` from the headers, ``T_world_sensor`` the poses in the header frame.

    Raises
    ------
    BagError
        No such topic, a type without poses, no messages, or a damaged bag.
    """
    bag = _Bag(path)
    if topic not in bag.topics:
        candidates = [t.name for t in bag.topics.values() if t.msgtype in POSE_MSGTYPES]
        raise BagError(
            f'{path}: no topic {topic!r}; pose topics: {", ".join(candidates) or "none"}.'
        )
    msgtype = bag.topics[topic].msgtype
    if msgtype not in POSE_MSGTYPES:
        raise BagError(
            f'{path}: topic {topic} carries {msgtype}; expected one of {", ".join(POSE_MSGTYPES)}.'
        )
    stamps: list[int] = []
    poses: list[NDArray[np.float64]] = []
    for _, msg in bag.messages(topic):
        if msgtype == PATH:
            stamps = [stamp_to_ns(p.header.stamp) for p in msg.poses]
            poses = [_matrix(p.pose.position, p.pose.orientation) for p in msg.poses]
            continue
        stamps.append(stamp_to_ns(msg.header.stamp))
        if msgtype == 'geometry_msgs/msg/TransformStamped':
            poses.append(_matrix(msg.transform.translation, msg.transform.rotation))
        else:
            pose = msg.pose if msgtype == POSESTAMPED else msg.pose.pose  # *WithCovariance
            poses.append(_matrix(pose.position, pose.orientation))
    if not poses:
        raise BagError(f'{path}: topic {topic} has no poses.')
    return Trajectory(np.array(stamps, dtype=np.int64), np.stack(poses))


class Recording(NamedTuple):
    """A recorded input: its scans and, when known, the reference poses of the sensor.

    Attributes
    ----------
    source : ScanSource
        The scans.
    reference : Trajectory or None
        Reference poses ``T_world_sensor`` as read (not associated with the scans).
    reference_origin : str
        Where they came from: the pose file or the bag topic; ``''`` without them.
    """

    source: ScanSource
    reference: Trajectory | None
    reference_origin: str


def open_recording(
    path: str | Path,
    *,
    topic: str | None = None,
    poses: str | Path | None = None,
    poses_topic: str = GROUND_TRUTH_TOPIC,
    fields: Sequence[str] | None = (),
) -> Recording:
    """Open a bag or a scan folder with its reference poses, wherever they are.

    The reference is ``poses`` when given; otherwise, for a bag, its ``poses_topic`` (a bag
    without that topic is logged at INFO, an unreadable one at WARNING: the scans can still be
    read), and for a scan folder a pose file beside the scans (see
    :func:`~kentreg_ros.io.poses.pose_file_beside`; an unreadable one is logged and ignored).
    When a timed reference holds exactly one pose per scan of a folder, its times stamp the
    scans.

    Parameters
    ----------
    path : str or Path
        A bag or a folder of scan files (see :func:`open_scan_source`).
    topic : str, optional
        Bags only: the PointCloud2 topic, needed when there are several.
    poses : str or Path, optional
        A pose file (KITTI, TUM, ETH, BALM; see :func:`~kentreg_ros.io.poses.read_poses`).
    poses_topic : str
        The bag topic of the reference poses (see :func:`read_ground_truth`).
    fields : sequence of str, optional
        Extra per-point fields to keep; ``()`` (default) none, None all.

    Returns
    -------
    Recording

    Raises
    ------
    ScanFileError
        ``path`` does not exist.
    BagError, ScanFileError, PoseFileError, ValueError
        As :func:`open_scan_source` and :func:`~kentreg_ros.io.poses.read_poses`.
    """
    p = Path(path)
    if not p.exists():
        raise ScanFileError(f'{p}: no such file or folder')
    reference: Trajectory | None = None
    origin = ''
    if poses is not None:
        reference, origin = read_poses(poses), str(poses)
    if is_bag(p):
        source = open_scan_source(p, topic=topic, fields=fields)
        if reference is None:
            try:
                reference, origin = read_ground_truth(p, topic=poses_topic), poses_topic
            except KentRegError as exc:
                # A bag without the topic is common (logged quietly); an unreadable topic is
                # worth a warning, but the odometry can still run.
                missing = poses_topic not in bag_topics(p)
                level = logging.INFO if missing else logging.WARNING
                logger.log(level, 'No ground truth from the bag: %s', describe_error(exc))
        return Recording(source, reference, origin)
    if topic is not None:
        raise ValueError(f'`topic` applies to bags; {p} is not a bag.')
    if reference is None and p.is_dir():
        beside = pose_file_beside(p)
        if beside is not None:
            try:
                reference, origin = read_poses(beside), str(beside)
                logger.info('Ground truth: %s (found beside the scans).', beside)
            except KentRegError as exc:
                logger.warning('Ignoring %s: %s', beside, exc)
    stamps: Trajectory | None = None
    if reference is not None and reference.stamps_ns is not None and p.is_dir():
        if len(list_scans(p)) == len(reference.T_world_sensor):
            stamps = reference  # one pose per scan: its times stamp the scans
    return Recording(open_scan_source(p, fields=fields, poses=stamps), reference, origin)
