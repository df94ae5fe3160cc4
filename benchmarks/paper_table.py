"""The paper's Table 1 protocol on the real data here: every method, two starts, consecutive pairs.

Fahandezh-Saadi et al. report the average rotation / translation error of ICP, point-to-plane
ICP, CICP, GICP, NDT and their method over consecutive scans of ETH Hauptgebaeude, from the
identity, after downsampling to ~10,000 points. This script runs the same protocol on

- ``balm``: the 49 consecutive pairs of ``../shared/data/balm`` (real, 72-90k points per scan);
- ``small_gicp_pair``: the one real pair of ``../shared/data/small_gicp_pair``;
- ``--eth PATH``: an ETH sequence folder (``Hokuyo_<i>.csv`` + ``pose_scanner_leica.csv``),
  when you have it;

from the identity and from the constant-velocity guess (the previous pair's reference motion,
identity for the first pair; not applicable to a single pair). Every method gets the same voxel
downsampling (the voxel giving ~10,000 points on the data set's first scan, as in the paper);
see ``benchmarks/methods.py`` for each method's settings.

Time per pair = preparing the new (source) scan + registering it; the target was prepared once
before, as an odometry does. Single thread (``--threads``) by default.

Usage::

    nice python3 benchmarks/paper_table.py                      # full run (~15 min)
    python3 benchmarks/paper_table.py --pairs 5 --methods gicp kentreg_robust   # quick look

Writes ``benchmarks/results/paper_table.json`` and ``paper_table.md`` (``--out`` to change).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Sequence as Seq
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.common import (  # noqa: E402
    RESULTS,
    SHARED_DATA,
    Sequence,
    errors,
    fmt,
    load_balm,
    load_eth,
    load_small_gicp_pair,
    machine_info,
    select_pairs,
    summarize,
    timed,
    write_json,
)
from benchmarks.methods import (  # noqa: E402
    ALL_METHODS,
    GATE_VOXELS,
    MAX_ITERATIONS,
    Method,
    make_methods,
    paper_voxel,
    voxel_downsample,
)

logger = logging.getLogger('paper_table')

STARTS = ('identity', 'constant_velocity')

#: The paper's Table 1 (ETH Hauptgebaeude, from identity): average e_R (deg), e_t (m).
PAPER_TABLE1: dict[str, tuple[str, float, float]] = {
    'icp_pt2pt': ('ICP', 1.27, 0.403),
    'icp_pt2pl': ('ICPp2pl', 0.57, 0.164),
    'cicp': ('CICP', 1.162, 0.260),
    'gicp': ('GICP', 0.23, 0.025),
    'ndt': ('NDT', 0.52, 0.070),
    'kentreg_paper': ('Ours', 0.66, 0.018),
}


def motion_stats(seq: Sequence, pairs: Seq[int]) -> dict[str, float]:
    """Median and max rotation (deg) and translation (m) of the reference pair motions."""
    rot, trans = [], []
    for p in pairs:
        e_R, e_t = errors(seq.truth(p), np.eye(4))
        rot.append(e_R)
        trans.append(e_t)
    return {
        'rotation_deg_median': float(np.median(rot)),
        'rotation_deg_max': float(np.max(rot)),
        'translation_m_median': float(np.median(trans)),
        'translation_m_max': float(np.max(trans)),
    }


def run_pair(
    method: Method,
    cache: dict[int, tuple[Any, float]],
    seq: Sequence,
    clouds: dict[int, np.ndarray],
    pair: int,
    starts: Seq[str],
) -> dict[str, dict[str, Any]]:
    """One pair with one method from every start: ``{start: record}``.

    ``cache`` holds the method's prepared scans (index -> (prep, ms)); the target of a pair is
    usually the previous pair's source, prepared once as in odometry.
    """
    for old in [k for k in cache if k < pair]:
        del cache[old]
    for i in (pair, pair + 1):
        if i not in cache:
            cache[i] = timed(method.prepare, clouds[i])
    target, _ = cache[pair]
    source, prep_ms = cache[pair + 1]
    truth = seq.truth(pair)
    out = {}
    for start in starts:
        init = np.eye(4) if start == 'identity' else seq.constant_velocity(pair)
        record: dict[str, Any] = {'pair': pair, 'prepare_ms': prep_ms}
        try:
            T, reg_ms = timed(method.register, source, target, init)
            e_R, e_t = errors(T, truth)
        except Exception as exc:  # a method that raises (any error) is a failed pair
            logger.warning('%s on %s pair %d (%s): %s', method.name, seq.name, pair, start, exc)
            reg_ms, e_R, e_t = float('nan'), float('nan'), float('nan')
            record['error'] = f'{type(exc).__name__}: {exc}'
        record.update({'e_R_deg': e_R, 'e_t_m': e_t, 'register_ms': reg_ms})
        record['ms'] = prep_ms + reg_ms
        out[start] = record
    return out


def run_sequence(
    seq: Sequence,
    methods: Seq[Method],
    pairs: Seq[int],
    starts: Seq[str],
    voxel: float,
) -> dict[str, Any]:
    """Run every method on ``pairs`` of ``seq``; returns the data set's results block."""
    needed = sorted({p for p in pairs} | {p + 1 for p in pairs})
    clouds = {i: voxel_downsample(seq.load(i), voxel) for i in needed}
    sizes = [len(c) for c in clouds.values()]
    if seq.T_world_sensor is None:
        starts = [s for s in starts if s == 'identity']
    block: dict[str, Any] = {
        'note': seq.note,
        'voxel_m': voxel,
        'pairs': list(pairs),
        'points_per_scan': {
            'min': min(sizes),
            'median': float(np.median(sizes)),
            'max': max(sizes),
        },
        'reference_motion': motion_stats(seq, pairs),
        'starts': {s: {} for s in starts},
    }
    # Pairs outer, methods inner: every method sees the same stretch of machine load.
    caches: dict[str, dict[int, tuple[Any, float]]] = {m.name: {} for m in methods}
    records: dict[str, dict[str, list[dict[str, Any]]]] = {
        m.name: {s: [] for s in starts} for m in methods
    }
    t0 = time.perf_counter()
    for k, pair in enumerate(pairs):
        for method in methods:
            for start, rec in run_pair(
                method, caches[method.name], seq, clouds, pair, starts
            ).items():
                records[method.name][start].append(rec)
        logger.info(
            '%s: pair %d/%d (%.0f s)', seq.name, k + 1, len(pairs), time.perf_counter() - t0
        )
    for method in methods:
        parts = []
        for start in starts:
            rows = records[method.name][start]
            summ = summarize(rows)
            block['starts'][start][method.name] = {'summary': summ, 'pairs': rows}
            parts.append(
                f'{start}: {fmt(summ["e_R_deg"]["median"], ".3f")} deg / '
                f'{fmt(summ["e_t_m"]["median"], ".4f")} m median, {summ["failures"]} fail, '
                f'{fmt(summ["ms"]["median"], ".0f")} ms'
            )
        logger.info('%s %-32s %s', seq.name, method.name, ', '.join(parts))
    return block


def markdown(results: dict[str, Any]) -> str:
    """The markdown tables of a results dict (what ``paper_table.md`` holds)."""
    lines = []
    for name, block in results['datasets'].items():
        mot = block['reference_motion']
        pts = block['points_per_scan']
        lines.append(
            f'**{name}**: {len(block["pairs"])} pair(s), voxel {block["voxel_m"]:.2f} m '
            f'({pts["min"]}–{pts["max"]} points per scan); reference motion between scans '
            f'{mot["rotation_deg_median"]:.1f}° / {mot["translation_m_median"]:.2f} m median, '
            f'up to {mot["rotation_deg_max"]:.1f}° / {mot["translation_m_max"]:.2f} m. '
            f'Reference: {block["note"]}.'
        )
        lines.append('')
        for start, by_method in block['starts'].items():
            lines.append(f'*{name}, start: {start.replace("_", " ")}*')
            lines.append('')
            lines.append(
                '| method | mean e_R (°) | median e_R (°) | mean e_t (m) | median e_t (m) '
                '| failures | median ms/pair | paper Table 1 (ETH): avg e_R / e_t |'
            )
            lines.append('|---|---|---|---|---|---|---|---|')
            for method, entry in by_method.items():
                s = entry['summary']
                paper = PAPER_TABLE1.get(method)
                paper_txt = f'{paper[0]}: {paper[1]}° / {paper[2]} m' if paper else ''
                errs = f' ({s["n_errors"]} raised)' if s['n_errors'] else ''
                lines.append(
                    f'| {method} | {fmt(s["e_R_deg"]["mean"], ".3f")} '
                    f'| {fmt(s["e_R_deg"]["median"], ".3f")} | {fmt(s["e_t_m"]["mean"], ".4f")} '
                    f'| {fmt(s["e_t_m"]["median"], ".4f")} | {s["failures"]}/{s["n"]}{errs} '
                    f'| {fmt(s["ms"]["median"], ".0f")} | {paper_txt} |'
                )
            lines.append('')
    meta = results['meta']
    lines.append(
        f'Failure: e_R > 2° or e_t > 0.2 m. Time: preparing the new scan + registering it, '
        f'{meta["threads"]} thread(s), {meta["machine"]["cpu"]}; gate {GATE_VOXELS:g} voxels, '
        f'iteration cap {MAX_ITERATIONS}, convergence tests end first (benchmarks/methods.py). '
        f'Generated by `{meta["command"]}` at commit {meta["machine"]["git_commit"]}.'
    )
    return '\n'.join(lines) + '\n'


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--methods', nargs='+', default=list(ALL_METHODS), metavar='NAME')
    parser.add_argument(
        '--pairs', type=int, default=None, help='evenly spread pairs per data set (default all)'
    )
    parser.add_argument('--starts', nargs='+', default=list(STARTS), choices=STARTS)
    parser.add_argument('--datasets', nargs='+', default=['balm', 'small_gicp_pair'])
    parser.add_argument('--eth', type=Path, default=None, help='ETH sequence folder')
    parser.add_argument('--data', type=Path, default=SHARED_DATA, help='../shared/data')
    parser.add_argument('--voxel', type=float, default=0.0, help='0: ~10,000 points per scan')
    parser.add_argument('--threads', type=int, default=1)
    parser.add_argument('--out', type=Path, default=RESULTS)
    return parser


def main(argv: Seq[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format='%(message)s')
    loaders = {
        'balm': lambda: load_balm(args.data / 'balm'),
        'small_gicp_pair': lambda: load_small_gicp_pair(args.data / 'small_gicp_pair'),
    }
    sequences = []
    for name in args.datasets:
        if name not in loaders:
            raise SystemExit(f'Unknown data set {name!r}; choose from {sorted(loaders)}.')
        sequences.append(loaders[name]())
    if args.eth is not None:
        sequences.append(load_eth(args.eth))
    command = 'python3 benchmarks/paper_table.py ' + ' '.join(
        argv if argv is not None else sys.argv[1:]
    )
    results: dict[str, Any] = {
        'meta': {
            'command': command.strip(),
            'threads': args.threads,
            'machine': machine_info(),
            'paper_table1': {
                k: {'name': v[0], 'e_R_deg': v[1], 'e_t_m': v[2]} for k, v in PAPER_TABLE1.items()
            },
        },
        'datasets': {},
    }
    for seq in sequences:
        voxel = args.voxel or paper_voxel(seq.load(0))
        methods = make_methods(args.methods, voxel=voxel, threads=args.threads)
        pairs = select_pairs(seq.n_pairs, args.pairs)
        block = run_sequence(seq, methods, pairs, args.starts, voxel)
        block['method_params'] = {m.name: {'library': m.library, **m.params} for m in methods}
        results['datasets'][seq.name] = block
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / 'paper_table.json', results)
    text = markdown(results)
    (args.out / 'paper_table.md').write_text(text)
    print(text)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
