"""Input validation, range cropping and voxel downsampling of point clouds."""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core.errors import InvalidPointCloudError

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
    if not allow_nonfinite:
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
    d2 = np.sum((points - np.asarray(origin, dtype=np.float64)) ** 2, axis=1)
    keep = d2 >= min_range**2
    if max_range > 0.0:
        keep &= d2 <= max_range**2
    return np.ascontiguousarray(points[keep])


def _voxel_keys(points: FloatArray, voxel_size: float) -> NDArray[np.int64]:
    idx = np.floor(points / voxel_size).astype(np.int64)
    idx -= idx.min(axis=0)
    span = idx.max(axis=0) + 1
    return (idx[:, 0] * span[1] + idx[:, 1]) * span[2] + idx[:, 2]


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
        raise ValueError(f'Expected `voxel_size` > 0, got {voxel_size!r}.')
    if len(pts) == 0:
        return pts
    keys = _voxel_keys(pts, voxel_size)
    uniq, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    out = np.empty((len(uniq), 3))
    for axis in range(3):
        out[:, axis] = np.bincount(inverse, weights=pts[:, axis], minlength=len(uniq))
    out /= counts[:, None]
    return out


def count_voxels(points: FloatArray, voxel_size: float) -> int:
    """Number of occupied voxels of edge ``voxel_size``."""
    return int(np.unique(_voxel_keys(points, voxel_size)).size)


def choose_voxel_size(
    points: FloatArray, target_points: int, *, iterations: int = 4, initial: float = 0.0
) -> float:
    """Voxel size for which :func:`voxel_downsample` keeps about ``target_points`` points.

    Surfaces dominate LiDAR scans, so the voxel count scales roughly as ``size**-2``; a few
    secant steps in that model converge to within a few percent. ``initial`` (e.g. the size
    chosen for the previous scan of a sequence) replaces the bounding-box guess, which usually
    leaves a single counting pass.
    """
    n = len(points)
    if n <= target_points:
        return 0.0
    extent = float(np.max(np.ptp(points, axis=0)))
    if extent <= 0.0:
        return 0.0
    # Initial guess: the area of a bounding-box shell split into target_points squares.
    size = initial if initial > 0.0 else max(extent * np.sqrt(6.0 / target_points) * 0.5, 1e-6)
    best = size
    for _ in range(iterations):
        count = count_voxels(points, size)
        best = size
        ratio = count / target_points
        if abs(ratio - 1.0) < 0.05:
            break
        size *= float(np.clip(np.sqrt(ratio), 0.25, 4.0))
    return best


def downsample(
    points: FloatArray,
    *,
    voxel_size: float = 0.0,
    target_points: int = 10000,
    voxel_size_hint: float = 0.0,
) -> tuple[FloatArray, float]:
    """Voxel downsample with a fixed size, or an automatic size reaching ``target_points``.

    ``voxel_size_hint`` starts the automatic search (see :func:`choose_voxel_size`).
    Returns ``(points, voxel_size_used)``; ``voxel_size_used`` is 0 when nothing was done.
    """
    size = (
        voxel_size
        if voxel_size > 0.0
        else choose_voxel_size(points, target_points, initial=voxel_size_hint)
    )
    if size <= 0.0:
        return points, 0.0
    return voxel_downsample(points, size), size
