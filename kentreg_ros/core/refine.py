"""Joint 6-DOF refinement on positions and Kent-weighted normals.

The hybrid direction of G-IMLOP (Billings & Taylor 2015) and Min et al. (2019) cited by the
paper: every correspondence carries a positional term and an orientational term. Here the
positional term is point-to-plane, or plane-to-plane with GICP-style covariances (Segal et al.
2009) built from our normals, and the orientational term enters as a Kent/von Mises-Fisher
likelihood weight ``exp(kappa (n_q . R n_p - 1))`` of the two normals. A Geman-McClure kernel on
the point-to-plane distance rejects outliers. Solved by Gauss-Newton on SE(3) with the left
perturbation ``T <- exp(delta) T``, ``delta = (omega, v)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from kentreg_ros.core.rotations import exp_so3, hat, project_to_so3
from kentreg_ros.core.translation import geman_mcclure_weights, robust_scale

FloatArray = NDArray[np.float64]

PLANE_EPSILON = 1e-3


@dataclass(frozen=True)
class RefineResult:
    """Outcome of :func:`refine_joint`.

    Attributes
    ----------
    T : ndarray, shape (4, 4)
        Refined ``T_target_source``.
    hessian : ndarray, shape (6, 6)
        Gauss-Newton information matrix in (omega, v) order.
    sigma2 : float
        Weighted mean squared (Mahalanobis) residual.
    iterations : int
    converged : bool
    inlier_fraction : float
        Fraction of source points with a gated correspondence at the end.
    kappa_normal : float
        Concentration used for the normal weights at the end.
    """

    T: FloatArray
    hessian: FloatArray
    sigma2: float
    iterations: int
    converged: bool
    inlier_fraction: float
    kappa_normal: float


def plane_covariances(normals: FloatArray, epsilon: float = PLANE_EPSILON) -> FloatArray:
    """GICP's regularised planar covariances ``I - (1 - eps) n n^T``, shape (N, 3, 3)."""
    return np.eye(3)[None] - (1.0 - epsilon) * np.einsum('ni,nj->nij', normals, normals)


def _solve_spd(H: FloatArray, g: FloatArray) -> FloatArray:
    reg = 1e-9 * max(float(np.trace(H)), 1e-12)
    return np.linalg.solve(H + reg * np.eye(len(H)), g)


def refine_joint(
    T0: FloatArray,
    source: FloatArray,
    source_normals: FloatArray,
    target: FloatArray,
    target_normals: FloatArray,
    target_tree: cKDTree,
    *,
    method: str = 'plane_to_plane',
    normal_weight: bool = True,
    max_iterations: int = 30,
    max_distance: float = 1.0,
    min_distance: float = 0.1,
    tolerance: float = 1e-5,
    noise_floor: float = 0.005,
    kappa_range: tuple[float, float] = (5.0, 500.0),
) -> RefineResult:
    """Refine ``T_target_source`` by robust, normal-weighted Gauss-Newton.

    Parameters
    ----------
    T0 : ndarray, shape (4, 4)
        Start (the decoupled rotation/translation estimate).
    source, source_normals : ndarray, shape (N, 3)
    target, target_normals : ndarray, shape (M, 3)
    target_tree : cKDTree
        Tree on ``target``.
    method : {'plane_to_plane', 'point_to_plane'}
    normal_weight : bool
        Multiply each correspondence's weight by ``exp(kappa (n_q . R n_p - 1))``, kappa being
        re-estimated from the current normal residuals (clipped to ``kappa_range``).
    max_distance, min_distance : float
        The correspondence gate shrinks geometrically from the first to the second.
    """
    R = T0[:3, :3].copy()
    t = T0[:3, 3].copy()
    gate = max_distance
    Cs = plane_covariances(source_normals) if method == 'plane_to_plane' else None
    Ct = plane_covariances(target_normals) if method == 'plane_to_plane' else None
    H = np.zeros((6, 6))
    sigma2 = 0.0
    inlier = 0.0
    kappa_n = kappa_range[0]
    converged = False
    it = 0
    for it in range(1, max_iterations + 1):
        x = source @ R.T + t
        dist, idx = target_tree.query(x, k=1, distance_upper_bound=gate, workers=-1)
        ok = np.flatnonzero(np.isfinite(dist))
        if len(ok) < 12:
            break
        j = idx[ok]
        xo = x[ok]
        e = target[j] - xo  # residual vector, (n, 3)
        nq = target_normals[j]
        np_rot = source_normals[ok] @ R.T
        r_plane = np.einsum('ij,ij->i', nq, e)
        sigma = robust_scale(r_plane, noise_floor)
        w = geman_mcclure_weights(r_plane, sigma)
        if normal_weight:
            cos = np.einsum('ij,ij->i', nq, np_rot)
            resid = np.maximum(1.0 - cos, 0.0)
            kappa_n = float(np.clip(1.0 / max(float(np.average(resid, weights=w + 1e-12)),
                                              1e-9), *kappa_range))
            w = w * np.exp(kappa_n * (cos - 1.0))
        # J = d e / d delta = [hat(x), -I] for the left perturbation delta = (omega, v).
        J = np.zeros((len(ok), 3, 6))
        J[:, :, :3] = hat(xo)
        J[:, :, 3:] = -np.eye(3)
        if method == 'plane_to_plane':
            assert Cs is not None and Ct is not None
            cov = Ct[j] + np.einsum('ij,njk,lk->nil', R, Cs[ok], R)
            W = np.linalg.inv(cov) * w[:, None, None]
            JW = np.einsum('nai,nab->nib', J, W)  # J^T W, (n, 6, 3)
            H = np.einsum('nib,nbj->ij', JW, J)
            g = np.einsum('nib,nb->i', JW, e)
            maha = np.einsum('na,nab,nb->n', e, W, e)
            sigma2 = float(np.sum(maha) / max(float(w.sum()), 1e-12))
        else:
            Jn = np.einsum('na,nai->ni', nq, J)  # (n, 6)
            H = (Jn * w[:, None]).T @ Jn
            g = (Jn * w[:, None]).T @ r_plane
            sigma2 = float(np.sum(w * r_plane**2) / max(float(w.sum()), 1e-12))
        delta = -_solve_spd(H, g)
        dR = exp_so3(delta[:3])
        R = project_to_so3(dR @ R)
        t = dR @ t + delta[3:]
        inlier = len(ok) / len(source)
        gate = max(gate * 0.7, min_distance)
        if (np.linalg.norm(delta[:3]) < tolerance and np.linalg.norm(delta[3:]) < tolerance
                and gate <= min_distance):
            converged = True
            break
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return RefineResult(T=T, hessian=H, sigma2=sigma2, iterations=it, converged=converged,
                        inlier_fraction=inlier, kappa_normal=kappa_n)
