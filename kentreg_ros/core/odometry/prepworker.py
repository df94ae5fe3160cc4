"""The worker process of :class:`~kentreg_ros.core.odometry.pipeline.PipelinedOdometry`: it
prepares the scans the main process sends, in order, and sends back each
:class:`~kentreg_ros.core.odometry.stages.Preparation` with the inputs it was made with.

Run as ``python -m kentreg_ros.core.odometry.prepworker REQUESTS_FD RESULTS_FD PARENT_PID`` by
the pipeline (never by hand; nothing imports this module, so ``-m`` runs it once). Messages
(pickled tuples) from the main process: ``('job', id, path, has_times, field, stamp, hint)``
(the points and times in the file ``path``, see
:func:`~kentreg_ros.core.odometry.handover.write_scan_file`), ``('go', id, twist, hint)`` (the
loop's inputs for that scan, once known), ``('discard', id)``, ``('config', generation,
config)``, ``('stop',)``. Replies: ``('result', id, generation, preparation)`` or
``('error', id, generation, traceback)``.
"""

from __future__ import annotations

import os
import queue
import signal
import sys
import threading
import time
import traceback
from collections import deque
from dataclasses import dataclass, replace
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.errors import InvalidPointCloudError
from kentreg_ros.core.odometry.deskew import PointTimes
from kentreg_ros.core.odometry.handover import PARENT_CHECK_S, read_scan_file
from kentreg_ros.core.odometry.preparation import Preparation, prepare_sweep
from kentreg_ros.core.odometry.stages import Sweep, read_sweep
from kentreg_ros.core.scan.prepared import elapsed_ms

FloatArray = NDArray[np.float64]


@dataclass
class _Job:
    """A scan given to the worker, as the worker holds it."""

    id: int
    points: NDArray[Any]
    times: NDArray[Any] | None
    field: str
    stamp: int
    hint: float | None  # None: continue from the worker's last prepared scan
    sweep: Sweep | None = None


def _strip(prep: Preparation) -> Preparation:
    """``prep`` without the raw points of a sweep that has no times (the main process needs
    them only to deskew again): a third of the bytes of a result, not 3 MB."""
    sweep = prep.sweep
    if sweep is None or sweep.times is not None:
        return prep
    return replace(prep, sweep=replace(sweep, points=np.zeros((0, 3))))


class _Worker:
    """The worker's state: its configuration, the scans it holds and the voxel-size chain."""

    def __init__(self, results: Connection) -> None:
        self.results = results
        self.config = KentRegConfig()
        self.generation = 0
        self.chain = 0.0  # voxel size of the last scan this worker prepared
        # The last scan prepared and the hint it used: a scan the main process drops after it
        # was prepared (a full queue) must not be the next one's hint, as the sequential loop
        # never saw it (else every drop would make the next scan be prepared again, on the
        # critical path, when the node is already behind).
        self.last_done: tuple[int, float] | None = None
        self.jobs: deque[_Job] = deque()
        self.go: dict[int, tuple[FloatArray, float]] = {}
        self.discarded: set[int] = set()
        self.failed: dict[int, str] = {}  # scans whose file could not be read: the traceback

    def take(self, message: tuple[Any, ...]) -> bool:
        """Act on one message; False on 'stop'."""
        kind = message[0]
        if kind == 'job':
            job_id, path, has_times, field, stamp, hint = message[1:]
            try:
                points, times = read_scan_file(path, has_times)
            except Exception:  # noqa: BLE001 - reported when the scan's turn comes
                points, times = np.zeros((0, 3)), None
                self.failed[job_id] = traceback.format_exc()
            self.jobs.append(_Job(job_id, points, times, field, stamp, hint))
        elif kind == 'go':
            if self.jobs and message[1] >= self.jobs[0].id:  # else: already prepared
                self.go[message[1]] = (message[2], message[3])
        elif kind == 'discard':
            if self.last_done is not None and message[1] == self.last_done[0]:
                self.chain, self.last_done = self.last_done[1], None
            else:
                self.discarded.add(message[1])
        elif kind == 'config':
            if message[2].preprocess != self.config.preprocess:
                self.chain = 0.0  # as the sequential loop: searched for other settings
            self.generation, self.config = message[1], message[2]
        return kind != 'stop'

    def waiting(self) -> bool:
        """Nothing to do until a message comes: no scan, or a sweep waiting for its twist."""
        jobs = self.jobs
        return not jobs or (jobs[0].sweep is not None and jobs[0].id not in self.go)

    def reply(self, message: tuple[Any, ...]) -> bool:
        try:
            self.results.send(message)
        except (OSError, ValueError):  # the main process closed its end: it is done with us
            return False
        return True

    def prepare_first(self) -> tuple[Any, ...] | None:
        """Prepare the first scan held; its reply, or None when it waits for its twist (or
        was discarded)."""
        job = self.jobs[0]
        if job.id in self.discarded:
            self.jobs.popleft()
            self.discarded.discard(job.id)
            self.go.pop(job.id, None)
            return None
        try:
            t0 = time.perf_counter()
            if job.id in self.failed:
                raise RuntimeError(f'the scan could not be read:\n{self.failed.pop(job.id)}')
            if job.sweep is None:
                times = None if job.times is None else PointTimes(job.times, job.field)
                try:
                    job.sweep = read_sweep(job.points, times, job.stamp, self.config)
                except InvalidPointCloudError as exc:
                    self.jobs.popleft()
                    rejected = Preparation(None, None, str(exc), elapsed_ms(t0))
                    return ('result', job.id, self.generation, rejected)
                if job.sweep.times is not None and job.id not in self.go:
                    # A sweep to deskew waits for the twist the main process learns once it
                    # has registered the scan before (this scan's 'go').
                    return None
            twist, hint = self.go.pop(job.id, (np.zeros(6), job.hint))
            hint = self.chain if hint is None else hint
            prep = prepare_sweep(job.sweep, twist, self.config, hint, t0=t0)
            if prep.scan is not None:
                self.last_done, self.chain = (job.id, hint), prep.scan.voxel_size
            answer: tuple[Any, ...] = ('result', job.id, self.generation, _strip(prep))
        except Exception:  # noqa: BLE001 - reported to the main process, which raises it
            answer = ('error', job.id, self.generation, traceback.format_exc())
        self.jobs.popleft()
        return answer


def _worker_main(requests: Connection, results: Connection, parent: int) -> None:
    """Entry point of the worker process: prepare the scans of ``requests`` in order."""
    from kentreg_ros.core import kernels

    # Ctrl-C reaches the whole process group: the node shuts down and closes the pipe, which
    # ends this process; an interrupt of its own would only print a traceback.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    kernels.warm_up()
    worker = _Worker(results)
    # The pipe is read by a thread of its own, so the main process's sends (3 MB scans) never
    # wait for a preparation to finish while this process waits to send a result: each side
    # blocked on a full pipe would deadlock the other.
    inbox: queue.Queue[tuple[Any, ...]] = queue.Queue()
    threading.Thread(target=_read, args=(requests, inbox), daemon=True).start()
    while True:
        while True:
            waiting = worker.waiting()
            try:
                message = inbox.get(timeout=PARENT_CHECK_S) if waiting else inbox.get_nowait()
            except queue.Empty:
                if not waiting:
                    break
                if os.getppid() != parent:
                    return  # the parent is gone: never outlive it
                continue
            if not worker.take(message):
                return
        answer = worker.prepare_first()
        if answer is not None and not worker.reply(answer):
            return


def _read(requests: Connection, inbox: queue.Queue[tuple[Any, ...]]) -> None:
    """Move every request into ``inbox``; a closed pipe is a stop."""
    while True:
        try:
            message = requests.recv()
        except (EOFError, OSError):
            inbox.put(('stop',))
            return
        inbox.put(message)
        if message[0] == 'stop':
            return


if __name__ == '__main__':
    # python -m kentreg_ros.core.odometry.prepworker REQUESTS_FD RESULTS_FD PARENT_PID
    _worker_main(
        Connection(int(sys.argv[1]), writable=False),
        Connection(int(sys.argv[2]), readable=False),
        int(sys.argv[3]),
    )
