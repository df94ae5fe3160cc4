"""A batch from start to end: its jobs, the ones already finished, the run, the summary.

:func:`plan_batch` turns the inputs into one :class:`~kentreg_ros.batch.job.BatchJob` each (its
output folder named by :func:`~kentreg_ros.batch.inputs.output_names`); :func:`run_batch` skips
those an earlier run finished with the same settings, runs the others on the engine
(:mod:`kentreg_ros.batch.engine`) and rewrites the summary
(:mod:`kentreg_ros.batch.summary`) each time an input finishes, and once more at the end or on
Ctrl-C.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from kentreg_ros.batch import engine
from kentreg_ros.batch.inputs import output_names
from kentreg_ros.batch.job import BatchJob, InputEntry, InputStatus, finished_entry, read_marker
from kentreg_ros.batch.summary import write_summary
from kentreg_ros.core import KentRegConfig
from kentreg_ros.eval.replay import ReplayOptions


@dataclass
class BatchResult:
    """What a batch did: one entry per input, in the order of the inputs.

    Attributes
    ----------
    entries : list of InputEntry
    complete : bool
        The batch ran to its end (not interrupted).
    wall_s : float
        Wall time of the batch, the cluster's start included.
    n_run : int
        Inputs run (the others were skipped).
    """

    entries: list[InputEntry]
    complete: bool
    wall_s: float
    n_run: int

    @property
    def failed(self) -> list[InputEntry]:
        """The inputs that failed."""
        return [e for e in self.entries if e.status == InputStatus.FAILED]


def plan_batch(
    inputs: Sequence[str],
    out: Path,
    config: KentRegConfig,
    options: ReplayOptions,
    *,
    config_label: str = 'defaults',
    overrides: Sequence[str] = (),
    command: Sequence[str] = (),
) -> list[BatchJob]:
    """One job per input, each writing into its own folder of ``out``."""

    def finished_by(name: str) -> str | None:
        marker = read_marker(out / name)
        return str(marker['input']) if marker is not None else None

    names = output_names(inputs, finished_by=finished_by)
    return [
        BatchJob(
            input=item,
            name=name,
            out=out / name,
            config=config,
            options=options,
            config_label=config_label,
            overrides=tuple(overrides),
            command=tuple(command),
        )
        for item, name in zip(inputs, names, strict=True)
    ]


def run_batch(
    jobs: Sequence[BatchJob],
    out: Path,
    *,
    workers: int | None = None,
    address: str | None = None,
    in_process: bool = False,
    command: Sequence[str] = (),
    on_entry: Callable[[InputEntry], object] | None = None,
) -> BatchResult:
    """Run the jobs not finished before and keep ``out/summary.json`` and ``summary.md`` true.

    Parameters
    ----------
    jobs : sequence of BatchJob
        :func:`plan_batch`'s.
    out : Path
        The batch's output folder (created).
    workers, address : int, str, optional
        The local cluster's worker processes, or a running cluster's scheduler
        (:func:`~kentreg_ros.batch.engine.run_on_cluster`).
    in_process : bool
        Run the inputs in this process instead, one after the other.
    command : sequence of str
        Recorded in ``summary.json``.
    on_entry : callable, optional
        Called with each input's entry as it is known (a skipped one first), e.g. a progress
        bar.

    Raises
    ------
    KeyboardInterrupt
        Ctrl-C, after the summary is written (inputs not finished ``pending``).
    """
    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    entries = [
        finished_entry(job) or InputEntry(job.input, job.name, InputStatus.PENDING) for job in jobs
    ]
    row = {job.name: i for i, job in enumerate(jobs)}
    todo = [
        job
        for job, entry in zip(jobs, entries, strict=True)
        if entry.status != InputStatus.SKIPPED
    ]
    if on_entry is not None:
        for entry in entries:
            if entry.status == InputStatus.SKIPPED:
                on_entry(entry)
    write_summary(out, entries, command=command, complete=not todo)

    def finished(entry: InputEntry) -> None:
        entries[row[entry.name]] = entry
        write_summary(out, entries, command=command, complete=False)
        if on_entry is not None:
            on_entry(entry)

    if todo:
        try:
            if in_process:
                engine.run_in_process(todo, finished)
            else:
                engine.run_on_cluster(todo, finished, workers=workers, address=address)
        except KeyboardInterrupt:
            # The workers are stopped now; an input they finished before they were (its marker
            # written) is done, though its entry never came back.
            for i, job in enumerate(jobs):
                if entries[i].status == InputStatus.PENDING:
                    entries[i] = finished_entry(job, status=InputStatus.DONE) or entries[i]
            write_summary(out, entries, command=command, complete=False)
            raise
        write_summary(out, entries, command=command, complete=True)
    return BatchResult(entries, True, time.perf_counter() - t0, len(todo))
