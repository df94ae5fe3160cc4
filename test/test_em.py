"""EM on the sphere recovers the rotation of synthetic Kent mixtures."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kentreg_ros.core.em import ModelClusters, paper_cluster_em, shared_rotation_em
from kentreg_ros.core.kent import KentParams, sample_kent
from kentreg_ros.core.rotations import exp_so3, rotation_angle


def _mixture(
    rng: np.random.Generator, n_per: int, kappa: float, beta: float
) -> tuple[np.ndarray, np.ndarray]:
    """Samples of a 4-component Kent mixture with well separated means, and their labels."""
    frames = Rotation.random(4, random_state=rng).as_matrix()
    means = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [-0.6, -0.8, 0]])
    samples = []
    for f, m in zip(frames, means, strict=True):
        a = np.cross(m, f[:, 0])
        a /= np.linalg.norm(a)
        gamma = np.column_stack([m, a, np.cross(m, a)])
        samples.append(sample_kent(KentParams(kappa=kappa, beta=beta, gamma=gamma), n_per, rng))
    return np.concatenate(samples), np.repeat(np.arange(4), n_per)


@pytest.mark.parametrize(('angle_deg', 'outliers'), [(5.0, 0.0), (20.0, 0.0), (10.0, 0.3)])
def test_shared_rotation_em_recovers_rotation_of_kent_mixture(
    angle_deg: float, outliers: float
) -> None:
    rng = np.random.default_rng(int(angle_deg) + int(10 * outliers))
    y, labels = _mixture(rng, 1500, kappa=150.0, beta=50.0)
    model = ModelClusters.from_labels(y, labels, 4)
    x_model_frame, _ = _mixture(np.random.default_rng(99), 1500, kappa=150.0, beta=50.0)
    axis = rng.normal(size=3)
    R_true = exp_so3(axis / np.linalg.norm(axis) * np.radians(angle_deg))
    x = x_model_frame @ R_true  # observed normals: y = R_true x
    if outliers:
        m = int(len(x) * outliers / (1 - outliers))
        junk = rng.normal(size=(m, 3))
        x = np.concatenate([x, junk / np.linalg.norm(junk, axis=1, keepdims=True)])
    result = shared_rotation_em(x, model, np.eye(3))
    assert np.degrees(rotation_angle(result.R.T @ R_true)) < 0.5
    assert result.inlier_fraction < 1.0 - 0.8 * outliers + 1e-9
    assert np.all(result.beta < result.kappa / 2)


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
    assert result.beta[0] < result.kappa[0] / 2
