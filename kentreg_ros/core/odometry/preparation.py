"""The prepare stage as one value: :func:`prepare_input` runs
:func:`~kentreg_ros.core.odometry.stages.read_sweep` and
:func:`~kentreg_ros.core.odometry.stages.prepare` and returns a :class:`Preparation` (the scan,
or why it was rejected, with the inputs it was made with), so the stage can run in another
process (:mod:`kentreg_ros.core.odometry.pipeline`) with the same result."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.errors import InvalidPointCloudError
from kentreg_ros.core.odometry.deskew import PointTimes
from kentreg_ros.core.odometry.stages import Sweep, prepare, read_sweep
from kentreg_ros.core.scan import PreparedScan
from kentreg_ros.core.scan.prepared import elapsed_ms

FloatArray = NDArray[np.float64]


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
        Milliseconds the stage took.
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


def prepare_input(
    points: ArrayLike,
    point_times: ArrayLike | PointTimes | None,
    stamp: int,
    config: KentRegConfig,
    twist: FloatArray,
    voxel_size_hint: float,
) -> Preparation:
    """The prepare stage: :func:`read_sweep`, then :func:`prepare` with ``twist`` (used only
    when the sweep has times) and ``voxel_size_hint``. A pure function of its inputs, so the
    stage can run in another process with the same result; an unusable cloud is a
    :class:`Preparation` with ``rejected`` set, not an exception."""
    t0 = time.perf_counter()
    try:
        sweep = read_sweep(points, point_times, stamp, config)
    except InvalidPointCloudError as exc:
        return Preparation(None, None, str(exc), elapsed_ms(t0), None, voxel_size_hint)
    return prepare_sweep(sweep, twist, config, voxel_size_hint, t0=t0)


def prepare_sweep(
    sweep: Sweep,
    twist: FloatArray,
    config: KentRegConfig,
    voxel_size_hint: float,
    *,
    t0: float | None = None,
) -> Preparation:
    """The second half of :func:`prepare_input`, on a sweep already read (``t0``: when the
    stage started, a ``time.perf_counter()`` reading; default now)."""
    start = time.perf_counter() if t0 is None else t0
    used = np.array(twist, dtype=np.float64) if sweep.times is not None else None
    try:
        scan = prepare(sweep, twist, config, voxel_size_hint)
    except InvalidPointCloudError as exc:
        return Preparation(sweep, None, str(exc), elapsed_ms(start), None, voxel_size_hint)
    return Preparation(sweep, scan, '', elapsed_ms(start), used, voxel_size_hint)
