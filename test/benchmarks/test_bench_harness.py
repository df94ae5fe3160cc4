"""benchmarks/harness: the datasets registry, composed perturbations, the pipeline interface
and the renderer's table helpers (no Open3D, small_gicp or KISS-ICP needed)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from scenes import box_room, random_transform, transform_points  # noqa: E402

from benchmarks.harness import datasets, perturb, pipelines, report, runner  # noqa: E402
from benchmarks.harness.methods import RawMethod  # noqa: E402
from kentreg_ros.io.sources import Scan  # noqa: E402


def _scans(n: int) -> list[Scan]:
    rng = np.random.default_rng(3)
    return [Scan(i * 10**8, 'lidar', box_room(rng, 2000), {}) for i in range(n)]


def test_perturbations_compose_left_to_right() -> None:
    scans = _scans(9)
    both = perturb.compose(perturb.stride(3), perturb.raw_outliers(0.2, np.random.default_rng(0)))
    out = both(scans)
    assert [s.stamp_ns for s in out] == [0, 3 * 10**8, 6 * 10**8]
    kept = scans[::3]
    assert all(
        len(o.points) == len(s.points) + round(len(s.points) * 0.25)
        for o, s in zip(out, kept, strict=True)
    )
    with pytest.raises(ValueError, match='n'):
        perturb.stride(0)


def test_merge_joins_each_scan_with_its_predecessor_by_the_poses() -> None:
    world = box_room(np.random.default_rng(4), 3000)
    T = np.stack([np.eye(4), random_transform(np.random.default_rng(5), 5.0, 0.2)])
    scans = [
        Scan(i, 'lidar', transform_points(np.linalg.inv(Ti), world), {}) for i, Ti in enumerate(T)
    ]
    (merged,) = perturb.merge(2, T)(scans)
    assert len(merged.points) == 2 * len(world)
    np.testing.assert_allclose(merged.points[len(world) :], scans[1].points, atol=1e-9)
    np.testing.assert_allclose(merged.points[: len(world)], scans[1].points, atol=1e-9)


def test_scan_to_scan_chains_poses_and_counts_raised_steps() -> None:
    calls: list[int] = []

    def register(src: Any, tgt: Any, init: Any) -> tuple[np.ndarray, dict[str, Any]]:
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError('no convergence')
        step = np.eye(4)
        step[0, 3] = 1.0
        return step, {}

    method = RawMethod('step', lambda p: p, register, lambda prep: 0.1)
    run = runner.run_pipeline(lambda: pipelines.scan_to_scan(method), _scans(4))
    # Moves 1 m per scan; the raised second step repeats the last motion, as an odometry would.
    np.testing.assert_allclose(run.poses[:, 0, 3], [0.0, 1.0, 2.0, 3.0])
    assert run.health == {'n_raised': 1} and run.ms_per_scan.shape == (4,)


def test_make_pipeline_rejects_unknown_names_and_load_dataset_unknown_data() -> None:
    with pytest.raises(ValueError, match='Unknown pipeline'):
        pipelines.make_pipeline('icp_magic')
    with pytest.raises(ValueError, match='Unknown data set'):
        datasets.load_dataset('no_such_data_set')


def test_the_sample_bag_is_a_sequence_with_a_pose_per_scan() -> None:
    seq = datasets.load_dataset('balm_50')
    assert seq.T_world is not None and len(seq.T_world) == len(seq.scans) == 50
    np.testing.assert_allclose(seq.truth(3), np.linalg.inv(seq.T_world[3]) @ seq.T_world[4])
    np.testing.assert_allclose(seq.constant_velocity(4), seq.truth(3))


def test_table_and_cells_render_markdown_from_nested_results() -> None:
    entry = {'e_R_deg': {'median': 0.12345}, 'ate': None, 'ms': float('nan')}
    assert report.cells(entry, 'e_R_deg.median:.3f', 'ate.rmse:.2f', 'ms:.0f') == [
        '0.123',
        '–',
        '–',
    ]
    assert report.table('a | b', [[1, 2]]) == ['| a | b |', '|---|---|', '| 1 | 2 |']


def test_map_consistent_poses_pull_a_noisy_reference_onto_the_scenes_truth() -> None:
    # Six views of one room (each its own noise draw) at known poses; the reference handed in
    # is off by 1.5-3 cm and 0.3-0.6 deg per pose. The first pose is the gauge (kept exactly).
    pytest.importorskip('small_gicp')
    from benchmarks.harness.consistent import map_consistent_poses

    rng = np.random.default_rng(11)
    room = box_room(np.random.default_rng(2), 20000, noise=0.0)
    truth = np.stack([np.eye(4)] + [random_transform(rng, 10.0, 0.5) for _ in range(5)])
    clouds = [
        transform_points(np.linalg.inv(T), room) + rng.normal(scale=0.005, size=room.shape)
        for T in truth
    ]
    noisy = truth.copy()
    for i in range(1, len(truth)):
        noisy[i] = truth[i] @ random_transform(
            rng, rng.uniform(0.3, 0.6), rng.uniform(0.015, 0.03)
        )
    out = map_consistent_poses(clouds, noisy, voxel=0.1)
    before = np.linalg.norm(noisy[1:, :3, 3] - truth[1:, :3, 3], axis=1)
    after = np.linalg.norm(out.poses[1:, :3, 3] - truth[1:, :3, 3], axis=1)
    assert before.min() > 0.014
    assert after.max() < 0.004, after
    np.testing.assert_allclose(out.poses[0], truth[0], atol=1e-12)
    assert out.converged and len(out.moved_m) < 12  # stopped because nothing moved
    with pytest.raises(ValueError, match='one pose per cloud'):
        map_consistent_poses(clouds[:2], noisy[:2])
