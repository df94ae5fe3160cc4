"""benchmarks/robustness.py and the harness perturbations: raw outliers, offsets, turns, report.

None of these tests needs Open3D, small_gicp or KISS-ICP (CI does not install them): the
bookkeeping is run with stand-in methods on a synthetic room.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from scenes import box_room, random_transform, transform_points  # noqa: E402

from benchmarks.harness.datasets import Sequence  # noqa: E402
from benchmarks.harness.methods import RawMethod  # noqa: E402
from benchmarks.harness.perturb import (  # noqa: E402
    draw_pairs,
    inject_raw_outliers,
    offset_transform,
    outlier_voxel_share,
    turn_transform,
)
from benchmarks.harness.runner import errors, failure_mask  # noqa: E402
from benchmarks.robustness import (  # noqa: E402
    markdown,
    plot,
    run_outliers,
    run_strides,
    run_turned,
)
from kentreg_ros.io.sources import Scan  # noqa: E402


@pytest.fixture(scope='module')
def raw_scan() -> np.ndarray:
    """A raw scan in the sensor frame: a room around the origin, 20,000 points."""
    return box_room(np.random.default_rng(1), 20000)


@pytest.mark.parametrize('fraction', [0.1, 0.2, 0.3, 0.4])
def test_raw_outliers_are_the_exact_share_inside_the_bounding_box(
    raw_scan: np.ndarray, fraction: float
) -> None:
    cloud, is_outlier = inject_raw_outliers(raw_scan, fraction, np.random.default_rng(2))
    n, k = len(raw_scan), int(is_outlier.sum())
    assert len(cloud) == n + k
    assert k == round(n * fraction / (1 - fraction))
    assert abs(k / len(cloud) - fraction) <= 0.5 / len(cloud)
    lo, hi = raw_scan.min(axis=0), raw_scan.max(axis=0)
    assert np.all((cloud[is_outlier] >= lo) & (cloud[is_outlier] <= hi))
    # The raw points are all kept, unchanged (the cloud is shuffled, not downsampled).
    kept = cloud[~is_outlier]
    np.testing.assert_array_equal(kept[np.lexsort(kept.T)], raw_scan[np.lexsort(raw_scan.T)])
    assert not np.all(is_outlier[-k:])  # interleaved, not appended


def test_raw_outliers_are_seeded_and_reproducible(raw_scan: np.ndarray) -> None:
    a, mask_a = inject_raw_outliers(raw_scan, 0.3, np.random.default_rng(5))
    b, mask_b = inject_raw_outliers(raw_scan, 0.3, np.random.default_rng(5))
    c, _ = inject_raw_outliers(raw_scan, 0.3, np.random.default_rng(6))
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(mask_a, mask_b)
    assert not np.array_equal(a, c)


def test_raw_outliers_in_the_range_shell_stay_within_the_scans_ranges(
    raw_scan: np.ndarray,
) -> None:
    cloud, is_outlier = inject_raw_outliers(
        raw_scan, 0.4, np.random.default_rng(3), shell_share=1.0
    )
    r = np.linalg.norm(raw_scan, axis=1)
    r_out = np.linalg.norm(cloud[is_outlier], axis=1)
    assert r.min() - 1e-9 <= r_out.min() and r_out.max() <= r.max() + 1e-9
    sin_el = raw_scan[:, 2] / r
    sin_out = cloud[is_outlier, 2] / r_out
    assert sin_el.min() - 1e-9 <= sin_out.min() and sin_out.max() <= sin_el.max() + 1e-9
    assert is_outlier.mean() == pytest.approx(0.4, abs=0.5 / len(cloud))
    half, mask = inject_raw_outliers(raw_scan, 0.4, np.random.default_rng(3), shell_share=0.5)
    lo, hi = raw_scan.min(axis=0), raw_scan.max(axis=0)
    inside = np.all((half[mask] >= lo) & (half[mask] <= hi), axis=1)
    assert inside.sum() >= round(mask.sum() * 0.5)  # the box half, plus shell points inside it


def test_raw_outliers_reject_bad_arguments(raw_scan: np.ndarray) -> None:
    rng = np.random.default_rng(0)
    cloud, mask = inject_raw_outliers(raw_scan, 0.0, rng)
    assert len(cloud) == len(raw_scan) and not mask.any()
    for bad in (-0.1, 1.0):
        with pytest.raises(ValueError, match='fraction'):
            inject_raw_outliers(raw_scan, bad, rng)
    with pytest.raises(ValueError, match='shell_share'):
        inject_raw_outliers(raw_scan, 0.1, rng, shell_share=1.5)
    with pytest.raises(ValueError, match='non-empty'):
        inject_raw_outliers(np.zeros((0, 3)), 0.1, rng)


def test_outlier_voxel_share_counts_voxels_holding_only_outliers() -> None:
    real = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [1.5, 0.1, 0.1]])
    outliers = np.array([[0.3, 0.3, 0.3], [5.5, 5.5, 5.5], [7.5, 0.5, 0.5], [7.6, 0.6, 0.6]])
    cloud = np.concatenate([real, outliers])
    mask = np.arange(len(cloud)) >= len(real)
    # Voxels of 1 m: (0,0,0) mixed, (1,0,0) real, (5,5,5) and (7,0,0) outliers only.
    assert outlier_voxel_share(cloud, mask, 1.0) == pytest.approx(0.5)


def test_offset_and_turn_have_exactly_the_stated_errors() -> None:
    T_true = random_transform(np.random.default_rng(8), 20.0, 1.0)
    start = T_true @ offset_transform(np.random.default_rng(9), 5.0, 0.2)
    assert errors(start, T_true) == pytest.approx((5.0, 0.2), abs=1e-9)
    T_turn = turn_transform(np.random.default_rng(10), 120.0)
    assert errors(T_turn, np.eye(4)) == pytest.approx((120.0, 0.0), abs=1e-9)


def test_pairs_are_drawn_without_replacement_and_seeded() -> None:
    pairs = draw_pairs(49, 20, 0, 2)
    assert len(set(pairs)) == 20 and all(0 <= p < 49 for p in pairs)
    assert pairs == draw_pairs(49, 20, 0, 2) != draw_pairs(49, 20, 1, 2)
    assert draw_pairs(49, 100, 0, 2) == list(range(49))


def test_failure_mask_fails_large_and_nan_errors_elementwise() -> None:
    e_R = np.array([0.1, 2.5, 0.1, np.nan, 2.0])
    e_t = np.array([0.01, 0.01, 0.3, 0.01, 0.2])
    assert failure_mask(e_R, e_t).tolist() == [False, True, True, True, False]


@pytest.fixture(scope='module')
def room_sample() -> Sequence:
    """Nine views of one room along a known trajectory, sensor at each pose's origin."""
    rng = np.random.default_rng(11)
    world = box_room(rng, 8000)
    poses = [np.eye(4)]
    for _ in range(8):
        poses.append(poses[-1] @ random_transform(rng, 3.0, 0.1))
    scans = [
        Scan(i * 100_000_000, 'lidar', transform_points(np.linalg.inv(T), world), {})
        for i, T in enumerate(poses)
    ]
    return Sequence('room', scans, np.stack(poses), 'exact', 'synthetic room')


def _stand_in(name: str, answer: str) -> RawMethod:
    """A method that returns the start ('init') or raises ('raise')."""

    def register(
        source: Any, target: Any, init: np.ndarray | None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        if answer == 'raise':
            raise RuntimeError('no convergence')
        return np.eye(4) if init is None else init, {'status': 'converged'}

    return RawMethod(name, lambda points: points, register, lambda prep: 0.5, {'answer': answer})


@pytest.mark.integration
def test_report_bookkeeping_end_to_end_with_stand_in_methods(
    room_sample: Sequence, tmp_path: Path
) -> None:
    runners = [_stand_in('stay', 'init'), _stand_in('crash', 'raise')]
    strides = run_strides(room_sample, runners, [1, 3], None)
    assert strides['3']['input_indices'] == [0, 3, 6]
    stay = strides['3']['methods']['stay']
    # Starting from the identity and repeating it: every pair is off by the true motion.
    assert stay['n_pairs'] == 2 and stay['failed'] == 2
    assert stay['failed_pairs'] == [[0, 3], [3, 6]]
    assert strides['1']['methods']['crash']['n_raised'] == 8

    outliers = run_outliers(room_sample, runners, [0.0, 0.2], [1, 4], seed=0, shell_share=0.0)
    summary = outliers['0.20']['methods']['stay']['summary']
    # The start is the reference perturbed by exactly 5 deg / 0.2 m, and 'stay' returns it.
    assert summary['e_R_deg']['median'] == pytest.approx(5.0, abs=1e-6)
    assert summary['e_t_m']['median'] == pytest.approx(0.2, abs=1e-9)
    assert summary['failures'] == 2 and summary['median_e_R_ratio_to_clean'] == pytest.approx(1)
    assert 0.0 < summary['outlier_share_after_downsampling'] < 1.0
    assert outliers['0.20']['realised_share']['mean'] == pytest.approx(0.2, abs=1e-3)
    assert outliers['0.00']['methods']['crash']['summary']['n_errors'] == 2

    turned = run_turned(room_sample, runners, [30.0, 180.0], [2], seed=0)
    entry = turned['180']['methods']['stay']['summary']
    assert entry['recovered'] == 0 and entry['recovered_fraction'] == 0.0
    assert turned['30']['reference_rotation_deg']['max'] > 20.0

    meta = {
        'command': 'test',
        'machine': {'git': 'abc', 'cpu': 'cpu', 'load_avg_at_start': [1.0], 'date': 'today'},
        'input': 'synthetic room',
        'n_input_scans': 9,
        'seed': 0,
        'threads': 1,
        'peer_voxel_m': 0.5,
        'n_pairs': 2,
        'n_available_pairs': 8,
        'shell_share': 0.0,
        'start_offset': {'degrees': 5.0, 'metres': 0.2},
    }
    results = {
        'meta': meta,
        'strides': {'meta': meta, 'strides': strides},
        'outliers': {'meta': meta, 'levels': outliers},
        'turned': {'meta': meta, 'angles': turned},
    }
    text = markdown(results)
    assert '| 3 |' in text and '| stay | 2/2 |' in text
    assert re.search(r'\| stay \| 0/1 \(0 %\), \d+ ms \| 0/1 \(0 %\), \d+ ms \|', text)
    assert 'without replacement' in text
    assert '| crash | 2/2 (2 raised), – %, – ms |' in text  # a method that raised: no time
    assert '| crash | 0/1 (0 %), – ms (1 raised) |' in text  # a method that raised: no time
    plot(results, tmp_path / 'robustness.png')
    assert (tmp_path / 'robustness.png').read_bytes().startswith(b'\x89PNG')
