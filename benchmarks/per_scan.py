"""Per-scan odometry cost: raw scan in, pose out, previous scan cached; one thread per method.

What a live node pays for every scan of a spinning LiDAR. Each method runs as its own scan-to-
previous-scan odometry over the same raw scans (``../shared/data/balm``: 72k-90k points, or
``bags/balm_50`` when the shared data are absent) in its own subprocess, pinned to one CPU
(:func:`benchmarks.methods.limit_threads`) with the library's own thread count set to 1:

``kentreg``
    ``kentreg_ros.core.odometry.loop.Odometry(KentRegConfig())`` as is: automatic voxel size,
    normals, clusters, the registration from the constant-velocity prediction, and the start-free
    search whenever a step is doubtful (its cost is in the scans that needed it).
``kentreg_numpy``
    The same without the compiled kernels (``KENTREG_NO_JIT=1``, numpy only; the same
    results): what the ``fast`` extra's numba pays, in time and memory.
``gicp``
    small_gicp: ``preprocess_points`` on the raw scan (its own voxel grid at 0.25 m, 10
    covariance neighbours, KD-tree), ``align`` (GICP) to the cached previous scan from the
    constant-velocity prediction.
``icp_pt2pl``
    Open3D: ``voxel_down_sample`` (0.25 m), normals from 15 neighbours, KD-tree, point-to-plane
    ``registration_icp`` (gate 1 m) from the constant-velocity prediction.
``kiss_icp``
    KISS-ICP's own odometry pipeline (``KissICP.register_frame``, default configuration for the
    sensor's range): its voxel grid, adaptive threshold, constant-velocity model and local map.

Reported per method: p50 / p95 / max of the wall time per scan (the first scan, which only
prepares, excluded), the process's resident memory once the method is set up (its libraries
imported, kentreg's compiled kernels loaded, the scan file opened) and at its peak, the growth
of the peak over the run (what the method itself keeps and allocates), and the pair errors
against the
reference poses (median e_R / e_t and failures, e_R > 2 deg or e_t > 0.2 m). Ratios to GICP come
from the same run; the methods run in ``--rounds`` rounds in rotated order and the JSON keeps
every round, so a load change on the shared machine does not land on one method only.

Usage::

    python3 benchmarks/per_scan.py                    # all methods, 2 rounds, ~5 min
    python3 benchmarks/per_scan.py --methods kentreg gicp --scans 20

Writes ``benchmarks/results/per_scan.json`` and ``per_scan.md`` (``per_scan_merge<K>.*`` with
``--merge K``: denser scans, each joined with its predecessors by the reference poses).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
import tracemalloc
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.common import (  # noqa: E402
    RESULTS,
    SHARED_DATA,
    errors,
    git_describe,
    is_failure,
    load_balm,
    machine_info,
    write_json,
)
from kentreg_ros.core import invert_transform  # noqa: E402

FloatArray = NDArray[np.float64]
logger = logging.getLogger('per_scan')

METHODS = ('kentreg', 'kentreg_numpy', 'gicp', 'icp_pt2pl', 'kiss_icp')
#: The peers' voxel edge on BALM (the edge giving ~10k points on a raw scan, as in the other
#: benchmarks) and their neighbour counts (small_gicp's and Open3D's usual values).
PEER_VOXEL = 0.25
GICP_NEIGHBORS = 10
NORMAL_NEIGHBORS = 15
PEER_GATE = 1.0
PERIOD_NS = 500_000_000  # BALM is a 2 Hz recording; stamps only feed the velocity models
#: Steps of the memory run: the 50 scans forth and back nine times. Resident memory still grows
#: for the first ~200 steps (the allocator settling: 103 -> 108.6 MB for kentreg), then stays
#: within a few hundred kB; the growth is measured over the second half.
LONG_STEPS = 450


def _kentreg() -> Callable[[FloatArray, int], FloatArray]:
    from kentreg_ros.core import KentRegConfig, Odometry

    odometry = Odometry(KentRegConfig(), max_history=2)

    def step(points: FloatArray, stamp_ns: int) -> FloatArray:
        return np.asarray(odometry.step(points, stamp_ns).T_world_lidar)

    return step


def _chained(
    prepare: Callable[[FloatArray], Any], align: Callable[[Any, Any, FloatArray], FloatArray]
) -> Callable[[FloatArray, int], FloatArray]:
    """Scan-to-previous-scan odometry from a prepare/align pair, constant-velocity start."""
    state: dict[str, Any] = {'prev': None, 'pose': np.eye(4), 'motion': np.eye(4)}

    def step(points: FloatArray, stamp_ns: int) -> FloatArray:
        scan = prepare(points)
        if state['prev'] is not None:
            motion = align(scan, state['prev'], state['motion'])
            state['motion'] = motion
            state['pose'] = state['pose'] @ motion
        state['prev'] = scan
        return np.array(state['pose'])

    return step


def _gicp() -> Callable[[FloatArray, int], FloatArray]:
    import small_gicp

    def prepare(points: FloatArray) -> Any:
        return small_gicp.preprocess_points(
            points, downsampling_resolution=PEER_VOXEL, num_neighbors=GICP_NEIGHBORS, num_threads=1
        )

    def align(source: Any, target: Any, init: FloatArray) -> FloatArray:
        result = small_gicp.align(
            target[0], source[0], target[1], init_T_target_source=init, num_threads=1
        )
        return np.array(result.T_target_source)

    return _chained(prepare, align)


def _icp_pt2pl() -> Callable[[FloatArray, int], FloatArray]:
    import open3d as o3d

    o3d.utility.set_max_threads(1)
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    reg = o3d.pipelines.registration

    def prepare(points: FloatArray) -> Any:
        pcd = o3d.geometry.PointCloud()
        pcd.points = o3d.utility.Vector3dVector(points)
        pcd = pcd.voxel_down_sample(PEER_VOXEL)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(NORMAL_NEIGHBORS))
        return pcd

    def align(source: Any, target: Any, init: FloatArray) -> FloatArray:
        result = reg.registration_icp(
            source, target, PEER_GATE, init, reg.TransformationEstimationPointToPlane()
        )
        return np.array(result.transformation)

    return _chained(prepare, align)


def _kiss_icp() -> Callable[[FloatArray, int], FloatArray]:
    from kiss_icp.config import load_config
    from kiss_icp.kiss_icp import KissICP

    config = load_config(None)
    config.registration.max_num_threads = 1
    pipeline = KissICP(config)

    def step(points: FloatArray, stamp_ns: int) -> FloatArray:
        pipeline.register_frame(points, np.zeros(0))  # no per-point times: no deskewing
        return np.array(pipeline.last_pose)

    return step


def _kentreg_numpy() -> Callable[[FloatArray, int], FloatArray]:
    from kentreg_ros.core import kernels

    os.environ[kernels.DISABLE_ENV] = '1'  # this worker process only
    return _kentreg()


FACTORIES: dict[str, Callable[[], Callable[[FloatArray, int], FloatArray]]] = {
    'kentreg': _kentreg,
    'kentreg_numpy': _kentreg_numpy,
    'gicp': _gicp,
    'icp_pt2pl': _icp_pt2pl,
    'kiss_icp': _kiss_icp,
}


def _forth_and_back(n: int, steps: int) -> list[int]:
    """Scan indices 0..n-1, then back n-1..0, and so on, ``steps`` of them: a long run with
    no jump between consecutive scans."""
    cycle = list(range(n)) + list(range(n - 1, -1, -1))
    return [cycle[k % len(cycle)] for k in range(steps)]


def run_worker(method: str, scans_file: Path, out_file: Path, steps: int = 0) -> None:
    """Run one method over the scans (this process is pinned to one CPU by the caller);
    ``steps`` > 0: that many steps over the scans forth and back (a long run, for memory)."""
    from benchmarks.methods import limit_threads

    limit_threads(1)
    data = np.load(scans_file)  # an NpzFile: each scan is read when it is used
    n = int(data['n'])
    step = FACTORIES[method]()
    base_mb = _rss_mb('VmRSS')
    _reset_peak_rss()
    if steps > 0:  # the memory run: numpy's and Python's live memory, exactly (not timed)
        tracemalloc.start()
    poses, ms, rss, traced = [], [], [], []
    for k, i in enumerate(_forth_and_back(n, steps) if steps > 0 else range(n)):
        points = np.ascontiguousarray(data[f's{i}'], dtype=np.float64)
        t0 = time.perf_counter()
        poses.append(step(points, k * PERIOD_NS))
        ms.append((time.perf_counter() - t0) * 1e3)
        rss.append(_rss_mb('VmRSS'))
        if steps > 0:
            traced.append(tracemalloc.get_traced_memory()[0] / 2**20)
    peak_mb = _rss_mb('VmHWM')
    out_file.write_text(
        json.dumps(
            {
                'ms': ms,
                'poses': np.array(poses).tolist(),
                'start_rss_mb': base_mb,
                'peak_rss_mb': peak_mb,
                'peak_growth_mb': peak_mb - base_mb,
                'rss_mb': rss,
                'traced_mb': traced,
            }
        )
    )


def _rss_mb(key: str) -> float:
    """Resident memory of this process from /proc/self/status (VmRSS now, VmHWM its peak)."""
    for line in Path('/proc/self/status').read_text().splitlines():
        if line.startswith(key + ':'):
            return float(line.split()[1]) / 1024.0
    return float('nan')


def _reset_peak_rss() -> None:
    """Reset VmHWM to the current RSS (Linux: '5' to /proc/self/clear_refs), so the peak is
    the method's own over the run, not the imports' or the loader's."""
    try:
        Path('/proc/self/clear_refs').write_text('5')
    except OSError:
        pass


def summarize(ms: list[float], poses: FloatArray, truth: FloatArray) -> dict[str, Any]:
    per_scan = np.array(ms[1:])  # the first scan only prepares
    e = [
        errors(
            invert_transform(poses[i - 1]) @ poses[i], invert_transform(truth[i - 1]) @ truth[i]
        )
        for i in range(1, len(poses))
    ]
    e_R = np.array([a for a, _ in e])
    e_t = np.array([b for _, b in e])
    return {
        'ms_per_scan': {
            'p50': float(np.percentile(per_scan, 50)),
            'p95': float(np.percentile(per_scan, 95)),
            'max': float(per_scan.max()),
            'mean': float(per_scan.mean()),
        },
        'e_R_deg_median': float(np.median(e_R)),
        'e_t_m_median': float(np.median(e_t)),
        'failures': int(sum(is_failure(a, b) for a, b in zip(e_R, e_t, strict=True))),
        'n_pairs': len(e_R),
    }


def markdown(report: dict[str, Any]) -> str:
    meta = report['meta']
    base = report['methods'].get('gicp', {}).get('ms_per_scan', {}).get('p50')
    lines = [
        f'Per-scan odometry on {meta["n_scans"]} raw BALM scans ({meta["points"]}'
        + (
            f'; each joined with its {meta["merge"] - 1} predecessor(s) by the reference poses'
            if meta.get('merge', 1) > 1
            else ''
        )
        + '), one thread '
        f'per method, {meta["rounds"]} rounds; the first scan (prepare only) excluded.',
        '',
        '| method | p50 ms/scan | p95 | max | ratio to GICP (p50) '
        '| resident MB once started / peak | peak memory growth MB '
        f'| memory growth over the second half of {meta.get("long_steps") or "–"} steps MB: '
        'live numpy/Python (tracemalloc) / resident '
        '| median e_R (deg) | median e_t (mm) | failed pairs |',
        '|---|---|---|---|---|---|---|---|---|---|---|',
    ]
    for name, r in report['methods'].items():
        t = r['ms_per_scan']
        start = r.get('start_rss_mb')
        resident = f'{start:.0f} / {r["peak_rss_mb"]:.0f}' if start is not None else '–'
        ratio = f'{t["p50"] / base:.2f}×' if base else '–'
        lr = r.get('long_run')
        growth = f'{lr["growth_mb"]:.2f} / {lr["rss_growth_mb"]:.1f}' if lr else '–'
        lines.append(
            f'| {name} | {t["p50"]:.1f} | {t["p95"]:.1f} | {t["max"]:.1f} | {ratio} '
            f'| {resident} | {r["peak_growth_mb"]:.0f} | {growth} | {r["e_R_deg_median"]:.3f} '
            f'| {1e3 * r["e_t_m_median"]:.1f} | {r["failures"]}/{r["n_pairs"]} |'
        )
    lines += ['', f'Run at {meta["git"]}; load average {meta["load"]} at the start.', '']
    return '\n'.join(lines)


def merge_scans(
    scans: list[FloatArray], T_world_sensor: FloatArray, k: int
) -> tuple[list[FloatArray], FloatArray]:
    """Scan ``i`` joined with scans ``i-k+1 .. i-1`` moved into its sensor frame by the
    reference poses (from scan ``k-1`` on): denser real scans, as a sensor with more beams
    would return, with the same motion between them."""
    out = []
    for i in range(k - 1, len(scans)):
        inv = np.linalg.inv(T_world_sensor[i])
        parts = [scans[i]]
        for j in range(i - k + 1, i):
            T = inv @ T_world_sensor[j]
            parts.append(scans[j] @ T[:3, :3].T + T[:3, 3])
        out.append(np.ascontiguousarray(np.vstack(parts)))
    return out, T_world_sensor[k - 1 :]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--methods', nargs='+', default=list(METHODS), choices=METHODS)
    parser.add_argument('--scans', type=int, default=50, help='scans from the start (>= 2)')
    parser.add_argument('--rounds', type=int, default=2)
    parser.add_argument('--out', type=Path, default=RESULTS)
    parser.add_argument(
        '--long-steps',
        type=int,
        default=LONG_STEPS,
        help='steps of the memory run per method (the scans forth and back; 0: none)',
    )
    parser.add_argument(
        '--merge',
        type=int,
        default=1,
        help='denser scans: each scan joined with its K-1 predecessors, moved into its frame by '
        'the reference poses (K=2: ~150-180k points; default 1, the raw scans)',
    )
    parser.add_argument(
        '--worker', nargs=4, metavar=('METHOD', 'SCANS', 'OUT', 'STEPS'), help=argparse.SUPPRESS
    )
    args = parser.parse_args(argv)
    if args.worker:
        method, scans_arg, out_arg, steps_arg = args.worker
        run_worker(method, Path(scans_arg), Path(out_arg), int(steps_arg))
        return 0
    logging.basicConfig(level=logging.INFO, format='%(name)s: %(message)s')
    seq = load_balm(SHARED_DATA / 'balm')
    n = min(args.scans, len(seq.scan_paths))
    scans = [seq.load(i) for i in range(n)]
    truth = np.asarray(seq.T_world_sensor)[:n]
    if args.merge > 1:
        scans, truth = merge_scans(scans, truth, args.merge)
        n = len(scans)
    samples: dict[str, dict[str, Any]] = {m: {'ms': [], 'rounds': []} for m in args.methods}
    with tempfile.TemporaryDirectory() as tmp:
        scans_file = Path(tmp) / 'scans.npz'
        np.savez(scans_file, n=n, **{f's{i}': s for i, s in enumerate(scans)})
        for r in range(args.rounds):
            order = args.methods[r % len(args.methods) :] + args.methods[: r % len(args.methods)]
            for method in order:
                out_file = Path(tmp) / f'{method}_{r}.json'
                cmd = [
                    sys.executable,
                    __file__,
                    '--worker',
                    method,
                    str(scans_file),
                    str(out_file),
                    '0',
                ]
                t0 = time.perf_counter()
                subprocess.run(cmd, check=True, cwd=ROOT)
                res = json.loads(out_file.read_text())
                samples[method]['ms'].extend(res['ms'][1:])
                samples[method]['rounds'].append(res)
                logger.info(
                    'round %d %s: p50 %.1f ms/scan (%.0f s)',
                    r,
                    method,
                    np.median(res['ms'][1:]),
                    time.perf_counter() - t0,
                )
    methods: dict[str, Any] = {}
    for method, s in samples.items():
        first = s['rounds'][0]
        summary = summarize([first['ms'][0], *s['ms']], np.array(first['poses']), truth)
        summary['start_rss_mb'] = max(r['start_rss_mb'] for r in s['rounds'])
        summary['peak_rss_mb'] = max(r['peak_rss_mb'] for r in s['rounds'])
        summary['peak_growth_mb'] = max(r['peak_growth_mb'] for r in s['rounds'])
        summary['rounds_p50'] = [float(np.median(r['ms'][1:])) for r in s['rounds']]
        methods[method] = summary
    if args.long_steps > n:
        # Flat memory over a long run: resident memory after the last step minus at the middle
        # of the run (the allocator has settled by then); a leak of 10 kB per step would show
        # as 2 MB.
        with tempfile.TemporaryDirectory() as tmp:
            scans_file = Path(tmp) / 'scans.npz'
            np.savez(scans_file, n=n, **{f's{i}': s for i, s in enumerate(scans)})
            for method in args.methods:
                out_file = Path(tmp) / f'{method}_long.json'
                cmd = [sys.executable, __file__, '--worker', method, str(scans_file),
                       str(out_file), str(args.long_steps)]  # fmt: skip
                subprocess.run(cmd, check=True, cwd=ROOT)
                res = json.loads(out_file.read_text())
                rss, traced = res['rss_mb'], res['traced_mb']
                middle = args.long_steps // 2
                methods[method]['long_run'] = {
                    'steps': args.long_steps,
                    'from_step': middle,
                    'rss_at_middle_mb': rss[middle - 1],
                    'rss_at_end_mb': rss[-1],
                    'rss_growth_mb': rss[-1] - rss[middle - 1],
                    # numpy and Python objects alive (tracemalloc): exact, blind to C++ heaps
                    'traced_at_middle_mb': traced[middle - 1],
                    'traced_at_end_mb': traced[-1],
                    'growth_mb': traced[-1] - traced[middle - 1],
                }
    info = machine_info()
    report = {
        'meta': {
            'n_scans': n,
            'points': f'{min(len(s) for s in scans)}-{max(len(s) for s in scans)} points each',
            'merge': args.merge,
            'rounds': args.rounds,
            'long_steps': args.long_steps if args.long_steps > n else 0,
            'git': git_describe() or 'unknown',
            'load': info.get('load_avg_at_start', info.get('load_avg')),
            'machine': info,
        },
        'methods': methods,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    stem = 'per_scan' if args.merge <= 1 else f'per_scan_merge{args.merge}'
    write_json(args.out / f'{stem}.json', report)
    (args.out / f'{stem}.md').write_text(markdown(report))
    print(markdown(report))
    return 0


if __name__ == '__main__':
    sys.exit(main())
