"""Exact nearest-neighbour correspondences for query points that move a little per iteration.

ICP-style loops (the translation stage and the joint refinement) query the target's KD-tree for
every source point on every iteration, although after the first few iterations the points move
by millimetres while neighbouring target points are centimetres apart. A query at position
``x0`` with ``k = 2`` gives the nearest target point ``q1`` and a radius ``r`` (the second
neighbour's distance, or the query bound) such that every other target point is at least ``r``
from ``x0``. After the point has moved to ``x``, with ``m = |x - x0|``, every other target
point is at least ``r - m`` from ``x`` (triangle inequality); so if ``|x - q1| <= r - m``,
``q1`` is still the nearest neighbour, and a point that had no neighbour within ``r`` still has
none within any gate ``< r - m``. Only points failing this certificate are queried again. The
correspondences are therefore exactly those of a fresh query (up to ties between equidistant
target points), at a fraction of the cost once the iteration settles.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core import kernels
from kentreg_ros.core.scan.neighbors import NeighborIndex

FloatArray = NDArray[np.float64]


def _row_norms(v: FloatArray) -> FloatArray:
    out: FloatArray = np.sqrt(np.einsum('ij,ij->i', v, v))
    return out


class NearestNeighborCache:
    """Nearest target point of each of N moving query points, re-querying only when needed.

    Parameters
    ----------
    tree : NeighborIndex
        Tree on ``target``.
    target : ndarray, shape (M, 3)
        The points the tree was built on.
    n_queries : int
        Number of query points; every call to :meth:`query` passes them in the same order.

    Attributes
    ----------
    n_queried : int
        Query points sent to the tree so far (for diagnostics and tests).
    n_calls : int
    """

    def __init__(self, tree: NeighborIndex, target: FloatArray, n_queries: int) -> None:
        if len(target) != tree.n:
            raise ValueError(
                f'Expected `target` to hold the {tree.n} points of `tree`, got {len(target)}.'
            )
        self._tree = tree
        self._target = target
        self._x0 = np.zeros((n_queries, 3))
        self._idx = np.full(n_queries, -1, dtype=np.intp)
        # Every target point other than _idx is at least _radius from _x0 (all points when
        # _idx < 0); -inf before the first query.
        self._radius = np.full(n_queries, -np.inf)
        self.n_queried = 0
        self.n_calls = 0

    def query(
        self, x: FloatArray, distance_upper_bound: float
    ) -> tuple[FloatArray, NDArray[np.intp]]:
        """Nearest target point of every row of ``x`` closer than ``distance_upper_bound``.

        Same output convention as ``cKDTree.query(x, k=1, distance_upper_bound=...)``:
        ``(dist, idx)`` with ``dist = inf`` and ``idx = M`` where no target point is closer
        than the bound.

        Parameters
        ----------
        x : ndarray, shape (N, 3)
        distance_upper_bound : float

        Returns
        -------
        dist : ndarray, shape (N,)
        idx : ndarray of int, shape (N,)
        """
        gate = float(distance_upper_bound)
        self.n_calls += 1
        dist, valid = kernels.certified_distances(
            x, self._x0, self._radius, self._idx, self._target, gate
        )
        redo = np.flatnonzero(~valid)
        if len(redo):
            moved = np.take(x, redo, axis=0)
            d2, i2 = self._tree.query(moved, k=2, distance_upper_bound=gate)
            found = np.isfinite(d2[:, 0])
            self._x0[redo] = moved
            self._idx[redo] = np.where(found, i2[:, 0], -1)
            self._radius[redo] = np.where(found, np.minimum(d2[:, 1], gate), gate)
            dist[redo] = d2[:, 0]
            self.n_queried += len(redo)
        idx = np.where(self._idx >= 0, self._idx, self._tree.n)
        outside = ~(dist < gate)
        dist[outside] = np.inf
        idx[outside] = self._tree.n
        return dist, idx
