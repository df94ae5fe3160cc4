"""How a caller that receives scans one at a time (the node) has them prepared: in the odometry's
thread (``pipeline: sequential``) or ahead in a worker process (``pipeline: process``).

Either is a :class:`ScanPreparer`: a :class:`~kentreg_ros.core.Preparer` the caller gives the
odometry, which also takes each scan as it arrives (:meth:`ScanPreparer.prefetch`), takes back
one the caller dropped (:meth:`ScanPreparer.discard`) and stops with the caller
(:meth:`ScanPreparer.close`; :func:`close_after` once the caller's worker thread is done). The
poses are the same either way.
"""

from __future__ import annotations

import threading
from typing import Protocol

from numpy.typing import ArrayLike

from kentreg_ros.core import (
    InThreadPreparer,
    PointTimes,
    Preparation,
    PrepareInputs,
    Preparer,
    RawScan,
)
from kentreg_ros.runtime.preparer import ProcessPreparer


class ScanPreparer(Preparer, Protocol):
    """A preparer fed with scans as they arrive."""

    def prefetch(
        self,
        points: ArrayLike,
        stamp_ns: int,
        *,
        point_times: ArrayLike | PointTimes | None = None,
    ) -> None:
        """A scan arrived; the odometry will step with the same ``points`` object."""

    def discard(self, points: ArrayLike) -> None:
        """A scan handed to :meth:`prefetch` will not be stepped."""

    def close(self) -> None:
        """Stop (idempotent)."""


class SequentialPreparer:
    """Each scan prepared in the odometry's thread when its step asks for it; the scans handed
    over on arrival are not looked at before."""

    def __init__(self) -> None:
        self._here = InThreadPreparer()

    def prepare(self, scan: RawScan, inputs: PrepareInputs) -> Preparation:
        return self._here.prepare(scan, inputs)

    def expect(self, inputs: PrepareInputs) -> None:
        """Nothing: this preparer does not work ahead."""

    def prefetch(
        self,
        points: ArrayLike,
        stamp_ns: int,
        *,
        point_times: ArrayLike | PointTimes | None = None,
    ) -> None:
        """Nothing: the scan is prepared when it is stepped."""

    def discard(self, points: ArrayLike) -> None:
        """Nothing to take back."""

    def close(self) -> None:
        """Nothing to stop."""


def create_preparer(*, process: bool) -> ScanPreparer:
    """A :class:`ProcessPreparer` (its worker started now) or a :class:`SequentialPreparer`."""
    return ProcessPreparer() if process else SequentialPreparer()


def close_after(preparer: ScanPreparer, worker: threading.Thread) -> None:
    """Close ``preparer`` once the caller's ``worker`` thread has stopped: now, or (when it
    still holds a scan past the caller's stop timeout) right after it finishes it."""
    if not worker.is_alive():
        preparer.close()
        return

    def close_when_done() -> None:
        worker.join()
        preparer.close()

    threading.Thread(target=close_when_done, name='kentreg_preparer_close', daemon=True).start()
