"""Median per-stage times of kentreg at about 3k / 10k / 30k points per scan.

Scans: consecutive pairs of the real BALM sequence (``../shared/data/balm``, read with
:func:`kentreg_ros.io.read_scan`) when present, otherwise a seeded synthetic room (walls, floor,
ceiling and three boxes, 80k points, moved 5 deg / 0.3 m per scan). For each size the target
(model) scan is prepared once and cached, as in odometry; the timed work per pair is the new
scan's preprocessing (crop, voxel downsampling, normals, outlier removal, clustering) plus
``register``.

Usage::

    python benchmarks/bench_register.py [--pairs 10] [--sizes 3000 10000 30000] [--json out.json]

Prints a table and writes ``benchmarks/results/bench_register.json``.
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
sys.path.insert(0, str(ROOT))

from kentreg_ros.core import KentRegConfig, exp_so3, make_transform, prepare_scan, register  # noqa: E402  # noqa: E402
from kentreg_ros.io import read_scan  # noqa: E402

BALM = ROOT.parent / 'shared' / 'data' / 'balm'
STAGES_PREP = ('downsample', 'normals', 'outliers', 'clustering')
STAGES_REG = ('rotation', 'translation', 'refine')


def load_balm_scan(i: int) -> np.ndarray:
    return np.asarray(read_scan(BALM / f'full{i}.pcd', fields=()).points, dtype=np.float64)


def box_room(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` points (1 cm noise) on an 8 x 6 x 3 m room and three boxes turned about z."""
    lo, ex, ey, ez = np.array([-4.0, -3.0, -1.0]), *np.diag([8.0, 6.0, 3.0])
    faces = [(lo, ex, ey), (lo + ez, ex, ey), (lo, ex, ez), (lo + ey, ex, ez)]
    faces += [(lo, ey, ez), (lo + ex, ey, ez)]
    for i in range(3):
        c = np.array([rng.uniform(-8 / 3, 8 / 3), rng.uniform(-2.0, 2.0), -1.0])
        R = exp_so3(np.array([0.0, 0.0, rng.uniform(0, np.pi / 2)]) + 0.05 * i)
        a, b, h = R @ [0.8, 0.0, 0.0], R @ [0.0, 0.6, 0.0], np.array([0.0, 0.0, 1.0])
        faces += [(c, a, h), (c + b, a, h), (c, b, h), (c + a, b, h), (c + h, a, b)]
    areas = np.array([np.linalg.norm(np.cross(u, v)) for _, u, v in faces])
    counts = rng.multinomial(n, areas / areas.sum())
    pts = np.concatenate(
        [
            o + rng.random((k, 1)) * u + rng.random((k, 1)) * v
            for (o, u, v), k in zip(faces, counts, strict=True)
        ]
    )
    return pts + rng.normal(scale=0.01, size=pts.shape)


def synthetic_scans(n: int) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    base = box_room(rng, 80000)
    scans = []
    for _ in range(n):
        axis, direction = rng.normal(size=3), rng.normal(size=3)
        R = exp_so3(axis / np.linalg.norm(axis) * np.radians(5.0))
        T = make_transform(R, direction / np.linalg.norm(direction) * 0.3)
        scans.append(base @ T[:3, :3].T + T[:3, 3])
    return scans


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--pairs', type=int, default=10)
    parser.add_argument('--sizes', type=int, nargs='+', default=[3000, 10000, 30000])
    parser.add_argument(
        '--json', type=Path, default=ROOT / 'benchmarks' / 'results' / 'bench_register.json'
    )
    args = parser.parse_args(argv)
    if BALM.exists():
        scans = [load_balm_scan(i) for i in range(args.pairs + 1)]
        source = 'BALM (real, 72k-90k points per raw scan)'
    else:
        scans = synthetic_scans(args.pairs + 1)
        source = 'synthetic room (../shared/data/balm not found)'
    load_before = os.getloadavg()[0]
    rows = []
    for size in args.sizes:
        cfg = KentRegConfig().with_updates({'preprocess.target_points': size})
        # Warm-up (imports, caches) on the first pair, not timed.
        model = prepare_scan(scans[0], config=cfg)
        register(prepare_scan(scans[1], config=cfg), model, config=cfg)
        per_pair = []
        for i in range(args.pairs):
            model = prepare_scan(scans[i], config=cfg)
            t0 = time.perf_counter()
            scan = prepare_scan(scans[i + 1], config=cfg)
            result = register(scan, model, config=cfg)
            wall = (time.perf_counter() - t0) * 1e3
            entry = {f'prep.{k}': scan.timings.get(k, 0.0) for k in STAGES_PREP}
            entry.update({f'reg.{k}': result.timings[k] for k in STAGES_REG})
            entry['prep.total'] = scan.timings['total']
            entry['reg.total'] = result.timings['total']
            entry['prep+reg'] = wall
            entry['points'] = float(len(scan))
            per_pair.append(entry)
        med = {k: float(np.median([e[k] for e in per_pair])) for k in per_pair[0]}
        med['target_points'] = size
        rows.append(med)
    keys = (
        [f'prep.{k}' for k in STAGES_PREP]
        + ['prep.total']
        + [f'reg.{k}' for k in STAGES_REG]
        + ['reg.total', 'prep+reg']
    )
    print(f'kentreg per-stage median ms over {args.pairs} pairs of {source}')
    load_after = os.getloadavg()[0]
    print(
        f'machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cpus, '
        f'python {platform.python_version()}, numpy {np.__version__}, '
        f'1-min load average {load_before:.1f} before / {load_after:.1f} after (other processes '
        'share the cpus)'
    )
    header = f'{"stage":<22}' + ''.join(f'{int(r["target_points"]):>10}' for r in rows)
    print(header)
    print(f'{"points after prep":<22}' + ''.join(f'{r["points"]:>10.0f}' for r in rows))
    for k in keys:
        print(f'{k:<22}' + ''.join(f'{r[k]:>10.1f}' for r in rows))
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(
        json.dumps(
            {
                'source': source,
                'pairs': args.pairs,
                'rows': rows,
                'cpus': os.cpu_count(),
                'load_average_1min': [load_before, load_after],
            },
            indent=2,
        )
    )
    print(f'wrote {args.json}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
