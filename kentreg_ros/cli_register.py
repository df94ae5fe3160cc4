"""``kentreg_register``: register two scan files and print the transform and diagnostics.

Example::

    kentreg_register source.ply target.ply --ref T_target_source.txt

Exits 0 on success (whatever the status, which is printed), 2 with one readable line on bad
input.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

from kentreg_ros.core import KentRegConfig, KentRegError, register
from kentreg_ros.eval.metrics import pair_errors
from kentreg_ros.io.params import load_config


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog='kentreg_register',
        description='Estimate T_target_source between two scans (PCD, PLY, KITTI .bin, ETH CSV).',
    )
    p.add_argument('source', type=Path, help='scan to align (the observed scan)')
    p.add_argument('target', type=Path, help='reference scan (the model)')
    p.add_argument('--config', type=Path, help='YAML parameters (config/kentreg.yaml form)')
    p.add_argument('--mode', choices=('robust', 'paper'), help='override the config mode')
    p.add_argument('--init', type=Path, help='4x4 text file: initial T_target_source')
    p.add_argument('--ref', type=Path, help='4x4 text file: reference T_target_source')
    p.add_argument('-v', '--verbose', action='store_true')
    return p


def _read_matrix(path: Path, what: str) -> np.ndarray:
    try:
        T = np.loadtxt(path, dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise KentRegError(f'Cannot read {what} {str(path)!r}: {exc}') from exc
    if T.shape != (4, 4):
        raise KentRegError(f'Expected a 4x4 matrix in {str(path)!r}, got shape {T.shape}.')
    return T


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING,
        format='%(levelname)s %(name)s: %(message)s',
    )
    try:
        from kentreg_ros.io import read_scan  # noqa: PLC0415

        cfg = load_config(args.config) if args.config else KentRegConfig()
        if args.mode:
            cfg = cfg.with_updates({'mode': args.mode})
        init = _read_matrix(args.init, 'initial transform') if args.init else None
        ref = _read_matrix(args.ref, 'reference transform') if args.ref else None
        for path in (args.source, args.target):
            if not path.is_file():
                raise KentRegError(f'No such scan file: {str(path)!r}.')
        source = read_scan(args.source, fields=()).points
        target = read_scan(args.target, fields=()).points
        result = register(source, target, init=init, config=cfg)
    except (KentRegError, ValueError) as exc:
        print(f'kentreg_register: error: {exc}', file=sys.stderr)
        return 2
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
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
