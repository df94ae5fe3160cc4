"""kentreg_ros.core.registration.uncertainty and the odometry's twist covariance.

The covariance of a registration is checked against the scatter of repeated registrations of
seeded synthetic scenes with a known transform (its convention: ``exp(d) = T_true T^-1``, the
left perturbation in the target frame, order x, y, z, roll, pitch, yaw), its growth with the
noise, its inflation along a corridor's axis, and its parts on rows built by hand; the twist's
against a Monte Carlo of perturbed steps.
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray
from scenes import box_room, corridor

from kentreg_ros.core import exp_so3, log_so3, make_transform, register
from kentreg_ros.core.geometry import invert_transform
from kentreg_ros.core.odometry.covariance import twist_covariance
from kentreg_ros.core.registration.uncertainty import (
    Residuals,
    inflate_degenerate,
    pose_covariance,
)

FloatArray = NDArray[np.float64]

T_TRUE = make_transform(exp_so3(np.array([0.02, -0.01, 0.6])), np.array([0.4, -0.2, 0.05]))
INIT = make_transform(exp_so3(np.array([0.0, 0.0, 0.55])), np.array([0.3, -0.1, 0.0]))


def _step_error(T_true: FloatArray, T_est: FloatArray) -> FloatArray:
    E = T_true @ invert_transform(T_est)
    return np.concatenate([E[:3, 3], log_so3(E[:3, :3])])


def _room_pair(seed: int, noise: float, n: int = 20000) -> tuple[FloatArray, FloatArray]:
    """Two independent samplings of one room (its geometry fixed), the source moved by
    ``T_TRUE^-1`` so that ``T_target_source = T_TRUE``."""
    surface = box_room(np.random.default_rng(7), 3 * n, noise=0.0)
    rng = np.random.default_rng([seed, 1])
    target, source = (
        surface[rng.choice(len(surface), n, replace=False)] + rng.normal(0.0, noise, (n, 3))
        for _ in range(2)
    )
    return (source - T_TRUE[:3, 3]) @ T_TRUE[:3, :3], target


def test_covariance_is_symmetric_positive_definite() -> None:
    source, target = _room_pair(0, 0.01)
    cov = register(source, target, init=INIT).covariance
    np.testing.assert_allclose(cov, cov.T, rtol=0, atol=1e-15)
    assert np.linalg.eigvalsh(cov).min() > 0.0


def test_covariance_matches_the_scatter_of_repeated_registrations() -> None:
    """NEES of the step error in the documented convention over independent samplings: a
    consistent 6-DOF covariance gives a median of 5.3; the synthetic planes are cleaner than
    a LiDAR's surfaces, so somewhat conservative is expected, too confident is not."""
    nees = []
    for seed in range(8):
        source, target = _room_pair(seed, 0.01)
        result = register(source, target, init=INIT)
        d = _step_error(T_TRUE, result.T_target_source)
        nees.append(float(d @ np.linalg.solve(result.covariance, d)))
    assert 1.0 < np.median(nees) < 12.0


def test_covariance_grows_with_the_noise() -> None:
    """Three times the range noise: each sigma about three times larger, or more (the normals
    are fitted to the noisier points too)."""
    sigma = {}
    for noise in (0.01, 0.03):
        source, target = _room_pair(0, noise)
        cov = register(source, target, init=INIT).covariance
        sigma[noise] = np.sqrt(np.diag(cov))
    ratio = sigma[0.03] / sigma[0.01]
    assert np.all(ratio > 2.0) and np.all(ratio < 6.0), ratio


def test_corridor_axis_is_flagged_and_its_variance_inflated() -> None:
    """Along a featureless corridor (x) the pose is held by nothing: the degeneracy test flags
    x and the covariance along it is at least the distinct distance's square, hundreds of
    times the other axes'."""
    target = corridor(np.random.default_rng(1), 20000, 0.01)
    source = (corridor(np.random.default_rng(2), 20000, 0.01) - T_TRUE[:3, 3]) @ T_TRUE[:3, :3]
    result = register(source, target, init=INIT)
    assert len(result.degenerate_directions) == 1
    assert abs(result.degenerate_directions[0][0]) > 0.95
    var = np.diag(result.covariance)
    assert var[0] > 0.1**2 and var[0] > 100 * max(var[1], var[2])
    d = _step_error(T_TRUE, result.T_target_source)
    assert abs(d[0]) < 2.0 * np.sqrt(var[0])


def test_inflate_degenerate_adds_along_the_direction_only() -> None:
    cov = np.diag([1e-6] * 3 + [1e-8] * 3)
    u = np.array([0.6, 0.8, 0.0])
    out = inflate_degenerate(
        cov, u[None], 0.5, rotation_axis=np.array([0, 0, 1.0]), sigma_rotation=0.1
    )
    np.testing.assert_allclose(out - cov, np.block([
        [0.25 * np.outer(u, u), np.zeros((3, 3))],
        [np.zeros((3, 3)), np.diag([0.0, 0.0, 0.01])],
    ]), atol=1e-15)  # fmt: skip
    np.testing.assert_array_equal(inflate_degenerate(cov, np.zeros((0, 3)), 0.5), cov)


def _rows(rng: np.random.Generator, n: int, sigma: float, scale: float = 1.0) -> Residuals:
    """Rows on the six faces of a 4 m box around the origin, white residuals of ``sigma``,
    unit weights, the kernel's scale ``scale``."""
    axis = rng.integers(0, 3, n)
    sign = rng.choice([-1.0, 1.0], n)
    normals = np.zeros((n, 3))
    normals[np.arange(n), axis] = sign
    points = rng.uniform(-2.0, 2.0, (n, 3))
    points[np.arange(n), axis] = 2.0 * sign
    r = rng.normal(0.0, sigma, n)
    return Residuals(points, normals, r, np.ones(n), scale)


def test_white_residuals_within_the_kernel_give_least_squares_covariance() -> None:
    """Residuals far inside the kernel's scale, every row its own cell, no calibration: the
    sandwich is the least-squares ``sigma^2 H^-1``."""
    rows = _rows(np.random.default_rng(0), 20000, 0.01, scale=10.0)
    cov = pose_covariance(rows, 0.0, calibration=1.0)
    J = np.column_stack([np.cross(rows.normals, rows.points), -rows.normals])
    expected = 0.01**2 * np.linalg.inv(J.T @ J)
    order = [3, 4, 5, 0, 1, 2]
    np.testing.assert_allclose(np.diag(cov), np.diag(expected[np.ix_(order, order)]), rtol=0.1)


def test_residuals_near_the_kernel_scale_weigh_less_than_irls_says() -> None:
    """The robust cost's curvature, not IRLS's weights: the same residuals give a larger
    covariance when they lie near the Geman-McClure scale than far inside it."""
    rng = np.random.default_rng(1)
    rows = _rows(rng, 5000, 0.01, scale=10.0)
    near = Residuals(rows.points, rows.normals, rows.residuals, rows.weights, 0.012)
    wide = pose_covariance(rows, 0.0)
    tight = pose_covariance(near, 0.0)
    assert np.all(np.diag(tight) > 1.5 * np.diag(wide))


def test_cells_count_the_rows_of_one_patch_once() -> None:
    """Rows of one cell sharing their residual error are one measurement: with cells, the
    covariance is about the rows per cell times that of independent rows."""
    rng = np.random.default_rng(2)
    rows = _rows(rng, 20000, 0.01, scale=10.0)
    edge = 0.5  # 8 x 8 cells per face: about 40 rows per cell
    cell = np.floor(rows.points / edge).astype(int)
    _, which = np.unique(cell, axis=0, return_inverse=True)
    shared = rng.normal(0.0, 0.01, which.max() + 1)[which.ravel()]
    patchy = Residuals(rows.points, rows.normals, shared, rows.weights, rows.scale)
    per_cell = len(rows) / (which.max() + 1)
    ratio = np.diag(pose_covariance(patchy, edge / 8.0)) / np.diag(pose_covariance(patchy, 0.0))
    assert np.all(ratio > 0.4 * per_cell) and np.all(ratio < 2.0 * per_cell), ratio


def _corridor_rows(rng: np.random.Generator, n: int, wall_offset: float) -> Residuals:
    """Rows on the walls (y = +-1.2 m, normals inwards), floor and ceiling (z = -+1.3 m) of a
    30 m corridor along x: white residuals of 2 mm, and ``wall_offset`` on both walls (the
    source's corridor that much narrower than the target's: what a fit shows of an error each
    wall's points share, the rest of which moved the pose across the corridor)."""
    face = rng.integers(0, 4, n)
    normals = np.zeros((n, 3))
    normals[face == 0, 1], normals[face == 1, 1] = -1.0, 1.0
    normals[face == 2, 2], normals[face == 3, 2] = 1.0, -1.0
    points = np.column_stack(
        [rng.uniform(-15.0, 15.0, n), rng.uniform(-1.2, 1.2, n), rng.uniform(-1.3, 1.3, n)]
    )
    points[face < 2, 1] = -1.2 * normals[face < 2, 1]
    points[face >= 2, 2] = -1.3 * normals[face >= 2, 2]
    r = rng.normal(0.0, 0.002, n) + np.where(face < 2, wall_offset, 0.0)
    return Residuals(points, normals, r, np.ones(n), 10.0)


def test_planes_count_an_error_their_rows_share_once() -> None:
    """An offset all of one wall's rows share is invisible in the scatter between its cells and
    plain in the walls' sums: with the planes as clusters too, the lateral sigma is of the
    order of that offset (without, about a tenth of it: one wall is ~170 cells of 8 spacings),
    and the white rows of the box keep the cells' covariance."""
    offset = 0.001
    rows = _corridor_rows(np.random.default_rng(4), 8000, offset)
    sigma_y = np.sqrt(pose_covariance(rows, 0.09)[1, 1])
    assert 0.5 * offset < sigma_y < 3.0 * offset, sigma_y
    white = _rows(np.random.default_rng(5), 20000, 0.01, scale=10.0)
    ratio = np.diag(pose_covariance(white, 0.06)) / np.diag(pose_covariance(white, 0.0))
    assert np.all(ratio < 2.0), ratio  # 2 m faces, cells of 0.5 m: 16 per face


def test_covariance_turns_with_the_frame_of_the_rows() -> None:
    """The same rows in a frame turned by Q: the covariance turns with it (translation and
    rotation about the frame's axes)."""
    rows = _rows(np.random.default_rng(3), 3000, 0.01, scale=0.02)
    Q = exp_so3(np.array([0.3, -0.5, 1.1]))
    turned = Residuals(rows.points @ Q.T, rows.normals @ Q.T, rows.residuals, rows.weights, 0.02)
    B = np.kron(np.eye(2), Q)
    np.testing.assert_allclose(
        pose_covariance(turned, 0.0), B @ pose_covariance(rows, 0.0) @ B.T, rtol=1e-8, atol=1e-14
    )


@pytest.mark.parametrize('mounted', [False, True])
def test_twist_covariance_matches_monte_carlo(mounted: bool) -> None:
    """The twist ``(R^T t, log R) / dt`` of a step perturbed as its covariance says, in a frame
    mounted away from the sensor (a rotation of the sensor moves it) or the sensor's own."""
    rng = np.random.default_rng(4)
    T = make_transform(exp_so3(np.array([0.05, -0.1, 0.3])), np.array([0.8, 0.1, -0.05]))
    A = make_transform(exp_so3(np.array([0.1, 0.2, -0.4])), np.array([0.5, -1.2, 1.5]))
    A = A if mounted else np.eye(4)
    L = rng.normal(size=(6, 6)) * 1e-3
    S = L @ L.T
    dt = 0.1

    def twist(T_step: FloatArray) -> FloatArray:
        M = A @ T_step @ invert_transform(A)
        return np.concatenate([M[:3, :3].T @ M[:3, 3], log_so3(M[:3, :3])]) / dt

    base = twist(T)
    draws = rng.multivariate_normal(np.zeros(6), S, 20000)
    samples = [twist(make_transform(exp_so3(d[3:]), d[:3]) @ T) - base for d in draws]
    expected = np.cov(np.array(samples).T)
    got = twist_covariance(S, T, dt, A if mounted else None)
    assert np.abs(got - expected).max() < 0.05 * np.abs(expected).max()
