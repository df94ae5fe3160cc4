"""Preprocessing, PCA normals with outlier removal, and spherical k-means."""

from __future__ import annotations

import numpy as np
import pytest

from kentreg_ros.core import InvalidInputError, InvalidPointCloudError, KentRegError, exp_so3
from kentreg_ros.core.kent import KentParams
from kentreg_ros.core.kent_sampling import sample_kent
from kentreg_ros.core.scan.clusters import spherical_kmeans
from kentreg_ros.core.scan.normals import (
    estimate_normals,
    neighbourhood_covariances,
    normal_inlier_mask,
    orient_normals,
    smallest_eigenpairs_3x3,
)
from kentreg_ros.core.scan.voxels import (
    as_points,
    choose_voxel_size,
    count_voxels,
    crop_range,
    downsample,
    drop_nonfinite,
    voxel_downsample,
)


def test_voxel_downsample_returns_voxel_centroids() -> None:
    pts = np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [1.5, 0.2, 0.2], [1.7, 0.4, 0.2]])
    out = voxel_downsample(pts, 1.0)
    np.testing.assert_allclose(sorted(out.tolist()), [[0.2, 0.2, 0.2], [1.6, 0.3, 0.2]])


def test_automatic_voxel_size_reaches_the_target_count() -> None:
    rng = np.random.default_rng(0)
    pts = np.column_stack(
        [rng.uniform(0, 20, 80000), rng.uniform(0, 20, 80000), rng.normal(scale=0.01, size=80000)]
    )
    out, grid = downsample(pts, target_points=10000)
    # Within the search tolerance (5 %) of the target, every kept voxel holds >= 2 returns.
    assert abs(len(out) - 10000) < 500
    assert grid.min_points == 2 and grid.size == choose_voxel_size(pts, 10000)


def test_voxel_count_and_automatic_downsampling_agree_with_a_direct_computation() -> None:
    rng = np.random.default_rng(5)
    pts = rng.normal(scale=[10.0, 10.0, 2.0], size=(30000, 3)) - [3.0, -7.0, 1.0]
    for size in (0.05, 0.3, 1.7):
        keys = np.floor(pts / size).astype(np.int64)
        assert count_voxels(pts, size) == len(np.unique(keys, axis=0))
    out, grid = downsample(pts, voxel_size=0.5, min_voxel_points=1)
    np.testing.assert_allclose(out, voxel_downsample(pts, 0.5), rtol=1e-12, atol=1e-12)
    keys = np.floor(pts / 0.5).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    out2, grid2 = downsample(pts, voxel_size=0.5, min_voxel_points=2)
    # A blob this dense has no stray returns to raise the floor above the one asked for.
    assert grid.min_points == 1 and grid2.min_points == 2
    assert len(out2) == int((counts >= 2).sum())
    assert grid2.n_isolated == int(counts[counts < 2].sum())


def _surfaces_with_stray_returns(
    rng: np.random.Generator, n_surface: int, share: float
) -> tuple[np.ndarray, np.ndarray]:
    """A 30 x 20 x 6 m box's floor and walls, plus uniform stray returns in its volume making
    ``share`` of all points; returns the points and a mask of the stray ones."""
    lo, hi = np.array([-15.0, -10.0, -1.0]), np.array([15.0, 10.0, 5.0])
    pts = rng.uniform(lo, hi, (n_surface, 3))
    face = rng.integers(0, 3, n_surface)
    pts[face == 0, 2] = lo[2]
    pts[face == 1, 0] = rng.choice([lo[0], hi[0]], int((face == 1).sum()))
    pts[face == 2, 1] = rng.choice([lo[1], hi[1]], int((face == 2).sum()))
    n_stray = int(round(share / (1.0 - share) * n_surface))
    stray = rng.uniform(lo, hi, (n_stray, 3))
    return np.concatenate([pts, stray]), np.r_[np.zeros(n_surface, bool), np.ones(n_stray, bool)]


@pytest.mark.parametrize('share', [0.2, 0.4, 0.6])
def test_stray_returns_neither_choose_the_voxel_nor_survive_it(share: float) -> None:
    rng = np.random.default_rng(int(share * 10))
    # 100 returns per square metre of surface, as a LiDAR gives at ~10 m.
    clean, _ = _surfaces_with_stray_returns(rng, 120000, 0.0)
    noisy, stray = _surfaces_with_stray_returns(rng, 120000, share)
    size_clean = choose_voxel_size(clean, 10000)
    out, grid = downsample(noisy, target_points=10000)
    # Counting every occupied voxel, the stray returns (one per voxel) would dominate the count
    # and push the size up several times; counting voxels with several returns keeps it within
    # the factor the returns-per-voxel floor moves it by (>= 2 returns at 40 %, more above).
    assert grid.size < 1.5 * size_clean
    assert len(out) > 0.5 * 10000
    # Kept voxels are the surfaces': a voxel is stray when it lies off every face.
    lo, hi = np.array([-15.0, -10.0, -1.0]), np.array([15.0, 10.0, 5.0])
    off = np.min(np.abs(np.column_stack([out[:, 2] - lo[2], out[:, :2] - lo[:2],
                                         hi[:2] - out[:, :2]])), axis=1)  # fmt: skip
    assert np.mean(off > 2.0 * grid.size) < 0.1  # MAX_ISOLATED_SHARE of the kept voxels
    # Stray returns that share a voxel with a surface are averaged into it (surface voxels fill
    # ~12 % of this box at its voxel size); nearly all others are dropped.
    assert grid.n_isolated >= 0.75 * stray.sum()


def test_points_validation_messages() -> None:
    with pytest.raises(InvalidPointCloudError, match=r'shape \(N, 3\), got \(5, 2\)'):
        as_points(np.zeros((5, 2)))
    pts, dropped = drop_nonfinite(np.array([[0, 0, 0], [np.nan, 0, 0], [1, np.inf, 0.0]]))
    assert dropped == 2 and pts.shape == (1, 3)


def test_plane_normals_are_exact_and_face_the_viewpoint() -> None:
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-2, 2, 2000), rng.uniform(-2, 2, 2000), np.full(2000, 3.0)])
    est = estimate_normals(pts, 15, viewpoint=(0, 0, 0))
    np.testing.assert_allclose(est.normals, np.tile([0, 0, -1.0], (2000, 1)), atol=1e-9)
    est_up = estimate_normals(pts, 15, viewpoint=(0, 0, 10))
    assert np.all(est_up.normals[:, 2] > 0.999)
    assert np.all(est.curvature < 1e-9)
    # Neighbours queried beforehand (as prepare_scan does, to time the search) give the same
    # normals; neighbours of another shape are refused.
    given = estimate_normals(pts, 15, viewpoint=(0, 0, 0), neighbors=est.neighbors)
    np.testing.assert_array_equal(given.normals, est.normals)
    with pytest.raises(InvalidInputError, match='neighbors'):
        estimate_normals(pts, 15, neighbors=est.neighbors[:, :10])


def test_bad_arguments_are_kentreg_errors_and_still_value_errors() -> None:
    """The scan room's argument checks raise the library's InvalidInputError, which callers
    catching ValueError (as before) or KentRegError both catch."""
    with pytest.raises(InvalidInputError, match=r'`k` >= 3'):
        estimate_normals(np.zeros((30, 3)), 2)
    with pytest.raises(KentRegError, match='at least one vector'):
        spherical_kmeans(np.zeros((0, 3)), 3)
    with pytest.raises(ValueError, match=r'`voxel_size` > 0'):
        voxel_downsample(np.zeros((30, 3)), 0.0)


def test_neighbourhood_covariances_match_the_dense_computation() -> None:
    rng = np.random.default_rng(6)
    pts = rng.normal(size=(500, 3)) * [5.0, 3.0, 0.5] + [20.0, -4.0, 1.0]
    nbrs = np.argsort(np.linalg.norm(pts[:, None] - pts[None], axis=2), axis=1)[:, :12]
    cov = neighbourhood_covariances(pts, nbrs)
    dense = np.array([np.cov(pts[n].T, bias=True) for n in nbrs])
    np.testing.assert_allclose(cov, dense.reshape(-1, 9)[:, [0, 1, 2, 4, 5, 8]], atol=1e-10)


def test_closed_form_smallest_eigenpairs_match_eigh_including_degenerate_matrices() -> None:
    rng = np.random.default_rng(7)
    Q = np.array([exp_so3(w) for w in rng.normal(size=(400, 3))])
    evals = np.sort(rng.uniform(0.0, 1.0, size=(400, 3)), axis=1) ** 3
    evals[:50, 0] = 0.0  # exact planes
    evals[50:100, 1] = evals[50:100, 0]  # lines: two equal small eigenvalues
    evals[100:120] = 0.3  # isotropic
    evals[120:130] = 0.0  # one repeated point
    evals[130:200, 0] = 1e-7 * evals[130:200, 2]  # nearly planar
    M = np.einsum('nij,nj,nkj->nik', Q, evals, Q)
    cov = M.reshape(-1, 9)[:, [0, 1, 2, 4, 5, 8]]
    lam, vec, _ = smallest_eigenpairs_3x3(cov)
    w, v = np.linalg.eigh(M)
    np.testing.assert_allclose(lam, w[:, 0], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(vec, axis=1), 1.0, atol=1e-12)
    # Each returned vector is an eigenvector of the smallest eigenvalue (the direction is only
    # defined when that eigenvalue is simple).
    np.testing.assert_allclose(np.einsum('nij,nj->ni', M, vec), lam[:, None] * vec, atol=1e-10)
    simple = (w[:, 1] - w[:, 0]) > 1e-3 * w[:, 2]
    cos = np.abs(np.einsum('ni,ni->n', vec, v[:, :, 0]))
    assert simple.sum() > 250 and np.all(cos[simple] > 1.0 - 1e-12)


def test_edge_on_normals_get_a_fixed_orientation_whatever_their_rounding() -> None:
    """Points in the sensor's horizontal plane (z = 0) with vertical normals: the viewpoint
    cannot orient them, so rounding-level changes must not flip them."""
    pts = np.array([[5.0, 1.0, 0.0], [-3.0, 2.0, 0.0], [0.0, -4.0, 0.0], [2.0, 2.0, 1.0]])
    for tilt in (1e-13, -1e-13, 0.0):
        n = np.array([[tilt, 0.0, 1.0], [0.0, tilt, -1.0], [tilt, tilt, -1.0], [0.0, 0.0, 1.0]])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        out = orient_normals(pts, n)
        assert np.all(out[:3, 2] > 0.999)  # edge-on: largest component made positive
        assert out[3, 2] < -0.999  # a normal the ray does orient still faces the viewpoint


def test_normal_outlier_removal_drops_scattered_points_not_the_plane() -> None:
    rng = np.random.default_rng(2)
    plane = np.column_stack(
        [rng.uniform(-2, 2, 3000), rng.uniform(-2, 2, 3000), rng.normal(scale=0.002, size=3000)]
    )
    clutter = rng.uniform(-2, 2, size=(300, 3)) * [1, 1, 0.5] + [0, 0, 1.0]
    pts = np.concatenate([plane, clutter])
    est = estimate_normals(pts, 15, viewpoint=(0, 0, 5))
    keep = normal_inlier_mask(est.normals, est.neighbors, 0.8)
    assert keep[:3000].mean() > 0.97
    assert keep[3000:].mean() < 0.6
    assert normal_inlier_mask(est.normals, est.neighbors, -1.0).all()


def test_too_few_points_for_normals_is_a_clear_error() -> None:
    with pytest.raises(InvalidPointCloudError, match='at least k=15'):
        estimate_normals(np.random.default_rng(0).random((10, 3)), 15)


def test_spherical_kmeans_recovers_kent_clusters_and_is_seeded() -> None:
    rng = np.random.default_rng(3)
    means = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [-0.6, -0.8, 0]])
    samples = []
    for m in means:
        a = np.cross(m, [0.3, 0.5, 0.8])
        a /= np.linalg.norm(a)
        gamma = np.column_stack([m, a, np.cross(m, a)])
        samples.append(sample_kent(KentParams(kappa=100.0, beta=30.0, gamma=gamma), 500, rng))
    x = np.concatenate(samples)
    labels, centers = spherical_kmeans(x, 4, rng=0)
    for m in means:
        assert np.max(centers @ m) > 0.99
    truth = np.repeat(np.arange(4), 500)
    for j in range(4):  # every true cluster maps onto one label
        assert np.bincount(labels[truth == j]).max() >= 495
    labels2, centers2 = spherical_kmeans(x, 4, rng=0)
    np.testing.assert_array_equal(labels, labels2)
    np.testing.assert_array_equal(centers, centers2)


def test_spherical_kmeans_handles_more_clusters_than_points() -> None:
    x = exp_so3([0.1, 0.2, 0.3])[:2]
    labels, centers = spherical_kmeans(x, 5)
    assert len(centers) == 2 and set(labels) == {0, 1}


def test_a_cloud_already_downsampled_at_the_voxel_keeps_its_samples() -> None:
    rng = np.random.default_rng(8)
    raw = np.column_stack(
        [rng.uniform(0, 20, 60000), rng.uniform(0, 20, 60000), rng.normal(scale=0.01, size=60000)]
    )
    once = voxel_downsample(raw, 0.25)  # one point per voxel of this grid
    again, grid = downsample(once, voxel_size=0.25)
    # Dropping single-return voxels would leave nothing: they are the cloud's samples here.
    assert grid.min_points == 1 and len(again) == len(once)


def test_crop_range_keeps_the_points_within_the_ring_in_order() -> None:
    rng = np.random.default_rng(12)
    points = rng.normal(scale=20.0, size=(5000, 3))
    origin = np.array([1.0, -2.0, 0.5])
    dist = np.linalg.norm(points - origin, axis=1)
    for lo, hi in ((0.0, 0.0), (5.0, 0.0), (0.0, 30.0), (5.0, 30.0)):
        want = points[(dist >= lo) & ((dist <= hi) if hi > 0.0 else True)]
        got = crop_range(points, lo, hi, origin)
        np.testing.assert_array_equal(got, want)
        assert got.flags.c_contiguous
