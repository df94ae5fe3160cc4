"""Exact k-nearest-neighbour queries on a fixed point set.

:class:`NeighborIndex` answers ``query(x, k, distance_upper_bound)`` with the conventions of
``scipy.spatial.cKDTree.query`` (distances, indices; ``inf`` and ``n`` where no neighbour lies
within the bound). Its tree is the compiled k-d tree of :mod:`kentreg_ros.core.kernels` when the
kernels are compiled (numba, the ``fast`` extra), else small_gicp's (nanoflann, C++) when
small_gicp is installed, else scipy's cKDTree: all three are exact, so results agree up to the
order of equidistant neighbours, and the first two give the same distances bit for bit.
small_gicp answers the queries this package makes about twice as fast as cKDTree on one
thread; the compiled tree answers them as fast as small_gicp's and is built in a fraction of
its time, which counts because the local map is indexed anew every step (figures in
``docs/notes-registration.md``). Neighbour queries are the largest cost of preparing and
registering a scan (``benchmarks/per_scan.py``).
"""

from __future__ import annotations

import importlib.util
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from kentreg_ros.core import kernels
from kentreg_ros.core.errors import InvalidInputError

FloatArray = NDArray[np.float64]

#: Whether small_gicp's KD-tree is installed (an optional, compiled dependency).
HAVE_SMALL_GICP = importlib.util.find_spec('small_gicp') is not None
#: The backends, fastest first.
BACKENDS = ('compiled', 'small_gicp', 'scipy')


def default_backend() -> str:
    """The fastest backend available here: ``'compiled'`` when the kernels are compiled, else
    ``'small_gicp'`` when it is installed, else ``'scipy'``."""
    if kernels.enabled():
        return 'compiled'
    return 'small_gicp' if HAVE_SMALL_GICP else 'scipy'


class NeighborIndex:
    """Exact nearest-neighbour index of ``points`` (N, 3), built once, queried many times.

    Attributes
    ----------
    n : int
        Number of indexed points (the "no neighbour" index, as in cKDTree).
    backend : str
        One of :data:`BACKENDS` (default: :func:`default_backend`).

    Notes
    -----
    ``order`` (a permutation of the points, e.g. spatially sorted) is the order the tree is built
    from: a tree is built faster from points whose neighbours lie near them in memory (the
    local map's points in voxel-key order; see ``docs/notes-registration.md``). The answers
    index ``points`` as given.
    """

    def __init__(
        self,
        points: FloatArray,
        *,
        backend: str | None = None,
        order: NDArray[np.intp] | None = None,
    ) -> None:
        pts = np.ascontiguousarray(points, dtype=np.float64)
        self.n = len(pts)
        self.backend = backend or default_backend()
        if self.backend not in BACKENDS:
            raise InvalidInputError(f'Expected a backend of {BACKENDS}, got {self.backend!r}.')
        if self.backend == 'compiled' and not kernels.enabled():
            raise InvalidInputError("The 'compiled' backend needs the compiled kernels (numba).")
        if order is not None:
            order = np.asarray(order, dtype=np.intp)
            if order.shape != (self.n,):
                raise InvalidInputError(
                    f'Expected `order` of shape ({self.n},), got {order.shape}.'
                )
        self._points = pts
        # The tree is built from the points in this order (see Notes); its answers are mapped
        # back to indices into ``points``.
        self._order = order
        self._built: Any = None

    @property
    def _tree(self) -> Any:
        """The tree, built on first use: a scan prepared in another process arrives without
        one (small_gicp's tree does not pickle), and a scan that is never queried (the local
        map's scans, which enter the map and are not targets) never pays for it."""
        if self._built is None:
            pts = self._points if self._order is None else self._points.take(self._order, axis=0)
            if self.backend == 'compiled':
                tree = kernels.kdtree_build(pts)
                if self._order is not None:
                    tree = (self._order[tree[0]], *tree[1:])
                self._built = tree
                return self._built
            if self.backend == 'small_gicp':
                import small_gicp  # compiled, optional: imported only when used

                self._built = small_gicp.KdTree(pts, num_threads=1)
            else:
                self._built = cKDTree(pts)
        return self._built

    def build(self) -> NeighborIndex:
        """Build the tree now (it is otherwise built at the first query); returns ``self``."""
        _ = self._tree
        return self

    def __getstate__(self) -> dict[str, Any]:
        """Pickled as its points; the tree is rebuilt where it is used (the same tree)."""
        return {
            'n': self.n,
            'backend': self.backend,
            '_points': self._points,
            '_order': self._order,
            '_built': None,
        }

    def _original(self, idx: NDArray[np.intp]) -> NDArray[np.intp]:
        """Indices into the tree's points as indices into ``points`` (``n``: none, kept)."""
        if self._order is None:
            return idx
        out: NDArray[np.intp] = np.where(
            idx < self.n, self._order[np.minimum(idx, self.n - 1)], idx
        )
        return out

    def neighbor_indices(self, x: FloatArray, k: int) -> NDArray[np.intp]:
        """Indices of the ``k <= n`` nearest points of every row of ``x``, shape (M, k),
        without the distances (the normals' neighbourhoods need only these)."""
        if not 1 <= k <= self.n:
            raise InvalidInputError(f'Expected 1 <= k <= {self.n}, got {k}.')
        queries = np.ascontiguousarray(x, dtype=np.float64)
        if self.backend == 'compiled':
            found = kernels.kdtree_knn(self._tree, queries, k, np.inf)[1]
            if not (found >= 0).all():  # cannot happen with k <= n; say so if it does
                raise RuntimeError('The k-d tree returned fewer than k neighbours.')
            return found
        if self.backend == 'scipy':
            found = np.asarray(self._tree.query(queries, k=k)[1], dtype=np.intp).reshape(-1, k)
            return self._original(found)
        raw_idx, _ = self._tree.batch_knn_search(queries, k, num_threads=1)
        idx = np.asarray(raw_idx).view(np.int64)  # small_gicp's "not found" -1 as uint64
        if not (idx >= 0).all():  # cannot happen with k <= n; say so if it does
            raise RuntimeError('small_gicp returned fewer than k neighbours.')
        return self._original(idx.astype(np.intp, copy=False))

    def query(
        self, x: FloatArray, k: int = 1, *, distance_upper_bound: float = np.inf
    ) -> tuple[FloatArray, NDArray[np.intp]]:
        """Distances and indices of the ``k`` nearest points of every row of ``x``.

        Shapes ``(M,)`` for ``k = 1``, ``(M, k)`` otherwise; beyond ``distance_upper_bound`` (or
        when fewer than ``k`` points exist) the distance is ``inf`` and the index ``n``.
        """
        queries = np.ascontiguousarray(x, dtype=np.float64)
        if self.backend == 'scipy':
            dist, idx = self._tree.query(queries, k=k, distance_upper_bound=distance_upper_bound)
            return np.asarray(dist, dtype=np.float64), self._original(np.asarray(idx, np.intp))
        kk = min(k, self.n)
        if self.backend == 'compiled':
            # Searched a hair beyond the bound: the filter below then keeps what the other
            # backends keep (a distance <= the bound, compared after the square root).
            bound2 = (distance_upper_bound * (1.0 + 1e-9)) ** 2
            if kk:
                sq, idx = kernels.kdtree_knn(self._tree, queries, kk, bound2)
            else:  # no points
                sq, idx = np.zeros((len(queries), 0)), np.zeros((len(queries), 0), np.intp)
        else:
            raw_idx, sq = self._tree.batch_knn_search(queries, kk, num_threads=1)
            idx = np.asarray(raw_idx).astype(np.intp)
        dist = np.sqrt(np.asarray(sq, dtype=np.float64))
        if kk < k:
            pad = k - kk
            dist = np.pad(dist, ((0, 0), (0, pad)), constant_values=np.inf)
            idx = np.pad(idx, ((0, 0), (0, pad)), constant_values=self.n)
        missing = ~(dist <= distance_upper_bound) | (idx < 0) | (idx >= self.n)
        dist[missing] = np.inf
        idx[missing] = self.n
        if self.backend != 'compiled':  # the compiled tree's perm already maps them back
            idx = self._original(idx)
        if k == 1:
            return dist[:, 0], idx[:, 0]
        return dist, idx
