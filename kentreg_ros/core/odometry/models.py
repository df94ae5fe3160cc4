"""The model strategies of the odometry: what each scan is registered against (the previous scan,
or a local map of the accepted scans), and the only thing that moves it."""

from __future__ import annotations

import logging
import time
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.errors import InvalidPointCloudError
from kentreg_ros.core.geometry import row_norms
from kentreg_ros.core.odometry.localmap import LocalMap, nearest_spacing
from kentreg_ros.core.odometry.stages import Sweep, prepare
from kentreg_ros.core.odometry.step import Health
from kentreg_ros.core.scan import PreparedScan
from kentreg_ros.core.scan.prepared import elapsed_ms

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


class ModelStrategy(Protocol):
    """What each scan is registered against, and the only thing that moves it.

    ``scan`` is the model in its own frame, posed at ``T_world`` (with covariance ``cov``),
    taken at ``stamp_ns`` from scan number ``index``; None before the first scan.
    """

    scan: PreparedScan | None
    T_world: FloatArray
    cov: FloatArray
    stamp_ns: int
    index: int
    #: Milliseconds of the last update's parts (empty where it has none worth timing).
    timings: dict[str, float]

    def update(
        self,
        scan: PreparedScan | None,
        outcome: Health,
        T_world_scan: FloatArray,
        cov: FloatArray,
        stamp_ns: int,
        index: int,
        sweep: Sweep | None,
    ) -> None:
        """Take the step's scan (None: rejected) with its pose and health."""

    def deskew_first(self, twist: FloatArray, config: KentRegConfig) -> PreparedScan:
        """The model, with the first scan deskewed by ``twist`` if it was prepared before any
        motion was known (its sweep moved like the current one: constant velocity)."""


class PreviousScanModel:
    """The previous scan is the model (the design card's odometry): every prepared scan moves
    the model on, including one that fell back (its predicted pose is the best estimate, and
    the next registration then bridges one scan gap, not two); a rejected one does not."""

    def __init__(self, T_world: FloatArray) -> None:
        self.scan: PreparedScan | None = None
        self.T_world = T_world.copy()
        self.cov = np.zeros((6, 6))
        self.stamp_ns = 0
        self.index = -1
        self.timings: dict[str, float] = {}
        # Raw points and times of a first scan prepared before any motion was known.
        self._first_sweep: Sweep | None = None

    @classmethod
    def like(cls, other: ModelStrategy, config: KentRegConfig) -> PreviousScanModel:
        """This strategy continuing from ``other``'s model."""
        out = cls(other.T_world)
        out._take_over(other)
        return out

    def _take_over(self, other: ModelStrategy) -> None:
        """Continue from ``other``'s model: its scan, covariance, stamp and index."""
        self.scan, self.cov, self.stamp_ns, self.index = (
            other.scan,
            other.cov,
            other.stamp_ns,
            other.index,
        )

    def update(
        self,
        scan: PreparedScan | None,
        health: Health,
        T_world_scan: FloatArray,
        cov: FloatArray,
        stamp_ns: int,
        index: int,
        sweep: Sweep | None,
    ) -> None:
        if scan is None:
            self.timings = {}
            return
        self._move(scan, T_world_scan, cov, stamp_ns, index)
        self._first_sweep = sweep if health == Health.FIRST and sweep is not None else None
        self._index_target()

    def _index_target(self) -> None:
        """Build the next registration's target index now, with the model's upkeep (which a
        pipeline runs after the pose is out), not at that registration's first query: ~1.2 ms
        of a 10k-point scan off the next scan's latency."""
        assert self.scan is not None
        t0 = time.perf_counter()
        self.scan.tree.build()
        self.timings = {'target_tree': elapsed_ms(t0)}

    def _move(
        self, scan: PreparedScan, T_world: FloatArray, cov: FloatArray, stamp_ns: int, index: int
    ) -> None:
        self.scan, self.T_world, self.cov = scan, T_world.copy(), cov
        self.stamp_ns, self.index = stamp_ns, index

    def deskew_first(self, twist: FloatArray, config: KentRegConfig) -> PreparedScan:
        assert self.scan is not None
        if self._first_sweep is not None:
            self.scan = prepare(self._first_sweep, twist, config, self.scan.voxel_size)
            self._first_sweep = None
        return self.scan


class LocalMapModel(PreviousScanModel):
    """A bounded voxel map of the accepted scans (:class:`LocalMap`, world frame, the normals
    each scan brought), expressed in the frame of the last accepted pose. Only an accepted step
    (or the first scan) enters the map and moves the model; one that fell back or was rejected
    leaves both as they were, so the next scan is registered from the last accepted pose."""

    def __init__(self, T_world: FloatArray, config: KentRegConfig) -> None:
        super().__init__(T_world)
        self.config = config
        self.map: LocalMap | None = None

    @classmethod
    def like(cls, other: ModelStrategy, config: KentRegConfig) -> LocalMapModel:
        out = cls(other.T_world, config)
        out._take_over(other)
        return out

    def update(
        self,
        scan: PreparedScan | None,
        health: Health,
        T_world_scan: FloatArray,
        cov: FloatArray,
        stamp_ns: int,
        index: int,
        sweep: Sweep | None,
    ) -> None:
        self.timings = {}
        if scan is None:
            return
        if self.scan is not None and self.map is not None and not health.accepted:
            return  # a fall-back stays out of the map
        super().update(
            self._insert(scan, T_world_scan), health, T_world_scan, cov, stamp_ns, index, sweep
        )

    def _index_target(self) -> None:
        """Nothing: :meth:`LocalMap.target` builds the map's index with the rest of the upkeep
        (a scan that stands in for a map too small to be a target is indexed when queried);
        the map's own timings stay as :meth:`update` set them."""

    def _insert(self, scan: PreparedScan, T_world_scan: FloatArray) -> PreparedScan:
        """Insert ``scan`` (posed at ``T_world_scan``) into the map, drop what lies beyond the
        map radius, and return the map in the scan's frame as the next model."""
        odo = self.config.odometry
        if (
            self.map is None
            or self.map.voxels.max_points_per_voxel != odo.map_points_per_voxel
            or (odo.map_voxel_size > 0.0 and self.map.voxel_size != odo.map_voxel_size)
        ):
            voxel = odo.map_voxel_size or scan.voxel_size or nearest_spacing(scan.points)
            self.map = LocalMap(voxel, max_points_per_voxel=odo.map_points_per_voxel)
        radius = odo.map_radius or float(np.max(row_norms(scan.points)))
        t0 = time.perf_counter()
        self.map.insert_scan(scan, T_world_scan, radius=radius)
        self.timings = {'map_insert': elapsed_ms(t0)}
        try:
            target = self.map.target(T_world_scan, rotation_model=scan, config=self.config)
            self.timings |= {f'map_{k}': v for k, v in target.timings.items() if k != 'total'}
            return target
        except InvalidPointCloudError as exc:
            # Too few map points survive the radius: register against the scan itself.
            logger.warning('The local map cannot be a target (%s); using the scan itself.', exc)
            return scan

    def deskew_first(self, twist: FloatArray, config: KentRegConfig) -> PreparedScan:
        assert self.scan is not None
        if self._first_sweep is not None and self.map is not None:
            first = prepare(self._first_sweep, twist, config, self.scan.voxel_size)
            self.map.clear()  # the map holds only the first scan yet
            self.scan = self._insert(first, self.T_world)
            self._first_sweep = None
        return self.scan
