"""The odometry on two cores: scans prepared in a worker process while the loop registers.

:class:`PipelinedOdometry` is :class:`~kentreg_ros.core.odometry.loop.Odometry` with its
prepare stage (:func:`~kentreg_ros.core.odometry.stages.prepare_input`: time interpretation,
deskew, crop, voxels, normals, clusters) moved into one worker process, and the model's upkeep
(the local map's insertion and target) deferred past the step's pose, to run while the worker
prepares the next scan:

============================= ================================ =============================
main process                  worker process                   note
============================= ================================ =============================
:meth:`prefetch` (scan k+1)   prepare k+1 (no per-point times)  on arrival
register k, return its pose
``go`` k+1 (twist, hint)      prepare k+1 (per-point times)     deskewing needs k's motion
move the model with k                                           overlaps the worker
register k+1 ...
============================= ================================ =============================

Why a process: the stages are numpy calls on arrays of a few thousand points with Python
between them, which hold the GIL; a thread pipeline measured 0.98-1.13x, a worker process
1.28-1.52x (the stage times are in ``benchmarks/live.py``).

Why the local map's upkeep stays in the main process: it lies between the pose of scan k and
the registration of scan k+1 wherever it runs, so moving it only moves work between the
processes. Measured (2026-12-02, 50 KITTI frames, local map, the two builds alternated): with
the map kept by the worker (its copy updated by the same function, the target sent back
without its index; poses and map bit-identical, a killed worker's map rebuilt from its last
copy), the main process spent 18 ms less CPU per scan and the worker 26 ms more (the hand-over
of scans and targets), fed at once no faster (139-153 against 129-143 ms a scan), and fed live
at 10 Hz it dropped 14-16 scans of 50 against 11-12. Building the map's index in a thread
beside its clustering (small_gicp releases the GIL) changed nothing measurable either: the
second core is the worker's. What bounds a step is the work itself (see ``benchmarks/live.py``).

Exactness: the prepare stage is a pure function of (points, times, stamp, configuration,
twist, voxel-size hint). The twist and hint the sequential loop would use are known only once
the previous scan is prepared (hint) or registered (twist), so the worker uses the hint it last
produced, or one the main process sends when it knows it, and waits for the twist of a sweep
with per-point times. Every result carries the inputs it was prepared with; the main process
checks them against the sequential loop's and prepares the scan itself when they differ (after
a reset, a reconfiguration or a dropped scan). The poses are therefore those of the sequential
loop, bit for bit (``test/test_pipeline.py``).

Failures: an exception in the worker while preparing a scan (a bug; an unusable cloud is the
ordinary ``rejected`` health) is raised from :meth:`PipelinedOdometry.step` as
:class:`PipelineError`, as the sequential loop would raise it. A worker that dies is reported
once per death (``logging``), counted in :attr:`PipelinedOdometry.n_worker_restarts`, and
replaced; the scans it held are prepared in the main process, so none is lost. The worker exits
when its parent closes the pipe, exits or dies (it checks its parent every
:data:`PARENT_CHECK_S`), so it is never left behind; :meth:`PipelinedOdometry.close` stops it.
"""

from __future__ import annotations

import fcntl
import itertools
import logging
import multiprocessing as mp
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.errors import KentRegError
from kentreg_ros.core.odometry.deskew import PointTimes
from kentreg_ros.core.odometry.handover import PARENT_CHECK_S, write_scan_file
from kentreg_ros.core.odometry.loop import Odometry
from kentreg_ros.core.odometry.preparation import Preparation
from kentreg_ros.core.odometry.step import OdometryStep
from kentreg_ros.core.scan.prepared import elapsed_ms

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: The worker's module, run as ``python -m``.
WORKER_MODULE = 'kentreg_ros.core.odometry.prepworker'
#: Seconds :meth:`PipelinedOdometry.close` waits for the worker to stop before terminating it.
STOP_TIMEOUT_S = 2.0
#: Scans prefetched and not yet stepped beyond which the oldest is discarded: the node keeps
#: a bounded queue, and a caller that prefetches without stepping must not fill the worker.
MAX_OPEN_JOBS = 8


class PipelineError(KentRegError, RuntimeError):
    """The worker process failed on a scan (its traceback is in the message)."""


#: The worker's native libraries on one thread each: it is one of the two processes the
#: pipeline spreads over two cores, and BLAS threads spinning beside the main process's work
#: would take the core it registers on.
ONE_THREAD_ENV = {'OMP_NUM_THREADS': '1', 'OPENBLAS_NUM_THREADS': '1', 'MKL_NUM_THREADS': '1'}
#: Where scans are handed to the worker: memory (tmpfs) where the system has it.
SCAN_DIR = '/dev/shm' if os.path.isdir('/dev/shm') else tempfile.gettempdir()


def _unlink(path: str) -> None:
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass


def _widen_pipe(fd: int) -> None:
    """Give the results pipe 1 MB (Linux; 64 kB by default), so a prepared scan (~0.5 MB)
    goes in one write and the main process reads it in one piece."""
    try:
        fcntl.fcntl(fd, fcntl.F_SETPIPE_SZ, 1 << 20)
    except (AttributeError, OSError):  # not Linux, or above /proc/sys/fs/pipe-max-size
        pass


def _package_path() -> str:
    """PYTHONPATH for the worker: the directory this package is imported from first, so the
    worker runs the same code as its parent (a source tree, not another installed copy)."""
    root = str(Path(__file__).resolve().parents[3])
    rest = os.environ.get('PYTHONPATH', '')
    return root if not rest else f'{root}{os.pathsep}{rest}'


# ------------------------------------------------------------------------------------------------
# The main process


@dataclass
class _Open:
    """A scan handed to the worker and not yet stepped."""

    id: int
    points: Any  # the caller's array: identifies the scan when it is stepped
    stamp: int
    worker: int  # the worker (by number) that holds it
    path: str = ''  # the file handing the scan over (the worker removes it when it reads it)
    went: bool = False  # the worker was told the loop's inputs for it


@dataclass
class PipelineStats:
    """What the pipeline did (for diagnostics and benchmarks)."""

    prepared_remote: int = 0
    prepared_here: int = 0
    redone: int = 0  # prepared by the worker with other inputs than the loop's, then here
    worker_restarts: int = 0
    wait_ms: deque[float] = field(default_factory=lambda: deque(maxlen=1000))


class PipelinedOdometry(Odometry):
    """:class:`~kentreg_ros.core.odometry.loop.Odometry` with the prepare stage in a worker
    process and the model's upkeep after the pose (see the module docstring).

    Same parameters, results and poses as :class:`Odometry`. Call :meth:`prefetch` with a scan
    as soon as it arrives (before the steps of the scans before it have finished) for the
    worker to prepare it meanwhile; :meth:`step` then takes it by identity of ``points``. A
    scan stepped without a prefetch is handed to the worker then (no overlap but the model's
    upkeep). Prefetched scans that are never stepped (dropped by the caller) are discarded
    when a later scan is stepped, or by :meth:`discard`. Call :meth:`close` (or use the
    instance as a context manager) to stop the worker.

    :meth:`prefetch` and :meth:`discard` may be called from another thread than
    :meth:`step`; everything else belongs to the thread that steps.
    """

    def __init__(
        self,
        config: KentRegConfig | None = None,
        *,
        initial_pose: ArrayLike | None = None,
        max_history: int | None = None,
    ) -> None:
        self._lock = threading.Lock()
        self._ids = itertools.count()
        self._open: deque[_Open] = deque()
        self._results: dict[int, tuple[str, int, Any]] = {}
        self._generation = 0
        self._stepping = False
        self._proc: Any = None
        self._requests: Connection | None = None
        self._replies: Connection | None = None
        self._n_workers = 0
        self._closed = False
        self._upkeep: threading.Thread | None = None
        self._upkeep_ms = 0.0
        self._upkeep_error: BaseException | None = None
        self.stats = PipelineStats()
        super().__init__(config, initial_pose=initial_pose, max_history=max_history)
        self._start_worker()

    # -- the worker's life ---------------------------------------------------------------------

    def _start_worker(self) -> None:
        # A fresh interpreter running this module (not a fork: rclpy runs threads, and a fork
        # of a threaded process can deadlock; not multiprocessing's spawn either, which runs
        # the caller's main script again in the child unless it is guarded).
        req_r, req_w = mp.Pipe(duplex=False)
        res_r, res_w = mp.Pipe(duplex=False)
        fds = (req_r.fileno(), res_w.fileno())
        _widen_pipe(res_w.fileno())
        proc = subprocess.Popen(
            [
                sys.executable,
                '-m',
                'kentreg_ros.core.odometry.prepworker',
                str(fds[0]),
                str(fds[1]),
                str(os.getpid()),
            ],
            pass_fds=fds,
            stdin=subprocess.DEVNULL,
            env={**os.environ, **ONE_THREAD_ENV, 'PYTHONPATH': _package_path()},
        )
        req_r.close()
        res_w.close()
        self._proc, self._requests, self._replies = proc, req_w, res_r
        self._n_workers += 1
        self._send(('config', self._generation, self.config))

    def _send(self, message: tuple[Any, ...]) -> bool:
        """Send to the worker (under the lock); False when the pipe is broken."""
        if self._requests is None:
            return False
        try:
            self._requests.send(message)
        except (OSError, ValueError):
            return False
        return True

    def _worker_died(self) -> None:
        """The worker is gone: report it, forget what it held, start another."""
        code = self._proc.poll() if self._proc is not None else None
        logger.error(
            'The scan preparation worker process died (exit code %s); starting another. The '
            'scans it held are prepared in the main process.',
            code,
        )
        self.stats.worker_restarts += 1
        with self._lock:
            self._stop_worker(wait=False)
            self._results.clear()
            for item in self._open:
                _unlink(item.path)
            if not self._closed:
                self._start_worker()

    def _stop_worker(self, *, wait: bool) -> None:
        proc, self._proc = self._proc, None
        if self._requests is not None:
            if wait:
                self._send(('stop',))
            self._requests.close()
        if self._replies is not None:
            self._replies.close()
        self._requests = self._replies = None
        if proc is None:
            return
        try:
            proc.wait(STOP_TIMEOUT_S if wait else 0.1)
        except subprocess.TimeoutExpired:
            proc.terminate()
            try:
                proc.wait(STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:  # pragma: no cover - a worker ignoring SIGTERM
                proc.kill()
                proc.wait()

    def close(self) -> None:
        """Stop the worker process (idempotent); the instance cannot step afterwards."""
        upkeep, self._upkeep = self._upkeep, None
        if upkeep is not None:
            upkeep.join()
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._stop_worker(wait=True)
            for item in self._open:
                _unlink(item.path)  # files the worker did not read
            self._open.clear()

    @property
    def worker_pid(self) -> int | None:
        """Process id of the worker (None once closed)."""
        return self._proc.pid if self._proc is not None else None

    @property
    def n_worker_restarts(self) -> int:
        """Times a dead worker was replaced."""
        return self.stats.worker_restarts

    def __enter__(self) -> PipelinedOdometry:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- scans in --------------------------------------------------------------------------------

    def prefetch(
        self,
        points: ArrayLike,
        stamp_ns: int,
        *,
        point_times: ArrayLike | PointTimes | None = None,
    ) -> None:
        """Hand a scan to the worker now; :meth:`step` with the same ``points`` object takes it.

        The arguments are those :meth:`step` will get. Nothing is checked here: whatever is
        wrong with the scan is reported by its step, as in the sequential loop.
        """
        item = self._submit(points, stamp_ns, point_times)
        if item is not None:
            with self._lock:
                self._open.append(item)

    def _submit(
        self, points: ArrayLike, stamp_ns: int, point_times: ArrayLike | PointTimes | None
    ) -> _Open | None:
        """Send a scan to the worker; its open job (None when closed or the pipe broke)."""
        pts = np.asarray(points)
        field_name = point_times.field if isinstance(point_times, PointTimes) else ''
        times = None if point_times is None else np.asarray(point_times)
        job = next(self._ids)
        path = os.path.join(SCAN_DIR, f'kentreg_scan_{os.getpid()}_{id(self)}_{job}.npy')
        try:
            write_scan_file(path, pts, times)
        except (OSError, ValueError) as exc:  # no room, or a dtype np.save refuses
            _unlink(path)
            logger.warning('Could not hand the scan to the worker (%s); preparing it here.', exc)
            return None
        with self._lock:
            if self._closed:
                _unlink(path)
                return None
            while len(self._open) >= MAX_OPEN_JOBS:
                self._drop(self._open.popleft().id)
            # The hint the loop will use is known when no earlier scan is still to be prepared.
            hint = None if (self._open or self._stepping) else self.voxel_size_hint
            message = ('job', job, path, times is not None, field_name, int(stamp_ns), hint)
            if not self._send(message):
                _unlink(path)
                return None
            return _Open(job, points, int(stamp_ns), self._n_workers, path)

    def discard(self, points: ArrayLike) -> None:
        """Forget a prefetched scan that will not be stepped (e.g. dropped from a queue)."""
        with self._lock:
            for item in self._open:
                if item.points is points:
                    self._open.remove(item)
                    self._drop(item.id)
                    return

    # -- the loop --------------------------------------------------------------------------------

    def step(
        self,
        points: ArrayLike,
        stamp_ns: int,
        *,
        frame_id: str | None = None,
        point_times: ArrayLike | PointTimes | None = None,
    ) -> OdometryStep:
        """:meth:`Odometry.step` with the preparation from the worker (see the class).

        Raises
        ------
        PipelineError
            The worker raised while preparing this scan (a bug, as the sequential loop would
            raise it); the step did not happen.
        """
        if self._closed:
            raise PipelineError('This PipelinedOdometry is closed.')
        stamp = self._checked_stamp(stamp_ns)
        with self._lock:
            self._stepping = True
        try:
            pending = self._begin(points, stamp, frame_id)
            item = self._take(points, point_times, stamp)
            if item is not None and not item.went:
                self._go(item)
            t0 = time.perf_counter()
            self.update_model()  # the last step's upkeep, if it is still running
            wait_ms, upkeep_ms = elapsed_ms(t0), self._upkeep_ms
            prep = self._receive(item, points, point_times, stamp)
            step = self._step(pending, prep, defer=True)
        finally:
            with self._lock:
                self._stepping = False
        with self._lock:  # the next scan's inputs are known now: its worker need not wait
            following = self._open[0] if self._open else None
        if following is not None and following.worker == self._n_workers:
            self._go(following)
        # The model moves on in a thread of this process while the caller publishes the pose
        # and the worker prepares the next scan; the next step (or anything that reads the
        # model) waits for it.
        self._upkeep = threading.Thread(target=self._run_upkeep, name='kentreg_upkeep')
        self._upkeep.start()
        step.timings['model_previous'] = upkeep_ms
        step.timings['model_wait'] = wait_ms
        return step

    def _run_upkeep(self) -> None:
        t0 = time.perf_counter()
        try:
            Odometry.update_model(self)
        except BaseException as exc:  # noqa: BLE001 - raised from the next update_model
            self._upkeep_error = exc
        self._upkeep_ms = elapsed_ms(t0)

    def update_model(self) -> None:
        """Wait for the last step's model upkeep (run in a thread after the step); an error it
        raised is raised here, so from the next step."""
        upkeep, self._upkeep = self._upkeep, None
        if upkeep is not None:
            upkeep.join()
        error, self._upkeep_error = self._upkeep_error, None
        if error is not None:
            raise error
        super().update_model()

    def _checked_stamp(self, stamp_ns: int) -> int:
        from kentreg_ros.core.odometry.loop import _as_stamp

        return _as_stamp(stamp_ns)

    def _take(
        self, points: ArrayLike, point_times: ArrayLike | PointTimes | None, stamp: int
    ) -> _Open | None:
        """The open job of ``points`` (earlier ones discarded), submitted now if there is none."""
        with self._lock:
            mine = next((o for o in self._open if o.points is points), None)
            if mine is not None:
                while self._open[0] is not mine:
                    self._drop(self._open.popleft().id)
                self._open.popleft()
                if mine.worker == self._n_workers:
                    return mine
        return self._submit(points, stamp, point_times)

    def _go(self, item: _Open) -> None:
        """Tell the worker the twist and hint of this scan (the loop's, now known)."""
        with self._lock:
            item.went = True
            self._send(('go', item.id, self.twist_for_next, self.voxel_size_hint))

    def _receive(
        self,
        item: _Open | None,
        points: ArrayLike,
        point_times: ArrayLike | PointTimes | None,
        stamp: int,
    ) -> Preparation:
        """The worker's preparation of ``item`` if it was made with the loop's inputs; else
        the scan prepared here."""
        t0 = time.perf_counter()
        reply = self._wait(item.id) if item is not None else None
        if reply is None and item is not None:
            _unlink(item.path)  # the worker died before it read the scan
        self.stats.wait_ms.append(elapsed_ms(t0))
        if reply is not None:
            kind, generation, payload = reply
            if kind == 'error':
                raise PipelineError(f'The scan preparation worker raised:\n{payload}')
            if generation == self._generation and self._same_inputs(payload):
                self.stats.prepared_remote += 1
                return payload
            self.stats.redone += 1
        self.stats.prepared_here += 1
        return self._prepare_here(points, point_times, stamp)

    def _same_inputs(self, prep: Preparation) -> bool:
        """Whether ``prep`` was made with the inputs the sequential loop uses now (a cloud
        rejected before its sweep was read depends on neither the hint nor the twist)."""
        if prep.sweep is None:
            return True
        if prep.voxel_size_hint != self.voxel_size_hint:
            return False
        return prep.twist is None or bool(np.array_equal(prep.twist, self.twist_for_next))

    def _drop(self, job: int) -> None:
        """Tell the worker to skip ``job`` and forget its reply if it came (under the lock)."""
        self._send(('discard', job))
        self._results.pop(job, None)

    def _keep(self, job: int, done: int, reply: tuple[str, int, Any]) -> None:
        """Keep the reply for ``done`` while waiting for ``job``: this job's, a later one's, or
        that of a scan still to be stepped although its job is older (a scan handed over again
        after its first job was discarded, by a caller more than :data:`MAX_OPEN_JOBS` behind;
        dropping that reply left the scan's step waiting forever). The others are replies for
        discarded jobs."""
        with self._lock:
            if done >= job or any(item.id == done for item in self._open):
                self._results[done] = reply

    def _wait(self, job: int) -> tuple[str, int, Any] | None:
        """The worker's reply for ``job``; None when the worker died before answering."""
        while job not in self._results:
            replies = self._replies
            if replies is None:
                return None
            try:
                ready = replies.poll(PARENT_CHECK_S)
                message = replies.recv() if ready else None
            except (EOFError, OSError):
                message, ready = None, False
            if message is not None:
                kind, done, generation, payload = message
                self._keep(job, done, (kind, generation, payload))
            elif self._proc is None or self._proc.poll() is not None:
                self._worker_died()
                return None
        return self._results.pop(job)

    # -- state -----------------------------------------------------------------------------------

    def reset(self, initial_pose: ArrayLike | None = None) -> None:
        """:meth:`Odometry.reset`; scans already handed to the worker are checked against
        the new trajectory's inputs when they are stepped (and prepared again if need be)."""
        upkeep, self._upkeep = getattr(self, '_upkeep', None), None
        if upkeep is not None:
            upkeep.join()  # it moves the model being forgotten: let it finish first
        self._upkeep_error = None
        super().reset(initial_pose)

    def reconfigure(self, config: KentRegConfig) -> None:
        """:meth:`Odometry.reconfigure`, and the worker's configuration with it."""
        super().reconfigure(config)
        with self._lock:
            self._generation += 1
            self._send(('config', self._generation, self.config))
