"""The prepare stage in a worker process, ahead of the steps: :class:`ProcessPreparer`.

The odometry (:class:`~kentreg_ros.core.Odometry`) takes where its prepare stage runs as a
:class:`~kentreg_ros.core.Preparer`. This one hands each scan to one worker process as soon as
it arrives (:meth:`ProcessPreparer.prefetch`: time interpretation, deskew, crop, voxels,
normals, clusters), so that it is prepared while the odometry registers the scans before it:

============================= ================================ =============================
main process                  worker process                   note
============================= ================================ =============================
:meth:`prefetch` (scan k+1)   prepare k+1 (no per-point times)  on arrival
register k, chain its pose
``expect`` -> Go k+1          prepare k+1 (per-point times)     deskewing needs k's motion
move the model with k                                           overlaps the worker
register k+1 ...
============================= ================================ =============================

Why a process: the stages are numpy calls on arrays of a few thousand points with Python
between them, which hold the GIL; a thread pipeline gains nothing worth having, a worker
process does (``docs/notes-odometry.md``). The model's upkeep (the local map's insertion and
target) stays in the main process: it lies between the pose of scan k and the registration of
scan k+1 wherever it runs, so moving it only moves work between the processes.

Exactness: the prepare stage is a pure function of the scan and its
:class:`~kentreg_ros.core.PrepareInputs` (configuration, twist, voxel-size hint). The twist and
hint the loop uses are known only once the previous scan is prepared (hint) or registered
(twist), so the worker uses the hint it last produced, or one the odometry has said
(:meth:`ProcessPreparer.expect`), and waits for the twist of a sweep with per-point times.
Every reply carries the inputs it was made with; :meth:`ProcessPreparer.prepare` checks them
against the loop's and prepares the scan in this process when they differ (after a reset, a
new configuration or a dropped scan). The poses are therefore those of the sequential loop,
bit for bit (``test/runtime/test_pipeline.py``).

Failures: an exception in the worker while preparing a scan (a bug; an unusable cloud is the
ordinary ``rejected`` health) is raised from :meth:`ProcessPreparer.prepare`, so from the
odometry's step, as :class:`PipelineError`. A worker that dies is reported once per death
(``logging``), counted in :attr:`ProcessPreparer.n_worker_restarts`, and replaced; the scans it
held are prepared in the main process, so none is lost. The worker exits when its parent closes
the pipe, exits or dies (it checks its parent every
:data:`~kentreg_ros.runtime.messages.PARENT_CHECK_S`), so it is never left behind;
:meth:`ProcessPreparer.close` stops it.
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
from numpy.typing import ArrayLike

from kentreg_ros.core import (
    InThreadPreparer,
    KentRegConfig,
    KentRegError,
    PointTimes,
    Preparation,
    PrepareInputs,
    RawScan,
)
from kentreg_ros.runtime.messages import (
    PARENT_CHECK_S,
    Configure,
    Discard,
    Failed,
    Go,
    Job,
    Prepared,
    Reply,
    Request,
    Stop,
    unlink,
    write_scan_file,
)

logger = logging.getLogger(__name__)

#: The worker's module, run as ``python -m``.
WORKER_MODULE = 'kentreg_ros.runtime.worker'
#: Seconds :meth:`ProcessPreparer.close` waits for the worker to stop before terminating it.
STOP_TIMEOUT_S = 2.0
#: Scans prefetched and not yet prepared beyond which the oldest is discarded: the node keeps
#: a bounded queue, and a caller that prefetches without stepping must not fill the worker.
MAX_OPEN_JOBS = 8
#: The worker's native libraries on one thread each: it is one of the two processes the
#: pipeline spreads over two cores, and BLAS threads spinning beside the main process's work
#: would take the core it registers on.
ONE_THREAD_ENV = {'OMP_NUM_THREADS': '1', 'OPENBLAS_NUM_THREADS': '1', 'MKL_NUM_THREADS': '1'}
#: Where scans are handed to the worker: memory (tmpfs) where the system has it.
SCAN_DIR = '/dev/shm' if os.path.isdir('/dev/shm') else tempfile.gettempdir()


class PipelineError(KentRegError, RuntimeError):
    """The worker process failed on a scan (its traceback is in the message), or the preparer
    is closed."""


def _widen_pipe(fd: int) -> None:
    """Give the replies pipe 1 MB (Linux; 64 kB by default), so a prepared scan (~0.5 MB)
    goes in one write and the main process reads it in one piece."""
    try:
        fcntl.fcntl(fd, fcntl.F_SETPIPE_SZ, 1 << 20)
    except (AttributeError, OSError):  # not Linux, or above /proc/sys/fs/pipe-max-size
        pass


#: The directory this package is imported from.
PACKAGE_ROOT = str(Path(__file__).resolve().parents[2])


def _package_path() -> str:
    """PYTHONPATH for the worker: the directory this package is imported from first, so the
    worker runs the same code as its parent (a source tree, not another installed copy)."""
    rest = os.environ.get('PYTHONPATH', '')
    return PACKAGE_ROOT if not rest else f'{PACKAGE_ROOT}{os.pathsep}{rest}'


@dataclass
class _Open:
    """A scan handed to the worker and not yet prepared for its step."""

    id: int
    points: Any  # the caller's array: identifies the scan when it is stepped
    worker: int  # the worker (by number) that holds it
    path: str = ''  # the file handing the scan over (the worker removes it when it reads it)
    went: bool = False  # the worker was told the loop's inputs for it


@dataclass
class PipelineStats:
    """What the preparer did (for diagnostics and benchmarks)."""

    prepared_remote: int = 0
    prepared_here: int = 0
    redone: int = 0  # prepared by the worker with other inputs than the loop's, then here
    worker_restarts: int = 0
    wait_ms: deque[float] = field(default_factory=lambda: deque(maxlen=1000))


class ProcessPreparer:
    """The prepare stage in a worker process, ahead of the steps (see the module docstring).

    Give it to one :class:`~kentreg_ros.core.Odometry` (``preparer=``): the poses are those of
    the sequential loop. Call :meth:`prefetch` with a scan as soon as it arrives (before the
    steps of the scans before it have finished) for the worker to prepare it meanwhile; the
    step then takes it by identity of ``points``. A scan stepped without a prefetch is handed
    to the worker then (no overlap). Prefetched scans that are never stepped (dropped by the
    caller) are discarded when a later scan is stepped, or by :meth:`discard`. Call
    :meth:`close` (or use the instance as a context manager) to stop the worker.

    :meth:`prefetch` and :meth:`discard` may be called from another thread than the one that
    steps the odometry.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._ids = itertools.count()
        self._open: deque[_Open] = deque()
        self._results: dict[int, Reply] = {}
        self._generation = 0
        self._config: KentRegConfig | None = None  # the worker's settings
        self._next: PrepareInputs | None = None  # the next scan's inputs, when known
        self._proc: subprocess.Popen[bytes] | None = None
        self._requests: Connection | None = None
        self._replies: Connection | None = None
        self._n_workers = 0
        self._closed = False
        self._here = InThreadPreparer()
        self.stats = PipelineStats()
        self._start_worker()

    # -- the worker's life ---------------------------------------------------------------------

    def _start_worker(self) -> None:
        # A fresh interpreter running the worker module (not a fork: rclpy runs threads, and a
        # fork of a threaded process can deadlock; not multiprocessing's spawn either, which
        # runs the caller's main script again in the child unless it is guarded).
        req_r, req_w = mp.Pipe(duplex=False)
        rep_r, rep_w = mp.Pipe(duplex=False)
        fds = (req_r.fileno(), rep_w.fileno())
        _widen_pipe(rep_w.fileno())
        proc = subprocess.Popen(
            [sys.executable, '-m', WORKER_MODULE, str(fds[0]), str(fds[1]), str(os.getpid())],
            pass_fds=fds,
            stdin=subprocess.DEVNULL,
            env={**os.environ, **ONE_THREAD_ENV, 'PYTHONPATH': _package_path()},
            # ``-m`` puts the working directory first on sys.path, before PYTHONPATH: run it
            # where the package is, or a kentreg_ros in the caller's directory would be the
            # worker's (another tree's code, whose messages the parent's may not unpickle).
            cwd=PACKAGE_ROOT,
        )
        req_r.close()
        rep_w.close()
        self._proc, self._requests, self._replies = proc, req_w, rep_r
        self._n_workers += 1
        if self._config is not None:
            self._send(Configure(self._generation, self._config))

    def _send(self, message: Request) -> bool:
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
                unlink(item.path)
            if not self._closed:
                self._start_worker()

    def _stop_worker(self, *, wait: bool) -> None:
        proc, self._proc = self._proc, None
        if self._requests is not None:
            if wait:
                self._send(Stop())
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
        """Stop the worker process (idempotent); the preparer cannot prepare afterwards."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._stop_worker(wait=True)
            for item in self._open:
                unlink(item.path)  # files the worker did not read
            self._open.clear()

    @property
    def worker_pid(self) -> int | None:
        """Process id of the worker (None once closed)."""
        return self._proc.pid if self._proc is not None else None

    @property
    def n_worker_restarts(self) -> int:
        """Times a dead worker was replaced."""
        return self.stats.worker_restarts

    def __enter__(self) -> ProcessPreparer:
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
        """Hand a scan to the worker now; the odometry's step with the same ``points`` object
        takes it.

        The arguments are those the step will get. Nothing is checked here: whatever is wrong
        with the scan is reported by its step, as in the sequential loop.
        """
        item = self._submit(RawScan(points, point_times, int(stamp_ns)))
        if item is not None:
            with self._lock:
                self._open.append(item)

    def discard(self, points: ArrayLike) -> None:
        """Forget a prefetched scan that will not be stepped (e.g. dropped from a queue)."""
        with self._lock:
            for item in self._open:
                if item.points is points:
                    self._open.remove(item)
                    self._drop(item.id)
                    return

    def _submit(self, scan: RawScan) -> _Open | None:
        """Send a scan to the worker; its open job (None when closed or the pipe broke)."""
        points = np.asarray(scan.points)
        field_name = scan.point_times.field if isinstance(scan.point_times, PointTimes) else ''
        times = None if scan.point_times is None else np.asarray(scan.point_times)
        job = next(self._ids)
        path = os.path.join(SCAN_DIR, f'kentreg_scan_{os.getpid()}_{id(self)}_{job}.npy')
        try:
            write_scan_file(path, points, times)
        except (OSError, ValueError) as exc:  # no room, or a dtype np.save refuses
            unlink(path)
            logger.warning('Could not hand the scan to the worker (%s); preparing it here.', exc)
            return None
        with self._lock:
            if self._closed:
                unlink(path)
                return None
            while len(self._open) >= MAX_OPEN_JOBS:
                self._drop(self._open.popleft().id)
            # The hint the loop will use is known when no earlier scan is still to be prepared.
            nxt = None if self._open else self._next
            hint = nxt.voxel_size_hint if nxt is not None else None
            message = Job(job, path, times is not None, field_name, scan.stamp_ns, hint)
            if not self._send(message):
                unlink(path)
                return None
            return _Open(job, scan.points, self._n_workers, path)

    # -- the Preparer ----------------------------------------------------------------------------

    def prepare(self, scan: RawScan, inputs: PrepareInputs) -> Preparation:
        """The worker's preparation of ``scan`` if it was made with ``inputs``; else ``scan``
        prepared here.

        Raises
        ------
        PipelineError
            The worker raised while preparing this scan (a bug, as the sequential loop would
            raise it), or the preparer is closed.
        """
        if self._closed:
            raise PipelineError('This ProcessPreparer is closed.')
        with self._lock:
            self._next = None  # the next scan's inputs are known once this one is stepped
        self._configure(inputs.config)
        item = self._take(scan)
        if item is not None and not item.went:
            self._go(item, inputs)
        t0 = time.perf_counter()
        reply = self._wait(item.id) if item is not None else None
        if reply is None and item is not None:
            unlink(item.path)  # the worker died before it read the scan
        self.stats.wait_ms.append((time.perf_counter() - t0) * 1e3)
        if isinstance(reply, Failed):
            raise PipelineError(f'The scan preparation worker raised:\n{reply.traceback}')
        if reply is not None:
            if reply.generation == self._generation and reply.preparation.made_with(inputs):
                self.stats.prepared_remote += 1
                return reply.preparation
            self.stats.redone += 1
        self.stats.prepared_here += 1
        return self._here.prepare(scan, inputs)

    def expect(self, inputs: PrepareInputs) -> None:
        """The next scan's inputs are known: tell the worker (it may be waiting for them)."""
        self._configure(inputs.config)
        with self._lock:
            self._next = inputs
            following = self._open[0] if self._open else None
        if following is not None and following.worker == self._n_workers:
            self._go(following, inputs)

    def _configure(self, config: KentRegConfig) -> None:
        """Send the worker ``config`` when it has other settings (a new generation)."""
        with self._lock:
            if config != self._config:
                self._generation += 1
                self._config = config
                self._send(Configure(self._generation, config))

    def _take(self, scan: RawScan) -> _Open | None:
        """The open job of ``scan`` (earlier ones discarded), submitted now if there is none."""
        with self._lock:
            mine = next((o for o in self._open if o.points is scan.points), None)
            if mine is not None:
                while self._open[0] is not mine:
                    self._drop(self._open.popleft().id)
                self._open.popleft()
                if mine.worker == self._n_workers:
                    return mine
        return self._submit(scan)

    def _go(self, item: _Open, inputs: PrepareInputs) -> None:
        """Tell the worker the loop's twist and hint for this scan."""
        with self._lock:
            item.went = True
            self._send(Go(item.id, inputs.twist, inputs.voxel_size_hint))

    def _drop(self, job: int) -> None:
        """Tell the worker to skip ``job`` and forget its reply if it came (under the lock)."""
        self._send(Discard(job))
        self._results.pop(job, None)

    def _wait(self, job: int) -> Reply | None:
        """The worker's reply for ``job``; None when the worker died before answering.

        The replies that come meanwhile are kept when they are a later job's, or that of a scan
        still to be stepped although its job is older (a scan handed over again after its first
        job was discarded, by a caller more than :data:`MAX_OPEN_JOBS` behind; dropping that
        reply left the scan's step waiting forever). The others are replies for discarded
        jobs."""
        while job not in self._results:
            replies = self._replies
            if replies is None:
                return None
            try:
                ready = replies.poll(PARENT_CHECK_S)
                message = replies.recv() if ready else None
            except (EOFError, OSError):
                message, ready = None, False
            if isinstance(message, Prepared | Failed):
                with self._lock:
                    if message.id >= job or any(item.id == message.id for item in self._open):
                        self._results[message.id] = message
            elif self._proc is None or self._proc.poll() is not None:
                self._worker_died()
                return None
        return self._results.pop(job)
