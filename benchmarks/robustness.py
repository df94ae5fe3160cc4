"""Robustness: kentreg at its defaults against GICP, point-to-plane ICP and KISS-ICP, raw scans.

Every method as a user gets it (``methods.at_defaults``) on the 50 BALM scans (``strides``:
odometry over every N-th scan; ``outliers``: ``perturb.inject_raw_outliers`` on seeded pairs from
a start 5 deg / 0.2 m off; ``turned``: the source turned 30..180 deg, from the identity); the
protocol is in benchmarks/README.md, section 4.
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeAlias

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository

from benchmarks.harness import datasets, methods, perturb, pipelines, report, runner  # noqa: E402
from benchmarks.harness.report import fmt, table  # noqa: E402
from kentreg_ros.core import KentRegConfig  # noqa: E402
from kentreg_ros.eval import evaluate  # noqa: E402
from kentreg_ros.eval.metrics import FAIL_ROTATION_DEG, FAIL_TRANSLATION_M  # noqa: E402

logger = logging.getLogger('robustness')

Data: TypeAlias = datasets.Sequence
Methods: TypeAlias = Sequence[methods.RawMethod]
TESTS = ('strides', 'outliers', 'turned')
DEFAULT_METHODS = ('kentreg', 'gicp', 'icp_pt2pl', 'kiss_icp')
STRIDES = (1, 2, 3, 4)
LEVELS = (0.0, 0.1, 0.2, 0.3, 0.4)
ANGLES_DEG = (30.0, 60.0, 90.0, 120.0, 150.0, 180.0)
#: Start offset of the outlier test: a few times BALM's median inter-scan motion, well inside
#: every method's basin on clean pairs (all converge from the identity in paper_table.py).
START_OFFSET_DEG = 5.0
START_OFFSET_M = 0.2
#: Pairs per test in a full run (about 30 min on one loaded core); 20 resolve rates to 5 %.
OUTLIER_PAIRS = 20
TURNED_PAIRS = 20
QUICK = {'max_input_scans': 25, 'outlier_pairs': 3, 'turned_pairs': 2}
FAIL_RULE = f'e_R > {FAIL_ROTATION_DEG:g}° or e_t > {FAIL_TRANSLATION_M:g} m'


def _stride_entry(run: runner.Run, T_gt: Any, idx: Any) -> dict[str, Any]:
    """One method's odometry over the strided scans, evaluated like the replay."""
    result = evaluate(run.poses, T_gt)
    pairs = result['pairs']  # its failures and statistics, as in odometry.json
    return {
        'n_pairs': pairs['count'], 'failed': pairs['n_failed'],
        'failed_pairs': [[int(idx[i]), int(idx[i + 1])] for i in pairs['failed_pairs']],
        'e_R_deg': {k: pairs['rotation_deg'][k] for k in ('median', 'max')},
        'e_t_m': {k: pairs['translation_m'][k] for k in ('median', 'max')},
        'ate_rmse_m': None if result['ate'] is None else result['ate']['rmse'],
        'ms_per_scan_median': float(np.median(run.ms_per_scan)),
        'per_pair': {'e_R_deg': pairs['e_R_deg'], 'e_t_m': pairs['e_t_m']},
    }  # fmt: skip


def run_strides(data: Data, built: Methods, strides: Sequence[int], max_input: int | None) -> dict:
    """Odometry of every method over every ``stride``-th scan, evaluated like the replay
    (kentreg: its ``Odometry`` at ``KentRegConfig()``; the peers scan to scan)."""
    assert data.T_world is not None
    scans = data.scans[:max_input]
    makers: dict[str, Callable[[], pipelines.Pipeline]] = {
        m.name: functools.partial(pipelines.scan_to_scan, m) for m in built
    }
    if 'kentreg' in makers:
        makers['kentreg'] = functools.partial(pipelines.KentregPipeline, KentRegConfig())
    out: dict[str, Any] = {}
    for n in strides:
        idx = np.arange(0, len(scans), n)
        T_gt = data.T_world[idx]
        motion = runner.motion_stats(np.linalg.inv(T_gt[:-1]) @ T_gt[1:])
        score = functools.partial(_stride_entry, idx=idx)
        entries = runner.score_pipelines(makers, perturb.stride(n)(scans), T_gt, score=score)
        for name, scored in entries.items():
            if 'run' in scored:
                health = scored['run'].health
                entry = scored['metrics'] | ({'health': health} if name == 'kentreg' else health)
                entries[name] = entry
                failed, ate = f'{entry["failed"]}/{entry["n_pairs"]}', entry['ate_rmse_m']
                logger.info('strides: N=%d %s: %s failed, ATE %s m', n, name, failed,
                            fmt(ate, '.3f'))  # fmt: skip
        out[str(n)] = {'input_indices': idx.tolist(), 'reference_motion': motion,
                       'methods': entries}  # fmt: skip
    return out


def _spread(values: Sequence[float], stats: Sequence[str]) -> dict[str, float]:
    """The numpy statistics ``stats`` ('mean', 'median', 'min', 'max') of ``values``."""
    return {s: float(getattr(np, s)(values)) for s in stats}


def _summary(recs: list[dict[str, Any]]) -> dict[str, Any]:
    """The runner's summary, times over the pairs that ran, and kentreg's own failure flags."""
    summ = runner.summarize(recs, finite_times=True)
    return summ | {'reported_failed': sum(r.get('status') == 'failed' for r in recs)}


def _outlier_trial(
    data: Data, level: float, i: int, pair: int, seed: int, shell_share: float,
    realised: list[float],
) -> runner.Trial:  # fmt: skip
    """Pair ``pair`` (trial ``i``) with raw outliers at ``level`` in both scans, from a start
    off by the offsets; the realised shares appended to ``realised``."""
    rng = np.random.default_rng([seed, 2, i])
    offset = perturb.offset_transform(rng, START_OFFSET_DEG, START_OFFSET_M)
    rng = np.random.default_rng([seed, 2, i, int(round(level * 1000))])
    inject = functools.partial(perturb.inject_raw_outliers, shell_share=shell_share)
    target, tgt_out = inject(data.raw(pair), level, rng)
    source, src_out = inject(data.raw(pair + 1), level, rng)
    realised += [tgt_out.mean(), src_out.mean()]

    def mark(row: dict[str, Any]) -> None:
        if np.isfinite(row['voxel_m']):
            share = perturb.outlier_voxel_share(source, src_out, row['voxel_m'])
            row['outlier_share_after_downsampling'] = share

    truth, extra = data.truth(pair), {'trial': i, 'pair': pair}
    return runner.Trial(target, source, truth, {'': truth @ offset}, extra, mark=mark)


def run_outliers(
    data: Data, built: Methods, levels: Sequence[float], pairs: Sequence[int], seed: int,
    shell_share: float,
) -> dict[str, Any]:  # fmt: skip
    """Per level and method, the per-pair records, their summary and the clean-median ratio."""
    out: dict[str, Any] = {}
    for level in levels:
        realised: list[float] = []
        trials = (_outlier_trial(data, level, i, p, seed, shell_share, realised)
                  for i, p in enumerate(pairs))  # fmt: skip
        rows = runner.run_trials(built, trials)
        methods_out = {}
        for name, by_start in rows.items():
            recs = by_start['']
            shares = [r['outlier_share_after_downsampling'] for r in recs
                      if 'outlier_share_after_downsampling' in r]  # fmt: skip
            voxels = [r['voxel_m'] for r in recs if np.isfinite(r['voxel_m'])]
            summ = _summary(recs) | {
                'outlier_share_after_downsampling': float(np.mean(shares)) if shares else np.nan,
                'voxel_m_median': float(np.median(voxels)) if voxels else np.nan,
            }
            methods_out[name] = {'summary': summ, 'pairs': recs}
        spread = _spread(realised, ('mean', 'min', 'max'))
        out[f'{level:.2f}'] = {'realised_share': spread, 'methods': methods_out}
        logger.info('outliers: %.0f %% done', 100 * level)
    clean = out.get(f'{min(levels):.2f}') if levels else None
    for block in out.values():
        for name, entry in block['methods'].items():
            base = clean['methods'][name]['summary']['e_R_deg']['median'] if clean else None
            med = entry['summary']['e_R_deg']['median']
            ok = base and np.isfinite(base) and np.isfinite(med)
            entry['summary']['median_e_R_ratio_to_clean'] = med / base if ok else float('nan')
    return out


def run_turned(
    data: Data, built: Methods, angles: Sequence[float], pairs: Sequence[int], seed: int
) -> dict:
    """Per angle and method, the records of pairs whose source was turned, from the identity."""
    reference_angle: dict[str, list[float]] = {f'{a:g}': [] for a in angles}

    def trial(i: int, pair: int, angle: float) -> runner.Trial:
        T_turn = perturb.turn_transform(np.random.default_rng([seed, 3, i, int(angle)]), angle)
        ref = data.truth(pair) @ np.linalg.inv(T_turn)
        angle_deg = np.degrees(Rotation.from_matrix(ref[:3, :3]).magnitude())
        reference_angle[f'{angle:g}'].append(float(angle_deg))
        turned = perturb.transform(T_turn, data.raw(pair + 1))
        # No prior at all: kentreg's register() without init, the peers from the identity.
        extra = {'trial': i, 'pair': pair}
        return runner.Trial(data.raw(pair), turned, ref, {f'{angle:g}': None}, extra, (pair, None))

    trials = (trial(i, p, a) for i, p in enumerate(pairs) for a in angles)
    rows = runner.run_trials(built, trials)
    out: dict[str, Any] = {}
    for key, degrees in reference_angle.items():
        spread = _spread(degrees, ('min', 'median', 'max'))
        out[key] = {'reference_rotation_deg': spread, 'methods': {}}
        for name, by_angle in rows.items():
            summ = _summary(by_angle[key])
            summ['recovered'] = summ['n'] - summ['failures']
            summ['recovered_fraction'] = summ['recovered'] / summ['n'] if summ['n'] else None
            out[key]['methods'][name] = {'summary': summ, 'pairs': by_angle[key]}
    return out


# --------------------------------------------------------------------------------------------
# Report


def _run_at(meta: dict[str, Any]) -> list[str]:
    commit = meta['machine'].get('git') or meta['machine'].get('git_commit') or '?'
    return ['', f'Run at {commit}: `{meta["command"]}`.', '']


def _raised_note(summary: dict[str, Any]) -> str:
    return f' ({summary["n_errors"]} raised)' if summary['n_errors'] else ''


def _percent(key: str) -> str:
    return f'{float(key) * 100:.0f} %'


def _strides_md(strides: dict[str, Any]) -> list[str]:
    meta, rows = strides['meta'], []
    values = ('e_R_deg.median:.3f', 'e_R_deg.max:.2f', 'e_t_m.median:.4f', 'e_t_m.max:.3f',
              'ate_rmse_m:.3f', 'ms_per_scan_median:.0f')  # fmt: skip
    for n, block in strides['strides'].items():
        ref = block['reference_motion']
        motion = (
            f'{ref["rotation_deg_median"]:.1f}° / {ref["rotation_deg_max"]:.1f}°, '
            f'{ref["translation_m_median"]:.2f} / {ref["translation_m_max"]:.2f} m'
        )
        for i, (name, m) in enumerate(block['methods'].items()):
            head = [n, motion if i == 0 else '', name]
            if 'error' in m:
                rows.append([*head, f'error: {m["error"]}', '', '', '', '', '', ''])
            else:
                rows.append([*head, f'{m["failed"]}/{m["n_pairs"]}', *report.cells(m, *values)])
    lines = [
        f'**Strides** ({meta["input"]}, every N-th of {meta["n_input_scans"]} scans, stamps '
        'unchanged). kentreg: its `Odometry` with `KentRegConfig()` (what `kentreg_replay '
        '--stride N` runs); peers: scan-to-previous-scan, each started from its own previous '
        'estimate (constant velocity; identity for the first pair). A pair joins consecutive '
        f'processed scans and fails when {FAIL_RULE}; ATE after SE(3) alignment.',
        '',
        *table(
            'N | reference motion per pair: median / max | method | failed pairs | median e_R (°) '
            '| max e_R (°) | median e_t (m) | max e_t (m) | ATE rmse (m) | median ms/scan',
            rows,
        ),
    ]
    health = [
        f'N={n}: '
        + ', '.join(f'{k} {v}' for k, v in b['methods']['kentreg']['health'].items() if v)
        for n, b in strides['strides'].items()
        if 'health' in b['methods'].get('kentreg', {})
    ]
    if health:
        lines += ['', "kentreg's odometry health per stride: " + '; '.join(health) + '.']
    return [*lines, *_run_at(meta)]


def _e_R(entry: dict[str, Any]) -> str:
    median, ratio, mean = report.cells(
        entry['summary'], 'e_R_deg.median:.3f', 'median_e_R_ratio_to_clean:.1f', 'e_R_deg.mean:.3f'
    )
    return f'{median} ({ratio}×) / {mean}'  # fmt: skip


def _e_t(entry: dict[str, Any]) -> str:
    return ' / '.join(report.cells(entry['summary'], 'e_t_m.median:.4f', 'e_t_m.mean:.4f'))


def _failures(entry: dict[str, Any]) -> str:
    s = entry['summary']
    share = fmt(100 * s['outlier_share_after_downsampling'], '.0f')
    ms = fmt(s['ms']['median'], '.0f')
    return f'{s["failures"]}/{s["n"]}{_raised_note(s)}, {share} %, {ms} ms'


def _outliers_md(outliers: dict[str, Any]) -> list[str]:
    meta, levels = outliers['meta'], outliers['levels']
    head = ['method', *map(_percent, levels)]
    shell = f', {meta["shell_share"] * 100:.0f} % of them in the range shell'
    realised = report.realised(levels, 'realised_share', '.2f')
    lines = [
        f'**Raw outliers** ({meta["n_pairs"]} of the {meta["n_available_pairs"]} consecutive '
        f'pairs, drawn without replacement, seed {meta["seed"]}; the same pairs at every '
        f"level). Outliers uniform in each raw scan's bounding box"
        f'{shell if meta["shell_share"] else ""}, added before any downsampling as the stated '
        f'share of the raw cloud (realised: {realised}); every method at its defaults on the '
        'contaminated raw scans; start = reference perturbed by '
        f'{meta["start_offset"]["degrees"]:g}° about a random axis and '
        f'{meta["start_offset"]["metres"]:g} m.',
    ]
    for caption, cell in (
        ("*e_R (°): median (× the method's own outlier-free median) / mean*", _e_R),
        ('*e_t (m): median / mean*', _e_t),
        (f'*Failures ({FAIL_RULE}; "raised": the method threw an exception, counted as '
         'failed); outlier share among the points the method downsampled to; median ms per '
         'pair that ran (source preparation + registration)*', _failures),
    ):  # fmt: skip
        lines += ['', caption, '', *table(head, report.method_rows(levels, cell))]
    kentreg = {k: b['methods']['kentreg']['summary'] for k, b in levels.items()
               if 'kentreg' in b['methods']}  # fmt: skip
    if kentreg:
        flagged = ', '.join(f'{_percent(k)}: {s["reported_failed"]}' for k, s in kentreg.items())
        voxel = ', '.join(
            f'{_percent(k)} → {fmt(s["voxel_m_median"], ".2f")} m' for k, s in kentreg.items()
        )
        lines += [
            '',
            f"kentreg's own `status == 'failed'` per level: {flagged}. Its automatic "
            f'voxel (median over the source scans): {voxel}; the peers use '
            f'{meta["peer_voxel_m"]:.2f} m throughout.',
        ]
    return [
        *lines,
        '',
        'Downsampled outlier share: voxels (origin-anchored grid at the voxel the method '
        'used) holding only injected points, among all occupied voxels of the source scan; '
        'for kentreg before its normal-based outlier test.',
        *_run_at(meta),
    ]


def _recovered(entry: dict[str, Any]) -> str:
    s = entry['summary']
    share, ms = fmt(100 * s['recovered_fraction'], '.0f'), fmt(s['ms']['median'], '.0f')
    return f'{s["recovered"]}/{s["n"]} ({share} %), {ms} ms{_raised_note(s)}'


def _turned_md(turned: dict[str, Any]) -> list[str]:
    meta, angles = turned['meta'], turned['angles']
    references = (f'{b["reference_rotation_deg"]["median"]:.0f}°' for b in angles.values())
    lines = [
        f'**Turned pairs** ({meta["n_pairs"]} of the {meta["n_available_pairs"]} consecutive '
        f'pairs, drawn without replacement, seed {meta["seed"]}): the raw source scan turned '
        'about a seeded random axis through the sensor origin, every method started from the '
        'identity (kentreg: `register()` without `init`, which searches rotations); recovered = '
        f'not failed ({FAIL_RULE}); median ms per pair (source preparation + registration).',
        '',
        *table(['method', *(f'{k}°' for k in angles)], report.method_rows(angles, _recovered)),
        '| *reference rotation (median)* | ' + ' | '.join(references) + ' |',
    ]
    flagged = [f'{k}°: {b["methods"]["kentreg"]["summary"]["reported_failed"]}'
               for k, b in angles.items() if 'kentreg' in b['methods']]  # fmt: skip
    if flagged:
        lines += ['', "kentreg's own `status == 'failed'` per angle: " + ', '.join(flagged) + '.']
    return [*lines, *_run_at(meta)]


def markdown(results: dict[str, Any]) -> str:
    """Tables of every test present in ``results`` (the numbers of the JSON, rounded)."""
    lines: list[str] = []
    for test, render in zip(TESTS, (_strides_md, _outliers_md, _turned_md), strict=True):
        if results.get(test):
            lines += render(results[test])
    meta, machine = results['meta'], results['meta']['machine']
    lines.append(
        f'Methods pinned to {meta["threads"]} thread(s); {machine["cpu"]}, load average '
        f'{machine["load_avg_at_start"][0]:.1f} at the start of the last run ({machine["date"]}).'
    )
    return '\n'.join(lines) + '\n'


def plot(results: dict[str, Any], path: Path) -> None:
    """Strides (failures, ATE, worst e_R), outliers (median e_R, failures), turned (recovered)."""
    nan = float('nan')
    strides, levels, angles = (
        results.get(t, {}).get(k)
        for t, k in zip(TESTS, ('strides', 'levels', 'angles'), strict=True)
    )
    pct, raw = {'ylim': (-2, 102)}, 'outliers in the raw scan (%)'
    specs = [  # blocks, value, scale, log, x label, y label, title, more axes
        (strides, lambda e: 100 * e['failed'] / e['n_pairs'] if 'failed' in e else nan, 1, '',
         'stride N (every N-th scan)', 'failed pairs (%)', 'strides: failed pairs', pct),
        (strides, lambda e: e.get('ate_rmse_m') or nan, 1, 'y', 'stride N', 'ATE rmse (m)',
         'strides: ATE', {}),
        (levels, lambda e: e['summary']['e_R_deg']['median'], 100, 'y', raw, 'e_R (deg)',
         'raw outliers: median e_R', {}),
        (levels, lambda e: 100 * e['summary']['failure_rate'], 100, '', raw, 'failed pairs (%)',
         'raw outliers: failures', pct),
        (angles, lambda e: 100 * (e['summary']['recovered_fraction'] or 0.0), 1, '',
         'turn of the source scan (deg)', 'recovered (%)', 'turned pairs from the identity', pct),
        (strides, lambda e: e['e_R_deg']['max'] if 'e_R_deg' in e else nan, 1, 'y', 'stride N',
         'e_R (deg)', 'strides: worst pair e_R', {}),
    ]  # fmt: skip
    panels = [
        report.method_panel(b, f, scale=k, log=g, xlabel=x, ylabel=y, title=t, **more)
        for b, f, k, g, x, y, t, more in specs
    ]
    title = (
        'kentreg_ros robustness (BALM): kentreg at KentRegConfig() defaults (solid) against '
        f'the benchmarks/harness/methods.py peers (dashed)\nfailure: {FAIL_RULE}; '
        f'{results["meta"]["threads"]} thread(s)'
    )
    report.plot_panels(path, [panels[:3], panels[3:]], size=(15, 9), title=title)


# --------------------------------------------------------------------------------------------
# Entry point


def _tests(text: str) -> list[str]:
    names = [t.strip() for t in text.split(',') if t.strip()]
    if not names or any(t not in TESTS for t in names):
        raise argparse.ArgumentTypeError(f'expected a subset of {",".join(TESTS)}, got {text!r}')
    return names


OPTIONS: list[report.Option] = [
    ('--quick', {'action': 'store_true', 'help': f'smoke test {QUICK}; out: a tmp folder'}),
    ('--only', {'type': _tests, 'default': list(TESTS), 'metavar': 'TESTS',
                'help': 'comma-separated subset of strides,outliers,turned; the others are kept '
                'from an existing robustness.json'}),
    ('--methods', {'nargs': '+', 'choices': ('kentreg', *methods.ALL_METHODS),
                   'default': list(DEFAULT_METHODS)}),
    ('--seed', {'type': int, 'default': 0, 'help': 'seed of every random draw'}),
    ('--data', {'type': Path, 'help': 'scans with poses (default ../shared/data/balm)'}),
    ('--threads', {'type': int, 'default': 1, 'help': 'CPUs every method may use'}),
    ('--strides', {'nargs': '+', 'type': int, 'default': list(STRIDES)}),
    ('--levels', {'nargs': '+', 'type': float, 'default': list(LEVELS)}),
    ('--angles', {'nargs': '+', 'type': float, 'default': list(ANGLES_DEG)}),
    ('--outlier-pairs', {'type': int, 'help': f'default {OUTLIER_PAIRS}'}),
    ('--turned-pairs', {'type': int, 'help': f'default {TURNED_PAIRS}'}),
    ('--shell-share', {'type': float, 'default': 0.0,
                       'help': "share of the outliers in the sensor's range shell"}),
]  # fmt: skip


def _run_test(test: str, args: argparse.Namespace, data: Data, built: Methods) -> dict:
    """One test's JSON block (without the common metadata)."""
    n_pairs = data.n_pairs
    if test == 'strides':
        max_input = QUICK['max_input_scans'] if args.quick else None
        meta = {
            'n_input_scans': len(data.scans[:max_input]),
            'strides': args.strides,
            'peer_start': 'own previous estimate (constant velocity), identity first',
        }
        return {'meta': meta, 'strides': run_strides(data, built, args.strides, max_input)}
    key = 'outlier_pairs' if test == 'outliers' else 'turned_pairs'
    full = OUTLIER_PAIRS if test == 'outliers' else TURNED_PAIRS
    count = getattr(args, key) or (QUICK[key] if args.quick else full)
    pairs = perturb.draw_pairs(n_pairs, count, args.seed, 2 if test == 'outliers' else 3)
    meta = {'n_pairs': len(pairs), 'n_available_pairs': n_pairs, 'pairs': pairs,
            'pair_draw': 'without replacement, seeded'}  # fmt: skip
    if test == 'outliers':
        body = run_outliers(data, built, args.levels, pairs, args.seed, args.shell_share)
        offset = {'degrees': START_OFFSET_DEG, 'metres': START_OFFSET_M}
        meta |= {'shell_share': args.shell_share, 'start_offset': offset}
        return {'meta': meta, 'levels': body}
    body = run_turned(data, built, args.angles, pairs, args.seed)
    return {'meta': meta | {'start': 'identity'}, 'angles': body}


def run(args: argparse.Namespace, argv: list[str]) -> dict[str, Any]:
    """Run the selected tests (the others kept from ``--out``'s robustness.json)."""
    if args.threads < 1 or min(args.strides) < 1:
        raise SystemExit('--threads and --strides must be >= 1')
    if not all(0.0 <= f < 1.0 for f in args.levels) or not 0.0 <= args.shell_share <= 1.0:
        raise SystemExit('--levels must be in [0, 1) and --shell-share in [0, 1]')
    logging.basicConfig(level=logging.INFO, format='%(name)s: %(message)s')
    methods.limit_threads(args.threads)
    if args.quick and '--out' not in argv:
        args.out = Path(tempfile.gettempdir()) / 'robustness_quick'
    data = datasets.load_recording(args.data or datasets.default_balm())
    voxel = methods.paper_voxel(data.raw(0))
    built = methods.at_defaults(args.methods, voxel, args.threads)
    results: dict[str, Any] = {}
    previous = args.out / 'robustness.json'
    if set(args.only) != set(TESTS) and previous.is_file():
        kept = json.loads(previous.read_text())
        results.update({t: kept[t] for t in TESTS if t in kept and t not in args.only})
    machine = report.machine_info()
    common = {
        'command': ' '.join(['python3', 'benchmarks/robustness.py', *argv]),
        'machine': machine, 'input': data.description, 'ground_truth': data.note,
        'seed': args.seed, 'threads': args.threads, 'quick': args.quick, 'peer_voxel_m': voxel,
        'methods': {m.name: m.params for m in built},
    }  # fmt: skip
    t_all = time.perf_counter()
    for test in (t for t in TESTS if t in args.only):
        block, ms = runner.timed(_run_test, test, args, data, built)
        results[test] = block | {'meta': {**common, **block['meta'], 'wall_s': ms / 1e3}}
    report.finish_machine(machine)
    results['meta'] = {**common, 'tests_run': args.only, 'wall_s': time.perf_counter() - t_all}
    return {'meta': results['meta'], **{t: results[t] for t in TESTS if t in results}}


if __name__ == '__main__':
    raise SystemExit(report.experiment_main(__doc__, 'robustness', OPTIONS, run, markdown, plot))
