"""Odometry on re-simulated sequences with exact poses, at faster motion than the sample's.

The sample's scene re-simulated (``harness/simulator.py``) at ``--steps`` m per scan,
``--seeds`` samplings each, clean, with ``--outliers`` raw outliers (``perturb.raw_outliers``)
and swept (``--sweep`` s, points timed); the odometry pipelines run on each, one round (README
section 3b, which also says what the simulation leaves out).
``--write DIR``: one sequence as a scan folder instead (``scan_<i>.pcd``, ``t`` with sweeps, and
``alidarPose.csv`` with the exact poses, stamped at the input's scan rate), which
``kentreg_replay`` and ``benchmarks/odometry.py`` read like any recording.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import functools
import logging
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository

from benchmarks.harness import methods, perturb, pipelines, report, runner, simulator  # noqa: E402
from kentreg_ros.core import KentRegConfig, prepare_scan  # noqa: E402
from kentreg_ros.io.scanfiles import write_pcd  # noqa: E402

#: Pipelines run on the clean sequences only, and not on the swept ones (module docstring).
CLEAN_ONLY = ('kiss_icp',)
UNSWEPT_ONLY = ('kiss_icp',)
#: The local map with deskewing off, on the swept sequences only: what the deskewing is worth.
NO_DESKEW = 'kentreg_local_map_no_deskew'


def _entry(run: runner.Run, T_gt: Any) -> dict[str, Any]:
    """The numbers of one pipeline on one sequence (:func:`runner.evaluate_run`)."""
    m = runner.evaluate_run(run, T_gt)
    return {'ate_m': m['ate']['rmse'], 'drift_pct': m['drift']['translation_pct'],
            'rpe_frame_m': m['rpe']['translation_m']['rmse'],
            'rpe_frame_deg': m['rpe']['rotation_deg']['rmse'], 'n_failed': m['pairs']['n_failed'],
            'n_pairs': m['pairs']['count'], 'ms_per_scan_mean': float(np.mean(run.ms_per_scan)),
            'health': run.health}  # fmt: skip


def run_condition(
    world: simulator.World, step: float, share: float, names: Sequence[str], seeds: int,
    sensor: simulator.Sensor, cfg: KentRegConfig,
) -> dict[str, Any]:  # fmt: skip
    """Every pipeline on ``seeds`` sequences at ``step`` metres per scan, with a share
    ``share`` of raw outliers on every scan, or swept (``sensor.sweep_period > 0``)."""
    swept = sensor.sweep_period > 0.0
    names = list(names)
    if swept and 'kentreg_local_map' in names:
        names.insert(names.index('kentreg_local_map') + 1, NO_DESKEW)
    skip = set(CLEAN_ONLY if share > 0.0 else ()) | set(UNSWEPT_ONLY if swept else ())
    runs: list[dict[str, Any]] = []
    errors: dict[str, str] = {}
    motion, n_scans = {}, 0
    for seed in range(seeds):
        scans, gt = simulator.simulate(world, step, seed, sensor)
        if share > 0.0:  # (no sweep with outliers: their times would be undefined)
            scans = perturb.raw_outliers(share, np.random.default_rng([seed, 1]))(scans)
        T_gt = np.asarray(gt.trajectory.T_world_sensor, dtype=np.float64)
        motion, n_scans = simulator.motion_stats(T_gt), len(scans)
        options = {'config': cfg, 'threads': 1,
                   'voxel': prepare_scan(scans[0].points, config=cfg).voxel_size}  # fmt: skip
        makers = {n: functools.partial(pipelines.make_pipeline, n, **options)
                  for n in names if n not in skip}  # fmt: skip
        scored = runner.score_pipelines(makers, scans, T_gt, warmup=2, score=_entry)
        entries = {n: e.get('metrics', e) for n, e in scored.items()}
        errors |= {n: e['error'] for n, e in entries.items() if 'error' in e}
        runs.append({'seed': seed, 'methods': entries})
    return {'step_m': step, 'outliers': share, 'sweep_s': sensor.sweep_period,
            'n_scans': n_scans, 'motion': motion, 'runs': runs,
            'summary': summarize_step(runs, names), 'errors': errors}  # fmt: skip


def summarize_step(runs: list[dict[str, Any]], names: Sequence[str]) -> dict[str, Any]:
    """Per method, over the seeds of one step: ATE, ratio to kentreg, drift, failures, speed."""
    out: dict[str, Any] = {}
    for name in names:
        both = [r['methods'] for r in runs if 'ate_m' in r['methods'].get(name, {})]
        if not both:
            continue
        rows = [m[name] for m in both]
        ratios = [m[name]['ate_m'] / m['kentreg']['ate_m'] for m in both
                  if 'ate_m' in m.get('kentreg', {})]  # fmt: skip
        spread = (('median', np.median), ('min', np.min), ('max', np.max))

        def median(key: str, rows: list[dict[str, Any]] = rows) -> float:
            return float(np.median([m[key] for m in rows]))

        out[name] = {
            'runs': len(rows), 'ate_m_median': median('ate_m'),
            'ate_ratio_to_kentreg': {k: float(f(ratios)) if ratios else None for k, f in spread},
            'drift_pct_median': median('drift_pct'), 'rpe_frame_m_median': median('rpe_frame_m'),
            'failed_pairs': int(sum(m['n_failed'] for m in rows)),
            'pairs': int(sum(m['n_pairs'] for m in rows)),
            'ms_per_scan_mean': float(np.mean([m['ms_per_scan_mean'] for m in rows])),
        }  # fmt: skip
    return out


def _input_text(step: dict[str, Any]) -> str:
    """What a condition fed the pipelines: clean, with raw outliers, or swept."""
    if step.get('sweep_s'):
        return f'{1e3 * step["sweep_s"]:.0f} ms sweeps, timed'
    share = step.get('outliers', 0.0)
    return f'{100 * share:.0f} % raw outliers' if share else 'clean'


#: The columns of the table: a row per step, condition and method.
COLUMNS: list[report.Column] = [
    ('step [m]', lambda r: r['step']['step_m']),
    ('input', lambda r: _input_text(r['step'])),
    ('scans', lambda r: r['step']['n_scans']),
    ('rotation/scan median, max [deg]',
     lambda r: '{rotation_median_deg:.1f}, {rotation_max_deg:.1f}'.format(**r['step']['motion'])),
    ('method', 'name:s'),
    ('ATE median [mm]', lambda r: f'{1e3 * r["ate_m_median"]:.2f}'),
    ('ATE / kentreg: median (range)',
     lambda r: '{median:.2f} ({min:.2f}–{max:.2f})'.format(**r['ate_ratio_to_kentreg'])),
    ('drift [%]', 'drift_pct_median:.2f'),
    ('RPE/frame [mm]', lambda r: f'{1e3 * r["rpe_frame_m_median"]:.2f}'),
    ('failures', lambda r: f'{r["failed_pairs"]} / {r["pairs"]}'),
    ('ms/scan', 'ms_per_scan_mean:.1f'),
]  # fmt: skip


def format_table(doc: dict[str, Any]) -> str:
    """Markdown table of the per-step summaries."""
    entries = [
        {'step': step, **row} for step in doc['steps'] for row in report.named(step['summary'])
    ]
    lines = [
        f'Re-simulated `bags/balm_50` scene, exact poses; {doc["seeds"]} seeds per step '
        f'(independent sampling and noise); 1 thread; one round per pipeline.',
        '',
        *report.column_table(COLUMNS, entries),
    ]
    for step in doc['steps']:
        for name, error in step.get('errors', {}).items():
            condition = f'{step["step_m"]}, {step.get("outliers", 0.0)} outliers'
            lines.append(f'\n{name} at step {condition}: {error}')
    if doc.get('machine', {}).get('git'):
        command = ' '.join(doc.get('command', []))
        lines += ['', f'Run at {doc["machine"]["git"]}: `{command}`.']
    return '\n'.join(lines) + '\n'


OPTIONS: list[report.Option] = [
    ('--input', {'type': Path, 'default': simulator.DEFAULT_INPUT, 'help': 'scene to simulate'}),
    ('--steps', {'type': float, 'nargs': '+', 'default': [0.15, 0.3, 0.6], 'metavar': 'M'}),
    ('--outliers', {'type': float, 'nargs': '+', 'default': [0.0, 0.4], 'metavar': 'SHARE',
                    'help': 'raw outlier shares, each a run of every step (default 0 0.4)'}),
    ('--sweep', {'type': float, 'metavar': 'S', 'help': 'also every step with sweeps of S '
                 'seconds (default 0.1; 0: none; with --write: the sweep, default none)'}),
    ('--seeds', {'type': int, 'default': 5, 'help': 'sequences per step (default 5)'}),
    ('--methods', {'nargs': '+', 'choices': pipelines.ODOMETRY,
                   'default': list(pipelines.ODOMETRY)}),
    ('--write', {'type': Path, 'metavar': 'DIR', 'help': 'only write the sequence of the first '
                 '--steps value as a scan folder (clean; swept with --sweep)'}),
    ('--seed', {'type': int, 'default': 0, 'help': 'the sequence --write writes (default 0)'}),
]  # fmt: skip


def write_sequence(folder: Path, scans: list[Any], gt: Any) -> None:
    """``scan_<i>.pcd`` per scan and ``alidarPose.csv``: the 3x4 ``[R | t]`` and
    ``0,0,0,<time>`` per pose (17 digits)."""
    folder.mkdir(parents=True, exist_ok=True)
    for i, scan in enumerate(scans):
        write_pcd(folder / f'scan_{i:04d}.pcd', scan.points.astype(np.float32), scan.extras)
    lines: list[str] = []
    for Ti, ns in zip(gt.trajectory.T_world_sensor, gt.trajectory.stamps_ns, strict=True):
        lines.extend(','.join(f'{v:.17g}' for v in row) + ',' for row in Ti[:3])
        lines.append(f'0,0,0,{ns * 1e-9:.9f},')
    (folder / 'alidarPose.csv').write_text('\n'.join(lines) + '\n')


def run(args: argparse.Namespace, argv: list[str]) -> dict[str, Any]:
    if args.seeds < 1 or any(s <= 0 for s in args.steps):
        raise SystemExit('--seeds must be >= 1 and --steps > 0')
    if any(not 0.0 <= f < 1.0 for f in args.outliers) or 'kentreg' not in args.methods:
        raise SystemExit('--outliers must be in [0, 1) and --methods must include kentreg')
    sweep = args.sweep if args.sweep is not None else 0.0 if args.write else 0.1
    if args.write:
        world = simulator.build_world(args.input, simulator.WORLD_VOXEL)
        sensor = simulator.Sensor(sweep_period=sweep)
        write_sequence(args.write, *simulator.simulate(world, args.steps[0], args.seed, sensor))
        raise SystemExit(0)
    methods.pin_threads(1, argv, __file__)
    logging.basicConfig(level=logging.WARNING, format='%(name)s: %(levelname)s: %(message)s')
    t_start = time.perf_counter()
    world_voxel = simulator.WORLD_VOXEL
    world = simulator.build_world(args.input, world_voxel)
    sensor, cfg = simulator.Sensor(), KentRegConfig()
    doc: dict[str, Any] = {
        'benchmark': 'simulated', 'command': ['python3', 'benchmarks/simulated.py', *argv],
        'date': datetime.datetime.now().isoformat(timespec='seconds'),
        'machine': report.machine_info(), 'input': str(args.input),
        'world': {'voxel_m': world_voxel, 'points': len(world.points), 'period_s': world.period},
        'sensor': dataclasses.asdict(sensor), 'seeds': args.seeds, 'methods': args.methods,
    }  # fmt: skip
    conditions = [(share, sensor) for share in args.outliers]
    if sweep > 0.0:
        conditions.append((0.0, dataclasses.replace(sensor, sweep_period=sweep)))
    doc['steps'] = [run_condition(world, step, share, args.methods, args.seeds, sens, cfg)
                    for step in args.steps for share, sens in conditions]  # fmt: skip
    doc['seconds'] = time.perf_counter() - t_start
    report.finish_machine(doc['machine'])
    return doc


if __name__ == '__main__':
    raise SystemExit(report.experiment_main(__doc__, 'simulated', OPTIONS, run, format_table))
