"""The parameter reference of ``kentreg_node``, generated from the code that defines it.

Every :class:`~kentreg_ros.core.config.KentRegConfig` field (dotted names such as
``em.max_iterations``, read by the node and by ``kentreg_replay --config``) and every ``node.*``
parameter of the node (:data:`kentreg_ros.ros.params.NODE_PARAMETERS`) becomes one row of a
markdown table: name, ROS type, default, allowed values, description. The README holds the table
between the markers :data:`BEGIN` and :data:`END`; a test keeps it equal to the rendering.

Command line::

    python3 -m kentreg_ros.docs                    # print the tables
    python3 -m kentreg_ros.docs --check README.md  # exit 1 when the README is out of date
    python3 -m kentreg_ros.docs --write README.md  # regenerate the README block
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from kentreg_ros.core.config import KentRegConfig, iter_fields, plain_value
from kentreg_ros.ros.params import NODE_PARAMETERS

PROG = 'python3 -m kentreg_ros.docs'
BEGIN = '<!-- BEGIN parameters -->'
END = '<!-- END parameters -->'

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


def config_parameters(config: KentRegConfig | None = None) -> list[ParameterDoc]:
    """Rows for every configuration field (defaults from ``config``, else the built-in ones)."""
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


def node_parameters(parameters: Sequence[Any] | None = None) -> list[ParameterDoc]:
    """Rows for the node's own ``node.*`` parameters.

    Parameters
    ----------
    parameters : sequence, optional
        :class:`~kentreg_ros.ros.params.NodeParameter` objects or ``(name, default,
        description)`` tuples; default: the node's ``NODE_PARAMETERS`` (rclpy-free).
    """
    params = NODE_PARAMETERS if parameters is None else parameters
    rows = []
    for p in params or ():
        if isinstance(p, tuple):
            name, default, description = p[:3]
            range_, choices, read_only = None, None, False
        else:
            name, default, description = p.name, p.default, p.description
            range_ = getattr(p, 'range', None)
            choices = getattr(p, 'choices', None)
            read_only = bool(getattr(p, 'read_only', False))
        if read_only:
            description = f'{description} Read-only: set at start-up.'
        rows.append(
            ParameterDoc(
                name=str(name),
                ros_type=_ros_type(default),
                default=_format_value(default),
                allowed=_allowed(range_, choices, default),
                description=str(description),
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


def render_parameters(
    config_rows: Sequence[ParameterDoc] | None = None,
    node_rows: Sequence[ParameterDoc] | None = None,
) -> str:
    """The markdown block that goes between :data:`BEGIN` and :data:`END`."""
    config_rows = config_parameters() if config_rows is None else config_rows
    node_rows = node_parameters() if node_rows is None else node_rows
    parts = [
        f'<!-- Generated by `{PROG} --write README.md` from kentreg_ros/core/config.py and '
        'the node parameters; edit those, not this table. -->',
        '',
        '**Registration and odometry** (`KentRegConfig`; read by `kentreg_node` and by '
        '`kentreg_replay --config`):',
        '',
        render_table(config_rows),
    ]
    if node_rows:
        parts += [
            '',
            '**Node** (`node.*`; read by `kentreg_node` only, ignored by `kentreg_replay`):',
            '',
            render_table(node_rows),
        ]
    return '\n'.join(parts)


def replace_block(text: str, block: str, *, source: str = 'text') -> str:
    """``text`` with the part between the :data:`BEGIN` and :data:`END` lines set to ``block``.

    Raises
    ------
    ValueError
        The markers are missing, repeated, or out of order.
    """
    lines = text.splitlines(keepends=True)
    begins = [i for i, line in enumerate(lines) if line.strip() == BEGIN]
    ends = [i for i, line in enumerate(lines) if line.strip() == END]
    if len(begins) != 1 or len(ends) != 1 or ends[0] < begins[0]:
        raise ValueError(
            f'{source}: expected one line {BEGIN!r} followed by one line {END!r}; found '
            f'{len(begins)} and {len(ends)}.'
        )
    head = ''.join(lines[: begins[0] + 1])
    tail = ''.join(lines[ends[0] :])
    return f'{head}{block}\n{tail}'


def main(argv: Sequence[str] | None = None) -> int:
    """Print, check or write the parameter tables; exit 0 (up to date), 1 (stale), 2 (error)."""
    parser = argparse.ArgumentParser(
        prog=PROG, description='Render the kentreg_node parameter reference as markdown.'
    )
    group = parser.add_mutually_exclusive_group()
    group.add_argument('--check', type=Path, metavar='FILE', help='exit 1 if FILE is stale')
    group.add_argument('--write', type=Path, metavar='FILE', help='update the block in FILE')
    args = parser.parse_args(argv)
    block = render_parameters()
    path = args.check or args.write
    if path is None:
        print(block)
        return 0
    try:
        text = path.read_text(encoding='utf-8')
        updated = replace_block(text, block, source=str(path))
    except (OSError, ValueError) as exc:
        print(f'{PROG}: error: {exc}', file=sys.stderr)
        return 2
    if args.check is not None:
        if updated != text:
            print(
                f'{path}: the parameter table is out of date; run `{PROG} --write {path}`.',
                file=sys.stderr,
            )
            return 1
        return 0
    if updated != text:
        path.write_text(updated, encoding='utf-8')
        print(f'{path}: parameter table updated.')
    return 0


if __name__ == '__main__':
    sys.exit(main())
