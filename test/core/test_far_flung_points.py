"""Memory follows the point count, never the cloud's extent: scans with points thrown far
beyond any sensor's range (garbage returns, a wrong deskew) get a status, not the OOM killer."""

from __future__ import annotations

import tracemalloc
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from kentreg_ros.core import HEALTHS, KentRegConfig, Odometry, VoxelMap, prepare_scan
from kentreg_ros.core.registration.translation import plane_offset_translation


def _peak_bytes(run: Callable[[], object]) -> int:
    tracemalloc.start()
    try:
        run()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.fixture(scope='module')
def sample_scans(repo_root: Path) -> list[np.ndarray]:
    pytest.importorskip('rosbags', reason='rosbags is not installed (pip install -e .[io])')
    from kentreg_ros.io import open_scan_source

    bag = repo_root / 'bags' / 'balm_50'
    return [s.points for _, s in zip(range(5), open_scan_source(bag), strict=False)]


def test_plane_offset_histograms_are_bounded_by_the_point_count(
    sample_scans: list[np.ndarray],
) -> None:
    """Every 7th target point thrown 1e5 times farther out: the histograms at half-spacing bins
    over that extent took 4 GB; bounded, they cost what the clean pair costs, and the offsets
    of the genuine points still give the translation."""
    src, tgt = prepare_scan(sample_scans[1]), prepare_scan(sample_scans[0])
    far = tgt.points.copy()
    far[::7] *= 1e5
    args = (np.eye(3), np.zeros(3), src.points, src.normals)

    def clean() -> object:
        return plane_offset_translation(*args, tgt.points, tgt.normals, tgt.centers)

    def flung() -> object:
        return plane_offset_translation(*args, far, tgt.normals, tgt.centers)

    t_clean, _ = clean()  # type: ignore[misc]
    t_far, used = flung()  # type: ignore[misc]
    assert used > 0
    assert _peak_bytes(flung) < 4 * _peak_bytes(clean) + 4_000_000
    # Coarser bins along the flung directions: still within a few voxels of the clean answer.
    assert np.linalg.norm(t_far - t_clean) < 1.0


@pytest.mark.parametrize('model', ['previous_scan', 'local_map'])
@pytest.mark.parametrize('scale', [1e3, 1e6, 1e9])
def test_odometry_answers_far_flung_scans_with_a_status(
    sample_scans: list[np.ndarray], model: str, scale: float
) -> None:
    """Points of every scan after the first thrown ``scale`` metres out: every step returns a
    health and a message, within the memory of a clean run."""
    config = KentRegConfig().with_updates({'odometry.model': model})
    rng = np.random.default_rng(int(np.log10(scale)))

    def run(perturb: bool) -> list[str]:
        odometry = Odometry(config)
        healths = []
        for i, points in enumerate(sample_scans):
            q = points.copy()
            if perturb and i > 0:
                # A third of the points as a coherent block far out (as a wrong deskew throws
                # them: dense, so it survives the voxel filter and joins the model), and a
                # tenth scattered over the same reach.
                sel = rng.random(len(q)) < 1 / 3
                q[sel] += scale * rng.normal(size=3)
                spray = rng.random(len(q)) < 1 / 10
                q[spray] *= scale * rng.uniform(0.5, 2.0, size=(int(spray.sum()), 1))
            step = odometry.step(q, i * 500_000_000)
            assert step.health in HEALTHS and step.message
            healths.append(step.health)
        return healths

    clean_peak = _peak_bytes(lambda: run(False))
    healths: list[str] = []
    peak = _peak_bytes(lambda: healths.extend(run(True)))
    assert peak < 4 * clean_peak, f'{peak / 1e6:.0f} MB against {clean_peak / 1e6:.0f} MB clean'
    assert healths[0] == 'first' and len(healths) == len(sample_scans)


def test_voxel_map_drops_points_beyond_its_keys_reach() -> None:
    vmap = VoxelMap(0.1)
    far = 0.1 * 2.0**21  # beyond the 21-bit voxel coordinates
    added = vmap.insert(np.array([[0.0, 0.0, 0.0], [far, 0.0, 0.0], [0.5, 0.0, 0.0]]))
    assert added == 2 and len(vmap) == 2 and vmap.n_out_of_reach == 1


def test_voxel_keys_of_a_grid_beyond_int64_stay_exact() -> None:
    """Two points 1e12 voxels apart on every axis: the linear index of their grid overflows
    int64 and made distinct voxels share keys; they must stay distinct and ordered."""
    from kentreg_ros.core import count_voxels

    near = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.15, 0.0, 0.0]])
    far = np.array([[1e11, 1e11, 1e11], [1e11 + 0.05, 1e11, 1e11]])
    assert count_voxels(np.vstack([near, far]), 0.1) == 3  # {near 0, near 1, far}
    negative = np.array([[-1e11 + 0.01, -1e11, -1e11], [-1e11 + 0.06, -1e11, -1e11]])
    assert count_voxels(np.vstack([near, negative]), 0.1) == 3
