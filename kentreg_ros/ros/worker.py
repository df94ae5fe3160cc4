"""The node's worker: one thread that takes the scans from a bounded queue, steps the odometry and
publishes what it found.

The subscription callback (:mod:`kentreg_ros.ros.node`) only decodes a cloud and hands it to
:meth:`ScanWorker.put`; when the queue is full the oldest scan is dropped ("latest wins"), so the
odometry never lags the sensor, and every drop is counted. With ``pipeline: process`` the scan is
also given at once to the preparer that works ahead (:class:`~kentreg_ros.runtime.ScanPreparer`:
a worker process prepares it while this thread registers the scan before); with ``pipeline:
sequential`` there is none, and the odometry prepares each scan in this thread. Parameter
changes and resets reach the thread as pending values, applied between scans. With a
``map_file`` each step is handed on to the localization's own thread after its outputs, and
``map -> odom`` goes out with it (:class:`~kentreg_ros.ros.localization.LocalizationWorker`):
this thread never waits for a search.

A scan that does not continue the trajectory is the odometry's to tell
(:class:`~kentreg_ros.core.ScanOrderError`): a repeated stamp is dropped and counted; an earlier
stamp (a bag played again, a sensor restarted) or another sensor frame restarts the trajectory
with a warning instead of corrupting it.

An unexpected error while the thread handles a scan (a bug: any exception but the odometry's
ordinary healths) skips that scan, counts it and logs its traceback once per kind of error; the
trajectory goes on, and restarts only after :data:`MAX_ERRORS_IN_A_ROW` errors in a row.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from kentreg_ros.core import KentRegConfig, Odometry, OutOfOrder, PointTimes, ScanOrderError
from kentreg_ros.io.params import NodeSettings
from kentreg_ros.ros.diagnostics import Counters, Snapshot
from kentreg_ros.ros.frames import Frames, moving_frame
from kentreg_ros.ros.localization import LocalizationWorker
from kentreg_ros.ros.logbridge import UnexpectedErrors
from kentreg_ros.ros.outputs import Outputs
from kentreg_ros.runtime import ScanPreparer, close_after

#: Poses the odometry keeps (the prediction needs two); the path keeps its own bounded history.
ODOMETRY_HISTORY = 4
#: Seconds between repeated warnings of the same kind (malformed input, drops, the core's).
THROTTLE_S = 5.0
#: Unexpected worker errors in a row after which the trajectory restarts. One error costs one
#: scan (skipped; the pose goes on from the scans before, and odom must not jump, REP-105). But
#: errors that keep coming on scan after scan point at the odometry's own state (a model or a
#: velocity left broken), which only a restart clears; three in a row tells that apart from
#: two unrelated odd scans, and costs a 10 Hz sensor 0.3 s of odometry.
MAX_ERRORS_IN_A_ROW = 3


@dataclass
class QueuedScan:
    """A decoded cloud waiting for the worker."""

    points: np.ndarray
    stamp_ns: int
    frame_id: str
    received: float  # time.monotonic()
    point_times: PointTimes | None = None  # the driver's per-point times, for deskewing


class ScanWorker:
    """The queue of scans and the thread that steps the odometry and publishes.

    Parameters
    ----------
    odometry : Odometry
        The odometry this thread steps (with at least :data:`ODOMETRY_HISTORY` poses kept).
    ahead : ScanPreparer or None
        The preparer the odometry was given when it prepares the scans ahead in a worker
        process: each scan is handed to it on arrival, and it is closed when this worker
        stops. None when the odometry prepares each scan in this thread.
    settings : NodeSettings
        The node's settings at start-up; :meth:`change` replaces them.
    counters : Counters
        The node's counters (shared with its callbacks and diagnostics).
    frames, outputs : Frames, Outputs
        The mount lookup and the publishers.
    log : rclpy logger
        The node's logger.
    running : callable
        Whether the node's ROS context is still up (an exception after it went down is the
        node ending, not an error).
    localization : LocalizationWorker, optional
        With a ``map_file``: takes each step after its outputs (and sends ``map -> odom``
        with it) and hears of every restart of the trajectory.
    """

    def __init__(
        self,
        odometry: Odometry,
        ahead: ScanPreparer | None,
        settings: NodeSettings,
        counters: Counters,
        frames: Frames,
        outputs: Outputs,
        log: Any,
        running: Callable[[], bool],
        localization: LocalizationWorker | None = None,
    ) -> None:
        self._counters, self._frames, self._outputs = counters, frames, outputs
        self._localization = localization
        self._log, self._running = log, running
        self._lock = threading.Condition()
        self._queue: collections.deque[QueuedScan] = collections.deque()
        self._settings = settings
        self._pending_config: KentRegConfig | None = None
        self._pending_reset = False
        self._stop = False
        #: The model the odometry registers against (changed by this thread, under the lock,
        #: when it adopts a pending configuration).
        self._model_in_use = odometry.config.odometry.model
        self.odometry, self.ahead = odometry, ahead
        # Only this thread reads or writes these (the diagnostics read the last four under the
        # lock).
        self._last_stepped_ns: int | None = None  # of the last scan the odometry stepped
        self._errors_in_a_row = 0
        self._errors = UnexpectedErrors(log, THROTTLE_S)
        self._frame_id = ''
        self._last_health, self._last_message = '', ''
        self._latencies_ms: collections.deque[float] = collections.deque(maxlen=1000)
        self._steps_ms: collections.deque[float] = collections.deque(maxlen=1000)
        self._thread = threading.Thread(target=self._run, name='kentreg_worker', daemon=True)

    # ----------------------------------------------------------------------------------------
    # From the node (executor thread)

    def start(self) -> int | None:
        """Start the thread; its id."""
        self._thread.start()
        return self._thread.ident

    @property
    def settings(self) -> NodeSettings:
        """The node settings in use."""
        with self._lock:
            return self._settings

    def put(self, scan: QueuedScan) -> None:
        """Queue a scan (the oldest dropped when the queue is full) and hand it to the
        preparer that works ahead, if any."""
        if self.ahead is not None:
            self.ahead.prefetch(scan.points, scan.stamp_ns, point_times=scan.point_times)
        with self._lock:
            if len(self._queue) >= self._settings.queue_size:
                self._counters.add('dropped_queue')  # the oldest: latest wins
                self._take_back(self._queue.popleft())
            self._queue.append(scan)
            self._lock.notify()

    def change(self, config: KentRegConfig | None, settings: NodeSettings | None) -> None:
        """Use ``config`` from the next scan on, and ``settings`` now (None: unchanged). A new
        mount or pair of frames restarts the trajectory; a shorter queue drops its oldest."""
        with self._lock:
            if config is not None:
                self._pending_config = config
            if settings is None:
                return
            old, self._settings = self._settings, settings
            if settings.base_to_lidar != old.base_to_lidar or (
                settings.odom_frame,
                settings.base_frame,
            ) != (old.odom_frame, old.base_frame):
                self._pending_reset = True  # the published frame changed
            while len(self._queue) > settings.queue_size:
                self._take_back(self._queue.popleft())
                self._counters.add('dropped_queue')

    def _take_back(self, scan: QueuedScan) -> None:
        """A scan that will not be stepped: the preparer working ahead forgets it."""
        if self.ahead is not None:
            self.ahead.discard(scan.points)

    def request_reset(self) -> None:
        """Restart the trajectory at the next scan."""
        with self._lock:
            self._pending_reset = True
            self._lock.notify()

    def snapshot(self, published: int, processed: int) -> Snapshot:
        """What the diagnostics report of this worker (the last ``published`` latencies and
        ``processed`` step times)."""
        with self._lock:
            pending = self._pending_config
            return Snapshot(
                queued=len(self._queue),
                model=str(self._model_in_use),
                pending_model=str(pending.odometry.model) if pending is not None else '',
                latencies_ms=list(self._latencies_ms)[-max(published, 1) :],
                steps_ms=list(self._steps_ms)[-max(processed, 1) :],
                frame_id=self._frame_id,
                last_health=str(self._last_health),
                last_message=self._last_message,
            )

    def stop(self, timeout: float) -> bool:
        """Stop the thread (it finishes the scan in hand) and then the preparer working ahead;
        True when the thread stopped within ``timeout`` s (else the preparer stops right after
        it)."""
        with self._lock:
            self._stop = True
            self._lock.notify_all()
        self._thread.join(timeout=timeout)
        if self.ahead is not None:
            close_after(self.ahead, self._thread)
        return not self._thread.is_alive()

    def is_alive(self) -> bool:
        return self._thread.is_alive()

    def join(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)

    # ----------------------------------------------------------------------------------------
    # The thread

    def _run(self) -> None:
        while True:
            with self._lock:
                while not self._queue and not self._stop:
                    self._lock.wait(timeout=0.5)
                if self._stop:
                    return
                scan = self._queue.popleft()
                config, self._pending_config = self._pending_config, None
                reset, self._pending_reset = self._pending_reset, False
                settings = self._settings
            try:
                if config is not None:
                    self.odometry.reconfigure(config)
                    with self._lock:
                        self._model_in_use = config.odometry.model
                if reset:
                    self.reset('reset requested')
                self.process(scan, settings)
            except Exception as exc:
                if not self._running():
                    # Ctrl-C (or an external shutdown) took the ROS context down under the scan
                    # in hand, so its outputs could not go out: the end of the node, not an
                    # error of the scan. Nothing more can be published; the worker stops.
                    return
                # Broad on purpose: an exception would end this thread silently, leaving a node
                # that still subscribes and reports but never publishes odometry again.
                self._on_error(exc, scan)
            else:
                self._errors_in_a_row = 0

    def process(self, scan: QueuedScan, settings: NodeSettings) -> None:
        """Step the odometry with ``scan`` and publish the step."""
        T_moving_lidar = self._frames.mount(scan.frame_id, settings, time.monotonic())
        if T_moving_lidar is None:
            self._counters.add('dropped_waiting_for_tf')
            return
        try:
            step = self.odometry.step(
                scan.points, scan.stamp_ns, frame_id=scan.frame_id, point_times=scan.point_times
            )
        except ScanOrderError as exc:
            if self._restarted_for(exc, scan):
                self.process(scan, settings)  # the first scan of the new trajectory
            return
        # The twist spans the odometry's own last step: after a scan skipped by an error the
        # scan before it, not the skipped one.
        prev_stamp, self._last_stepped_ns = self._last_stepped_ns, scan.stamp_ns
        self._counters.add('processed')
        self._counters.add(step.health)
        if step.searched:
            self._counters.add('searched')
        child = moving_frame(scan.frame_id, settings)
        self._outputs.publish(step, T_moving_lidar, prev_stamp, settings, child)
        if self._localization is not None:
            self._localization.after_step(step, T_moving_lidar, self._outputs.anchor, settings)
        self._counters.add('published')
        latency_ms = (time.monotonic() - scan.received) * 1e3
        with self._lock:  # read by the diagnostics timer on the executor thread
            self._frame_id = scan.frame_id
            self._last_health, self._last_message = step.health, step.message
            self._latencies_ms.append(latency_ms)
            self._steps_ms.append(step.timings.get('total', 0.0))

    def _restarted_for(self, exc: ScanOrderError, scan: QueuedScan) -> bool:
        """React to a scan the odometry refused: drop a repeated stamp (False), restart the
        trajectory for an earlier stamp or another frame (True)."""
        if exc.kind is OutOfOrder.REPEATED_STAMP:
            self._counters.add('dropped_duplicate_stamp')
            self._take_back(scan)
            self._log.warning(
                'Dropped a scan with the same stamp as the previous one.',
                throttle_duration_sec=THROTTLE_S,
            )
            return False
        if exc.kind is OutOfOrder.EARLIER_STAMP:
            self._log.warning(
                f'{exc} (Bag replayed? Sensor restarted?) Restarting the trajectory.'
            )
            self.reset('time went backwards')
        else:
            self._log.warning(f'{exc} Restarting the trajectory.')
            self.reset('sensor frame changed')
        return True

    def _on_error(self, exc: Exception, scan: QueuedScan) -> None:
        """Count an unexpected error, skip its scan and keep the trajectory (REP-105: ``odom``
        must not jump); log the traceback once per kind of error; restart the trajectory only
        after :data:`MAX_ERRORS_IN_A_ROW` in a row."""
        self._counters.add('errors')
        self._errors_in_a_row += 1
        self._errors.log(
            exc,
            f'Unexpected error on the scan stamped {scan.stamp_ns * 1e-9:.3f} s '
            f'({type(exc).__name__}: {exc}): the scan is skipped (diagnostics count it in '
            'errors), the trajectory goes on.',
        )
        if self._errors_in_a_row >= MAX_ERRORS_IN_A_ROW:
            self._log.error(
                f'{self._errors_in_a_row} unexpected errors in a row: the odometry state is '
                'taken to be broken, so the trajectory restarts (odom starts again at the '
                'identity).'
            )
            self._errors_in_a_row = 0
            self.reset(f'{MAX_ERRORS_IN_A_ROW} unexpected errors in a row')

    def reset(self, why: str) -> None:
        """Restart the trajectory (odometry, outputs, mount) and say why."""
        self.odometry.reset()
        self._outputs.reset()
        self._frames.reset()
        if self._localization is not None:
            self._localization.trajectory_restarted()  # the odometry frame starts again
        self._last_stepped_ns = None
        with self._lock:
            self._frame_id = ''
        self._counters.add('resets')
        self._log.info(f'Trajectory restarted ({why}).')
