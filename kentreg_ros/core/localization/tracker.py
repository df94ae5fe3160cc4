"""Tracking a run through a saved map with the odometry, and relocalizing when lost.

:class:`Localizer` keeps ``T_map_odom``, the odometry frame in the map (REP-105's ``map ->
odom``). Each scan comes with its odometry pose ``T_odom_scan``:

- **localized**: the pose predicted by the odometry, ``T_map_odom T_odom_scan``, starts a
  registration against the map around it; it is taken when it passes the gates of
  :func:`~kentreg_ros.core.localization.localize` and corrects the prediction by no more than
  ``localization.tracking_distance`` / ``tracking_angle_deg``. A larger correction is not
  applied (the map frame never jumps silently): it counts as a miss, and the scan is searched
  like a relocalization, whose agreement it then needs.
- **searching** (no pose yet, or after :meth:`relocalize`): each scan is localized without a
  start (or within the window of :meth:`set_initial_pose`); a ``localized`` answer proposes
  ``T_map_odom``, and it is taken once ``localization.agreement`` consecutive scans propose
  the same one (within the tracking gates): the odometry chains them, so a twin or a wrong
  place has to be repeated by the motion to be taken.
- **lost**: ``localization.agreement`` misses in a row while localized; it searches again
  (``T_map_odom`` is kept, and published as the last known, until a new one is taken).
- **ambiguous**: the last search found distinct poses fitting about equally.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.geometry import check_transform, invert_transform, rotation_angle
from kentreg_ros.core.localization.localize import (
    LocalizationResult,
    LocalizationStatus,
    localize,
)
from kentreg_ros.core.localization.pointmap import PointMap
from kentreg_ros.core.localization.search import Window
from kentreg_ros.core.scan import PreparedScan

FloatArray = NDArray[np.float64]


class TrackingState(StrEnum):
    """What the localizer knows of the run's place in the map."""

    SEARCHING = 'searching'
    LOCALIZED = 'localized'
    LOST = 'lost'
    AMBIGUOUS = 'ambiguous'


@dataclass(frozen=True, eq=False)
class TrackStep:
    """What :meth:`Localizer.update` did with one scan.

    Attributes
    ----------
    state : TrackingState
        The state after this scan.
    T_map_odom : ndarray, shape (4, 4), or None
        The odometry frame in the map (the last taken; None before the first).
    T_map_scan : ndarray, shape (4, 4), or None
        This scan's pose in the map, when this scan was localized (tracked, or the last of an
        agreeing search).
    result : LocalizationResult
        The localization of this scan.
    searched : bool
        This scan was searched (not tracked).
    message : str
    """

    state: TrackingState
    T_map_odom: FloatArray | None
    T_map_scan: FloatArray | None
    result: LocalizationResult
    searched: bool
    message: str


class Localizer:
    """Tracks scans through ``pmap`` with their odometry poses (module docstring)."""

    def __init__(self, pmap: PointMap, config: KentRegConfig | None = None) -> None:
        self.pmap = pmap
        self.config = config or KentRegConfig()
        self.state = TrackingState.SEARCHING
        self.T_map_odom: FloatArray | None = None
        self._proposals: deque[FloatArray] = deque(maxlen=self.config.localization.agreement)
        self._misses = 0
        self._start: tuple[FloatArray, Window] | None = None

    def relocalize(self) -> None:
        """Search again from no start (keeping the last ``T_map_odom`` until a new one)."""
        self.state = TrackingState.SEARCHING
        self._proposals.clear()
        self._start = None

    def set_initial_pose(self, T_map_scan: ArrayLike, window: Window) -> None:
        """Search within ``window`` of ``T_map_scan`` (the next scan's pose in the map, as an
        operator gives it, e.g. rviz's 2D Pose Estimate with its covariance)."""
        self._start = (check_transform(T_map_scan, 'T_map_scan'), window)
        self.state = TrackingState.SEARCHING
        self._proposals.clear()

    def update(self, scan: PreparedScan, T_odom_scan: ArrayLike) -> TrackStep:
        """Place the scan whose odometry pose is ``T_odom_scan``."""
        T_os = check_transform(T_odom_scan, 'T_odom_scan')
        if self.state is TrackingState.LOCALIZED and self.T_map_odom is not None:
            step = self._track(scan, T_os)
            if step is not None:
                return step
        return self._search(scan, T_os)

    def _within_gates(self, T_a: FloatArray, T_b: FloatArray) -> bool:
        loc = self.config.localization
        D = invert_transform(T_a) @ T_b
        return bool(
            np.linalg.norm(D[:3, 3]) <= loc.tracking_distance
            and np.degrees(rotation_angle(D[:3, :3])) <= loc.tracking_angle_deg
        )

    def _track(self, scan: PreparedScan, T_os: FloatArray) -> TrackStep | None:
        assert self.T_map_odom is not None
        predicted = self.T_map_odom @ T_os
        result = localize(scan, self.pmap, init=predicted, config=self.config)
        if result.localized and result.T_map_scan is not None:
            if self._within_gates(predicted, result.T_map_scan):
                self._misses = 0
                self.T_map_odom = result.T_map_scan @ invert_transform(T_os)
                return TrackStep(
                    TrackingState.LOCALIZED, self.T_map_odom.copy(), result.T_map_scan, result,
                    False, 'Tracked.',
                )  # fmt: skip
        self._misses += 1
        if self._misses < self.config.localization.agreement:
            why = 'moved past the tracking gates' if result.localized else result.message
            return TrackStep(
                TrackingState.LOCALIZED, self.T_map_odom.copy(), None, result, False,
                f'Missed ({self._misses} in a row): {why}',
            )  # fmt: skip
        self._misses = 0
        self.state = TrackingState.LOST
        self._proposals.clear()
        return None

    def _search(self, scan: PreparedScan, T_os: FloatArray) -> TrackStep:
        if self._start is not None:
            T0, window = self._start
            result = localize(scan, self.pmap, init=T0, window=window, config=self.config)
        else:
            result = localize(scan, self.pmap, config=self.config)
        last = None if self.T_map_odom is None else self.T_map_odom.copy()
        if result.status is LocalizationStatus.AMBIGUOUS:
            self._proposals.clear()
            if self.state is not TrackingState.LOST:
                self.state = TrackingState.AMBIGUOUS
            return TrackStep(self.state, last, None, result, True, result.message)
        if not result.localized or result.T_map_scan is None:
            self._proposals.clear()
            return TrackStep(self.state, last, None, result, True, result.message)
        proposal = result.T_map_scan @ invert_transform(T_os)
        if self._proposals and not self._within_gates(self._proposals[-1], proposal):
            self._proposals.clear()
        self._proposals.append(proposal)
        need = self.config.localization.agreement
        if len(self._proposals) < need:
            message = f'Found a pose; {len(self._proposals)} of {need} scans agree so far.'
            return TrackStep(self.state, last, None, result, True, message)
        self.T_map_odom = proposal
        self.state = TrackingState.LOCALIZED
        self._start = None
        self._proposals.clear()
        self._misses = 0
        return TrackStep(
            self.state, proposal.copy(), result.T_map_scan, result, True,
            f'Localized: {need} consecutive scans agree.',
        )  # fmt: skip
