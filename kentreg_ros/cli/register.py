"""``kentreg_register``: register two scan files and print the transform and diagnostics.

Example::

    kentreg_register source.ply target.ply --ref T_target_source.txt

The configuration is the defaults, or ``--config FILE`` (the node's YAML), with ``--set
KEY=VALUE`` overrides and ``--mode`` (a shortcut for ``--set mode=...``) on top.

Exits 0 on success (whatever the status, which is printed), 2 with one readable line on bad
input, 130 when interrupted.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from kentreg_ros import __version__
from kentreg_ros.cli import common
from kentreg_ros.core import register
from kentreg_ros.eval.metrics import pair_errors
from kentreg_ros.io import read_scan

PROG = 'kentreg_register'


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface of ``kentreg_register``."""
    p = common.ArgumentParser(
        prog=PROG,
        description='Estimate T_target_source between two scans (PCD, PLY, KITTI .bin, ETH CSV).',
    )
    p.add_argument('source', type=Path, help='scan to align (the observed scan)')
    p.add_argument('target', type=Path, help='reference scan (the model)')
    common.add_config_options(p)
    p.add_argument('--mode', choices=('robust', 'paper'), help='override the config mode')
    p.add_argument('--init', type=Path, help='4x4 text file: initial T_target_source')
    p.add_argument('--ref', type=Path, help='4x4 text file: reference T_target_source')
    p.add_argument('-v', '--verbose', action='store_true', help='log every stage')
    p.add_argument('--version', action='version', version=f'%(prog)s {__version__}')
    return p


def read_matrix(path: Path, what: str) -> NDArray[np.float64]:
    """A 4x4 matrix from a text file, or a :class:`~kentreg_ros.cli.common.CliError`."""
    try:
        T = np.loadtxt(path, dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise common.CliError(f'Cannot read {what} {str(path)!r}: {exc}') from exc
    if T.shape != (4, 4):
        raise common.CliError(f'Expected a 4x4 matrix in {str(path)!r}, got shape {T.shape}.')
    return T


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``kentreg_register``; returns the exit status (see the module docstring)."""
    return common.run_main(PROG, lambda: _register(argv))


def _register(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    level = logging.DEBUG if args.verbose else logging.WARNING
    with common.logging_to_stderr(PROG, level):
        cfg = common.config_from_args(args)
        if args.mode:
            cfg = cfg.with_updates({'mode': args.mode})
        init = read_matrix(args.init, 'initial transform') if args.init else None
        ref = read_matrix(args.ref, 'reference transform') if args.ref else None
        for path in (args.source, args.target):
            if not path.is_file():
                raise common.CliError(f'No such scan file: {str(path)!r}.')
        source = read_scan(args.source, fields=()).points
        target = read_scan(args.target, fields=()).points
        result = register(source, target, init=init, config=cfg)
    np.set_printoptions(precision=6, suppress=True)
    print(f'mode: {result.mode}   status: {result.status} ({result.message})')
    print(
        f'points used: source {result.n_source}, target {result.n_target}; '
        f'inliers {result.inlier_fraction:.1%}; iterations {result.iterations}'
    )
    print('T_target_source =')
    print(result.T_target_source)
    print('timings (ms): ' + ', '.join(f'{k} {v:.1f}' for k, v in result.timings.items()))
    if ref is not None:
        e_r, e_t = pair_errors(result.T_target_source[None], ref[None])
        print(
            f'error vs reference: rotation {float(e_r[0]):.4f} deg, '
            f'translation {float(e_t[0]):.4f} m'
        )
    return common.EXIT_OK


if __name__ == '__main__':
    sys.exit(main())
