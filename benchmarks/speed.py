"""Speed benchmark: time per registration against N points, one library per process.

Every method of :mod:`benchmarks.methods` (same downsampled clouds, same API, shared settings)
registers the same real pairs at N = 3k, 10k, 30k and 100k points. Reported per method and N:
the median time per pair of *source preparation* (what an odometry does once per new scan:
normals, covariances, KD-tree, grids, kentreg's ``prepare_scan``) plus *registration*, the two
parts separately, and the ratio to small_gicp GICP measured in the same run.

Clouds (from the real BALM scans, ``../shared/data/balm``: 72k-90k points each):

- N up to half the smallest raw scan (3k, 10k, 30k): each cloud is one raw scan, voxel-
  downsampled (voxel centroids, :func:`benchmarks.methods.voxel_downsample`) with one voxel edge
  per N: the median over the pairs' scans of the edge that gives about N points (bisection on
  :func:`kentreg_ros.core.scan.voxels.count_voxels`), so counts vary a little per scan.
- Larger N (100k, more than one scan holds): each cloud is a two-scan submap, scans ``k`` and
  ``k + 1`` merged into the frame of ``k`` with the reference poses (about 160k points), then
  downsampled the same way; the pairs join disjoint submaps (``k + 2, k + 3`` onto ``k, k + 1``).

Pairs: ``--pairs`` consecutive pairs spread evenly over the sequence. The initial guess is the
reference motion composed with a fixed error of 1 deg about a seeded random axis and 5 cm in a
seeded random direction (the same for every method): the size of a constant-velocity
prediction error of a 10 Hz LiDAR, inside every method's basin, so the benchmark times the
normal case of converging from an odometry prediction. (This sample is a 2 Hz hand-held
recording: its own constant-velocity prediction is off by up to 19 deg on single-scan pairs,
where the ICP family fails and runs to its iteration cap, which would time failures, not
registrations; robustness to that is what ``benchmarks/odometry.py`` measures.) The target of a
pair is prepared once, untimed (an odometry reuses the previous scan's preparation);
``--repeats`` times per pair the source is prepared and registered, timed, fewer when the
untimed warm-up pair shows that the cell would exceed ``--cell-budget`` seconds (the JSON records
the samples taken). Medians are over pairs x repeats. The pair errors of every method against the
reference are recorded, so a fast failure is visible.

Processes and threads: the main process builds the clouds once and saves them to a temporary
``.npz``; then every library runs in its own subprocess (``sys.executable`` running this file
with ``--worker``), one after the other, with ``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS`` and
``MKL_NUM_THREADS`` set to ``--threads`` (default 1) in its environment, its CPU affinity limited
to that many cores and the library's own thread argument set (:func:`benchmarks.methods.
make_methods`). The libraries run in ``--rounds`` rounds (default 2), each round in a rotated
order, and every cell pools its rounds' samples, so a change in the machine's load (other jobs)
does not land on one library only; the JSON records how much GICP's own time varied between
rounds.

Usage::

    python3 benchmarks/speed.py                       # all methods, 1 thread, ~10 min
    python3 benchmarks/speed.py --methods gicp kentreg_robust --sizes 10000 --pairs 3

Writes ``benchmarks/results/speed.json``, ``speed.md`` (table) and ``speed.png`` (log-log time
against N per method, and the ratio to GICP).
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.common import git_describe, machine_info  # noqa: E402
from kentreg_ros.eval.metrics import (  # noqa: E402
    FAIL_ROTATION_DEG,
    FAIL_TRANSLATION_M,
    failed_pairs,
)

logger = logging.getLogger('benchmarks.speed')

FloatArray = NDArray[np.float64]

DEFAULT_INPUT = ROOT.parent / 'shared' / 'data' / 'balm'
RESULTS = ROOT / 'benchmarks' / 'results'
SIZES = (3000, 10000, 30000, 100000)
REFERENCE = 'gicp'
#: Which library each method of :mod:`benchmarks.methods` loads (one process per library).
LIBRARY_OF = {
    'gicp': 'small_gicp',
    'icp_pt2pt': 'open3d',
    'icp_pt2pl': 'open3d',
    'kiss_icp': 'kiss_icp',
    'ndt': 'baseline',
    'cicp': 'baseline',
    'kentreg_robust': 'kentreg',
    'kentreg_paper': 'kentreg',
}
DEFAULT_METHODS = (
    'gicp',
    'icp_pt2pt',
    'icp_pt2pl',
    'kiss_icp',
    'ndt',
    'cicp',
    'kentreg_robust',
    'kentreg_paper',
)
THREAD_ENV = ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS')
#: Largest N built from single scans, as a fraction of the smallest raw scan.
SINGLE_SCAN_FRACTION = 0.5
#: Error of the initial guess: rotation (deg) about a random axis, translation (m).
INIT_ERROR_DEG = 1.0
INIT_ERROR_M = 0.05
#: A worker gets this long before it is stopped (its library is then reported as timed out).
WORKER_TIMEOUT_S = 1800.0
MARKERS = {
    'gicp': 'o',
    'icp_pt2pt': 'v',
    'icp_pt2pl': '^',
    'kiss_icp': 'D',
    'ndt': 'x',
    'cicp': '+',
    'kentreg_robust': 's',
    'kentreg_paper': 'P',
}


# --------------------------------------------------------------------------------------------
# Inputs (main process)


def _scan_files(folder: Path) -> tuple[list[Path], Path]:
    from kentreg_ros.io.poses import POSE_FILES_BESIDE_SCANS, pose_file_beside
    from kentreg_ros.io.scanfiles import list_scans

    if not folder.is_dir():
        raise SystemExit(f'{folder}: no such folder (the raw BALM scans, see --help)')
    poses = pose_file_beside(folder)
    if poses is None:
        raise SystemExit(f'{folder}: no pose file ({", ".join(POSE_FILES_BESIDE_SCANS)})')
    return list_scans(folder), poses


def pair_starts(n_scans: int, n_pairs: int, span: int) -> list[int]:
    """First scans ``k`` of ``n_pairs`` pairs spread over the sequence.

    Each pair needs scans ``k`` to ``k + 2 span - 1``.
    """
    first, last = 0, n_scans - 2 * span
    if last < first:
        raise SystemExit(f'need at least {2 * span} scans, got {n_scans}')
    starts = np.unique(np.linspace(first, last, n_pairs).round().astype(int))
    return [int(k) for k in starts]


def voxel_for_count(points: FloatArray, count: int, *, iterations: int = 24) -> float:
    """Voxel edge whose downsampling keeps about ``count`` points (bisection in log size).

    The occupied-voxel count falls monotonically (up to grid-alignment noise) with the edge, so
    bisection converges where kentreg's few-step secant search (which assumes surface scaling,
    ``count ~ size**-2``) stops short near the raw density.
    """
    from kentreg_ros.core import count_voxels

    if count >= len(points):
        raise SystemExit(f'cannot keep {count} of {len(points)} points by downsampling')
    lo, hi = np.log(1e-3), np.log(10.0)
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        if count_voxels(points, float(np.exp(mid))) > count:
            lo = mid
        else:
            hi = mid
    return float(np.exp(0.5 * (lo + hi)))


def perturbation(rng: np.random.Generator) -> FloatArray:
    """A 4x4 error of :data:`INIT_ERROR_DEG` about a random axis, :data:`INIT_ERROR_M` along a
    random direction."""
    from scipy.spatial.transform import Rotation

    axis, direction = rng.normal(size=(2, 3))
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(
        np.radians(INIT_ERROR_DEG) * axis / np.linalg.norm(axis)
    ).as_matrix()
    T[:3, 3] = INIT_ERROR_M * direction / np.linalg.norm(direction)
    return T


def build_clouds(
    folder: Path, sizes: Sequence[int], n_pairs: int, *, seed: int = 0
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The downsampled clouds, initial guesses and reference motions of every size.

    Returns
    -------
    arrays : dict
        ``'n{N}_source_{i}'``, ``'n{N}_target_{i}'`` (M, 3) clouds, ``'n{N}_init'`` and
        ``'n{N}_reference'`` (P, 4, 4) for the ``P`` pairs of size ``N``.
    info : dict
        Per size: how the clouds were made, the voxel edge, the scans used, point counts.
    """
    from benchmarks.methods import voxel_downsample
    from kentreg_ros.eval.groundtruth import GroundTruth
    from kentreg_ros.io.poses import read_poses
    from kentreg_ros.io.scanfiles import read_scan

    files, pose_file = _scan_files(folder)
    T_world = GroundTruth(read_poses(pose_file), str(pose_file)).trajectory.T_world_sensor
    T_world = np.asarray(T_world, dtype=np.float64)[: len(files)]
    cache: dict[int, FloatArray] = {}

    def raw(k: int) -> FloatArray:
        if k not in cache:
            cache[k] = np.asarray(read_scan(files[k], fields=()).points, dtype=np.float64)
        return cache[k]

    def relative(a: int, b: int) -> FloatArray:
        return np.asarray(np.linalg.inv(T_world[a]) @ T_world[b], dtype=np.float64)

    def submap(k: int) -> FloatArray:
        T = relative(k, k + 1)
        return np.vstack([raw(k), raw(k + 1) @ T[:3, :3].T + T[:3, 3]])

    smallest = min(len(raw(k)) for k in pair_starts(len(files), n_pairs, 1))
    rng = np.random.default_rng(seed)
    arrays: dict[str, Any] = {}
    info: dict[str, Any] = {}
    for size in sizes:
        single = size <= SINGLE_SCAN_FRACTION * smallest
        span = 1 if single else 2
        cloud_of = raw if single else submap
        starts = pair_starts(len(files), n_pairs, span)
        # One edge for every cloud of this size: the median of the edges that give N points.
        voxel = float(np.median([voxel_for_count(cloud_of(k), size) for k in starts]))
        counts = []
        inits, refs = [], []
        for i, k in enumerate(starts):
            target = voxel_downsample(cloud_of(k), voxel)
            source = voxel_downsample(cloud_of(k + span), voxel)
            arrays[f'n{size}_target_{i}'] = target
            arrays[f'n{size}_source_{i}'] = source
            counts += [len(source), len(target)]
            refs.append(relative(k, k + span))
            inits.append(refs[-1] @ perturbation(rng))
        arrays[f'n{size}_init'] = np.stack(inits)
        arrays[f'n{size}_reference'] = np.stack(refs)
        info[str(size)] = {
            'clouds': 'one raw scan'
            if single
            else 'two-scan submap (scans k, k+1 merged in the frame of k by the reference poses)',
            'voxel': voxel,
            'pairs': [[k + span, k] for k in starts],
            'points': {
                'min': int(min(counts)),
                'median': float(np.median(counts)),
                'max': int(max(counts)),
            },
            'init': f'reference motion x error of {INIT_ERROR_DEG:g} deg, {INIT_ERROR_M:g} m '
            f'(random axis and direction, seed {seed})',
        }
    return arrays, info


# --------------------------------------------------------------------------------------------
# Worker (one library per process)


def _pair_error(T_est: FloatArray, T_ref: FloatArray) -> tuple[float, float]:
    from kentreg_ros.eval.metrics import pair_errors

    e_R, e_t = pair_errors(T_est[None], T_ref[None])
    return float(e_R[0]), float(e_t[0])


def run_worker(
    data_path: Path, methods: Sequence[str], threads: int, repeats: int, cell_budget_s: float
) -> dict[str, Any]:
    """Time every method of one library on every size of the saved clouds."""
    from benchmarks.methods import make_methods

    data = np.load(data_path)
    voxels = json.loads(str(data['voxels']))
    out: dict[str, Any] = {'pid': os.getpid(), 'affinity': [], 'env': {}, 'sizes': {}}
    for size, voxel in voxels.items():
        built = make_methods(list(methods), voxel=voxel, threads=threads)
        out['affinity'] = sorted(os.sched_getaffinity(0))
        out['env'] = {name: os.environ.get(name) for name in THREAD_ENV}
        inits = data[f'n{size}_init']
        refs = data[f'n{size}_reference']
        sources = [data[f'n{size}_source_{i}'] for i in range(len(inits))]
        targets = [data[f'n{size}_target_{i}'] for i in range(len(inits))]
        per_method: dict[str, Any] = {}
        for method in built:
            # Warm-up: imports, allocators, caches; not timed, but it sizes the repeats.
            t0 = time.perf_counter()
            method.register(method.prepare(sources[0]), method.prepare(targets[0]), inits[0])
            warm_s = time.perf_counter() - t0
            n_repeats = int(np.clip(cell_budget_s // (warm_s * len(inits)), 1, repeats))
            prep_ms, reg_ms, errors = [], [], []
            for i in range(len(inits)):
                target = method.prepare(targets[i])
                for _ in range(n_repeats):
                    t0 = time.perf_counter()
                    source = method.prepare(sources[i])
                    t1 = time.perf_counter()
                    T = method.register(source, target, inits[i])
                    t2 = time.perf_counter()
                    prep_ms.append((t1 - t0) * 1e3)
                    reg_ms.append((t2 - t1) * 1e3)
                errors.append(_pair_error(np.asarray(T, dtype=np.float64), refs[i]))
            per_method[method.name] = {
                'library': method.library,
                'params': dict(method.params),
                'repeats': n_repeats,
                'prepare_ms': prep_ms,
                'register_ms': reg_ms,
                'e_R_deg': [e[0] for e in errors],
                'e_t_m': [e[1] for e in errors],
            }
        out['sizes'][size] = per_method
    return out


# --------------------------------------------------------------------------------------------
# Aggregation and outputs (main process)


def summarize_cell(samples: list[dict[str, Any]]) -> dict[str, Any]:
    """Medians of one method at one size, over every pair, repeat and round of ``samples``.

    The pair errors are those of the first round (the same pairs again in later rounds).
    """
    prep = np.concatenate([s['prepare_ms'] for s in samples])
    reg = np.concatenate([s['register_ms'] for s in samples])
    e_R = np.asarray(samples[0]['e_R_deg'])
    e_t = np.asarray(samples[0]['e_t_m'])
    return {
        'n_samples': int(prep.size),
        'n_rounds': len(samples),
        'total_ms': float(np.median(prep + reg)),
        'prepare_ms': float(np.median(prep)),
        'register_ms': float(np.median(reg)),
        'total_ms_p90': float(np.percentile(prep + reg, 90)),
        'median_e_R_deg': float(np.median(e_R)),
        'max_e_R_deg': float(np.max(e_R)),
        'median_e_t_m': float(np.median(e_t)),
        'max_e_t_m': float(np.max(e_t)),
        'n_failed': int(np.sum(failed_pairs(e_R, e_t))),
        'n_pairs': int(e_R.size),
    }


def format_table(report: dict[str, Any]) -> str:
    """Markdown: median ms per pair (prepare + register) and the ratio to GICP, per N."""
    sizes = list(report['clouds'])
    results = report['results']
    head = ' | '.join(f'N≈{int(s) // 1000}k' for s in sizes)
    lines = [
        f'Median ms per pair (source preparation + registration) and ratio to small_gicp GICP; '
        f'{report["threads"]} thread(s), {report["pairs"]} pairs x {report["repeats"]} repeats '
        f'x {report["rounds"]} rounds per cell; failures (e_R > {FAIL_ROTATION_DEG:g} deg or '
        f'e_t > {FAIL_TRANSLATION_M:g} m) out of '
        f'{report["pairs"]} pairs.',
        '',
        f'| method | {head} |',
        '|---|' + '---|' * len(sizes),
    ]
    for name, cells in results.items():
        row = []
        for s in sizes:
            cell = cells.get(s)
            if cell is None:
                row.append('-')
                continue
            fail = f', {cell["n_failed"]} failed' if cell['n_failed'] else ''
            row.append(f'{cell["total_ms"]:.1f} ms ({cell["ratio_to_gicp"]:.2f}×{fail})')
        lines.append(f'| {name} | ' + ' | '.join(row) + ' |')
    lines += [
        '',
        'The two parts, median ms: source preparation / registration.',
        '',
        f'| method | {head} |',
        '|---|' + '---|' * len(sizes),
    ]
    for name, cells in results.items():
        row = [
            f'{cells[s]["prepare_ms"]:.1f} / {cells[s]["register_ms"]:.1f}' if s in cells else '-'
            for s in sizes
        ]
        lines.append(f'| {name} | ' + ' | '.join(row) + ' |')
    reduced = [
        f'{name} N≈{int(s) // 1000}k ({c["n_samples"]})'
        for name, cells in results.items()
        for s, c in cells.items()
        if c['n_samples'] < c['n_pairs'] * c['n_rounds'] * report['repeats']
    ]
    if reduced:
        lines += [
            '',
            'Fewer timed samples (cell budget, see --help) for: ' + ', '.join(reduced) + '.',
        ]
    clouds = report['clouds']
    lines += [
        '',
        'Clouds: '
        + '; '.join(
            f'N≈{int(s) // 1000}k: {c["clouds"].split(" (")[0]}, voxel {c["voxel"]:.3f} m, '
            f'{c["points"]["min"]}-{c["points"]["max"]} points'
            for s, c in clouds.items()
        )
        + '.',
    ]
    if report.get('gicp_drift') is not None:
        lines.append(
            f"GICP's own median time varied by up to "
            f'{report["gicp_drift"]["max"]:.2f}× between rounds (slowest / fastest round, over '
            'the sizes): the machine was shared.'
        )
    return '\n'.join(lines) + '\n'


def plot(path: Path, report: dict[str, Any]) -> None:
    """Log-log time per pair against N, and the ratio to GICP."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(13.5, 5), layout='constrained')
    FigureCanvasAgg(fig)
    ax_t, ax_r = fig.subplots(1, 2)
    failed_label_owner = next(
        (
            name
            for name, cells in report['results'].items()
            if any(c['n_failed'] for c in cells.values())
        ),
        None,
    )
    for name, cells in report['results'].items():
        sizes = sorted(cells, key=int)
        n = [report['clouds'][s]['points']['median'] for s in sizes]
        total = [cells[s]['total_ms'] for s in sizes]
        ratio = [cells[s]['ratio_to_gicp'] for s in sizes]
        style = {'marker': MARKERS.get(name, 'o'), 'label': name}
        lw = 2.2 if name.startswith('kentreg') or name == REFERENCE else 1.0
        ax_t.loglog(n, total, lw=lw, **style)
        ax_r.semilogx(n, ratio, lw=lw, **style)
        failed = [i for i, s in enumerate(sizes) if cells[s]['n_failed']]
        for ax, values in ((ax_t, total), (ax_r, ratio)):
            ax.scatter(
                [n[i] for i in failed],
                [values[i] for i in failed],
                s=160,
                facecolors='none',
                edgecolors='red',
                zorder=3,
                label='some pairs failed' if name == failed_label_owner else None,
            )
    ax_t.set(xlabel='points per cloud', ylabel='ms per pair (prepare source + register)', title='')
    ax_t.set_title(f'time per registration, {report["threads"]} thread(s)')
    ax_r.axhline(1.5, color='red', ls='--', lw=0.8, label='goal: 1.5× GICP')
    ax_r.set_yscale('log')
    ax_r.set(xlabel='points per cloud', ylabel='time / small_gicp GICP time')
    ax_r.set_title('ratio to small_gicp GICP (same run)')
    for ax in (ax_t, ax_r):
        ax.grid(True, which='both', alpha=0.3)
    ax_r.legend(fontsize=8, loc='upper left', bbox_to_anchor=(1.01, 1.0))
    fig.savefig(path, dpi=100)


def run_library(
    library: str,
    methods: Sequence[str],
    data_path: Path,
    args: argparse.Namespace,
    tmp: Path,
    tag: str,
) -> dict[str, Any]:
    """Run one library's worker process; its parsed result, or an ``error`` entry."""
    result_path = tmp / f'{library}-{tag}.json'
    env = dict(os.environ)
    env.update({name: str(args.threads) for name in THREAD_ENV})
    cmd = [
        sys.executable,
        str(Path(__file__).resolve()),
        '--worker',
        str(result_path),
        '--data',
        str(data_path),
        '--methods',
        *methods,
        '--threads',
        str(args.threads),
        '--repeats',
        str(args.repeats),
        '--cell-budget',
        str(args.cell_budget / args.rounds),
    ]
    t0 = time.perf_counter()
    print(f'[{library}] {" ".join(methods)} ...', file=sys.stderr, flush=True)
    try:
        proc = subprocess.run(
            cmd, env=env, capture_output=True, text=True, timeout=WORKER_TIMEOUT_S, check=False
        )
    except subprocess.TimeoutExpired:
        return {'error': f'timed out after {WORKER_TIMEOUT_S:.0f} s'}
    wall = time.perf_counter() - t0
    print(f'[{library}] done in {wall:.0f} s', file=sys.stderr, flush=True)
    if proc.returncode != 0 or not result_path.is_file():
        tail = proc.stderr.strip().splitlines()[-1:] or ['no output']
        return {'error': f'exit {proc.returncode}: {tail[0]}'}
    result: dict[str, Any] = json.loads(result_path.read_text())
    result['wall_s'] = wall
    if proc.stderr.strip():
        result['stderr'] = proc.stderr.strip().splitlines()[-5:]
    return result


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        '--input',
        type=Path,
        default=DEFAULT_INPUT,
        metavar='FOLDER',
        help='raw scan folder with its pose file (default ../shared/data/balm)',
    )
    parser.add_argument(
        '--sizes',
        type=int,
        nargs='+',
        default=list(SIZES),
        metavar='N',
        help='points per cloud (default 3000 10000 30000 100000)',
    )
    parser.add_argument(
        '--methods',
        nargs='+',
        default=list(DEFAULT_METHODS),
        choices=sorted(LIBRARY_OF),
        help='methods to time (gicp is always included: it is the reference)',
    )
    parser.add_argument('--pairs', type=int, default=5, help='pairs per size (default 5)')
    parser.add_argument('--repeats', type=int, default=2, help='timed runs per pair (default 2)')
    parser.add_argument(
        '--cell-budget',
        type=float,
        default=30.0,
        metavar='S',
        help='seconds per method and size: fewer repeats (at least 1) for slower cells '
        '(default 30)',
    )
    parser.add_argument(
        '--threads', type=int, default=1, help='threads per library process (default 1)'
    )
    parser.add_argument(
        '--rounds',
        type=int,
        default=2,
        help='rounds over the libraries, in rotated order, pooled (default 2)',
    )
    parser.add_argument(
        '--out',
        type=Path,
        default=RESULTS,
        help='folder for speed.json/.md/.png (default benchmarks/results)',
    )
    parser.add_argument('--worker', type=Path, help=argparse.SUPPRESS)
    parser.add_argument('--data', type=Path, help=argparse.SUPPRESS)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format='%(name)s: %(levelname)s: %(message)s')
    if min(args.threads, args.pairs, args.repeats, args.rounds) < 1:
        raise SystemExit('--threads, --pairs, --repeats and --rounds must be >= 1')
    if args.worker is not None:
        result = run_worker(args.data, args.methods, args.threads, args.repeats, args.cell_budget)
        args.worker.write_text(json.dumps(result))
        return 0

    methods = [REFERENCE] + [m for m in args.methods if m != REFERENCE]
    libraries: dict[str, list[str]] = {}
    for name in methods:
        libraries.setdefault(LIBRARY_OF[name], []).append(name)
    t_start = time.perf_counter()
    arrays, clouds = build_clouds(args.input, sorted(set(args.sizes)), args.pairs)
    report: dict[str, Any] = {
        'benchmark': 'speed',
        'command': ['python3', 'benchmarks/speed.py', *argv],
        'date': datetime.datetime.now().isoformat(timespec='seconds'),
        'machine': machine_info(),
        'load_avg_at_start': list(os.getloadavg()),
        'threads': args.threads,
        'pairs': args.pairs,
        'repeats': args.repeats,
        'rounds': args.rounds,
        'input': str(args.input),
        'timing': 'per pair: prepare(source) + register(source, target, init), target prepared '
        'once untimed; median over pairs x repeats (fewer repeats when a cell would exceed '
        '--cell-budget) after one untimed warm-up pair per method and size; input clouds '
        'already voxel-downsampled (the downsampling is not timed)',
        'cell_budget_s': args.cell_budget,
        'clouds': clouds,
        'workers': {},
    }
    samples: dict[str, dict[str, list[dict[str, Any]]]] = {}
    with tempfile.TemporaryDirectory(prefix='kentreg-speed-') as tmp_name:
        tmp = Path(tmp_name)
        data_path = tmp / 'clouds.npz'
        voxels = {size: info['voxel'] for size, info in clouds.items()}
        np.savez(data_path, voxels=json.dumps(voxels), **arrays)
        groups = list(libraries.items())
        order = [
            (library, names, f'round{r}')
            for r in range(args.rounds)
            for library, names in groups[r % len(groups) :] + groups[: r % len(groups)]
        ]
        for library, names, tag in order:
            result = run_library(library, names, data_path, args, tmp, tag)
            report['workers'][f'{library}-{tag}'] = {
                k: v for k, v in result.items() if k != 'sizes'
            }
            if 'error' in result:
                logger.error('%s: %s', library, result['error'])
                continue
            for size, per_method in result['sizes'].items():
                for name, sample in per_method.items():
                    samples.setdefault(name, {}).setdefault(size, []).append(sample)
    results: dict[str, dict[str, Any]] = {}
    for name in methods:
        if name not in samples:
            continue
        results[name] = {
            size: summarize_cell(cell)
            | {'library': cell[0]['library'], 'params': cell[0]['params']}
            for size, cell in samples[name].items()
        }
    reference = results.get(REFERENCE, {})
    for cells in results.values():
        for size, cell in cells.items():
            ref = reference.get(size)
            cell['ratio_to_gicp'] = cell['total_ms'] / ref['total_ms'] if ref else None
            cell['register_ratio_to_gicp'] = (
                cell['register_ms'] / ref['register_ms'] if ref else None
            )
    ref_samples = samples.get(REFERENCE, {})
    drift = {}
    for size, cell in ref_samples.items():
        per_round = [float(np.median(np.add(c['prepare_ms'], c['register_ms']))) for c in cell]
        if len(per_round) > 1:
            drift[size] = max(per_round) / min(per_round)
    report['gicp_drift'] = (
        {'max': max(drift.values()), 'per_size': drift, 'measure': 'slowest / fastest round'}
        if drift
        else None
    )
    report['results'] = results
    report['load_avg_at_end'] = list(os.getloadavg())
    report['git_at_end'] = git_describe()
    if report['git_at_end'] != report['machine']['git']:
        logger.warning(
            'The checkout changed during the run (%s -> %s): rerun for consistent numbers.',
            report['machine']['git'],
            report['git_at_end'],
        )
    report['wall_s'] = time.perf_counter() - t_start
    args.out.mkdir(parents=True, exist_ok=True)
    table = format_table(report)
    (args.out / 'speed.md').write_text(table)
    (args.out / 'speed.json').write_text(json.dumps(report, indent=1) + '\n')
    plot(args.out / 'speed.png', report)
    print(table)
    print(f'wrote {args.out}/speed.json, speed.md, speed.png ({report["wall_s"]:.0f} s)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
