"""The parameter reference, generated from the code that defines it.

Two tables in the configuration reference (:data:`PAGE`, ``docs/configuration.md``): the
parameters an operator sets (:data:`kentreg_ros.io.params.PARAMETERS`, what ``kentreg_node``
declares and ``config/kentreg.yaml`` holds) between :data:`BEGIN` and :data:`END`, and the
research configuration (every :class:`~kentreg_ros.core.config.KentRegConfig` field, dotted
names such as ``em.tolerance``, reached from Python and the command lines' ``--set``) between
:data:`RESEARCH_BEGIN` and :data:`RESEARCH_END`. Tests keep the page equal to the rendering and
the shipped parameter file equal to :func:`~kentreg_ros.io.paramfile.dump_parameter_file`.

Command line::

    python3 -m kentreg_ros.docs                                # print the tables
    python3 -m kentreg_ros.docs --check docs/configuration.md  # exit 1 when it is out of date
    python3 -m kentreg_ros.docs --write docs/configuration.md  # regenerate its blocks
    python3 -m kentreg_ros.docs --parameter-file > config/kentreg.yaml
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from kentreg_ros.core import KentRegConfig, iter_fields, plain_value
from kentreg_ros.io.paramfile import dump_parameter_file
from kentreg_ros.io.params import PARAMETERS, Parameter

PROG = 'python3 -m kentreg_ros.docs'
#: The page that holds the tables, relative to the repository root.
PAGE = 'docs/configuration.md'
BEGIN = '<!-- BEGIN parameters -->'
END = '<!-- END parameters -->'
RESEARCH_BEGIN = '<!-- BEGIN research -->'
RESEARCH_END = '<!-- END research -->'

_ROS_TYPES = {bool: 'bool', int: 'integer', float: 'double', str: 'string'}


@dataclass(frozen=True)
class ParameterDoc:
    """One row of the parameter table."""

    name: str
    ros_type: str
    default: str
    allowed: str
    description: str


def _ros_type(value: Any) -> str:
    if isinstance(value, list | tuple):
        kinds = {type(v) for v in value}
        inner = _ROS_TYPES.get(kinds.pop(), 'string') if len(kinds) == 1 else 'double'
        return f'{inner}[]'
    return _ROS_TYPES.get(type(value), type(value).__name__)


def _format_value(value: Any) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, list | tuple):
        return '[' + ', '.join(_format_value(v) for v in value) + ']'
    return str(value)


def _allowed(range_: Sequence[float] | None, choices: Iterable[str] | None, default: Any) -> str:
    if choices is not None:
        return ', '.join(f'`{c}`' for c in choices)
    if isinstance(default, bool):
        return '`true`, `false`'
    if isinstance(default, list | tuple):
        return f'{len(default)} numbers'
    if range_ is not None:
        lo, hi = range_
        if isinstance(default, int) and not isinstance(default, bool):
            lo, hi = int(lo), int(hi)
        else:
            lo, hi = float(lo), float(hi)
        return f'{_format_value(lo)} … {_format_value(hi)}'
    return 'any'


def _cell(text: str) -> str:
    return ' '.join(str(text).split()).replace('|', '\\|')


def research_parameters(config: KentRegConfig | None = None) -> list[ParameterDoc]:
    """Rows for every research field (defaults from ``config``, else the built-in ones)."""
    cfg = KentRegConfig() if config is None else config
    rows = []
    for name, value, f in iter_fields(cfg):
        value = plain_value(value)
        meta = f.metadata
        rows.append(
            ParameterDoc(
                name=name,
                ros_type=_ros_type(value),
                default=_format_value(value),
                allowed=_allowed(meta.get('range'), meta.get('choices'), value),
                description=str(meta.get('description', '')),
            )
        )
    return rows


def product_parameters(parameters: Sequence[Parameter] = PARAMETERS) -> list[ParameterDoc]:
    """Rows for the parameters an operator sets."""
    rows = []
    for p in parameters:
        description = p.description
        if p.field:
            description = f'{description} (`{p.field}`)'
        if p.read_only:
            description = f'{description} Read-only: set at start-up.'
        rows.append(
            ParameterDoc(
                name=p.name,
                ros_type=_ros_type(p.default),
                default=_format_value(p.default),
                allowed=_allowed(p.range, p.choices, p.default),
                description=description,
            )
        )
    return rows


def render_table(rows: Sequence[ParameterDoc]) -> str:
    """A markdown table of ``rows``."""
    lines = [
        '| parameter | type | default | allowed | description |',
        '|---|---|---|---|---|',
    ]
    for r in rows:
        default = f'`{_cell(r.default)}`' if r.default != '' else '`""`'
        lines.append(
            f'| `{r.name}` | {r.ros_type} | {default} | {_cell(r.allowed)} | '
            f'{_cell(r.description)} |'
        )
    return '\n'.join(lines)


def render_parameters(rows: Sequence[ParameterDoc] | None = None) -> str:
    """The markdown block that goes between :data:`BEGIN` and :data:`END`."""
    rows = product_parameters() if rows is None else rows
    return '\n'.join(
        [
            f'<!-- Generated by `{PROG} --write {PAGE}` from kentreg_ros/io/params.py (and '
            'the core fields behind its core parameters); edit those, not this table. -->',
            '',
            render_table(rows),
        ]
    )


def render_research(rows: Sequence[ParameterDoc] | None = None) -> str:
    """The markdown block that goes between :data:`RESEARCH_BEGIN` and :data:`RESEARCH_END`."""
    rows = research_parameters() if rows is None else rows
    return '\n'.join(
        [
            f'<!-- Generated by `{PROG} --write {PAGE}` from kentreg_ros/core/config.py; '
            'edit it, not this table. -->',
            '',
            render_table(rows),
        ]
    )


def replace_block(
    text: str, block: str, *, source: str = 'text', begin: str = BEGIN, end: str = END
) -> str:
    """``text`` with the part between the ``begin`` and ``end`` lines set to ``block``.

    Raises
    ------
    ValueError
        The markers are missing, repeated, or out of order.
    """
    lines = text.splitlines(keepends=True)
    begins = [i for i, line in enumerate(lines) if line.strip() == begin]
    ends = [i for i, line in enumerate(lines) if line.strip() == end]
    if len(begins) != 1 or len(ends) != 1 or ends[0] < begins[0]:
        raise ValueError(
            f'{source}: expected one line {begin!r} followed by one line {end!r}; found '
            f'{len(begins)} and {len(ends)}.'
        )
    head = ''.join(lines[: begins[0] + 1])
    tail = ''.join(lines[ends[0] :])
    return f'{head}{block}\n{tail}'


def render_page(text: str, *, source: str = 'text') -> str:
    """``text`` (the configuration reference) with both generated blocks up to date."""
    text = replace_block(text, render_parameters(), source=source)
    return replace_block(
        text, render_research(), source=source, begin=RESEARCH_BEGIN, end=RESEARCH_END
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Print, check or write the tables (or print the parameter file); exit 0 (up to date), 1
    (stale), 2 (error)."""
    parser = argparse.ArgumentParser(
        prog=PROG, description='Render the kentreg parameter reference as markdown.'
    )
    group = parser.add_mutually_exclusive_group()
    group.add_argument('--check', type=Path, metavar='FILE', help='exit 1 if FILE is stale')
    group.add_argument('--write', type=Path, metavar='FILE', help='update the blocks in FILE')
    group.add_argument(
        '--parameter-file', action='store_true', help='print the shipped parameter file'
    )
    args = parser.parse_args(argv)
    if args.parameter_file:
        print(dump_parameter_file(), end='')
        return 0
    path = args.check or args.write
    if path is None:
        print(render_parameters() + '\n\n' + render_research())
        return 0
    try:
        text = path.read_text(encoding='utf-8')
        updated = render_page(text, source=str(path))
    except (OSError, ValueError) as exc:
        print(f'{PROG}: error: {exc}', file=sys.stderr)
        return 2
    if args.check is not None:
        if updated != text:
            print(
                f'{path}: the parameter tables are out of date; run `{PROG} --write {path}`.',
                file=sys.stderr,
            )
            return 1
        return 0
    if updated != text:
        path.write_text(updated, encoding='utf-8')
        print(f'{path}: parameter tables updated.')
    return 0


if __name__ == '__main__':
    sys.exit(main())
