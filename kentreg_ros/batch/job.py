"""One input of a batch: the replay of it, its summary entry and its marker of completion.

:func:`run_job` is what a worker runs (in a worker process of a cluster, or in the batch's own
process): the replay (:func:`kentreg_ros.eval.replay.replay`, the code ``kentreg_replay`` runs)
into the input's folder, then, only when every output is written and the run is complete, the
marker ``.done`` (written last, by a rename, so it exists only whole). It returns the input's
:class:`InputEntry` and never raises for a bad input: an input that cannot be read, or that
breaks the replay, is ``failed`` with its error, and the batch goes on. The marker holds the
entry and the settings of the run (the input, the configuration and the replay's options): a
rerun skips an input whose marker is there with the same settings, and redoes one without it
(interrupted, failed) or with other settings.
"""

from __future__ import annotations

import ctypes
import dataclasses
import fcntl
import json
import logging
import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

from kentreg_ros.core import KentRegConfig, KentRegError, kernels
from kentreg_ros.eval.replay import ReplayOptions, ReplaySummary, replay
from kentreg_ros.io.paramfile import dump_config

logger = logging.getLogger(__name__)

#: The marker of a finished input, in its output folder; written after every other output.
MARKER = '.done'
#: Environment variables that hold the numeric libraries of a worker to one thread, so that N
#: workers use N cores (set before the libraries load: the engine spawns its workers with them).
ONE_THREAD_ENV = {
    'OMP_NUM_THREADS': '1',
    'OPENBLAS_NUM_THREADS': '1',
    'MKL_NUM_THREADS': '1',
    'NUMBA_NUM_THREADS': '1',
}


class InputStatus(StrEnum):
    """Where an input of a batch stands."""

    DONE = 'done'
    FAILED = 'failed'
    SKIPPED = 'skipped'  # finished by an earlier run (its marker), not run again
    PENDING = 'pending'  # not finished yet (while the batch runs, or after Ctrl-C)


@dataclass(frozen=True)
class InputEntry:
    """One input's line of ``summary.json``.

    Attributes
    ----------
    input : str
        The input as given (or as found in a folder of inputs).
    name : str
        Its output folder under the batch's output folder.
    status : InputStatus
    error : str or None
        Why it failed.
    scans : int or None
        Scans processed.
    health : dict or None
        Steps per health (``first``, ``ok``, ..., ``rejected``).
    failed_steps : int or None
        Steps that fell back or were rejected.
    ms_per_scan : float or None
        Mean milliseconds per scan.
    failed_pairs, pairs : int or None
        Failed pairs (e_R > 2 deg or e_t > 0.2 m) and pairs, with a reference.
    ate_m : float or None
        ATE RMSE after SE(3) alignment (m), with a reference of 3 poses or more.
    wall_s : float or None
        Wall time of the input in its worker (seconds), kernels' loading included.
    """

    input: str
    name: str
    status: InputStatus
    error: str | None = None
    scans: int | None = None
    health: dict[str, int] | None = None
    failed_steps: int | None = None
    ms_per_scan: float | None = None
    failed_pairs: int | None = None
    pairs: int | None = None
    ate_m: float | None = None
    wall_s: float | None = None

    def to_json(self) -> dict[str, Any]:
        """The entry as JSON values (``status`` as its string)."""
        out = dataclasses.asdict(self)
        out['status'] = str(self.status)
        return out

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> InputEntry:
        """The entry :meth:`to_json` wrote (unknown keys ignored)."""
        known = {f.name for f in dataclasses.fields(cls)}
        values = {k: v for k, v in data.items() if k in known}
        return cls(**{**values, 'status': InputStatus(values['status'])})


@dataclass(frozen=True)
class BatchJob:
    """One input to replay into ``out`` with ``config`` and ``options`` (picklable: it travels
    to a worker).

    ``config_label``, ``overrides`` and ``command`` are recorded in the input's
    ``metrics.json`` as the replay records them.
    """

    input: str
    name: str
    out: Path
    config: KentRegConfig
    options: ReplayOptions
    config_label: str = 'defaults'
    overrides: tuple[str, ...] = ()
    command: tuple[str, ...] = ()

    def settings(self) -> dict[str, Any]:
        """What decides the outputs: the input (resolved), the configuration, the options."""
        options = {k: _plain(v) for k, v in dataclasses.asdict(self.options).items()}
        return {
            'input': str(Path(self.input).resolve()),
            'config': dump_config(self.config),
            'options': options,
        }


def _plain(value: Any) -> Any:
    return str(value) if isinstance(value, Path) else value


def read_marker(folder: Path) -> dict[str, Any] | None:
    """The marker of a finished input's folder (``input``, ``settings``, ``entry``), or None
    without a readable one."""
    try:
        data = json.loads((folder / MARKER).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and 'entry' in data and 'settings' in data else None


def finished_entry(
    job: BatchJob, *, status: InputStatus = InputStatus.SKIPPED
) -> InputEntry | None:
    """The entry of ``job`` as its marker records it (with ``status``: ``skipped`` for a run
    before this one), when the marker is there with the same settings; None when it is not and
    the input has to run."""
    marker = read_marker(job.out)
    if marker is None:
        return None
    if marker['settings'] != job.settings():
        logger.info('%s: finished with other settings before; running it again.', job.input)
        return None
    try:
        entry = InputEntry.from_json(marker['entry'])
    except (KeyError, TypeError, ValueError):
        return None
    return dataclasses.replace(entry, input=job.input, name=job.name, status=status)


def run_job(job: BatchJob) -> InputEntry:
    """Replay ``job``'s input into ``job.out`` (emptied first) and mark it finished.

    Returns the input's entry: ``done`` (outputs and marker written), or ``failed`` with the
    first line of the error (an input that cannot be read or a read error part way, whose
    outputs are kept without a marker; an unexpected exception of the replay, logged with its
    traceback). Ctrl-C in the batch's own process stops the replay, writes what it did (as
    ``kentreg_replay`` does) and raises ``KeyboardInterrupt``.
    """
    t0 = time.perf_counter()
    try:
        load_kernels()
        if job.out.is_dir() and not job.out.is_symlink():
            shutil.rmtree(job.out)  # an interrupted or outdated run's files: none may remain
        summary = replay(
            job.input,
            job.config,
            job.out,
            job.options,
            config_label=job.config_label,
            overrides=job.overrides,
            command=job.command,
        )
    except (KentRegError, ValueError, OSError) as exc:
        return _failed(job, first_line(exc), t0)
    except Exception as exc:  # a bug met on this input: it fails, the other inputs go on
        logger.exception('%s: the replay raised', job.input)
        return _failed(job, f'{type(exc).__name__}: {first_line(exc)}', t0)
    if summary.run.interrupted:
        raise KeyboardInterrupt
    entry = _entry(job, summary, time.perf_counter() - t0)
    if summary.run.error is not None:
        error = f'{summary.run.error} (outputs of the {entry.scans} scans read are in {job.out})'
        return dataclasses.replace(entry, status=InputStatus.FAILED, error=error)
    write_marker(job, entry)
    return entry


def _entry(job: BatchJob, summary: ReplaySummary, wall_s: float) -> InputEntry:
    pairs = summary.failed_pairs
    return InputEntry(
        input=job.input,
        name=job.name,
        status=InputStatus.DONE,
        scans=summary.n_scans,
        health=summary.health,
        failed_steps=int(summary.report['n_failed_steps']),
        ms_per_scan=round(summary.ms_per_scan, 3),
        failed_pairs=pairs[0] if pairs is not None else None,
        pairs=pairs[1] if pairs is not None else None,
        ate_m=summary.ate_m,
        wall_s=round(wall_s, 3),
    )


def _failed(job: BatchJob, error: str, t0: float) -> InputEntry:
    logger.info('%s failed: %s', job.input, error)
    wall_s = round(time.perf_counter() - t0, 3)
    return InputEntry(job.input, job.name, InputStatus.FAILED, error=error, wall_s=wall_s)


def first_line(exc: BaseException) -> str:
    """The first line of an exception's message, or its type's name when it has none."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def write_marker(job: BatchJob, entry: InputEntry) -> None:
    """Write ``job.out/.done`` whole or not at all (a temporary file renamed)."""
    data = {'input': job.settings()['input'], 'settings': job.settings(), 'entry': entry.to_json()}
    write_atomic(job.out / MARKER, json.dumps(data, indent=2) + '\n')


def write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file beside it and a rename, so a reader
    (or an interruption) sees the old file or the new one, never a part."""
    fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', dir=path.parent)
    try:
        with os.fdopen(fd, 'w') as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_kernels() -> bool:
    """Compile or load the compiled kernels (:func:`kentreg_ros.core.kernels.warm_up`) with an
    exclusive lock held, so that the workers of one machine do it one after the other.

    numba's cache writes each file by a rename, but two processes compiling at once can still
    both pick the same name for different entries of its index; in turn, the first worker
    compiles into the cache (11 s on this 2-core VM) and the others load from it (0.6 s)
    instead of each compiling. Returns whether the kernels are used.
    """
    lock = Path(tempfile.gettempdir()) / f'kentreg-kernels-{os.getuid()}.lock'
    with lock.open('a') as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            return kernels.warm_up()
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def prepare_worker() -> None:
    """Make this worker process run the odometry as a process of its own would, on one core.

    Its numeric libraries are held to one thread: the environment (:data:`ONE_THREAD_ENV`)
    reaches those loaded after this, threadpoolctl (the ``cluster`` extra) the BLAS and OpenMP
    pools already loaded. And when the process was started with ``MALLOC_TRIM_THRESHOLD_`` set
    (a ``dask worker``'s nanny sets 65536 by default), glibc's mmap threshold is raised back to
    its dynamic ceiling: the variable fixes it at 128 KiB, so that every numpy temporary above
    it was mapped anew and paid its page faults, a BALM scan 29 ms instead of 19.
    """
    os.environ.update(ONE_THREAD_ENV)
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        pass
    else:
        threadpool_limits(1)
    if 'MALLOC_TRIM_THRESHOLD_' in os.environ:
        _raise_malloc_thresholds()


def _raise_malloc_thresholds() -> None:
    try:
        mallopt = ctypes.CDLL(None).mallopt  # glibc; elsewhere there is nothing to undo
    except (OSError, AttributeError):
        return
    m_trim_threshold, m_mmap_threshold = -1, -3  # glibc's malloc.h
    mallopt(m_mmap_threshold, 32 << 20)  # DEFAULT_MMAP_THRESHOLD_MAX on 64-bit
    mallopt(m_trim_threshold, 64 << 20)  # twice it, as the dynamic threshold keeps it
