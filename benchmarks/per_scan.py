"""Per-scan odometry cost: raw scan in, pose out; one process and one thread per pipeline.

The pipelines (``kentreg``, ``kentreg_numpy``, ``gicp``, ``icp_pt2pl``, ``kiss_icp``) over the
same raw BALM scans, ``--rounds`` rotated rounds: ms per scan, resident memory, memory growth
over a long run (``--long-steps``), pair errors (README section 3). ``--merge K``: denser scans
(``perturb.merge``), written as ``per_scan_merge<K>.*``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import tracemalloc
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository

from benchmarks.harness import datasets, methods, perturb, pipelines, report, runner  # noqa: E402
from kentreg_ros.core import invert_transform  # noqa: E402
from kentreg_ros.eval.metrics import pair_errors  # noqa: E402
from kentreg_ros.io.sources import Scan  # noqa: E402

FloatArray = NDArray[np.float64]
METHODS = ('kentreg', 'kentreg_numpy', 'gicp', 'icp_pt2pl', 'kiss_icp')
#: The peers' voxel edge on BALM (~10k points on a raw scan, as in the other benchmarks).
PEER_VOXEL = 0.25
PERIOD_NS = 500_000_000  # BALM is a 2 Hz recording; stamps only feed the velocity models
#: Steps of the memory run: resident memory settles over the first ~200 steps (the
#: allocator), so the growth is measured over the second half.
LONG_STEPS = 450


def _forth_and_back(n: int, steps: int) -> list[int]:
    """Scan indices 0..n-1, then back n-1..0, and so on, ``steps`` of them."""
    cycle = list(range(n)) + list(range(n - 1, -1, -1))
    return [cycle[k % len(cycle)] for k in range(steps)]


def _rss_mb(key: str) -> float:
    """Resident memory of this process from /proc/self/status (VmRSS now, VmHWM its peak)."""
    for line in Path('/proc/self/status').read_text().splitlines():
        if line.startswith(key + ':'):
            return float(line.split()[1]) / 1024.0
    return float('nan')


def run_worker(args: argparse.Namespace) -> dict[str, Any]:
    """One method over the saved scans in this (pinned) process; ``--long-steps`` > 0: the
    memory run (scans forth and back, numpy's and Python's live memory traced, not timed)."""
    methods.limit_threads(1)
    data, steps = np.load(args.data), args.long_steps  # an NpzFile: a scan is read when used
    n = int(data['n'])
    pipeline = pipelines.make_pipeline(args.methods[0], voxel=PEER_VOXEL, threads=1, max_history=2)
    base_mb = _rss_mb('VmRSS')
    try:  # the peak from here on: the method's own, not the imports' (Linux)
        Path('/proc/self/clear_refs').write_text('5')
    except OSError:
        pass
    if steps > 0:
        tracemalloc.start()
    poses, ms, rss, traced = [], [], [], []
    for k, i in enumerate(_forth_and_back(n, steps) if steps > 0 else range(n)):
        points = np.ascontiguousarray(data[f's{i}'], dtype=np.float64)
        pose, t = runner.timed(pipeline.step, Scan(k * PERIOD_NS, 'lidar', points, {}))
        poses.append(pose)
        ms.append(t)
        rss.append(_rss_mb('VmRSS'))
        if steps > 0:
            traced.append(tracemalloc.get_traced_memory()[0] / 2**20)
    peak_mb = _rss_mb('VmHWM')
    return {'ms': ms, 'poses': np.array(poses).tolist(), 'start_rss_mb': base_mb,
            'peak_rss_mb': peak_mb, 'peak_growth_mb': peak_mb - base_mb, 'rss_mb': rss,
            'traced_mb': traced}  # fmt: skip


def summarize(ms: list[float], poses: FloatArray, truth: FloatArray) -> dict[str, Any]:
    per_scan = np.array(ms[1:])  # the first scan only prepares
    rel = [
        [invert_transform(T[i - 1]) @ T[i] for i in range(1, len(poses))] for T in (poses, truth)
    ]
    e_R, e_t = pair_errors(np.array(rel[0]), np.array(rel[1]))
    return {
        'ms_per_scan': {'p50': float(np.percentile(per_scan, 50)),
                        'p95': float(np.percentile(per_scan, 95)),
                        'max': float(per_scan.max()), 'mean': float(per_scan.mean())},
        'e_R_deg_median': float(np.median(e_R)), 'e_t_m_median': float(np.median(e_t)),
        'failures': int(runner.failure_mask(e_R, e_t).sum()), 'n_pairs': len(e_R),
    }  # fmt: skip


def markdown(doc: dict[str, Any]) -> str:
    meta = doc['meta']
    base = doc['methods'].get('gicp', {}).get('ms_per_scan', {}).get('p50')
    merged = (
        f'; each joined with its {meta["merge"] - 1} predecessor(s) by the reference poses'
        if meta.get('merge', 1) > 1
        else ''
    )
    long_run = (f'memory growth over the second half of {meta.get("long_steps") or "–"} steps '
                'MB: live numpy/Python (tracemalloc) / resident')  # fmt: skip
    columns: list[report.Column] = [
        ('method', 'name:s'), ('p50 ms/scan', 'ms_per_scan.p50:.1f'),
        ('p95', 'ms_per_scan.p95:.1f'), ('max', 'ms_per_scan.max:.1f'),
        ('ratio to GICP (p50)', lambda r: f'{r["ms_per_scan"]["p50"] / base:.2f}×' if base
         else '–'),
        ('resident MB once started / peak', lambda r: '–' if r.get('start_rss_mb') is None
         else f'{r["start_rss_mb"]:.0f} / {r["peak_rss_mb"]:.0f}'),
        ('peak memory growth MB', 'peak_growth_mb:.0f'),
        (long_run, lambda r: f'{lr["growth_mb"]:.2f} / {lr["rss_growth_mb"]:.1f}'
         if (lr := r.get('long_run')) else '–'),
        ('median e_R (deg)', 'e_R_deg_median:.3f'),
        ('median e_t (mm)', lambda r: f'{1e3 * r["e_t_m_median"]:.1f}'),
        ('failed pairs', lambda r: f'{r["failures"]}/{r["n_pairs"]}'),
    ]  # fmt: skip
    lines = [
        f'Per-scan odometry on {meta["n_scans"]} raw BALM scans ({meta["points"]}{merged}), one '
        f'thread per method, {meta["rounds"]} rounds; the first scan (prepare only) excluded.',
        '',
        *report.column_table(columns, report.named(doc['methods'])),
        '',
        f'Run at {meta["git"]}; load average {meta["load"]} at the start.',
        '',
    ]
    return '\n'.join(lines)


def _in_worker(method: str, scans_file: Path, steps: int) -> dict[str, Any]:
    options = ['--methods', method, '--data', str(scans_file), '--long-steps', str(steps)]
    res = runner.in_subprocess(__file__, options)
    if 'error' in res and not ('ImportError' in res['error'] or 'No module' in res['error']):
        raise SystemExit(f'{method}: {res["error"]}')  # else: left out, its library cannot load
    return res


def _long_run(method: str, scans_file: Path, steps: int) -> dict[str, Any]:
    """Flat memory over a long run: memory after the last step minus at the middle (the
    allocator has settled by then); a leak of 10 kB per step would show as 2 MB."""
    res = _in_worker(method, scans_file, steps)
    rss, traced, mid = res['rss_mb'], res['traced_mb'], steps // 2
    return {'steps': steps, 'from_step': mid, 'rss_at_middle_mb': rss[mid - 1],
            'rss_at_end_mb': rss[-1], 'rss_growth_mb': rss[-1] - rss[mid - 1],
            'traced_at_middle_mb': traced[mid - 1], 'traced_at_end_mb': traced[-1],
            'growth_mb': traced[-1] - traced[mid - 1]}  # fmt: skip


OPTIONS: list[report.Option] = [
    ('--methods', {'nargs': '+', 'default': list(METHODS), 'choices': METHODS}),
    ('--scans', {'type': int, 'default': 50, 'help': 'scans from the start (>= 2)'}),
    ('--rounds', {'type': int, 'default': 2}),
    ('--long-steps', {'type': int, 'default': LONG_STEPS,
                      'help': 'steps of the memory run per method (0: none)'}),
    ('--merge', {'type': int, 'default': 1, 'help': 'denser scans: each joined with its K-1 '
                 'predecessors (K=2: ~150-180k points; default 1, the raw scans)'}),
    ('--data', {'type': Path, 'help': argparse.SUPPRESS}),
]  # fmt: skip


def run(args: argparse.Namespace, argv: list[str]) -> dict[str, Any]:
    seq = datasets.load_balm()
    scans = seq.scans[: args.scans]
    truth = np.asarray(seq.T_world)[: len(scans)]
    if args.merge > 1:
        scans = perturb.merge(args.merge, truth)(scans)
        truth = truth[args.merge - 1 :]
    n = len(scans)
    long_steps = args.long_steps if args.long_steps > n else 0
    samples: dict[str, list[dict[str, Any]]] = {m: [] for m in args.methods}
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        scans_file = Path(tmp) / 'scans.npz'
        arrays: dict[str, Any] = {f's{i}': np.asarray(s.points) for i, s in enumerate(scans)}
        np.savez(scans_file, n=n, **arrays)
        for r, method in runner.rotated(list(args.methods), args.rounds):
            res, took_ms = runner.timed(_in_worker, method, scans_file, 0)
            samples[method] += [] if 'error' in res else [res]
            said = res.get('error') or f'p50 {np.median(res["ms"][1:]):.1f} ms/scan'
            print(f'round {r} {method}: {said} ({took_ms / 1e3:.0f} s)', file=sys.stderr)
        for method, rounds in ((m, rounds) for m, rounds in samples.items() if rounds):
            ms = [rounds[0]['ms'][0]] + [t for res in rounds for t in res['ms'][1:]]
            summary = summarize(ms, np.array(rounds[0]['poses']), truth)
            for key in ('start_rss_mb', 'peak_rss_mb', 'peak_growth_mb'):
                summary[key] = max(res[key] for res in rounds)
            summary['rounds_p50'] = [float(np.median(res['ms'][1:])) for res in rounds]
            if long_steps:
                summary['long_run'] = _long_run(method, scans_file, long_steps)
            results[method] = summary
    info, sizes = report.machine_info(), [len(s.points) for s in scans]
    meta = {'n_scans': n, 'points': f'{min(sizes)}-{max(sizes)} points each', 'merge': args.merge,
            'rounds': args.rounds, 'long_steps': long_steps,
            'git': report.git_describe() or 'unknown', 'load': info.get('load_avg_at_start'),
            'machine': info}  # fmt: skip
    return {'meta': meta, 'methods': results}


def _stem(args: argparse.Namespace) -> str:
    return 'per_scan' if args.merge <= 1 else f'per_scan_merge{args.merge}'


if __name__ == '__main__':
    main = report.experiment_main
    raise SystemExit(main(__doc__, _stem, OPTIONS, run, markdown, worker=run_worker))
