"""Bags in, through rosbags (>= 0.11): one iterator for bags and scan folders alike.

Reading
    rosbag2 (``.db3`` or ``.mcap``, the file or its folder) and ROS 1 ``.bag`` files, through
    :class:`rosbags.highlevel.AnyReader` with the ROS 2 Jazzy typestore for bags that embed no
    message definitions. Scans are ``sensor_msgs/PointCloud2`` or Livox ``CustomMsg``
    (:mod:`kentreg_ros.io.livox`, decoded with the definition the bag carries checked); the
    scan topic is picked automatically when there is exactly one.
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

import logging
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import DTypeLike

from kentreg_ros.core import InvalidPointCloudError, KentRegError
from kentreg_ros.io.errors import BagError, describe_error
from kentreg_ros.io.livox import custom_msg_to_array, definition_problem, is_custom_msg
from kentreg_ros.io.pointcloud2 import (
    default_typestore,
    pointcloud2_to_array,
    stamp_to_ns,
)
from kentreg_ros.io.sources import Scan, ScanSource, SkippedScan

logger = logging.getLogger(__name__)

POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'
POSESTAMPED = 'geometry_msgs/msg/PoseStamped'
ODOMETRY = 'nav_msgs/msg/Odometry'
PATH = 'nav_msgs/msg/Path'
BAG_SUFFIXES = ('.bag', '.mcap', '.db3')


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
        #: A ROS 1 bag (its messages are in the ROS 1 wire format, not CDR).
        self.ros1 = False
        #: The message types as the bag defines them (rosbags' ``fielddefs``).
        self.fielddefs: Mapping[str, Any] = {}
        try:
            with self._reader() as reader:
                self.topics = {
                    name: BagTopic(name, info.msgtype or '?', int(info.msgcount))
                    for name, info in reader.topics.items()
                }
                self.ros1 = not reader.is2
                self.fielddefs = dict(reader.typestore.fielddefs)
        except BagError:
            raise
        except Exception as exc:  # rosbags raises many types for damaged files
            mcap_file = self._mcap_file()
            if mcap_file is None:
                raise BagError(f'{self.path}: cannot open bag ({describe_error(exc)}).') from exc
            logger.warning(
                '%s: rosbags cannot open it (%s); reading the MCAP records one by one.',
                self.path,
                describe_error(exc),
            )
            self.salvage = _McapSalvage(mcap_file)
            self.topics = self.salvage.topics
            self.fielddefs = dict(self.salvage.typestore.fielddefs)

    def _reader(self) -> Any:
        from rosbags.highlevel import AnyReader

        return AnyReader([self.target], default_typestore=default_typestore())

    def _mcap_file(self) -> Path | None:
        if self.target.is_file():
            return self.target if self.target.suffix.lower() == '.mcap' else None
        files = [f for f in _storage_files(self.target) if f.suffix.lower() == '.mcap']
        return files[0] if len(files) == 1 else None

    def messages(self, topic: str, *, raw: bool = False) -> Iterator[tuple[int, Any]]:
        """Yield ``(log_time_ns, message)`` of ``topic`` (the serialised bytes when ``raw``);
        raise BagError at a fault."""
        if self.salvage is not None:
            yield from self.salvage.messages(topic, raw=raw)
            return
        count = 0
        try:
            reader = self._reader()
            reader.open()
        except Exception as exc:
            raise BagError(f'{self.path}: cannot open bag ({describe_error(exc)}).') from exc
        try:
            connections = [c for c in reader.connections if c.topic == topic]
            stream = reader.messages(connections=connections)
            while True:
                try:
                    connection, log_time, data = next(stream)
                    msg = data if raw else reader.deserialize(data, connection.msgtype)
                except StopIteration:
                    return
                except Exception as exc:
                    raise BagError(
                        f'{self.path}: bag is corrupt after {count} message(s) of {topic} '
                        f'({describe_error(exc)}).'
                    ) from exc
                count += 1
                yield int(log_time), msg
        finally:
            try:
                reader.close()
            except Exception:  # closing a reader that failed mid-read may fail again
                logger.debug('%s: error while closing the reader.', self.path, exc_info=True)


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
                self.fault = describe_error(exc)

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
            return default_typestore()
        store = get_typestore(Stores.EMPTY)
        store.register(types)
        return store

    def messages(self, topic: str, *, raw: bool = False) -> Iterator[tuple[int, Any]]:
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
                msg = record.data if raw else self.typestore.deserialize_cdr(record.data, msgtype)
            except Exception as exc:
                raise BagError(
                    f'{self.path}: message {count} of {topic} cannot be decoded '
                    f'({describe_error(exc)}).'
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


class BagScanSource(ScanSource):
    """The scans of one topic of a bag: ``sensor_msgs/PointCloud2`` or a Livox ``CustomMsg``
    (:data:`~kentreg_ros.io.livox.CUSTOM_MSG_TYPES`, decoded by
    :func:`~kentreg_ros.io.livox.custom_msg_to_array` once the definition the bag carries is
    found to be the driver's).

    Parameters
    ----------
    path : str or Path
        ``.bag``, ``.mcap``, ``.db3`` file, or rosbag2 folder.
    topic : str, optional
        The scan topic; needed only when the bag has more than one.
    fields : sequence of str, optional
        Extra fields to keep; None keeps all, ``()`` none.
    dtype : {numpy.float64, numpy.float32}

    Raises
    ------
    BagError
        Unreadable bag, no/ambiguous scan topic, a topic of another type, a CustomMsg defined
        otherwise than by Livox's drivers, no messages.
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
        clouds = [t.name for t in topics.values() if _is_scan_type(t.msgtype)]
        only_pc2 = all(topics[name].msgtype == POINTCLOUD2 for name in clouds)
        kind = POINTCLOUD2 if only_pc2 else 'point cloud'
        listed = f'{"PointCloud2" if only_pc2 else "point cloud"} topics: '
        listed += ', '.join(clouds) or 'none'
        if topic is None:
            if not clouds:
                raise BagError(
                    f'{self.path}: no {POINTCLOUD2} topic; topics: {_topics_text(topics)} '
                    '(scans are read from PointCloud2 and Livox CustomMsg topics).'
                )
            if len(clouds) > 1:
                raise BagError(
                    f'{self.path}: {len(clouds)} {kind} topics ({", ".join(clouds)}); '
                    'choose one with topic= (--topic on the command line).'
                )
            topic = clouds[0]
        elif topic not in topics:
            raise BagError(f'{self.path}: no topic {topic!r}; {listed}.')
        elif not _is_scan_type(topics[topic].msgtype):
            raise BagError(
                f'{self.path}: topic {topic} carries {topics[topic].msgtype}, not {POINTCLOUD2} '
                f'or a Livox CustomMsg; {listed}.'
            )
        msgtype = topics[topic].msgtype
        self.livox = is_custom_msg(msgtype)
        if self.livox:
            self._check_livox_definition(topic, msgtype)
        if topics[topic].count == 0:
            raise BagError(f'{self.path}: topic {topic} has no messages.')
        self.topic = topic

    def _check_livox_definition(self, topic: str, msgtype: str) -> None:
        if msgtype not in self._bag.fielddefs:
            # A rosbag2 recorded before Iron stores no definitions; the type's name is then all
            # there is, and the decoder's byte counts refuse another layout message by message.
            logger.info(
                "%s: the bag carries no definition of %s; reading it as Livox's driver "
                'defines it.',
                self.path,
                msgtype,
            )
            return
        problem = definition_problem(self._bag.fielddefs, msgtype)
        if problem is not None:
            raise BagError(
                f"{self.path}: topic {topic} carries {msgtype}, but not Livox's driver's: "
                f'{problem}.'
            )

    def __len__(self) -> int:
        return self._bag.topics[self.topic].count

    @property
    def description(self) -> str:
        kind = 'damaged MCAP' if self._bag.salvage is not None else 'bag'
        return f'{kind} {self.path} topic {self.topic} ({len(self)} messages)'

    def entries(self) -> Iterator[Scan | SkippedScan]:
        for index, (log_time, msg) in enumerate(self._bag.messages(self.topic, raw=self.livox)):
            try:
                if self.livox:
                    cloud = custom_msg_to_array(
                        msg, ros1=self._bag.ros1, fields=self.fields, dtype=self.dtype
                    )
                else:
                    cloud = pointcloud2_to_array(msg, fields=self.fields, dtype=self.dtype)
            except InvalidPointCloudError as exc:
                stamp = 0 if self.livox else _header_stamp(msg)
                yield SkippedScan(index, stamp or int(log_time), describe_error(exc))
                continue
            self.n_dropped += cloud.n_dropped
            stamp = cloud.stamp_ns or log_time
            yield Scan(int(stamp), cloud.frame_id, cloud.points, cloud.extras)

    def _skip_error(self, entry: SkippedScan) -> KentRegError:
        return InvalidPointCloudError(
            f'{self.path}: message {entry.index} of {self.topic}: {entry.reason}'
        )


def _is_scan_type(msgtype: str) -> bool:
    return msgtype == POINTCLOUD2 or is_custom_msg(msgtype)


def _header_stamp(msg: Any) -> int:
    """A message's header stamp in ns (0 when it has none or it cannot be read)."""
    try:
        return stamp_to_ns(msg.header.stamp)
    except (AttributeError, TypeError, ValueError):
        return 0


# --- ground truth ----------------------------------------------------------------------------


# --- recordings: scans and reference poses ------------------------------------------------------
