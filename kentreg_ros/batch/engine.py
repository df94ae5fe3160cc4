"""Where a batch's inputs run: worker processes of Dask's distributed scheduler, or this process.

A local cluster (``dask.distributed.LocalCluster``: a scheduler and N worker processes of one
thread each, started with their numeric libraries held to one thread,
:data:`~kentreg_ros.batch.job.ONE_THREAD_ENV`) runs the inputs over this machine's cores; with
an address, the batch joins a running cluster (``dask scheduler`` and ``dask worker`` on
several machines, which see the inputs and the output folder at the same paths) and its
inputs run on all of it. Each input is one task, :func:`~kentreg_ros.batch.job.run_job`. The
scheduler hands a task whose worker died (killed, out of memory, a crash in native code) to
another worker, up to its ``allowed-failures`` (3); after that the input is ``failed``
(``KilledWorker``). Why Dask and not Ray (start-up, memory, failures, measured here):
``benchmarks/README.md``, section 6.

Without the ``cluster`` extra the inputs run one after the other in this process
(:func:`run_in_process`), which only one worker can be.
"""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import os
import signal
import threading
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from kentreg_ros.batch.job import (
    ONE_THREAD_ENV,
    BatchJob,
    InputEntry,
    InputStatus,
    first_line,
    prepare_worker,
    run_job,
)

logger = logging.getLogger(__name__)

#: What to install for more than one worker or for a cluster's address.
INSTALL_HINT = "pip install 'kentreg_ros[cluster]' (Dask's distributed scheduler)"
#: Seconds to wait for a running cluster's scheduler to answer.
CONNECT_TIMEOUT_S = 20


def cluster_available() -> bool:
    """Whether Dask's distributed scheduler (the ``cluster`` extra) is installed."""
    return importlib.util.find_spec('distributed') is not None


def run_in_process(jobs: Sequence[BatchJob], on_entry: Callable[[InputEntry], object]) -> None:
    """Run the jobs one after the other in this process, calling ``on_entry`` with each entry;
    Ctrl-C stops at once (``KeyboardInterrupt``)."""
    for job in jobs:
        on_entry(run_job(job))


def run_on_cluster(
    jobs: Sequence[BatchJob],
    on_entry: Callable[[InputEntry], object],
    *,
    workers: int | None = None,
    address: str | None = None,
) -> None:
    """Run the jobs as tasks of a Dask cluster, calling ``on_entry`` with each entry as it
    finishes.

    Parameters
    ----------
    jobs : sequence of BatchJob
    on_entry : callable
        Called in this process, in the order the inputs finish.
    workers : int, optional
        Worker processes of the local cluster started for the jobs (at most one per job).
    address : str, optional
        The scheduler of a running cluster to join instead (``tcp://host:8786``).

    Raises
    ------
    OSError
        The scheduler at ``address`` did not answer.
    KeyboardInterrupt
        Ctrl-C: the tasks are cancelled and a local cluster's workers stopped first.
    """
    with _client(workers=workers, address=address, n_jobs=len(jobs)) as (client, local_pids):
        from distributed import as_completed

        # Keys of this run only: a task of an earlier run may still be running on a cluster,
        # and a new task under its key would be given that task's result.
        run = uuid.uuid4().hex[:12]
        futures = {
            client.submit(_task, job, key=f'kentreg-batch-{run}-{i}-{job.name}', pure=False): job
            for i, job in enumerate(jobs)
        }
        try:
            for future in as_completed(futures):
                job = futures[future]
                try:
                    entry: InputEntry = future.result()
                except Exception as exc:  # the worker died too often, or the task never ran
                    error = f'{type(exc).__name__}: {first_line(exc)}'
                    logger.info('%s failed on the cluster: %s', job.input, error)
                    entry = InputEntry(job.input, job.name, InputStatus.FAILED, error=error)
                on_entry(entry)
        except BaseException:
            client.cancel(list(futures), force=True)
            # Dask cannot stop a running task: the local workers are killed (their inputs keep
            # no marker and run again next time); a remote cluster's finish theirs.
            for pid in local_pids:
                with contextlib.suppress(OSError):
                    os.kill(pid, signal.SIGKILL)
            raise


def _task(job: BatchJob) -> InputEntry:
    """One input in a worker: the worker made like a process of its own, then the job."""
    prepare_worker()
    return run_job(job)


@contextmanager
def _client(
    *, workers: int | None, address: str | None, n_jobs: int
) -> Iterator[tuple[Any, list[int]]]:
    """A client of a running cluster (``address``) or of a local cluster started here, and the
    process ids of the local cluster's workers."""
    from distributed import Client, LocalCluster

    if address is not None:
        client = Client(address, timeout=CONNECT_TIMEOUT_S)
        try:
            client.forward_logging('kentreg_ros', level=logging.WARNING)
            yield client, []
        finally:
            client.close()
        return
    import dask

    n = max(1, min(workers or 1, n_jobs))
    # Dask's nanny would start the workers with MALLOC_TRIM_THRESHOLD_=65536, which slows the
    # odometry by half (kentreg_ros.batch.job.prepare_worker): None leaves it unset. The workers
    # start with Ctrl-C ignored (a disposition a new process keeps): it reaches this process
    # alone, which stops them.
    with (
        dask.config.set({'distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_': None}),
        _ctrl_c_ignored(),
    ):
        cluster = LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            silence_logs=logging.CRITICAL,  # the summary reports failures, not workers' noise
            env=dict(ONE_THREAD_ENV),
        )
    try:
        client = Client(cluster)
        try:
            client.forward_logging('kentreg_ros', level=logging.WARNING)
            pids: dict[str, int] = client.run(os.getpid)
            yield client, list(pids.values())
        finally:
            client.close()
    finally:
        cluster.close()


@contextmanager
def _ctrl_c_ignored() -> Iterator[None]:
    """SIGINT ignored while the block runs (in the main thread; elsewhere nothing changes)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
