"""The paper's Table 1 protocol on real data: every pair method, two starts, consecutive pairs.

``balm`` (49 pairs), ``small_gicp_pair`` and ``--eth PATH``, from the identity and from the
constant-velocity guess; time per pair = preparing the new scan + registering it (README
section 1).
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TypeAlias

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.harness import datasets, methods, perturb, report, runner  # noqa: E402

logger = logging.getLogger('paper_table')

STARTS = ('identity', 'constant_velocity')
Data: TypeAlias = datasets.Sequence
Methods: TypeAlias = Sequence[methods.Method]
Ints: TypeAlias = Sequence[int]
Strs: TypeAlias = Sequence[str]
#: The paper's Table 1 (ETH Hauptgebaeude, from identity): average e_R (deg), e_t (m).
PAPER_TABLE1: dict[str, tuple[str, float, float]] = {
    'icp_pt2pt': ('ICP', 1.27, 0.403), 'icp_pt2pl': ('ICPp2pl', 0.57, 0.164),
    'cicp': ('CICP', 1.162, 0.260), 'gicp': ('GICP', 0.23, 0.025), 'ndt': ('NDT', 0.52, 0.070),
    'kentreg_paper': ('Ours', 0.66, 0.018),
}  # fmt: skip


def run_pair(
    method: methods.Method, prepared: dict[int, tuple[Any, float]], seq: Data, pair: int,
    starts: Strs,
) -> dict[str, dict[str, Any]]:  # fmt: skip
    """One pair with one method from every start: ``{start: record}``."""
    target, _ = prepared[pair]
    source, prep_ms = prepared[pair + 1]
    out = {}
    for start in starts:
        init = np.eye(4) if start == 'identity' else seq.constant_velocity(pair)
        record: dict[str, Any] = {'pair': pair, 'prepare_ms': prep_ms}
        try:
            T, reg_ms = runner.timed(method.register, source, target, init)
            e_R, e_t = runner.errors(T, seq.truth(pair))
        except Exception as exc:  # a method that raises (any error) is a failed pair
            logger.warning('%s on %s pair %d (%s): %s', method.name, seq.name, pair, start, exc)
            reg_ms, e_R, e_t = float('nan'), float('nan'), float('nan')
            record['error'] = f'{type(exc).__name__}: {exc}'
        record.update({'e_R_deg': e_R, 'e_t_m': e_t, 'register_ms': reg_ms})
        record['ms'] = prep_ms + reg_ms
        out[start] = record
    return out


def run_sequence(seq: Data, built: Methods, pairs: Ints, starts: Strs, voxel: float) -> dict:
    """Every method on ``pairs`` of ``seq``, pairs outer (every method sees the same load)."""
    needed = sorted({p for p in pairs} | {p + 1 for p in pairs})
    clouds = {i: methods.voxel_downsample(seq.raw(i), voxel) for i in needed}
    sizes = [len(c) for c in clouds.values()]
    if seq.T_world is None:
        starts = [s for s in starts if s == 'identity']
    records: dict[str, dict[str, list[dict[str, Any]]]] = {
        m.name: {s: [] for s in starts} for m in built
    }
    cache: dict[str, dict[int, tuple[Any, float]]] = {m.name: {} for m in built}
    for pair in pairs:
        for m in built:
            prepared = cache[m.name]
            for old in [k for k in prepared if k < pair]:
                del prepared[old]  # the target is the previous pair's source, prepared once
            for i in (pair, pair + 1):
                if i not in prepared:
                    prepared[i] = runner.timed(m.prepare, clouds[i])
            for start, rec in run_pair(m, prepared, seq, pair, starts).items():
                records[m.name][start].append(rec)
    motion = runner.motion_stats(np.stack([seq.truth(p) for p in pairs]))
    points = {'min': min(sizes), 'median': float(np.median(sizes)), 'max': max(sizes)}
    return {
        'note': seq.note, 'voxel_m': voxel, 'pairs': list(pairs), 'points_per_scan': points,
        'reference_motion': motion,
        'starts': {
            s: {m: {'summary': runner.summarize(r[s]), 'pairs': r[s]} for m, r in records.items()}
            for s in starts
        },
    }  # fmt: skip


def _paper(entry: dict[str, Any]) -> str:
    paper = PAPER_TABLE1.get(entry['name'])
    return f'{paper[0]}: {paper[1]}° / {paper[2]} m' if paper else ''


def _failures(entry: dict[str, Any]) -> str:
    s = entry['summary']
    return f'{s["failures"]}/{s["n"]}' + (f' ({s["n_errors"]} raised)' if s['n_errors'] else '')


#: The columns of a table: a row per method.
COLUMNS: list[report.Column] = [
    ('method', 'name:s'), ('mean e_R (°)', 'summary.e_R_deg.mean:.3f'),
    ('median e_R (°)', 'summary.e_R_deg.median:.3f'), ('mean e_t (m)', 'summary.e_t_m.mean:.4f'),
    ('median e_t (m)', 'summary.e_t_m.median:.4f'), ('failures', _failures),
    ('median ms/pair', 'summary.ms.median:.0f'), ('paper Table 1 (ETH): avg e_R / e_t', _paper),
]  # fmt: skip


def markdown(results: dict[str, Any]) -> str:
    """The markdown tables of a results dict (what ``paper_table.md`` holds)."""
    lines = []
    for name, block in results['datasets'].items():
        mot, pts = block['reference_motion'], block['points_per_scan']
        lines += [
            f'**{name}**: {len(block["pairs"])} pair(s), voxel {block["voxel_m"]:.2f} m '
            f'({pts["min"]}–{pts["max"]} points per scan); reference motion between scans '
            f'{mot["rotation_deg_median"]:.1f}° / {mot["translation_m_median"]:.2f} m median, '
            f'up to {mot["rotation_deg_max"]:.1f}° / {mot["translation_m_max"]:.2f} m. '
            f'Reference: {block["note"]}.',
            '',
        ]
        for start, by_method in block['starts'].items():
            title = f'*{name}, start: {start.replace("_", " ")}*'
            lines += [title, '', *report.column_table(COLUMNS, report.named(by_method)), '']
    meta = results['meta']
    lines.append(
        f'Failure: e_R > 2° or e_t > 0.2 m. Time: preparing the new scan + registering it, '
        f'{meta["threads"]} thread(s), {meta["machine"]["cpu"]}; gate '
        f'{methods.GATE_VOXELS:g} voxels, iteration cap {methods.MAX_ITERATIONS}, convergence '
        f'tests end first (benchmarks/methods.py). Generated by `{meta["command"]}` at commit '
        f'{meta["machine"]["git_commit"]}.'
    )
    return '\n'.join(lines) + '\n'


OPTIONS: list[report.Option] = [
    ('--methods', {'nargs': '+', 'default': list(methods.ALL_METHODS), 'metavar': 'NAME'}),
    ('--pairs', {'type': int, 'help': 'evenly spread pairs per data set (default all)'}),
    ('--starts', {'nargs': '+', 'default': list(STARTS), 'choices': STARTS}),
    ('--datasets', {'nargs': '+', 'default': ['balm', 'small_gicp_pair']}),
    ('--eth', {'type': Path, 'help': 'ETH sequence folder'}),
    ('--voxel', {'type': float, 'default': 0.0, 'help': '0: ~10,000 points per scan'}),
    ('--threads', {'type': int, 'default': 1}),
]  # fmt: skip


def run(args: argparse.Namespace, argv: list[str]) -> dict[str, Any]:
    logging.basicConfig(level=logging.INFO, format='%(message)s')
    names = list(args.datasets) + ([f'eth:{args.eth}'] if args.eth is not None else [])
    table1 = {k: {'name': v[0], 'e_R_deg': v[1], 'e_t_m': v[2]} for k, v in PAPER_TABLE1.items()}
    command = ' '.join(['python3 benchmarks/paper_table.py', *argv])
    meta = {'command': command, 'threads': args.threads, 'machine': report.machine_info(),
            'paper_table1': table1}  # fmt: skip
    results: dict[str, Any] = {'meta': meta, 'datasets': {}}
    for name in names:
        seq = datasets.load_dataset(name)
        voxel = args.voxel or methods.paper_voxel(seq.raw(0))
        built = methods.make_methods(args.methods, voxel=voxel, threads=args.threads)
        pairs = perturb.select_pairs(seq.n_pairs, args.pairs)
        block = run_sequence(seq, built, pairs, args.starts, voxel)
        block['method_params'] = {m.name: {'library': m.library, **m.params} for m in built}
        results['datasets'][seq.name] = block
    return results


if __name__ == '__main__':
    raise SystemExit(report.experiment_main(__doc__, 'paper_table', OPTIONS, run, markdown))
