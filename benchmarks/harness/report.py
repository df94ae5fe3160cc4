"""The one renderer: results JSON, markdown tables, line plots and the run's provenance.

An experiment writes ``<stem>.json`` (its numbers) and ``<stem>.md`` (its tables, built with
:func:`table` and :func:`fmt` from that JSON only, so ``--table`` can render a committed JSON
again) with :func:`write_results`, and optionally ``<stem>.png`` (:func:`plot_panels`).
``benchmarks/render_readme.py`` pastes the ``.md`` files into the READMEs.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import tempfile
from argparse import RawDescriptionHelpFormatter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np

from kentreg_ros.eval import jsonable

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / 'benchmarks' / 'results'
_DISTRIBUTIONS = {'open3d': 'open3d-cpu', 'small_gicp': 'small_gicp', 'kiss_icp': 'kiss-icp'}


def _git(*args: str) -> str:
    return subprocess.run(
        ['git', *args], cwd=ROOT, capture_output=True, text=True, check=False
    ).stdout.strip()


def git_describe() -> str | None:
    """``git describe --always`` of the repository, ``-dirty`` when a file other than the
    benchmark results differs from it; None outside a checkout."""
    try:
        out = _git('describe', '--always')
        changed = _git('status', '--porcelain', '--', '.', ':(exclude)benchmarks/results')
    except OSError:
        return None
    if not out:
        return None
    return f'{out}-dirty' if changed else out


def machine_info() -> dict[str, Any]:
    """CPU, cores, Python and library versions, git commit, date (for every results file)."""
    cpu = platform.processor() or ''
    try:
        for line in Path('/proc/cpuinfo').read_text().splitlines():
            if line.startswith('model name'):
                cpu = line.split(':', 1)[1].strip()
                break
    except OSError:
        pass
    versions: dict[str, str | None] = {}
    for mod in ('numpy', 'scipy', 'open3d', 'small_gicp', 'kiss_icp'):
        try:
            versions[mod] = version(_DISTRIBUTIONS.get(mod, mod))
        except Exception:  # a missing library is reported as such
            versions[mod] = None
    commit = os.environ.get('KENTREG_GIT_COMMIT', '')  # set when running from a `git archive`
    try:
        commit = commit or _git('rev-parse', '--short', 'HEAD')
    except OSError:
        commit = ''
    return {
        'git': git_describe(), 'cpu': cpu, 'cores': os.cpu_count(),
        'cores_used': len(os.sched_getaffinity(0)), 'load_avg_at_start': list(os.getloadavg()),
        'machine': platform.machine(), 'system': f'{platform.system()} {platform.release()}',
        'python': platform.python_version(), 'versions': versions, 'git_commit': commit,
        'date': datetime.datetime.now(datetime.UTC).isoformat(timespec='seconds'),
    }  # fmt: skip


def finish_machine(machine: dict[str, Any]) -> None:
    """Record the load and the commit at the end of a run (a warning when the checkout moved)."""
    machine['load_avg_at_end'] = list(os.getloadavg())
    machine['git_at_end'] = git_describe()
    if machine['git_at_end'] != machine['git']:
        print(
            f'warning: the checkout changed during the run ({machine["git"]} -> '
            f'{machine["git_at_end"]}): rerun for consistent numbers'
        )


def relative_paths(text: str) -> str:
    """``text`` with this machine's paths named as a reader of the repository finds them: the
    repository's own relative to it (``bags/balm_50``), its neighbours with ``../``
    (``../shared/data/balm``), and the temporary folder as ``$TMPDIR`` (a run's ``--out``)."""
    text = text.replace(str(ROOT) + '/', '').replace(str(ROOT.parent) + '/', '../')
    return text.replace(tempfile.gettempdir().rstrip('/') + '/', '$TMPDIR/')


def write_results(out: Path, stem: str, data: Any, text: str) -> None:
    """``<stem>.json`` (``data`` as indented JSON: numpy values as Python values, NaN written
    as null) and ``<stem>.md`` (``text``, printed too) in ``out``, with :func:`relative_paths`."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f'{stem}.json').write_text(relative_paths(json.dumps(jsonable(data), indent=1)) + '\n')
    (out / f'{stem}.md').write_text(relative_paths(text))
    print(text)


def cells(entry: dict[str, Any], *specs: str, missing: str = '–') -> list[str]:
    """Formatted values of ``entry``: each spec ``'key.subkey:format'`` (e.g.
    ``'e_R_deg.median:.3f'``); a missing key or a None/NaN value gives ``missing``."""
    out = []
    for spec in specs:
        path, _, form = spec.partition(':')
        value: Any = entry
        for key in path.split('.'):
            value = value.get(key) if isinstance(value, dict) else None
        out.append(fmt(value, form, missing))
    return out


def realised(levels: dict[str, Any], key: str, spec: str) -> str:
    """'10 % → 10.0 %, ...': each outlier level with the mean share ``key`` it realised."""
    return ', '.join(
        f'{float(k) * 100:.0f} % → {format(v[key]["mean"] * 100, spec)} %'
        for k, v in levels.items()
    )


def fmt(value: Any, spec: str, missing: str = '–') -> str:
    """Format a number for a markdown table (``missing`` for None/NaN)."""
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return missing
    return format(value, spec)


def table(header: str | Sequence[str], rows: Iterable[Sequence[Any]]) -> list[str]:
    """The lines of a markdown table (``header``: the cells, or one string ``'a | b'``)."""
    header = header.split(' | ') if isinstance(header, str) else header
    lines = ['| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header)]
    lines += ['| ' + ' | '.join(str(c) for c in row) + ' |' for row in rows]
    return lines


#: A column of :func:`column_table`: its header and its cell, a :func:`cells` spec
#: (``'key.subkey:format'``) or a function of the row's entry.
Column = tuple[str, str | Callable[[Any], Any]]


def column_table(
    columns: Sequence[Column], entries: Iterable[Any], missing: str = '–'
) -> list[str]:
    """The lines of a markdown table with a row per entry and a cell per column."""
    rows = [
        [cells(e, cell, missing=missing)[0] if isinstance(cell, str) else cell(e)
         for _, cell in columns]
        for e in entries
    ]  # fmt: skip
    return table([head for head, _ in columns], rows)


def named(entries: dict[str, Any]) -> list[dict[str, Any]]:
    """Each entry of ``{name: entry}`` with its name as ``'name'`` (:func:`column_table`)."""
    return [{'name': name, **entry} for name, entry in entries.items()]


def method_rows(blocks: dict[str, Any], cell: Callable[[Any], str]) -> list[list[str]]:
    """A row per method of ``blocks`` (``{x: {'methods': {name: entry}}}``, as the results JSON
    nests them): its name and ``cell(entry)`` of every block."""
    names = list(next(iter(blocks.values()))['methods'])
    return [[n, *(cell(b['methods'][n]) for b in blocks.values())] for n in names]


@dataclass
class Panel:
    """One axes of :func:`plot_panels`: ``lines`` are ``(label, x, y, style)``."""

    lines: list[tuple[str | None, Any, Any, dict[str, Any]]] = field(default_factory=list)
    axes: dict[str, Any] = field(default_factory=dict)
    log: str = ''  # 'x', 'y' or 'xy'
    legend: dict[str, Any] = field(default_factory=lambda: {'fontsize': 8, 'loc': 'best'})

    def add(self, label: str | None, x: Any, y: Any, **style: Any) -> None:
        self.lines.append((label, x, y, style))


def plot_panels(
    path: Path, panels: Sequence[Sequence[Panel]], *, size: tuple[float, float], title: str = ''
) -> None:
    """A grid of line plots (rows of :class:`Panel`) saved as a PNG."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, layout='constrained')
    FigureCanvasAgg(fig)
    axes = np.atleast_2d(fig.subplots(len(panels), len(panels[0]), squeeze=False))
    for row, ax_row in zip(panels, axes, strict=True):
        for panel, ax in zip(row, ax_row, strict=True):
            for label, x, y, style in panel.lines:
                if style.pop('fill', False):
                    ax.fill_between(x, *y, label=label, **style)
                else:
                    ax.plot(x, y, label=label, **style)
            ax.set_xscale('log' if 'x' in panel.log else 'linear')
            ax.set_yscale('log' if 'y' in panel.log else 'linear')
            ax.set(**panel.axes)
            ax.grid(True, which='both', alpha=0.3)
            if ax.has_data() and any(label for label, *_ in panel.lines):
                ax.legend(**panel.legend)
    if title:
        fig.suptitle(title)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)


def colours(names: Iterable[str]) -> dict[str, str]:
    """A matplotlib colour per name, in order."""
    return {name: f'C{i % 10}' for i, name in enumerate(names)}


def line_style(name: str) -> str:
    """kentreg solid, peers dashed."""
    return '-' if name.startswith('kentreg') else '--'


#: A command-line option: its flag(s) and ``argparse.add_argument`` keywords.
Option = tuple[str, dict[str, Any]]


def experiment_main(
    doc: str, stem: str | Callable[[argparse.Namespace], str], options: Sequence[Option],
    run: Callable[[argparse.Namespace, list[str]], dict[str, Any]],
    markdown: Callable[[dict[str, Any]], str],
    plot: Callable[[dict[str, Any], Path], None] | None = None,
    argv: Sequence[str] | None = None,
    worker: Callable[[argparse.Namespace], dict[str, Any]] | None = None,
) -> int:  # fmt: skip
    """The command line of an experiment: parse ``options`` (plus ``--out`` and ``--table``),
    ``run(args, argv)`` to a results dict, write ``<stem>.json``, ``<stem>.md`` (and
    ``<stem>.png`` with ``plot``) into ``--out``; ``--table JSON`` only prints its tables.
    With ``worker``, ``--worker OUT`` writes ``worker(args)`` to OUT instead
    (:func:`~benchmarks.harness.runner.in_subprocess`)."""
    import sys

    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(description=doc, formatter_class=RawDescriptionHelpFormatter)
    common: list[Option] = [
        ('--out', {'type': Path, 'default': RESULTS, 'help': 'folder for the results'}),
        ('--table', {'type': Path, 'metavar': 'JSON', 'help': 'only print the tables of a file'}),
    ]  # fmt: skip
    if worker is not None:
        common.append(('--worker', {'type': Path, 'help': argparse.SUPPRESS}))
    for flag, kwargs in (*options, *common):
        parser.add_argument(flag, **kwargs)
    args = parser.parse_args(argv)
    if getattr(args, 'worker', None) is not None and worker is not None:
        args.worker.write_text(json.dumps(worker(args)))
        return 0
    if args.table is not None:
        print(markdown(json.loads(args.table.read_text())), end='')
        return 0
    results = run(args, argv)
    name = stem if isinstance(stem, str) else stem(args)
    write_results(args.out, name, results, markdown(results))
    if plot is not None:
        plot(results, args.out / f'{name}.png')
    return 0


def method_panel(
    blocks: dict[str, Any] | None, value: Callable[[dict[str, Any]], float], *,
    scale: float = 1.0, log: str = '', **axes: Any,
) -> Panel:  # fmt: skip
    """One line per method of ``blocks`` (``{x: {'methods': {name: entry}}}``, as the results
    JSON nests them): ``value(entry)`` against ``x * scale``; an empty panel without blocks."""
    panel = Panel(log=log, axes=axes)
    if not blocks:
        return panel
    names = list(next(iter(blocks.values()))['methods'])
    x = [float(k) * scale for k in blocks]
    for name, colour in colours(names).items():
        y = [value(b['methods'][name]) for b in blocks.values()]
        panel.add(name, x, y, marker='o', color=colour, linestyle=line_style(name))
    return panel
