"""Speed of kentreg_ros.io: PointCloud2 decoding, scan files, the sample bag.

Run from the repository root::

    python3 benchmarks/bench_io.py [--repeat 200]

Prints the best and median time of each operation (the best is the cost without interference
from other processes on a shared machine). The target from the I/O issue: decoding a 100k-point
PointCloud2 to an (N, 3) float array well under 5 ms.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.harness.datasets import SAMPLE_BAG, SHARED_DATA  # noqa: E402
from kentreg_ros.io.pointcloud2 import array_to_pointcloud2, pointcloud2_to_array  # noqa: E402
from kentreg_ros.io.scanfiles import read_pcd  # noqa: E402
from kentreg_ros.io.sources import open_scan_source  # noqa: E402


def _time(fn: Callable[[], Any], repeat: int) -> tuple[float, float]:
    fn()  # warm up
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times) * 1e3, statistics.median(times) * 1e3


def _ouster_like(n: int, rng: np.random.Generator) -> Any:
    """A 100k-point cloud laid out like an Ouster driver's: 48-byte padded points, 128 rows."""
    from kentreg_ros.io.pointcloud2 import rosbags_factory

    layout = np.dtype(
        {
            'names': ['x', 'y', 'z', 'intensity', 't', 'reflectivity', 'ring', 'ambient', 'range'],
            'formats': ['<f4', '<f4', '<f4', '<f4', '<u4', '<u2', '<u2', '<u2', '<u4'],
            'offsets': [0, 4, 8, 16, 20, 24, 26, 28, 32],
            'itemsize': 48,
        }
    )
    arr = np.zeros(n, layout)
    for c in 'xyz':
        arr[c] = rng.normal(scale=20, size=n)
    arr['x'][::50] = np.nan  # 2 % invalid returns, as an organised cloud has
    fac = rosbags_factory()
    codes = {'f4': 7, 'u4': 6, 'u2': 4}
    offsets = {name: spec[1] for name, spec in (layout.fields or {}).items()}
    fields = [
        fac.point_field(
            name=name, offset=offsets[name], datatype=codes[layout[name].str[1:]], count=1
        )
        for name in layout.names or ()
    ]
    height = 128
    return fac.point_cloud2(
        header=fac.header(stamp=fac.time(sec=0, nanosec=0), frame_id='os_lidar'),
        height=height,
        width=n // height,
        fields=fields,
        is_bigendian=False,
        point_step=48,
        row_step=48 * (n // height),
        data=arr.view(np.uint8),
        is_dense=False,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--repeat', type=int, default=200)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    n = 100_000
    rows = []

    packed = array_to_pointcloud2(
        rng.normal(scale=20, size=(n, 3)), extra={'intensity': rng.random(n).astype(np.float32)}
    )
    rows.append(
        (
            'PointCloud2 100k xyz+intensity (16 B) -> (N,3) float64, no extras',
            _time(lambda: pointcloud2_to_array(packed, fields=()), args.repeat),
        )
    )
    rows.append(
        (
            'PointCloud2 100k xyz+intensity (16 B) -> (N,3) float64 + intensity',
            _time(lambda: pointcloud2_to_array(packed), args.repeat),
        )
    )
    rows.append(
        (
            'PointCloud2 100k xyz+intensity (16 B) -> (N,3) float32, no extras',
            _time(lambda: pointcloud2_to_array(packed, fields=(), dtype=np.float32), args.repeat),
        )
    )
    ouster = _ouster_like(n - n % 128, rng)
    rows.append(
        (
            'PointCloud2 99,968 Ouster-like 48 B, 128 rows, 2 % NaN -> (N,3) + 6 fields',
            _time(lambda: pointcloud2_to_array(ouster), args.repeat),
        )
    )
    xyz = rng.normal(size=(n, 3))
    rows.append(
        (
            '(N,3) float64 100k -> PointCloud2 float32 (rosbags message)',
            _time(lambda: array_to_pointcloud2(xyz), args.repeat),
        )
    )
    balm = SHARED_DATA / 'balm' / 'full0.pcd'
    if balm.is_file():
        rows.append(
            (
                'read_pcd BALM full0.pcd (73,452 points, binary)',
                _time(lambda: read_pcd(balm), max(args.repeat // 10, 5)),
            )
        )
    bag = SAMPLE_BAG
    if bag.is_dir():
        rows.append(
            (
                'open_scan_source bags/balm_50: all 50 scans (zstd MCAP)',
                _time(lambda: list(open_scan_source(bag)), 3),
            )
        )
    width = max(len(name) for name, _ in rows)
    print(f'{"operation":<{width}}  {"best ms":>8}  {"median ms":>9}')
    for name, (best, median) in rows:
        print(f'{name:<{width}}  {best:8.3f}  {median:9.3f}')


if __name__ == '__main__':
    main()
