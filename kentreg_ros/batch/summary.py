"""The batch's summary: ``summary.json`` (one entry per input) and the ``summary.md`` table.

Both are rewritten whole (a temporary file renamed) each time an input finishes, so at any
moment, after Ctrl-C too, they say what is finished: inputs not finished are ``pending``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from kentreg_ros import __version__
from kentreg_ros.batch.job import InputEntry, InputStatus, write_atomic

SUMMARY_JSON = 'summary.json'
SUMMARY_MD = 'summary.md'


def counts(entries: Sequence[InputEntry]) -> dict[str, int]:
    """Inputs per status."""
    return {str(s): sum(e.status == s for e in entries) for s in InputStatus}


def summary_data(
    entries: Sequence[InputEntry], *, command: Sequence[str], complete: bool
) -> dict[str, Any]:
    """What ``summary.json`` holds: ``inputs`` (:meth:`InputEntry.to_json` of each, in the
    order of the inputs), ``counts`` per status, ``complete`` (the batch ran to its end)."""
    return {
        'kentreg_version': __version__,
        'command': list(command),
        'complete': complete,
        'counts': counts(entries),
        'inputs': [e.to_json() for e in entries],
    }


def write_summary(
    out: Path, entries: Sequence[InputEntry], *, command: Sequence[str], complete: bool
) -> None:
    """Write ``out/summary.json`` and ``out/summary.md``, each whole or not at all."""
    data = summary_data(entries, command=command, complete=complete)
    write_atomic(out / SUMMARY_JSON, json.dumps(data, indent=2) + '\n')
    write_atomic(out / SUMMARY_MD, summary_markdown(entries, complete=complete))


def _number(value: float | None, spec: str) -> str:
    return '–' if value is None else format(value, spec)


def summary_markdown(entries: Sequence[InputEntry], *, complete: bool = True) -> str:
    """The table of ``summary.md``: one row per input."""
    tally = ', '.join(f'{n} {status}' for status, n in counts(entries).items() if n)
    lines = [
        '# kentreg batch',
        '',
        f'{len(entries)} input{"s" if len(entries) != 1 else ""}: {tally}'
        + ('' if complete else ' (the batch did not finish)'),
        '',
        '| input | status | output | scans | ms/scan | failed steps | failed pairs | ATE [m] '
        '| error |',
        '|---|---|---|---:|---:|---:|---:|---:|---|',
    ]
    for e in entries:
        pairs = f'{e.failed_pairs}/{e.pairs}' if e.failed_pairs is not None else '–'
        error = (e.error or '').replace('|', '\\|')
        lines.append(
            f'| {e.input} | {e.status} | {e.name}/ | {_number(e.scans, "d")} '
            f'| {_number(e.ms_per_scan, ".1f")} | {_number(e.failed_steps, "d")} | {pairs} '
            f'| {_number(e.ate_m, ".4f")} | {error} |'
        )
    return '\n'.join(lines) + '\n'
