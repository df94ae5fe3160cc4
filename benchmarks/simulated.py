"""Odometry on re-simulated sequences with exact reference poses, at faster motion than the
sample's.

``benchmarks/simulate.py`` rebuilds the scene of ``bags/balm_50`` as one cloud and lets a
simulated spinning LiDAR (2 cm range noise, 0.5 deg beams, occlusion) travel its path at
``--steps`` metres per scan, every one with ``--seeds`` independent samplings and noise.
The poses are exact, so the differences of a few millimetres between pipelines that the
sample's reference (a LiDAR-inertial estimate) cannot resolve are measured here; and the
faster steps stand in for the recordings the odometry is judged on but that are not in this
repository (0.6 m and 8 deg median between scans, up to 48 deg).

Every step runs clean, with ``--outliers`` (default 40 %) of raw outliers added to every
scan before anything else (uniform in the scan's bounding box, as ``robustness.py`` adds
them), and swept (``--sweep``, default 0.1 s: each scan taken over a sweep ending at its
stamp while the sensor moves with the velocity that brought it from the previous scan, every
point timed in a field ``t``; kentreg deskews, GICP uses the points as they are, KISS-ICP
is left out (see ``UNSWEPT_ONLY``), and ``kentreg_local_map_no_deskew`` shows the local map
without deskewing). The four pipelines of ``benchmarks/odometry.py`` run on every sequence
(KISS-ICP on the clean ones only, see ``CLEAN_ONLY``), one round each:
``kentreg`` (previous scan), ``kentreg_local_map``, ``kiss_icp`` and ``gicp``, with the same
settings as there. Per step the table gives, over the seeds: the median ATE (rmse after SE(3)
alignment), the median and range of each pipeline's per-seed ATE ratio to ``kentreg``, the
drift per metre over KITTI segments scaled to the path, the failed pairs (``e_R > 2 deg`` or
``e_t > 0.2 m``) and the mean milliseconds per scan.

What the simulation leaves out, so what these numbers do not show: smooth changes of
velocity (the simulated velocity is constant between scans and jumps at each; a real sensor's
changes within a sweep), moving objects, reflectivity-dependent dropouts and the path's
length (the scene is the sample's 10 m; the longest sequence has 66 scans, so drift has less
room to grow than over a long recording).

Usage::

    python3 benchmarks/simulated.py                # 0.15 0.3 0.6 m; clean, 40 %, swept
    python3 benchmarks/simulated.py --steps 0.6 --seeds 2 --out /tmp/sim

Writes ``benchmarks/results/simulated.json`` and ``simulated.md``; ``--table JSON`` prints
the table of an earlier results file again.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import logging
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.common import git_describe, machine_info, write_json  # noqa: E402
from benchmarks.odometry import (  # noqa: E402
    METHODS,
    evaluate_pipeline,
    pin_threads,
    run_gicp,
    run_kentreg,
    run_kiss_icp,
)
from benchmarks.robustness import inject_raw_outliers  # noqa: E402
from benchmarks.simulate import (  # noqa: E402
    DEFAULT_INPUT,
    WORLD_VOXEL,
    Sensor,
    World,
    build_world,
    motion_stats,
    simulate,
)
from kentreg_ros.core import KentRegConfig, prepare_scan  # noqa: E402
from kentreg_ros.io.sources import Scan  # noqa: E402

logger = logging.getLogger('benchmarks.simulated')

RESULTS = ROOT / 'benchmarks' / 'results'
#: Pipelines run on the clean sequences only. KISS-ICP's map keeps up to 20 points in every
#: 1 m voxel its scans reach, so outliers spread through each scan's bounding box fill its
#: volume: with 40 % of them one 66-scan sequence had not finished after 10 minutes (against
#: about 10 s clean), which would make this benchmark take hours.
CLEAN_ONLY = ('kiss_icp',)
#: Pipelines not run on the swept sequences. KISS-ICP's deskewing takes a sweep to fill the
#: interval between two scans (it normalises the times of a scan to [0, 1] and moves the
#: points by that fraction of the whole motion since the previous scan); these sweeps last
#: 0.1 s of a 0.5 s interval (every 5th sweep of a 10 Hz sensor), so it would deskew them by
#: five times their motion: a mismatch of this set-up, not a measure of KISS-ICP.
UNSWEPT_ONLY = ('kiss_icp',)
#: The local map with deskewing off, run on the swept sequences only (beside the default,
#: which deskews them): what the deskewing is worth.
NO_DESKEW = 'kentreg_local_map_no_deskew'


def run_sequence(name: str, scans: list[Any], voxel: float, cfg: KentRegConfig) -> Any:
    """One pipeline over one simulated sequence."""
    if name == 'kentreg':
        return run_kentreg(scans, cfg)
    if name == 'kentreg_local_map':
        local = cfg.with_updates({'odometry.model': 'local_map'})
        return run_kentreg(scans, local, 'kentreg_local_map')
    if name == NO_DESKEW:
        local = cfg.with_updates({'odometry.model': 'local_map', 'odometry.deskew': 'off'})
        return run_kentreg(scans, local, NO_DESKEW)
    if name == 'kiss_icp':
        return run_kiss_icp(scans, threads=1)
    return run_gicp(scans, voxel, threads=1)


def run_condition(
    world: World,
    step: float,
    share: float,
    args: argparse.Namespace,
    sensor: Sensor,
    cfg: KentRegConfig,
) -> dict[str, Any]:
    """Every pipeline on ``args.seeds`` sequences at ``step`` metres per scan, with a share
    ``share`` of raw outliers added to every scan before anything else (uniform in the scan's
    bounding box, as ``robustness.py`` adds them; seeded by the sequence's seed), or swept
    (``sensor.sweep_period > 0``: every point timed; then also :data:`NO_DESKEW`)."""
    methods = list(args.methods)
    if sensor.sweep_period > 0.0 and 'kentreg_local_map' in methods:
        methods.insert(methods.index('kentreg_local_map') + 1, NO_DESKEW)
    runs: list[dict[str, Any]] = []
    errors: dict[str, str] = {}
    motion: dict[str, float] = {}
    n_scans = 0
    for seed in range(args.seeds):
        scans, gt = simulate(world, step, seed, sensor)
        if share > 0.0:
            rng = np.random.default_rng([seed, 1])
            scans = [
                Scan(s.stamp_ns, s.frame_id, inject_raw_outliers(s.points, share, rng)[0], {})
                for s in scans  # (no sweep with outliers: their times would be undefined)
            ]
        motion = motion_stats(gt.trajectory.T_world_sensor)
        n_scans = len(scans)
        voxel = prepare_scan(scans[0].points, config=cfg).voxel_size
        entry: dict[str, Any] = {'seed': seed, 'methods': {}}
        for name in methods:
            if (share > 0.0 and name in CLEAN_ONLY) or (
                sensor.sweep_period > 0.0 and name in UNSWEPT_ONLY
            ):
                continue
            try:
                run = run_sequence(name, scans, voxel, cfg)
            except Exception as exc:  # a pipeline crashing is a result, not a stop
                logger.exception('%s failed at step %s seed %d', name, step, seed)
                errors[name] = f'{type(exc).__name__}: {exc}'
                entry['methods'][name] = {'error': errors[name]}
                continue
            m, _, _ = evaluate_pipeline(run, scans, gt)
            entry['methods'][name] = {
                'ate_m': m['ate']['rmse'],
                'drift_pct': m['drift']['translation_pct'],
                'rpe_frame_m': m['rpe']['translation_m']['rmse'],
                'rpe_frame_deg': m['rpe']['rotation_deg']['rmse'],
                'n_failed': m['pairs']['n_failed'],
                'n_pairs': m['pairs']['count'],
                'ms_per_scan_mean': float(np.mean(run.ms_per_scan)),
                'health': run.health,
            }
        runs.append(entry)
        logger.warning(
            'step %s outliers %s sweep %s s seed %d: %s',
            step,
            share,
            sensor.sweep_period,
            seed,
            ', '.join(
                f'{k} {1e3 * v["ate_m"]:.2f} mm'
                for k, v in entry['methods'].items()
                if 'ate_m' in v
            ),
        )
    return {
        'step_m': step,
        'outliers': share,
        'sweep_s': sensor.sweep_period,
        'n_scans': n_scans,
        'motion': motion,
        'runs': runs,
        'summary': summarize_step(runs, methods),
        'errors': errors,
    }


def summarize_step(runs: list[dict[str, Any]], methods: Sequence[str]) -> dict[str, Any]:
    """Per method, over the seeds of one step: ATE, ratio to kentreg, drift, failures, speed."""
    out: dict[str, Any] = {}
    for name in methods:
        rows = [r['methods'][name] for r in runs if 'ate_m' in r['methods'].get(name, {})]
        if not rows:
            continue
        ratios = [
            r['methods'][name]['ate_m'] / r['methods']['kentreg']['ate_m']
            for r in runs
            if 'ate_m' in r['methods'].get(name, {}) and 'ate_m' in r['methods'].get('kentreg', {})
        ]
        out[name] = {
            'runs': len(rows),
            'ate_m_median': float(np.median([m['ate_m'] for m in rows])),
            'ate_ratio_to_kentreg': {
                'median': float(np.median(ratios)) if ratios else None,
                'min': float(np.min(ratios)) if ratios else None,
                'max': float(np.max(ratios)) if ratios else None,
            },
            'drift_pct_median': float(np.median([m['drift_pct'] for m in rows])),
            'rpe_frame_m_median': float(np.median([m['rpe_frame_m'] for m in rows])),
            'failed_pairs': int(sum(m['n_failed'] for m in rows)),
            'pairs': int(sum(m['n_pairs'] for m in rows)),
            'ms_per_scan_mean': float(np.mean([m['ms_per_scan_mean'] for m in rows])),
        }
    return out


def _input_text(step: dict[str, Any]) -> str:
    """What a condition fed the pipelines: clean, with raw outliers, or swept."""
    if step.get('sweep_s'):
        return f'{1e3 * step["sweep_s"]:.0f} ms sweeps, timed'
    share = step.get('outliers', 0.0)
    return f'{100 * share:.0f} % raw outliers' if share else 'clean'


def format_table(report: dict[str, Any]) -> str:
    """Markdown table of the per-step summaries."""
    lines = [
        f'Re-simulated `bags/balm_50` scene, exact poses; {report["seeds"]} seeds per step '
        f'(independent sampling and noise); 1 thread; one round per pipeline.',
        '',
        '| step [m] | input | scans | rotation/scan median, max [deg] | method '
        '| ATE median [mm] | ATE / kentreg: median (range) | drift [%] | RPE/frame [mm] '
        '| failures | ms/scan |',
        '|---|---|---|---|---|---|---|---|---|---|---|',
    ]
    for step in report['steps']:
        motion = step['motion']
        for name, s in step['summary'].items():
            ratio = s['ate_ratio_to_kentreg']
            lines.append(
                f'| {step["step_m"]} | {_input_text(step)} '
                f'| {step["n_scans"]} '
                f'| {motion["rotation_median_deg"]:.1f}, {motion["rotation_max_deg"]:.1f} '
                f'| {name} | {1e3 * s["ate_m_median"]:.2f} '
                f'| {ratio["median"]:.2f} ({ratio["min"]:.2f}–{ratio["max"]:.2f}) '
                f'| {s["drift_pct_median"]:.2f} | {1e3 * s["rpe_frame_m_median"]:.2f} '
                f'| {s["failed_pairs"]} / {s["pairs"]} | {s["ms_per_scan_mean"]:.1f} |'
            )
    for step in report['steps']:
        for name, error in step.get('errors', {}).items():
            lines.append(
                f'\n{name} at step {step["step_m"]}, {step.get("outliers", 0.0)} outliers: {error}'
            )
    machine = report.get('machine', {})
    if machine.get('git'):
        command = ' '.join(report.get('command', []))
        lines += ['', f'Run at {machine["git"]}: `{command}`.']
    return '\n'.join(lines) + '\n'


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        '--input', type=Path, default=DEFAULT_INPUT, help='recording whose scene is re-simulated'
    )
    parser.add_argument(
        '--steps',
        type=float,
        nargs='+',
        default=[0.15, 0.3, 0.6],
        metavar='M',
        help='metres per scan (default 0.15 0.3 0.6)',
    )
    parser.add_argument(
        '--outliers',
        type=float,
        nargs='+',
        default=[0.0, 0.4],
        metavar='SHARE',
        help='raw outlier shares, each a run of every step (default 0 0.4)',
    )
    parser.add_argument(
        '--sweep',
        type=float,
        default=0.1,
        metavar='S',
        help='also run every step with sweeps of S seconds, points timed (default 0.1: a 10 Hz '
        'spinning LiDAR; 0: no such run)',
    )
    parser.add_argument('--seeds', type=int, default=5, help='sequences per step (default 5)')
    parser.add_argument(
        '--methods', nargs='+', choices=METHODS, default=list(METHODS), help='pipelines to run'
    )
    parser.add_argument('--out', type=Path, default=RESULTS, help='folder for the results')
    parser.add_argument(
        '--table', type=Path, metavar='JSON', help='only print the table of a results file'
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    if args.table is not None:
        print(format_table(json.loads(args.table.read_text())), end='')
        return 0
    if args.seeds < 1 or any(s <= 0 for s in args.steps):
        raise SystemExit('--seeds must be >= 1 and --steps > 0')
    if any(not 0.0 <= f < 1.0 for f in args.outliers):
        raise SystemExit('--outliers must be in [0, 1)')
    if 'kentreg' not in args.methods:
        raise SystemExit('--methods must include kentreg (the ratios are to it)')
    pin_threads(1, argv, Path(__file__))
    logging.basicConfig(level=logging.WARNING, format='%(name)s: %(levelname)s: %(message)s')
    t_start = time.perf_counter()
    world = build_world(args.input, WORLD_VOXEL)
    sensor = Sensor()
    cfg = KentRegConfig()
    report: dict[str, Any] = {
        'benchmark': 'simulated',
        'command': ['python3', 'benchmarks/simulated.py', *argv],
        'date': datetime.datetime.now().isoformat(timespec='seconds'),
        'machine': machine_info(),
        'input': str(args.input),
        'world': {'voxel_m': WORLD_VOXEL, 'points': len(world.points), 'period_s': world.period},
        'sensor': dataclasses.asdict(sensor),
        'seeds': args.seeds,
        'methods': args.methods,
        'steps': [],
    }
    for step in args.steps:
        for share in args.outliers:
            report['steps'].append(run_condition(world, step, share, args, sensor, cfg))
        if args.sweep > 0.0:
            swept = dataclasses.replace(sensor, sweep_period=args.sweep)
            report['steps'].append(run_condition(world, step, 0.0, args, swept, cfg))
    report['seconds'] = time.perf_counter() - t_start
    report['machine']['git_at_end'] = git_describe()
    args.out.mkdir(parents=True, exist_ok=True)
    table = format_table(report)
    (args.out / 'simulated.md').write_text(table)
    write_json(args.out / 'simulated.json', report)
    print(table)
    print(f'wrote {args.out}/simulated.json, simulated.md')
    return 0


if __name__ == '__main__':
    sys.exit(main())
