"""Building ``sensor_msgs/msg/PointCloud2`` messages from numpy arrays (the encoding half of
:mod:`kentreg_ros.io.pointcloud2`, which re-exports these names): a packed record of the
points and their extra fields, one PointField per field, for rclpy or rosbags messages alike.
"""

from __future__ import annotations

import array
import functools
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, DTypeLike, NDArray

from kentreg_ros.core import InvalidPointCloudError
from kentreg_ros.io.pointcloud2 import (
    _DTYPE_TO_DATATYPE,
    PADDING_FIELDS,
    ns_to_sec_nanosec,
)


@dataclass(frozen=True)
class MessageFactory:
    """Constructors of the messages :func:`array_to_pointcloud2` builds, for one ROS binding.

    Every callable takes keyword arguments named like the message fields; ``point_cloud2``
    receives ``data`` as a contiguous uint8 ndarray and stores it as its binding needs.
    Use :func:`rosbags_factory` (rosbags, the default) or :func:`rclpy_factory` (a node).
    """

    point_cloud2: Callable[..., Any]
    point_field: Callable[..., Any]
    header: Callable[..., Any]
    time: Callable[..., Any]


@functools.lru_cache(maxsize=4)
def default_typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def rosbags_factory(typestore: Any = None) -> MessageFactory:
    """Factory building rosbags messages (for bags), from ``typestore`` or ROS 2 Jazzy's."""
    store = default_typestore() if typestore is None else typestore
    types = store.types
    return MessageFactory(
        point_cloud2=types['sensor_msgs/msg/PointCloud2'],
        point_field=types['sensor_msgs/msg/PointField'],
        header=types['std_msgs/msg/Header'],
        time=types['builtin_interfaces/msg/Time'],
    )


def rclpy_factory(
    point_cloud2: type, point_field: type, header: type, time: type
) -> MessageFactory:
    """Factory building rclpy messages from the classes a node imports.

    Example: ``rclpy_factory(sensor_msgs.msg.PointCloud2, sensor_msgs.msg.PointField,
    std_msgs.msg.Header, builtin_interfaces.msg.Time)``. ``data`` is handed over as an
    ``array.array('B')``, the one type rclpy's setter takes without a per-byte check.
    """

    def make_cloud(*, data: NDArray[np.uint8], **kwargs: Any) -> Any:
        msg = point_cloud2(**kwargs)
        payload = array.array('B')
        payload.frombytes(data.tobytes())
        msg.data = payload
        return msg

    return MessageFactory(make_cloud, point_field, header, time)


def _pointfield_datatype(dtype: np.dtype[Any], name: str) -> int:
    code = _DTYPE_TO_DATATYPE.get((dtype.kind, dtype.itemsize))
    if code is None:
        raise InvalidPointCloudError(
            f'Field {name!r} has dtype {dtype}, which PointField cannot hold; cast it to one of '
            'int8, uint8, int16, uint16, int32, uint32, float32, float64.'
        )
    return code


def cloud_dtype(
    xyz_dtype: DTypeLike = np.float32,
    extra: Mapping[str, NDArray[Any]] | None = None,
    *,
    big_endian: bool = False,
) -> np.dtype[Any]:
    """Packed structured dtype ``x, y, z, <extra fields...>`` as :func:`array_to_pointcloud2`
    lays points out (no padding).
    """
    order: Literal['<', '>'] = '>' if big_endian else '<'
    base = np.dtype(xyz_dtype)
    _pointfield_datatype(base, 'x')
    descr: list[tuple[Any, ...]] = [(c, base.newbyteorder(order)) for c in 'xyz']
    for name, values in (extra or {}).items():
        if name in ('x', 'y', 'z') or name in PADDING_FIELDS:
            raise InvalidPointCloudError(f'Extra field name {name!r} is reserved.')
        dt = np.dtype(np.uint8) if values.dtype == np.bool_ else values.dtype
        _pointfield_datatype(dt, name)
        sub = values.shape[1:] if values.ndim > 1 else ()
        item = dt.newbyteorder(order)
        descr.append((name, item, sub) if sub else (name, item))
    return np.dtype(descr)


def _point_fields(dtype: np.dtype[Any], fac: MessageFactory) -> list[Any]:
    """The PointField messages describing the packed record ``dtype``."""
    out = []
    for name in dtype.names or ():
        fdt, offset = dtype.fields[name][:2]  # type: ignore[index]
        base, count = (fdt.base, int(np.prod(fdt.shape))) if fdt.shape else (fdt, 1)
        out.append(
            fac.point_field(
                name=name,
                offset=int(offset),
                datatype=_pointfield_datatype(base, name),
                count=count,
            )
        )
    return out


def array_to_pointcloud2(
    points: ArrayLike,
    *,
    extra: Mapping[str, ArrayLike] | None = None,
    frame_id: str = 'lidar',
    stamp_ns: int = 0,
    xyz_dtype: DTypeLike = np.float32,
    big_endian: bool = False,
    factory: MessageFactory | None = None,
) -> Any:
    """Build a PointCloud2 message from points and optional per-point fields.

    Parameters
    ----------
    points : array_like, shape (N, 3) or (H, W, 3)
        Coordinates; a 3-D array gives an organised cloud of height H. NaN/inf are kept (the
        message is then ``is_dense=False``).
    extra : dict of str to array_like, each shape (N,), (N, k), (H, W) or (H, W, k), optional
        Per-point fields in their own dtype (int8 ... float64; bool is stored as uint8); a
        trailing dimension k becomes a field with ``count=k``.
    frame_id : str
        Header frame.
    stamp_ns : int
        Header stamp in nanoseconds.
    xyz_dtype : dtype
        Type of x, y, z: float32 (default, what RViz and PCL expect) or any PointField type.
    big_endian : bool
        Write big-endian data (for tests of readers; ROS machines are little-endian).
    factory : MessageFactory, optional
        Message classes to build; default :func:`rosbags_factory` (needs rosbags).

    Returns
    -------
    PointCloud2
        Fields packed in the order x, y, z, extras (``point_step`` = sum of field sizes).

    Raises
    ------
    InvalidPointCloudError
        Wrong shapes, or a dtype PointField cannot hold.
    """
    pts = np.asarray(points)
    if pts.ndim not in (2, 3) or pts.shape[-1] != 3:
        raise InvalidPointCloudError(
            f'Expected `points` to have shape (N, 3) or (H, W, 3), got {pts.shape}.'
        )
    if pts.dtype.kind not in 'iuf':
        raise InvalidPointCloudError(f'Expected numeric `points`, got dtype {pts.dtype}.')
    grid = pts.shape[:-1] if pts.ndim == 3 else (1, pts.shape[0])
    height, width = int(grid[0]), int(grid[1])
    n = height * width
    extras: dict[str, NDArray[Any]] = {}
    for name, values in (extra or {}).items():
        arr = np.asarray(values)
        lead = pts.shape[:-1]
        if arr.shape[: len(lead)] != lead or arr.ndim > len(lead) + 1:
            raise InvalidPointCloudError(
                f'Expected extra field {name!r} to have shape {lead} or {lead + ("k",)}, '
                f'got {arr.shape}.'
            )
        extras[name] = arr.reshape((n,) + arr.shape[len(lead) :])
    dtype = cloud_dtype(xyz_dtype, extras, big_endian=big_endian)
    packed = np.empty(n, dtype)
    flat = pts.reshape(n, 3)
    for axis, c in enumerate('xyz'):
        packed[c] = flat[:, axis]
    for name, values in extras.items():
        packed[name] = values
    is_dense = True
    if np.dtype(xyz_dtype).kind == 'f' and n:
        is_dense = bool(
            np.isfinite(packed['x']).all()
            and np.isfinite(packed['y']).all()
            and np.isfinite(packed['z']).all()
        )
    fac = factory if factory is not None else rosbags_factory()
    fields_msg = _point_fields(dtype, fac)
    sec, nanosec = ns_to_sec_nanosec(stamp_ns)
    return fac.point_cloud2(
        header=fac.header(stamp=fac.time(sec=sec, nanosec=nanosec), frame_id=frame_id),
        height=height,
        width=width,
        fields=fields_msg,
        is_bigendian=bool(big_endian),
        point_step=dtype.itemsize,
        row_step=dtype.itemsize * width,
        data=packed.view(np.uint8).reshape(-1),
        is_dense=is_dense,
    )
