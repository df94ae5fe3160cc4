"""A measured run of the odometry over recorded scans: what ``kentreg_replay`` and the benchmarks
time and evaluate.

:func:`run_odometry` feeds the scans of a recording, in order and at CPU speed (none is dropped),
to the same :class:`~kentreg_ros.core.odometry.loop.Odometry` the ROS node runs, and records every
step with the time spent reading. The loop itself stays in the core (``Odometry.step``); this is
the harness around it that selects the scans, times them and keeps a partial run when the input
breaks or the user interrupts.
"""

from __future__ import annotations

import itertools
import logging
import time
from collections.abc import Callable, Generator, Iterator
from contextlib import closing
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core import KentRegError, Odometry, OdometryStep, ScanOrderError
from kentreg_ros.io.pointcloud2 import point_time_field
from kentreg_ros.io.runmap import DEFAULT_MAX_POINTS, RunMap
from kentreg_ros.io.sources import ScanSource, SkippedScan

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
#: Skipped (undecodable) scans a run names; beyond these it only counts them. Enough to show
#: whether the bad ones cluster (one stretch of a recording, every n-th message), few enough
#: for a summary to list.
MAX_SKIPPED_NAMED = 5


class ScanLike(Protocol):
    """One scan: what :func:`run_odometry` reads of a :class:`kentreg_ros.io.sources.Scan`."""

    @property
    def stamp_ns(self) -> int: ...

    @property
    def frame_id(self) -> str: ...

    @property
    def points(self) -> NDArray[np.floating]: ...


class ScanSequence(Protocol):
    """Scans in order with their count: a :class:`kentreg_ros.io.sources.ScanSource` or a list."""

    def __len__(self) -> int: ...

    def __iter__(self) -> Iterator[ScanLike]: ...


@dataclass
class OdometryRun:
    """What the odometry did with the scans of one input.

    Attributes
    ----------
    steps : list of OdometryStep
        One per processed scan, in order.
    input_indices : list of int
        The index in the input of each processed scan (``start + k * stride``).
    read_ms : list of float
        Milliseconds spent reading each processed scan (skipped scans included).
    elapsed_s : float
        Wall time of the whole run, reading included.
    interrupted : bool
        Ctrl-C ended the run early; ``steps`` holds the scans processed before it.
    error : str or None
        The first line of the read error that ended the run early (a damaged bag), or None.
    n_skipped : int
        Input scans that were selected but could not be decoded (a malformed PointCloud2, an
        unreadable scan file): skipped, as the ROS node skips them, and counted here.
    skipped : list of SkippedScan
        The first :data:`MAX_SKIPPED_NAMED` of them (input index, stamp, reason).
    map : RunMap or None
        With ``map_voxel_size``: the map of the run (:class:`~kentreg_ros.io.runmap.RunMap`,
        the one ``kentreg_node`` builds): the prepared points of every accepted scan (and the
        first) at its pose in the odometry frame, one per voxel.
    """

    steps: list[OdometryStep] = field(default_factory=list)
    input_indices: list[int] = field(default_factory=list)
    read_ms: list[float] = field(default_factory=list)
    elapsed_s: float = 0.0
    interrupted: bool = False
    error: str | None = None
    n_skipped: int = 0
    skipped: list[SkippedScan] = field(default_factory=list)
    map: RunMap | None = None

    @property
    def poses(self) -> FloatArray:
        """``T_world_lidar`` of every step, shape (N, 4, 4)."""
        if not self.steps:
            return np.zeros((0, 4, 4))
        return np.stack([s.T_world_lidar for s in self.steps])

    @property
    def stamps_ns(self) -> NDArray[np.int64]:
        """Stamps of the processed scans, shape (N,)."""
        return np.array([s.stamp_ns for s in self.steps], dtype=np.int64)


def run_odometry(
    source: ScanSequence,
    odometry: Odometry,
    *,
    start: int = 0,
    max_scans: int | None = None,
    stride: int = 1,
    on_step: Callable[[OdometryStep], object] | None = None,
    map_voxel_size: float = 0.0,
    map_max_points: int = DEFAULT_MAX_POINTS,
) -> OdometryRun:
    """Feed the scans ``start, start + stride, ...`` of ``source`` (at most ``max_scans``).

    The scans in between are read and skipped (a bag is sequential); the processed scans keep
    their own stamps, so the odometry sees ``stride`` times the gaps. ``max_scans`` counts
    processed scans, and :attr:`OdometryRun.input_indices` records which input scans they were.

    A selected scan that cannot be decoded (a malformed PointCloud2 in a bag, an unreadable scan
    file; :meth:`~kentreg_ros.io.sources.ScanSource.entries`) is skipped and counted in
    :attr:`OdometryRun.n_skipped`, the first few named in :attr:`OdometryRun.skipped`; the run
    goes on, as the ROS node does. A read error of the container itself (a damaged bag), or a
    scan the odometry refuses (:class:`~kentreg_ros.core.ScanOrderError`), ends the run early;
    the scans before it are kept and the error is recorded in :attr:`OdometryRun.error`. Ctrl-C
    does the same with :attr:`OdometryRun.interrupted`. A generator source is closed at the end
    (a bag is closed now, not at garbage collection).

    Parameters
    ----------
    source : ScanSequence
        The scans, e.g. :func:`kentreg_ros.io.open_scan_source` or a list of
        :class:`kentreg_ros.io.Scan`.
    odometry : Odometry
        The odometry to step (usually fresh).
    start : int
        Index of the first scan processed, ``0 <= start < len(source)``.
    max_scans : int, optional
        Most scans processed: the first ``max_scans`` selected input scans (skipped ones among
        them are not replaced).
    stride : int
        Process every ``stride``-th scan, ``>= 1``.
    on_step : callable, optional
        Called with each step after it ran (a progress bar).
    map_voxel_size : float
        When positive, accumulate the map of the run in :attr:`OdometryRun.map`: the prepared
        points (:attr:`OdometryStep.points`: downsampled, outlier-free, deskewed) of every scan
        whose pose was registered (and of the first), moved by that pose into the odometry
        frame, at most one per voxel of this edge (m); the node's map, built the same way (see
        :mod:`kentreg_ros.io.runmap` for why these points). Scans that fell back or were
        rejected stay out: their pose is only a prediction.
    map_max_points : int
        Points the map keeps at most; beyond them its voxel edge doubles.

    Returns
    -------
    OdometryRun

    Raises
    ------
    ValueError
        ``start`` beyond the input, or ``stride`` not a positive integer.
    """
    indices = selected_indices(len(source), start, max_scans, stride)
    run = OdometryRun()
    if map_voxel_size > 0.0:
        run.map = RunMap(map_voxel_size, max_points=map_max_points)
    t_run = time.perf_counter()
    with closing(read_selected(source, indices, run)) as scans:
        try:
            for index, scan, read_ms in scans:
                run.read_ms.append(read_ms)
                if not _step(odometry, scan, index, run, on_step):
                    break  # the odometry refused the scan: the run's error says why
        except KeyboardInterrupt:
            run.interrupted = True
    run.elapsed_s = time.perf_counter() - t_run
    return run


class ReadLog(Protocol):
    """Where :func:`read_selected` counts what it could not give (an :class:`OdometryRun`, or
    a localization run)."""

    error: str | None
    n_skipped: int
    skipped: list[SkippedScan]


def read_selected(
    source: ScanSequence, indices: range, log: ReadLog
) -> Generator[tuple[int, ScanLike, float], None, None]:
    """The scans at ``indices`` (:func:`selected_indices`) with their input index and the
    milliseconds their reading took. An undecodable scan is skipped and counted in ``log``; a
    read error of the container ends the iteration with the first line of its message in
    ``log.error``. Closing the generator closes the source's reader."""
    reader: Iterator[ScanLike | SkippedScan] = (
        source.entries() if isinstance(source, ScanSource) else iter(source)
    )
    scans = itertools.islice(reader, indices.start, indices.stop, indices.step)
    try:
        for index in indices:
            t0 = time.perf_counter()
            try:
                scan = next(scans)
            except StopIteration:
                return
            except KentRegError as exc:
                text = str(exc).strip()
                log.error = text.splitlines()[0] if text else type(exc).__name__
                return
            if isinstance(scan, SkippedScan):
                log.n_skipped += 1
                if len(log.skipped) < MAX_SKIPPED_NAMED:
                    log.skipped.append(scan)
                logger.info('Scan %d skipped: %s', index, scan.reason)
                continue
            yield index, scan, (time.perf_counter() - t0) * 1e3
    finally:
        if isinstance(reader, Generator):
            reader.close()


def _step(
    odometry: Odometry,
    scan: ScanLike,
    index: int,
    run: OdometryRun,
    on_step: Callable[[OdometryStep], object] | None,
) -> bool:
    """One scan through the odometry, recorded in ``run`` (and its map) and given to
    ``on_step``; False when the odometry refused it (its stamp or frame does not continue the
    trajectory), which is then the run's error."""
    try:
        step = odometry.step(
            scan.points,
            scan.stamp_ns,
            frame_id=scan.frame_id,
            point_times=point_time_field(getattr(scan, 'extras', None)),
        )
    except ScanOrderError as exc:
        run.error = f'scan {index}: {exc}'
        return False
    run.steps.append(step)
    run.input_indices.append(index)
    if run.map is not None and step.ok and step.points is not None:
        run.map.add(step.points, step.T_world_lidar)
    logger.debug(
        'Scan %d: %s in %.0f ms (%s)', index, step.health, step.timings['total'], step.message
    )
    if on_step is not None:
        on_step(step)
    return True


def selected_indices(n_total: int, start: int, max_scans: int | None, stride: int) -> range:
    """The input indices a run takes: ``start, start + stride, ...``, at most ``max_scans``.

    Raises
    ------
    ValueError
        ``start`` beyond the input, or ``stride`` not a positive integer.
    """
    if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
        raise ValueError(f'stride: expected a positive integer (>= 1), got {stride!r}')
    if start >= n_total:
        raise ValueError(f'start {start}: the input has only {n_total} scans')
    indices = range(start, n_total, stride)
    return indices[:max_scans] if max_scans is not None else indices
