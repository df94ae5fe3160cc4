"""Spherical k-means over unit vectors (Hornik et al. 2012) with k-means++ seeding."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core import kernels

FloatArray = NDArray[np.float64]


def _normalize_rows(x: FloatArray) -> FloatArray:
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)


def _rng(rng: np.random.Generator | int | None) -> np.random.Generator:
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)


def kmeanspp_sphere(
    x: FloatArray,
    k: int,
    rng: np.random.Generator | int | None = 0,
    weights: FloatArray | None = None,
) -> FloatArray:
    """k-means++ seeding on the sphere with the cosine dissimilarity ``1 - x . c``.

    Parameters
    ----------
    x : ndarray, shape (N, 3)
        Unit vectors.
    k : int
        Number of seeds (``1 <= k <= N``).
    rng : Generator or int, optional
    weights : ndarray, shape (N,), optional
        Non-negative sample weights.

    Returns
    -------
    ndarray, shape (k, 3)
    """
    gen = _rng(rng)
    n = len(x)
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    centers = np.empty((k, 3))
    first = gen.choice(n, p=w / w.sum())
    centers[0] = x[first]
    dist = np.maximum(1.0 - x @ centers[0], 0.0)
    for j in range(1, k):
        p = dist * w
        total = p.sum()
        idx = gen.choice(n, p=p / total) if total > 0 else gen.integers(n)
        centers[j] = x[idx]
        dist = np.minimum(dist, np.maximum(1.0 - x @ centers[j], 0.0))
    return centers


def spherical_kmeans(
    x: ArrayLike,
    k: int,
    *,
    max_iterations: int = 50,
    rng: np.random.Generator | int | None = 0,
    weights: ArrayLike | None = None,
    restarts: int = 3,
    sample_size: int = 0,
) -> tuple[NDArray[np.intp], FloatArray]:
    """Cluster unit vectors by spherical k-means.

    Each centre is the normalised (weighted) mean of its members; members are assigned to the
    centre of largest cosine. Empty clusters are re-seeded at the worst-fitting vector. The
    best of ``restarts`` k-means++ initialisations (largest total cosine) is returned.

    Parameters
    ----------
    x : array_like, shape (N, 3)
        Unit vectors (re-normalised defensively).
    k : int
        Number of clusters; clipped to N.
    max_iterations : int
    rng : Generator or int, optional
        Seed of the k-means++ initialisation.
    weights : array_like, shape (N,), optional
    restarts : int
        Independent seeded initialisations.
    sample_size : int
        When positive and smaller than N, the restarts run on a seeded random subset of this
        many vectors and only the best one is continued on all of them (0: every restart on
        all vectors).

    Returns
    -------
    labels : ndarray of int, shape (N,)
    centers : ndarray, shape (k, 3)
    """
    xs = np.asarray(x, dtype=np.float64)
    if xs.ndim != 2 or xs.shape[1] != 3:
        raise ValueError(f'Expected `x` to have shape (N, 3), got {xs.shape}.')
    if len(xs) == 0:
        raise ValueError('Expected at least one vector to cluster, got 0.')
    if k < 1:
        raise ValueError(f'Expected `k` >= 1, got {k}.')
    xs = _normalize_rows(xs)
    w = np.ones(len(xs)) if weights is None else np.asarray(weights, dtype=np.float64)
    k = min(k, len(xs))
    gen = _rng(rng)
    subset = 0 < sample_size < len(xs) and k <= sample_size
    xr, wr = xs, w
    if subset:
        pick = np.sort(gen.choice(len(xs), size=sample_size, replace=False))
        xr, wr = xs[pick], w[pick]
    best: tuple[float, NDArray[np.intp], FloatArray] | None = None
    for _ in range(max(1, restarts)):
        labels, centers = _lloyd(xr, wr, kmeanspp_sphere(xr, k, gen, wr), max_iterations)
        score = float(np.sum(wr * np.einsum('ij,ij->i', xr, centers[labels])))
        if best is None or score > best[0]:
            best = (score, labels, centers)
    assert best is not None
    if subset:
        return _lloyd(xs, w, best[2], max_iterations)
    return best[1], best[2]


def refine_spherical_kmeans(
    x: ArrayLike,
    centers: ArrayLike,
    *,
    max_iterations: int = 50,
    weights: ArrayLike | None = None,
) -> tuple[NDArray[np.intp], FloatArray]:
    """Spherical k-means from given centres (a warm start: no k-means++ restarts).

    Parameters
    ----------
    x : array_like, shape (N, 3)
        Unit vectors (re-normalised defensively).
    centers : array_like, shape (K, 3)
        Starting centres (re-normalised), e.g. those of a previous clustering of most of ``x``.
    max_iterations : int
    weights : array_like, shape (N,), optional

    Returns
    -------
    labels : ndarray of int, shape (N,)
    centers : ndarray, shape (K, 3)
    """
    xs = np.asarray(x, dtype=np.float64)
    cs = np.asarray(centers, dtype=np.float64)
    if xs.ndim != 2 or xs.shape[1] != 3 or len(xs) == 0:
        raise ValueError(f'Expected `x` to have shape (N, 3) with N >= 1, got {xs.shape}.')
    if cs.ndim != 2 or cs.shape[1] != 3 or not 1 <= len(cs) <= len(xs):
        raise ValueError(
            f'Expected `centers` to have shape (K, 3) with 1 <= K <= {len(xs)}, got {cs.shape}.'
        )
    w = np.ones(len(xs)) if weights is None else np.asarray(weights, dtype=np.float64)
    return _lloyd(_normalize_rows(xs), w, _normalize_rows(cs), max_iterations)


def _lloyd(
    xs: FloatArray, w: FloatArray, centers: FloatArray, max_iterations: int
) -> tuple[NDArray[np.intp], FloatArray]:
    k = len(centers)
    n = len(xs)
    labels = np.full(n, -1, dtype=np.intp)
    weighted = [xs[:, axis] * w for axis in range(3)]  # fixed across iterations
    compiled = kernels.enabled()
    weighted_rows = np.array(weighted) if compiled else None  # (3, N) for the kernel
    for _ in range(max_iterations):
        if weighted_rows is not None:
            new_labels, sums = kernels.assign_and_sum(xs, weighted_rows, centers)
        else:
            new_labels = np.argmax(xs @ centers.T, axis=1)
            sums = np.zeros((k, 3))
            for axis in range(3):
                sums[:, axis] = np.bincount(new_labels, weights=weighted[axis], minlength=k)
        norms = np.linalg.norm(sums, axis=1)
        empty = norms < 1e-12
        if empty.any():
            fit = (xs @ centers.T)[np.arange(n), new_labels]
            worst = np.argsort(fit)[: int(empty.sum())]
            sums[empty] = xs[worst]
            new_labels[worst] = np.flatnonzero(empty)
            norms = np.linalg.norm(sums, axis=1)
        centers = sums / norms[:, None]
        if np.array_equal(new_labels, labels):
            break
        labels = new_labels
    return labels, centers
