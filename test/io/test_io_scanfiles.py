"""Scan file readers: real PCD/PLY files, every PCD/PLY encoding, KITTI, ETH CSV, bad files."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from kentreg_ros.io.errors import ScanFileError
from kentreg_ros.io.ply import read_ply
from kentreg_ros.io.scanfiles import (
    list_scans,
    natural_key,
    read_eth_csv,
    read_kitti_bin,
    read_pcd,
    read_scan,
    write_pcd,
)

# Values read independently of kentreg_ros (struct.unpack on the raw files).
BALM_FULL0 = (
    73452,
    (-8.208431243896484, 0.8606574535369873, 8.384442329406738),
    8.0,
    (-22.212488174438477, -4.079528331756592, -1.8420984745025635),
    11.0,
)
BALM_FULL49 = (
    84855,
    (-4.034760475158691, 0.35834330320358276, 0.8068276643753052),
    229.0,
    (-3.505347967147827, -0.5166869759559631, 0.4386644661426544),
    313.0,
)
GICP_SOURCE = (
    69792,
    (0.004045109264552593, 2.5751945972442627, -1.5272173881530762),
    70.0,
    (-0.004093721974641085, 1.804250717163086, 0.3399392366409302),
    36.0,
)
GICP_TARGET = (
    69088,
    (0.0031398916617035866, 2.570034980773926, -1.5241568088531494),
    68.0,
    (-0.004370204173028469, 1.9261064529418945, 0.3628981113433838),
    36.0,
)


@pytest.mark.parametrize(('name', 'expected'), [('full0', BALM_FULL0), ('full49', BALM_FULL49)])
def test_read_real_balm_pcd(shared_data: Path, name: str, expected: tuple) -> None:
    count, first, first_i, last, last_i = expected
    cloud = read_pcd(shared_data / 'balm' / f'{name}.pcd')
    assert len(cloud) == count and cloud.n_dropped == 0
    assert list(cloud.extras) == ['intensity', 'normal_x', 'normal_y', 'normal_z', 'curvature']
    np.testing.assert_array_equal(cloud.points[0], first)
    np.testing.assert_array_equal(cloud.points[-1], last)
    assert cloud.extras['intensity'][0] == first_i and cloud.extras['intensity'][-1] == last_i


@pytest.mark.parametrize(('name', 'expected'), [('source', GICP_SOURCE), ('target', GICP_TARGET)])
def test_read_real_small_gicp_ply(shared_data: Path, name: str, expected: tuple) -> None:
    plyfile = pytest.importorskip('plyfile')
    count, first, first_i, last, last_i = expected
    path = shared_data / 'small_gicp_pair' / f'{name}.ply'
    cloud = read_ply(path)
    assert len(cloud) == count
    np.testing.assert_array_equal(cloud.points[0], first)
    np.testing.assert_array_equal(cloud.points[-1], last)
    intensity = cloud.extras['scalar_intensity']
    assert intensity[0] == first_i and intensity[-1] == last_i
    vertex = plyfile.PlyData.read(str(path))['vertex'].data
    np.testing.assert_array_equal(cloud.points, np.c_[vertex['x'], vertex['y'], vertex['z']])


def test_read_scan_dispatches_and_lists_real_folder(shared_data: Path) -> None:
    scans = list_scans(shared_data / 'balm')
    assert [p.name for p in scans[:12]] == [f'full{i}.pcd' for i in range(12)]
    assert len(scans) == 50  # alidarPose.csv is not a scan
    cloud = read_scan(scans[0], fields=('intensity',), dtype=np.float32)
    assert cloud.points.dtype == np.float32 and list(cloud.extras) == ['intensity']


def _cloud(n: int = 500, seed: int = 0) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    pts = rng.normal(scale=10, size=(n, 3)).astype(np.float32)
    extra = {
        'intensity': rng.random(n).astype(np.float32),
        'ring': rng.integers(0, 128, n).astype(np.uint16),
        'normal': rng.normal(size=(n, 3)).astype(np.float32),
        't': rng.random(n),
    }
    return pts, extra


@pytest.mark.parametrize('data', ['ascii', 'binary', 'binary_compressed'])
def test_pcd_roundtrip_every_encoding(tmp_path: Path, data: str) -> None:
    pytest.importorskip('lzf')
    pts, extra = _cloud()
    pts[7, 1] = np.nan
    path = tmp_path / f'{data}.pcd'
    write_pcd(path, pts, extra, data=data)
    cloud = read_pcd(path)
    keep = np.ones(len(pts), bool)
    keep[7] = False
    assert cloud.n_dropped == 1
    np.testing.assert_array_equal(cloud.points, pts[keep].astype(np.float64))
    assert cloud.extras['normal'].shape == (499, 3)
    for name, values in extra.items():
        np.testing.assert_array_equal(cloud.extras[name], values[keep])


def _pcd_header(
    fields: str,
    size: str,
    typ: str,
    count: str,
    n: int,
    data: str,
    *,
    width: int | None = None,
    height: int = 1,
) -> bytes:
    return (
        f'# .PCD v0.7\nVERSION 0.7\nFIELDS {fields}\nSIZE {size}\nTYPE {typ}\nCOUNT {count}\n'
        f'WIDTH {n if width is None else width}\nHEIGHT {height}\nVIEWPOINT 0 0 0 1 0 0 0\n'
        f'POINTS {n}\nDATA {data}\n'
    ).encode()


def test_pcd_binary_compressed_written_by_hand(tmp_path: Path) -> None:
    """Field-major (x..., y..., z..., rgb...) LZF block, as PCL writes it."""
    lzf = pytest.importorskip('lzf')
    rng = np.random.default_rng(8)
    x, y, z = (np.round(rng.normal(size=300), 2).astype('<f4') for _ in range(3))
    rgb = rng.integers(0, 2**24, 300).astype('<u4')
    plain = x.tobytes() + y.tobytes() + z.tobytes() + rgb.tobytes()
    packed = lzf.compress(plain)
    assert packed is not None and len(packed) < len(plain)
    head = _pcd_header('x y z rgb', '4 4 4 4', 'F F F U', '1 1 1 1', 300, 'binary_compressed')
    path = tmp_path / 'pcl.pcd'
    path.write_bytes(head + struct.pack('<II', len(packed), len(plain)) + packed)
    cloud = read_pcd(path)
    np.testing.assert_array_equal(cloud.points, np.c_[x, y, z])
    np.testing.assert_array_equal(cloud.extras['rgb'], rgb)


def test_pcd_ascii_organised_with_nans(tmp_path: Path) -> None:
    rows = ['1 2 3 10', 'nan nan nan 0', '4 5 6 11', '7 8 9 12', 'nan 1 1 0', '0 0 0 13']
    path = tmp_path / 'organised.pcd'
    head = _pcd_header(
        'x y z intensity', '4 4 4 2', 'F F F U', '1 1 1 1', 6, 'ascii', width=3, height=2
    )
    path.write_bytes(head + '\n'.join(rows).encode() + b'\n')
    cloud = read_pcd(path)
    assert cloud.n_dropped == 2
    np.testing.assert_array_equal(cloud.points, [[1, 2, 3], [4, 5, 6], [7, 8, 9], [0, 0, 0]])
    np.testing.assert_array_equal(cloud.extras['intensity'], [10, 11, 12, 13])
    assert cloud.extras['intensity'].dtype == np.uint16


def test_truncated_binary_pcd_raises(shared_data: Path, tmp_path: Path) -> None:
    raw = (shared_data / 'balm' / 'full0.pcd').read_bytes()
    path = tmp_path / 'cut.pcd'
    path.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(
        ScanFileError,
        match=r'cut.pcd: PCD binary data is truncated: \d+ bytes, '
        r'expected POINTS \* point size = 73452 \* 32',
    ):
        read_pcd(path)


def test_truncated_synthetic_pcds_raise(tmp_path: Path) -> None:
    pytest.importorskip('lzf')
    pts, _ = _cloud(50)
    for data, pattern in [
        ('binary', 'binary data is truncated'),
        ('binary_compressed', 'binary_compressed data is truncated'),
        ('ascii', 'ascii data has 49 rows of 3 values; header says POINTS 50'),
    ]:
        path = tmp_path / f'{data}.pcd'
        write_pcd(path, pts, data=data)
        raw = path.read_bytes()
        cut = raw.rstrip(b'\n').rfind(b'\n') + 1 if data == 'ascii' else len(raw) - 7
        path.write_bytes(raw[:cut])
        with pytest.raises(ScanFileError, match=pattern):
            read_pcd(path)


def test_pcd_header_count_errors(tmp_path: Path) -> None:
    body = np.zeros(12, '<f4').tobytes()
    cases = [
        (
            _pcd_header('x y z', '4 4 4', 'F F F', '1 1 1', 4, 'binary', width=3),
            r'WIDTH \* HEIGHT = 3 \* 1 = 3 but POINTS = 4',
        ),
        (
            _pcd_header('x y z', '4 4', 'F F F', '1 1 1', 4, 'binary'),
            r'FIELDS/SIZE/TYPE/COUNT differ in length \(3/2/3/3\)',
        ),
        (
            _pcd_header('x y z', '4 4 4', 'F F X', '1 1 1', 4, 'binary'),
            "field 'z' has unsupported TYPE X SIZE 4",
        ),
        (_pcd_header('x y w', '4 4 4', 'F F F', '1 1 1', 4, 'binary'), 'no z field'),
        (_pcd_header('x y z', '4 4 4', 'F F F', '1 1 1', 4, 'binary_lz4'), 'unknown PCD DATA'),
        (b'VERSION 0.7\nFIELDS x y z\n', 'no DATA line'),
    ]
    for i, (head, pattern) in enumerate(cases):
        path = tmp_path / f'bad{i}.pcd'
        path.write_bytes(head + body)
        with pytest.raises(ScanFileError, match=pattern):
            read_pcd(path)


def test_corrupt_lzf_raises(tmp_path: Path) -> None:
    head = _pcd_header('x y z', '4 4 4', 'F F F', '1 1 1', 4, 'binary_compressed')
    path = tmp_path / 'corrupt.pcd'
    path.write_bytes(head + struct.pack('<II', 10, 48) + b'\xff' * 10)
    with pytest.raises(ScanFileError, match='corrupt'):
        read_pcd(path)


@pytest.mark.parametrize('text', [True, False], ids=['ascii', 'binary_be'])
def test_ply_written_by_plyfile_with_faces(tmp_path: Path, text: bool) -> None:
    plyfile = pytest.importorskip('plyfile')
    rng = np.random.default_rng(9)
    vertex = np.zeros(40, [('x', 'f8'), ('y', 'f4'), ('z', 'f4'), ('red', 'u1'), ('q', 'i2')])
    for name in vertex.dtype.names:
        vertex[name] = rng.integers(0, 100, 40) if name in ('red', 'q') else rng.normal(size=40)
    faces = np.empty(2, dtype=[('vertex_indices', object)])
    faces['vertex_indices'] = [np.array([0, 1, 2]), np.array([3, 4, 5, 6])]
    path = tmp_path / 'mesh.ply'
    plyfile.PlyData(
        [
            plyfile.PlyElement.describe(vertex, 'vertex'),
            plyfile.PlyElement.describe(faces, 'face'),
        ],
        text=text,
        byte_order='>',
    ).write(str(path))
    cloud = read_ply(path)
    np.testing.assert_array_equal(cloud.points, np.c_[vertex['x'], vertex['y'], vertex['z']])
    np.testing.assert_array_equal(cloud.extras['red'], vertex['red'])
    assert cloud.extras['q'].dtype == np.int16


def test_ply_errors(tmp_path: Path) -> None:
    head = b'ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\n'
    cases = [
        (
            head + b'property float y\nproperty float z\nend_header\n' + bytes(100),
            r'PLY binary vertex data is truncated: 100 bytes, expected 10 \* 12 = 120',
        ),
        (head + b'property float y\nend_header\n' + bytes(80), 'no z field'),
        (head + b'property quad y\nend_header\n', "'y' has unknown type 'quad'"),
        (
            b'ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n'
            b'property float z\nend_header\n1 2 3\n4 5 6\n',
            'truncated: 2 of 3 rows',
        ),
        (b'ply\nformat binary_little_endian 1.0\nelement face 1\n', 'no end_header'),
        (b'PK\x03\x04', 'not a PLY file'),
    ]
    for i, (raw, pattern) in enumerate(cases):
        path = tmp_path / f'bad{i}.ply'
        path.write_bytes(raw)
        with pytest.raises(ScanFileError, match=pattern):
            read_ply(path)


def test_kitti_bin(tmp_path: Path) -> None:
    rng = np.random.default_rng(10)
    records = rng.normal(size=(1000, 4)).astype('<f4')
    path = tmp_path / '000000.bin'
    records.tofile(path)
    cloud = read_scan(path)
    np.testing.assert_array_equal(cloud.points, records[:, :3])
    np.testing.assert_array_equal(cloud.extras['intensity'], records[:, 3])
    path.write_bytes(records.tobytes()[:-6])
    with pytest.raises(ScanFileError, match='not a multiple of 16 bytes'):
        read_kitti_bin(path)


def test_eth_csv(tmp_path: Path) -> None:
    path = tmp_path / 'Hokuyo_0.csv'
    path.write_text(
        'timestamp, x, y, z, intensity\n1.5, 1, 2, 3, 0.5\n1.5, 4, 5, 6, 0.7\n'
        '1.5, nan, 5, 6, 0.1\n'
    )
    cloud = read_scan(path)
    np.testing.assert_array_equal(cloud.points, [[1, 2, 3], [4, 5, 6]])
    assert cloud.n_dropped == 1 and list(cloud.extras) == ['timestamp', 'intensity']
    path.write_text('timestamp, x, y, z\n1, 2, 3\n')
    with pytest.raises(ScanFileError, match='rows have 3 values, header names 4'):
        read_eth_csv(path)
    path.write_text('a, b, c\n1, 2, 3\n')
    with pytest.raises(ScanFileError, match='must name x, y and z'):
        read_eth_csv(path)


def test_list_scans_natural_order_and_errors(tmp_path: Path) -> None:
    for i in (10, 2, 0, 1, 11):
        (tmp_path / f'full{i}.pcd').write_bytes(b'')
    (tmp_path / 'alidarPose.csv').write_text('')
    (tmp_path / 'notes.txt').write_text('')
    assert [p.name for p in list_scans(tmp_path)] == [
        'full0.pcd',
        'full1.pcd',
        'full2.pcd',
        'full10.pcd',
        'full11.pcd',
    ]
    assert sorted(['scan_b2', 'scan_a10', 'scan_a9'], key=natural_key) == [
        'scan_a9',
        'scan_a10',
        'scan_b2',
    ]
    (tmp_path / 'extra.ply').write_bytes(b'')
    with pytest.raises(ScanFileError, match=r'mixes scan formats \(5 .pcd, 1 .ply\)'):
        list_scans(tmp_path)
    assert len(list_scans(tmp_path, suffixes=['.ply'])) == 1
    with pytest.raises(ScanFileError, match='missing: not a folder'):
        list_scans(tmp_path / 'missing')
    with pytest.raises(ScanFileError, match='no scan files'):
        list_scans(tmp_path, suffixes=['.bin'])
    with pytest.raises(ScanFileError, match="unknown scan format '.las'"):
        read_scan(tmp_path / 'x.las')
