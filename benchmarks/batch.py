"""kentreg_batch with one worker and with two (local Dask clusters): wall time, and the ratio.

``--copies`` links to one recording (default ``../shared/data/balm``: 50 raw scans of 72-90k
points, a longer run per input than the sample bag) are one batch, run with the defaults a user
gets by the batch's library (what ``kentreg_batch --workers N`` runs), alternately with one and
two workers, ``--rounds`` times; a batch's wall time includes starting its cluster, and its
cores busy (CPU seconds of this process and its workers over the wall time) show how much of the
shared machine it had. Issue #41's bar: two workers take at most 1/1.5 of one worker's time.
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository

from benchmarks.harness import report  # noqa: E402
from kentreg_ros.batch import plan_batch, run_batch  # noqa: E402
from kentreg_ros.core import KentRegConfig  # noqa: E402
from kentreg_ros.eval.replay import ReplayOptions  # noqa: E402

OPTIONS: list[report.Option] = [
    ('--input', {'type': Path, 'default': report.ROOT.parent / 'shared' / 'data' / 'balm'}),
    ('--copies', {'type': int, 'default': 4}), ('--rounds', {'type': int, 'default': 3}),
]  # fmt: skip


def run(args: argparse.Namespace, argv: list[str]) -> dict[str, Any]:
    machine = report.machine_info()
    walls: dict[str, list[float]] = {'1': [], '2': []}  # by worker count, as the JSON has it
    ms: dict[str, list[float]] = {'1': [], '2': []}
    cores: dict[str, list[float]] = {'1': [], '2': []}
    with tempfile.TemporaryDirectory() as tmp:
        inputs = [Path(tmp, f'copy{i}') for i in range(args.copies)]
        for link in inputs:
            link.symlink_to(args.input.resolve(), target_is_directory=True)
        for r, n in ((r, n) for r in range(args.rounds) for n in ('1', '2')):
            out = Path(tmp, f'out-{n}-{r}')
            jobs = plan_batch([str(p) for p in inputs], out, KentRegConfig(), ReplayOptions())
            cpu_s = _cpu_s()
            result = run_batch(jobs, out, workers=int(n))
            assert not result.failed, result.failed
            walls[n].append(result.wall_s)
            cores[n].append((_cpu_s() - cpu_s) / result.wall_s)
            ms[n] += [e.ms_per_scan or np.nan for e in result.entries]
    report.finish_machine(machine)
    median = {n: float(np.median(w)) for n, w in walls.items()}
    return {'machine': machine, 'argv': argv, 'input': str(args.input), 'copies': args.copies,
            'scans_per_input': result.entries[0].scans, 'wall_s': walls, 'median_wall_s': median,
            'median_ms_per_scan': {n: float(np.median(v)) for n, v in ms.items()},
            'median_cores_busy': {n: float(np.median(v)) for n, v in cores.items()},
            'ratio_two_to_one': median['2'] / median['1']}  # fmt: skip


def _cpu_s() -> float:
    """CPU seconds of this process and of its children that ended (the cluster's workers)."""
    use = [resource.getrusage(w) for w in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
    return sum(u.ru_utime + u.ru_stime for u in use)


def markdown(res: dict[str, Any]) -> str:
    rows = [[n, f'{res["median_wall_s"][n]:.1f}', ', '.join(f'{w:.1f}' for w in res['wall_s'][n]),
             f'{res["median_ms_per_scan"][n]:.1f}', f'{res["median_cores_busy"][n]:.2f}']
            for n in ('1', '2')]  # fmt: skip
    return '\n'.join([
        f'kentreg_batch: {res["copies"]} inputs of {res["scans_per_input"]} scans '
        f'({res["input"]}), at {res["machine"]["git"]}', '',
        *report.table(['workers', 'median wall (s)', 'batches (s)', 'median ms/scan',
                       'median cores busy'], rows), '',
        f'Two workers take {res["ratio_two_to_one"]:.2f} of one worker\'s time (bar: 0.667). '
        'Load average at the start and the end: '
        + ' and '.join('/'.join(f'{x:.1f}' for x in res['machine'][f'load_avg_at_{when}'])
                       for when in ('start', 'end')) + '.',
    ]) + '\n'  # fmt: skip


if __name__ == '__main__':
    sys.exit(report.experiment_main(__doc__ or '', 'batch', OPTIONS, run, markdown))
