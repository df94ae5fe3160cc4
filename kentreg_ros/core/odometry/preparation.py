"""The prepare stage as a strategy: the scan read as a sweep, deskewed with the predicted motion,
then cropped, downsampled, given normals and clusters, once.

:func:`prepare` is the stage: a pure function of the scan and of :class:`PrepareInputs` (the
configuration, the twist to deskew with and where the voxel-size search starts), returning a
:class:`Preparation` (the prepared scan, or why the cloud was rejected, with the inputs it was
made with). Being pure, it can run anywhere with the same result. :class:`Preparer` is where the
odometry has it run: :class:`InThreadPreparer` here (the default), or one outside the core that
prepares scans in a worker process ahead of their step (:mod:`kentreg_ros.runtime`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.errors import InvalidPointCloudError
from kentreg_ros.core.odometry.deskew import PointTimes, Sweep, prepare_sweep, read_sweep
from kentreg_ros.core.scan import PreparedScan

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class RawScan:
    """A scan as the odometry is given it.

    Attributes
    ----------
    points : array_like, shape (N, 3)
        Finite points in the sensor frame.
    point_times : array_like, shape (N,), or PointTimes or None
        The driver's per-point times (see :func:`~.deskew.sweep_times`).
    stamp_ns : int
        Acquisition time, integer nanoseconds.
    """

    points: ArrayLike
    point_times: ArrayLike | PointTimes | None
    stamp_ns: int


@dataclass(frozen=True, eq=False)
class PrepareInputs:
    """What the loop gives the prepare stage besides the scan.

    Attributes
    ----------
    config : KentRegConfig
    twist : ndarray, shape (6,)
        The twist a sweep with per-point times is deskewed with: the last accepted motion's
        (zero before there is one).
    voxel_size_hint : float
        Where the voxel-size search starts: the last prepared scan's size (0: from the scan's
        own extent).
    """

    config: KentRegConfig
    twist: FloatArray
    voxel_size_hint: float


@dataclass(frozen=True, eq=False)
class Preparation:
    """What the prepare stage hands the registration: the sweep and the prepared scan, or why
    the cloud was rejected.

    Attributes
    ----------
    sweep : Sweep or None
        The points and their times (None when the cloud was rejected before they were read).
    scan : PreparedScan or None
        None: rejected (``rejected`` says why).
    rejected : str
        The :class:`~kentreg_ros.core.errors.InvalidPointCloudError` message, '' when prepared.
    ms : float
        Milliseconds the stage took (wherever it ran).
    twist : ndarray, shape (6,), or None
        The twist the sweep was deskewed with (None: it has no times, the twist did not enter).
    voxel_size_hint : float
        Where the voxel-size search started.
    """

    sweep: Sweep | None
    scan: PreparedScan | None
    rejected: str = ''
    ms: float = 0.0
    twist: FloatArray | None = None
    voxel_size_hint: float = 0.0

    @property
    def timings(self) -> dict[str, float]:
        """Milliseconds of the preparation's parts (:attr:`PreparedScan.timings`, no total)."""
        if self.scan is None:
            return {}
        return {k: v for k, v in self.scan.timings.items() if k != 'total'}

    @property
    def timed_sweep(self) -> Sweep | None:
        """The sweep when it has per-point times (it is deskewed), else None."""
        return self.sweep if self.sweep is not None and self.sweep.times is not None else None

    def made_with(self, inputs: PrepareInputs) -> bool:
        """Whether this preparation is the one ``inputs`` give (the configuration aside: a
        cloud rejected before its sweep was read depends on neither the hint nor the twist)."""
        if self.sweep is None:
            return True
        if self.voxel_size_hint != inputs.voxel_size_hint:
            return False
        return self.twist is None or bool(np.array_equal(self.twist, inputs.twist))


def prepare(scan: RawScan, inputs: PrepareInputs) -> Preparation:
    """The prepare stage: :func:`~.deskew.read_sweep`, then :func:`~.deskew.prepare_sweep` with
    the inputs' twist (used only when the sweep has times) and voxel-size hint. An unusable
    cloud is a :class:`Preparation` with ``rejected`` set, not an exception."""
    t0 = time.perf_counter()
    try:
        sweep = read_sweep(scan.points, scan.point_times, scan.stamp_ns, inputs.config)
    except InvalidPointCloudError as exc:
        ms = (time.perf_counter() - t0) * 1e3
        return Preparation(None, None, str(exc), ms, None, inputs.voxel_size_hint)
    return prepare_swept(sweep, inputs, t0=t0)


def prepare_swept(sweep: Sweep, inputs: PrepareInputs, *, t0: float | None = None) -> Preparation:
    """The second half of :func:`prepare`, on a sweep already read (``t0``: when the stage
    started, a ``time.perf_counter()`` reading; default now)."""
    start = time.perf_counter() if t0 is None else t0
    hint = inputs.voxel_size_hint
    used = np.array(inputs.twist, dtype=np.float64) if sweep.times is not None else None
    try:
        prepared = prepare_sweep(sweep, inputs.twist, inputs.config, hint)
    except InvalidPointCloudError as exc:
        ms = (time.perf_counter() - start) * 1e3
        return Preparation(sweep, None, str(exc), ms, None, hint)
    return Preparation(sweep, prepared, '', (time.perf_counter() - start) * 1e3, used, hint)


class Preparer(Protocol):
    """Where the odometry's prepare stage runs.

    :meth:`prepare` returns the :func:`prepare` of ``scan`` with ``inputs``, exactly (a
    preparer that prepared the scan ahead with other inputs prepares it again). :meth:`expect`
    says, as soon as they are known, the inputs the next scan will be prepared with, for a
    preparer that works ahead; the odometry calls it after each step, a reset and a new
    configuration.
    """

    def prepare(self, scan: RawScan, inputs: PrepareInputs) -> Preparation:
        """The scan prepared with ``inputs``."""

    def expect(self, inputs: PrepareInputs) -> None:
        """The inputs the next scan will be prepared with."""


class InThreadPreparer:
    """The prepare stage in the caller's thread, when the step asks for it (the default)."""

    #: The stage itself: in the caller's thread there is nothing to hand over or take back,
    #: so nothing to wrap around :func:`prepare`.
    prepare = staticmethod(prepare)

    def expect(self, inputs: PrepareInputs) -> None:
        """Nothing: this preparer does not work ahead."""
