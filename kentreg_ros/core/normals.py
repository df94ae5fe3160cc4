"""Surface normals by PCA over k nearest neighbours, oriented toward a viewpoint.

Implements Section 3.1 of Fahandezh-Saadi et al.: PCA normals (Klasing et al. 2009),
viewpoint-consistent orientation ``n . (vp - x) > 0`` (Rusu 2013), and removal of normals whose
cosine similarity to their neighbourhood's mean normal is low (after Zhang 1994, Rusu 2008).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from kentreg_ros.core.errors import InvalidPointCloudError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class NormalEstimate:
    """PCA normals of a point cloud.

    Attributes
    ----------
    normals : ndarray, shape (N, 3)
        Unit normals oriented toward the viewpoint.
    curvature : ndarray, shape (N,)
        Surface variation ``l0 / (l0 + l1 + l2)`` of the local covariance (0 = planar,
        1/3 = isotropic).
    neighbors : ndarray of int, shape (N, k)
        Indices of the k nearest neighbours (including the point itself).
    """

    normals: FloatArray
    curvature: FloatArray
    neighbors: NDArray[np.intp]


def estimate_normals(
    points: FloatArray,
    k: int = 15,
    *,
    viewpoint: ArrayLike = (0.0, 0.0, 0.0),
    tree: cKDTree | None = None,
) -> NormalEstimate:
    """Estimate unit surface normals by PCA over the k nearest neighbours.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
    k : int
        Neighbourhood size (the paper uses 15); ``N >= k`` is required.
    viewpoint : array_like, shape (3,)
        Normals are flipped so that ``n . (viewpoint - x) > 0``.
    tree : cKDTree, optional
        A tree already built on ``points``.

    Raises
    ------
    InvalidPointCloudError
        If there are fewer than ``k`` points.
    """
    n = len(points)
    if k < 3:
        raise ValueError(f'Expected `k` >= 3, got {k}.')
    if n < k:
        raise InvalidPointCloudError(
            f'Expected at least k={k} points to estimate normals, got {n}.'
        )
    if tree is None:
        tree = cKDTree(points)
    _, idx = tree.query(points, k=k, workers=-1)
    idx = np.asarray(idx, dtype=np.intp)
    centered = points - points.mean(axis=0)
    nb = centered[idx]  # (N, k, 3)
    mean = nb.mean(axis=1)
    cov = np.einsum('nki,nkj->nij', nb, nb) / k - mean[:, :, None] * mean[:, None, :]
    evals, evecs = np.linalg.eigh(cov)
    normals = np.ascontiguousarray(evecs[:, :, 0])
    total = evals.sum(axis=1)
    curvature = np.where(total > 0, evals[:, 0] / np.where(total > 0, total, 1.0), 1.0 / 3.0)
    normals = orient_normals(points, normals, viewpoint)
    return NormalEstimate(
        normals=normals, curvature=np.clip(curvature, 0.0, 1.0 / 3.0), neighbors=idx
    )


def orient_normals(
    points: FloatArray, normals: FloatArray, viewpoint: ArrayLike = (0.0, 0.0, 0.0)
) -> FloatArray:
    """Flip normals so that ``n . (viewpoint - x) >= 0`` (Rusu 2013)."""
    vp = np.asarray(viewpoint, dtype=np.float64).reshape(3)
    sign = np.where(np.einsum('ij,ij->i', normals, vp - points) < 0.0, -1.0, 1.0)
    return normals * sign[:, None]


def normal_consistency(normals: FloatArray, neighbors: NDArray[np.intp]) -> FloatArray:
    """Cosine between each normal and the mean normal of its neighbourhood, shape (N,)."""
    mean = normals[neighbors].sum(axis=1)
    norm = np.linalg.norm(mean, axis=1)
    return np.einsum('ij,ij->i', normals, mean) / np.maximum(norm, 1e-12)


def normal_inlier_mask(
    normals: FloatArray, neighbors: NDArray[np.intp], min_cosine: float
) -> NDArray[np.bool_]:
    """Mask of normals agreeing with their neighbourhood (cosine >= ``min_cosine``).

    ``min_cosine <= -1`` keeps every normal.
    """
    if min_cosine <= -1.0:
        return np.ones(len(normals), dtype=bool)
    return normal_consistency(normals, neighbors) >= min_cosine
