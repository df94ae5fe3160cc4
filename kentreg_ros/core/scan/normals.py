"""Surface normals by PCA over k nearest neighbours, oriented toward a viewpoint.

Implements Section 3.1 of Fahandezh-Saadi et al.: PCA normals (Klasing et al. 2009),
viewpoint-consistent orientation ``n . (vp - x) > 0`` (Rusu 2013), and removal of normals whose
cosine similarity to their neighbourhood's mean normal is low (after Zhang 1994, Rusu 2008).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core import kernels
from kentreg_ros.core.errors import InvalidInputError, InvalidPointCloudError
from kentreg_ros.core.scan.neighbors import NeighborIndex

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
    flatness : ndarray, shape (N,)
        ``l0 / l1``, the smallest over the middle eigenvalue of the local covariance: small on
        a plane (also a narrow strip of one), near 1 where the normal is undefined (a line of
        points, an isotropic blob). See :func:`planar_mask`.
    neighbors : ndarray of int, shape (N, k)
        Indices of the k nearest neighbours (including the point itself).
    """

    normals: FloatArray
    curvature: FloatArray
    flatness: FloatArray
    neighbors: NDArray[np.intp]


def estimate_normals(
    points: FloatArray,
    k: int = 15,
    *,
    viewpoint: ArrayLike = (0.0, 0.0, 0.0),
    neighbors: NDArray[np.intp] | None = None,
) -> NormalEstimate:
    """Estimate unit surface normals by PCA over the k nearest neighbours.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
    k : int
        Neighbourhood size (the paper uses 15); ``N >= k`` is required.
    viewpoint : array_like, shape (3,)
        Normals are flipped so that ``n . (viewpoint - x) > 0``.
    neighbors : ndarray of int, shape (N, k), optional
        The ``k`` nearest neighbours of every point (each row including the point), already
        queried (e.g. on a tree the caller keeps); otherwise queried here.

    Raises
    ------
    InvalidPointCloudError
        If there are fewer than ``k`` points.
    """
    n = len(points)
    if k < 3:
        raise InvalidInputError(f'Expected `k` >= 3, got {k}.')
    if n < k:
        raise InvalidPointCloudError(
            f'Expected at least k={k} points to estimate normals, got {n}.'
        )
    if neighbors is not None:
        idx = np.asarray(neighbors, dtype=np.intp)
        if idx.shape != (n, k):
            raise InvalidInputError(f'Expected `neighbors` of shape {(n, k)}, got {idx.shape}.')
    else:
        idx = NeighborIndex(points).neighbor_indices(points, k)
    cov = neighbourhood_covariances(points, idx)
    evals, normals, mid = smallest_eigenpairs_3x3(cov)
    total = cov[:, 0] + cov[:, 3] + cov[:, 5]
    curvature = np.where(total > 0, evals / np.where(total > 0, total, 1.0), 1.0 / 3.0)
    lo = np.maximum(evals, 0.0)
    flatness = np.where(mid > 0, lo / np.where(mid > 0, mid, 1.0), 1.0)
    normals = orient_normals(points, normals, viewpoint)
    return NormalEstimate(
        normals=normals,
        curvature=np.clip(curvature, 0.0, 1.0 / 3.0),
        flatness=np.clip(flatness, 0.0, 1.0),
        neighbors=idx,
    )


def neighbourhood_covariances(points: FloatArray, neighbors: NDArray[np.intp]) -> FloatArray:
    """Covariance of every neighbourhood, as its 6 distinct entries.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
    neighbors : ndarray of int, shape (M, k)
        Indices into ``points`` of each neighbourhood.

    Returns
    -------
    ndarray, shape (M, 6)
        ``(xx, xy, xz, yy, yz, zz)`` of ``mean(p p^T) - mean(p) mean(p)^T``.

    Notes
    -----
    The first and second moments of all neighbourhoods are one sparse matrix product (the
    neighbourhood-averaging operator times the per-point monomials), an order of magnitude
    faster than gathering an (M, k, 3) array and contracting it. Coordinates are centred on the
    cloud's mean first, as before, so the cancellation in ``E[p p^T] - E[p] E[p]^T`` is
    unchanged.
    """
    return kernels.neighbourhood_covariances(points - points.mean(axis=0), neighbors)


def smallest_eigenpairs_3x3(
    cov: FloatArray, *, gap_ratio: float = 1e-6
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Smallest eigenvalue and its unit eigenvector, and the middle eigenvalue, of many
    symmetric 3x3 matrices.

    Closed form: eigenvalues by the trigonometric solution of the characteristic cubic
    (Smith 1961), the eigenvector as the largest cross product of two rows of
    ``A - lambda_min I`` (Kopp 2008). Its error is about ``eps ||A|| / (lambda_mid -
    lambda_min)``; matrices whose two smallest eigenvalues are closer than ``gap_ratio`` times
    the largest (e.g. collinear or isotropic neighbourhoods, where the normal is undefined)
    are handed to ``numpy.linalg.eigh`` instead. Several times faster than a batched ``eigh``.

    Parameters
    ----------
    cov : ndarray, shape (N, 6)
        Entries ``(xx, xy, xz, yy, yz, zz)``.
    gap_ratio : float

    Returns
    -------
    evals : ndarray, shape (N,)
    evecs : ndarray, shape (N, 3)
        Unit eigenvectors (sign arbitrary).
    mid : ndarray, shape (N,)
        Middle eigenvalues.
    """
    evals, evecs, mid, hard = kernels.smallest_eigenpairs_3x3(cov, gap_ratio)
    return _eigh_where_hard(cov, hard, evals, evecs, mid)


def _eigh_where_hard(
    cov: FloatArray,
    hard: NDArray[np.bool_],
    evals: FloatArray,
    evecs: FloatArray,
    mid: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The closed form's results with ``numpy.linalg.eigh``'s where ``hard``."""
    if hard.any():
        full = np.empty((int(hard.sum()), 3, 3))
        sub = cov[hard]
        for i, (r, col) in enumerate([(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]):
            full[:, r, col] = full[:, col, r] = sub[:, i]
        w, v = np.linalg.eigh(full)
        evals = evals.copy()
        mid = mid.copy()
        evals[hard] = w[:, 0]
        mid[hard] = w[:, 1]
        evecs[hard] = v[:, :, 0]
    return evals, np.ascontiguousarray(evecs), mid


def orient_normals(
    points: FloatArray,
    normals: FloatArray,
    viewpoint: ArrayLike = (0.0, 0.0, 0.0),
    *,
    edge_on: float = 1e-6,
) -> FloatArray:
    """Flip normals so that ``n . (viewpoint - x) >= 0`` (Rusu 2013).

    A normal within ``edge_on`` (the cosine to the viewing ray) of perpendicular to the ray
    belongs to a surface seen edge-on, e.g. points in the sensor's own horizontal plane, which
    many LiDARs return at exactly ``z = 0``. The viewpoint cannot orient it, and the sign of
    its tiny dot product would only reflect rounding in the eigen-solver; such normals get a
    fixed convention instead: the component of largest magnitude is made positive.
    """
    vp = np.asarray(viewpoint, dtype=np.float64).reshape(3)
    ray = vp - points
    dot = np.einsum('ij,ij->i', normals, ray)
    ray_len = np.sqrt(np.einsum('ij,ij->i', ray, ray))
    sign = np.where(dot < 0.0, -1.0, 1.0)
    tie = np.abs(dot) <= edge_on * ray_len
    if tie.any():
        sub = normals[tie]
        largest = sub[np.arange(len(sub)), np.argmax(np.abs(sub), axis=1)]
        sign[tie] = np.where(largest < 0.0, -1.0, 1.0)
    return normals * sign[:, None]


def normal_consistency(normals: FloatArray, neighbors: NDArray[np.intp]) -> FloatArray:
    """Cosine between each normal and the mean normal of its neighbourhood, shape (N,)."""
    return kernels.normal_consistency(normals, neighbors)


def normal_inlier_mask(
    normals: FloatArray, neighbors: NDArray[np.intp], min_cosine: float
) -> NDArray[np.bool_]:
    """Mask of normals agreeing with their neighbourhood (cosine >= ``min_cosine``).

    ``min_cosine <= -1`` keeps every normal.
    """
    if min_cosine <= -1.0:
        return np.ones(len(normals), dtype=bool)
    return normal_consistency(normals, neighbors) >= min_cosine


#: Default of :func:`planar_mask`: the normal of k neighbours spread with eigenvalues
#: ``l0 <= l1`` is determined to about ``sqrt(l0 / (k l1))`` rad; at ``l0 / l1 = 1/4`` and
#: ``k = 15`` that is 7 deg, about the spread of a plane's normals within one cluster. Above it
#: the neighbourhood is a line of points, a blob or a crease, not a surface.
MAX_FLATNESS = 0.25


def planar_mask(flatness: FloatArray, max_flatness: float = MAX_FLATNESS) -> NDArray[np.bool_]:
    """Mask of neighbourhoods flat enough to define a normal (``l0 / l1 <= max_flatness``).

    ``max_flatness >= 1`` keeps every normal.
    """
    if max_flatness >= 1.0:
        return np.ones(len(flatness), dtype=bool)
    return flatness <= max_flatness
