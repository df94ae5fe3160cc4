"""Odometry: kentreg (previous scan, local map) against KISS-ICP and GICP scan-to-scan.

The pipelines get the same scans in memory (kentreg with the replay's configuration, or
``--config`` / ``--set``), ``--rounds`` rotated rounds after a two-scan warm-up, evaluated with
the replay's metrics; ``--strides``: once more on every N-th scan (README section 3).
``--consistent-voxels``: the ATE also against a map-consistent reference (the recording's
reference refined so every scan fits the map of all the others, built at the first voxel size;
the second measures that reference's own precision; ``benchmarks/harness/consistent.py``).
"""

from __future__ import annotations

import argparse
import datetime
import functools
import logging
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository

from benchmarks.harness import datasets, methods, perturb, pipelines, report, runner  # noqa: E402
from benchmarks.harness.consistent import map_consistent_poses  # noqa: E402
from kentreg_ros.core import prepare_scan  # noqa: E402
from kentreg_ros.eval import alignment, metrics  # noqa: E402
from kentreg_ros.io.paramfile import effective_config  # noqa: E402

METHODS = pipelines.ODOMETRY
TIMING = (
    'wall time of everything a pipeline does with one scan (preprocessing included, reading '
    'excluded), every scan including the first, after an untimed two-scan warm-up; per scan the '
    'median over --rounds rounds, which run the pipelines in rotated order'
)
COLOURS = dict(zip(METHODS, ('tab:blue', 'tab:purple', 'tab:orange', 'tab:green'), strict=True))


PAIRS = 'pairs.rotation_deg.median:.3f', 'pairs.translation_m.median:.4f'
RPE = ('rpe.rotation_deg.rmse:.3f', 'rpe.translation_m.rmse:.4f',
       'rpe_per_metre.translation_pct.rmse:.2f', 'rpe_per_metre.rotation_deg_per_m.rmse:.3f',
       'rpe_segment.rotation_deg.rmse:.3f', 'rpe_segment.translation_m.rmse:.4f')  # fmt: skip
SPEED = ('speed.ms_per_scan.mean:.1f', 'speed.ms_per_scan.p95:.1f',
         'speed.points_used_per_scan.mean:.0f')  # fmt: skip


def _row(name: str, entry: dict[str, Any], *specs: str | Callable[[Any], str]) -> list[str]:
    """``name`` and the cells of ``entry``'s metrics (a :func:`report.cells` spec or a function
    of them), or its error and blank cells."""
    m = entry.get('metrics')
    if m is None:
        return [name, f'error: {entry["error"]}', *[''] * (len(specs) - 1)]
    return [name, *(report.cells(m, c, missing='-')[0] if isinstance(c, str) else c(m)
                    for c in specs)]  # fmt: skip


def _failed(m: dict[str, Any]) -> str:
    return f'{m["pairs"]["n_failed"]} / {m["pairs"]["count"]}'


def _drift(m: dict[str, Any]) -> str:
    d = m.get('drift')
    return '-' if d is None else f'{d["translation_pct"]:.2f}, {d["rotation_deg_per_m"]:.4f}'


def _ate(m: dict[str, Any]) -> str:
    ate = m.get('ate')
    return '-' if ate is None else f'{ate["rmse"]:.4f}'


def _ate_cons(m: dict[str, Any]) -> str:
    value = m.get('ate_consistent_m')
    return '-' if value is None else f'{value:.4f}'


def _consistent_caption(cons: dict[str, Any]) -> str:
    moved = cons['moved_m_per_round'][0]
    text = (
        f'Map-consistent reference: the reference refined until every scan fits the map of all '
        f'the others (small_gicp GICP at {cons["voxels_m"][0]:g} m voxels, leave-one-out, '
        f'{len(moved)} rounds, the last moving a pose by at most {1e3 * moved[-1][1]:.2f} mm; '
        f'`benchmarks/harness/consistent.py`). It lies {1e3 * cons["ate_to_reference_m"]:.1f} '
        f'mm (ATE) from the reference'
    )
    if cons.get('precision_ate_m') is not None:
        text += (f'; built at {cons["voxels_m"][1]:g} m instead it moves '
                 f'{1e3 * cons["precision_ate_m"]:.1f} mm (ATE): its precision')  # fmt: skip
    return text + '.'


def markdown(doc: dict[str, Any]) -> str:
    """Markdown tables of the report (the same numbers as the JSON, rounded)."""
    rows, frames = doc['methods'], runner.SEGMENT_FRAMES
    n_pairs = next((e['metrics']['pairs']['count'] for e in rows.values() if 'metrics' in e), 0)
    lines = [
        f'Input: {doc["input"]["description"]}, {doc["input"]["n_scans"]} scans, {n_pairs} '
        f'consecutive pairs; {doc["threads"]} thread(s); ms per scan: per-scan median over '
        f'{doc["rounds"]} rounds.',
        '',
        *report.table('method | median e_R [deg] | median e_t [m] | max e_R [deg] | max e_t [m] '
                      '| failures (e_R>2 deg or e_t>0.2 m)',
                      [_row(n, e, *PAIRS, 'pairs.rotation_deg.max:.3f',
                            'pairs.translation_m.max:.4f', _failed) for n, e in rows.items()]),
        '',
        *report.table(
            'method | RPE/frame rot rmse [deg] | RPE/frame trans rmse [m] | RPE/m trans rmse [%] '
            f'| RPE/m rot rmse [deg/m] | RPE/{frames} frames rot rmse [deg] | RPE/{frames} frames '
            'trans rmse [m] | drift (KITTI segments) [%, deg/m] | ATE rmse [m] (SE(3)) '
            '| ms/scan mean | ms/scan p95 | points used/scan',
            [_row(n, e, *RPE, _drift, 'ate.rmse:.4f', *SPEED) for n, e in rows.items()
             if 'metrics' in e],
        ),
    ]  # fmt: skip
    cons = doc.get('consistent_reference')
    if cons:
        head = 'method | ATE rmse [m], reference | ATE rmse [m], map-consistent reference'
        body = [[n, _ate(e['metrics']), _ate_cons(e['metrics'])]
                for n, e in rows.items() if 'metrics' in e]  # fmt: skip
        lines += ['', _consistent_caption(cons), '', *report.table(head, body)]
    more: tuple[str | Callable[[Any], str], ...] = (
        'rpe_per_metre.translation_pct.rmse:.2f', 'ate.rmse:.4f', 'speed.ms_per_scan.mean:.1f',
    )  # fmt: skip
    more = (*more, _ate_cons) if cons else more
    srows = [[stride, *_row(name, entry, *PAIRS, _failed, *more)]
             for stride, block in (doc.get('strides') or {}).items()
             for name, entry in block.items() if name != 'n_scans']  # fmt: skip
    if srows:
        head = ('stride | method | median e_R [deg] | median e_t [m] | failures '
                '| RPE/m trans rmse [%] | ATE rmse [m] | ms/scan mean')  # fmt: skip
        head += ' | ATE rmse [m], map-consistent reference' if cons else ''
        caption = 'Frame skipping: every N-th scan of the same input, one round per pipeline.'
        lines += ['', caption, '', *report.table(head, srows)]
    return '\n'.join(lines) + '\n'


def plot(doc: dict[str, Any], path: Path) -> None:
    """Top view of every trajectory (aligned onto the reference by its ATE alignment) over the
    reference, position and per-pair errors."""
    T_gt = np.asarray(doc['reference_T_world_lidar'])
    errors = {n: e['metrics'] for n, e in doc['methods'].items() if 'metrics' in e}
    aligned = {n: np.asarray(m['ate']['T_gt_est'])
               @ np.asarray(doc['methods'][n]['poses_T_world_lidar'])
               for n, m in errors.items() if m['ate'] is not None}  # fmt: skip
    if not aligned:
        return
    top, pos = report.Panel(), report.Panel()
    rot, trans = report.Panel(log='y'), report.Panel(log='y')
    top.add('reference', T_gt[:, 0, 3], T_gt[:, 1, 3], color='black', lw=4, alpha=0.25)
    for name, poses in aligned.items():
        style = {'color': COLOURS[name], 'lw': 0.8, 'marker': '.'}
        top.add(name, poses[:, 0, 3], poses[:, 1, 3], color=COLOURS[name], lw=1.2)
        err = np.linalg.norm(poses[:, :3, 3] - T_gt[:, :3, 3], axis=1)
        pos.add(f'{name} (rmse {errors[name]["ate"]["rmse"]:.3f} m)', np.arange(len(err)), err,
                **style)  # fmt: skip
        pairs = errors[name]['pairs']
        x = np.arange(1, len(pairs['e_R_deg']) + 1)
        rot.add(None, x, np.maximum(pairs['e_R_deg'], 1e-4), **style)
        trans.add(None, x, np.maximum(pairs['e_t_m'], 1e-5), **style)
    top.add('start', T_gt[:1, 0, 3], T_gt[:1, 1, 3], color='black', marker='o')
    top.axes = {'xlabel': 'x [m]', 'ylabel': 'y [m]', 'aspect': 'equal',
                'title': 'top view, each SE(3)-aligned onto the reference'}  # fmt: skip
    pos.axes = {'xlabel': 'scan', 'ylabel': 'position error [m]',
                'title': 'ATE: position error after alignment'}  # fmt: skip
    for panel, label, limit in ((rot, 'e_R [deg]', 2.0), (trans, 'e_t [m]', 0.2)):
        panel.add('failure threshold', [1, len(T_gt) - 1], [limit, limit], color='red', lw=0.8,
                  linestyle='--')  # fmt: skip
        panel.axes = {'xlabel': 'pair', 'ylabel': label, 'title': f'per-pair {label} error'}
    report.plot_panels(path, [[top, pos], [rot, trans]], size=(13, 9))


OPTIONS: list[report.Option] = [
    ('--input', {'type': Path, 'default': datasets.SAMPLE_BAG, 'metavar': 'PATH',
                 'help': 'bag with /ground_truth, or scan folder with its pose file'}),
    ('--topic', {'help': 'PointCloud2 topic, when the bag has several'}),
    ('--threads', {'type': int, 'default': 1, 'help': 'threads for every library'}),
    ('--methods', {'nargs': '+', 'choices': METHODS, 'default': list(METHODS)}),
    ('--kiss-max-range', {'type': float, 'metavar': 'M',
                          'help': "KISS-ICP's data.max_range (default: its own 100 m)"}),
    ('--config', {'type': Path, 'help': "kentreg parameter file (the node's YAML)"}),
    ('--set', {'dest': 'overrides', 'action': 'append', 'default': [], 'metavar': 'KEY=VALUE',
               'help': 'override one kentreg parameter (repeatable)'}),
    ('--rounds', {'type': int, 'default': 3, 'help': 'runs per pipeline (default 3)'}),
    ('--max-scans', {'type': int, 'metavar': 'N', 'help': 'use the first N scans only'}),
    ('--strides', {'type': int, 'nargs': '*', 'default': [2, 3, 4], 'metavar': 'N',
                   'help': 'also every N-th scan, one round (default 2 3 4; none: --strides)'}),
    ('--consistent-voxels', {'type': float, 'nargs': '*', 'default': [0.1, 0.2],
                             'metavar': 'M',
                             'help': 'voxel sizes of the map-consistent reference (default 0.1 '
                                     '0.2: built at the first, the second its precision; '
                                     'none: --consistent-voxels)'}),
]  # fmt: skip


def _entries(
    names: Sequence[str], scans: list[Any], T_gt: runner.FloatArray, options: dict[str, Any],
    rounds: int, full: bool = True, T_consistent: runner.FloatArray | None = None,
) -> dict[str, dict[str, Any]]:  # fmt: skip
    """Every pipeline in ``rounds`` rotated rounds after a two-scan warm-up, evaluated (its error
    when it crashed); ``full``: the rounds combined, with the settings and poses;
    ``T_consistent``: also the ATE rmse against that reference (metrics' ``ate_consistent_m``)."""
    makers = {n: functools.partial(pipelines.make_pipeline, n, **options) for n in names}
    scored = runner.score_pipelines(makers, scans, T_gt, rounds=rounds, warmup=2, combine=full)
    for entry in scored.values():
        if 'run' in entry:
            run = entry.pop('run')
            entry['health'] = run.health
            if T_consistent is not None:
                entry['metrics']['ate_consistent_m'] = alignment.ate(run.poses, T_consistent)[
                    'rmse'
                ]
            if full:
                entry |= {'settings': run.settings, 'poses_T_world_lidar': run.poses}
    return scored


def _consistent(
    doc: dict[str, Any], scans: list[Any], T_gt: runner.FloatArray, voxels: Sequence[float],
    threads: int,
) -> runner.FloatArray | None:  # fmt: skip
    """The map-consistent reference at ``voxels[0]`` (None without voxels), recorded in ``doc``
    with its rounds, and its precision: the ATE between it and the one at ``voxels[1]``."""
    if not voxels:
        return None
    clouds = [np.asarray(s.points, float) for s in scans]
    built = [map_consistent_poses(clouds, T_gt, v, threads=threads) for v in voxels[:2]]
    doc['consistent_reference'] = {
        'voxels_m': list(voxels[:2]), 'T_world_lidar': built[0].poses,
        'moved_m_per_round': [b.moved_m for b in built],
        'converged': [b.converged for b in built],
        'ate_to_reference_m': alignment.ate(built[0].poses, T_gt)['rmse'],
        'precision_ate_m': (alignment.ate(built[0].poses, built[1].poses)['rmse']
                            if len(built) > 1 else None),
    }  # fmt: skip
    return built[0].poses


def run(args: argparse.Namespace, argv: list[str]) -> dict[str, Any]:
    if args.threads < 1 or args.rounds < 1 or any(n < 1 for n in args.strides):
        raise SystemExit('--threads, --rounds and --strides must be >= 1')
    methods.pin_threads(args.threads, argv, __file__)
    logging.basicConfig(level=logging.WARNING, format='%(name)s: %(levelname)s: %(message)s')
    cfg = effective_config(args.config, args.overrides)
    seq = datasets.load_recording(args.input, topic=args.topic)
    scans, T_gt = seq.scans[: args.max_scans], np.asarray(seq.T_world)[: args.max_scans]
    voxel = prepare_scan(scans[0].points, config=cfg).voxel_size
    env = {name: os.environ.get(name) for name in methods.THREAD_ENV}
    pinning = {'env': env, 'cpu_affinity': sorted(os.sched_getaffinity(0))}
    points = metrics.summarize([len(s.points) for s in scans])
    doc: dict[str, Any] = {
        'benchmark': 'odometry', 'command': ['python3', 'benchmarks/odometry.py', *argv],
        'date': datetime.datetime.now().isoformat(timespec='seconds'),
        'machine': report.machine_info(), 'threads': args.threads, 'thread_pinning': pinning,
        'input': {'path': str(args.input), 'description': seq.description, 'n_scans': len(scans),
                  'points_per_scan': points, 'ground_truth': seq.note},
        'ms_per_scan_measures': TIMING, 'rounds': args.rounds,
    }  # fmt: skip
    options = {'config': cfg, 'voxel': voxel, 'threads': args.threads,
               'max_range': args.kiss_max_range}  # fmt: skip
    doc['reference_T_world_lidar'] = T_gt
    T_cons = _consistent(doc, scans, T_gt, args.consistent_voxels, args.threads)
    doc['methods'] = _entries(args.methods, scans, T_gt, options, args.rounds, True, T_cons)
    if 'settings' in doc['methods'].get('gicp', {}):
        choice = "kentreg's automatic voxel size for the first scan"
        doc['methods']['gicp']['settings']['voxel_choice'] = choice
    alive = [n for n in args.methods if 'error' not in doc['methods'][n]]
    doc['strides'] = {}
    for n in args.strides:
        batch = perturb.stride(n)(scans)
        T_sub = None if T_cons is None else T_cons[::n]
        block = _entries(alive, batch, T_gt[::n], options, 1, False, T_sub)
        doc['strides'][str(n)] = {'n_scans': len(batch), **block}
    report.finish_machine(doc['machine'])
    return doc


if __name__ == '__main__':
    raise SystemExit(report.experiment_main(__doc__, 'odometry', OPTIONS, run, markdown, plot))
