"""Rotation estimation: Procrustes, the Kent M-step solver, rotation averaging."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core.errors import InvalidInputError
from kentreg_ros.core.geometry import exp_so3, project_to_so3, vee

FloatArray = NDArray[np.float64]


def procrustes(C: FloatArray) -> FloatArray:
    """``argmax_{R in SO(3)} tr(R C)`` (Wahba's problem), with ``C = sum w x y^T``.

    The returned R rotates the ``x`` vectors onto the ``y`` vectors.
    """
    U, _, Vt = np.linalg.svd(C)
    V = Vt.T
    d = np.sign(np.linalg.det(V @ U.T)) or 1.0
    return V @ np.diag([1.0, 1.0, d]) @ U.T


@dataclass(frozen=True)
class KentRotationProblem:
    """The M-step objective ``f(R) = sum_k tr(R^T A_k R B_k) - tr(R C)``.

    This is the paper's eq. (solve_for_R) ``beta tr(R^T A R B) - kappa tr(R C)`` generalised to
    several Kent components: pass ``A_k`` already scaled by ``beta_k`` and ``C`` already scaled
    by the ``kappa_k``. ``A_k`` and ``B_k`` are symmetric.

    Attributes
    ----------
    A : ndarray, shape (K, 3, 3)
    B : ndarray, shape (K, 3, 3)
    C : ndarray, shape (3, 3)
    """

    A: FloatArray
    B: FloatArray
    C: FloatArray

    def value(self, R: FloatArray) -> float:
        quad = np.vdot(R.T @ self.A @ R, self.B)  # sum_k tr(R^T A_k R B_k), B_k symmetric
        return float(quad - np.trace(R @ self.C))

    def gradient(self, R: FloatArray) -> FloatArray:
        """Riemannian gradient for the right perturbation ``R exp(hat(w))``, shape (3,)."""
        G = 2.0 * (self.A @ R @ self.B).sum(axis=0) - self.C.T
        M = R.T @ G
        return 2.0 * vee(M)

    def hessian(self, R: FloatArray) -> FloatArray:
        """Riemannian Hessian for the right perturbation ``R exp(hat(w))``, shape (3, 3).

        Closed form from the second-order expansion ``exp(hat(w)) = I + hat(w) +
        hat(w)^2 / 2 + O(|w|^3)`` with ``At_k = R^T A_k R`` and ``Ct = C R``: the quadratic
        term is ``sum_k [-tr(hat(w) At_k hat(w) B_k) + tr(hat(w)^2 S_k) / 2] -
        tr(hat(w)^2 Ct) / 2`` with ``S_k = At_k B_k + B_k At_k``, and
        ``hat(w)^2 = w w^T - |w|^2 I``. Symmetric; equals the symmetrised central difference
        of :meth:`gradient` (the connection term is antisymmetric).
        """
        At = R.T @ self.A @ R  # (K, 3, 3)
        B = self.B
        AB = At @ B
        S = AB.sum(axis=0)
        S = S + S.T  # sum_k (At_k B_k + B_k At_k)
        # M_ef = sum_k eps_abe eps_cdf At_bc B_da, expanded with the epsilon-delta identity:
        # M = sum_k (<At, B> - tr At tr B) I - (B At + At B) + tr(B) At + tr(At) B.
        tr_a = np.trace(At, axis1=1, axis2=2)
        tr_b = np.trace(B, axis1=1, axis2=2)
        scalar = float(np.trace(AB, axis1=1, axis2=2).sum() - tr_a @ tr_b)
        M = scalar * np.eye(3) - S + np.tensordot(tr_b, At, axes=1) + np.tensordot(tr_a, B, axes=1)
        Ct = self.C @ R
        Cs = 0.5 * (Ct + Ct.T)
        H = -(M + M.T) + S - np.trace(S) * np.eye(3) - Cs + np.trace(Cs) * np.eye(3)
        out: FloatArray = 0.5 * (H + H.T)
        return out


def solve_kent_rotation(
    problem: KentRotationProblem,
    R0: FloatArray,
    *,
    max_iterations: int = 50,
    tolerance: float = 1e-12,
) -> tuple[FloatArray, int]:
    """Minimise a :class:`KentRotationProblem` over SO(3) by Riemannian Newton steps.

    Newton directions come from the Riemannian Hessian (damped to be positive definite, so a
    descent direction always results); step lengths from Armijo backtracking along the
    retraction ``R exp(hat(w))``. Converges quadratically near a non-degenerate minimum.

    Returns
    -------
    R : ndarray, shape (3, 3)
    iterations : int
    """
    R = np.array(R0, dtype=np.float64)
    f = problem.value(R)
    it = 0
    for it in range(1, max_iterations + 1):
        g = problem.gradient(R)
        gnorm = float(np.linalg.norm(g))
        if gnorm < tolerance:
            break
        H = problem.hessian(R)
        evals, evecs = np.linalg.eigh(H)
        floor = max(1e-9, 1e-6 * float(np.max(np.abs(evals))))
        evals = np.maximum(np.abs(evals), floor)
        step = -(evecs @ ((evecs.T @ g) / evals))
        slope = float(g @ step)
        t = 1.0
        while t > 1e-10:
            R_new = R @ exp_so3(t * step)
            f_new = problem.value(R_new)
            if f_new <= f + 1e-4 * t * slope:
                break
            t *= 0.5
        else:
            break
        R, f_prev, f = project_to_so3(R_new), f, f_new
        if float(np.linalg.norm(t * step)) < 1e-13 or abs(f_prev - f) <= 1e-15 * max(1, abs(f)):
            break
    return R, it


def average_rotations(
    rotations: Sequence[FloatArray] | FloatArray, weights: ArrayLike | None = None
) -> FloatArray:
    """Euclidean (chordal L2) mean of rotations, as in the paper's eq. (rot_avg) (Moakher 2002).

    ``R = Rbar U diag(1/sqrt(l1), 1/sqrt(l2), s/sqrt(l3)) U^T`` where ``Rbar`` is the
    (weighted) arithmetic mean, ``Rbar^T Rbar = U diag(l1, l2, l3) U^T`` with ``l3`` the smallest
    eigenvalue, and ``s = sign(det Rbar)``.

    Parameters
    ----------
    rotations : array_like, shape (K, 3, 3)
    weights : array_like, shape (K,), optional
        Non-negative weights (default: equal).
    """
    Rs = np.asarray(rotations, dtype=np.float64)
    if Rs.ndim != 3 or Rs.shape[1:] != (3, 3) or len(Rs) == 0:
        raise InvalidInputError(f'Expected `rotations` to have shape (K, 3, 3), got {Rs.shape}.')
    w = np.ones(len(Rs)) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (len(Rs),) or np.any(w < 0) or not w.sum() > 0:
        raise InvalidInputError(
            f'Expected {len(Rs)} non-negative weights with a positive sum, got {w}.'
        )
    Rbar = np.einsum('k,kij->ij', w / w.sum(), Rs)
    evals, U = np.linalg.eigh(Rbar.T @ Rbar)  # ascending: evals[0] is the smallest
    evals = np.maximum(evals, 1e-15)
    s = 1.0 if np.linalg.det(Rbar) > 0 else -1.0
    scale = np.array([s / np.sqrt(evals[0]), 1.0 / np.sqrt(evals[1]), 1.0 / np.sqrt(evals[2])])
    return Rbar @ U @ np.diag(scale) @ U.T
