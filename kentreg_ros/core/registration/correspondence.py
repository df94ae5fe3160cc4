"""Exact nearest-neighbour correspondences for query points that move a little per iteration.

ICP-style loops (the translation stage and the joint refinement) query the target's KD-tree for
every source point on every iteration, although after the first few iterations the points move
by millimetres while neighbouring target points are centimetres apart. A query at position
``x0`` with ``k = C + 1`` gives ``C`` candidates (the nearest target points) and a radius ``r``
(the next neighbour's distance, or the query bound) such that every other target point is at
least ``r`` from ``x0``. After the point has moved to ``x``, with ``m = |x - x0|``, every
non-candidate is at least ``r - m`` from ``x`` (triangle inequality); so if the nearest
candidate is within ``r - m`` of ``x``, it is the nearest neighbour, and if the gate is below
``r - m``, no non-candidate is within the gate. Only points failing this certificate are queried
again. The correspondences are therefore exactly those of a fresh query (up to ties between
equidistant target points), at a fraction of the cost once the iteration settles.

Two candidates rather than one: a point that sits between two target points (the common case
on a surface sampled at the voxel size) swaps between them as it moves, which one candidate
cannot certify, and the radius from the third neighbour is larger. Two re-query markedly fewer
points than one, for the same poses bit for bit; a third saves little more for a third distance
per point per iteration (figures in ``docs/notes-registration.md``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core import kernels
from kentreg_ros.core.errors import InvalidInputError
from kentreg_ros.core.scan.neighbors import NeighborIndex

FloatArray = NDArray[np.float64]
#: Target points cached per query point (see the module's notes).
CANDIDATES = 2


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
            raise InvalidInputError(
                f'Expected `target` to hold the {tree.n} points of `tree`, got {len(target)}.'
            )
        self._tree = tree
        self._target = target
        self._x0 = np.zeros((n_queries, 3))
        # The CANDIDATES nearest target points at _x0 (-1 for none); every other target point
        # is at least _radius from _x0; -inf before the first query.
        self._cand = np.full((n_queries, CANDIDATES), -1, dtype=np.intp)
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
        dist, nearest, valid = kernels.certified_distances(
            x, self._x0, self._radius, self._cand, self._target, gate
        )
        redo = np.flatnonzero(~valid)
        if len(redo):
            moved = np.take(x, redo, axis=0)
            d, i = self._tree.query(moved, k=CANDIDATES + 1, distance_upper_bound=gate)
            found = np.isfinite(d)
            self._x0[redo] = moved
            self._cand[redo] = np.where(found[:, :CANDIDATES], i[:, :CANDIDATES], -1)
            self._radius[redo] = np.where(found[:, CANDIDATES], d[:, CANDIDATES], gate)
            dist[redo] = d[:, 0]
            nearest[redo] = np.where(found[:, 0], i[:, 0], -1)
            self.n_queried += len(redo)
        idx = np.where(nearest >= 0, nearest, self._tree.n)
        outside = ~(dist < gate)
        dist[outside] = np.inf
        idx[outside] = self._tree.n
        return dist, idx
