"""Paste the generated tables into the READMEs and docs/live.md, so they always equal the results.

Every ``results/<name>.md`` replaces the text between ``<!-- BEGIN <name> -->`` and
``<!-- END <name> -->`` in benchmarks/README.md; the main README's ``headline`` table is built
from the results JSON, and docs/live.md's ``live`` block is the opening of ``results/live.md``.
Goals are prose in the READMEs, not code.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
README = HERE / 'README.md'
MAIN_README = HERE.parent / 'README.md'
#: The live-measurement notebook: the ``live`` block (results/live.md's opening and table).
LIVE_PAGE = HERE.parent / 'docs' / 'live.md'
RESULTS = HERE / 'results'
#: The headline's columns: the robustness peers at their defaults.
HEADLINE = {'kentreg': 'kentreg (defaults)', 'gicp': 'GICP (small_gicp)',
            'icp_pt2pl': 'point-to-plane ICP (Open3D)', 'kiss_icp': 'KISS-ICP'}  # fmt: skip


def _stat(summary: dict[str, Any], key: str, stat: str, scale: float = 1.0) -> str:
    value = summary.get(key, {}).get(stat)
    return '–' if value is None else f'{scale * value:.3g}'


def _commit(meta: dict[str, Any]) -> str:
    """The commit a results file records (the benchmarks name it in slightly different keys)."""
    machine: dict[str, Any] = meta['machine'] if isinstance(meta.get('machine'), dict) else {}
    commit = machine.get('git') or machine.get('git_commit') or meta.get('git')
    return str(commit or 'an unrecorded commit')


def _paper_paragraph(paper: dict[str, Any] | None) -> str:
    """The rotation-stage sentence under the headline table (paper_table.json)."""
    ident = paper['datasets']['balm']['starts']['identity'] if paper else {}
    stage, full, pap, avg = (
        ident.get(name, {}).get('summary')
        for name in ('kentreg_robust-no_refine', 'kentreg_robust', 'kentreg_paper',
                     'kentreg_robust-averaged_no_refine')
    )  # fmt: skip
    if not (stage and full and pap):
        return ''
    body = (
        f'\nFrom the identity on the {stage["n"]} sample pairs (paper Table 1 protocol, '
        f'`benchmarks/paper_table.py`): the rotation from normals alone (the shared-'
        f'rotation Kent mixture EM, no refinement) is off by '
        f'{_stat(stage, "e_R_deg", "median")}° median, {_stat(stage, "e_R_deg", "max")}° '
        f'at most; the full pipeline {_stat(full, "e_R_deg", "median")}° / '
        f'{_stat(full, "e_t_m", "median", 1e3)} mm median ({full["failures"]} failed); '
        "the paper's recipe as written (`mode: paper`) "
        f'{_stat(pap, "e_R_deg", "median")}° / '
        f'{_stat(pap, "e_t_m", "median", 1e3)} mm median, {pap["failures"]} of '
        f'{pap["n"]} failed'
    )
    if avg:
        body += (
            "; the same rotation stage with the paper's per-cluster EM and averaging "
            f'instead of the shared M-step {_stat(avg, "e_R_deg", "median")}° median, '
            f'{_stat(avg, "e_R_deg", "max")}° at most'
        )
    return body + '.\n'


def headline_block(
    robustness: dict[str, Any] | None,
    paper: dict[str, Any] | None,
    per_scan: dict[str, Any] | None,
) -> str | None:
    """The README's headline table: every number from a committed result file."""
    if robustness is None:
        return None
    strides = robustness['strides']['strides']
    levels, angles = robustness['outliers']['levels'], robustness['turned']['angles']
    top, s1 = max(levels, key=float), strides['1']['methods']

    def strided(m: str) -> str:
        return ' / '.join(
            '{failed}/{n_pairs}'.format(**strides[n]['methods'][m]) for n in ('2', '3', '4')
        )

    def outliers(m: str) -> str:
        s = levels[top]['methods'][m]['summary']
        return (f'{_stat(s, "e_R_deg", "median")}° ({s["median_e_R_ratio_to_clean"]:.1f}× '
                f'clean), {s["failures"]}/{s["n"]} failed')  # fmt: skip

    def turned(m: str) -> str:
        got = [angles[a]['methods'][m]['summary'] for a in angles]
        recovered, total = sum(g['recovered'] for g in got), sum(g['n'] for g in got)
        return f'{recovered}/{total} ({100 * recovered / total:.0f} %)'

    rows = [
        ('odometry on the 50 sample scans: median e_R / e_t, failed pairs', s1,
         lambda m: f'{_stat(s1[m], "e_R_deg", "median")}° / '
         f'{_stat(s1[m], "e_t_m", "median", 1e3)} mm, {s1[m]["failed"]}/{s1[m]["n_pairs"]}'),
        ('frame skipping, every 2nd / 3rd / 4th scan: failed pairs', s1, strided),
        (f'{float(top) * 100:.0f} % outliers added to the raw scans: median e_R',
         levels[top]['methods'], outliers),
        (f'source turned {min(angles, key=float)}–{max(angles, key=float)}°, no start: recovered',
         {m for m in HEADLINE if all(m in b['methods'] for b in angles.values())}, turned),
    ]  # fmt: skip
    ps = per_scan['methods'] if per_scan is not None else {}
    base = ps.get('gicp', {}).get('ms_per_scan', {}).get('p50')
    if per_scan is not None:
        rows.append((
            'time per raw scan, 1 thread: p50 as a ratio to GICP in the same run; p95',
            {m for m in ps if base and 'ms_per_scan' in ps[m]},
            lambda m: '{:.1f}× GICP; p95 {:.0f} ms'.format(
                ps[m]['ms_per_scan']['p50'] / base, ps[m]['ms_per_scan']['p95']),
        ))  # fmt: skip
    lines = ['| | ' + ' | '.join(HEADLINE.values()) + ' |', '|---|' + '---|' * len(HEADLINE)]
    lines += [f'| {label} | ' + ' | '.join(cell(m) if m in have else '–' for m in HEADLINE) + ' |'
              for label, have, cell in rows]  # fmt: skip
    commits = sorted(
        {_commit(d['meta']) for d in (robustness, paper, per_scan) if d and 'meta' in d}
    )
    return (
        '\n'.join(lines) + '\n' + _paper_paragraph(paper)
        + '\nGenerated by `benchmarks/render_readme.py` from `benchmarks/results/` (runs at '
        f'{", ".join(commits)}); the commands and full tables are in benchmarks/README.md.\n'
    )  # fmt: skip


def _ratio(a: float | None, b: float | None) -> str:
    return '–' if a is None or b is None or b == 0 else f'{a / b:.2f}×'


def models_block(
    odometry: dict[str, Any] | None, livox: dict[str, Any] | None, live: dict[str, Any] | None,
) -> str | None:  # fmt: skip
    """The README's choice of model: the ATE of the previous scan and the local map on every
    recording with a reference, and what the map costs per scan (the live run's stage table)."""
    rows, sources = [], []
    if odometry is not None:
        sources.append(f'`odometry.json` ({_commit(odometry)})')
        full = {'1': odometry['methods'], **(odometry.get('strides') or {})}
        for stride, block in full.items():
            if stride not in ('1', '2', '3'):
                continue
            prev, lmap = block.get('kentreg', {}), block.get('kentreg_local_map', {})
            if 'metrics' not in prev or 'metrics' not in lmap:
                continue
            a, b = prev['metrics']['ate']['rmse'], lmap['metrics']['ate']['rmse']
            every = {'1': 'every scan', '2': 'every 2nd scan', '3': 'every 3rd scan'}[stride]
            cells = [f'{1e3 * a:.1f} mm', f'{1e3 * b:.1f} mm', _ratio(b, a)]
            c, d = (prev['metrics'].get('ate_consistent_m'),
                    lmap['metrics'].get('ate_consistent_m'))  # fmt: skip
            if c is not None and d is not None:
                cells += [f'{1e3 * c:.1f} mm', f'{1e3 * d:.1f} mm', _ratio(d, c)]
            else:
                cells += ['–'] * 3
            rows.append([f'BALM sample, {every}', *cells])
    if livox is not None:
        sources.append(f'`livox.json` ({_commit(livox)})')
        for seq in livox['sequences']:
            prev, lmap = seq['methods'].get('kentreg'), seq['methods'].get('kentreg_local_map')
            if prev and lmap:
                a, b = prev['ate_m'], lmap['ate_m']
                rows.append([f'Livox Avia {seq["name"]}, keyframes', f'{a:.3f} m', f'{b:.3f} m',
                             _ratio(b, a), '–', '–', '–'])  # fmt: skip
    if not rows:
        return None
    head = ('| recording | ATE, previous scan | ATE, local map | local map / previous '
            '| against the map-consistent reference: previous | local map | ratio |')  # fmt: skip
    lines = [head, '|---|---|---|---|---|---|---|', *('| ' + ' | '.join(r) + ' |' for r in rows)]
    cons = (odometry or {}).get('consistent_reference') or {}
    if cons.get('precision_ate_m') is not None:
        far, good = 1e3 * cons['ate_to_reference_m'], 1e3 * cons['precision_ate_m']
        lines += ['', f'The BALM reference is a LiDAR-inertial estimate {far:.0f} mm (ATE) from '
                  'the map-consistent one (every scan refined to fit the map of all the others; '
                  '[benchmarks/README.md](benchmarks/README.md#3-odometry-and-speed-odometrypy-'
                  f'speedpy)), which is itself good to about {good:.1f} mm (built at two voxel '
                  'sizes): differences below that are not resolved.']  # fmt: skip
    if live is not None:
        sources.append(f'`live.json` ({_commit(live)})')
        costs = []
        for stream, entry in live['streams'].items():
            st = entry.get('stages', {})
            if {'previous_scan', 'local_map'} <= set(st):
                cpu = st['local_map']['cpu'] / st['previous_scan']['cpu']
                costs.append(f'{cpu:.2f}× on {stream}')
        if costs:
            lines += ['', 'The local map costs ' + ', '.join(costs) + " the previous scan's CPU "
                      "time per scan (one thread, the live run's stage table)."]  # fmt: skip
    lines += ['', f'Generated by `benchmarks/render_readme.py` from {", ".join(sources)}.']
    return '\n'.join(lines) + '\n'


def render(text: str, blocks: dict[str, str]) -> tuple[str, list[str]]:
    """``text`` with every block pasted between its markers; also the names without markers."""
    missing = []
    for name, body in blocks.items():
        found = re.search(
            rf'(<!-- BEGIN {re.escape(name)} -->\n).*?(<!-- END {re.escape(name)} -->)', text, re.S
        )
        if found is None:
            missing.append(name)
            continue
        text = text[: found.end(1)] + body.rstrip('\n') + '\n' + text[found.start(2) :]
    return text, missing


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--check', action='store_true', help='exit 1 if a page is stale')
    parser.add_argument('--readme', type=Path, default=README)
    parser.add_argument('--main-readme', type=Path, default=MAIN_README)
    parser.add_argument('--live-page', type=Path, default=LIVE_PAGE)
    parser.add_argument('--results', type=Path, default=RESULTS)
    parser.add_argument('--only', nargs='+', metavar='NAME', help='render only these blocks')
    args = parser.parse_args(argv)
    blocks = {p.stem: p.read_text() for p in sorted(args.results.glob('*.md'))}
    loaded = [args.results / f'{n}.json' for n in ('robustness', 'paper_table', 'per_scan')]
    headline = headline_block(
        *(json.loads(p.read_text()) if p.is_file() else None for p in loaded)
    )
    main_blocks = {} if headline is None else {'headline': headline}
    models = models_block(*(
        json.loads(p.read_text()) if p.is_file() else None
        for p in (args.results / f'{n}.json' for n in ('odometry', 'livox', 'live'))
    ))  # fmt: skip
    if models is not None:
        main_blocks['models'] = models
    live_blocks = {}
    if 'live' in blocks:  # live.md's opening paragraph and table, without its title
        live_blocks['live'] = blocks['live'].split('\n## ')[0].split('\n', 2)[2]
    if args.only:
        blocks = {k: v for k, v in blocks.items() if k in args.only}
        main_blocks = {k: v for k, v in main_blocks.items() if k in args.only}
        live_blocks = {k: v for k, v in live_blocks.items() if k in args.only}
    stale, lost = [], []
    # A result file may have no block in benchmarks/README.md yet (a note); the headline and the
    # live table must be in their pages (a page that lost its markers fails).
    pages = (
        (args.readme, blocks, False),
        (args.main_readme, main_blocks, True),
        (args.live_page, live_blocks, True),
    )
    for readme, these, required in pages:
        if not these:
            continue
        old = readme.read_text()
        new, missing = render(old, these)
        for name in missing:
            markers = f'<!-- BEGIN {name} --> / <!-- END {name} --> markers'
            if required:
                lost.append(f'{readme} has no {markers}')
            else:
                print(f'note: no {markers} in {readme}')
        if args.check:
            stale += [readme] if new != old else []
            continue
        readme.write_text(new)
        print(f'rendered {", ".join(n for n in these if n not in missing)} into {readme}')
    for readme in stale:
        print(f'{readme} is out of date; run python3 benchmarks/render_readme.py')
    for message in lost:
        print(f'error: {message}', file=sys.stderr)
    return 1 if stale or lost else 0


if __name__ == '__main__':
    sys.exit(main())
