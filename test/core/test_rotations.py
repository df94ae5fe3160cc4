"""SO(3) helpers, the Riemannian Kent M-step solver and rotation averaging."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from kentreg_ros.core import exp_so3, log_so3, project_to_so3, rotation_angle
from kentreg_ros.core.registration.rotations import (
    KentRotationProblem,
    average_rotations,
    procrustes,
    solve_kent_rotation,
)


def _random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    return Rotation.random(n, random_state=rng).as_matrix()


def test_exp_log_round_trip_including_near_pi() -> None:
    rng = np.random.default_rng(0)
    for w in [*rng.normal(size=(20, 3)), np.array([1e-10, 0, 0]), np.array([0, np.pi - 1e-7, 0])]:
        R = exp_so3(w)
        np.testing.assert_allclose(R, Rotation.from_rotvec(w).as_matrix(), atol=1e-9)
        np.testing.assert_allclose(exp_so3(log_so3(R)), R, atol=1e-6)


def test_procrustes_recovers_rotation_from_noisy_vectors() -> None:
    rng = np.random.default_rng(1)
    R = _random_rotations(rng, 1)[0]
    x = rng.normal(size=(500, 3))
    y = x @ R.T + rng.normal(scale=0.01, size=x.shape)
    R_est = procrustes(x.T @ y)
    assert np.degrees(rotation_angle(R_est.T @ R)) < 0.2


def _random_problem(rng: np.random.Generator, beta: float, kappa: float) -> KentRotationProblem:
    g = _random_rotations(rng, 1)[0]
    A = np.outer(g[:, 2], g[:, 2]) - np.outer(g[:, 1], g[:, 1])
    x = rng.normal(size=(200, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    R_true = _random_rotations(rng, 1)[0]
    y = x @ R_true.T
    y += rng.normal(scale=0.3, size=y.shape)
    y /= np.linalg.norm(y, axis=1, keepdims=True)
    B = x.T @ x
    C = x.T @ y
    return KentRotationProblem(beta * A[None], B[None], kappa * C)


@pytest.mark.parametrize(('beta', 'kappa'), [(0.0, 10.0), (5.0, 20.0), (40.0, 100.0)])
def test_kent_rotation_solver_matches_brute_force_optimisation(beta: float, kappa: float) -> None:
    rng = np.random.default_rng(int(beta + kappa))
    problem = _random_problem(rng, beta, kappa)
    R_start = procrustes(problem.C)
    R_newton, _ = solve_kent_rotation(problem, R_start)
    # Brute force: many random starts of a derivative-free optimiser over rotation vectors.
    best = np.inf
    for w0 in rng.normal(scale=2.0, size=(30, 3)):
        res = minimize(
            lambda w: problem.value(exp_so3(w)),
            w0,
            method='Nelder-Mead',
            options={'xatol': 1e-10, 'fatol': 1e-12, 'maxiter': 4000},
        )
        best = min(best, res.fun)
    assert problem.value(R_newton) <= best + 1e-6 * max(1.0, abs(best))
    # First-order optimality relative to the problem's scale F, the size of the terms of f.
    # The solver accepts a step only when f decreases by more than its rounding noise
    # (~20 eps F for the ~20 products behind each term); a Newton step from gradient g gains
    # g^2 / (2 lambda) with lambda <= 2 F (the Hessian is a sum of the same terms), so it may
    # stop anywhere below |g| ~ sqrt(4 lambda 20 eps F) ~ 13 sqrt(eps) F. Where exactly depends
    # on the last bits of the BLAS kernel: measured |g| / F up to 2.6 sqrt(eps) over 7500 seeded
    # problems x 4 OpenBLAS kernels, and 1e-16 to 3e-9 for this very problem. 30 sqrt(eps) F
    # covers the worst case; stopping one Newton step early leaves |g| 13x (40/100) to 400x
    # (5/20) above it.
    F = np.linalg.norm(problem.C) + 2.0 * sum(
        np.linalg.norm(A) * np.linalg.norm(B) for A, B in zip(problem.A, problem.B, strict=True)
    )
    gradient_norm = np.linalg.norm(problem.gradient(R_newton))
    assert gradient_norm <= 30.0 * np.sqrt(np.finfo(float).eps) * F, (gradient_norm, F)


def test_kent_rotation_solver_gradient_matches_finite_differences() -> None:
    rng = np.random.default_rng(3)
    problem = _random_problem(rng, 7.0, 15.0)
    R = _random_rotations(rng, 1)[0]
    g = problem.gradient(R)
    h = 1e-6
    fd = [
        (problem.value(R @ exp_so3(h * e)) - problem.value(R @ exp_so3(-h * e))) / (2 * h)
        for e in np.eye(3)
    ]
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-6)


def test_kent_rotation_hessian_matches_second_differences_of_the_objective() -> None:
    """The closed-form Riemannian Hessian against second differences along random directions
    and the symmetrised central difference of the gradient."""
    rng = np.random.default_rng(4)
    parts = [_random_problem(rng, beta, 15.0) for beta in (7.0, 2.0, 5.0)]  # K = 3 components
    problem = KentRotationProblem(
        np.concatenate([p.A for p in parts]),
        np.concatenate([p.B for p in parts]),
        sum(p.C for p in parts),
    )
    for R in _random_rotations(rng, 5):
        H = problem.hessian(R)
        np.testing.assert_allclose(H, H.T, atol=1e-12)
        h = 1e-4
        for w in rng.normal(size=(4, 3)):
            d2 = (
                problem.value(R @ exp_so3(h * w))
                - 2.0 * problem.value(R)
                + problem.value(R @ exp_so3(-h * w))
            ) / h**2
            assert abs(d2 - w @ H @ w) < 1e-5 * max(1.0, abs(d2)), (d2, w @ H @ w)
        fd = np.column_stack(
            [
                (
                    problem.gradient(R @ exp_so3(1e-6 * e))
                    - problem.gradient(R @ exp_so3(-1e-6 * e))
                )
                / 2e-6
                for e in np.eye(3)
            ]
        )
        np.testing.assert_allclose(H, 0.5 * (fd + fd.T), rtol=1e-6, atol=1e-6 * np.abs(H).max())


@pytest.mark.parametrize('spread_deg', [1.0, 20.0, 60.0])
def test_average_matches_scipy_rotation_mean(spread_deg: float) -> None:
    rng = np.random.default_rng(4)
    center = _random_rotations(rng, 1)[0]
    Rs = np.array(
        [center @ exp_so3(rng.normal(size=3) * np.radians(spread_deg)) for _ in range(7)]
    )
    w = rng.random(7)
    for weights in (None, w):
        ours = average_rotations(Rs, weights)
        theirs = Rotation.from_matrix(Rs).mean(weights=weights).as_matrix()
        np.testing.assert_allclose(ours, theirs, atol=1e-9)


def test_average_of_identical_rotations_is_that_rotation() -> None:
    R = _random_rotations(np.random.default_rng(5), 1)[0]
    np.testing.assert_allclose(average_rotations(np.array([R, R, R])), R, atol=1e-12)


def test_average_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match=r'shape \(K, 3, 3\)'):
        average_rotations(np.zeros((3, 3)))
    with pytest.raises(ValueError, match='non-negative'):
        average_rotations(np.array([np.eye(3)]), [-1.0])


def test_project_to_so3_returns_a_rotation() -> None:
    M = np.random.default_rng(6).normal(size=(3, 3))
    R = project_to_so3(M)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_check_transform_accepts_exactly_what_allclose_accepts() -> None:
    """The transform check's tolerances are np.allclose's (atol, and its default rtol), in
    one comparison each: perturbations around both bounds are judged the same way."""
    from kentreg_ros.core.errors import InvalidInputError
    from kentreg_ros.core.geometry import ORTHONORMAL_TOLERANCE, check_transform

    rng = np.random.default_rng(8)
    seen = set()
    for scale in np.geomspace(1e-9, 1e-4, 60):
        T = np.eye(4)
        T[:3, :3] += rng.normal(size=(3, 3)) * scale
        T[3, :3] += rng.normal(size=3) * scale * 1e-3
        R = T[:3, :3]
        want = (
            np.allclose(R.T @ R, np.eye(3), atol=ORTHONORMAL_TOLERANCE)
            and np.linalg.det(R) >= 0.0
            and np.allclose(T[3], [0.0, 0.0, 0.0, 1.0])
        )
        try:
            check_transform(T, 'T')
            got = True
        except InvalidInputError:
            got = False
        assert got == want, scale
        seen.add(got)
    assert seen == {True, False}  # both sides of the bounds were tried
