"""PointCloud2 <-> numpy: every datatype, both byte orders, padding, organised clouds, errors."""

from __future__ import annotations

import array
import logging
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from kentreg_ros.core import InvalidPointCloudError
from kentreg_ros.io import pointcloud2 as pc2
from kentreg_ros.io.pointcloud2 import (
    array_to_pointcloud2,
    pointcloud2_to_array,
    rclpy_factory,
    rosbags_factory,
)

DTYPES = ['i1', 'u1', 'i2', 'u2', 'i4', 'u4', 'f4', 'f8']
CODES = dict(zip(DTYPES, range(1, 9), strict=True))


def _values(rng: np.random.Generator, dtype: str, shape: tuple[int, ...]) -> np.ndarray:
    dt = np.dtype(dtype)
    if dt.kind == 'f':
        return rng.normal(scale=20.0, size=shape).astype(dt)
    info = np.iinfo(dt)
    return rng.integers(info.min, info.max, size=shape, endpoint=True, dtype=dt)


def _message(
    arr: np.ndarray,
    *,
    big_endian: bool = False,
    row_pad: int = 0,
    is_dense: bool = False,
    stamp_ns: int = 1_700_000_000_123_456_789,
    fields: list[Any] | None = None,
) -> Any:
    """A rosbags PointCloud2 over a structured array (H, W) laid out exactly as given."""
    fac = rosbags_factory()
    height, width = arr.shape
    order = '>' if big_endian else '<'
    dtype = arr.dtype.newbyteorder(order)
    if fields is None:
        fields = []
        for name in dtype.names:
            fdt, offset = dtype.fields[name][:2]
            base, count = (fdt.base, int(np.prod(fdt.shape))) if fdt.shape else (fdt, 1)
            code = CODES[base.kind + str(base.itemsize)]
            fields.append(fac.point_field(name=name, offset=offset, datatype=code, count=count))
    rows = np.zeros((height, width * dtype.itemsize + row_pad), np.uint8)
    rows[:, : width * dtype.itemsize] = arr.astype(dtype).view(np.uint8).reshape(height, -1)
    sec, nsec = divmod(stamp_ns, 10**9)
    return fac.point_cloud2(
        header=fac.header(stamp=fac.time(sec=sec, nanosec=nsec), frame_id='os_lidar'),
        height=height,
        width=width,
        fields=fields,
        is_bigendian=big_endian,
        point_step=dtype.itemsize,
        row_step=rows.shape[1],
        data=rows.reshape(-1),
        is_dense=is_dense,
    )


@pytest.mark.parametrize('big_endian', [False, True], ids=['little', 'big'])
@pytest.mark.parametrize('dtype', DTYPES)
def test_roundtrip_every_datatype_and_byte_order(dtype: str, big_endian: bool) -> None:
    rng = np.random.default_rng(7)
    points = _values(rng, dtype, (257, 3))
    extra = {f'f_{d}': _values(rng, d, (257,)) for d in DTYPES}
    extra['rgb3'] = _values(rng, dtype, (257, 3))
    msg = array_to_pointcloud2(
        points, extra=extra, xyz_dtype=dtype, big_endian=big_endian, stamp_ns=42
    )
    assert msg.is_bigendian is big_endian
    assert [f.datatype for f in msg.fields[:3]] == [CODES[dtype]] * 3
    assert msg.fields[-1].count == 3
    wire = np.dtype(dtype).newbyteorder('>' if big_endian else '<')
    assert bytes(msg.data[: wire.itemsize]) == np.array(points[0, 0], wire).tobytes()
    cloud = pointcloud2_to_array(msg)
    np.testing.assert_array_equal(cloud.points, points.astype(np.float64))
    assert cloud.points.dtype == np.float64 and cloud.n_dropped == 0
    assert set(cloud.extras) == set(extra)
    for name, values in extra.items():
        assert cloud.extras[name].dtype == values.dtype.newbyteorder('=')
        np.testing.assert_array_equal(cloud.extras[name], values)
    assert cloud.stamp_ns == 42 and cloud.frame_id == 'lidar'


def test_padded_ouster_like_layout_with_row_padding() -> None:
    rng = np.random.default_rng(1)
    # Ouster-style point: x y z, 4 pad bytes, intensity, t, reflectivity, ring, ambient, range.
    layout = np.dtype(
        {
            'names': ['x', 'y', 'z', 'intensity', 't', 'reflectivity', 'ring', 'ambient', 'range'],
            'formats': ['<f4', '<f4', '<f4', '<f4', '<u4', '<u2', '<u2', '<u2', '<u4'],
            'offsets': [0, 4, 8, 16, 20, 24, 26, 28, 32],
            'itemsize': 48,
        }
    )
    arr = np.zeros((4, 64), layout)
    for name in layout.names:
        arr[name] = _values(rng, layout[name].str[1:], (4, 64))
    arr['x'][1, 3] = np.nan
    arr['z'][2, 10] = np.inf
    msg = _message(arr, row_pad=13)
    assert msg.row_step == 64 * 48 + 13
    cloud = pointcloud2_to_array(msg)
    keep = np.isfinite(np.stack([arr['x'], arr['y'], arr['z']], -1)).all(-1).reshape(-1)
    assert cloud.n_dropped == 2 and len(cloud) == 254
    expected = np.stack([arr[c].reshape(-1)[keep] for c in 'xyz'], -1).astype(np.float64)
    np.testing.assert_array_equal(cloud.points, expected)
    for name in ['intensity', 't', 'reflectivity', 'ring', 'ambient', 'range']:
        np.testing.assert_array_equal(cloud.extras[name], arr[name].reshape(-1)[keep])
    assert cloud.extras['t'].dtype == np.uint32
    assert cloud.frame_id == 'os_lidar' and cloud.stamp_ns == 1_700_000_000_123_456_789


def test_big_endian_padded_layout_with_scattered_mixed_xyz_types() -> None:
    layout = np.dtype(
        {
            'names': ['z', 'pad', 'x', 'y', 'time'],
            'formats': ['>i2', '>u1', '>f8', '>f4', '>f8'],
            'offsets': [0, 2, 4, 16, 24],
            'itemsize': 40,
        }
    )
    rng = np.random.default_rng(2)
    arr = np.zeros((1, 100), layout)
    for name in layout.names:
        arr[name] = _values(rng, layout[name].str[1:], (1, 100))
    fac = rosbags_factory()
    fields = [
        fac.point_field(name='z', offset=0, datatype=pc2.INT16, count=1),
        fac.point_field(name='_', offset=2, datatype=pc2.UINT8, count=1),  # PCL padding
        fac.point_field(name='x', offset=4, datatype=pc2.FLOAT64, count=1),
        fac.point_field(name='y', offset=16, datatype=pc2.FLOAT32, count=1),
        fac.point_field(name='time', offset=24, datatype=pc2.FLOAT64, count=1),
    ]
    cloud = pointcloud2_to_array(_message(arr, big_endian=True, fields=fields))
    np.testing.assert_array_equal(cloud.points[:, 0], arr['x'][0])
    np.testing.assert_array_equal(cloud.points[:, 1], arr['y'][0].astype(np.float64))
    np.testing.assert_array_equal(cloud.points[:, 2], arr['z'][0])
    assert list(cloud.extras) == ['time']
    np.testing.assert_array_equal(cloud.extras['time'], arr['time'][0])


def test_organised_cloud_with_nans_roundtrip() -> None:
    rng = np.random.default_rng(3)
    grid = rng.normal(size=(16, 32, 3))
    grid[0] = np.nan  # a whole ring without returns
    grid[5, ::3, 1] = np.nan
    grid[7, 4, 2] = -np.inf
    ring = np.repeat(np.arange(16, dtype=np.uint16)[:, None], 32, axis=1)
    msg = array_to_pointcloud2(grid, extra={'ring': ring}, xyz_dtype=np.float64)
    assert (msg.height, msg.width, msg.is_dense) == (16, 32, False)
    cloud = pointcloud2_to_array(msg)
    keep = np.isfinite(grid).all(-1).reshape(-1)
    assert cloud.n_dropped == int((~keep).sum()) == 32 + 11 + 1
    np.testing.assert_array_equal(cloud.points, grid.reshape(-1, 3)[keep])
    np.testing.assert_array_equal(cloud.extras['ring'], ring.reshape(-1)[keep])


def test_dense_cloud_is_marked_dense() -> None:
    msg = array_to_pointcloud2(np.ones((5, 3)))
    assert msg.is_dense is True


def test_is_dense_true_with_nans_is_cleaned_and_logged(caplog: pytest.LogCaptureFixture) -> None:
    arr = np.zeros((1, 6), np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4')]))
    arr['y'][0, 2] = np.nan
    pc2._warned_not_dense = False
    with caplog.at_level(logging.WARNING, logger='kentreg_ros.io.pointcloud2'):
        cloud = pointcloud2_to_array(_message(arr, is_dense=True))
    assert cloud.n_dropped == 1 and len(cloud) == 5
    assert 'is_dense=True' in caplog.text


def test_field_selection_and_float32_output() -> None:
    rng = np.random.default_rng(4)
    pts = rng.normal(size=(10, 3)).astype(np.float32)
    extra = {'intensity': rng.random(10).astype(np.float32), 'ring': np.arange(10, dtype='u2')}
    msg = array_to_pointcloud2(pts, extra=extra)
    assert pointcloud2_to_array(msg, fields=()).extras == {}
    only = pointcloud2_to_array(msg, fields=['ring'], dtype=np.float32)
    assert list(only.extras) == ['ring'] and only.points.dtype == np.float32
    np.testing.assert_array_equal(only.points, pts)
    with pytest.raises(InvalidPointCloudError, match="no field 'rgb'"):
        pointcloud2_to_array(msg, fields=['rgb'])


def test_empty_cloud() -> None:
    msg = array_to_pointcloud2(np.empty((0, 3)), extra={'intensity': np.empty(0, 'f4')})
    cloud = pointcloud2_to_array(msg)
    assert cloud.points.shape == (0, 3) and cloud.extras['intensity'].shape == (0,)


def _xyz_message(**overrides: Any) -> Any:
    msg = array_to_pointcloud2(np.arange(12, dtype=np.float32).reshape(4, 3))
    for key, value in overrides.items():
        setattr(msg, key, value)
    return msg


def test_missing_z_field_raises() -> None:
    msg = _xyz_message()
    msg.fields = msg.fields[:2]
    with pytest.raises(InvalidPointCloudError, match="no z field; its fields are \\['x', 'y'\\]"):
        pointcloud2_to_array(msg)


def test_data_length_mismatch_raises() -> None:
    msg = _xyz_message()
    msg.data = msg.data[:-1]
    with pytest.raises(InvalidPointCloudError, match=r'47 bytes; expected row_step \* height'):
        pointcloud2_to_array(msg)


def test_point_step_smaller_than_fields_raises() -> None:
    with pytest.raises(
        InvalidPointCloudError, match="point_step 8 is smaller than the fields: 'z'"
    ):
        pointcloud2_to_array(_xyz_message(point_step=8))


def test_unknown_datatype_raises() -> None:
    msg = _xyz_message()
    msg.fields[1].datatype = 9
    with pytest.raises(InvalidPointCloudError, match="'y' has unknown datatype 9"):
        pointcloud2_to_array(msg)


def test_row_step_smaller_than_points_raises() -> None:
    msg = _xyz_message(width=2, height=2, row_step=12, data=np.zeros(24, np.uint8))
    with pytest.raises(InvalidPointCloudError, match='row_step 12 is smaller than width'):
        pointcloud2_to_array(msg)


def test_duplicate_field_raises() -> None:
    msg = _xyz_message()
    msg.fields = [*msg.fields, msg.fields[0]]
    with pytest.raises(InvalidPointCloudError, match="'x' appears twice"):
        pointcloud2_to_array(msg)


def test_writer_rejects_bad_shapes_and_dtypes() -> None:
    with pytest.raises(InvalidPointCloudError, match=r'shape \(N, 3\) or \(H, W, 3\)'):
        array_to_pointcloud2(np.zeros((4, 2)))
    with pytest.raises(InvalidPointCloudError, match="'ring' to have shape"):
        array_to_pointcloud2(np.zeros((4, 3)), extra={'ring': np.zeros(5)})
    with pytest.raises(InvalidPointCloudError, match="'t' has dtype int64"):
        array_to_pointcloud2(np.zeros((4, 3)), extra={'t': np.zeros(4, np.int64)})


class _FakeRclpyCloud:
    """Mimics rclpy's PointCloud2: keyword constructor, ``data`` accepts array.array('B')."""

    def __init__(self, **kwargs: Any) -> None:
        self._data = array.array('B')
        for key, value in kwargs.items():
            setattr(self, key, value)

    @property
    def data(self) -> array.array:
        return self._data

    @data.setter
    def data(self, value: Any) -> None:
        if not isinstance(value, array.array):
            raise AssertionError('test double accepts only array.array, as rclpy fast path')
        self._data = value


def test_rclpy_style_messages_both_directions() -> None:
    def ns(**kw: Any) -> SimpleNamespace:
        return SimpleNamespace(**kw)

    factory = rclpy_factory(_FakeRclpyCloud, ns, ns, ns)
    rng = np.random.default_rng(5)
    pts = rng.normal(size=(50, 3)).astype(np.float32)
    msg = array_to_pointcloud2(
        pts,
        extra={'intensity': np.ones(50, 'f4')},
        frame_id='velodyne',
        stamp_ns=3 * 10**9 + 7,
        factory=factory,
    )
    assert isinstance(msg, _FakeRclpyCloud) and isinstance(msg.data, array.array)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (3, 7)
    cloud = pointcloud2_to_array(msg)
    np.testing.assert_array_equal(cloud.points, pts)
    assert cloud.frame_id == 'velodyne' and cloud.stamp_ns == 3 * 10**9 + 7
    # A message whose data is a plain list (hand-made) decodes too.
    msg.data = array.array('B', list(msg.data))
    listed = SimpleNamespace(**{k: getattr(msg, k) for k in vars(msg) if k != '_data'})
    listed.data = list(msg.data)
    np.testing.assert_array_equal(pointcloud2_to_array(listed).points, pts)
