"""Localization runs over recorded scans, and their score against a reference.

Two ways through a recording and a saved map (:class:`~kentreg_ros.core.PointMap`):

- :func:`track_recording`: the odometry runs over the scans as in ``kentreg_replay``
  (:func:`~kentreg_ros.eval.run.run_odometry`), and each scan it prepared, with its odometry
  pose, goes to a :class:`~kentreg_ros.core.Localizer` (search, agreement, tracking);
- :func:`localize_each`: every scan on its own from no start
  (:func:`~kentreg_ros.core.localize`), the benchmark's mode.

Both give a :class:`LocalizationRun`, one :class:`LocalizedScan` per scan read.
:func:`score_localization` compares the localized poses with reference poses, which is possible
only when both are in one frame: :func:`reference_frame_note` checks that the map was built at
the reference poses (its trajectory is at them).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from contextlib import closing
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core import (
    InThreadPreparer,
    InvalidPointCloudError,
    KentRegConfig,
    LocalizationStatus,
    Localizer,
    Odometry,
    OdometryStep,
    PointMap,
    Preparation,
    PrepareInputs,
    RawScan,
    localize,
)
from kentreg_ros.eval.groundtruth import GroundTruth, associate
from kentreg_ros.eval.metrics import pair_errors
from kentreg_ros.eval.run import (
    OdometryRun,
    ScanSequence,
    read_selected,
    run_odometry,
    selected_indices,
)
from kentreg_ros.io.poses import Trajectory
from kentreg_ros.io.sources import SkippedScan

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: A localized pose off the reference by more than either of these is wrong (issue 39's bars:
#: a relocalization that a tracking registration cannot finish from is no help).
MAX_ROTATION_DEG = 2.0
MAX_TRANSLATION_M = 0.5
#: The map's trajectory is at the reference poses when every pose of it that has a reference
#: pose agrees with it within these (pose files print 6-9 digits; a map built from odometry
#: poses drifts from the reference by centimetres to metres).
FRAME_TOLERANCE_M = 0.05
FRAME_TOLERANCE_DEG = 0.5


class RunMode(StrEnum):
    """How the scans went through the map."""

    #: The odometry chains the scans and a :class:`~kentreg_ros.core.Localizer` tracks them.
    TRACK = 'track'
    #: Every scan localized on its own from no start.
    GLOBAL_EACH = 'global_each'


@dataclass(frozen=True, eq=False)
class LocalizedScan:
    """What became of one scan.

    Attributes
    ----------
    index : int
        The scan's index in the input.
    stamp_ns : int
    status : str
        :class:`~kentreg_ros.core.TrackingState` after this scan when tracking (``searching``,
        ``localized``, ``lost``, ``ambiguous``), else :class:`~kentreg_ros.core.LocalizationStatus`
        (``localized``, ``ambiguous``, ``not_found``).
    T_map_scan : ndarray, shape (4, 4), or None
        The scan's pose in the map when this scan was placed (tracked, the last of an agreeing
        search, or localized on its own), else None.
    fit : float
        Balanced fit of the best candidate (NaN without one).
    message : str
    ms : float
        Milliseconds of the localization (the scan's preparation included, the odometry not).
    searched : bool
        The scan was searched (not tracked from the odometry's prediction).
    """

    index: int
    stamp_ns: int
    status: str
    T_map_scan: FloatArray | None
    fit: float
    message: str
    ms: float
    searched: bool = True

    @property
    def localized(self) -> bool:
        """A pose was given for this scan."""
        return self.T_map_scan is not None

    def record(self) -> dict[str, Any]:
        """The scan's entry of ``localization.json`` (NaN written as None)."""
        pose = None if self.T_map_scan is None else np.round(self.T_map_scan, 9).tolist()
        return {
            'index': self.index,
            'stamp_ns': self.stamp_ns,
            'status': str(self.status),
            'T_map_scan': pose,
            'fit': round(self.fit, 4) if np.isfinite(self.fit) else None,
            'message': self.message,
            'ms': round(self.ms, 1),
            'searched': self.searched,
        }


@dataclass
class LocalizationRun:
    """The scans of one input through a map.

    Attributes
    ----------
    mode : RunMode
    scans : list of LocalizedScan
        One per scan read, in order.
    interrupted : bool
        Ctrl-C ended the run early.
    error : str or None
        The read error (or refused scan) that ended the run early.
    n_skipped : int
        Selected scans that could not be decoded.
    skipped : list of SkippedScan
        The first few of them.
    odometry : OdometryRun or None
        The odometry's run when tracking.
    """

    mode: RunMode
    scans: list[LocalizedScan] = field(default_factory=list)
    interrupted: bool = False
    error: str | None = None
    n_skipped: int = 0
    skipped: list[SkippedScan] = field(default_factory=list)
    odometry: OdometryRun | None = None

    @property
    def localized(self) -> list[LocalizedScan]:
        """The scans given a pose."""
        return [s for s in self.scans if s.localized]

    def counts(self) -> dict[str, int]:
        """Scans per status, and ``with_pose``: those given a pose."""
        out: dict[str, int] = {}
        for s in self.scans:
            out[str(s.status)] = out.get(str(s.status), 0) + 1
        out['with_pose'] = len(self.localized)
        return out


def localize_each(
    source: ScanSequence,
    pmap: PointMap,
    *,
    config: KentRegConfig | None = None,
    start: int = 0,
    max_scans: int | None = None,
    stride: int = 1,
    on_scan: Callable[[LocalizedScan], object] | None = None,
) -> LocalizationRun:
    """Localize every selected scan of ``source`` in ``pmap`` on its own, from no start.

    A scan that cannot be used (too few points) is ``not_found`` with the reason. Ctrl-C ends
    the run early with the scans so far (``interrupted``).

    Parameters
    ----------
    source : ScanSequence
        The scans (a :class:`~kentreg_ros.io.sources.ScanSource` or a list of scans).
    pmap : PointMap
    config : KentRegConfig, optional
    start, max_scans, stride :
        Which scans (:func:`~kentreg_ros.eval.run.selected_indices`).
    on_scan : callable, optional
        Called with each scan's outcome (a progress bar).

    Returns
    -------
    LocalizationRun
    """
    cfg = config or KentRegConfig()
    run = LocalizationRun(RunMode.GLOBAL_EACH)
    indices = selected_indices(len(source), start, max_scans, stride)
    try:
        with closing(read_selected(source, indices, run)) as scans:
            for index, scan, _ in scans:
                t0 = time.perf_counter()
                points = np.asarray(scan.points, dtype=np.float64)
                try:
                    result = localize(points, pmap, config=cfg)
                except InvalidPointCloudError as exc:
                    ms = (time.perf_counter() - t0) * 1e3
                    status, fit, message = LocalizationStatus.NOT_FOUND, float('nan'), str(exc)
                    entry = LocalizedScan(index, scan.stamp_ns, status, None, fit, message, ms)
                else:
                    best = result.best
                    entry = LocalizedScan(
                        index, scan.stamp_ns, result.status, result.T_map_scan,
                        best.fit if best is not None else float('nan'), result.message,
                        result.timings.get('total', (time.perf_counter() - t0) * 1e3),
                    )  # fmt: skip
                run.scans.append(entry)
                if on_scan is not None:
                    on_scan(entry)
    except KeyboardInterrupt:
        run.interrupted = True
    return run


class _KeepingPreparer:
    """The odometry's prepare stage in this thread, keeping the last scan it prepared for the
    localizer (the scan is prepared once, for both)."""

    def __init__(self) -> None:
        self._inner = InThreadPreparer()
        self.last: Preparation | None = None

    def prepare(self, scan: RawScan, inputs: PrepareInputs) -> Preparation:
        self.last = self._inner.prepare(scan, inputs)
        return self.last

    def expect(self, inputs: PrepareInputs) -> None:
        self._inner.expect(inputs)


def track_recording(
    source: ScanSequence,
    pmap: PointMap,
    *,
    config: KentRegConfig | None = None,
    start: int = 0,
    max_scans: int | None = None,
    stride: int = 1,
    on_scan: Callable[[str], object] | None = None,
) -> LocalizationRun:
    """Track the selected scans of ``source`` through ``pmap``: the odometry's steps, and each
    prepared scan with its odometry pose ``T_odom_scan`` given to a
    :class:`~kentreg_ros.core.Localizer` (searching, then tracking; see its module).

    A scan the odometry rejected (an unusable cloud) keeps the localizer's state and no pose.
    The scan's prepared points are those deskewed with the predicted motion (the odometry
    deskews once more after its registration; a few centimetres at most at walking speed).

    Parameters
    ----------
    source, pmap, config, start, max_scans, stride :
        As :func:`localize_each`.
    on_scan : callable, optional
        Called with each scan's status after it ran (a progress bar).

    Returns
    -------
    LocalizationRun
        With :attr:`LocalizationRun.odometry` the odometry's run.
    """
    cfg = config or KentRegConfig()
    preparer = _KeepingPreparer()
    odometry = Odometry(cfg, preparer=preparer)
    localizer = Localizer(pmap, cfg)
    outcomes: list[tuple[str, FloatArray | None, float, str, float, bool]] = []

    def place(step: OdometryStep) -> None:
        prep = preparer.last
        t0 = time.perf_counter()
        if prep is None or prep.scan is None:
            why = f'Not placed: the odometry rejected the scan ({step.message})'
            outcomes.append((localizer.state, None, float('nan'), why, 0.0, False))
        else:
            track = localizer.update(prep.scan, step.T_world_lidar)
            best = track.result.best
            fit = best.fit if best is not None else float('nan')
            ms = (time.perf_counter() - t0) * 1e3
            outcomes.append(
                (track.state, track.T_map_scan, fit, track.message, ms, track.searched)
            )
        if on_scan is not None:
            on_scan(outcomes[-1][0])

    odo = run_odometry(
        source, odometry, start=start, max_scans=max_scans, stride=stride, on_step=place
    )
    run = LocalizationRun(
        RunMode.TRACK, interrupted=odo.interrupted, error=odo.error, n_skipped=odo.n_skipped,
        skipped=list(odo.skipped), odometry=odo,
    )  # fmt: skip
    for index, step, outcome in zip(odo.input_indices, odo.steps, outcomes, strict=False):
        run.scans.append(LocalizedScan(index, step.stamp_ns, *outcome))
    return run


# --------------------------------------------------------------------------------------------
# Scoring against a reference


def reference_frame_note(map_trajectory: Trajectory | None, reference: GroundTruth) -> str:
    """'' when the map's frame is the reference's, else why the localized poses cannot be
    compared with the reference.

    The frames are one when the map was built at the reference poses: its trajectory (the poses
    it was recorded from) is at the reference poses of the same stamps (within
    :data:`FRAME_TOLERANCE_M` and :data:`FRAME_TOLERANCE_DEG`). A map built from odometry poses
    has the odometry's frame, which another recording's reference does not share.
    """
    if map_trajectory is None:
        return 'no trajectory beside the map tells its frame'
    if map_trajectory.stamps_ns is None or reference.trajectory.stamps_ns is None:
        return "the map's trajectory or the reference has no stamps to pair their poses by"
    stamps = np.asarray(map_trajectory.stamps_ns, dtype=np.int64)
    rows, ref_rows = associate(stamps, list(range(len(stamps))), reference.trajectory)
    if len(rows) == 0:
        return "the map's trajectory shares no stamp with the reference"
    T_map = np.asarray(map_trajectory.T_world_sensor, dtype=np.float64)[rows]
    T_ref = np.asarray(reference.trajectory.T_world_sensor, dtype=np.float64)[ref_rows]
    e_R, e_t = pair_errors(T_map, T_ref)
    if e_t.max() > FRAME_TOLERANCE_M or e_R.max() > FRAME_TOLERANCE_DEG:
        return (
            f"the map's trajectory is not at the reference poses (up to {e_t.max():.2f} m and "
            f'{e_R.max():.1f} deg off): the map was not built from them'
        )
    return ''


@dataclass(frozen=True)
class LocalizationScore:
    """The localized poses of a run against reference poses in the map's frame.

    Attributes
    ----------
    n_scans : int
        Scans of the run.
    n_referenced : int
        Of them, those with a reference pose (associated by stamp).
    n_localized : int
        Scans with a reference pose that were given one.
    n_correct : int
        Of them, those within :data:`MAX_ROTATION_DEG` and :data:`MAX_TRANSLATION_M`.
    false_accepts : list of int
        Input indices of the localized scans beyond either bar.
    e_R_deg, e_t_m : list of float
        Errors of every localized scan with a reference pose, in run order.
    """

    n_scans: int
    n_referenced: int
    n_localized: int
    n_correct: int
    false_accepts: list[int]
    e_R_deg: list[float]
    e_t_m: list[float]

    def record(self) -> dict[str, Any]:
        """JSON-ready summary (shares of the scans with a reference pose)."""
        n = max(self.n_referenced, 1)
        return {
            'n_scans': self.n_scans,
            'n_referenced': self.n_referenced,
            'n_localized': self.n_localized,
            'localized_share': self.n_localized / n,
            'n_correct': self.n_correct,
            'correct_share': self.n_correct / n,
            'n_false_accepts': len(self.false_accepts),
            'false_accepts': self.false_accepts,
            'bars': {'rotation_deg': MAX_ROTATION_DEG, 'translation_m': MAX_TRANSLATION_M},
            'e_R_deg_median': float(np.median(self.e_R_deg)) if self.e_R_deg else None,
            'e_t_m_median': float(np.median(self.e_t_m)) if self.e_t_m else None,
        }


def score_localization(scans: list[LocalizedScan], reference: GroundTruth) -> LocalizationScore:
    """Compare the localized poses of ``scans`` with ``reference`` (the same frame: see
    :func:`reference_frame_note`); the reference pose of a scan is the one nearest its stamp
    (:func:`~kentreg_ros.eval.groundtruth.associate`)."""
    stamps = np.array([s.stamp_ns for s in scans], dtype=np.int64)
    rows, ref_rows = associate(stamps, [s.index for s in scans], reference.trajectory)
    T_ref = np.asarray(reference.trajectory.T_world_sensor, dtype=np.float64)
    e_R: list[float] = []
    e_t: list[float] = []
    wrong: list[int] = []
    for row, ref_row in zip(rows, ref_rows, strict=True):
        scan = scans[row]
        if scan.T_map_scan is None:
            continue
        er, et = pair_errors(scan.T_map_scan[None], T_ref[ref_row][None])
        e_R.append(float(er[0]))
        e_t.append(float(et[0]))
        if e_R[-1] > MAX_ROTATION_DEG or e_t[-1] > MAX_TRANSLATION_M:
            wrong.append(scan.index)
    return LocalizationScore(
        len(scans), len(rows), len(e_R), len(e_R) - len(wrong), wrong, e_R, e_t
    )
