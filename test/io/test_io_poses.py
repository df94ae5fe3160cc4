"""Pose files: the real BALM file, KITTI/TUM/ETH round trips, exact times, bad files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kentreg_ros.io.errors import PoseFileError
from kentreg_ros.io.poses import (
    detect_pose_format,
    read_poses,
    seconds_to_ns,
    write_kitti,
    write_tum,
)


def _poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    T[:, :3, 3] = rng.normal(scale=5.0, size=(n, 3))
    return T


def test_read_real_balm_poses(shared_data: Path) -> None:
    path = shared_data / 'balm' / 'alidarPose.csv'
    assert detect_pose_format(path) == 'balm'
    stamps, T = read_poses(path)
    assert T.shape == (50, 4, 4) and stamps is not None and stamps.dtype == np.int64
    # Line 4 of the first and last pose: 0,0,0,1630577758.569490 / ...,1630577783.069794.
    assert stamps[0] == 1_630_577_758_569_490_000 and stamps[-1] == 1_630_577_783_069_794_000
    np.testing.assert_array_equal(
        T[0, :3],
        [
            [0.999997, 0.001400, 0.001959, -0.005801],
            [-0.001398, 0.999999, -0.000921, -0.005146],
            [-0.001960, 0.000919, 0.999998, -0.003052],
        ],
    )
    np.testing.assert_array_equal(T[-1, :3, 3], [3.462937, 8.477385, 0.090855])
    np.testing.assert_array_equal(T[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (50, 1)))
    assert np.all(np.diff(stamps) > 0)


def test_seconds_to_ns_is_exact() -> None:
    assert seconds_to_ns('1403636579.763555584') == 1_403_636_579_763_555_584
    assert seconds_to_ns(' 1630577758.569490 ') == 1_630_577_758_569_490_000
    assert seconds_to_ns('1.5e9') == 1_500_000_000 * 10**9
    with pytest.raises(ValueError, match='not a number'):
        seconds_to_ns('noon')


def test_tum_roundtrip_keeps_exact_stamps(tmp_path: Path) -> None:
    T = _poses(20)
    stamps = 1_403_636_579_763_555_584 + np.arange(20, dtype=np.int64) * 100_000_001
    path = tmp_path / 'traj.tum'
    write_tum(path, stamps, T)
    assert path.read_text().splitlines()[0].startswith('1403636579.763555584 ')
    assert detect_pose_format(path) == 'tum'
    back = read_poses(path)
    np.testing.assert_array_equal(back.stamps_ns, stamps)
    np.testing.assert_allclose(back.T_world_sensor, T, atol=1e-8)
    np.testing.assert_allclose(back.stamps, stamps / 1e9)


def test_kitti_roundtrip_with_times(tmp_path: Path) -> None:
    T = _poses(5, seed=1)
    path = tmp_path / '00.txt'
    write_kitti(path, T)
    assert detect_pose_format(path) == 'kitti'
    stamps, back = read_poses(path)
    assert stamps is None
    np.testing.assert_allclose(back, T, atol=1e-8)
    times = tmp_path / 'times.txt'
    times.write_text('0.000000e+00\n1.038200e-01\n2.072925e-01\n3.102800e-01\n4.133000e-01\n')
    timed = read_poses(path, times=times)
    assert timed.stamps_ns is not None and timed.stamps_ns[1] == 103_820_000
    times.write_text('0.0\n0.1\n')
    with pytest.raises(PoseFileError, match='2 times for 5 poses'):
        read_poses(path, times=times)


def test_eth_pose_file(tmp_path: Path) -> None:
    T = _poses(3, seed=2)
    lines = ['poseId, timestamp, ' + ', '.join(f'T{i}{j}' for i in range(4) for j in range(4))]
    for i, M in enumerate(T):
        lines.append(f'{i}, {1000 + i}.25, ' + ', '.join(f'{v:.17g}' for v in M.reshape(-1)))
    path = tmp_path / 'pose_scanner_leica.csv'
    path.write_text('\n'.join(lines) + '\n')
    stamps, back = read_poses(path)
    np.testing.assert_array_equal(stamps, [1000_250_000_000, 1001_250_000_000, 1002_250_000_000])
    np.testing.assert_array_equal(back, T)


def test_bad_pose_files_raise(tmp_path: Path) -> None:
    path = tmp_path / 'poses.txt'
    path.write_text('1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n')
    with pytest.raises(PoseFileError, match='line 2 .* has 11 values, expected 12'):
        read_poses(path, format='kitti')
    path.write_text('1 0 0 0 0 2 0 0 0 0 1 0\n')
    with pytest.raises(PoseFileError, match='pose 0 is not a rigid transform'):
        read_poses(path)
    path.write_text('0.0 0 0 0 0 0 0 2\n')
    with pytest.raises(PoseFileError, match='quaternion of pose 0 has norm 2'):
        read_poses(path, format='tum')
    balm = tmp_path / 'alidarPose.csv'
    balm.write_text('1,0,0,0,\n0,1,0,0,\n0,0,1,0,\n')
    with pytest.raises(PoseFileError, match='3 lines, not a multiple of 4'):
        read_poses(balm)
    path.write_text('1 2 3\n')
    with pytest.raises(PoseFileError, match='cannot tell the pose format'):
        read_poses(path)
    with pytest.raises(PoseFileError, match='cannot read'):
        read_poses(tmp_path / 'missing.txt', format='tum')


@pytest.mark.parametrize('name', ['poses_tum.txt', 'poses_kitti.txt'])
def test_a_kitti_layout_velodyne_folder_finds_the_pose_file_beside_it(
    tmp_path: Path, name: str
) -> None:
    """``<sequence>/velodyne/*.bin`` with the poses in ``<sequence>/`` (KITTI's layout, and the
    shared Livox sequences'): the replay given the ``velodyne`` folder evaluates without --gt."""
    from kentreg_ros.io.poses import pose_file_beside

    scans = tmp_path / 'seq' / 'velodyne'
    scans.mkdir(parents=True)
    assert pose_file_beside(scans) is None
    (tmp_path / 'seq' / name).write_text('')
    assert pose_file_beside(scans) == tmp_path / 'seq' / name
    other = tmp_path / 'seq' / 'lidar'  # only a folder named velodyne looks up a level
    other.mkdir()
    assert pose_file_beside(other) is None
