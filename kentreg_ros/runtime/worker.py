"""The worker process of :class:`~kentreg_ros.runtime.preparer.ProcessPreparer`: it prepares the
scans the main process sends, in order, and sends back each
:class:`~kentreg_ros.core.Preparation` with the inputs it was made with.

Run as ``python -m kentreg_ros.runtime.worker REQUESTS_FD REPLIES_FD PARENT_PID`` by the
preparer (never by hand; nothing imports this module, so ``-m`` runs it once). The messages are
the dataclasses of :mod:`kentreg_ros.runtime.messages`.
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

from kentreg_ros.core import (
    InvalidPointCloudError,
    KentRegConfig,
    PointTimes,
    Preparation,
    PrepareInputs,
    Sweep,
    prepare_swept,
    read_sweep,
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
    read_scan_file,
)

FloatArray = NDArray[np.float64]


@dataclass
class _Held:
    """A scan given to the worker, as the worker holds it."""

    job: Job
    points: NDArray[Any]
    times: NDArray[Any] | None
    sweep: Sweep | None = None


def _strip(prep: Preparation) -> Preparation:
    """``prep`` without the raw points of a sweep that has no times (the main process needs
    them only to deskew again): a third of the bytes of a reply."""
    sweep = prep.sweep
    if sweep is None or sweep.times is not None:
        return prep
    return replace(prep, sweep=replace(sweep, points=np.zeros((0, 3))))


class _Worker:
    """The worker's state: its configuration, the scans it holds and the voxel-size chain."""

    def __init__(self, replies: Connection) -> None:
        self.replies = replies
        self.config = KentRegConfig()
        self.generation = 0
        self.chain = 0.0  # voxel size of the last scan this worker prepared
        # The last scan prepared and the hint it used: a scan the main process drops after it
        # was prepared (a full queue) must not be the next one's hint, as the sequential loop
        # never saw it (else every drop would make the next scan be prepared again, on the
        # critical path, when the node is already behind).
        self.last_done: tuple[int, float] | None = None
        self.held: deque[_Held] = deque()
        self.go: dict[int, Go] = {}
        self.discarded: set[int] = set()
        self.failed: dict[int, str] = {}  # scans whose file could not be read: the traceback

    def take(self, message: Request) -> bool:
        """Act on one request; False on :class:`Stop`."""
        if isinstance(message, Job):
            try:
                points, times = read_scan_file(message.path, message.has_times)
            except Exception:  # noqa: BLE001 - reported when the scan's turn comes
                points, times = np.zeros((0, 3)), None
                self.failed[message.id] = traceback.format_exc()
            self.held.append(_Held(message, points, times))
        elif isinstance(message, Go):
            if self.held and message.id >= self.held[0].job.id:  # else: already prepared
                self.go[message.id] = message
        elif isinstance(message, Discard):
            if self.last_done is not None and message.id == self.last_done[0]:
                self.chain, self.last_done = self.last_done[1], None
            else:
                self.discarded.add(message.id)
        elif isinstance(message, Configure):
            if message.config.preprocess != self.config.preprocess:
                self.chain = 0.0  # as the sequential loop: searched for other settings
            self.generation, self.config = message.generation, message.config
        return not isinstance(message, Stop)

    def waiting(self) -> bool:
        """Nothing to do until a message comes: no scan, or a sweep waiting for its twist."""
        held = self.held
        return not held or (held[0].sweep is not None and held[0].job.id not in self.go)

    def reply(self, message: Reply) -> bool:
        try:
            self.replies.send(message)
        except (OSError, ValueError):  # the main process closed its end: it is done with us
            return False
        return True

    def prepare_first(self) -> Reply | None:
        """Prepare the first scan held; its reply, or None when it waits for its twist (or
        was discarded)."""
        first = self.held[0]
        job = first.job
        if job.id in self.discarded:
            self.held.popleft()
            self.discarded.discard(job.id)
            self.go.pop(job.id, None)
            return None
        try:
            t0 = time.perf_counter()
            if job.id in self.failed:
                raise RuntimeError(f'the scan could not be read:\n{self.failed.pop(job.id)}')
            if first.sweep is None:
                times = None if first.times is None else PointTimes(first.times, job.field)
                try:
                    first.sweep = read_sweep(first.points, times, job.stamp_ns, self.config)
                except InvalidPointCloudError as exc:
                    self.held.popleft()
                    ms = (time.perf_counter() - t0) * 1e3
                    return Prepared(job.id, self.generation, Preparation(None, None, str(exc), ms))
                if first.sweep.times is not None and job.id not in self.go:
                    # A sweep to deskew waits for the twist the main process learns once it
                    # has registered the scan before (this scan's Go).
                    return None
            go = self.go.pop(job.id, None)
            twist = go.twist if go is not None else np.zeros(6)
            hint = go.hint if go is not None else job.hint
            hint = self.chain if hint is None else hint
            prep = prepare_swept(first.sweep, PrepareInputs(self.config, twist, hint), t0=t0)
            if prep.scan is not None:
                self.last_done, self.chain = (job.id, hint), prep.scan.voxel_size
            answer: Reply = Prepared(job.id, self.generation, _strip(prep))
        except Exception:  # noqa: BLE001 - reported to the main process, which raises it
            answer = Failed(job.id, self.generation, traceback.format_exc())
        self.held.popleft()
        return answer


def _worker_main(requests: Connection, replies: Connection, parent: int) -> None:
    """Entry point of the worker process: prepare the scans of ``requests`` in order."""
    from kentreg_ros.core import kernels

    # Ctrl-C reaches the whole process group: the node shuts down and closes the pipe, which
    # ends this process; an interrupt of its own would only print a traceback.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    kernels.warm_up()
    worker = _Worker(replies)
    # The pipe is read by a thread of its own, so the main process's sends never wait for a
    # preparation to finish while this process waits to send a result: each side blocked on a
    # full pipe would deadlock the other.
    inbox: queue.Queue[Request] = queue.Queue()
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


def _read(requests: Connection, inbox: queue.Queue[Request]) -> None:
    """Move every request into ``inbox``; a closed pipe is a stop."""
    while True:
        try:
            message = requests.recv()
        except (EOFError, OSError):
            inbox.put(Stop())
            return
        inbox.put(message)
        if isinstance(message, Stop):
            return


if __name__ == '__main__':
    # python -m kentreg_ros.runtime.worker REQUESTS_FD REPLIES_FD PARENT_PID
    _worker_main(
        Connection(int(sys.argv[1]), writable=False),
        Connection(int(sys.argv[2]), readable=False),
        int(sys.argv[3]),
    )
