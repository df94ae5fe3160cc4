"""The model strategies of the odometry: what each scan is registered against (the previous scan,
or a local map of the accepted scans), and the only thing that moves it.

A model moves once per step, at its end (:meth:`ModelStrategy.update`), never in the middle of
one: the first scan deskewed again during a step (:class:`~.deskew.Deskewer`) is made into a
:class:`FirstAgain` beside the model (:meth:`ModelStrategy.with_first`) and taken by the update.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.errors import InvalidPointCloudError
from kentreg_ros.core.geometry import row_norms
from kentreg_ros.core.odometry.covariance import moved_into_pose
from kentreg_ros.core.odometry.deskew import Sweep
from kentreg_ros.core.odometry.localmap import LocalMap, nearest_spacing
from kentreg_ros.core.odometry.motion import Chained
from kentreg_ros.core.odometry.step import Health
from kentreg_ros.core.scan import PreparedScan
from kentreg_ros.core.stopwatch import Stopwatch

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class PosedScan:
    """What a step gives the model: its scan with the pose and health the step chose.

    Attributes
    ----------
    scan : PreparedScan or None
        The prepared scan (None: rejected).
    health : Health
    pose : Chained
        Its pose in the world (``T_world``) with the covariance.
    stamp_ns, index : int
    sweep : Sweep or None
        The scan's sweep when it has times (a first scan keeps it, to be deskewed again once a
        motion is known).
    first : FirstAgain or None
        The model's first scan, deskewed again during this step: taken before the scan.
    own_covariance : ndarray, shape (6, 6), or None
        The registration's own covariance of the step (without the model's
        :attr:`ModelStrategy.anchor`); None when nothing was registered.
    """

    scan: PreparedScan | None
    health: Health
    pose: Chained
    stamp_ns: int
    index: int
    sweep: Sweep | None = None
    first: FirstAgain | None = None
    own_covariance: FloatArray | None = None


@dataclass(frozen=True, eq=False)
class FirstAgain:
    """The model's first scan deskewed again, and the model it makes (the scan itself, or a
    local map of it in the first scan's frame)."""

    scan: PreparedScan
    target: PreparedScan
    map: LocalMap | None = None


class ModelStrategy(Protocol):
    """What each scan is registered against, and the only thing that moves it.

    ``scan`` is the model in its own frame, posed at ``T_world`` (with covariance ``cov``),
    taken at ``stamp_ns`` from scan number ``index``; None before the first scan.
    ``first_sweep`` is the sweep of the first scan while the model is that scan alone and it
    has per-point times (it was prepared before any motion was known, so not deskewed).
    ``anchor`` is the error of the model's pose against the model itself, in its frame: zero
    for a scan (a step against it is one pair's), the registration of the last accepted pose
    against a local map (a step against the map has that error and its own; issue #40).
    """

    scan: PreparedScan | None
    T_world: FloatArray
    cov: FloatArray
    stamp_ns: int
    index: int
    first_sweep: Sweep | None
    anchor: FloatArray

    def update(self, posed: PosedScan, watch: Stopwatch) -> None:
        """Take the step's scan with its pose and health (its upkeep timed in ``watch`` as
        ``model.<part>``)."""

    def with_first(self, first: PreparedScan) -> FirstAgain:
        """The model as it would be with ``first`` as its first scan; nothing changes here."""


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
        self.first_sweep: Sweep | None = None
        self.anchor = np.zeros((6, 6))

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

    def update(self, posed: PosedScan, watch: Stopwatch) -> None:
        if posed.first is not None:
            self.scan = posed.first.target
        if posed.scan is None:
            return
        self._move(posed, posed.scan)
        # Built now, with the model's upkeep (model.target_tree), not inside the next
        # registration's first query: the registration's timings then hold only its own work.
        with watch('model.target_tree'):
            posed.scan.tree.build()

    def _move(self, posed: PosedScan, model: PreparedScan) -> None:
        self.scan, self.T_world, self.cov = model, posed.pose.T_world.copy(), posed.pose.covariance
        self.stamp_ns, self.index = posed.stamp_ns, posed.index
        self.first_sweep = posed.sweep if posed.health == Health.FIRST else None

    def with_first(self, first: PreparedScan) -> FirstAgain:
        return FirstAgain(first, first)


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

    def update(self, posed: PosedScan, watch: Stopwatch) -> None:
        if posed.first is not None:
            self.map, self.scan = posed.first.map, posed.first.target
        if posed.scan is None:
            return
        if self.scan is not None and self.map is not None and not posed.health.accepted:
            return  # a fall-back stays out of the map
        self.map = self._map_for(posed.scan, self.map)
        # The map's index is built by LocalMap.target, with the rest of the upkeep.
        target = self._insert(self.map, posed.scan, posed.pose.T_world, watch)
        self._move(posed, target)
        # The pose's error against the map, which the next step against the map shares: the
        # step errors are differences of these (lag-one correlation -0.5 in issue #40's
        # simulated sequences, corridor and the sample's scene alike).
        own = posed.own_covariance
        self.anchor = (
            moved_into_pose(own, posed.pose.T_model)
            if own is not None and target is not posed.scan
            else np.zeros((6, 6))
        )

    def with_first(self, first: PreparedScan) -> FirstAgain:
        assert self.map is not None  # the first scan is in it
        empty = LocalMap(
            self.map.voxel_size, max_points_per_voxel=self.map.voxels.max_points_per_voxel
        )
        lmap = self._map_for(first, empty)
        return FirstAgain(first, self._insert(lmap, first, self.T_world, Stopwatch()), lmap)

    def _map_for(self, scan: PreparedScan, lmap: LocalMap | None) -> LocalMap:
        """``lmap``, or a new map when there is none or the settings changed its voxels."""
        odo = self.config.odometry
        if (
            lmap is None
            or lmap.voxels.max_points_per_voxel != odo.map_points_per_voxel
            or (odo.map_voxel_size > 0.0 and lmap.voxel_size != odo.map_voxel_size)
        ):
            voxel = odo.map_voxel_size or scan.voxel_size or nearest_spacing(scan.points)
            return LocalMap(voxel, max_points_per_voxel=odo.map_points_per_voxel)
        return lmap

    def _insert(
        self, lmap: LocalMap, scan: PreparedScan, T_world_scan: FloatArray, watch: Stopwatch
    ) -> PreparedScan:
        """Insert ``scan`` (posed at ``T_world_scan``) into ``lmap``, drop what lies beyond the
        map radius, and return the map in the scan's frame as the next model."""
        odo = self.config.odometry
        radius = odo.map_radius or float(np.max(row_norms(scan.points)))
        with watch('model.map_insert'):
            lmap.insert_scan(scan, T_world_scan, radius=radius)
        try:
            target = lmap.target(T_world_scan, rotation_model=scan, config=self.config)
        except InvalidPointCloudError as exc:
            # Too few map points survive the radius: register against the scan itself.
            logger.warning('The local map cannot be a target (%s); using the scan itself.', exc)
            return scan
        watch.merge({k: v for k, v in target.timings.items() if k != 'total'}, 'model.map_')
        return target
