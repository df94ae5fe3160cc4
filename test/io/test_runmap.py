"""kentreg_ros.io.runmap: the map of a run (one per voxel, first point wins, bounded) and its
trajectory, against a brute-force reference."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from kentreg_ros.core import InvalidInputError, exp_so3, make_transform
from kentreg_ros.io.poses import read_tum_poses
from kentreg_ros.io.runmap import RunMap, TrajectoryLog, save_run


def _reference(batches: list[np.ndarray], voxel: float) -> np.ndarray:
    """The first point of every voxel, in arrival order, by a dictionary."""
    seen: dict[tuple[int, int, int], np.ndarray] = {}
    for batch in batches:
        for p in batch:
            seen.setdefault(tuple(np.floor(p / voxel).astype(int)), p)
    return np.array(list(seen.values()))


def test_the_map_keeps_the_first_point_of_every_voxel_across_scans() -> None:
    rng = np.random.default_rng(0)
    voxel = 0.5
    batches = [rng.uniform(-5, 5, size=(400, 3)) + [0.3 * k, 0, 0] for k in range(30)]
    m = RunMap(voxel)
    for b in batches:
        m.add(b)
    expected = _reference(batches, voxel)
    got = m.points
    assert len(m) == len(got) == len(expected)
    # Same points (float32), in the order they were added.
    np.testing.assert_allclose(got, expected, atol=1e-5)
    # Log-structured keys: few sorted runs, never one per scan.
    assert len(m._runs) <= int(np.log2(len(m))) + 1


def test_points_are_moved_by_the_pose_given() -> None:
    T = make_transform(exp_so3(np.array([0.0, 0.2, 1.0])), np.array([4.0, -2.0, 1.0]))
    pts = np.random.default_rng(1).uniform(-1, 1, size=(50, 3)) * 10
    m = RunMap(0.01)
    assert m.add(pts, T) == 50
    np.testing.assert_allclose(m.points, pts @ T[:3, :3].T + T[:3, 3], atol=1e-5)


def test_the_map_coarsens_instead_of_growing_past_its_bound(
    caplog: pytest.LogCaptureFixture,
) -> None:
    rng = np.random.default_rng(2)
    m = RunMap(0.1, max_points=5000)
    for k in range(20):
        m.add(rng.uniform(0, 20, size=(2000, 3)) * [1, 1, 0.05] + [20 * k, 0, 0])
    assert len(m) <= 5000 and m.n_coarsened >= 1
    assert m.voxel_size == pytest.approx(0.1 * 2**m.n_coarsened)
    # Still one point per (coarser) voxel, and still the whole run: the first scan's area too.
    cells = np.floor(m.points.astype(np.float64) / m.voxel_size)
    assert len(np.unique(cells, axis=0)) == len(m)
    assert m.points[:, 0].min() < 5.0 and m.points[:, 0].max() > 380.0
    assert 'voxel edge doubles' in caplog.text
    m.clear()
    assert len(m) == 0 and m.voxel_size == 0.1


def test_around_is_the_part_within_the_radius() -> None:
    pts = np.array([[0.0, 0, 0], [3.0, 0, 0], [0, 4.9, 0], [10.0, 0, 0]])
    m = RunMap(0.5)
    m.add(pts)
    np.testing.assert_allclose(m.around([0, 0, 0], 5.0), pts[:3])
    assert len(m.around([100, 0, 0], 1.0)) == 0


def test_far_points_are_dropped_and_counted_and_bad_arguments_refused() -> None:
    m = RunMap(0.01)
    assert m.add(np.array([[0.0, 0, 0], [1e9, 0, 0]])) == 1
    assert m.n_out_of_reach == 1
    with pytest.raises(InvalidInputError):
        RunMap(0.0)
    with pytest.raises(InvalidInputError):
        RunMap(0.1, max_points=0)


def test_reading_while_another_thread_adds_is_safe() -> None:
    m = RunMap(0.05)
    rng = np.random.default_rng(3)
    batches = [rng.uniform(-10, 10, size=(3000, 3)) for _ in range(40)]
    sizes: list[int] = []

    def reader() -> None:
        for _ in range(200):
            pts = m.points
            sizes.append(len(pts))
            assert np.isfinite(pts).all()

    t = threading.Thread(target=reader)
    t.start()
    for b in batches:
        m.add(b)
    t.join()
    assert sizes == sorted(sizes)  # never a torn read
    assert len(m) == len(_reference(batches, 0.05))


def test_trajectory_log_and_save_run(tmp_path: Path) -> None:
    log = TrajectoryLog()
    poses = [
        make_transform(exp_so3(np.array([0, 0, 0.01 * k])), np.array([k, 0, 0.0]))
        for k in range(600)
    ]
    for k, T in enumerate(poses):
        log.append(10**9 + k * 10**8, T)
    stamps, T_all = log.snapshot()
    assert len(log) == 600 and stamps[-1] == 10**9 + 599 * 10**8
    np.testing.assert_allclose(T_all, poses)
    assert len(log.snapshot(last=5)[0]) == 5
    saved = save_run(tmp_path / 'a' / 'b', np.ones((3, 3)), stamps, T_all, voxel_size=0.1)
    assert saved.map_path.is_file() and (saved.n_points, saved.n_poses) == (3, 600)
    back = read_tum_poses(saved.trajectory_path)
    np.testing.assert_allclose(back.T_world_sensor, T_all, atol=1e-6)
    np.testing.assert_array_equal(back.stamps_ns, stamps)
