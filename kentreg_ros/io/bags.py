"""Bags in, through rosbags (>= 0.11): one iterator for bags and scan folders alike.

Reading
    rosbag2 (``.db3`` or ``.mcap``, the file or its folder) and ROS 1 ``.bag`` files, through
    :class:`rosbags.highlevel.AnyReader` with the ROS 2 Jazzy typestore for bags that embed no
    message definitions. The PointCloud2 topic is picked automatically when there is exactly one.
    Faults are one :class:`~kentreg_ros.io.errors.BagError`, raised where they happen: every
    message before the fault has already been yielded. An MCAP file that rosbags cannot open
    (truncated: no summary, no footer) is streamed record by record with the ``mcap`` package,
    so the messages written before the cut are still delivered.
Recordings
    :func:`open_recording` opens a bag or a scan folder together with its reference poses (a
    pose file, the bag's ``/ground_truth`` topic, or a pose file beside the scans), as
    ``kentreg_replay`` and the benchmarks read their input.

Writing is in :mod:`kentreg_ros.io.bagwriter`.
"""

from __future__ import annotations

import abc
import logging
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import DTypeLike, NDArray
from scipy.spatial.transform import Rotation

from kentreg_ros.core import InvalidPointCloudError, KentRegError
from kentreg_ros.io.errors import BagError, PoseFileError, ScanFileError
from kentreg_ros.io.pointcloud2 import (
    _default_typestore,
    pointcloud2_to_array,
    stamp_to_ns,
)
from kentreg_ros.io.poses import Trajectory, pose_file_beside, read_poses
from kentreg_ros.io.scanfiles import SCAN_SUFFIXES, list_scans, read_scan

logger = logging.getLogger(__name__)

POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'
POSESTAMPED = 'geometry_msgs/msg/PoseStamped'
ODOMETRY = 'nav_msgs/msg/Odometry'
PATH = 'nav_msgs/msg/Path'
#: Message types :func:`read_ground_truth` accepts.
POSE_MSGTYPES = (
    POSESTAMPED,
    ODOMETRY,
    'geometry_msgs/msg/PoseWithCovarianceStamped',
    'geometry_msgs/msg/TransformStamped',
    PATH,
)
BAG_SUFFIXES = ('.bag', '.mcap', '.db3')
#: Topic of the reference poses :func:`read_ground_truth` and :func:`open_recording` read.
GROUND_TRUTH_TOPIC = '/ground_truth'
DEFAULT_RATE_HZ = 10.0


class Scan(NamedTuple):
    """One scan from a bag or a scan folder.

    Attributes
    ----------
    stamp_ns : int
        Header stamp (bags; the receive time when the header stamp is zero), or the pose
        file's time / ``start + i / rate`` (scan folders), in nanoseconds.
    frame_id : str
        Sensor frame.
    points : ndarray, shape (N, 3)
        Finite points in the sensor frame.
    extras : dict of str to ndarray, each shape (N,) or (N, k)
        Per-point fields aligned with ``points``.
    """

    stamp_ns: int
    frame_id: str
    points: NDArray[np.floating[Any]]
    extras: dict[str, NDArray[Any]]


@dataclass(frozen=True)
class SkippedScan:
    """An input message or scan file that holds no usable scan (see :meth:`ScanSource.entries`).

    Attributes
    ----------
    index : int
        Its position in the input: the message index on the topic, or the file's index.
    stamp_ns : int or None
        Its stamp when it could be read (a bag message's header stamp, or its log time when the
        header stamp is zero; a scan file's stamp), else None.
    reason : str
        Why it was skipped, one line (the decoder's message).
    """

    index: int
    stamp_ns: int | None
    reason: str


@dataclass(frozen=True)
class BagTopic:
    """A topic of a bag: name, message type and message count."""

    name: str
    msgtype: str
    count: int


# --- opening bags ----------------------------------------------------------------------------


def is_bag(path: str | Path) -> bool:
    """True if ``path`` is a ``.bag``/``.mcap``/``.db3`` file or a rosbag2 folder."""
    p = Path(path)
    if p.is_file():
        return p.suffix.lower() in BAG_SUFFIXES
    if p.is_dir():
        return (p / 'metadata.yaml').is_file() or len(_storage_files(p)) == 1
    return False


def _storage_files(folder: Path) -> list[Path]:
    return sorted(x for x in folder.iterdir() if x.suffix.lower() in ('.mcap', '.db3'))


def _topics_text(topics: Mapping[str, BagTopic]) -> str:
    return ', '.join(f'{t.name} ({t.msgtype}, {t.count})' for t in topics.values()) or 'none'


class _Bag:
    """Topics and messages of one bag, with record-by-record salvage of damaged MCAP files."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise BagError(f'{self.path}: no such file or folder.')
        self.target = self.path
        if self.path.is_dir() and not (self.path / 'metadata.yaml').is_file():
            files = _storage_files(self.path)
            if len(files) != 1:
                raise BagError(
                    f'{self.path}: not a rosbag2 folder (no metadata.yaml, '
                    f'{len(files)} .mcap/.db3 files).'
                )
            self.target = files[0]
        elif self.path.is_file() and self.path.suffix.lower() not in BAG_SUFFIXES:
            raise BagError(f'{self.path}: not a bag (expected {", ".join(BAG_SUFFIXES)}).')
        self.salvage: _McapSalvage | None = None
        try:
            with self._reader() as reader:
                self.topics = {
                    name: BagTopic(name, info.msgtype or '?', int(info.msgcount))
                    for name, info in reader.topics.items()
                }
        except BagError:
            raise
        except Exception as exc:  # rosbags raises many types for damaged files
            mcap_file = self._mcap_file()
            if mcap_file is None:
                raise BagError(f'{self.path}: cannot open bag ({_describe(exc)}).') from exc
            logger.warning(
                '%s: rosbags cannot open it (%s); reading the MCAP records one by one.',
                self.path,
                _describe(exc),
            )
            self.salvage = _McapSalvage(mcap_file)
            self.topics = self.salvage.topics

    def _reader(self) -> Any:
        from rosbags.highlevel import AnyReader

        return AnyReader([self.target], default_typestore=_default_typestore())

    def _mcap_file(self) -> Path | None:
        if self.target.is_file():
            return self.target if self.target.suffix.lower() == '.mcap' else None
        files = [f for f in _storage_files(self.target) if f.suffix.lower() == '.mcap']
        return files[0] if len(files) == 1 else None

    def messages(self, topic: str) -> Iterator[tuple[int, Any]]:
        """Yield ``(log_time_ns, message)`` of ``topic``; raise BagError at a fault."""
        if self.salvage is not None:
            yield from self.salvage.messages(topic)
            return
        count = 0
        try:
            reader = self._reader()
            reader.open()
        except Exception as exc:
            raise BagError(f'{self.path}: cannot open bag ({_describe(exc)}).') from exc
        try:
            connections = [c for c in reader.connections if c.topic == topic]
            stream = reader.messages(connections=connections)
            while True:
                try:
                    connection, log_time, raw = next(stream)
                    msg = reader.deserialize(raw, connection.msgtype)
                except StopIteration:
                    return
                except Exception as exc:
                    raise BagError(
                        f'{self.path}: bag is corrupt after {count} message(s) of {topic} '
                        f'({_describe(exc)}).'
                    ) from exc
                count += 1
                yield int(log_time), msg
        finally:
            try:
                reader.close()
            except Exception:  # closing a reader that failed mid-read may fail again
                logger.debug('%s: error while closing the reader.', self.path, exc_info=True)


def _describe(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]


class _McapSalvage:
    """Stream an MCAP file record by record (for files without a readable summary)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.schemas: dict[int, Any] = {}
        self.channels: dict[int, Any] = {}
        counts: dict[int, int] = {}
        self.fault: str | None = None
        for record in self._records():
            counts[record.channel_id] = counts.get(record.channel_id, 0) + 1
        if self.fault is not None and not self.channels:
            raise BagError(
                f'{path}: MCAP file is truncated or corrupt before any complete chunk '
                f'({self.fault}); nothing to read.'
            )
        self.topics = {}
        for cid, channel in self.channels.items():
            schema = self.schemas.get(channel.schema_id)
            msgtype = schema.name if schema is not None else '?'
            self.topics[channel.topic] = BagTopic(channel.topic, msgtype, counts.get(cid, 0))
        if self.fault is None:
            logger.warning('%s: all records read; only the summary section was damaged.', path)
        self.typestore = self._typestore()

    def _records(self) -> Iterator[Any]:
        """Yield Message records; remember schemas, channels and the first fault."""
        from mcap.records import Channel, Message, Schema
        from mcap.stream_reader import StreamReader

        self.fault = None
        with self.path.open('rb') as stream:
            try:
                for record in StreamReader(stream, validate_crcs=True).records:
                    if isinstance(record, Schema):
                        self.schemas[record.id] = record
                    elif isinstance(record, Channel):
                        self.channels[record.id] = record
                    elif isinstance(record, Message):
                        yield record
            except Exception as exc:  # truncated or corrupt: EndOfFile, struct.error, ...
                self.fault = _describe(exc)

    def _typestore(self) -> Any:
        from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

        types: dict[str, Any] = {}
        for schema in self.schemas.values():
            text = schema.data.decode('utf-8', errors='replace')
            try:
                if schema.encoding == 'ros2msg':
                    types.update(get_types_from_msg(text, schema.name))
                elif schema.encoding == 'ros2idl':
                    types.update(get_types_from_idl(text))
            except Exception:
                logger.warning('%s: cannot parse the schema of %s.', self.path, schema.name)
        if not types:
            return _default_typestore()
        store = get_typestore(Stores.EMPTY)
        store.register(types)
        return store

    def messages(self, topic: str) -> Iterator[tuple[int, Any]]:
        count = 0
        wanted = {cid for cid, c in self.channels.items() if c.topic == topic}
        for record in self._records():
            if record.channel_id not in wanted:
                continue
            channel = self.channels[record.channel_id]
            msgtype = self.topics[topic].msgtype
            if channel.message_encoding != 'cdr':
                raise BagError(
                    f'{self.path}: topic {topic} is encoded as '
                    f'{channel.message_encoding!r}, not cdr.'
                )
            try:
                msg = self.typestore.deserialize_cdr(record.data, msgtype)
            except Exception as exc:
                raise BagError(
                    f'{self.path}: message {count} of {topic} cannot be decoded '
                    f'({_describe(exc)}).'
                ) from exc
            count += 1
            yield int(record.log_time), msg
        if self.fault is not None:
            raise BagError(
                f'{self.path}: MCAP file is truncated or corrupt after {count} message(s) of '
                f'{topic} ({self.fault}).'
            )


def bag_topics(path: str | Path) -> dict[str, BagTopic]:
    """Topics of a bag (name -> :class:`BagTopic`)."""
    return dict(_Bag(path).topics)


# --- scan sources ----------------------------------------------------------------------------


class ScanSource(abc.ABC):
    """Iterable of :class:`Scan` from a bag or scan files; ``len()`` is the number of scans.

    Iterating opens the underlying files and closes them when done; a source can be
    iterated more than once. ``n_dropped`` counts the non-finite points dropped so far.

    Iterating a source raises at the first message (or file) that cannot be decoded as a scan
    (:class:`~kentreg_ros.core.errors.InvalidPointCloudError`,
    :class:`~kentreg_ros.io.errors.ScanFileError`). :meth:`entries` instead yields a
    :class:`SkippedScan` in its place and goes on, as the ROS node and ``kentreg_replay`` do
    with a malformed scan: skip it, count it, say which.
    """

    path: Path
    n_dropped: int = 0

    @abc.abstractmethod
    def entries(self) -> Iterator[Scan | SkippedScan]:
        """One entry per input message or file, in order: its :class:`Scan`, or a
        :class:`SkippedScan` when it cannot be decoded as one. A fault of the container itself
        (a corrupt bag, an unreadable folder) still raises: nothing after it can be read."""

    def __iter__(self) -> Iterator[Scan]:
        for entry in self.entries():
            if isinstance(entry, SkippedScan):
                raise self._skip_error(entry)
            yield entry

    def _skip_error(self, entry: SkippedScan) -> KentRegError:
        return InvalidPointCloudError(f'{self.path}: scan {entry.index}: {entry.reason}')

    @abc.abstractmethod
    def __len__(self) -> int: ...

    @property
    @abc.abstractmethod
    def description(self) -> str:
        """One line telling what is read (for logs)."""


class BagScanSource(ScanSource):
    """PointCloud2 messages of one topic of a bag.

    Parameters
    ----------
    path : str or Path
        ``.bag``, ``.mcap``, ``.db3`` file, or rosbag2 folder.
    topic : str, optional
        PointCloud2 topic; needed only when the bag has more than one.
    fields : sequence of str, optional
        Extra fields to keep; None keeps all, ``()`` none.
    dtype : {numpy.float64, numpy.float32}

    Raises
    ------
    BagError
        Unreadable bag, no/ambiguous PointCloud2 topic, a topic of another type, no messages.
    """

    def __init__(
        self,
        path: str | Path,
        topic: str | None = None,
        *,
        fields: Sequence[str] | None = None,
        dtype: DTypeLike = np.float64,
    ) -> None:
        self.path = Path(path)
        self._bag = _Bag(self.path)
        self.fields = fields
        self.dtype = dtype
        topics = self._bag.topics
        clouds = [t.name for t in topics.values() if t.msgtype == POINTCLOUD2]
        if topic is None:
            if not clouds:
                raise BagError(
                    f'{self.path}: no {POINTCLOUD2} topic; topics: {_topics_text(topics)}.'
                )
            if len(clouds) > 1:
                raise BagError(
                    f'{self.path}: {len(clouds)} {POINTCLOUD2} topics ({", ".join(clouds)}); '
                    'choose one with topic= (--topic on the command line).'
                )
            topic = clouds[0]
        elif topic not in topics:
            raise BagError(
                f'{self.path}: no topic {topic!r}; PointCloud2 topics: '
                f'{", ".join(clouds) or "none"}.'
            )
        elif topics[topic].msgtype != POINTCLOUD2:
            raise BagError(
                f'{self.path}: topic {topic} carries {topics[topic].msgtype}, not {POINTCLOUD2}; '
                f'PointCloud2 topics: {", ".join(clouds) or "none"}.'
            )
        if topics[topic].count == 0:
            raise BagError(f'{self.path}: topic {topic} has no messages.')
        self.topic = topic

    def __len__(self) -> int:
        return self._bag.topics[self.topic].count

    @property
    def description(self) -> str:
        kind = 'damaged MCAP' if self._bag.salvage is not None else 'bag'
        return f'{kind} {self.path} topic {self.topic} ({len(self)} messages)'

    def entries(self) -> Iterator[Scan | SkippedScan]:
        for index, (log_time, msg) in enumerate(self._bag.messages(self.topic)):
            try:
                cloud = pointcloud2_to_array(msg, fields=self.fields, dtype=self.dtype)
            except InvalidPointCloudError as exc:
                yield SkippedScan(index, _header_stamp(msg) or int(log_time), _describe(exc))
                continue
            self.n_dropped += cloud.n_dropped
            stamp = cloud.stamp_ns or log_time
            yield Scan(int(stamp), cloud.frame_id, cloud.points, cloud.extras)

    def _skip_error(self, entry: SkippedScan) -> KentRegError:
        return InvalidPointCloudError(
            f'{self.path}: message {entry.index} of {self.topic}: {entry.reason}'
        )


def _header_stamp(msg: Any) -> int:
    """A message's header stamp in ns (0 when it has none or it cannot be read)."""
    try:
        return stamp_to_ns(msg.header.stamp)
    except (AttributeError, TypeError, ValueError):
        return 0


class FilesScanSource(ScanSource):
    """Scan files in a given order, timed by a pose file or a rate.

    Parameters
    ----------
    files : sequence of str or Path
        Scan files (.pcd, .ply, .bin, .csv), in scan order.
    poses : Trajectory or str or Path, optional
        One pose per scan; its times stamp the scans unless ``rate`` is given.
    rate : float, optional
        Scan rate in Hz: stamps are ``start_ns + i / rate``. Default: the pose times, or
        10 Hz when there are none.
    start_ns : int
        First stamp when stamps come from ``rate``.
    frame_id : str
        Sensor frame given to every scan.
    fields, dtype
        As in :func:`~kentreg_ros.io.scanfiles.read_scan`.

    Raises
    ------
    PoseFileError
        The pose count differs from the scan count.
    """

    def __init__(
        self,
        files: Sequence[str | Path],
        *,
        poses: Trajectory | str | Path | None = None,
        rate: float | None = None,
        start_ns: int = 0,
        frame_id: str = 'lidar',
        fields: Sequence[str] | None = None,
        dtype: DTypeLike = np.float64,
    ) -> None:
        self.files = [Path(f) for f in files]
        if not self.files:
            raise ValueError('Expected at least one scan file.')
        self.path = self.files[0].parent
        self.trajectory = read_poses(poses) if isinstance(poses, str | Path) else poses
        if self.trajectory is not None and len(self.trajectory.T_world_sensor) != len(self.files):
            raise PoseFileError(
                f'{len(self.trajectory.T_world_sensor)} poses for {len(self.files)} scans in '
                f'{self.path}; give one pose per scan.'
            )
        if rate is not None and not rate > 0.0:
            raise ValueError(f'Expected `rate` > 0 Hz, got {rate!r}.')
        if rate is None and self.trajectory is not None and self.trajectory.stamps_ns is not None:
            self.stamps_ns = self.trajectory.stamps_ns.astype(np.int64)
            self.timing = 'pose file times'
        else:
            hz = DEFAULT_RATE_HZ if rate is None else float(rate)
            if start_ns < 0:
                raise ValueError(f'Expected `start_ns` >= 0, got {start_ns}.')
            steps = np.rint(np.arange(len(self.files)) * (1e9 / hz)).astype(np.int64)
            self.stamps_ns = int(start_ns) + steps
            self.timing = f'{hz:g} Hz'
            if rate is None:
                logger.info('No scan times given; stamping scans at %g Hz.', hz)
        self.frame_id = frame_id
        self.fields = fields
        self.dtype = dtype

    def __len__(self) -> int:
        return len(self.files)

    @property
    def description(self) -> str:
        return f'{len(self.files)} scan files in {self.path} ({self.timing})'

    def entries(self) -> Iterator[Scan | SkippedScan]:
        for index, (path, stamp) in enumerate(zip(self.files, self.stamps_ns, strict=True)):
            try:
                cloud = read_scan(path, fields=self.fields, dtype=self.dtype)
            except InvalidPointCloudError as exc:  # ScanFileError among them
                yield SkippedScan(index, int(stamp), _describe(exc))
                continue
            self.n_dropped += cloud.n_dropped
            yield Scan(int(stamp), self.frame_id, cloud.points, cloud.extras)

    def _skip_error(self, entry: SkippedScan) -> KentRegError:
        return ScanFileError(entry.reason)  # read_scan's message names the file


def open_scan_source(
    path: str | Path,
    *,
    topic: str | None = None,
    fields: Sequence[str] | None = None,
    dtype: DTypeLike = np.float64,
    poses: Trajectory | str | Path | None = None,
    rate: float | None = None,
    start_ns: int = 0,
    frame_id: str = 'lidar',
) -> ScanSource:
    """Open a bag, a scan folder or a single scan file as an iterable of :class:`Scan`.

    Parameters
    ----------
    path : str or Path
        A bag (``.bag``, ``.mcap``, ``.db3``, rosbag2 folder), a folder of scan files (natural
        order, see :func:`~kentreg_ros.io.scanfiles.list_scans`), or one scan file.
    topic : str, optional
        Bags only: the PointCloud2 topic, needed when there are several.
    fields : sequence of str, optional
        Extra fields to keep; None keeps all, ``()`` none.
    dtype : {numpy.float64, numpy.float32}
    poses, rate, start_ns, frame_id
        Scan files only; see :class:`FilesScanSource`.

    Returns
    -------
    ScanSource
        ``for stamp_ns, frame_id, points, extras in source: ...``

    Raises
    ------
    BagError, ScanFileError, PoseFileError
    """
    p = Path(path)
    if is_bag(p):
        if poses is not None or rate is not None:
            raise ValueError('`poses` and `rate` apply to scan files, not to bags.')
        return BagScanSource(p, topic, fields=fields, dtype=dtype)
    if topic is not None:
        raise ValueError(f'`topic` applies to bags; {p} is not a bag.')
    if p.is_dir():
        files = list_scans(p)
    elif p.is_file() and p.suffix.lower() in SCAN_SUFFIXES:
        files = [p]
    else:
        raise BagError(
            f'{p}: neither a bag ({", ".join(BAG_SUFFIXES)}, rosbag2 folder) nor a scan '
            f'folder or file ({", ".join(SCAN_SUFFIXES)}).'
        )
    return FilesScanSource(
        files,
        poses=poses,
        rate=rate,
        start_ns=start_ns,
        frame_id=frame_id,
        fields=fields,
        dtype=dtype,
    )


# --- ground truth ----------------------------------------------------------------------------


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


# --- recordings: scans and reference poses ------------------------------------------------------


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
                logger.log(level, 'No ground truth from the bag: %s', _describe(exc))
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
