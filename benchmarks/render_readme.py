"""Paste the generated tables into the READMEs, so they always equal the results.

Every ``results/<name>.md`` replaces the text between ``<!-- BEGIN <name> -->`` and
``<!-- END <name> -->`` in benchmarks/README.md; the main README's ``headline`` table is built
from the results JSON. Goals are prose in the READMEs, not code.

Usage::

    python3 benchmarks/render_readme.py          # rewrite the READMEs
    python3 benchmarks/render_readme.py --check  # exit 1 if they are out of date
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
README = HERE / 'README.md'
MAIN_README = HERE.parent / 'README.md'
RESULTS = HERE / 'results'


def _stat(summary: dict[str, Any], key: str, stat: str, scale: float = 1.0) -> str:
    value = summary.get(key, {}).get(stat)
    return '–' if value is None else f'{scale * value:.3g}'


def _commit(meta: dict[str, Any]) -> str:
    """The commit a results file records (the benchmarks name it in slightly different keys)."""
    machine: dict[str, Any] = meta['machine'] if isinstance(meta.get('machine'), dict) else {}
    for value in (machine.get('git'), machine.get('git_commit'), meta.get('git')):
        if value:
            return str(value)
    return 'an unrecorded commit'


def _paper_paragraph(paper: dict[str, Any] | None) -> str:
    """The rotation-stage sentence under the headline table (paper_table.json)."""
    if paper is None:
        return ''
    body = ''
    ident = paper['datasets']['balm']['starts']['identity']
    stage = ident.get('kentreg_robust-no_refine', {}).get('summary')
    full = ident.get('kentreg_robust', {}).get('summary')
    pap = ident.get('kentreg_paper', {}).get('summary')
    avg = ident.get('kentreg_robust-averaged_no_refine', {}).get('summary')
    if stage and full and pap:
        body += (
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
        body += '.\n'
    return body


def headline_block(
    robustness: dict[str, Any] | None,
    paper: dict[str, Any] | None,
    per_scan: dict[str, Any] | None,
) -> str | None:
    """The README's headline table: every number from a committed result file."""
    if robustness is None:
        return None
    rows = []
    methods = ('kentreg', 'gicp', 'icp_pt2pl', 'kiss_icp')
    names = {
        'kentreg': 'kentreg (defaults)',
        'gicp': 'GICP (small_gicp)',
        'icp_pt2pl': 'point-to-plane ICP (Open3D)',
        'kiss_icp': 'KISS-ICP',
    }
    strides = robustness['strides']['strides']
    levels = robustness['outliers']['levels']
    angles = robustness['turned']['angles']
    top = max(levels, key=float)
    head = (
        '| | ' + ' | '.join(names[m] for m in methods) + ' |\n|---|' + '---|' * len(methods) + '\n'
    )

    def row(label: str, cells: list[str]) -> None:
        rows.append(f'| {label} | ' + ' | '.join(cells) + ' |')

    s1 = strides['1']['methods']
    row(
        'odometry on the 50 sample scans: median e_R / e_t, failed pairs',
        [
            f'{_stat(s1[m], "e_R_deg", "median")}° / {_stat(s1[m], "e_t_m", "median", 1e3)} mm, '
            f'{s1[m]["failed"]}/{s1[m]["n_pairs"]}'
            if m in s1
            else '–'
            for m in methods
        ],
    )
    row(
        'frame skipping, every 2nd / 3rd / 4th scan: failed pairs',
        [
            ' / '.join(
                f'{strides[n]["methods"][m]["failed"]}/{strides[n]["methods"][m]["n_pairs"]}'
                for n in ('2', '3', '4')
            )
            if m in s1
            else '–'
            for m in methods
        ],
    )
    cells = []
    for m in methods:
        summ = levels[top]['methods'].get(m, {}).get('summary')
        if summ is None:
            cells.append('–')
            continue
        cells.append(
            f'{_stat(summ, "e_R_deg", "median")}° ({summ["median_e_R_ratio_to_clean"]:.1f}× '
            f'clean), {summ["failures"]}/{summ["n"]} failed'
        )
    row(f'{float(top) * 100:.0f} % outliers added to the raw scans: median e_R', cells)
    cells = []
    for m in methods:
        got = [angles[a]['methods'].get(m, {}).get('summary') for a in angles]
        if any(g is None for g in got):
            cells.append('–')
            continue
        rec = sum(g['recovered'] for g in got)
        total = sum(g['n'] for g in got)
        cells.append(f'{rec}/{total} ({100 * rec / total:.0f} %)')
    row(
        f'source turned {min(angles, key=float)}–{max(angles, key=float)}°, no start: recovered',
        cells,
    )
    if per_scan is not None:
        ps = per_scan['methods']
        base = ps.get('gicp', {}).get('ms_per_scan', {}).get('p50')
        cells = []
        for m in methods:
            t = ps.get(m, {}).get('ms_per_scan')
            if t is None or not base:
                cells.append('–')
                continue
            cells.append(f'{t["p50"] / base:.1f}× GICP; p95 {t["p95"]:.0f} ms')
        row('time per raw scan, 1 thread: p50 as a ratio to GICP in the same run; p95', cells)
    body = head + '\n'.join(rows) + '\n' + _paper_paragraph(paper)
    commits = sorted(
        {
            _commit(d['meta'])
            for d in (robustness, paper, per_scan)
            if d is not None and 'meta' in d
        }
    )
    body += (
        f'\nGenerated by `benchmarks/render_readme.py` from `benchmarks/results/` (runs at '
        f'{", ".join(commits)}); the commands and full tables are in benchmarks/README.md.\n'
    )
    return body


def _load(path: Path) -> dict[str, Any] | None:
    return json.loads(path.read_text()) if path.is_file() else None


def _paste(body: str) -> Callable[[re.Match[str]], str]:
    """A ``re.sub`` replacement putting ``body`` between a block's markers."""

    def paste(m: re.Match[str]) -> str:
        return m.group(1) + body.rstrip('\n') + '\n' + m.group(2)

    return paste


def render(text: str, blocks: dict[str, str]) -> tuple[str, list[str]]:
    """``text`` with every block pasted between its markers; also the names without markers."""
    missing = []
    for name, body in blocks.items():
        pattern = re.compile(
            rf'(<!-- BEGIN {re.escape(name)} -->\n).*?(<!-- END {re.escape(name)} -->)', re.S
        )
        if not pattern.search(text):
            missing.append(name)
            continue
        text = pattern.sub(_paste(body), text)
    return text, missing


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--check', action='store_true', help='exit 1 if the README is stale')
    parser.add_argument('--readme', type=Path, default=README)
    parser.add_argument('--main-readme', type=Path, default=MAIN_README)
    parser.add_argument('--results', type=Path, default=RESULTS)
    parser.add_argument('--only', nargs='+', metavar='NAME', help='render only these blocks')
    args = parser.parse_args(argv)
    blocks = {p.stem: p.read_text() for p in sorted(args.results.glob('*.md'))}
    main_blocks: dict[str, str] = {}
    headline = headline_block(
        _load(args.results / 'robustness.json'),
        _load(args.results / 'paper_table.json'),
        _load(args.results / 'per_scan.json'),
    )
    if headline is not None:
        main_blocks['headline'] = headline
    if args.only:
        blocks = {k: v for k, v in blocks.items() if k in args.only}
        main_blocks = {k: v for k, v in main_blocks.items() if k in args.only}
    stale = []
    for readme, these in ((args.readme, blocks), (args.main_readme, main_blocks)):
        if not these:
            continue
        old = readme.read_text()
        new, missing = render(old, these)
        for name in missing:
            print(f'note: no <!-- BEGIN {name} --> / <!-- END {name} --> markers in {readme}')
        if args.check:
            if new != old:
                stale.append(readme)
            continue
        readme.write_text(new)
        print(f'rendered {", ".join(n for n in these if n not in missing)} into {readme}')
    if stale:
        for readme in stale:
            print(f'{readme} is out of date; run python3 benchmarks/render_readme.py')
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
