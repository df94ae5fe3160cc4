"""The normal clusters of a scan: spherical k-means of its normals and their summary as a Kent
mixture (the model side of the EM): per-cluster Kent frames and normals binned at the width of
their kernel."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core import kernels
from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.errors import InvalidInputError
from kentreg_ros.core.geometry import row_norms
from kentreg_ros.core.kent import kent_from_moments
from kentreg_ros.core.scan.voxels import argsort_keys

FloatArray = NDArray[np.float64]


def _normalize_rows(x: FloatArray) -> FloatArray:
    return x / np.maximum(row_norms(x), 1e-12)[:, None]


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
        raise InvalidInputError(f'Expected `x` to have shape (N, 3), got {xs.shape}.')
    if len(xs) == 0:
        raise InvalidInputError('Expected at least one vector to cluster, got 0.')
    if k < 1:
        raise InvalidInputError(f'Expected `k` >= 1, got {k}.')
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
    unweighted = weights is None
    for _ in range(max(1, restarts)):
        seeds = kmeanspp_sphere(xr, k, gen, wr)
        labels, centers = _lloyd(xr, None if unweighted else wr, seeds, max_iterations)
        score = float(np.sum(wr * np.einsum('ij,ij->i', xr, centers[labels])))
        if best is None or score > best[0]:
            best = (score, labels, centers)
    assert best is not None
    if subset:
        return _lloyd(xs, None if unweighted else w, best[2], max_iterations)
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
        raise InvalidInputError(f'Expected `x` to have shape (N, 3) with N >= 1, got {xs.shape}.')
    if cs.ndim != 2 or cs.shape[1] != 3 or not 1 <= len(cs) <= len(xs):
        raise InvalidInputError(
            f'Expected `centers` to have shape (K, 3) with 1 <= K <= {len(xs)}, got {cs.shape}.'
        )
    w = None if weights is None else np.asarray(weights, dtype=np.float64)
    return _lloyd(_normalize_rows(xs), w, _normalize_rows(cs), max_iterations)


def _lloyd(
    xs: FloatArray, w: FloatArray | None, centers: FloatArray, max_iterations: int
) -> tuple[NDArray[np.intp], FloatArray]:
    """Lloyd's steps from ``centers``; ``w`` None: unit weights (the rows as they are)."""
    n = len(xs)
    labels = np.full(n, -1, dtype=np.intp)
    # (3, N), fixed; x * 1.0 is x, so unit weights are the transposed rows.
    weighted = (
        np.ascontiguousarray(xs.T) if w is None else np.array([xs[:, a] * w for a in range(3)])
    )
    left = max_iterations
    while left > 0:
        # The steps run compiled (one call, not a dozen numpy calls a step) until they
        # converge, run out, or a cluster empties, which is re-seeded here.
        labels, centers, sums, new_labels, state, steps = kernels.lloyd_steps(
            xs, weighted, centers, labels, left
        )
        left -= steps
        if state != 2:
            break
        empty = row_norms(sums) < 1e-12
        fit = (xs @ centers.T)[np.arange(n), new_labels]
        worst = np.argsort(fit)[: int(empty.sum())]
        sums[empty] = xs[worst]
        new_labels[worst] = np.flatnonzero(empty)
        centers = sums / row_norms(sums)[:, None]
        if np.array_equal(new_labels, labels):
            break
        labels = new_labels
    return labels, centers


#: Bin edge bounds (in unit-vector coordinates; 0.01 ~ 0.6 deg, 0.1 ~ 5.7 deg), see
#: :func:`bin_cell_for`.
MIN_BIN_CELL = 0.01


MAX_BIN_CELL = 0.1


@dataclass(frozen=True)
class NormalBins:
    """Unit normals summarised per occupied cell: direction, count and exact moments.

    Attributes
    ----------
    directions : ndarray, shape (B, 3)
        Unit mean direction of the normals in each cell.
    weights : ndarray, shape (B,)
        Number of normals in each cell.
    resultants : ndarray, shape (B, 3)
        Sum of the normals in each cell.
    scatters : ndarray, shape (B, 3, 3)
        Sum of ``x x^T`` over the normals in each cell.
    cell : float
        Smallest cell edge used, in unit-vector coordinates (about the cell's angular width
        in radians).
    """

    directions: FloatArray
    weights: FloatArray
    resultants: FloatArray
    scatters: FloatArray
    cell: float

    @classmethod
    def from_normals(
        cls,
        normals: FloatArray,
        cell: float | FloatArray,
        groups: NDArray[np.intp] | None = None,
    ) -> NormalBins:
        """Bin unit normals on a cubic grid of edge ``cell`` in R^3.

        ``cell`` may be given per normal together with ``groups`` (e.g. the normal clusters,
        each binned at the width its own kernel needs, :func:`bin_cell_for`); normals of
        different groups never share a bin.

        The E-step evaluates a cell's posteriors at its mean direction; the M-step uses the
        cell's exact first and second moments (``resultants``, ``scatters``), so binning only
        approximates how the posteriors vary across a cell, which is small for cells narrower
        than the Kent kernels.
        """
        cells = np.broadcast_to(np.asarray(cell, dtype=np.float64), (len(normals),))
        span = int(np.floor(1.0 / float(cells.min()))) + 2 if len(cells) else 2
        flat = kernels.normal_bin_keys(normals, cells, groups, span)
        order = argsort_keys(flat)
        starts, counts = kernels.run_starts(flat[order])
        sums, outer = kernels.bin_moments(normals, order, starts)
        scatters = outer.reshape(-1, 3, 3)
        norms = row_norms(sums)
        keep = norms > 1e-12 * counts  # opposite normals in one cell cancel: drop them
        return cls(
            directions=np.ascontiguousarray(sums[keep] / norms[keep, None]),
            weights=counts[keep],
            resultants=np.ascontiguousarray(sums[keep]),
            scatters=np.ascontiguousarray(scatters[keep]),
            cell=float(cells.min()) if len(cells) else 0.0,
        )

    def take(self, index: NDArray[np.intp]) -> NormalBins:
        """The bins ``index``, in that order."""
        return NormalBins(
            self.directions[index],
            self.weights[index],
            self.resultants[index],
            self.scatters[index],
            self.cell,
        )

    def __len__(self) -> int:
        return len(self.weights)


def kent_moments_of_bins(
    bins: NormalBins, weights: FloatArray, *, rotation: FloatArray | None = None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Kent's moment estimates (kappa, beta, gamma) of K weighted groups of bins.

    ``weights`` (K, B) weighs each bin's normals (1 = all of them); the moments are exact
    (:func:`~kentreg_ros.core.kent.kent_from_moments`). With ``rotation`` R they are those of
    the rotated normals ``R x`` (the K group moments are rotated, not the B bins). A group with
    no weight gets ``kappa = beta = 0`` and ``gamma = I``.
    """
    return kent_moments_of_sums(
        weights @ bins.weights,
        weights @ bins.resultants,
        weights @ bins.scatters.reshape(-1, 9),
        rotation=rotation,
    )


def kent_moments_of_sums(
    mass: FloatArray,
    resultant: FloatArray,
    scatter_sum: FloatArray,
    *,
    rotation: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`kent_moments_of_bins` from the groups' sums: weight (K,), resultant (K, 3) and
    scatter (K, 9, row-major)."""
    safe = np.where(mass > 0.0, mass, 1.0)
    xbar = resultant / safe[:, None]
    scatter = scatter_sum.reshape(-1, 3, 3) / safe[:, None, None]
    if rotation is not None:
        xbar = xbar @ rotation.T
        scatter = rotation @ scatter @ rotation.T
    kappa, beta, gamma = kent_from_moments(xbar, scatter)
    empty = ~(mass > 0.0)
    kappa[empty], beta[empty], gamma[empty] = 0.0, 0.0, np.eye(3)
    return kappa, beta, gamma


def bin_cell_for(kappa: FloatArray | float) -> FloatArray:
    """Cell edges for :class:`NormalBins`, each no wider than its Kent kernel.

    A Kent kernel of concentration ``kappa`` has an angular standard deviation of about
    ``1 / sqrt(kappa)`` per axis; a cluster's cell edge is its own, so a cell's normals lie
    within half a standard deviation of its mean, clipped to [:data:`MIN_BIN_CELL`,
    :data:`MAX_BIN_CELL`] (below 0.6 deg the normals' own estimation noise dominates; above
    5.7 deg the bins no longer resolve the planes within a cluster). Within that range the
    edge barely moves the rotation error on real pairs (docs/notes-registration.md), while the
    cost grows with the square of the number of bins.
    """
    k = np.asarray(kappa, dtype=np.float64)
    safe = np.where(k > 0.0, k, 1.0)
    out: FloatArray = np.where(
        k > 0.0, np.clip(1.0 / np.sqrt(safe), MIN_BIN_CELL, MAX_BIN_CELL), MAX_BIN_CELL
    )
    return out


@dataclass(frozen=True)
class ModelClusters:
    """The model's partition of its normals and the Kent parameters of each cluster.

    Attributes
    ----------
    centers : ndarray, shape (K, 3)
        Cluster mean directions (spherical k-means).
    gamma : ndarray, shape (K, 3, 3)
        Per cluster, columns (mean direction, major axis, minor axis) by Kent's moments.
    kappa, beta : ndarray, shape (K,)
        Kent concentration and ovalness of each cluster by Kent's moments.
    weights : ndarray, shape (K,)
        Share of the normals in each cluster (sums to 1).
    bins : NormalBins
        The model normals, binned, sorted by cluster.
    offsets : ndarray of int, shape (K + 1,)
        ``bins`` of cluster ``k`` are ``offsets[k]:offsets[k + 1]``.
    """

    centers: FloatArray
    gamma: FloatArray
    kappa: FloatArray
    beta: FloatArray
    weights: FloatArray
    bins: NormalBins
    offsets: NDArray[np.intp]

    @classmethod
    def from_bins(cls, bins: NormalBins, centers: FloatArray) -> ModelClusters:
        """Assign each bin to its nearest centre; Kent moments per cluster (empty ones go)."""
        labels = np.argmax(bins.directions @ centers.T, axis=1)
        k = len(centers)
        mass = np.bincount(labels, weights=bins.weights, minlength=k)
        keep = np.flatnonzero(mass > 0.0)
        remap = np.full(k, -1)
        remap[keep] = np.arange(len(keep))
        labels = remap[labels]
        order = np.argsort(labels, kind='stable')
        sorted_bins = bins.take(order)
        counts = np.bincount(labels, minlength=len(keep))
        offsets = np.r_[0, np.cumsum(counts)].astype(np.intp)
        member = np.zeros((len(keep), len(bins)))
        member[labels[order], np.arange(len(bins))] = 1.0
        kappa, beta, gamma = kent_moments_of_bins(sorted_bins, member)
        return cls(
            centers=np.ascontiguousarray(centers[keep]),
            gamma=gamma,
            kappa=kappa,
            beta=beta,
            weights=mass[keep] / mass.sum(),
            bins=sorted_bins,
            offsets=offsets,
        )

    def __len__(self) -> int:
        return len(self.centers)


def _cluster_kappa(normals: FloatArray, labels: NDArray[np.intp], k: int) -> FloatArray:
    """Kent's moment estimate of each cluster's concentration (0 for an empty cluster), from
    per-cluster sums (bincounts: no (K, N) weight matrix)."""
    mass, xbar, scatter = kernels.cluster_moments(normals, labels, k)
    safe = np.where(mass > 0.0, mass, 1.0)
    kappa, _, _ = kent_from_moments(xbar / safe[:, None], scatter / safe[:, None, None])
    kappa[mass == 0.0] = 0.0
    return kappa


def cluster_normals(
    normals: FloatArray, config: KentRegConfig
) -> tuple[NDArray[np.intp], FloatArray, ModelClusters]:
    """Spherical k-means of unit normals and the Kent frames of the clusters.

    Parameters
    ----------
    normals : ndarray, shape (N, 3)
        Unit normals.
    config : KentRegConfig
        ``clustering`` settings.

    Returns
    -------
    labels : ndarray of int, shape (N,)
    centers : ndarray, shape (K, 3)
    clusters : ModelClusters
    """
    c = config.clustering
    labels, centers = spherical_kmeans(
        normals,
        c.n_clusters,
        max_iterations=c.max_iterations,
        rng=c.seed,
        restarts=c.restarts,
        sample_size=c.restart_sample,
    )
    kappa_clusters = _cluster_kappa(normals, labels, len(centers))
    bins = NormalBins.from_normals(normals, bin_cell_for(kappa_clusters)[labels], labels)
    return labels, centers, ModelClusters.from_bins(bins, centers)
