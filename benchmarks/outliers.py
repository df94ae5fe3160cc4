"""The paper's outlier experiment on real BALM pairs: errors against the injected share.

Seeded BALM pairs (the same at every level) from the constant-velocity start, both scans with
``perturb.inject_free_voxel_outliers`` at each level (README section 2).

Usage::

    nice python3 benchmarks/outliers.py                # 5 levels x 100 trials
    python3 benchmarks/outliers.py --trials 3 --methods gicp kentreg_robust   # quick look
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TypeAlias

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.harness import datasets, methods, perturb, report, runner  # noqa: E402

logger = logging.getLogger('outliers')

LEVELS = (0.0, 0.1, 0.2, 0.3, 0.4)
Data: TypeAlias = datasets.Sequence
Methods: TypeAlias = Sequence[methods.Method]
Floats: TypeAlias = Sequence[float]
Ints: TypeAlias = Sequence[int]


def _trial(m: methods.Method, target: Any, source: Any, init: Any, truth: Any) -> dict[str, Any]:
    try:
        tgt = m.prepare(target)
        src, prep_ms = runner.timed(m.prepare, source)
        T, reg_ms = runner.timed(m.register, src, tgt, init)
        e_R, e_t = runner.errors(T, truth)
    except Exception as exc:  # a method that raises fails the trial
        logger.warning('%s: %s', m.name, exc)
        nan = float('nan')
        return {'e_R_deg': nan, 'e_t_m': nan, 'ms': nan, 'error': f'{type(exc).__name__}: {exc}'}
    return {'e_R_deg': e_R, 'e_t_m': e_t, 'ms': prep_ms + reg_ms}


def _summary(recs: list[dict[str, Any]]) -> dict[str, Any]:
    summ = runner.summarize(recs)
    for key in ('e_R_deg', 'e_t_m'):
        v = np.array([r[key] for r in recs], dtype=np.float64)
        v = v[np.isfinite([r['e_R_deg'] for r in recs]) & np.isfinite([r['e_t_m'] for r in recs])]
        summ[key]['std'] = float(v.std()) if len(v) else float('nan')
        summ[key]['q25'] = float(np.percentile(v, 25)) if len(v) else float('nan')
        summ[key]['q75'] = float(np.percentile(v, 75)) if len(v) else float('nan')
    return summ


def run(
    seq: Data, built: Methods, levels: Floats, trial_pairs: Ints, voxel: float, seed: int
) -> dict:
    """Per level and method, the per-trial records and their summary."""
    out: dict[str, Any] = {}
    for level in levels:
        rows: dict[str, list[dict[str, Any]]] = {m.name: [] for m in built}
        realised = []
        for trial, pair in enumerate(trial_pairs):
            rng = np.random.default_rng([seed, trial, int(round(level * 1000))])
            target, r_t = perturb.inject_free_voxel_outliers(seq.raw(pair), level, voxel, rng)
            source, r_s = perturb.inject_free_voxel_outliers(seq.raw(pair + 1), level, voxel, rng)
            realised += [r_t, r_s]
            init = seq.constant_velocity(pair)
            for m in built:
                record = _trial(m, target, source, init, seq.truth(pair))
                rows[m.name].append({'trial': trial, 'pair': pair, **record})
        out[f'{level:.2f}'] = {
            'realised_fraction': {
                'mean': float(np.mean(realised)),
                'min': float(np.min(realised)),
            },
            'methods': {n: {'summary': _summary(r), 'trials': r} for n, r in rows.items()},
        }
        logger.info('level %.0f%% done', level * 100)
    return out


def markdown(results: dict[str, Any]) -> str:
    """Tables of mean / median errors, failures and time per level and method."""
    levels, meta, fmt = results['levels'], results['meta'], report.fmt
    head = ['method', *(f'{float(k) * 100:.0f} %' for k in levels)]
    realised = report.realised(levels, 'realised_fraction', '.1f')
    lines = [
        f'{meta["trials"]} trials per level (seeded BALM pairs, constant-velocity start), voxel '
        f"{meta['voxel_m']:.2f} m; outliers uniform in each raw scan's bounding box "
        '(free voxels only), added before the shared downsampling. Realised outlier share of '
        f'the final points: {realised}.',
        '',
    ]
    for key, label, spec in (('e_R_deg', 'e_R (°)', '.3f'), ('e_t_m', 'e_t (m)', '.4f')):

        def cell(entry: dict[str, Any], key: str = key, spec: str = spec) -> str:
            s = entry['summary'][key]
            return f'{fmt(s["mean"], spec)} ± {fmt(s["std"], spec)} / {fmt(s["median"], spec)}'

        lines += [f'*{label}: mean ± std / median per outlier level*', '',
                  *report.table(head, report.method_rows(levels, cell)), '']  # fmt: skip

    def failures(entry: dict[str, Any]) -> str:
        s = entry['summary']
        return f'{s["failures"]}/{s["n"]}, {fmt(s["ms"]["median"], ".0f")} ms'

    lines += [
        '*Failures (e_R > 2° or e_t > 0.2 m) and median ms per pair per level*',
        '',
        *report.table(head, report.method_rows(levels, failures)),
        '',
        "Time: preparing both scans is needed per trial, the column counts the new scan's "
        f'preparation + registration, {meta["threads"]} thread(s). Generated by '
        f'`{meta["command"]}` at commit {meta["machine"]["git_commit"]}.',
    ]
    return '\n'.join(lines) + '\n'


def plot(results: dict[str, Any], path: Path) -> None:
    """Median (line) and interquartile range (band) of e_R and e_t, and failure rate, per level."""
    levels, meta = results['levels'], results['meta']
    x = [float(k) * 100 for k in levels]
    names = list(next(iter(levels.values()))['methods'])
    ylabels = ('rotation error e_R (deg)', 'translation error e_t (m)',
               'failures (%): e_R > 2 deg or e_t > 0.2 m')  # fmt: skip
    xlabel = 'injected outliers (% of the downsampled points)'
    panels = [report.Panel(log=log, axes={'xlabel': xlabel, 'ylabel': ylabel, 'xticks': x})
              for log, ylabel in zip(('y', 'y', ''), ylabels, strict=True)]  # fmt: skip
    panels[2].axes['ylim'] = (-2, 102)
    for name, colour in report.colours(names).items():
        style = {'marker': 'o', 'color': colour, 'linestyle': report.line_style(name)}
        summaries = [levels[k]['methods'][name]['summary'] for k in levels]
        for panel, key in zip(panels, ('e_R_deg', 'e_t_m'), strict=False):
            panel.add(name, x, [s[key]['median'] for s in summaries], **style)
            band = ([s[key]['q25'] for s in summaries], [s[key]['q75'] for s in summaries])
            panel.add(None, x, band, fill=True, color=colour, alpha=0.12)
        panels[2].add(name, x, [100 * s['failure_rate'] for s in summaries], **style)
    title = (f'BALM, {meta["trials"]} trials per level, constant-velocity start: median (line) '
             'and interquartile range (band)')  # fmt: skip
    report.plot_panels(path, [panels], size=(16, 5), title=title)


OPTIONS: list[report.Option] = [
    ('--methods', {'nargs': '+', 'default': list(methods.BASE_METHODS),
                   'choices': methods.ALL_METHODS}),
    ('--levels', {'nargs': '+', 'type': float, 'default': list(LEVELS)}),
    ('--trials', {'type': int, 'default': 100}),
    ('--seed', {'type': int, 'default': 0}),
    ('--voxel', {'type': float, 'default': 0.0, 'help': '0: ~10,000 points per scan'}),
    ('--threads', {'type': int, 'default': 1}),
]  # fmt: skip


def run_experiment(args: argparse.Namespace, argv: list[str]) -> dict[str, Any]:
    logging.basicConfig(level=logging.INFO, format='%(message)s')
    seq = datasets.load_dataset('balm')
    voxel = args.voxel or methods.paper_voxel(seq.raw(0))
    built = methods.make_methods(args.methods, voxel=voxel, threads=args.threads)
    trial_pairs = perturb.draw_trials(seq.n_pairs, args.trials, args.seed)
    t0 = time.perf_counter()
    levels = run(seq, built, args.levels, trial_pairs, voxel, args.seed)
    meta = {
        'command': ' '.join(['python3 benchmarks/outliers.py', *argv]), 'trials': args.trials,
        'seed': args.seed, 'voxel_m': voxel, 'start': 'constant_velocity',
        'threads': args.threads, 'trial_pairs': trial_pairs,
        'wall_s': time.perf_counter() - t0, 'machine': report.machine_info(),
        'method_params': {m.name: {'library': m.library, **m.params} for m in built},
    }  # fmt: skip
    return {'meta': meta, 'levels': levels}


if __name__ == '__main__':
    raise SystemExit(
        report.experiment_main(__doc__, 'outliers', OPTIONS, run_experiment, markdown, plot)
    )
