"""Normal-space sampling of the source's points for the position stages (translation, refinement,
fit), with the Kent clusters as strata.

Gelfand et al. (2003), "Geometrically stable sampling for the ICP algorithm": the points on
small groups of normals carry the weakly constrained directions of the alignment; thinning
them loses the constraint, thinning the large groups (floor, main walls) loses almost nothing.
The normal clusters of a prepared scan are those groups, so every cluster keeps
``min(n_k, cap)`` of its ``n_k`` points, evenly spaced in the scan's voxel order (so evenly in
space), and the rotation stage keeps using every normal (its bins are built from all of them).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def stratified_sample(labels: NDArray[np.intp], cap: int) -> NDArray[np.intp]:
    """Indices keeping at most ``cap`` points per label, evenly spaced within each label.

    Parameters
    ----------
    labels : ndarray of int, shape (N,)
        Stratum (normal cluster) of every point, in the order the points are stored.
    cap : int
        Points kept per stratum at most; ``cap <= 0`` keeps every point.

    Returns
    -------
    ndarray of int, shape (M,)
        Increasing indices into ``labels``; each stratum of ``n`` points contributes exactly
        ``min(n, cap)`` of them, the ``j``-th being its ``floor(j * n / min(n, cap))``-th point.
    """
    labels = np.asarray(labels, dtype=np.intp)
    n = len(labels)
    if cap <= 0 or n == 0:
        return np.arange(n, dtype=np.intp)
    order = np.argsort(labels, kind='stable')  # stable: each stratum keeps the storage order
    counts = np.bincount(labels)
    if counts.max() <= cap:
        return np.arange(n, dtype=np.intp)
    starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
    sorted_labels = labels[order]
    rank = np.arange(n) - starts[sorted_labels]
    size = counts[sorted_labels]
    kept = np.minimum(size, cap)
    # Rank r is floor(j * n / kept) for some integer j exactly when [r, r + 1) * kept / n holds
    # an integer: ceil(r * kept / n) < ceil((r + 1) * kept / n), true for `kept` ranks.
    take = ((rank + 1) * kept + size - 1) // size > (rank * kept + size - 1) // size
    return np.sort(order[take])
