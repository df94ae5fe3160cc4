"""The paper's outlier experiment on real BALM pairs: errors against the injected outlier share.

Fahandezh-Saadi et al. inject 0-40 % outliers into a staircase scan and plot the mean rotation
and translation errors over 100 trials: ICP and NDT degrade, their method stays flat. Here:

- a trial is a consecutive BALM pair drawn with a seeded RNG (the same pairs at every level),
  registered from the constant-velocity start (the previous pair's reference motion);
- at level ``f`` both scans get ``K = round(M f / (1 - f))`` points drawn uniformly in the raw
  scan's bounding box, where ``M`` is the scan's point count after the shared voxel
  downsampling, so outliers are ``f`` of the points every method receives. They are added to
  the raw scan *before* that downsampling (every method sees the same cloud) and drawn only in
  voxels the scan does not occupy, one per voxel, so each survives as one point (see
  :func:`inject_outliers`); the realised share is measured and reported. Fresh outliers per
  trial and level (seeded);
- every method of ``benchmarks/methods.py`` (default: all but kentreg's ablations).

Usage::

    nice python3 benchmarks/outliers.py                # 5 levels x 100 trials (~35 min)
    python3 benchmarks/outliers.py --trials 3 --methods gicp kentreg_robust   # quick look

Writes ``benchmarks/results/outliers.json``, ``outliers.md`` and ``outliers.png``.
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
    machine_info,
    summarize,
    timed,
    write_json,
)
from benchmarks.methods import (  # noqa: E402
    ALL_METHODS,
    BASE_METHODS,
    Method,
    make_methods,
    paper_voxel,
    voxel_downsample,
)
from kentreg_ros.core.scan.voxels import _voxel_keys  # noqa: E402

logger = logging.getLogger('outliers')

LEVELS = (0.0, 0.1, 0.2, 0.3, 0.4)


def inject_outliers(
    points: np.ndarray, fraction: float, voxel: float, rng: np.random.Generator
) -> tuple[np.ndarray, float]:
    """Add uniform outliers to a raw scan, then downsample it with the shared voxel.

    The outliers are uniform in the raw scan's bounding box, restricted to voxels the scan does
    not occupy and one per voxel (rejection sampling): a point drawn inside an occupied voxel
    would only move that voxel's centroid by less than a voxel, which is noise, not an outlier.
    So every outlier survives the downsampling as one point and the share is exact.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Raw scan.
    fraction : float
        Share of outliers among the downsampled points, in [0, 1).
    voxel : float
        Shared voxel edge (m).
    rng : numpy.random.Generator

    Returns
    -------
    cloud : ndarray, shape (M + K, 3)
        Downsampled scan (``M`` points) with ``K = round(M f / (1 - f))`` outliers.
    realised : float
        ``K / (M + K)``, measured on the result.
    """
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f'Expected `fraction` in [0, 1), got {fraction}.')
    clean = voxel_downsample(points, voxel)
    n_out = int(round(len(clean) * fraction / (1.0 - fraction)))
    if n_out == 0:
        return clean, 0.0
    lo, hi = points.min(axis=0), points.max(axis=0)
    # Every point involved lies in the raw scan's box, so keys on its grid name voxels alike.
    grid = (lo, hi)
    occupied = np.unique(_voxel_keys(clean, voxel, grid))
    chosen = np.empty((0, 3))
    taken = occupied
    for _ in range(100):
        draw = rng.uniform(lo, hi, size=(2 * (n_out - len(chosen)) + 16, 3))
        keys = _voxel_keys(draw, voxel, grid)
        free = ~np.isin(keys, taken)
        _, first = np.unique(keys[free], return_index=True)
        new = draw[free][np.sort(first)][: n_out - len(chosen)]
        chosen = np.concatenate([chosen, new])
        taken = np.union1d(taken, _voxel_keys(new, voxel, grid))
        if len(chosen) == n_out:
            break
    else:
        raise ValueError('The bounding box has too few free voxels for the requested outliers.')
    cloud = voxel_downsample(np.concatenate([points, chosen]), voxel)
    return cloud, (len(cloud) - len(clean)) / len(cloud)


def draw_trials(n_pairs: int, trials: int, seed: int) -> list[int]:
    """The pair of every trial (seeded, with replacement)."""
    return [int(p) for p in np.random.default_rng(seed).integers(0, n_pairs, size=trials)]


def run(
    seq: Sequence,
    methods: Seq[Method],
    levels: Seq[float],
    trial_pairs: Seq[int],
    voxel: float,
    seed: int,
) -> dict[str, Any]:
    """Per level and method, the per-trial records and their summary."""
    raw: dict[int, np.ndarray] = {}
    for p in sorted(set(trial_pairs)):
        for i in (p, p + 1):
            if i not in raw:
                raw[i] = seq.load(i)
    out: dict[str, Any] = {}
    for level in levels:
        t_level = time.perf_counter()
        rows: dict[str, list[dict[str, Any]]] = {m.name: [] for m in methods}
        realised = []
        for trial, pair in enumerate(trial_pairs):
            rng = np.random.default_rng([seed, trial, int(round(level * 1000))])
            target, r_t = inject_outliers(raw[pair], level, voxel, rng)
            source, r_s = inject_outliers(raw[pair + 1], level, voxel, rng)
            realised += [r_t, r_s]
            truth = seq.truth(pair)
            init = seq.constant_velocity(pair)
            for m in methods:
                rec: dict[str, Any] = {'trial': trial, 'pair': pair}
                try:
                    tgt = m.prepare(target)
                    src, prep_ms = timed(m.prepare, source)
                    T, reg_ms = timed(m.register, src, tgt, init)
                    e_R, e_t = errors(T, truth)
                except Exception as exc:  # a method that raises fails the trial
                    logger.warning('%s level %.0f%% trial %d: %s', m.name, level * 100, trial, exc)
                    prep_ms, reg_ms, e_R, e_t = (float('nan'),) * 4
                    rec['error'] = f'{type(exc).__name__}: {exc}'
                rec.update({'e_R_deg': e_R, 'e_t_m': e_t, 'ms': prep_ms + reg_ms})
                rows[m.name].append(rec)
        block = {
            'realised_fraction': {
                'mean': float(np.mean(realised)),
                'min': float(np.min(realised)),
            },
            'methods': {},
        }
        for name, recs in rows.items():
            summ = summarize(recs)
            e_R = np.array([r['e_R_deg'] for r in recs], dtype=np.float64)
            e_t = np.array([r['e_t_m'] for r in recs], dtype=np.float64)
            ok = np.isfinite(e_R) & np.isfinite(e_t)
            for key, v in (('e_R_deg', e_R[ok]), ('e_t_m', e_t[ok])):
                summ[key]['std'] = float(v.std()) if len(v) else float('nan')
                summ[key]['q25'] = float(np.percentile(v, 25)) if len(v) else float('nan')
                summ[key]['q75'] = float(np.percentile(v, 75)) if len(v) else float('nan')
            block['methods'][name] = {'summary': summ, 'trials': recs}
        out[f'{level:.2f}'] = block
        logger.info(
            'level %.0f%% (realised %.1f%%) done in %.0f s: %s',
            level * 100,
            100 * block['realised_fraction']['mean'],
            time.perf_counter() - t_level,
            ', '.join(
                f'{n} {b["summary"]["e_R_deg"]["median"]:.3f}deg'
                for n, b in block['methods'].items()
            ),
        )
    return out


def markdown(results: dict[str, Any]) -> str:
    """Tables of mean / median errors, failures and time per level and method."""
    levels = results['levels']
    meta = results['meta']
    names = list(next(iter(levels.values()))['methods'])
    lines = [
        f'{meta["trials"]} trials per level (seeded BALM pairs, constant-velocity start), voxel '
        f"{meta['voxel_m']:.2f} m; outliers uniform in each raw scan's bounding box "
        '(free voxels only), added before the shared downsampling. Realised outlier share of '
        'the final points: '
        + ', '.join(
            f'{float(k) * 100:.0f} % → {v["realised_fraction"]["mean"] * 100:.1f} %'
            for k, v in levels.items()
        )
        + '.',
        '',
    ]
    for key, label, spec in (('e_R_deg', 'e_R (°)', '.3f'), ('e_t_m', 'e_t (m)', '.4f')):
        lines.append(f'*{label}: mean ± std / median per outlier level*')
        lines.append('')
        lines.append('| method | ' + ' | '.join(f'{float(k) * 100:.0f} %' for k in levels) + ' |')
        lines.append('|---|' + '---|' * len(levels))
        for n in names:
            cells = []
            for block in levels.values():
                s = block['methods'][n]['summary'][key]
                cells.append(
                    f'{fmt(s["mean"], spec)} ± {fmt(s["std"], spec)} / {fmt(s["median"], spec)}'
                )
            lines.append(f'| {n} | ' + ' | '.join(cells) + ' |')
        lines.append('')
    lines.append('*Failures (e_R > 2° or e_t > 0.2 m) and median ms per pair per level*')
    lines.append('')
    lines.append('| method | ' + ' | '.join(f'{float(k) * 100:.0f} %' for k in levels) + ' |')
    lines.append('|---|' + '---|' * len(levels))
    for n in names:
        cells = []
        for block in levels.values():
            s = block['methods'][n]['summary']
            cells.append(f'{s["failures"]}/{s["n"]}, {fmt(s["ms"]["median"], ".0f")} ms')
        lines.append(f'| {n} | ' + ' | '.join(cells) + ' |')
    lines.append('')
    lines.append(
        f"Time: preparing both scans is needed per trial, the column counts the new scan's "
        f'preparation + registration, {meta["threads"]} thread(s). Generated by '
        f'`{meta["command"]}` at commit {meta["machine"]["git_commit"]}.'
    )
    return '\n'.join(lines) + '\n'


def plot(results: dict[str, Any], path: Path) -> None:
    """Median (line) and interquartile range (band) of e_R and e_t, and failure rate, per level."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    levels = results['levels']
    x = np.array([float(k) * 100 for k in levels])
    names = list(next(iter(levels.values()))['methods'])
    fig, axes = plt.subplots(1, 3, figsize=(16, 5))
    for i, n in enumerate(names):
        color = plt.cm.tab10(i % 10)
        style = '-' if n.startswith('kentreg') else '--'
        for ax, key in zip(axes[:2], ('e_R_deg', 'e_t_m'), strict=True):
            s = [levels[k]['methods'][n]['summary'][key] for k in levels]
            med = np.array([v['median'] for v in s], dtype=float)
            lo = np.array([v['q25'] for v in s], dtype=float)
            hi = np.array([v['q75'] for v in s], dtype=float)
            ax.plot(x, med, style, marker='o', color=color, label=n)
            ax.fill_between(x, lo, hi, color=color, alpha=0.12)
        fail = [100 * levels[k]['methods'][n]['summary']['failure_rate'] for k in levels]
        axes[2].plot(x, fail, style, marker='o', color=color, label=n)
    axes[0].set_ylabel('rotation error e_R (deg)')
    axes[1].set_ylabel('translation error e_t (m)')
    axes[2].set_ylabel('failures (%): e_R > 2 deg or e_t > 0.2 m')
    for ax in axes[:2]:
        ax.set_yscale('log')
    for ax in axes:
        ax.set_xlabel('injected outliers (% of the downsampled points)')
        ax.set_xticks(x)
        ax.grid(True, which='both', alpha=0.3)
    axes[2].set_ylim(-2, 102)
    axes[2].legend(fontsize=8, loc='upper left')
    meta = results['meta']
    fig.suptitle(
        f'BALM, {meta["trials"]} trials per level, constant-velocity start: '
        'median (line) and interquartile range (band)'
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--methods', nargs='+', default=list(BASE_METHODS), choices=ALL_METHODS)
    parser.add_argument('--levels', nargs='+', type=float, default=list(LEVELS))
    parser.add_argument('--trials', type=int, default=100)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--data', type=Path, default=SHARED_DATA, help='../shared/data')
    parser.add_argument('--voxel', type=float, default=0.0, help='0: ~10,000 points per scan')
    parser.add_argument('--threads', type=int, default=1)
    parser.add_argument('--out', type=Path, default=RESULTS)
    return parser


def main(argv: Seq[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format='%(message)s')
    seq = load_balm(args.data / 'balm')
    voxel = args.voxel or paper_voxel(seq.load(0))
    methods = make_methods(args.methods, voxel=voxel, threads=args.threads)
    trial_pairs = draw_trials(seq.n_pairs, args.trials, args.seed)
    command = 'python3 benchmarks/outliers.py ' + ' '.join(
        argv if argv is not None else sys.argv[1:]
    )
    t0 = time.perf_counter()
    levels = run(seq, methods, args.levels, trial_pairs, voxel, args.seed)
    results = {
        'meta': {
            'command': command.strip(),
            'trials': args.trials,
            'seed': args.seed,
            'voxel_m': voxel,
            'start': 'constant_velocity',
            'threads': args.threads,
            'trial_pairs': trial_pairs,
            'wall_s': time.perf_counter() - t0,
            'machine': machine_info(),
            'method_params': {m.name: {'library': m.library, **m.params} for m in methods},
        },
        'levels': levels,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / 'outliers.json', results)
    text = markdown(results)
    (args.out / 'outliers.md').write_text(text)
    plot(results, args.out / 'outliers.png')
    print(text)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
