"""What a caller that receives scans one at a time (the node) needs of a preparer that works
ahead of the steps (``pipeline: process``): :class:`ScanPreparer`, and :func:`close_after`.

With ``pipeline: sequential`` the caller gives the odometry no preparer (it prepares each scan
in its own thread, :class:`~kentreg_ros.core.InThreadPreparer`) and has nothing to hand scans
to on arrival, to take back or to stop. With ``pipeline: process`` it gives the odometry a
:class:`~kentreg_ros.runtime.ProcessPreparer`, a :class:`ScanPreparer`: it also takes each scan
as it arrives (:meth:`ScanPreparer.prefetch`), takes back one the caller dropped
(:meth:`ScanPreparer.discard`) and stops with the caller (:meth:`ScanPreparer.close`;
:func:`close_after` once the caller's worker thread is done). The poses are the same either
way.
"""

from __future__ import annotations

import threading
from typing import Protocol

from numpy.typing import ArrayLike

from kentreg_ros.core import PointTimes, Preparer


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
