"""Speed: time per registration against N points (3k..100k), one library per process.

Every pair method registers the same BALM pairs at each N (one raw scan, or a two-scan submap
beyond half the smallest scan, downsampled at the edge giving about N points) from the
reference off by 1 deg / 5 cm; per pair the target is prepared once untimed and the source
prepared + registered ``--repeats`` times; each library runs in its own pinned subprocess, in
``--rounds`` rotated rounds; ratios are to small_gicp GICP in the same run (README section 3).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository

from benchmarks.harness import datasets, methods, perturb, report, runner  # noqa: E402
from kentreg_ros.core import count_voxels  # noqa: E402
from kentreg_ros.eval.metrics import FAIL_ROTATION_DEG, FAIL_TRANSLATION_M  # noqa: E402

SIZES = (3000, 10000, 30000, 100000)
REFERENCE = 'gicp'
#: Which library each method loads (one process per library).
LIBRARY_OF = {'gicp': 'small_gicp', 'icp_pt2pt': 'open3d', 'icp_pt2pl': 'open3d',
              'kiss_icp': 'kiss_icp', 'ndt': 'baseline', 'cicp': 'baseline',
              'kentreg_robust': 'kentreg', 'kentreg_paper': 'kentreg'}  # fmt: skip
MARKERS = dict(zip(LIBRARY_OF, 'ov^Dx+sP', strict=True))
#: Largest N built from single scans, as a fraction of the smallest raw scan.
SINGLE_SCAN_FRACTION = 0.5
INIT_ERROR_DEG, INIT_ERROR_M = 1.0, 0.05
TIMING = (
    'per pair: prepare(source) + register(source, target, init), target prepared once untimed; '
    'median over pairs x repeats (fewer repeats when a cell would exceed --cell-budget) after '
    'one untimed warm-up pair per method and size; input clouds already voxel-downsampled '
    '(the downsampling is not timed)'
)


def pair_starts(n_scans: int, n_pairs: int, span: int) -> list[int]:
    """First scans ``k`` of ``n_pairs`` pairs spread over the sequence (scans k..k+2 span-1)."""
    if n_scans < 2 * span:
        raise SystemExit(f'need at least {2 * span} scans, got {n_scans}')
    starts = np.linspace(0, n_scans - 2 * span, n_pairs).round().astype(int)
    return [int(k) for k in np.unique(starts)]


def voxel_for_count(points: runner.FloatArray, count: int, *, iterations: int = 24) -> float:
    """Voxel edge keeping about ``count`` points: bisection in log size (the occupied-voxel
    count falls monotonically, up to grid noise, with the edge)."""
    if count >= len(points):
        raise SystemExit(f'cannot keep {count} of {len(points)} points by downsampling')
    lo, hi = np.log(1e-3), np.log(10.0)
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if count_voxels(points, float(np.exp(mid))) > count else (lo, mid)
    return float(np.exp(0.5 * (lo + hi)))


def build_clouds(
    seq: datasets.Sequence, sizes: list[int], n_pairs: int, *, seed: int = 0
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The clouds (``n{N}_source_{i}``, ``n{N}_target_{i}``), starts (``n{N}_init``) and
    reference motions (``n{N}_reference``) of every size, and how they were made."""

    def submap(k: int) -> runner.FloatArray:
        return np.vstack([seq.raw(k), perturb.transform(seq.relative(k, k + 1), seq.raw(k + 1))])

    n_scans, rng = len(seq.scans), np.random.default_rng(seed)
    smallest = min(len(seq.scans[k].points) for k in pair_starts(n_scans, n_pairs, 1))
    arrays: dict[str, Any] = {}
    info: dict[str, Any] = {}
    for size in sizes:
        single = size <= SINGLE_SCAN_FRACTION * smallest
        span, cloud_of = (1, seq.raw) if single else (2, submap)
        starts = pair_starts(n_scans, n_pairs, span)
        voxel = float(np.median([voxel_for_count(cloud_of(k), size) for k in starts]))
        inits, refs = [], []
        for i, k in enumerate(starts):
            for role, index in (('target', k), ('source', k + span)):
                arrays[f'n{size}_{role}_{i}'] = methods.voxel_downsample(cloud_of(index), voxel)
            refs.append(seq.relative(k, k + span))
            inits.append(refs[-1] @ perturb.offset_transform(rng, INIT_ERROR_DEG, INIT_ERROR_M))
        arrays[f'n{size}_init'], arrays[f'n{size}_reference'] = np.stack(inits), np.stack(refs)
        counts = [len(v) for k, v in arrays.items() if k.startswith(f'n{size}_') and v.ndim == 2]
        what = 'one raw scan' if single else 'two-scan submap (scans k, k+1 merged in the frame '
        info[str(size)] = {
            'clouds': what if single else what + 'of k by the reference poses)', 'voxel': voxel,
            'pairs': [[k + span, k] for k in starts],
            'points': {'min': int(min(counts)), 'median': float(np.median(counts)),
                       'max': int(max(counts))},
            'init': f'reference motion x error of {INIT_ERROR_DEG:g} deg, {INIT_ERROR_M:g} m '
            f'(random axis and direction, seed {seed})',
        }  # fmt: skip
    return arrays, info


def time_method(
    method: methods.Method, data: Any, size: str, repeats: int, budget_s: float
) -> dict[str, Any]:
    """Prepare + register times and pair errors of one method at one size (a worker's cell)."""
    inits, refs = data[f'n{size}_init'], data[f'n{size}_reference']
    clouds = [
        (data[f'n{size}_source_{i}'], data[f'n{size}_target_{i}']) for i in range(len(inits))
    ]
    # Warm-up: imports, allocators, caches; not timed, but it sizes the repeats.
    source, target = clouds[0]
    _, warm_ms = runner.timed(
        lambda: method.register(method.prepare(source), method.prepare(target), inits[0])
    )
    n_repeats = int(np.clip(budget_s // (warm_ms / 1e3 * len(inits)), 1, repeats))
    prep_ms, reg_ms, errors = [], [], []
    for (source_points, target_points), init, ref in zip(clouds, inits, refs, strict=True):
        target = method.prepare(target_points)
        for _ in range(n_repeats):
            source, t_prep = runner.timed(method.prepare, source_points)
            T, t_reg = runner.timed(method.register, source, target, init)
            prep_ms.append(t_prep)
            reg_ms.append(t_reg)
        errors.append(runner.errors(np.asarray(T, dtype=np.float64), ref))
    return {'library': method.library, 'params': dict(method.params), 'repeats': n_repeats,
            'prepare_ms': prep_ms, 'register_ms': reg_ms, 'e_R_deg': [e[0] for e in errors],
            'e_t_m': [e[1] for e in errors]}  # fmt: skip


def run_worker(args: argparse.Namespace) -> dict[str, Any]:
    """Time every method of one library on every size of the saved clouds (this process)."""
    data = np.load(args.data)
    out: dict[str, Any] = {'pid': os.getpid(), 'affinity': [], 'env': {}, 'sizes': {}}
    for size, voxel in json.loads(str(data['voxels'])).items():
        built = methods.make_methods(list(args.methods), voxel=voxel, threads=args.threads)
        out['affinity'] = sorted(os.sched_getaffinity(0))
        out['env'] = {name: os.environ.get(name) for name in methods.THREAD_ENV}
        cells = {m.name: time_method(m, data, size, args.repeats, args.cell_budget) for m in built}
        out['sizes'][size] = cells
    return out


def summarize_cell(samples: list[dict[str, Any]]) -> dict[str, Any]:
    """Medians of one method at one size over every pair, repeat and round (errors: round 1)."""
    prep = np.concatenate([s['prepare_ms'] for s in samples])
    reg = np.concatenate([s['register_ms'] for s in samples])
    e_R, e_t = np.asarray(samples[0]['e_R_deg']), np.asarray(samples[0]['e_t_m'])
    return {
        'n_samples': int(prep.size), 'n_rounds': len(samples),
        'total_ms': float(np.median(prep + reg)), 'prepare_ms': float(np.median(prep)),
        'register_ms': float(np.median(reg)), 'total_ms_p90': float(np.percentile(prep + reg, 90)),
        'median_e_R_deg': float(np.median(e_R)), 'max_e_R_deg': float(np.max(e_R)),
        'median_e_t_m': float(np.median(e_t)), 'max_e_t_m': float(np.max(e_t)),
        'n_failed': int(np.sum(runner.failure_mask(e_R, e_t))), 'n_pairs': int(e_R.size),
    }  # fmt: skip


def _total(c: dict[str, Any]) -> str:
    fail = f', {c["n_failed"]} failed' if c['n_failed'] else ''
    return f'{c["total_ms"]:.1f} ms ({c["ratio_to_gicp"]:.2f}×{fail})'


def format_table(doc: dict[str, Any]) -> str:
    """Markdown: median ms per pair (prepare + register) and the ratio to GICP, per N."""
    sizes, results = list(doc['clouds']), doc['results']
    head = ['method', *(f'N≈{int(s) // 1000}k' for s in sizes)]

    def rows(cell: Any) -> list[list[str]]:
        return [[n, *(cell(c[s]) if s in c else '-' for s in sizes)] for n, c in results.items()]

    lines = [
        'Median ms per pair (source preparation + registration) and ratio to small_gicp GICP; '
        f'{doc["threads"]} thread(s), {doc["pairs"]} pairs x {doc["repeats"]} repeats x '
        f'{doc["rounds"]} rounds per cell; failures (e_R > {FAIL_ROTATION_DEG:g} deg or e_t > '
        f'{FAIL_TRANSLATION_M:g} m) out of {doc["pairs"]} pairs.', '',
        *report.table(head, rows(_total)), '',
        'The two parts, median ms: source preparation / registration.', '',
        *report.table(head, rows(lambda c: f'{c["prepare_ms"]:.1f} / {c["register_ms"]:.1f}')),
    ]  # fmt: skip
    reduced = [f'{name} N≈{int(s) // 1000}k ({c["n_samples"]})'
               for name, cells in results.items() for s, c in cells.items()
               if c['n_samples'] < c['n_pairs'] * c['n_rounds'] * doc['repeats']]  # fmt: skip
    if reduced:
        lines += ['', f'Fewer timed samples (cell budget, see --help) for: {", ".join(reduced)}.']
    clouds = '; '.join(
        f'N≈{int(s) // 1000}k: {c["clouds"].split(" (")[0]}, voxel {c["voxel"]:.3f} m, '
        f'{c["points"]["min"]}-{c["points"]["max"]} points'
        for s, c in doc['clouds'].items()
    )
    lines += ['', f'Clouds: {clouds}.']
    if doc.get('gicp_drift') is not None:
        lines.append(f"GICP's own median time varied by up to {doc['gicp_drift']['max']:.2f}× "
                     'between rounds (slowest / fastest round, over the sizes): the machine was '
                     'shared.')  # fmt: skip
    return '\n'.join(lines) + '\n'


def plot(doc: dict[str, Any], path: Path) -> None:
    """Log-log time per pair against N, and the ratio to GICP (failed cells circled)."""
    times, ratios = report.Panel(log='xy'), report.Panel(log='xy')
    for name, cells in doc['results'].items():
        sizes = sorted(cells, key=int)
        n = [doc['clouds'][s]['points']['median'] for s in sizes]
        lw = 2.2 if name.startswith('kentreg') or name == REFERENCE else 1.0
        failed = [i for i, s in enumerate(sizes) if cells[s]['n_failed']]
        for panel, key in ((times, 'total_ms'), (ratios, 'ratio_to_gicp')):
            y = [cells[s][key] for s in sizes]
            panel.add(name, n, y, marker=MARKERS.get(name, 'o'), lw=lw)
            if failed:
                circles = {'ls': 'none', 'marker': 'o', 'ms': 14, 'mfc': 'none', 'mec': 'red'}
                panel.add(None, [n[i] for i in failed], [y[i] for i in failed], **circles)
    times.axes = {'xlabel': 'points per cloud',
                  'ylabel': 'ms per pair (prepare source + register)',
                  'title': f'time per registration, {doc["threads"]} thread(s)'}  # fmt: skip
    ratios.axes = {'xlabel': 'points per cloud', 'ylabel': 'time / small_gicp GICP time',
                   'title': 'ratio to small_gicp GICP (same run)'}  # fmt: skip
    ratios.legend = {'fontsize': 8, 'loc': 'upper left', 'bbox_to_anchor': (1.01, 1.0)}
    report.plot_panels(path, [[times, ratios]], size=(13.5, 5))


OPTIONS: list[report.Option] = [
    ('--input', {'type': Path, 'default': datasets.SHARED_DATA / 'balm', 'metavar': 'FOLDER',
                 'help': 'raw scan folder with its pose file'}),
    ('--sizes', {'type': int, 'nargs': '+', 'default': list(SIZES), 'metavar': 'N'}),
    ('--methods', {'nargs': '+', 'default': list(LIBRARY_OF), 'choices': sorted(LIBRARY_OF),
                   'help': 'gicp is always included'}),
    ('--pairs', {'type': int, 'default': 5, 'help': 'pairs per size (default 5)'}),
    ('--repeats', {'type': int, 'default': 2, 'help': 'timed runs per pair (default 2)'}),
    ('--cell-budget', {'type': float, 'default': 30.0, 'metavar': 'S',
                       'help': 'seconds per method and size: fewer repeats for slower cells'}),
    ('--threads', {'type': int, 'default': 1, 'help': 'threads per library process'}),
    ('--rounds', {'type': int, 'default': 2, 'help': 'rotated rounds (default 2)'}),
    ('--data', {'type': Path, 'help': argparse.SUPPRESS}),
]  # fmt: skip


def run_libraries(
    doc: dict[str, Any], arrays: dict[str, Any], args: argparse.Namespace,
    libraries: dict[str, list[str]],
) -> dict[str, dict[str, list[Any]]]:  # fmt: skip
    """Every library's worker in rotated rounds; the samples per method and size."""
    samples: dict[str, dict[str, list[Any]]] = {}
    env = dict(os.environ) | {name: str(args.threads) for name in methods.THREAD_ENV}
    with tempfile.TemporaryDirectory(prefix='kentreg-speed-') as tmp:
        data = Path(tmp) / 'clouds.npz'
        np.savez(data, voxels=json.dumps({s: c['voxel'] for s, c in doc['clouds'].items()}),
                 **arrays)  # fmt: skip
        for r, library in runner.rotated(list(libraries), args.rounds):
            options = ['--data', str(data), '--methods', *libraries[library], '--threads',
                       str(args.threads), '--repeats', str(args.repeats), '--cell-budget',
                       str(args.cell_budget / args.rounds)]  # fmt: skip
            t0 = time.perf_counter()
            result = runner.in_subprocess(__file__, options, env=env)
            result['wall_s'] = time.perf_counter() - t0
            doc['workers'][f'{library}-round{r}'] = {k: result[k] for k in result if k != 'sizes'}
            said = result.get('error') or ' | '.join(result.get('stderr', [])) or 'done'
            print(f'[{library}] round {r}: {said}', file=sys.stderr)  # why a method is left out
            for size, cells in result.get('sizes', {}).items():
                for name, sample in cells.items():
                    samples.setdefault(name, {}).setdefault(size, []).append(sample)
    return samples


def summarize_results(doc: dict[str, Any], samples: dict[str, Any], names: list[str]) -> None:
    """Per method and size the cell summary, its ratio to GICP, and GICP's drift over rounds."""
    results = {name: {size: summarize_cell(cell) | {'library': cell[0]['library'],
                                                    'params': cell[0]['params']}
                      for size, cell in samples[name].items()}
               for name in names if name in samples}  # fmt: skip
    reference = results.get(REFERENCE, {})
    for cells in results.values():
        for size, cell in cells.items():
            ref = reference.get(size)
            cell['ratio_to_gicp'] = cell['total_ms'] / ref['total_ms'] if ref else None
            cell['register_ratio_to_gicp'] = (
                cell['register_ms'] / ref['register_ms'] if ref else None
            )
    per_round = {size: [float(np.median(np.add(c['prepare_ms'], c['register_ms']))) for c in cell]
                 for size, cell in samples.get(REFERENCE, {}).items()}  # fmt: skip
    drift = {size: max(t) / min(t) for size, t in per_round.items() if len(t) > 1}
    doc['gicp_drift'] = {'max': max(drift.values()), 'per_size': drift,
                         'measure': 'slowest / fastest round'} if drift else None  # fmt: skip
    doc['results'] = results


def run(args: argparse.Namespace, argv: list[str]) -> dict[str, Any]:
    if min(args.threads, args.pairs, args.repeats, args.rounds) < 1:
        raise SystemExit('--threads, --pairs, --repeats and --rounds must be >= 1')
    names = [REFERENCE] + [m for m in args.methods if m != REFERENCE]
    libraries: dict[str, list[str]] = {}
    for name in names:
        libraries.setdefault(LIBRARY_OF[name], []).append(name)
    t_start = time.perf_counter()
    seq = datasets.load_recording(args.input)
    arrays, clouds = build_clouds(seq, sorted(set(args.sizes)), args.pairs)
    doc: dict[str, Any] = {
        'benchmark': 'speed', 'command': ['python3', 'benchmarks/speed.py', *argv],
        'date': datetime.datetime.now().isoformat(timespec='seconds'),
        'machine': report.machine_info(), 'load_avg_at_start': list(os.getloadavg()),
        'threads': args.threads, 'pairs': args.pairs, 'repeats': args.repeats,
        'rounds': args.rounds, 'input': str(args.input), 'timing': TIMING,
        'cell_budget_s': args.cell_budget, 'clouds': clouds, 'workers': {},
    }  # fmt: skip
    summarize_results(doc, run_libraries(doc, arrays, args, libraries), names)
    doc['load_avg_at_end'] = list(os.getloadavg())
    doc['git_at_end'] = report.git_describe()
    doc['wall_s'] = time.perf_counter() - t_start
    return doc


if __name__ == '__main__':
    main = report.experiment_main
    raise SystemExit(main(__doc__, 'speed', OPTIONS, run, format_table, plot, worker=run_worker))
