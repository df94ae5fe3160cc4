"""``sensor_msgs/msg/PointCloud2`` <-> numpy, for rclpy and rosbags messages alike.

Both directions are vectorised with numpy structured dtypes: a message's ``data`` is viewed,
never copied point by point, and no Python loop runs over points. Messages are read by field
name only (``header``, ``height``, ``width``, ``fields``, ``is_bigendian``, ``point_step``,
``row_step``, ``data``, ``is_dense``), so rclpy messages, rosbags' message classes and any
look-alike work. This module never imports rclpy; rosbags is imported only when a rosbags
message is built.

Layout rules follow the message definition (REP/``sensor_msgs``): point ``(r, c)`` starts at byte
``r * row_step + c * point_step``; every field lies within ``point_step`` bytes; ``data`` holds
exactly ``row_step * height`` bytes. Organised clouds (``height > 1``) are flattened row-major.
Fields named ``''`` or ``'_'`` are padding (as PCL writes them) and are skipped.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np
from numpy.typing import DTypeLike, NDArray

from kentreg_ros.core import InvalidPointCloudError

# The per-point time fields moved to io/pointtimes; the node still imports them from here.
from kentreg_ros.io.pointtimes import (  # noqa: F401
    POINT_TIME_FIELDS,
    point_time_field,
    shift_point_times,
)

logger = logging.getLogger(__name__)

# sensor_msgs/msg/PointField datatype constants.
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)

#: PointField datatype -> numpy dtype (byte order chosen per message).
DATATYPES: Mapping[int, np.dtype[Any]] = {
    INT8: np.dtype('i1'),
    UINT8: np.dtype('u1'),
    INT16: np.dtype('i2'),
    UINT16: np.dtype('u2'),
    INT32: np.dtype('i4'),
    UINT32: np.dtype('u4'),
    FLOAT32: np.dtype('f4'),
    FLOAT64: np.dtype('f8'),
}
_DATATYPE_NAMES = {
    INT8: 'INT8',
    UINT8: 'UINT8',
    INT16: 'INT16',
    UINT16: 'UINT16',
    INT32: 'INT32',
    UINT32: 'UINT32',
    FLOAT32: 'FLOAT32',
    FLOAT64: 'FLOAT64',
}
_DTYPE_TO_DATATYPE = {(dt.kind, dt.itemsize): code for code, dt in DATATYPES.items()}
PADDING_FIELDS = frozenset({'', '_'})
_warned_not_dense = False


class TimeLike(Protocol):
    """``builtin_interfaces/msg/Time``."""

    sec: int
    nanosec: int


class HeaderLike(Protocol):
    """``std_msgs/msg/Header``."""

    stamp: TimeLike
    frame_id: str


class PointFieldLike(Protocol):
    """``sensor_msgs/msg/PointField``."""

    name: str
    offset: int
    datatype: int
    count: int


class PointCloud2Like(Protocol):
    """``sensor_msgs/msg/PointCloud2`` as rclpy and rosbags both provide it."""

    header: HeaderLike
    height: int
    width: int
    fields: Sequence[PointFieldLike]
    is_bigendian: bool
    point_step: int
    row_step: int
    data: Any
    is_dense: bool


@dataclass(frozen=True)
class CloudArrays:
    """Points of one cloud as arrays.

    Attributes
    ----------
    points : ndarray, shape (N, 3)
        Finite x, y, z (float64 unless another dtype was asked for), in the sensor frame.
    extras : dict of str to ndarray, each shape (N,) or (N, count)
        Every other field (intensity, ring, per-point time ``t``/``time``/``timestamp``, ...),
        in its own dtype (native byte order), aligned with ``points``.
    n_dropped : int
        Points removed because a coordinate was NaN or inf.
    stamp_ns : int or None
        Header stamp in nanoseconds (None when the source has no time, e.g. a scan file).
    frame_id : str
        Header frame (empty when unknown).
    """

    points: NDArray[np.floating[Any]]
    extras: dict[str, NDArray[Any]] = field(default_factory=dict)
    n_dropped: int = 0
    stamp_ns: int | None = None
    frame_id: str = ''

    def __len__(self) -> int:
        return len(self.points)


@dataclass(frozen=True)
class _Field:
    name: str
    offset: int
    dtype: np.dtype[Any]
    count: int


def stamp_to_ns(stamp: TimeLike) -> int:
    """Convert a ``builtin_interfaces/msg/Time`` to integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_sec_nanosec(stamp_ns: int) -> tuple[int, int]:
    """Split integer nanoseconds into ``(sec, nanosec)`` for a ``Time`` message."""
    stamp_ns = int(stamp_ns)
    if stamp_ns < 0:
        raise ValueError(f'Expected `stamp_ns` >= 0, got {stamp_ns}.')
    return divmod(stamp_ns, 1_000_000_000)


def _layout(
    fields: Sequence[PointFieldLike],
    point_step: int,
    big_endian: bool,
    wanted: Sequence[str] | None,
) -> tuple[dict[str, _Field], list[str]]:
    """The fields of a message by name (padding skipped) and the extra fields to decode (all
    but x, y, z when ``wanted`` is None), after checking every field's datatype and extent
    within ``point_step``, that x, y, z are there with one value each, and that every wanted
    field is.

    Raises
    ------
    InvalidPointCloudError
    """
    order: Literal['<', '>'] = '>' if big_endian else '<'
    layout: dict[str, _Field] = {}
    for f in fields:
        name = str(f.name)
        datatype = int(f.datatype)
        if datatype not in DATATYPES:
            raise InvalidPointCloudError(
                f'PointField {name!r} has unknown datatype {datatype}; expected 1 (INT8) to '
                '8 (FLOAT64).'
            )
        if name in PADDING_FIELDS:
            continue
        if name in layout:
            raise InvalidPointCloudError(f'PointField {name!r} appears twice.')
        # count 0 is written by some drivers for scalars; it means 1 for every reader we know.
        count = max(int(f.count), 1)
        offset = int(f.offset)
        dtype = DATATYPES[datatype].newbyteorder(order)
        end = offset + dtype.itemsize * count
        if offset < 0 or end > point_step:
            raise InvalidPointCloudError(
                f'point_step {point_step} is smaller than the fields: {name!r} '
                f'({_DATATYPE_NAMES[datatype]} x{count} at offset {offset}) ends at byte {end}.'
            )
        layout[name] = _Field(name, offset, dtype, count)
    missing = [c for c in 'xyz' if c not in layout]
    if missing:
        raise InvalidPointCloudError(
            f'PointCloud2 has no {"/".join(missing)} field; its fields are {sorted(layout)}.'
        )
    for c in 'xyz':
        if layout[c].count != 1:
            raise InvalidPointCloudError(
                f'PointField {c!r} has count {layout[c].count}; expected 1.'
            )
    if wanted is None:
        return layout, [n for n in layout if n not in ('x', 'y', 'z')]
    names = [str(n) for n in wanted if n not in ('x', 'y', 'z')]
    absent = [n for n in names if n not in layout]
    if absent:
        raise InvalidPointCloudError(
            f'PointCloud2 has no field {absent[0]!r}; its fields are {sorted(layout)}.'
        )
    return layout, names


def _data(data: Any, height: int, width: int, row_step: int, point_step: int) -> NDArray[np.uint8]:
    """The message's ``data`` as bytes (a view where it can be), after checking that it is
    ``row_step * height`` bytes and that its rows hold ``width`` points.

    Raises
    ------
    InvalidPointCloudError
    """
    if isinstance(data, np.ndarray):
        buf = np.ascontiguousarray(data).reshape(-1).view(np.uint8)
    else:
        try:
            buf = np.frombuffer(memoryview(data), dtype=np.uint8)
        except TypeError:
            # A plain list of ints (old rclpy versions, hand-made messages).
            buf = np.asarray(data, dtype=np.uint8).reshape(-1)
    size = buf.size
    if height < 0 or width < 0 or size != row_step * height:
        raise InvalidPointCloudError(
            f'PointCloud2 data has {size} bytes; expected row_step * height = '
            f'{row_step} * {height} = {row_step * height}.'
        )
    if height * width > 0 and row_step < width * point_step:
        raise InvalidPointCloudError(
            f'PointCloud2 row_step {row_step} is smaller than width * point_step = '
            f'{width} * {point_step} = {width * point_step}.'
        )
    return buf


def _xyz(
    layout: Mapping[str, Any],
    buf: NDArray[np.uint8],
    height: int,
    width: int,
    row_step: int,
    point_step: int,
    out_dtype: np.dtype[Any],
) -> NDArray[Any]:
    """The x, y, z of every point, shape (height * width, 3), in ``out_dtype``."""
    fx, fy, fz = layout['x'], layout['y'], layout['z']
    points = np.empty((height, width, 3), out_dtype)
    step = fx.dtype.itemsize
    if (
        fx.dtype == fy.dtype == fz.dtype
        and fy.offset == fx.offset + step
        and (fz.offset == fx.offset + 2 * step)
    ):
        # x, y, z adjacent and of one type (nearly every driver): one strided copy.
        points[...] = np.ndarray(
            (height, width, 3),
            fx.dtype,
            buffer=buf,
            offset=fx.offset,
            strides=(row_step, point_step, step),
        )
    else:
        for axis, f in enumerate((fx, fy, fz)):
            points[..., axis] = np.ndarray(
                (height, width),
                f.dtype,
                buffer=buf,
                offset=f.offset,
                strides=(row_step, point_step),
            )
    return points.reshape(height * width, 3)


def _field_values(
    f: Any,
    buf: NDArray[np.uint8],
    height: int,
    width: int,
    row_step: int,
    point_step: int,
    keep: NDArray[np.bool_] | None,
    kept: NDArray[np.intp],
) -> NDArray[Any]:
    """The values of one extra field for the points kept (all when ``keep`` is None), in
    native byte order."""
    n = height * width
    native = f.dtype.newbyteorder('=')
    shape: tuple[int, ...] = (height, width, f.count) if f.count > 1 else (height, width)
    strides = (row_step, point_step, f.dtype.itemsize)[: len(shape)]
    view = np.ndarray(shape, f.dtype, buffer=buf, offset=f.offset, strides=strides)
    if keep is None:
        values = np.empty(shape, native)
        values[...] = view
        return values.reshape((n,) + shape[2:])
    if row_step == width * point_step:  # gather the kept points straight from the data
        flat = np.ndarray(
            (n,) + shape[2:],
            f.dtype,
            buffer=buf,
            offset=f.offset,
            strides=(point_step,) + strides[2:],
        )
        return flat.take(kept, axis=0).astype(native, copy=False)
    # rows padded: no flat view of the data
    return view[keep.reshape(height, width)].astype(native, copy=False)


def pointcloud2_to_array(
    msg: PointCloud2Like,
    *,
    fields: Sequence[str] | None = None,
    dtype: DTypeLike = np.float64,
) -> CloudArrays:
    """Decode a PointCloud2 message into an (N, 3) array plus per-point extra fields.

    Parameters
    ----------
    msg : PointCloud2
        An rclpy ``sensor_msgs.msg.PointCloud2``, a rosbags message, or anything with the same
        field names.
    fields : sequence of str, optional
        Extra fields to return. None (default) returns every field other than x, y, z; an empty
        sequence returns none (fastest). A named field that is absent raises.
    dtype : {numpy.float64, numpy.float32}
        dtype of the returned points.

    Returns
    -------
    CloudArrays
        ``points`` (N, 3) with the non-finite points dropped (``n_dropped`` counts them),
        ``extras`` aligned with ``points``, ``stamp_ns`` and ``frame_id`` from the header.

    Raises
    ------
    InvalidPointCloudError
        Missing x/y/z, a requested field absent, unknown datatype, a field beyond
        ``point_step``, ``row_step < width * point_step``, or ``len(data) != row_step * height``.

    Notes
    -----
    NaN/inf points are always looked for, whatever ``is_dense`` says: a message claiming
    ``is_dense=True`` that holds non-finite points is logged once as a warning and cleaned.
    Integer coordinates cannot be non-finite and skip the check.
    """
    global _warned_not_dense
    out_dtype = np.dtype(dtype)
    if out_dtype not in (np.dtype(np.float64), np.dtype(np.float32)):
        raise ValueError(f'Expected `dtype` float64 or float32, got {out_dtype}.')
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    layout, extra_names = _layout(msg.fields, point_step, bool(msg.is_bigendian), fields)
    buf = _data(msg.data, height, width, row_step, point_step)
    n = height * width
    stamp_ns = stamp_to_ns(msg.header.stamp)
    frame_id = str(msg.header.frame_id)
    if n == 0:
        extras = {
            name: np.empty(
                (0,) + ((layout[name].count,) if layout[name].count > 1 else ()),
                layout[name].dtype.newbyteorder('='),
            )
            for name in extra_names
        }
        return CloudArrays(np.empty((0, 3), out_dtype), extras, 0, stamp_ns, frame_id)

    points = _xyz(layout, buf, height, width, row_step, point_step, out_dtype)
    n_dropped = 0
    keep: NDArray[np.bool_] | None = None
    kept: NDArray[np.intp] = np.empty(0, np.intp)
    floats = 'f' in (layout['x'].dtype.kind, layout['y'].dtype.kind, layout['z'].dtype.kind)
    # One contiguous pass for the common all-finite case; column-wise otherwise (much faster
    # than .all(axis=1) on an (N, 3) array).
    if floats and not np.isfinite(points).all():
        keep = np.isfinite(points[:, 0])
        keep &= np.isfinite(points[:, 1])
        keep &= np.isfinite(points[:, 2])
        n_dropped = n - int(np.count_nonzero(keep))
        kept = np.flatnonzero(keep)
        points = points.take(kept, axis=0)  # take() is ~4x faster than boolean indexing
        if bool(msg.is_dense):
            level = logging.DEBUG if _warned_not_dense else logging.WARNING
            _warned_not_dense = True
            logger.log(
                level,
                'PointCloud2 in frame %r claims is_dense=True but has %d non-finite point(s); '
                'dropped them.',
                frame_id,
                n_dropped,
            )

    extras = {
        name: _field_values(layout[name], buf, height, width, row_step, point_step, keep, kept)
        for name in extra_names
    }
    return CloudArrays(points, extras, n_dropped, stamp_ns, frame_id)


# The encoding half lives in io/pointcloud2_encode; this module is the one place both are
# imported from (it needs the datatype tables above, hence at the end).
from kentreg_ros.io.pointcloud2_encode import (  # noqa: E402
    MessageFactory,
    array_to_pointcloud2,
    cloud_dtype,
    default_typestore,
    rclpy_factory,
    rosbags_factory,
)

__all__ = [
    'DATATYPES',
    'PADDING_FIELDS',
    'POINT_TIME_FIELDS',
    'CloudArrays',
    'MessageFactory',
    'array_to_pointcloud2',
    'cloud_dtype',
    'default_typestore',
    'ns_to_sec_nanosec',
    'point_time_field',
    'pointcloud2_to_array',
    'rclpy_factory',
    'rosbags_factory',
    'shift_point_times',
    'stamp_to_ns',
]
