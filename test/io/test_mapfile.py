"""Tests of kentreg_ros.io.mapfile: the map of a run as PLY or PCD, read back independently."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from optional import import_open3d
from scenes import read_ply_xyz

from kentreg_ros.core import InvalidPointCloudError
from kentreg_ros.io.errors import ScanFileError
from kentreg_ros.io.mapfile import write_map
from kentreg_ros.io.scanfiles import read_scan


@pytest.fixture
def points() -> np.ndarray:
    return np.random.default_rng(0).uniform(-50.0, 50.0, (1234, 3))


def test_write_map_ply_is_read_back_by_an_independent_reader(
    points: np.ndarray, tmp_path: Path
) -> None:
    path = tmp_path / 'map.ply'
    write_map(path, points)
    # float32 on disk: equal to the points rounded to float32.
    np.testing.assert_array_equal(read_ply_xyz(path), points.astype(np.float32))
    np.testing.assert_array_equal(read_scan(path).points, points.astype(np.float32))


def test_write_map_ply_opens_in_open3d(points: np.ndarray, tmp_path: Path) -> None:
    o3d = import_open3d()  # skips when Open3D is missing or cannot load
    path = tmp_path / 'map.ply'
    write_map(path, points)
    cloud = o3d.io.read_point_cloud(str(path))
    np.testing.assert_allclose(np.asarray(cloud.points), points, rtol=1e-6, atol=1e-5)


def test_write_map_pcd_round_trips(points: np.ndarray, tmp_path: Path) -> None:
    path = tmp_path / 'map.PCD'
    write_map(path, points)
    assert path.read_bytes().startswith(b'# .PCD v0.7')
    np.testing.assert_array_equal(read_scan(path).points, points.astype(np.float32))


def test_write_map_rejects_other_suffixes_and_bad_points(tmp_path: Path) -> None:
    with pytest.raises(ScanFileError, match=r"\.ply or \.pcd, got '\.xyz'"):
        write_map(tmp_path / 'map.xyz', np.zeros((3, 3)))
    with pytest.raises(InvalidPointCloudError, match=r'shape \(N, 3\)'):
        write_map(tmp_path / 'map.ply', np.zeros((3, 2)))
    assert not (tmp_path / 'map.ply').exists()
