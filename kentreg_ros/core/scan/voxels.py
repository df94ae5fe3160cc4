"""Input validation, range cropping and voxel downsampling of point clouds."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core import kernels
from kentreg_ros.core.errors import InvalidInputError, InvalidPointCloudError

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


def as_points(
    points: ArrayLike, name: str = 'points', *, allow_nonfinite: bool = False
) -> FloatArray:
    """Validate and convert an array-like to a C-contiguous float64 array of shape (N, 3).

    Parameters
    ----------
    points : array_like, shape (N, 3)
    name : str
        Name used in error messages.
    allow_nonfinite : bool
        If False (default), NaN or inf coordinates raise :class:`InvalidPointCloudError`.

    Raises
    ------
    InvalidPointCloudError
        Wrong shape, non-numeric data, or non-finite values.
    """
    try:
        arr = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidPointCloudError(f'Expected `{name}` to be numeric, got {exc}.') from exc
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidPointCloudError(f'Expected `{name}` to have shape (N, 3), got {arr.shape}.')
    if not allow_nonfinite and not np.isfinite(arr).all():  # fast path: one flat pass
        bad = ~np.isfinite(arr).all(axis=1)
        if bad.any():
            raise InvalidPointCloudError(
                f'`{name}` has {int(bad.sum())} point(s) with NaN or inf coordinates; '
                'drop them first (kentreg_ros.core.drop_nonfinite).'
            )
    return np.ascontiguousarray(arr)


def drop_nonfinite(points: ArrayLike) -> tuple[FloatArray, int]:
    """Remove points with a NaN or inf coordinate; return ``(points, n_dropped)``."""
    arr = as_points(points, allow_nonfinite=True)
    keep = np.isfinite(arr).all(axis=1)
    return np.ascontiguousarray(arr[keep]), int((~keep).sum())


def crop_range(
    points: FloatArray,
    min_range: float = 0.0,
    max_range: float = 0.0,
    origin: ArrayLike = (0.0, 0.0, 0.0),
) -> FloatArray:
    """Keep points whose distance to ``origin`` is in ``[min_range, max_range]``.

    ``max_range = 0`` means no upper bound.
    """
    if min_range <= 0.0 and max_range <= 0.0:
        return points
    d = points - np.asarray(origin, dtype=np.float64)
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    d2 = (dx * dx + dy * dy) + dz * dz  # np.sum(d ** 2, axis=1) in its order, several times faster
    keep = d2 >= min_range**2
    if max_range > 0.0:
        keep &= d2 <= max_range**2
    # take(): boolean indexing's rows, several times faster on (N, 3).
    return points.take(np.flatnonzero(keep), axis=0)


def _bounds(points: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Per-axis minimum and maximum; column by column, much faster than ``min(axis=0)`` on an
    (N, 3) array."""
    lo = np.array([points[:, axis].min() for axis in range(3)])
    hi = np.array([points[:, axis].max() for axis in range(3)])
    return lo, hi


def _voxel_keys(
    points: FloatArray, voxel_size: float, bounds: tuple[FloatArray, FloatArray] | None = None
) -> NDArray[np.int64]:
    """Linear index of every point's voxel in the bounding grid (ordered x, then y, then z).

    ``bounds`` are the per-axis minimum and maximum of ``points`` when already known (the
    voxel-size search reuses them). The grid corner is ``floor(min / voxel_size)``, which equals
    the smallest per-point voxel index because ``floor(p / s)`` is monotonic in ``p``; the index
    arithmetic runs in float64 (exact below 2**53 cells), in int64 below 2**62 cells; a grid of
    more cells (points far beyond any sensor's range) numbers its occupied voxels in the same
    order instead (a sort of the voxel coordinates: exact, and bounded by the point count).
    """
    lo, hi = bounds if bounds is not None else _bounds(points)
    corner = np.floor(lo / voxel_size)
    span = np.floor(hi / voxel_size) - corner + 1.0
    cells = float(np.prod(span))
    if cells >= 2.0**62:
        coords = np.floor(points / voxel_size)
        ranks: NDArray[np.int64] = np.unique(coords, axis=0, return_inverse=True)[1]
        return ranks.astype(np.int64).ravel()
    if cells >= 2.0**53:
        idx = np.floor(points / voxel_size).astype(np.int64) - corner.astype(np.int64)
        s = span.astype(np.int64)
        wide: NDArray[np.int64] = (idx[:, 0] * s[1] + idx[:, 1]) * s[2] + idx[:, 2]
        return wide
    return kernels.voxel_keys(points, voxel_size, corner, span)


def voxel_downsample(points: ArrayLike, voxel_size: float) -> FloatArray:
    """Replace the points of every occupied voxel by their centroid.

    Parameters
    ----------
    points : array_like, shape (N, 3)
    voxel_size : float
        Voxel edge length (same unit as the points), > 0.

    Returns
    -------
    ndarray, shape (M, 3)
        Voxel centroids, ordered by voxel key (deterministic).
    """
    pts = as_points(points)
    if not voxel_size > 0.0:
        raise InvalidInputError(f'Expected `voxel_size` > 0, got {voxel_size!r}.')
    if len(pts) == 0:
        return pts
    return _centroids(pts, _voxel_keys(pts, voxel_size))


def _centroids(points: FloatArray, keys: NDArray[np.int64]) -> FloatArray:
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    out = np.empty((len(counts), 3))
    for axis in range(3):
        out[:, axis] = np.bincount(inverse, weights=points[:, axis], minlength=len(counts))
    out /= counts[:, None]
    return out


def _run_lengths(keys: NDArray[np.int64]) -> NDArray[np.intp]:
    """Number of points in every occupied voxel (in key order), from the voxel keys."""
    if len(keys) == 0:
        return np.zeros(0, dtype=np.intp)
    ordered = np.sort(keys)
    starts = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]])
    return np.diff(np.r_[starts, len(ordered)])


def count_voxels(points: FloatArray, voxel_size: float) -> int:
    """Number of occupied voxels of edge ``voxel_size``."""
    return len(_run_lengths(_voxel_keys(points, voxel_size)))


#: Largest share of the kept voxels that isolated returns may be expected to fill (see
#: :func:`isolated_return_floor`). The registration's own outlier handling (the EM's uniform
#: component, pi0 = 0.1 by default, and the robust kernels) absorbs a few percent of stray
#: points; more than that and outliers start to shape normals and clusters.
MAX_ISOLATED_SHARE = 0.1
#: A returns-per-voxel floor that leaves fewer voxels than this has met a cloud already
#: sampled at the voxel size (every return alone in its voxel, e.g. downsampled before): its
#: single returns are its samples, not strays, and a registration needs hundreds of them.
MIN_KEPT_VOXELS = 100
#: Largest returns-per-voxel floor the isolated-return test may raise to.
MAX_MIN_VOXEL_POINTS = 8


def _poisson_tail(lam: float, m: int) -> float:
    """P(X >= m) for X ~ Poisson(lam)."""
    term = np.exp(-lam)
    below = 0.0
    for j in range(m):
        below += term
        term *= lam / (j + 1)
    return float(max(1.0 - below, 0.0))


def isolated_return_floor(counts: NDArray[np.intp], n_cells: float, lam: float, floor: int) -> int:
    """Fewest returns a voxel must hold so that isolated returns rarely reach it.

    Surfaces put several returns into a voxel; isolated returns (dust, rain, multipath, sensor
    noise) are spread through the volume. If they were uniform at ``lam`` returns per voxel
    over the ``n_cells`` voxels of the volume, the expected number of voxels they fill with
    ``m`` or more returns would be ``n_cells * P(Poisson(lam) >= m)``. The smallest
    ``m >= floor`` for which that is at most :data:`MAX_ISOLATED_SHARE` of the voxels holding
    ``m`` or more returns (``counts >= m``) is returned (at most
    :data:`MAX_MIN_VOXEL_POINTS`).

    Parameters
    ----------
    counts : ndarray of int, shape (V,)
        Returns per occupied voxel.
    n_cells : float
        Voxels in the volume the isolated returns come from.
    lam : float
        Isolated returns per voxel.
    floor : int
        Smallest value returned (``preprocess.min_voxel_points``).
    """
    m = max(int(floor), 1)
    while 1 < m < MAX_MIN_VOXEL_POINTS:
        kept = int(np.count_nonzero(counts >= m))
        if n_cells * _poisson_tail(lam, m) <= MAX_ISOLATED_SHARE * max(kept, 1):
            break
        m += 1
    return m


@dataclass(frozen=True)
class VoxelChoice:
    """The voxel grid :func:`downsample` used.

    Attributes
    ----------
    size : float
        Voxel edge (0 when the cloud was used as given).
    min_points : int
        Returns a voxel needed to be kept (the isolated-return floor).
    n_isolated : int
        Input points dropped because their voxel held fewer than ``min_points``.
    """

    size: float
    min_points: int
    n_isolated: int


def argsort_keys(keys: NDArray[np.int64]) -> NDArray[np.intp]:
    """Stable ``argsort`` of integer keys (the same order as ``np.argsort(keys, kind='stable')``).

    Non-negative keys (every voxel key) are sorted by an LSD radix sort over 16-bit digits
    (:func:`kentreg_ros.core.kernels.argsort_keys`): two or three passes for the voxel keys of
    a scan, each linear in the number of keys, several times faster than sorting the int64
    keys at once (figures in ``docs/notes-registration.md``).
    """
    if len(keys) == 0:
        return np.zeros(0, dtype=np.intp)
    if int(keys.min()) < 0:
        return np.argsort(keys, kind='stable')
    return kernels.argsort_keys(keys)


@dataclass(frozen=True)
class _Grid:
    """The points grouped by voxel: ``order`` sorts them by voxel key, voxel ``i`` holds
    ``counts[i]`` of them from ``starts[i]`` on."""

    order: NDArray[np.intp]
    starts: NDArray[np.intp]
    counts: NDArray[np.intp]

    @classmethod
    def of(cls, keys: NDArray[np.int64]) -> _Grid:
        order = argsort_keys(keys)
        ordered = keys[order]
        starts = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]]) if len(keys) else order
        counts = np.diff(np.r_[starts, len(keys)])
        return cls(order, starts, counts)

    def centroids(self, points: FloatArray, min_points: int) -> tuple[FloatArray, int]:
        """Centroids of the voxels holding at least ``min_points`` points, and the number of
        points in the others."""
        out = kernels.voxel_centroids(points, self.order, self.starts, self.counts, min_points)
        return out, int(self.counts[self.counts < min_points].sum())


class _VoxelProbe:
    """Cached run lengths of the voxel grids tried by the size search, and the isolated-return
    rate of the cloud."""

    def __init__(self, points: FloatArray) -> None:
        self.points = points
        self.bounds = _bounds(points)
        extent = np.maximum(self.bounds[1] - self.bounds[0], 0.0)
        self.extent = float(extent.max())
        # A flat or linear cloud has no volume; its zero extents count as one unit so that the
        # isolated-return rate stays finite (it only matters for clouds that fill a volume).
        sides = np.sort(np.where(extent > 0.0, extent, 1.0))
        self.volume = float(np.prod(sides))
        self.largest_face = float(sides[1] * sides[2])
        self.rate = 0.0  # isolated returns per unit volume, see measure_rate
        self._grids: dict[float, _Grid] = {}

    def grid(self, size: float) -> _Grid:
        if size not in self._grids:
            self._grids[size] = _Grid.of(_voxel_keys(self.points, size, self.bounds))
        return self._grids[size]

    def counts(self, size: float) -> NDArray[np.intp]:
        return self.grid(size).counts

    def kept(self, size: float, m: int) -> int:
        return int(np.count_nonzero(self.counts(size) >= m))

    def measure_rate(self, size: float) -> None:
        """Isolated returns per unit volume: the single-return voxels at ``size`` over the
        volume. Measured where surfaces put several returns into a voxel, so that a return
        alone in its voxel is a stray one (an upper bound: sparse surface samples count too).
        """
        self.rate = float(np.count_nonzero(self.counts(size) == 1)) / self.volume

    def floor(self, size: float, m: int) -> int:
        """:func:`isolated_return_floor` at ``size`` for the measured rate."""
        cell = size**3
        return isolated_return_floor(self.counts(size), self.volume / cell, self.rate * cell, m)

    @property
    def n_probes(self) -> int:
        return len(self._grids)


#: Ratio between consecutive sizes of the bracketing search (count ~ size^-2: a factor of 2
#: in voxel count per step).
_SEARCH_STEP = float(np.sqrt(2.0))
_SEARCH_TOLERANCE = 0.05
_SEARCH_MAX_PROBES = 12
#: Growing the size, surface voxels fall as size^-2 while voxels filled by pairs of isolated
#: returns grow as size^3 (while sparse); a count falling more slowly than 1 / size is no
#: longer the surfaces' (see :func:`_search_size`).
_SURFACE_SLOPE = -1.0
#: Returns per voxel at which the search starts: the points spread over the bounding box's
#: largest face would put this many in each voxel, well above the size at which surface voxels
#: start to hold single returns (the peak of the count).
_START_RETURNS = 8.0


def _search_size(probe: _VoxelProbe, target: int, m: int, start: float) -> tuple[float, bool]:
    """Largest voxel size on the surface branch whose ``>= m``-return voxels number ``target``.

    Starting at ``start``, the size is stepped by :data:`_SEARCH_STEP` until the count brackets
    ``target``, then interpolated in log-log. Going down, a count that stops growing means the
    cloud is too sparse for ``target`` voxels of ``m`` returns: the size of the largest count
    is returned. Going up, a count that falls more slowly than the surfaces' (slope above
    :data:`_SURFACE_SLOPE`) is made by isolated returns: the search stops and the second value
    is True (raise ``m`` and search again).
    """
    size = start
    count = probe.kept(size, m)
    if abs(count / target - 1.0) < _SEARCH_TOLERANCE:
        return size, False
    if count > target:
        lo, c_lo = size, count
        while True:
            hi = lo * _SEARCH_STEP
            c_hi = probe.kept(hi, m)
            slope = np.log(max(c_hi, 1) / max(c_lo, 1)) / np.log(_SEARCH_STEP)
            if c_hi > target and slope > _SURFACE_SLOPE:
                return lo, True
            if c_hi <= target:
                break
            if probe.n_probes >= _SEARCH_MAX_PROBES:
                return hi, False
            lo, c_lo = hi, c_hi
    else:
        hi, c_hi = size, count
        while True:
            lo = hi / _SEARCH_STEP
            c_lo = probe.kept(lo, m)
            if c_lo >= target:
                break
            if c_lo <= c_hi or probe.n_probes >= _SEARCH_MAX_PROBES:
                return (hi if c_hi >= c_lo else lo), False  # too sparse for target voxels
            hi, c_hi = lo, c_lo
    if c_lo <= 0 or c_hi <= 0 or c_lo == c_hi:
        return hi, False
    slope = (np.log(c_hi) - np.log(c_lo)) / (np.log(hi) - np.log(lo))
    return float(np.exp(np.log(lo) + (np.log(target) - np.log(c_lo)) / slope)), False


def choose_voxel_grid(
    points: FloatArray,
    target_points: int,
    *,
    initial: float = 0.0,
    min_voxel_points: int = 2,
) -> VoxelChoice:
    """Voxel size and returns-per-voxel floor keeping about ``target_points`` surface voxels.

    Only voxels that hold at least ``m`` returns count, and ``m`` (at least
    ``min_voxel_points``) is raised while isolated returns would fill more than
    :data:`MAX_ISOLATED_SHARE` of them (:func:`isolated_return_floor`, with the rate of
    single-return voxels at the size found) or while they, not the surfaces, make the count
    (:func:`_search_size`). So the size is chosen by the surfaces, not by stray points: with
    40 % uniform outliers added to a real scan the size moves by a few percent, where counting
    every occupied voxel let the outliers pick a voxel several times larger.

    The search starts at ``initial`` (e.g. the previous scan's size) or where the points,
    spread over the bounding box's largest face, would hold :data:`_START_RETURNS` per voxel.

    Returns
    -------
    VoxelChoice
        ``size`` 0 when the cloud has no more than ``target_points`` points.
    """
    if len(points) <= target_points:
        return VoxelChoice(0.0, 1, 0)
    probe = _VoxelProbe(points)
    return _choose_grid(probe, points, target_points, initial, max(int(min_voxel_points), 1))


def _choose_grid(
    probe: _VoxelProbe, points: FloatArray, target_points: int, initial: float, m: int
) -> VoxelChoice:
    """:func:`choose_voxel_grid` on a probe whose grids the caller reuses."""
    n = len(points)
    if n <= target_points or probe.extent <= 0.0:
        return VoxelChoice(0.0, 1, 0)
    start = float(np.sqrt(_START_RETURNS * probe.largest_face / n))
    size = initial if initial > 0.0 else min(start, probe.extent)
    for _ in range(MAX_MIN_VOXEL_POINTS):
        size, raise_floor = _search_size(probe, target_points, m, size)
        probe.measure_rate(size)
        m_needed = max(probe.floor(size, m), m + 1 if raise_floor else m)
        if m_needed <= m or m >= MAX_MIN_VOXEL_POINTS:
            break
        m = min(m_needed, MAX_MIN_VOXEL_POINTS)
    counts = probe.counts(size)
    return VoxelChoice(size, m, int(counts[counts < m].sum()))


def choose_voxel_size(
    points: FloatArray, target_points: int, *, initial: float = 0.0, min_voxel_points: int = 2
) -> float:
    """Voxel size of :func:`choose_voxel_grid` (0 when no downsampling is needed)."""
    grid = choose_voxel_grid(
        points, target_points, initial=initial, min_voxel_points=min_voxel_points
    )
    return grid.size


def downsample(
    points: FloatArray,
    *,
    voxel_size: float = 0.0,
    target_points: int = 10000,
    voxel_size_hint: float = 0.0,
    min_voxel_points: int = 2,
) -> tuple[FloatArray, VoxelChoice]:
    """Voxel centroids of the voxels holding enough returns; isolated returns are dropped.

    With ``voxel_size > 0`` that edge is used; otherwise :func:`choose_voxel_grid` picks it
    (starting at ``voxel_size_hint``). Either way a voxel is kept only when it holds at least
    the isolated-return floor of returns (:func:`isolated_return_floor`, at least
    ``min_voxel_points``). A cloud of no more than ``target_points`` points (automatic size) is
    returned as given.

    Returns
    -------
    points : ndarray, shape (M, 3)
        Centroids of the kept voxels, ordered by voxel key.
    grid : VoxelChoice
    """
    if len(points) == 0:
        return points, VoxelChoice(0.0, 1, 0)
    probe = _VoxelProbe(points)
    if voxel_size > 0.0:
        probe.measure_rate(voxel_size)
        m = probe.floor(voxel_size, max(int(min_voxel_points), 1))
        size = voxel_size
        if m > 1 and probe.kept(size, m) < MIN_KEPT_VOXELS <= probe.kept(size, 1):
            logger.warning(
                'Almost every voxel of %.3g holds a single return: the cloud looks already '
                'downsampled at this size, so its single returns are its samples; keeping them '
                '(preprocess.min_voxel_points applies to raw scans).',
                size,
            )
            m = 1
    else:
        grid = _choose_grid(
            probe, points, target_points, voxel_size_hint, max(int(min_voxel_points), 1)
        )
        if grid.size <= 0.0:
            return points, grid
        size, m = grid.size, grid.min_points
    out, n_isolated = probe.grid(size).centroids(points, m)
    return out, VoxelChoice(size, m, n_isolated)
