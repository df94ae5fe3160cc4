"""EM on the sphere: binning keeps the moments, and the EM recovers the rotation and the Kent
parameters of synthetic Kent mixtures within tolerances derived from the sample size."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_kent import _population_moment_estimate

from kentreg_ros.core import exp_so3, rotation_angle
from kentreg_ros.core.kent import KentParams, fit_kent_moments_batch
from kentreg_ros.core.kent_sampling import sample_kent
from kentreg_ros.core.registration.em import paper_cluster_em, shared_rotation_em
from kentreg_ros.core.scan.clusters import (
    ModelClusters,
    NormalBins,
    bin_cell_for,
    kent_moments_of_bins,
)

MEANS = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [-0.6, -0.8, 0]])


def _frames(rng: np.random.Generator) -> list[np.ndarray]:
    """Kent frames (mean, major, minor) with the means above and random major axes."""
    out = []
    for m in MEANS:
        a = np.cross(m, rng.normal(size=3))
        a /= np.linalg.norm(a)
        out.append(np.column_stack([m, a, np.cross(m, a)]))
    return out


def _sample(
    frames: list[np.ndarray], kappa: float, beta: float, n_per: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    x = [sample_kent(KentParams(kappa, beta, g), n_per, rng) for g in frames]
    return np.concatenate(x), np.repeat(np.arange(len(frames)), n_per)


def _bins(x: np.ndarray, labels: np.ndarray, kappa: float) -> NormalBins:
    cells = bin_cell_for(np.full(labels.max() + 1, kappa))
    return NormalBins.from_normals(x, cells[labels], labels)


def test_bins_keep_the_exact_moments_of_their_normals() -> None:
    rng = np.random.default_rng(1)
    frames = _frames(rng)
    x, labels = _sample(frames, 80.0, 30.0, 3000, rng)
    bins = _bins(x, labels, 80.0)
    assert len(bins) < len(x) / 3  # it summarises
    assert bins.weights.sum() == len(x)
    member = np.zeros((4, len(bins)))
    # A bin holds one group's normals only; recover its group from its direction.
    member[np.argmax(bins.directions @ MEANS.T, axis=1), np.arange(len(bins))] = 1.0
    k_bins, b_bins, g_bins = kent_moments_of_bins(bins, member)
    onehot = (labels[None, :] == np.arange(4)[:, None]).astype(float)
    k_pts, b_pts, g_pts = fit_kent_moments_batch(x, onehot)
    # Same sums in another order: equal up to rounding relative to the sums' size.
    np.testing.assert_allclose(k_bins, k_pts, rtol=1e-9)
    np.testing.assert_allclose(b_bins, b_pts, rtol=1e-9)
    np.testing.assert_allclose(np.abs(np.einsum('kij,kij->kj', g_bins, g_pts)), 1.0, atol=1e-9)


@pytest.mark.parametrize('use_beta', [False, True])
@pytest.mark.parametrize(
    ('kappa', 'beta', 'angle_deg', 'seed'),
    [(150.0, 50.0, 20.0, 0), (60.0, 25.0, 35.0, 1), (300.0, 0.0, 10.0, 2)],
)
def test_shared_em_recovers_rotation_and_kent_parameters(
    kappa: float, beta: float, angle_deg: float, seed: int, use_beta: bool
) -> None:
    rng = np.random.default_rng(seed)
    n = 3000
    frames = _frames(rng)
    y, y_labels = _sample(frames, kappa, beta, n, rng)
    model = ModelClusters.from_bins(_bins(y, y_labels, kappa), MEANS)
    axis = rng.normal(size=3)
    R_true = exp_so3(axis / np.linalg.norm(axis) * np.radians(angle_deg))
    x_model, x_labels = _sample(frames, kappa, beta, n, rng)
    x = x_model @ R_true  # observed normals: y = R_true x
    result = shared_rotation_em(_bins(x, x_labels, kappa), model, np.eye(3), use_beta=use_beta)
    assert result.converged
    # Rotation: each cluster's mean is known to ~1/sqrt(kappa n) rad per axis in each cloud;
    # 4 clusters, two clouds: the estimate's error is ~sqrt(2 / (4 kappa n)). 5 sigma:
    tol = 5.0 * np.sqrt(2.0 / (4.0 * kappa * n))
    assert rotation_angle(result.R.T @ R_true) < tol
    # Kent parameters: the moment estimator's large-N limit (biased for beta > 0, Kent 1982)
    # within sampling noise, relative std ~sqrt(1/n) for kappa and ~sqrt(2/n) kappa/beta for
    # beta (a difference of two spreads); 5 sigma.
    kappa_lim, beta_lim = _population_moment_estimate(kappa, beta)
    np.testing.assert_allclose(result.kappa, kappa_lim, rtol=5.0 / np.sqrt(n))
    if beta > 0:
        np.testing.assert_allclose(
            result.beta, beta_lim, rtol=5.0 * np.sqrt(2.0 / n) * kappa / beta
        )
    else:
        assert np.all(result.beta < 5.0 * np.sqrt(2.0 / n) * kappa)
    assert np.all((result.beta >= 0) & (result.beta < result.kappa / 2))
    assert result.inlier_fraction > 0.9


def test_shared_em_gives_outliers_to_the_uniform_component() -> None:
    rng = np.random.default_rng(7)
    frames = _frames(rng)
    y, y_labels = _sample(frames, 150.0, 50.0, 2000, rng)
    model = ModelClusters.from_bins(_bins(y, y_labels, 150.0), MEANS)
    R_true = exp_so3(np.radians([4.0, -7.0, 5.0]))
    x, x_labels = _sample(frames, 150.0, 50.0, 2000, rng)
    junk = rng.normal(size=(len(x) * 3 // 7, 3))  # 30 % of the observed normals
    junk /= np.linalg.norm(junk, axis=1, keepdims=True)
    observed = np.concatenate([x @ R_true, junk])
    groups = np.r_[x_labels, np.full(len(junk), 4)]
    bins = NormalBins.from_normals(observed, bin_cell_for(150.0), groups)
    result = shared_rotation_em(bins, model, np.eye(3))
    # The junk inside each cluster's Voronoi cell widens its moment spread and so its kernel,
    # which costs precision (without junk: < 0.2 deg); the stage must still land well within
    # the joint refinement's basin of a few degrees.
    assert np.degrees(rotation_angle(result.R.T @ R_true)) < 1.0
    # The junk's posterior mass goes mostly to the uniform component: the inlier share drops
    # by a good part of the junk's 30 % compared with the same normals without junk.
    clean = shared_rotation_em(_bins(x @ R_true, x_labels, 150.0), model, np.eye(3))
    assert clean.inlier_fraction - result.inlier_fraction > 0.1 * 0.3 / (1 + 0.3)


def test_paper_cluster_em_aligns_one_anisotropic_cluster() -> None:
    rng = np.random.default_rng(5)
    gamma = Rotation.random(random_state=rng).as_matrix()
    params = KentParams(kappa=60.0, beta=25.0, gamma=gamma)
    y = sample_kent(params, 600, rng)
    R_true = exp_so3(np.array([0.05, -0.08, 0.03]))
    x = sample_kent(params, 600, rng) @ R_true
    result = paper_cluster_em(y, x, np.eye(3))
    # The mean direction is recovered; rotation about it is only weakly determined (by beta).
    mean_err = np.degrees(
        np.arccos(np.clip((result.R @ R_true.T @ gamma[:, 0]) @ gamma[:, 0], -1, 1))
    )
    assert mean_err < 1.5
    assert result.iterations >= 1 and len(result.log_likelihood) == result.iterations
    assert 0 < result.beta[0] < result.kappa[0] / 2


@pytest.mark.parametrize('seed', range(4))
def test_m_step_without_ovalness_is_wahbas_svd_solution(seed: int) -> None:
    """With A = 0 (von Mises-Fisher kernels) the M-step returns the SVD solution directly; it
    must be the minimiser the Newton solver reaches, and a rank-1 C (one normal direction)
    must leave the twist about it where it was."""
    from kentreg_ros.core.registration.em import _shared_m_step
    from kentreg_ros.core.registration.rotations import KentRotationProblem, solve_kent_rotation

    rng = np.random.default_rng(seed)
    x = rng.normal(size=(40, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    R_true = Rotation.random(random_state=seed).as_matrix()
    C = 100.0 * (x.T @ (x @ R_true.T))  # sum x y^T with y = R x: maximised by R_true
    problem = KentRotationProblem(np.zeros((2, 3, 3)), np.zeros((2, 3, 3)), C)
    R0 = Rotation.random(random_state=seed + 10).as_matrix()
    R_svd = _shared_m_step(problem, R0)
    R_newton, _ = solve_kent_rotation(problem, min([R0, R_svd], key=problem.value))
    # (matrix norms: the angle from arccos resolves only sqrt(eps) near zero)
    assert np.linalg.norm(R_svd - R_true) < 1e-10
    assert np.linalg.norm(R_svd - R_newton) < 1e-6
    # rank 1: only the direction a is seen; the twist about it is not determined by C
    a = np.array([0.0, 0.0, 1.0])
    one = KentRotationProblem(np.zeros((1, 3, 3)), np.zeros((1, 3, 3)), np.outer(a, a))
    R_start = exp_so3(np.array([0.0, 0.0, 0.7]))  # turned about a only: already optimal
    np.testing.assert_allclose(_shared_m_step(one, R_start), R_start, atol=1e-9)
