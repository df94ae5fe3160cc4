"""Median per-stage times of kentreg at about 3k / 10k / 30k points per scan.

Consecutive raw BALM pairs (``balm_or_sample``); the target prepared once, the new scan's
preparation + ``register`` timed. Prints a table, writes ``results/bench_register.json``.

Usage::

    python benchmarks/bench_register.py [--pairs 10] [--sizes 3000 10000 30000] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.harness import datasets, report  # noqa: E402
from kentreg_ros.core import KentRegConfig, prepare_scan, register  # noqa: E402

STAGES_PREP = ('downsample', 'normals', 'outliers', 'clustering')
STAGES_REG = ('rotation', 'translation', 'refine')


def stage_times(scans: list[np.ndarray], size: int, pairs: int) -> dict[str, float]:
    """Median stage times (ms) of ``pairs`` pairs at ``preprocess.target_points = size``."""
    cfg = KentRegConfig().with_updates({'preprocess.target_points': size})
    # Warm-up (imports, caches) on the first pair, not timed.
    register(prepare_scan(scans[1], config=cfg), prepare_scan(scans[0], config=cfg), config=cfg)
    per_pair = []
    for i in range(pairs):
        model = prepare_scan(scans[i], config=cfg)
        t0 = time.perf_counter()
        scan = prepare_scan(scans[i + 1], config=cfg)
        result = register(scan, model, config=cfg)
        wall = (time.perf_counter() - t0) * 1e3
        entry = {f'prep.{k}': scan.timings.get(k, 0.0) for k in STAGES_PREP}
        entry |= {f'reg.{k}': result.timings[k] for k in STAGES_REG}
        entry |= {
            'prep.total': scan.timings['total'],
            'reg.total': result.timings['total'],
            'prep+reg': wall,
            'points': float(len(scan)),
        }
        per_pair.append(entry)
    med = {k: float(np.median([e[k] for e in per_pair])) for k in per_pair[0]}
    return med | {'target_points': size}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--pairs', type=int, default=10)
    parser.add_argument('--sizes', type=int, nargs='+', default=[3000, 10000, 30000])
    parser.add_argument('--json', type=Path, default=report.RESULTS / 'bench_register.json')
    args = parser.parse_args(argv)
    seq = datasets.load_dataset('balm_or_sample')
    scans = [seq.raw(i) for i in range(args.pairs + 1)]
    sizes = [len(s) for s in scans]
    source = f'{seq.name} (real, {min(sizes)}-{max(sizes)} points per raw scan)'
    load_before = os.getloadavg()[0]
    rows = [stage_times(scans, size, args.pairs) for size in args.sizes]
    load_after = os.getloadavg()[0]
    keys = [
        *(f'prep.{k}' for k in STAGES_PREP),
        'prep.total',
        *(f'reg.{k}' for k in STAGES_REG),
        'reg.total',
        'prep+reg',
    ]
    print(f'kentreg per-stage median ms over {args.pairs} pairs of {source}')
    print(
        f'machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cpus, '
        f'python {platform.python_version()}, numpy {np.__version__}, 1-min load average '
        f'{load_before:.1f} before / {load_after:.1f} after (other processes share the cpus)'
    )
    print(f'{"stage":<22}' + ''.join(f'{int(r["target_points"]):>10}' for r in rows))
    print(f'{"points after prep":<22}' + ''.join(f'{r["points"]:>10.0f}' for r in rows))
    for k in keys:
        print(f'{k:<22}' + ''.join(f'{r[k]:>10.1f}' for r in rows))
    args.json.parent.mkdir(parents=True, exist_ok=True)
    doc = {
        'source': source,
        'pairs': args.pairs,
        'rows': rows,
        'cpus': os.cpu_count(),
        'load_average_1min': [load_before, load_after],
    }
    args.json.write_text(json.dumps(doc, indent=2))
    print(f'wrote {args.json}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
