"""A scan prepared once for registration: cropped, voxel-downsampled (isolated returns
dropped), PCA normals gated by flatness and neighbourhood agreement, spherical k-means clusters
with their Kent moments and binned normals. The odometry prepares every scan once and reuses it
as the next model."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.errors import InvalidInputError, InvalidPointCloudError
from kentreg_ros.core.geometry import row_norms
from kentreg_ros.core.scan.clusters import (
    ModelClusters,
    cluster_normals,
)
from kentreg_ros.core.scan.neighbors import NeighborIndex
from kentreg_ros.core.scan.normals import estimate_normals, normal_inlier_mask, planar_mask
from kentreg_ros.core.scan.voxels import VoxelChoice, as_points, crop_range, downsample
from kentreg_ros.core.stopwatch import Stopwatch

logger = logging.getLogger(__name__)


FloatArray = NDArray[np.float64]


MIN_POINTS = 20


@dataclass(frozen=True, eq=False)
class PreparedScan:
    """A scan preprocessed once and reusable as source or target of many registrations.

    Attributes
    ----------
    points : ndarray, shape (N, 3)
        Downsampled points whose normals passed the outlier test.
    normals : ndarray, shape (N, 3)
        Unit normals oriented toward ``viewpoint``.
    labels : ndarray of int, shape (N,)
        Spherical k-means cluster of every normal.
    centers : ndarray, shape (K, 3)
        Cluster mean directions.
    clusters : ModelClusters
        Kent frames of the clusters (used when this scan is the model).
    tree : NeighborIndex
        Tree on ``points``.
    voxel_size : float
        Voxel edge used (0 if the input was used as is).
    viewpoint : ndarray, shape (3,)
    n_input : int
        Points given.
    n_isolated : int
        Input points dropped as isolated returns (their voxel held too few returns).
    min_voxel_points : int
        Returns a voxel needed to be kept (the isolated-return floor used).
    n_normal_outliers : int
        Points removed by the cosine-similarity normal test.
    timings : dict of str to float
        Milliseconds per preprocessing stage: ``downsample``, ``neighbours`` and ``normals``
        (only ``normals`` for given normals), ``outliers``, ``clustering`` and ``total``.
    """

    points: FloatArray
    normals: FloatArray
    labels: NDArray[np.intp]
    centers: FloatArray
    clusters: ModelClusters
    tree: NeighborIndex
    voxel_size: float
    viewpoint: FloatArray
    n_input: int
    n_isolated: int
    min_voxel_points: int
    n_normal_outliers: int
    timings: dict[str, float] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.points)


def elapsed_ms(t0: float) -> float:
    """Milliseconds since ``t0`` (a ``time.perf_counter()`` reading)."""
    return (time.perf_counter() - t0) * 1e3


def prepare_scan(
    points: ArrayLike,
    *,
    config: KentRegConfig | None = None,
    viewpoint: ArrayLike = (0.0, 0.0, 0.0),
    normals: ArrayLike | None = None,
    voxel_size_hint: float = 0.0,
) -> PreparedScan:
    """Preprocess a scan once: crop, downsample, normals, outlier removal, clustering.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Finite points in the sensor frame (drop NaN/inf first).
    config : KentRegConfig, optional
    viewpoint : array_like, shape (3,)
        Sensor origin in the points' frame; normals face it.
    normals : array_like, shape (N, 3), optional
        Precomputed normals for ``points``; then ``points`` are used as given (no cropping or
        downsampling) and only the cosine outlier test and clustering run.
    voxel_size_hint : float
        With automatic voxel sizing (``preprocess.voxel_size = 0``), start the size search
        here, e.g. at the previous scan's ``voxel_size``: usually one counting pass instead of
        four.

    Raises
    ------
    InvalidPointCloudError
        Wrong shape, NaN/inf, or too few points for the neighbourhood size.
    """
    cfg = config or KentRegConfig()
    watch = Stopwatch()
    pts = as_points(points)
    vp = np.asarray(viewpoint, dtype=np.float64).reshape(3)
    if not np.isfinite(vp).all():
        raise InvalidInputError(f'Expected a finite `viewpoint`, got {vp}.')
    n_input = len(pts)
    k = cfg.normals.k_neighbors
    voxel = 0.0
    n_isolated = 0
    floor = 1
    if normals is None:
        with watch('downsample'):
            pts, grid = _downsampled(pts, cfg, vp, voxel_size_hint)
            voxel, n_isolated, floor = grid.size, grid.n_isolated, grid.min_points
        with watch('neighbours'):  # timed apart: the largest single stage
            tree = NeighborIndex(pts)
            neighbours = tree.neighbor_indices(pts, k)
        with watch('normals'):
            est = estimate_normals(pts, k, viewpoint=vp, neighbors=neighbours)
            nrm, flat, nbrs = est.normals, est.flatness, est.neighbors
    else:
        with watch('normals'):
            nrm, tree, nbrs = _given_normals(pts, normals, k)
            flat = np.zeros(len(pts))  # given normals are trusted
    with watch('outliers'):
        keep = normal_inlier_mask(nrm, np.asarray(nbrs, dtype=np.intp), cfg.normals.outlier_cosine)
        keep &= planar_mask(flat, cfg.normals.max_flatness)
        n_out = int((~keep).sum())
        if keep.sum() < MIN_POINTS:
            raise InvalidPointCloudError(
                f'Only {int(keep.sum())} of {len(pts)} normals passed the planarity and outlier '
                f'tests (normals.max_flatness={cfg.normals.max_flatness}, '
                f'normals.outlier_cosine={cfg.normals.outlier_cosine}); need {MIN_POINTS}.'
            )
        if n_out:
            rows = np.flatnonzero(keep)  # take(): boolean indexing's rows, several times faster
            pts, nrm = pts.take(rows, axis=0), nrm.take(rows, axis=0)
            tree = NeighborIndex(pts)
    with watch('clustering'):
        labels, centers, clusters = cluster_normals(nrm, cfg)
    watch.add('total', watch.elapsed_ms())
    return PreparedScan(
        points=pts,
        normals=nrm,
        labels=labels,
        centers=centers,
        clusters=clusters,
        tree=tree,
        voxel_size=voxel,
        viewpoint=vp,
        n_input=n_input,
        n_isolated=n_isolated,
        min_voxel_points=floor,
        n_normal_outliers=n_out,
        timings=watch.as_dict(),
    )


def _downsampled(
    pts: FloatArray, cfg: KentRegConfig, vp: FloatArray, voxel_size_hint: float
) -> tuple[FloatArray, VoxelChoice]:
    """The points cropped and downsampled (see :func:`prepare_scan`).

    Raises
    ------
    InvalidPointCloudError
        Too few left for the neighbourhood size.
    """
    n_input = len(pts)
    k = cfg.normals.k_neighbors
    cropped = crop_range(pts, cfg.preprocess.min_range, cfg.preprocess.max_range, vp)
    out, grid = downsample(
        cropped,
        voxel_size=cfg.preprocess.voxel_size,
        target_points=cfg.preprocess.target_points,
        voxel_size_hint=voxel_size_hint,
        min_voxel_points=cfg.preprocess.min_voxel_points,
    )
    if len(out) < max(k, MIN_POINTS):
        # The extent only explains the error, so it is measured here, not on every scan.
        extent = float(np.max(np.ptp(cropped, axis=0))) if len(cropped) else 0.0
        raise InvalidPointCloudError(
            f'Expected at least {max(k, MIN_POINTS)} points after preprocessing '
            f'(k_neighbors={k}), got {len(out)} (from {n_input} input points, '
            f'{len(cropped)} within preprocess.min_range/max_range, spanning {extent:.4g} m, '
            f'in voxels of {grid.size:.4g} m).'
        )
    return out, grid


def _given_normals(
    pts: FloatArray, normals: ArrayLike, k: int
) -> tuple[FloatArray, NeighborIndex, NDArray[np.intp]]:
    """Given normals checked and normalised, the points' index and their ``k`` neighbours.

    Raises
    ------
    InvalidPointCloudError
        Normals of another shape or of zero length, or too few points.
    """
    nrm = as_points(normals, 'normals')
    if nrm.shape != pts.shape:
        raise InvalidPointCloudError(
            f'Expected `normals` to have the shape of `points` {pts.shape}, got {nrm.shape}.'
        )
    lengths = row_norms(nrm)
    if np.any(lengths < 1e-9):
        raise InvalidPointCloudError('`normals` contains zero-length vectors.')
    nrm = nrm / lengths[:, None]
    if len(pts) < max(k, MIN_POINTS):
        raise InvalidPointCloudError(
            f'Expected at least {max(k, MIN_POINTS)} points, got {len(pts)}.'
        )
    tree = NeighborIndex(pts)
    _, nbrs = tree.query(pts, k=k)
    return nrm, tree, nbrs


def as_prepared(
    scan: ArrayLike | PreparedScan,
    normals: ArrayLike | None,
    cfg: KentRegConfig,
    viewpoint: ArrayLike,
    name: str,
) -> PreparedScan:
    if isinstance(scan, PreparedScan):
        if normals is not None:
            raise InvalidInputError(
                f'`{name}_normals` cannot be given with a PreparedScan `{name}`.'
            )
        return scan
    try:
        return prepare_scan(scan, config=cfg, viewpoint=viewpoint, normals=normals)
    except InvalidPointCloudError as exc:
        raise InvalidPointCloudError(f'{name}: {exc}') from exc
