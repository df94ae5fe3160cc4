"""``kentreg_batch``: ``kentreg_replay`` over many recordings, on this machine's cores or on a
cluster.

Every input is replayed by the replay's own code (:func:`kentreg_ros.eval.replay.replay`) into
``DIR/<name>/``, which then holds exactly the files ``kentreg_replay --out DIR/<name>`` writes
(their ``metrics.json`` names the batch's command line), and a marker ``DIR/<name>/.done``
written after them. The inputs run as tasks of Dask's distributed
scheduler (the ``cluster`` extra): without ``--address`` on a local cluster of ``--workers``
processes (default: one per core), with it on a running cluster, whose workers must see the
inputs and ``DIR`` at the same paths. Without the extra, one worker runs in this process.

Examples
--------
Five bags and a folder of bags, over this machine's cores::

    kentreg_batch drive1.mcap drive2/ fleet/ --out results/fleet

On a cluster (``dask scheduler`` on one machine, ``dask worker tcp://head:8786`` on each)::

    kentreg_batch /data/fleet --out /data/results --address tcp://head:8786

Inputs and outputs
------------------
An argument is one input when ``kentreg_replay`` takes it as one (a file, a rosbag2 folder, a
folder of scan files); any other folder is a folder of inputs, expanded one level
(:mod:`kentreg_ros.batch.inputs`). Inputs with the same name get ``-2``, ``-3``, ...
``DIR/summary.json`` (``{"inputs": [...]}``, one entry per input: ``input``, ``name``,
``status`` done / failed / skipped (pending while not finished), ``error``, ``scans``,
``health``, ``failed_steps``, ``ms_per_scan``, ``failed_pairs`` and ``pairs``, ``ate_m``) and
``DIR/summary.md`` (a table) are rewritten whole as each input finishes.

Nothing lost, nothing done twice: an input that cannot be read fails with its error and the
others go on; a rerun skips the inputs finished with the same parameters (the marker) and
redoes the others (failed, interrupted, or run with other parameters). Ctrl-C stops the
workers and leaves the summary true.

Exit status: 0 when every input is done or skipped, 1 when any failed, 2 on bad arguments (one
line on stderr), 130 when interrupted.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from kentreg_ros import __version__
from kentreg_ros.batch import InputEntry, discover_inputs, plan_batch, run_batch
from kentreg_ros.batch.engine import INSTALL_HINT, cluster_available
from kentreg_ros.batch.summary import SUMMARY_JSON, SUMMARY_MD, counts
from kentreg_ros.cli import common
from kentreg_ros.cli.replay import add_replay_options, replay_options

PROG = 'kentreg_batch'
EXIT_FAILED = 1


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface of ``kentreg_batch``."""
    parser = common.ArgumentParser(
        prog=PROG,
        description="Run kentreg_replay over many bags or scan folders, on this machine's "
        'cores or on a Dask cluster; one output folder per input and a summary.',
    )
    add = parser.add_argument
    add(
        'inputs',
        nargs='+',
        metavar='INPUT',
        help='what kentreg_replay takes (a bag, a rosbag2 folder, a folder of scan files), or '
        'a folder of such',
    )
    add('--out', type=Path, required=True, metavar='DIR', help='output folder')
    add(
        '--workers',
        type=common.positive_int,
        metavar='N',
        help='worker processes of the local cluster (default: one per core; 1 without the '
        'cluster extra, which then runs in this process)',
    )
    add(
        '--address',
        metavar='ADDR',
        help='scheduler of a running Dask cluster to run on (e.g. tcp://head:8786) instead of '
        'a local cluster; its workers must see the inputs and DIR at the same paths',
    )
    add('--topic', help='PointCloud2 topic, for bags with several')
    common.add_config_options(parser)
    add_replay_options(parser)
    add('--no-progress', action='store_true', help='no progress bar')
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument('-v', '--verbose', action='store_true', help='log every input')
    verbosity.add_argument('-q', '--quiet', action='store_true', help='log errors only')
    add('--version', action='version', version=f'%(prog)s {__version__}')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``kentreg_batch``; returns the exit status (see the module docstring)."""
    return common.run_main(PROG, lambda: _batch(argv))


def _batch(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    level = logging.DEBUG if args.verbose else logging.ERROR if args.quiet else logging.WARNING
    with common.logging_to_stderr(PROG, level):
        return _run(args, [PROG, *(sys.argv[1:] if argv is None else argv)])


def default_workers() -> int:
    """One worker per core this process may use, or 1 without the ``cluster`` extra."""
    return len(os.sched_getaffinity(0)) if cluster_available() else 1


def _run(args: argparse.Namespace, command: list[str]) -> int:
    cfg = common.config_from_args(args)
    if args.address is not None and args.workers is not None:
        raise common.CliError(
            "--workers is the local cluster's; a cluster at --address has its own"
        )
    workers = args.workers if args.workers is not None else default_workers()
    in_process = args.address is None and workers == 1 and not cluster_available()
    if not in_process and not cluster_available():
        wanted = '--address' if args.address is not None else f'--workers {workers}'
        raise common.CliError(f'{wanted} needs a cluster: {INSTALL_HINT}')
    inputs = discover_inputs(args.inputs)
    jobs = plan_batch(
        inputs,
        args.out,
        cfg,
        replay_options(args),
        config_label=str(args.config) if args.config else 'defaults',
        overrides=args.overrides,
        command=command,
    )
    with common.progress_bar(PROG, len(jobs), enabled=not args.no_progress, unit='input') as bar:

        def advance(entry: InputEntry) -> None:
            if bar is not None:
                bar.update(1)

        try:
            result = run_batch(
                jobs,
                args.out,
                workers=workers,
                address=args.address,
                in_process=in_process,
                command=command,
                on_entry=advance,
            )
        except KeyboardInterrupt:
            print(
                f'{PROG}: interrupted; {args.out / SUMMARY_JSON} lists the inputs finished',
                file=sys.stderr,
            )
            return common.EXIT_INTERRUPTED
    n_local = min(workers, result.n_run)
    where = (
        'nothing to run' if not result.n_run
        else 'in this process' if in_process
        else args.address or f'{n_local} local worker{"s" if n_local > 1 else ""}'
    )  # fmt: skip
    tally = ', '.join(f'{n} {status}' for status, n in counts(result.entries).items() if n)
    inputs_text = f'{len(jobs)} input{"s" if len(jobs) != 1 else ""}'
    print(f'{PROG}: {inputs_text}: {tally} in {result.wall_s:.1f} s ({where})')
    for entry in result.failed:
        print(f'  failed     {entry.input}: {entry.error}')
    print(f'  summary    {args.out / SUMMARY_JSON}, {args.out / SUMMARY_MD}')
    return EXIT_FAILED if result.failed else common.EXIT_OK


if __name__ == '__main__':
    sys.exit(main())
