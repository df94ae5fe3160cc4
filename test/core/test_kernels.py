"""The compiled kernels (numba) against the numpy code they replace.

Each kernel repeats numpy's operations in numpy's order, so on this project's machines both give
the same numbers. The bounds hold on any CPU: a few units in the last place relative to the
data's scale, where another CPU or compiler may only sum in another order or fuse a
multiply-add on one side; divided by the eigen-gap where a result amplifies such differences
(eigenvectors); by the number of summed points for means.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np
import pytest

from kentreg_ros.core import KentRegConfig, kernels, prepare_scan
from kentreg_ros.core.registration.correspondence import NearestNeighborCache
from kentreg_ros.core.scan.clusters import (
    _cluster_kappa,
    refine_spherical_kmeans,
    spherical_kmeans,
)
from kentreg_ros.core.scan.neighbors import NeighborIndex
from kentreg_ros.core.scan.normals import (
    estimate_normals,
    neighbourhood_covariances,
    normal_consistency,
    smallest_eigenpairs_3x3,
)
from kentreg_ros.core.scan.voxels import downsample, voxel_downsample

pytest.importorskip('numba', reason='numba is not installed (pip install -e .[fast])')

T = TypeVar('T')

#: Units in the last place allowed, relative to the scale of the compared values.
ULPS = 64


def close(a: np.ndarray, b: np.ndarray, scale: float) -> bool:
    return a.shape == b.shape and bool(np.all(np.abs(a - b) <= ULPS * np.finfo(float).eps * scale))


def both(fn: Callable[[], T], monkeypatch: pytest.MonkeyPatch) -> tuple[T, T]:
    """``fn()`` with the kernels, then with numpy."""
    monkeypatch.delenv(kernels.DISABLE_ENV, raising=False)
    assert kernels.enabled()
    compiled = fn()
    monkeypatch.setenv(kernels.DISABLE_ENV, '1')
    assert not kernels.enabled()
    reference = fn()
    monkeypatch.delenv(kernels.DISABLE_ENV)
    return compiled, reference


@pytest.fixture(scope='module')
def cloud() -> np.ndarray:
    """A seeded scene of noisy planes and scattered returns, 20 m across."""
    rng = np.random.default_rng(7)
    planes = []
    for axis in range(3):
        p = rng.uniform(-10.0, 10.0, size=(4000, 3))
        p[:, axis] = rng.normal(scale=0.01, size=4000) + rng.choice([-5.0, 5.0], size=4000)
        planes.append(p)
    return np.vstack(planes + [rng.uniform(-10.0, 10.0, size=(600, 3))])


def test_kernels_can_be_disabled_by_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(kernels.DISABLE_ENV, '1')
    assert not kernels.enabled() and kernels.warm_up() is False
    monkeypatch.setenv(kernels.DISABLE_ENV, '0')
    assert kernels.enabled() and kernels.warm_up() is True
    # numba's own switch would leave the loops interpreted, far slower than numpy.
    monkeypatch.setenv('NUMBA_DISABLE_JIT', '1')
    assert not kernels.enabled()


def test_kernels_that_cannot_compile_fall_back_to_numpy_with_one_warning(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, cloud: np.ndarray
) -> None:
    monkeypatch.delenv(kernels.DISABLE_ENV, raising=False)
    monkeypatch.setattr(kernels, '_loaded', None)  # not tried yet
    monkeypatch.setattr(kernels, '_module', None)
    monkeypatch.setitem(sys.modules, 'kentreg_ros.core.kernels._jit', None)  # its import fails
    monkeypatch.delattr(kernels, '_jit', raising=False)
    with caplog.at_level(logging.WARNING, logger='kentreg_ros.core.kernels'):
        assert not kernels.enabled()
        assert not kernels.warm_up()
        idx = NeighborIndex(cloud).neighbor_indices(cloud, 15)
        cov = neighbourhood_covariances(cloud, idx)  # the numpy code, no error
    assert cov.shape == (len(cloud), 6) and np.isfinite(cov).all()
    warnings = [r for r in caplog.records if 'using numpy' in r.getMessage()]
    assert len(warnings) == 1


def test_neighbourhood_covariances_match_numpy(
    cloud: np.ndarray, monkeypatch: pytest.MonkeyPatch
) -> None:
    idx = NeighborIndex(cloud).neighbor_indices(cloud[::3], 15)
    compiled, reference = both(lambda: neighbourhood_covariances(cloud, idx), monkeypatch)
    assert close(compiled, reference, float(np.abs(cloud).max()) ** 2)


def test_smallest_eigenpairs_match_numpy_also_where_eigh_takes_over(
    cloud: np.ndarray, monkeypatch: pytest.MonkeyPatch
) -> None:
    idx = NeighborIndex(cloud).neighbor_indices(cloud, 15)
    cov = neighbourhood_covariances(cloud, idx)
    # Matrices the closed form cannot resolve: isotropic, a line, zero.
    special = np.array([[2.0, 0, 0, 2.0, 0, 2.0], [1.0, 1.0, 0, 1.0, 0, 0], [0.0] * 6])
    cov = np.vstack([cov, special])
    compiled, reference = both(lambda: smallest_eigenpairs_3x3(cov), monkeypatch)
    scale = float(np.abs(cov).max())
    assert close(compiled[0], reference[0], scale) and close(compiled[2], reference[2], scale)
    # Unit eigenvectors, sign included (both take the same cross product), each as sensitive
    # to rounding as the matrix's scale over its eigen-gap (where the gap vanishes, both take
    # numpy's eigh).
    gap = np.maximum(reference[2] - reference[0], 1e-300)
    bound = ULPS * np.finfo(float).eps * np.minimum(scale / gap, 1e12)
    assert np.all(np.abs(compiled[1] - reference[1]) <= bound[:, None])
    assert np.allclose(np.linalg.norm(compiled[1], axis=1), 1.0)


def test_normal_consistency_matches_numpy(
    cloud: np.ndarray, monkeypatch: pytest.MonkeyPatch
) -> None:
    est = estimate_normals(cloud, 15)
    compiled, reference = both(lambda: normal_consistency(est.normals, est.neighbors), monkeypatch)
    assert close(compiled, reference, 1.0)


def test_spherical_kmeans_matches_numpy(
    cloud: np.ndarray, monkeypatch: pytest.MonkeyPatch
) -> None:
    normals = estimate_normals(cloud, 15).normals
    (lab_c, cen_c), (lab_r, cen_r) = both(
        lambda: spherical_kmeans(normals, 6, rng=3, restarts=2, sample_size=2000), monkeypatch
    )
    assert np.array_equal(lab_c, lab_r)
    assert close(cen_c, cen_r, 1.0)


def test_an_empty_cluster_is_reseeded_the_same_way_with_the_kernels(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Normals near two directions and a third starting centre nothing is nearest to: Lloyd's
    # step leaves it empty and re-seeds it at the worst-fitting normal.
    rng = np.random.default_rng(2)
    x = np.repeat(np.eye(3)[:2], 50, axis=0) + rng.normal(scale=0.05, size=(100, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    start = np.eye(3)
    start[2] = [0.0, 0.0, -1.0]
    assert np.all(x @ start[2] < np.max(x @ start[:2].T, axis=1))  # the third starts empty
    (lab_c, cen_c), (lab_r, cen_r) = both(
        lambda: refine_spherical_kmeans(x, start, max_iterations=1), monkeypatch
    )
    assert set(lab_c.tolist()) == {0, 1, 2}
    assert np.array_equal(lab_c, lab_r)
    assert close(cen_c, cen_r, 1.0)


@pytest.mark.parametrize('iterations', [2, 50])
def test_lloyd_goes_on_after_a_reseed_the_same_way_with_the_kernels(
    iterations: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The compiled steps stop at the empty cluster, Python re-seeds it, the steps resume: with
    # room for it the result is a fixed point of Lloyd's step.
    rng = np.random.default_rng(5)
    x = np.repeat(np.eye(3)[:2], 60, axis=0) + rng.normal(scale=0.3, size=(120, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    start = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-0.6, -0.6, -0.5]])
    (lab_c, cen_c), (lab_r, cen_r) = both(
        lambda: refine_spherical_kmeans(x, start, max_iterations=iterations), monkeypatch
    )
    assert np.array_equal(lab_c, lab_r)
    assert close(cen_c, cen_r, 1.0)
    assert set(lab_c.tolist()) == {0, 1, 2}
    if iterations == 50:
        assert np.array_equal(np.argmax(x @ cen_c.T, axis=1), lab_c)
        sums = np.array([x[lab_c == j].sum(axis=0) for j in range(3)])
        np.testing.assert_allclose(cen_c, sums / np.linalg.norm(sums, axis=1)[:, None])


def test_cluster_moments_match_numpy(cloud: np.ndarray, monkeypatch: pytest.MonkeyPatch) -> None:
    normals = estimate_normals(cloud, 15).normals
    labels = np.argmax(np.abs(normals), axis=1) * 2 + (normals.max(axis=1) > 0.5)
    compiled, reference = both(lambda: _cluster_kappa(normals, labels, 7), monkeypatch)
    assert reference[6] == 0.0 or np.isfinite(reference[6])  # an empty label is allowed
    assert close(compiled, reference, float(np.abs(reference).max()))


def test_voxel_grid_matches_numpy(cloud: np.ndarray, monkeypatch: pytest.MonkeyPatch) -> None:
    compiled, reference = both(lambda: voxel_downsample(cloud, 0.37), monkeypatch)
    # Means of up to a few hundred points each, possibly summed in another order.
    assert close(compiled, reference, 1e3 * float(np.abs(cloud).max()))
    (pc, gc), (pr, gr) = both(
        lambda: downsample(cloud, voxel_size=0.0, target_points=3000, min_voxel_points=2),
        monkeypatch,
    )
    assert gc == gr
    assert close(pc, pr, 1e3 * float(np.abs(cloud).max()))


def test_nearest_neighbour_cache_matches_numpy(
    cloud: np.ndarray, monkeypatch: pytest.MonkeyPatch
) -> None:
    target = cloud[::2]
    tree = NeighborIndex(target)
    rng = np.random.default_rng(1)
    queries = cloud[1::4] + rng.normal(scale=0.05, size=(len(cloud[1::4]), 3))
    steps = [rng.normal(scale=s, size=queries.shape) for s in (0.0, 0.01, 0.002, 0.2)]

    def walk() -> list[tuple[np.ndarray, np.ndarray]]:
        cache = NearestNeighborCache(tree, target, len(queries))
        out, x = [], queries.copy()
        for step, gate in zip(steps, (1.0, 0.5, 0.3, 0.3), strict=True):
            x = x + step
            out.append(cache.query(x, gate))
        return out

    compiled, reference = both(walk, monkeypatch)
    for (dc, ic), (dr, ir) in zip(compiled, reference, strict=True):
        assert np.array_equal(ic, ir)
        assert np.array_equal(np.isinf(dc), np.isinf(dr))
        finite = np.isfinite(dr)
        assert close(dc[finite], dr[finite], 1.0)


def test_prepared_sample_scan_is_the_same_with_and_without_kernels(
    repo_root: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    pytest.importorskip('rosbags', reason='rosbags is not installed (pip install -e .[io])')
    from kentreg_ros.io import open_scan_source

    points = next(iter(open_scan_source(repo_root / 'bags' / 'balm_50'))).points
    compiled, reference = both(lambda: prepare_scan(points, config=KentRegConfig()), monkeypatch)
    assert compiled.voxel_size == reference.voxel_size
    assert len(compiled) == len(reference)
    assert close(compiled.points, reference.points, 1e3 * float(np.abs(points).max()))
    # A billionth of a radian: rounding amplified by any kept neighbourhood's conditioning
    # stays far below it, and any real difference in the normals far above.
    assert np.abs(compiled.normals - reference.normals).max() < 1e-9
    assert np.array_equal(compiled.labels, reference.labels)


def _pair(cloud: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A target with normals, and a source: the target's other half moved by a known motion."""
    from scipy.spatial.transform import Rotation

    target = cloud[::2]
    normals = estimate_normals(target, 15).normals
    R = Rotation.from_rotvec([0.01, -0.02, 0.015]).as_matrix()
    t = np.array([0.05, -0.03, 0.02])
    source = (cloud[1::2] - t) @ R  # x_target = R x_source + t
    src_normals = estimate_normals(source, 15).normals
    return target, normals, source, src_normals, np.vstack([np.c_[R, t], [0, 0, 0, 1]])


def test_point_to_plane_refinement_matches_numpy(
    cloud: np.ndarray, monkeypatch: pytest.MonkeyPatch
) -> None:
    from kentreg_ros.core.registration.refine import refine_joint

    target, normals, source, src_normals, T_true = _pair(cloud)
    tree = NeighborIndex(target)
    start = T_true.copy()
    start[:3, 3] += [0.1, 0.0, -0.05]
    for normal_weight in (True, False):
        compiled, reference = both(
            lambda nw=normal_weight: refine_joint(
                start, source, src_normals, target, normals, tree, normal_weight=nw
            ),
            monkeypatch,
        )
        assert compiled.iterations == reference.iterations
        # Sums in another order: the step differs by rounding, the poses by far less than
        # a nanometre / nanoradian after the same iterations.
        assert np.abs(compiled.T - reference.T).max() < 1e-9
        assert np.allclose(compiled.hessian, reference.hessian, rtol=1e-9, atol=0.0)
        assert compiled.sigma2 == pytest.approx(reference.sigma2, rel=1e-9)
        assert compiled.kappa_normal == pytest.approx(reference.kappa_normal, rel=1e-9)
        assert compiled.inlier_fraction == reference.inlier_fraction
        assert np.abs(reference.T - T_true).max() < 0.01  # the refinement itself works


def test_translation_stage_matches_numpy(
    cloud: np.ndarray, monkeypatch: pytest.MonkeyPatch
) -> None:
    from kentreg_ros.core.registration.translation import point_to_plane_translation

    target, normals, source, _, T_true = _pair(cloud)
    tree = NeighborIndex(target)
    compiled, reference = both(
        lambda: point_to_plane_translation(
            T_true[:3, :3], T_true[:3, 3] + [0.2, -0.1, 0.05], source, target, normals, tree
        ),
        monkeypatch,
    )
    assert compiled.iterations == reference.iterations
    assert np.abs(compiled.t - reference.t).max() < 1e-9
    assert np.allclose(compiled.hessian, reference.hessian, rtol=1e-9, atol=0.0)
    assert compiled.sigma2 == pytest.approx(reference.sigma2, rel=1e-9)
    assert compiled.inlier_fraction == reference.inlier_fraction
    assert np.abs(reference.t - T_true[:3, 3]).max() < 0.01  # the stage itself works


def test_normal_bins_are_the_same_with_and_without_kernels(
    cloud: np.ndarray, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The bins' moments agree with numpy's (summed in another order than ``add.reduceat``'s
    vectorised loop: to rounding, ~1e-14 of sums of at most a few hundred unit vectors)."""
    from kentreg_ros.core.scan.clusters import NormalBins

    normals = estimate_normals(cloud, 15).normals
    labels = np.argmax(np.abs(normals), axis=1)
    compiled, reference = both(
        lambda: NormalBins.from_normals(normals, 0.05 + 0.01 * labels, labels), monkeypatch
    )
    assert len(reference) > 10
    assert np.array_equal(compiled.weights, reference.weights)
    for name in ('directions', 'resultants', 'scatters'):
        got, want = getattr(compiled, name), getattr(reference, name)
        assert np.allclose(got, want, rtol=0.0, atol=1e-12 * max(1.0, float(want.max()))), name


@pytest.mark.parametrize('per_voxel', [1, 3])
def test_local_map_averaging_matches_numpy(
    cloud: np.ndarray, monkeypatch: pytest.MonkeyPatch, per_voxel: int
) -> None:
    """A voxel map that averages (the local map) after several scans merged into it, with the
    compiled merge and with numpy's: the same counts, sums and points (+, /, in numpy's
    order: bit for bit), and normals to rounding (their norm is summed as numpy's x86-64
    build sums it)."""
    from kentreg_ros.core.odometry.localmap import VoxelMap

    rng = np.random.default_rng(3)
    normals = estimate_normals(cloud, 15).normals
    shifts = [rng.normal(scale=0.02, size=cloud.shape) for _ in range(4)]
    # Some normals reversed, so the sign test that turns them to agree has work to do.
    flips = [np.where(rng.random(len(cloud)) < 0.3, -1.0, 1.0)[:, None] for _ in range(4)]

    def build() -> VoxelMap:
        vmap = VoxelMap(0.3, max_points_per_voxel=per_voxel, with_normals=True, average=True)
        for shift, flip in zip(shifts, flips, strict=True):
            vmap.insert(cloud + shift, normals * flip)
        return vmap

    compiled, reference = both(build, monkeypatch)
    assert len(reference) > 1000 and reference._merged.max() > 4  # merges happened
    names = ('_merged', '_sums', '_points', '_normal_sums', '_keys', '_order', '_sorted_keys')
    for name in names + ('_voxel_keys', '_voxel_counts'):
        assert np.array_equal(getattr(compiled, name), getattr(reference, name)), name
    assert close(compiled.normals, reference.normals, 1.0)


def test_kent_moment_estimates_match_numpy(
    cloud: np.ndarray, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Kent's estimates of real clusters, of a concentrated one (rounding-level spread: beta
    set to 0), of one along an axis (the frame's special case) and of an empty one (zero
    moments): the compiled frames and estimates against numpy's, with the tangent rotation
    numpy's in both."""
    from kentreg_ros.core.kent import KAPPA_MAX, kent_from_moments

    normals = estimate_normals(cloud, 15).normals
    labels = np.argmax(np.abs(normals), axis=1) + 3 * (normals[np.arange(len(normals)), 0] > 0)
    xbar = np.array([normals[labels == j].mean(axis=0) for j in range(6)])
    scatter = np.array([np.einsum('na,nb->ab', *(normals[labels == j],) * 2) for j in range(6)])
    scatter /= np.bincount(labels, minlength=6)[:, None, None]
    axis = np.array([1.0, 0.0, 0.0])
    xbar = np.vstack([xbar, axis, axis, np.zeros(3)])
    special = [np.outer(axis, axis), np.diag([0.9, 0.06, 0.04]), np.zeros((3, 3))]
    scatter = np.concatenate([scatter, np.array(special)])
    compiled, reference = both(lambda: kent_from_moments(xbar, scatter), monkeypatch)
    kappa, beta, gamma = compiled
    assert reference[0][:6].max() > 10.0 and reference[0][6] == KAPPA_MAX
    assert np.isfinite(reference[0]).all()
    assert close(gamma, reference[2], 1.0)
    # kappa ~ 1 / (1 - r1): rounding of r1 is amplified by kappa.
    assert np.all(np.abs(kappa - reference[0]) <= ULPS * np.finfo(float).eps * reference[0] ** 2)
    assert np.all(np.abs(beta - reference[1]) <= ULPS * np.finfo(float).eps * reference[0] ** 2)
    assert np.allclose(np.linalg.det(gamma), 1.0)


def test_em_group_moments_match_numpy(monkeypatch: pytest.MonkeyPatch) -> None:
    """The M-step's per-cluster sums of bins (posterior-weighted scatters, weights, resultants,
    scatters), summed in row order against numpy's matrix products (BLAS's order): to
    rounding; a cluster without bins has zero sums."""
    rng = np.random.default_rng(5)
    n, k = 700, 7
    x = rng.normal(size=(n, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    counts = rng.integers(1, 40, size=n).astype(float)
    resultants = x * counts[:, None]
    scatters = np.einsum('na,nb->nab', x, x).reshape(n, 9) * counts[:, None]
    labels = rng.integers(0, k - 1, size=n)  # the last cluster stays empty
    posterior = rng.random(n)
    compiled, reference = both(
        lambda: kernels.bin_group_moments(labels, posterior, counts, resultants, scatters, k),
        monkeypatch,
    )
    for got, want in zip(compiled, reference, strict=True):
        assert close(got, want, float(counts.sum()))
    assert not np.any(compiled[0][-1]) and compiled[1][-1] == 0.0


def test_em_e_step_matches_numpy(monkeypatch: pytest.MonkeyPatch) -> None:
    """The E-step (compiled log-posteriors and sums, numpy's exp and log between them) against
    the numpy code: clusters with and without the ovalness term, one with no model bins (its
    observed bins get no posterior mass), an observed bin far from every kernel (all its mass
    on the outlier term)."""
    rng = np.random.default_rng(11)

    def unit(n: int) -> np.ndarray:
        v = rng.normal(size=(n, 3))
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    n, k = 300, 4
    z = unit(n)
    assign = rng.integers(0, k, size=n)
    counts = rng.integers(1, 30, size=n).astype(float)
    resultants = z * counts[:, None]
    y = unit(200)
    off = np.array([0, 80, 150, 200, 200])  # the last cluster has no model bins
    log_pi = np.log(rng.uniform(0.001, 0.01, size=200))
    kappa = np.array([20.0, 50.0, 400.0, 10.0])
    beta = np.array([0.0, 5.0, 0.0, 2.0])
    gamma = np.array([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(k)])
    log_c = np.log(kappa / (2.0 * np.pi))
    log_out = float(np.log(0.1) - np.log(4.0 * np.pi))
    args = (z, assign, counts, resultants, y, y, off, log_pi, log_c, kappa, beta, gamma, log_out)
    compiled, reference = both(lambda: kernels.e_step(*args), monkeypatch)
    Cs, loglik, tn, t_unit = compiled
    assert np.all(reference[3][assign == 3] == 0.0) and np.all(t_unit[assign == 3] == 0.0)
    assert reference[3].min() < 1e-6 < reference[3].max()  # some bins are all outlier
    assert close(t_unit, reference[3], 1.0) and close(tn, reference[2], float(counts.max()))
    assert close(Cs, reference[0], float(kappa.max() * counts.sum()))
    assert loglik == pytest.approx(reference[1], rel=ULPS * np.finfo(float).eps * n)


@pytest.mark.parametrize('max_points', [1, 3])
def test_voxel_admission_and_sorted_positions_match_numpy(
    monkeypatch: pytest.MonkeyPatch, max_points: int
) -> None:
    """The merge walks of the map's insertion against numpy's searchsorted and run arithmetic:
    new keys before, between, equal to and after the map's, voxels full or not, no map yet."""
    rng = np.random.default_rng(5)
    voxel_keys = np.unique(rng.integers(10, 1000, 300))
    counts = rng.integers(1, max_points + 1, len(voxel_keys))
    new = np.sort(np.concatenate([rng.integers(0, 1100, 500), voxel_keys[:20], [0, 0, 2000]]))
    for haystack, held in ((voxel_keys, counts), (voxel_keys[:0], counts[:0])):
        compiled, reference = both(
            lambda h=haystack, c=held: kernels.voxel_admission(new, h, c, max_points),
            monkeypatch,
        )
        for got, want in zip(compiled, reference, strict=True):
            np.testing.assert_array_equal(got, want)
        for right in (False, True):
            got, want = both(
                lambda h=haystack, r=right: kernels.sorted_positions(h, new, right=r),
                monkeypatch,
            )
            np.testing.assert_array_equal(got, want)


def test_run_starts_match_numpy_also_on_no_keys(monkeypatch: pytest.MonkeyPatch) -> None:
    for ordered in (np.zeros(0, dtype=np.int64), np.array([2, 2, 5, 7, 7, 7], dtype=np.int64)):
        (sc, cc), (sr, cr) = both(lambda o=ordered: kernels.run_starts(o), monkeypatch)
        np.testing.assert_array_equal(sc, sr)
        np.testing.assert_array_equal(cc, cr)
        assert cc.sum() == len(ordered)
