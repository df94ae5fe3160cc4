"""A saved point-cloud map prepared once for localization: points, normals, their Kent
mixture, a neighbour index and the spectra of the translation search.

Any point-cloud map will do (what ``~/save_map`` and ``kentreg_replay --map`` write, or another
SLAM system's PLY/PCD): it is downsampled to ``localization.map_voxel_size`` and given PCA
normals. A normal's sign says which side its surface was seen from, which a point cloud does
not record. With the positions the map was recorded from (``viewpoints``: the trajectory
``~/save_map`` and the replay write beside their maps) every normal faces the nearest of them,
as a scan's normals face its sensor, and the search compares directed mixtures. Without them
the normals are **axes**, sign unknown: the rotation hypotheses use the mixture of the normals
and their opposites, whose twins (a scan turned inside out matches axes as well) need
:data:`AXIAL_ROTATIONS_FACTOR` times the rotations, and the translation search one channel per
axis. Either way a candidate's registration orients the normals of the map around it toward
its own sensor position (the surfaces a sensor sees face it).

The translation search correlates the occupancy of each normal axis in the map with that of
the scan turned by a rotation hypothesis (3-D FFT; Lucchese et al. 2002 align clouds this way,
and the normal channels keep a floor from matching a wall). The map's spectra are computed
here once. Their grid spans the map (its 0.1-99.9 % extent, within the search reach of a
viewpoint when they are known: a few far stray returns do not grow it) plus a scan's extent,
with cells of at least :data:`MIN_CELL` grown until it holds at most ``localization.grid_cells``
cells.

Memory, stated for a 5M-point map at 0.2 m (about 3M points kept): points and normals
float64 (144 MB), the channel of every point (3 MB), the neighbour index (~70 MB), the spectra
(one per search channel, each at most 2^20 / 2 complex64, 4.2 MB: the 6 cluster directions
with viewpoints, up to 12 axes without; 6 and 7 on the sample's map, 20 and 27 MB): ~250 MB,
bounded by the grid cap, not the site's size.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import scipy.fft as sfft
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.errors import InvalidPointCloudError
from kentreg_ros.core.scan.clusters import ModelClusters, cluster_normals
from kentreg_ros.core.scan.neighbors import NeighborIndex
from kentreg_ros.core.scan.normals import estimate_normals, planar_mask
from kentreg_ros.core.scan.voxels import as_points, downsample

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: Scan points farther than this from the sensor (m) do not enter the translation search (its
#: grid is padded by twice this on every axis): near structure places a scan, and the far
#: returns of a street would double the grid.
SEARCH_REACH = 30.0
#: Smallest cell of the translation search (m): the registration from a candidate converges
#: from a start within about a metre (its correspondence gate and plane-offset start).
MIN_CELL = 1.0
#: Normals closer than this (deg) to an axis already found belong to it (a cluster of
#: normals spreads over ~15-25 deg).
AXIS_SEPARATION_DEG = 30.0
#: Share of the map's points beyond the grid on each side (0.1 %): stray far returns.
EXTENT_QUANTILE = 0.001
#: The cache's format (bumped when what it holds changes).
CACHE_VERSION = 2
#: Rotation hypotheses searched in a map without viewpoints, as a multiple of
#: ``localization.rotations``: each rotation has a twin that turns the scan's normals onto the
#: opposite axes (it scores as well on the axes' mixture), up to three per Manhattan axis.
AXIAL_ROTATIONS_FACTOR = 3


@dataclass(frozen=True, eq=False)
class SearchGrid:
    """The translation search's grid and the map's occupancy spectra per normal axis.

    Attributes
    ----------
    lo : ndarray, shape (3,)
        World coordinate of cell (0, 0, 0)'s corner.
    cell : float
        Cell edge (m).
    shape : tuple of int
        Cells per axis.
    map_cells : ndarray of int, shape (3,)
        Cells the map occupies: a correlation index at or past it is a negative shift.
    spectra : ndarray, shape (C, shape[0], shape[1], shape[2] // 2 + 1)
        ``rfftn`` of the map's occupancy of each axis channel (complex64), stacked.
    """

    lo: FloatArray
    cell: float
    shape: tuple[int, int, int]
    map_cells: NDArray[np.intp]
    spectra: NDArray[np.complex64]

    @property
    def n_cells(self) -> int:
        return int(np.prod(self.shape))


@dataclass(frozen=True, eq=False)
class PointMap:
    """A map prepared for :func:`~kentreg_ros.core.localization.localize`.

    Attributes
    ----------
    points : ndarray, shape (M, 3)
        Voxel centroids (map frame).
    normals : ndarray, shape (M, 3)
        Unit normal axes (their sign carries no meaning).
    voxel_size : float
    viewpoints : ndarray, shape (V, 3), or None
        The positions the map was recorded from, when known: then the normals face them.
    directions : ndarray, shape (C, 3)
        The search channels' directions: the normals' cluster centres (oriented), or their
        axes.
    channels : ndarray of int, shape (M,)
        The channel of every point (:meth:`channel_of` its normal).
    clusters : ModelClusters
        Kent mixture of the normals (oriented), or of the normals and their opposites.
    tree : NeighborIndex
        Index on ``points``.
    grid : SearchGrid
    places : list of ModelClusters
        With viewpoints: the Kent mixture of the normals within :data:`SEARCH_REACH` of places
        along the recorded path (:func:`_places`): a scan's view matches the mixture of the
        place it is in far better than a large site's whole mixture, which is diffuse.
    """

    points: FloatArray
    normals: FloatArray
    voxel_size: float
    viewpoints: FloatArray | None
    directions: FloatArray
    channels: NDArray[np.intp]
    clusters: ModelClusters
    tree: NeighborIndex
    grid: SearchGrid
    places: list[ModelClusters]

    def __len__(self) -> int:
        return len(self.points)

    @property
    def oriented(self) -> bool:
        """The normals face the positions the map was recorded from (else they are axes)."""
        return self.viewpoints is not None

    def channel_of(self, normals: FloatArray) -> NDArray[np.intp]:
        """The search channel of each normal (N, 3): the nearest direction (or axis)."""
        cos = normals @ self.directions.T
        out: NDArray[np.intp] = np.argmax(cos if self.oriented else np.abs(cos), axis=1)
        return out

    @classmethod
    def from_points(
        cls,
        points: ArrayLike,
        *,
        config: KentRegConfig | None = None,
        viewpoints: ArrayLike | None = None,
    ) -> PointMap:
        """Prepare a map from its points, and the positions it was recorded from when known
        (``viewpoints``, shape (V, 3): a trajectory's positions, in the map's frame).

        Raises
        ------
        InvalidPointCloudError
            Malformed points, or too few surfaces left to localize in.
        """
        cfg = config or KentRegConfig()
        pts = as_points(points, 'map points')
        k = cfg.normals.k_neighbors
        voxel = cfg.localization.map_voxel_size
        pts, _ = downsample(pts, voxel_size=voxel, min_voxel_points=1)
        if len(pts) < 4 * k:
            raise InvalidPointCloudError(
                f'Expected a map of at least {4 * k} voxels of {voxel} m, got {len(pts)}.'
            )
        neighbours = NeighborIndex(pts).neighbor_indices(pts, k)
        est = estimate_normals(pts, k, neighbors=neighbours)
        # The planarity test only: the neighbourhood-agreement test needs normals whose signs
        # agree, which they do only once they face a viewpoint.
        keep = planar_mask(est.flatness, cfg.normals.max_flatness)
        pts, nrm = pts[keep], est.normals[keep]
        if len(pts) < 4 * k:
            raise InvalidPointCloudError(
                f'Only {len(pts)} map points lie on surfaces; a map needs at least {4 * k}.'
            )
        views = None if viewpoints is None else as_points(viewpoints, 'viewpoints')
        if views is not None:
            nrm = _facing(pts, nrm, views)
        return cls._assemble(pts, nrm, views, cfg)

    @classmethod
    def _assemble(
        cls, pts: FloatArray, nrm: FloatArray, views: FloatArray | None, cfg: KentRegConfig
    ) -> PointMap:
        oriented = views is not None
        if oriented:
            _, directions, clusters = cluster_normals(nrm, cfg)
            channels = np.argmax(nrm @ directions.T, axis=1)
        else:
            both = np.concatenate([nrm, -nrm])
            doubled = cfg.with_updates({'clustering.n_clusters': 2 * cfg.clustering.n_clusters})
            _, centers, clusters = cluster_normals(both, doubled)
            directions = _axes(centers)
            channels = np.argmax(np.abs(nrm @ directions.T), axis=1)
        cells = cfg.localization.grid_cells
        grid = _search_grid(pts, channels, len(directions), cells, views)
        tree = NeighborIndex(pts).build()
        voxel = cfg.localization.map_voxel_size
        places = [] if views is None else _places(pts, nrm, views, cfg)
        return cls(pts, nrm, voxel, views, directions, channels, clusters, tree, grid, places)

    # -- the cache ---------------------------------------------------------------------------

    def save(self, path: str | Path) -> None:
        """Write the points and normals (the costly part) to ``path`` (``.npz``)."""
        np.savez(
            path,
            version=CACHE_VERSION,
            points=self.points,
            normals=self.normals,
            voxel_size=self.voxel_size,
            viewpoints=np.zeros((0, 3)) if self.viewpoints is None else self.viewpoints,
        )

    @classmethod
    def load(cls, path: str | Path, *, config: KentRegConfig | None = None) -> PointMap:
        """A map saved by :meth:`save`; its clusters, index and spectra are made again.

        Raises
        ------
        InvalidPointCloudError
            Not a map cache of this version, or made at another voxel size.
        """
        cfg = config or KentRegConfig()
        with np.load(path) as data:
            if int(data.get('version', -1)) != CACHE_VERSION:
                raise InvalidPointCloudError(
                    f'{path}: not a map cache of version {CACHE_VERSION}.'
                )
            voxel = float(data['voxel_size'])
            if voxel != cfg.localization.map_voxel_size:
                raise InvalidPointCloudError(
                    f'{path}: made at {voxel} m voxels, not localization.map_voxel_size='
                    f'{cfg.localization.map_voxel_size}.'
                )
            pts, nrm = np.asarray(data['points']), np.asarray(data['normals'])
            views = np.asarray(data['viewpoints'])
        return cls._assemble(pts, nrm, views if len(views) else None, cfg)

    def with_grid_cells(self, grid_cells: int) -> PointMap:
        """The same map with its search grid made for another cell cap."""
        n = len(self.directions)
        grid = _search_grid(self.points, self.channels, n, grid_cells, self.viewpoints)
        return replace(self, grid=grid)


#: Places along the recorded path are this far apart at least (m): half the search reach, so
#: a sensor anywhere near the path is within half a reach of one.
PLACE_SPACING = 0.5 * SEARCH_REACH


def _places(
    points: FloatArray, normals: FloatArray, viewpoints: FloatArray, cfg: KentRegConfig
) -> list[ModelClusters]:
    """The normals' mixture around places along the path: viewpoints at least
    :data:`PLACE_SPACING` apart (greedily, in path order), each with the map within
    :data:`SEARCH_REACH` (places with too few normals to cluster are skipped)."""
    chosen: list[FloatArray] = []
    for v in viewpoints:
        if all(np.linalg.norm(v - c) >= PLACE_SPACING for c in chosen):
            chosen.append(v)
    out: list[ModelClusters] = []
    need = 4 * cfg.clustering.n_clusters * cfg.normals.k_neighbors
    for c in chosen:
        near = np.einsum('ij,ij->i', points - c, points - c) <= SEARCH_REACH**2
        if np.count_nonzero(near) >= need:
            out.append(cluster_normals(normals[near], cfg)[2])
    return out


def _facing(points: FloatArray, normals: FloatArray, viewpoints: FloatArray) -> FloatArray:
    """``normals`` flipped to face the nearest viewpoint of each point."""
    _, nearest = NeighborIndex(viewpoints).query(points, k=1)
    nearest = np.asarray(nearest).reshape(-1)
    away = np.einsum('ij,ij->i', normals, viewpoints[nearest] - points) < 0.0
    out = normals.copy()
    out[away] *= -1.0
    return out


def _axes(centers: FloatArray) -> FloatArray:
    """Normal axes from the centres of the normals' (symmetric) clusters: one per pair of
    opposite centres, at least :data:`AXIS_SEPARATION_DEG` apart."""
    cos_limit = np.cos(np.radians(AXIS_SEPARATION_DEG))
    axes: list[FloatArray] = []
    for c in centers:
        if all(abs(float(c @ a)) < cos_limit for a in axes):
            axes.append(c / np.linalg.norm(c))
    return np.array(axes)


def _search_grid(
    points: FloatArray,
    channels: NDArray[np.intp],
    n_channels: int,
    max_cells: int,
    viewpoints: FloatArray | None = None,
) -> SearchGrid:
    """The grid of the translation search and the map's spectra (module docstring).

    The map occupies cells ``[0, M)`` of each axis and a scan (within :data:`SEARCH_REACH` of
    its sensor, anchored at its own corner) ``[0, S)``, ``S <= 2 SEARCH_REACH / cell``: their
    correlation is non-zero for shifts in ``[-S, M)``, which a grid of ``M + S`` cells holds
    without aliasing (the negative ones wrapped to its end). With ``viewpoints`` the map is
    taken only within the reach of one of them (what a sensor near the recorded path sees).
    """
    usable = points
    if viewpoints is not None and len(viewpoints):
        dist, _ = NeighborIndex(viewpoints).query(points, k=1)
        usable = points[np.asarray(dist).reshape(-1) <= SEARCH_REACH + MIN_CELL]
        if len(usable) == 0:
            usable = points
    lo_map = np.quantile(usable, EXTENT_QUANTILE, axis=0)
    hi_map = np.quantile(usable, 1.0 - EXTENT_QUANTILE, axis=0)
    span = hi_map - lo_map + 2.0 * SEARCH_REACH
    cell = max(MIN_CELL, float(np.cbrt(np.prod(span) / max_cells)))
    shape = tuple(int(sfft.next_fast_len(int(np.ceil(s / cell)) + 2, real=True)) for s in span)
    inside = np.all((points >= lo_map) & (points <= hi_map), axis=1)
    ijk = np.floor((points[inside] - lo_map) / cell).astype(np.intp)
    spectra = np.stack(
        [
            sfft.rfftn(_occupancy(ijk[channels[inside] == c], shape), workers=1)
            for c in range(n_channels)
        ]
    )
    map_cells = np.floor((hi_map - lo_map) / cell).astype(np.intp) + 1
    return SearchGrid(lo_map, cell, (shape[0], shape[1], shape[2]), map_cells, spectra)


def _occupancy(ijk: NDArray[np.intp], shape: tuple[int, ...]) -> NDArray[np.float32]:
    """A binary occupancy grid of cells ``ijk`` (N, 3) (those outside the grid left out)."""
    grid = np.zeros(shape, dtype=np.float32)
    ok = np.all((ijk >= 0) & (ijk < np.array(shape)), axis=1)
    grid[tuple(ijk[ok].T)] = 1.0
    return grid
