"""Bags out, through rosbags (>= 0.11): :class:`BagWriter` and the odometry recording.

:class:`BagWriter` writes a rosbag2 folder with one MCAP file (zstd-compressed chunks by
default), readable by ``ros2 bag play``, rosbags, Foxglove and the ``mcap`` CLI: point clouds,
poses, odometry, paths and TF. :func:`write_odometry_mcap` writes the trajectory of an odometry
run as one self-contained MCAP file, the record ``kentreg_replay`` leaves of every run.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, DTypeLike
from scipy.spatial.transform import Rotation

from kentreg_ros.io import names
from kentreg_ros.io.bags import ODOMETRY, PATH, POSESTAMPED
from kentreg_ros.io.errors import BagError, describe_error
from kentreg_ros.io.pointcloud2 import (
    array_to_pointcloud2,
    default_typestore,
    ns_to_sec_nanosec,
    rosbags_factory,
)

if TYPE_CHECKING:
    from kentreg_ros.core import OdometryStep

#: Topics of :func:`write_odometry_mcap`: the node's (:mod:`kentreg_ros.io.names`) as they
#: resolve in the root namespace, so a recorded run and a live one look alike.
ODOMETRY_TOPIC = names.absolute(names.ODOMETRY)
POSE_TOPIC = names.absolute(names.POSE)
PATH_TOPIC = names.absolute(names.PATH)
CLOUD_REGISTERED_TOPIC = names.absolute(names.CLOUD_REGISTERED)
MAP_TOPIC = names.absolute(names.MAP)
TF_TOPIC = names.TF


class BagWriter:
    """Write a rosbag2 MCAP bag: point clouds, poses, odometry, paths, TF.

    Use as a context manager. The output is a rosbag2 folder ``<path>/`` holding
    ``<name>.mcap`` and ``metadata.yaml`` (what ``ros2 bag play <path>`` expects); a path ending
    in ``.mcap`` is taken without the suffix. The bag is closed properly even when the ``with``
    block raises, so what was written before an error stays readable.

    Parameters
    ----------
    path : str or Path
        Folder to create.
    compress : bool
        zstd-compress the MCAP chunks (default True; ``ros2 bag`` reads them natively).
    overwrite : bool
        Replace an existing rosbag2 folder (only one holding nothing but bag files).
    custom_data : dict of str to str, optional
        Stored in ``metadata.yaml`` (``custom_data``), e.g. provenance.
    typestore : rosbags Typestore, optional
        Default: ROS 2 Jazzy.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        compress: bool = True,
        overwrite: bool = False,
        custom_data: Mapping[str, str] | None = None,
        typestore: Any = None,
    ) -> None:
        p = Path(path)
        if p.suffix.lower() == '.mcap':
            p = p.with_suffix('')
        self.path = p
        self.compress = compress
        self.overwrite = overwrite
        self.custom_data = dict(custom_data or {})
        self.typestore = typestore if typestore is not None else default_typestore()
        self._factory = rosbags_factory(self.typestore)
        self._writer: Any = None
        self._connections: dict[str, Any] = {}
        self.counts: dict[str, int] = {}

    @property
    def mcap_path(self) -> Path:
        """The MCAP file inside the bag folder."""
        return self.path / f'{self.path.name}.mcap'

    def open(self) -> None:
        """Create the bag folder and start writing."""
        from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

        if self.path.exists():
            if not self.overwrite:
                raise BagError(f'{self.path} exists; not overwriting (use overwrite).')
            _remove_bag_folder(self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        if self.compress:
            writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        for key, value in self.custom_data.items():
            writer.set_custom_data(key, str(value))
        try:
            writer.open()
        except Exception as exc:
            raise BagError(f'{self.path}: cannot create bag ({describe_error(exc)}).') from exc
        self._writer = writer

    def close(self) -> None:
        """Finish the MCAP summary and metadata.yaml."""
        if self._writer is not None:
            writer, self._writer = self._writer, None
            writer.close()

    def __enter__(self) -> BagWriter:
        self.open()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def write(self, topic: str, msg: Any, stamp_ns: int) -> None:
        """Write any rosbags message of the writer's typestore, logged at ``stamp_ns``."""
        if self._writer is None:
            raise BagError(f'{self.path}: writer is not open.')
        msgtype = msg.__msgtype__
        connection = self._connections.get(topic)
        if connection is None:
            connection = self._writer.add_connection(topic, msgtype, typestore=self.typestore)
            self._connections[topic] = connection
            self.counts[topic] = 0
        elif connection.msgtype != msgtype:
            raise BagError(
                f'{self.path}: topic {topic} already carries {connection.msgtype}, not {msgtype}.'
            )
        self._writer.write(connection, int(stamp_ns), self.typestore.serialize_cdr(msg, msgtype))
        self.counts[topic] += 1

    def _header(self, stamp_ns: int, frame_id: str) -> Any:
        sec, nanosec = ns_to_sec_nanosec(stamp_ns)
        return self._factory.header(
            stamp=self._factory.time(sec=sec, nanosec=nanosec), frame_id=frame_id
        )

    def _pose(self, T: ArrayLike) -> Any:
        types = self.typestore.types
        M = np.asarray(T, dtype=np.float64)
        if M.shape != (4, 4):
            raise ValueError(f'Expected a pose of shape (4, 4), got {M.shape}.')
        x, y, z, w = Rotation.from_matrix(M[:3, :3]).as_quat()
        return types['geometry_msgs/msg/Pose'](
            position=types['geometry_msgs/msg/Point'](*(float(v) for v in M[:3, 3])),
            orientation=types['geometry_msgs/msg/Quaternion'](
                float(x), float(y), float(z), float(w)
            ),
        )

    def write_pointcloud(
        self,
        topic: str,
        stamp_ns: int,
        points: ArrayLike,
        *,
        extra: Mapping[str, ArrayLike] | None = None,
        frame_id: str = 'lidar',
        xyz_dtype: DTypeLike = np.float32,
    ) -> None:
        """Write a PointCloud2 (see :func:`~kentreg_ros.io.pointcloud2.array_to_pointcloud2`)."""
        msg = array_to_pointcloud2(
            points,
            extra=extra,
            frame_id=frame_id,
            stamp_ns=stamp_ns,
            xyz_dtype=xyz_dtype,
            factory=self._factory,
        )
        self.write(topic, msg, stamp_ns)

    def write_pose(
        self, topic: str, stamp_ns: int, T_frame_child: ArrayLike, *, frame_id: str = 'world'
    ) -> None:
        """Write a PoseStamped: the pose (4, 4) of the child in ``frame_id``."""
        msg = self.typestore.types[POSESTAMPED](
            header=self._header(stamp_ns, frame_id), pose=self._pose(T_frame_child)
        )
        self.write(topic, msg, stamp_ns)

    def write_odometry(
        self,
        topic: str,
        stamp_ns: int,
        T_frame_child: ArrayLike,
        *,
        frame_id: str = 'odom',
        child_frame_id: str = 'base_link',
        pose_covariance: ArrayLike | None = None,
    ) -> None:
        """Write an Odometry: pose (4, 4) of ``child_frame_id`` in ``frame_id``, zero twist.

        ``pose_covariance`` is the 6x6 covariance of (x, y, z, rot_x, rot_y, rot_z); default 0.
        """
        types = self.typestore.types
        cov = np.zeros(36) if pose_covariance is None else np.asarray(pose_covariance, float)
        if cov.size != 36:
            raise ValueError(f'Expected a 6x6 `pose_covariance`, got shape {cov.shape}.')
        zero = types['geometry_msgs/msg/Vector3'](0.0, 0.0, 0.0)
        msg = types[ODOMETRY](
            header=self._header(stamp_ns, frame_id),
            child_frame_id=child_frame_id,
            pose=types['geometry_msgs/msg/PoseWithCovariance'](
                pose=self._pose(T_frame_child), covariance=cov.reshape(36).copy()
            ),
            twist=types['geometry_msgs/msg/TwistWithCovariance'](
                twist=types['geometry_msgs/msg/Twist'](linear=zero, angular=zero),
                covariance=np.zeros(36),
            ),
        )
        self.write(topic, msg, stamp_ns)

    def write_path(
        self,
        topic: str,
        stamp_ns: int,
        stamps_ns: ArrayLike,
        T_frame_child: ArrayLike,
        *,
        frame_id: str = 'world',
    ) -> None:
        """Write a nav_msgs Path of poses (N, 4, 4) timed ``stamps_ns`` (N,)."""
        T = np.asarray(T_frame_child, dtype=np.float64)
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        if T.ndim != 3 or T.shape[1:] != (4, 4) or stamps.shape != (len(T),):
            raise ValueError(
                f'Expected poses (N, 4, 4) and stamps (N,), got {T.shape} and {stamps.shape}.'
            )
        posestamped = self.typestore.types[POSESTAMPED]
        poses = [
            posestamped(header=self._header(int(s), frame_id), pose=self._pose(M))
            for s, M in zip(stamps, T, strict=True)
        ]
        msg = self.typestore.types[PATH](header=self._header(stamp_ns, frame_id), poses=poses)
        self.write(topic, msg, stamp_ns)

    def write_transform(
        self,
        stamp_ns: int,
        T_frame_child: ArrayLike,
        *,
        frame_id: str,
        child_frame_id: str,
        topic: str = '/tf',
    ) -> None:
        """Write a tf2_msgs TFMessage with one transform ``frame_id`` -> ``child_frame_id``."""
        types = self.typestore.types
        pose = self._pose(T_frame_child)
        transform = types['geometry_msgs/msg/Transform'](
            translation=types['geometry_msgs/msg/Vector3'](
                pose.position.x, pose.position.y, pose.position.z
            ),
            rotation=pose.orientation,
        )
        stamped = types['geometry_msgs/msg/TransformStamped'](
            header=self._header(stamp_ns, frame_id),
            child_frame_id=child_frame_id,
            transform=transform,
        )
        self.write(topic, types['tf2_msgs/msg/TFMessage'](transforms=[stamped]), stamp_ns)


def _remove_bag_folder(path: Path) -> None:
    entries = list(path.iterdir()) if path.is_dir() else []
    is_bag_folder = (
        path.is_dir()
        and (path / 'metadata.yaml').is_file()
        and all(
            e.is_file() and e.suffix.lower() in ('.mcap', '.db3', '.yaml', '.zstd')
            for e in entries
        )
    )
    if not is_bag_folder:
        raise BagError(f'{path} exists and is not a rosbag2 folder; not removing it.')
    shutil.rmtree(path)


def write_odometry_mcap(
    path: Path,
    steps: Sequence[OdometryStep],
    *,
    odom_frame: str,
    child_frame: str,
    map_points: ArrayLike | None = None,
    clouds: bool = True,
) -> dict[str, int]:
    """Write an odometry run as one MCAP file; return the message count per topic.

    Per scan: nav_msgs/Odometry on :data:`ODOMETRY_TOPIC` (with the chained pose covariance),
    geometry_msgs/PoseStamped on :data:`POSE_TOPIC`, the ``odom_frame`` -> ``child_frame``
    transform on :data:`TF_TOPIC` and (``clouds``) the scan's registered points (prepared,
    deskewed) in ``odom_frame`` on :data:`CLOUD_REGISTERED_TOPIC`, as ``kentreg_node`` publishes
    them by default, stamped with the scan's header stamp; then one nav_msgs/Path
    of every pose on :data:`PATH_TOPIC` and, with ``map_points``, one sensor_msgs/PointCloud2
    of the map in ``odom_frame`` on :data:`MAP_TOPIC` (at the last stamp). The bag is written
    in a hidden folder beside ``path`` and its MCAP file moved to ``path``: a single
    self-contained file that rosbag2 (``ros2 bag play``/``info``) and Foxglove open as is.

    Parameters
    ----------
    path : Path
        The ``.mcap`` file to write (replaced if it exists); its folder must exist.
    steps : sequence of OdometryStep
        The run, in order.
    odom_frame, child_frame : str
        ``header.frame_id`` and ``child_frame_id`` of the poses.
    map_points : array_like, shape (M, 3), optional
        The map of the run in ``odom_frame`` (float32 ``x y z`` in the message).
    clouds : bool
        Write the registered cloud of every scan that has points (default True).

    Raises
    ------
    BagError
        The bag cannot be written.
    """
    tmp = path.parent / f'.{path.stem}-{os.getpid()}'
    if tmp.exists():
        shutil.rmtree(tmp)
    with BagWriter(tmp, compress=True) as writer:
        for step in steps:
            writer.write_odometry(
                ODOMETRY_TOPIC,
                step.stamp_ns,
                step.T_world_lidar,
                frame_id=odom_frame,
                child_frame_id=child_frame,
                pose_covariance=step.covariance,
            )
            writer.write_pose(POSE_TOPIC, step.stamp_ns, step.T_world_lidar, frame_id=odom_frame)
            writer.write_transform(
                step.stamp_ns,
                step.T_world_lidar,
                frame_id=odom_frame,
                child_frame_id=child_frame,
                topic=TF_TOPIC,
            )
            if clouds and step.points is not None:
                T = step.T_world_lidar
                writer.write_pointcloud(
                    CLOUD_REGISTERED_TOPIC,
                    step.stamp_ns,
                    step.points @ T[:3, :3].T + T[:3, 3],
                    frame_id=odom_frame,
                )
        if steps:
            writer.write_path(
                PATH_TOPIC,
                steps[-1].stamp_ns,
                [s.stamp_ns for s in steps],
                np.stack([s.T_world_lidar for s in steps]),
                frame_id=odom_frame,
            )
            if map_points is not None:
                writer.write_pointcloud(
                    MAP_TOPIC, steps[-1].stamp_ns, map_points, frame_id=odom_frame
                )
        counts = dict(writer.counts)
    os.replace(writer.mcap_path, path)
    shutil.rmtree(tmp)
    return counts
