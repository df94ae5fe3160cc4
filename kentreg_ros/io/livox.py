"""Livox ``CustomMsg`` -> numpy, read from bags without Livox's driver package.

Livox's ROS drivers publish a scan in one of two forms (``xfer_format`` in their launch files):

``0``: ``sensor_msgs/PointCloud2``
    livox_ros_driver2 packs ``x y z intensity`` (float32), ``tag line`` (uint8) and
    ``timestamp``, each point's absolute time in nanoseconds as a float64: 26 bytes a point, no
    padding (``timestamp`` sits at the unaligned offset 18); the header stamp is the first
    point's time. :func:`~kentreg_ros.io.pointcloud2.pointcloud2_to_array` reads it like any
    cloud, and the deskewing tells its nanoseconds from the absolute seconds Hesai and
    Robosense put in a float64 ``timestamp`` by their magnitude
    (:func:`~kentreg_ros.core.odometry.deskew.sweep_times`). This is the form ``kentreg_node``
    subscribes to. (The ROS 1 livox_ros_driver's PointCloud2 has no time field.)
``1``: ``livox_ros_driver2/msg/CustomMsg`` (ROS 1: ``livox_ros_driver/msg/CustomMsg``)
    What FAST-LIO and most Livox recordings use::

        std_msgs/Header header   # stamp: timebase (the driver sets it so)
        uint64 timebase          # the first point's time, ns
        uint32 point_num
        uint8 lidar_id
        uint8[3] rsvd
        CustomPoint[] points     # uint32 offset_time (ns from timebase), float32 x y z,
                                 # uint8 reflectivity tag line

    :func:`custom_msg_to_array` decodes it from its serialised bytes (CDR for rosbag2, the ROS 1
    wire format for ``.bag`` files): the points are a numpy view of the buffer (CDR aligns each
    20-byte point to 4 bytes; ROS 1 packs them in 19), never one Python object per point as a
    generic deserialiser makes (~25 ms for a 20k-point scan, before any conversion).

A bag carries the definitions of its message types (rosbag2: its metadata or MCAP schemas; ROS 1:
each connection's header), which rosbags registers when it opens the bag;
:func:`definition_problem` checks that the bag's CustomMsg is the layout decoded here (the
first livox_ros_driver had no ``offset_time``), so no Livox package is needed and a different
layout is refused, not misread. A live CustomMsg topic needs the Livox package's Python
message type, which is not on PyPI: :func:`live_custom_msg_hint` says what to do instead.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import DTypeLike, NDArray

from kentreg_ros.core import InvalidPointCloudError
from kentreg_ros.io.pointcloud2 import CloudArrays

#: Livox's point-cloud message types: livox_ros_driver2 (ROS 2, and ROS 1 builds of it),
#: livox_ros_driver (ROS 1) and livox_ros2_driver (``livox_interfaces``), one layout.
CUSTOM_MSG_TYPES = (
    'livox_ros_driver2/msg/CustomMsg',
    'livox_ros_driver/msg/CustomMsg',
    'livox_interfaces/msg/CustomMsg',
)
#: ``CustomMsg.msg`` as the drivers define it (comments left out).
CUSTOM_MSG_DEFINITION = """\
std_msgs/Header header
uint64 timebase
uint32 point_num
uint8 lidar_id
uint8[3] rsvd
CustomPoint[] points
"""
#: ``CustomPoint.msg`` as the drivers define it.
CUSTOM_POINT_DEFINITION = """\
uint32 offset_time
float32 x
float32 y
float32 z
uint8 reflectivity
uint8 tag
uint8 line
"""
#: The per-point fields of a CustomMsg besides x, y, z, as :func:`custom_msg_to_array` names
#: them; ``timestamp`` is derived (see there).
CUSTOM_POINT_FIELDS = ('offset_time', 'reflectivity', 'tag', 'line')

_MSG_FIELDS = (
    'header: std_msgs/msg/Header',
    'timebase: uint64',
    'point_num: uint32',
    'lidar_id: uint8',
    'rsvd: uint8[3]',
    'points: CustomPoint[]',
)
_POINT_FIELDS = (
    'offset_time: uint32',
    'x: float32',
    'y: float32',
    'z: float32',
    'reflectivity: uint8',
    'tag: uint8',
    'line: uint8',
)
#: Offsets of a point's fields from its start (the same in both wire formats).
_POINT_OFFSETS = (0, 4, 8, 12, 16, 17, 18)
_POINT_SIZE = 19
#: How far a header stamp may lie from ``timebase`` and still be it: livox_ros_driver stamps
#: ROS 1 headers with ``ros::Time(timebase / 1e9)``, a double of seconds (~0.2 us steps), and a
#: microsecond moves a point by a micrometre at 1 m/s.
STAMP_TOLERANCE_NS = 1_000
#: Bytes a CDR serialiser may append after the last point (padding to its alignment).
_MAX_CDR_PADDING = 7


def is_custom_msg(msgtype: str) -> bool:
    """True for a Livox point-cloud message type (:data:`CUSTOM_MSG_TYPES`)."""
    return msgtype in CUSTOM_MSG_TYPES


def custom_msg_types(package: str = 'livox_ros_driver2') -> dict[str, Any]:
    """rosbags type definitions of ``<package>/msg/CustomMsg`` and its ``CustomPoint``.

    Register them in a typestore to build or write such messages without the Livox package
    (``store.register(custom_msg_types())``). Reading a bag does not need them: the bag
    carries its own definitions.
    """
    from rosbags.typesys import get_types_from_msg

    types: dict[str, Any] = {}
    types.update(get_types_from_msg(CUSTOM_POINT_DEFINITION, f'{package}/msg/CustomPoint'))
    types.update(get_types_from_msg(CUSTOM_MSG_DEFINITION, f'{package}/msg/CustomMsg'))
    return types


def _type_text(node: tuple[Any, Any]) -> str:
    """One rosbags field type as msg syntax (``uint8[3]``, ``CustomPoint[]``)."""
    kind, detail = int(node[0]), node[1]
    if kind == 1:  # BASE: (name, string bound)
        return str(detail[0])
    if kind == 2:  # NAME: the full type name; CustomPoint's package varies with the driver
        name = str(detail)
        return 'CustomPoint' if name.endswith('/msg/CustomPoint') else name
    inner = _type_text(detail[0])
    return f'{inner}[{detail[1]}]' if kind == 3 else f'{inner}[]'  # ARRAY, SEQUENCE


def _fields_text(fielddefs: Mapping[str, Any], msgtype: str) -> tuple[str, ...]:
    return tuple(f'{name}: {_type_text(node)}' for name, node in fielddefs[msgtype][1])


def definition_problem(fielddefs: Mapping[str, Any], msgtype: str) -> str | None:
    """Why the definition of ``msgtype`` in ``fielddefs`` is not the layout
    :func:`custom_msg_to_array` decodes, or None when it is.

    Parameters
    ----------
    fielddefs : mapping
        A rosbags typestore's ``fielddefs`` (the types a bag carries, as rosbags registered
        them).
    msgtype : str
        A Livox CustomMsg type.

    Returns
    -------
    str or None
        What differs (or that the type is not defined: a rosbag2 recorded before Iron carries
        no definitions).
    """
    if msgtype not in fielddefs:
        return f'the bag does not define {msgtype}'
    got = _fields_text(fielddefs, msgtype)
    if got != _MSG_FIELDS:
        return f"its fields are {', '.join(got)}; the driver's are {', '.join(_MSG_FIELDS)}"
    point_type = str(fielddefs[msgtype][1][-1][1][1][0][1])
    if point_type not in fielddefs:
        return f'the bag does not define {point_type}'
    got = _fields_text(fielddefs, point_type)
    if got != _POINT_FIELDS:
        return (
            f"its CustomPoint fields are {', '.join(got)}; the driver's are "
            f'{", ".join(_POINT_FIELDS)}'
        )
    return None


def live_custom_msg_hint(topic: str, msgtype: str) -> str:
    """What to tell a user whose live input ``topic`` carries the Livox ``msgtype``."""
    return (
        f'{topic} carries {msgtype}, which this node cannot subscribe to: its Python message '
        "type comes only with Livox's driver package (not on PyPI). Set xfer_format to 0 in "
        "the driver's launch file: livox_ros_driver2 then publishes sensor_msgs/PointCloud2 "
        'with a per-point timestamp, which kentreg reads and deskews. A recorded CustomMsg '
        'bag runs offline as it is: kentreg_replay BAG --topic ' + topic
    )


@dataclass(frozen=True)
class _Head:
    """What precedes the points of a serialised CustomMsg, and where the points are."""

    stamp_ns: int
    frame_id: str
    timebase_ns: int
    point_num: int
    n_points: int
    offset: int  # of the first point, from the start of the buffer
    stride: int  # bytes from one point to the next
    order: Literal['<', '>']


class _Cursor:
    """Reads a serialised message front to back (CDR aligns to the size of what it reads,
    from the end of its 4-byte encapsulation header; ROS 1 does not align)."""

    def __init__(self, buf: bytes | memoryview, pos: int, order: str, align: bool) -> None:
        self.buf, self.pos, self.order, self.align = buf, pos, order, align
        self.origin = pos

    def take(self, fmt: str) -> tuple[Any, ...]:
        size = struct.calcsize(fmt)
        if self.align:
            pad = -(self.pos - self.origin) % struct.calcsize(fmt[0])
            self.pos += pad
        values = struct.unpack_from(self.order + fmt, self.buf, self.pos)
        self.pos += size
        return values

    def string(self, cdr: bool) -> str:
        (length,) = self.take('I')
        end = self.pos + length
        if end > len(self.buf):
            raise struct.error('string beyond the end')
        raw = bytes(self.buf[self.pos : end])
        self.pos = end
        return (raw[:-1] if cdr and raw.endswith(b'\0') else raw).decode('utf-8', 'replace')


def _read_head(buf: bytes | memoryview, ros1: bool) -> _Head:
    try:
        if ros1:
            cur = _Cursor(buf, 0, '<', align=False)
            cur.take('I')  # seq
            sec, nanosec = cur.take('II')
        else:
            kind = bytes(buf[:2])
            if kind not in (b'\x00\x01', b'\x00\x00'):
                raise InvalidPointCloudError(
                    f'CustomMsg is not CDR-encoded (encapsulation {kind.hex()}).'
                )
            cur = _Cursor(buf, 4, '<' if kind == b'\x00\x01' else '>', align=True)
            sec, nanosec = cur.take('iI')
        frame_id = cur.string(cdr=not ros1)
        (timebase,) = cur.take('Q')
        point_num, lidar_id = cur.take('IB')
        cur.take('BBB')  # rsvd
        (n_points,) = cur.take('I')
    except struct.error as exc:
        raise InvalidPointCloudError(
            f'CustomMsg of {len(buf)} bytes is truncated before its points ({exc}).'
        ) from exc
    order: Literal['<', '>'] = '<' if cur.order == '<' else '>'
    return _Head(
        stamp_ns=int(sec) * 1_000_000_000 + int(nanosec),
        frame_id=frame_id,
        timebase_ns=int(timebase),
        point_num=int(point_num),
        n_points=int(n_points),
        offset=cur.pos,
        stride=_POINT_SIZE if ros1 else 20,
        order=order,
    )


def _check_extent(head: _Head, size: int, ros1: bool) -> None:
    """Refuse a message whose bytes do not hold exactly ``point_num`` points after its head.

    Raises
    ------
    InvalidPointCloudError
        Truncated, bytes after the points (beyond CDR's alignment padding), or ``point_num``
        not the number of points the bytes hold.
    """
    n = head.n_points
    end = head.offset + (head.stride * (n - 1) + _POINT_SIZE if n else 0)
    if end > size:
        raise InvalidPointCloudError(
            f'CustomMsg of {size} bytes is truncated: its {n} points need {end}.'
        )
    if size - end > (0 if ros1 else _MAX_CDR_PADDING):
        raise InvalidPointCloudError(
            f'CustomMsg has {size - end} bytes after its {n} points: not the Livox layout.'
        )
    if head.point_num != n:
        raise InvalidPointCloudError(
            f'CustomMsg point_num is {head.point_num} but it holds {n} points.'
        )


def custom_msg_to_array(
    raw: bytes | memoryview,
    *,
    ros1: bool = False,
    fields: Sequence[str] | None = None,
    dtype: DTypeLike = np.float64,
) -> CloudArrays:
    """Decode a serialised Livox CustomMsg into an (N, 3) array plus per-point fields.

    Parameters
    ----------
    raw : bytes
        The message as a bag stores it: CDR (rosbag2), or the ROS 1 wire format (``ros1``).
    ros1 : bool
        ``raw`` comes from a ROS 1 ``.bag``.
    fields : sequence of str, optional
        Extra fields to return, among :data:`CUSTOM_POINT_FIELDS` and ``timestamp``
        (``timebase + offset_time``, float64 absolute ns); None (default) returns the former,
        and ``timestamp`` too for a header stamped otherwise (see below); an empty sequence
        none.
    dtype : {numpy.float64, numpy.float32}
        dtype of the returned points.

    Returns
    -------
    CloudArrays
        ``points`` (N, 3) with the non-finite points dropped (``n_dropped``), ``extras``
        aligned with them, ``stamp_ns`` (the header stamp, or ``timebase`` when the header has
        none) and ``frame_id``. The per-point times are ``offset_time`` (uint32 ns from
        ``timebase``) as the message has it, which the deskewing reads as nanoseconds from the
        stamp: the drivers stamp the header with ``timebase`` (the ROS 1 driver through a
        double of seconds, within :data:`STAMP_TOLERANCE_NS`). A header stamped otherwise
        (re-stamped downstream) also gets ``timestamp``, the absolute times, which the
        deskewing reads against the stamp instead, and refuses (not deskewing that scan, with a
        warning) when they are no sweep around it.

    Raises
    ------
    InvalidPointCloudError
        A truncated message, bytes after the points, ``point_num`` not the number of points,
        or a requested field it does not have.
    """
    out_dtype = np.dtype(dtype)
    if out_dtype not in (np.dtype(np.float64), np.dtype(np.float32)):
        raise ValueError(f'Expected `dtype` float64 or float32, got {out_dtype}.')
    names = _requested(fields)
    buf = memoryview(raw).cast('B') if not isinstance(raw, bytes) else raw
    head = _read_head(buf, ros1)
    _check_extent(head, len(buf), ros1)
    n = head.n_points
    stamp_ns = head.stamp_ns or head.timebase_ns
    o = head.order
    record = np.dtype(
        {
            'names': ['offset_time', 'x', 'y', 'z', 'reflectivity', 'tag', 'line'],
            'formats': [f'{o}u4', f'{o}f4', f'{o}f4', f'{o}f4', 'u1', 'u1', 'u1'],
            'offsets': list(_POINT_OFFSETS),
            'itemsize': _POINT_SIZE,
        }
    )
    points_view = np.ndarray((n,), record, buffer=buf, offset=head.offset, strides=(head.stride,))
    xyz = np.ndarray(
        (n, 3), f'{o}f4', buffer=buf, offset=head.offset + 4, strides=(head.stride, 4)
    ).astype(out_dtype)
    kept: NDArray[np.intp] | None = None
    n_dropped = 0
    if not np.isfinite(xyz).all():
        keep = np.isfinite(xyz[:, 0]) & np.isfinite(xyz[:, 1]) & np.isfinite(xyz[:, 2])
        kept = np.flatnonzero(keep)
        n_dropped = n - len(kept)
        xyz = xyz.take(kept, axis=0)
    base_ns = head.timebase_ns or stamp_ns  # what offset_time counts from
    if fields is None and abs(base_ns - stamp_ns) > STAMP_TOLERANCE_NS:
        names.append('timestamp')
    extras = _extras(points_view, kept, names, base_ns)
    return CloudArrays(xyz, extras, n_dropped, stamp_ns, head.frame_id)


def _requested(fields: Sequence[str] | None) -> list[str]:
    """The extra fields asked for (None: every field of a Livox point), after checking that a
    CustomMsg has them.

    Raises
    ------
    InvalidPointCloudError
    """
    names = list(CUSTOM_POINT_FIELDS) if fields is None else [str(f) for f in fields]
    unknown = [n for n in names if n not in (*CUSTOM_POINT_FIELDS, 'timestamp')]
    if unknown:
        raise InvalidPointCloudError(
            f'CustomMsg has no field {unknown[0]!r}; its fields are x, y, z, '
            f'{", ".join(CUSTOM_POINT_FIELDS)} (and timestamp, derived).'
        )
    return names


def _extras(
    records: NDArray[Any], kept: NDArray[np.intp] | None, names: list[str], base_ns: int
) -> dict[str, NDArray[Any]]:
    """The fields ``names`` of the points ``kept`` (all when None), as native copies;
    ``timestamp`` is ``base_ns + offset_time`` (float64 absolute ns)."""

    def column(name: str) -> NDArray[Any]:
        values = records[name]
        values = values if kept is None else values.take(kept)
        return np.array(values, dtype=values.dtype.newbyteorder('='))  # a copy, native

    extras: dict[str, NDArray[Any]] = {}
    for name in names:
        if name == 'timestamp':
            # livox_ros_driver2's PointCloud2 convention, and a type PointField has (a
            # player republishes it): 256 ns steps at 1.7e18, 0.3 um at 1 m/s.
            offsets = column('offset_time').astype(np.int64)
            extras[name] = (np.int64(base_ns) + offsets).astype(np.float64)
        else:
            extras[name] = column(name)
    return extras
