"""The benchmark baselines (NDT, correntropy ICP), the method registry and the data loaders."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from scenes import box_room, pose_errors, random_transform, transform_points  # noqa: E402

from benchmarks.harness.baselines.cicp import cicp_register, weighted_rigid_fit  # noqa: E402
from benchmarks.harness.baselines.ndt import (  # noqa: E402
    build_grid,
    gaussian_constants,
    ndt_derivatives,
    ndt_prepare,
    ndt_register,
)
from benchmarks.harness.datasets import load_eth  # noqa: E402
from benchmarks.harness.methods import (  # noqa: E402
    ALL_METHODS,
    kentreg_config,
    make_methods,
    voxel_downsample,
)
from benchmarks.harness.perturb import inject_free_voxel_outliers as inject_outliers  # noqa: E402
from benchmarks.harness.perturb import select_pairs  # noqa: E402
from benchmarks.harness.runner import summarize  # noqa: E402


@pytest.fixture(scope='module')
def room_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(source, target, T_target_source): a noisy room seen twice, 6 deg / 0.3 m apart."""
    rng = np.random.default_rng(7)
    target = voxel_downsample(box_room(rng, 30000), 0.15)
    T = random_transform(rng, 6.0, 0.3)
    source = transform_points(np.linalg.inv(T), target) + rng.normal(0, 0.005, target.shape)
    return source, target, T


def test_ndt_recovers_a_known_transform_of_a_room(
    room_pair: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> None:
    source, target, T = room_pair
    T_est = ndt_register(ndt_prepare(source), ndt_prepare(target), np.eye(4))
    e_R, e_t = pose_errors(T_est, T)
    assert e_R < 0.3
    assert e_t < 0.02


def test_cicp_recovers_a_known_transform_of_a_room(
    room_pair: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> None:
    source, target, T = room_pair
    T_est = cicp_register(source, target, np.eye(4))
    e_R, e_t = pose_errors(T_est, T)
    assert e_R < 0.3
    assert e_t < 0.02


def test_ndt_gradient_and_hessian_match_finite_differences() -> None:
    rng = np.random.default_rng(3)
    points = box_room(rng, 20000)
    grid = build_grid(points, 1.0)
    x = points[rng.choice(len(points), 2000, replace=False)] + rng.normal(0, 0.05, (2000, 3))
    x = x + np.array([0.05, -0.03, 0.02])
    frac = x - np.floor(x)
    x = x[((frac > 0.05) & (frac < 0.95)).all(axis=1)]  # no cell change within the steps below

    def score(delta: np.ndarray) -> float:
        from scipy.spatial.transform import Rotation

        y = x @ Rotation.from_rotvec(delta[3:]).as_matrix().T + delta[:3]
        return ndt_derivatives(grid, y)[0]

    _, gradient, hessian = ndt_derivatives(grid, x)
    h = 1e-4
    eye = np.eye(6) * h
    num_g = np.array([(score(eye[i]) - score(-eye[i])) / (2 * h) for i in range(6)])
    num_H = np.array(
        [
            [
                (
                    score(eye[i] + eye[j])
                    - score(eye[i] - eye[j])
                    - score(-eye[i] + eye[j])
                    + score(-eye[i] - eye[j])
                )
                / (4 * h * h)
                for j in range(6)
            ]
            for i in range(6)
        ]
    )
    assert np.abs(gradient - num_g).max() < 1e-4 * np.abs(gradient).max()
    assert np.abs(hessian - num_H).max() < 1e-3 * np.abs(hessian).max()


def test_ndt_constants_match_magnusson_for_a_one_metre_grid() -> None:
    d1, d2 = gaussian_constants(1.0, 0.55)
    assert d1 == pytest.approx(-2.2166, abs=1e-3)
    assert d2 == pytest.approx(0.4330, abs=1e-3)


def test_weighted_rigid_fit_is_exact_on_noise_free_points() -> None:
    rng = np.random.default_rng(1)
    x = rng.normal(size=(50, 3))
    T = random_transform(rng, 40.0, 2.0)
    T_est = weighted_rigid_fit(x, transform_points(T, x), rng.random(50) + 0.1)
    np.testing.assert_allclose(T_est, T, atol=1e-9)


def test_registry_methods_share_the_benchmark_api(
    room_pair: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> None:
    source, target, T = room_pair
    methods = make_methods(['ndt', 'cicp'], voxel=0.15, threads=None)
    assert [m.name for m in methods] == ['ndt', 'cicp']
    for m in methods:
        T_est = m.register(m.prepare(source), m.prepare(target), np.eye(4))
        assert T_est.shape == (4, 4)
        assert pose_errors(T_est, T)[0] < 0.3, m.name


def test_make_methods_rejects_unknown_names() -> None:
    with pytest.raises(ValueError, match='Unknown method'):
        make_methods(['icp_magic'], voxel=0.2, threads=None)


def test_kentreg_ablation_configs_change_exactly_their_switch() -> None:
    assert 'kentreg_robust-no_refine' in ALL_METHODS
    base = kentreg_config('kentreg_robust', 0.25).to_flat_dict()
    ablated = kentreg_config('kentreg_robust-no_refine', 0.25).to_flat_dict()
    assert {k for k in base if base[k] != ablated[k]} == {'refine.method'}
    assert base['preprocess.voxel_size'] == 0.25
    assert base['refine.max_correspondence_distance'] == pytest.approx(1.0)
    assert kentreg_config('kentreg_paper', 0.25).mode == 'paper'


def test_voxel_downsample_is_idempotent_at_the_same_voxel() -> None:
    rng = np.random.default_rng(2)
    once = voxel_downsample(box_room(rng, 5000), 0.2)
    np.testing.assert_allclose(voxel_downsample(once, 0.2), once)


def test_injected_outliers_reach_the_requested_share_of_downsampled_points() -> None:
    rng = np.random.default_rng(4)
    raw = box_room(rng, 40000)
    cloud, realised = inject_outliers(raw, 0.3, 0.2, np.random.default_rng(5))
    clean = voxel_downsample(raw, 0.2)
    assert realised == pytest.approx(0.3, abs=1e-3)
    assert len(cloud) == pytest.approx(len(clean) / (1 - realised), abs=1)
    same, _ = inject_outliers(raw, 0.3, 0.2, np.random.default_rng(5))
    np.testing.assert_array_equal(same, cloud)


def test_summary_counts_failures_and_raised_pairs() -> None:
    rows = [
        {'e_R_deg': 0.1, 'e_t_m': 0.01, 'ms': 10.0},
        {'e_R_deg': 3.0, 'e_t_m': 0.01, 'ms': 20.0},
        {'e_R_deg': 0.1, 'e_t_m': 0.5, 'ms': 30.0},
        {'e_R_deg': float('nan'), 'e_t_m': float('nan'), 'ms': float('nan')},
    ]
    s = summarize(rows)
    assert (s['failures'], s['n_errors'], s['n']) == (3, 1, 4)
    assert s['e_R_deg']['median'] == pytest.approx(0.1)
    assert select_pairs(49, 5) == [0, 12, 24, 36, 48]


def _write_eth_folder(folder: Path, poses: np.ndarray, scans: list[np.ndarray]) -> None:
    header = 'poseId, timestamp, ' + ', '.join(f'T{r}{c}' for r in range(4) for c in range(4))
    rows = [header]
    for i, T in enumerate(poses):
        rows.append(f'{i}, {1000 + i}, ' + ', '.join(f'{v:.12f}' for v in T.ravel()))
    (folder / 'pose_scanner_leica.csv').write_text('\n'.join(rows) + '\n')
    for i, pts in enumerate(scans):
        lines = ['timestamp, x, y, z']
        lines += [f'{i}, {p[0]:.9f}, {p[1]:.9f}, {p[2]:.9f}' for p in pts]
        (folder / f'Hokuyo_{i}.csv').write_text('\n'.join(lines) + '\n')


def test_load_eth_reads_scans_in_order_and_pair_motions(tmp_path: Path) -> None:
    rng = np.random.default_rng(6)
    poses = np.stack([np.eye(4)] + [random_transform(rng, 10.0, 1.0) for _ in range(10)])
    scans = [rng.normal(size=(20, 3)) for _ in range(11)]
    _write_eth_folder(tmp_path, poses, scans)
    (tmp_path / 'notes.csv').write_text('x, y, z\n1, 2, 3\n')
    seq = load_eth(tmp_path)
    assert [p.name for p in seq.paths][:3] == ['Hokuyo_0.csv', 'Hokuyo_1.csv', 'Hokuyo_2.csv']
    assert seq.paths[-1].name == 'Hokuyo_10.csv'
    assert seq.n_pairs == 10
    np.testing.assert_allclose(seq.truth(9), np.linalg.inv(poses[9]) @ poses[10], atol=1e-9)
    np.testing.assert_allclose(seq.constant_velocity(1), seq.truth(0))
    np.testing.assert_allclose(seq.raw(10), scans[10], atol=1e-8)


def test_load_eth_rejects_a_pose_count_mismatch(tmp_path: Path) -> None:
    rng = np.random.default_rng(8)
    _write_eth_folder(
        tmp_path, np.stack([np.eye(4)] * 3), [rng.normal(size=(5, 3)) for _ in range(2)]
    )
    with pytest.raises(ValueError, match='2 Hokuyo scans but 3 poses'):
        load_eth(tmp_path)
