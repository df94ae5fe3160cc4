"""How the node runs its odometry: one thread (``pipeline: sequential``) or two processes.

The node keeps its shape either way (:mod:`kentreg_ros.ros.node`): the subscription callback
decodes a cloud and queues it, one worker thread steps the odometry and publishes. With
``pipeline: process`` the odometry is a
:class:`~kentreg_ros.core.odometry.pipeline.PipelinedOdometry`: the callback also hands each
cloud to its worker process as it arrives (:func:`prefetch`), which prepares it while the
worker thread registers the scan before; a cloud the queue drops is taken back
(:func:`discard`); the worker process stops with the node (:func:`close_odometry`). The poses
are the sequential loop's.
"""

from __future__ import annotations

import threading
from typing import Any

from kentreg_ros.core import KentRegConfig, Odometry, PipelinedOdometry, PointTimes
from kentreg_ros.io.params import NodeSettings, PipelineMode


def create_odometry(config: KentRegConfig, settings: NodeSettings, max_history: int) -> Odometry:
    """The odometry the node's ``pipeline`` setting asks for."""
    if settings.pipeline == PipelineMode.PROCESS:
        return PipelinedOdometry(config, max_history=max_history)
    return Odometry(config, max_history=max_history)


def prefetch(
    odometry: Odometry, points: Any, stamp_ns: int, point_times: PointTimes | None
) -> None:
    """Hand a queued cloud to the preparing process now (nothing without a pipeline)."""
    if isinstance(odometry, PipelinedOdometry):
        odometry.prefetch(points, stamp_ns, point_times=point_times)


def discard(odometry: Odometry, points: Any) -> None:
    """A queued cloud was dropped: the preparing process need not prepare it."""
    if isinstance(odometry, PipelinedOdometry):
        odometry.discard(points)


def close_odometry(odometry: Odometry, worker: threading.Thread) -> None:
    """Stop the preparing process, if any, once the node's worker thread has stopped: now, or
    (when it still holds a scan past the node's stop timeout) right after it finishes it."""
    if not isinstance(odometry, PipelinedOdometry):
        return
    if not worker.is_alive():
        odometry.close()
        return

    def close_after() -> None:
        worker.join()
        odometry.close()

    threading.Thread(target=close_after, name='kentreg_pipeline_close', daemon=True).start()
