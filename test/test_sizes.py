"""Sizes a newcomer can read: no module of the package over 600 lines, no function over 100.

A module past 600 lines holds more than one concern, and a function past 100 lines more than
one step (the house rule since the odometry step was spread over ~300 lines). Counted as the
file's lines and a function's lines from its ``def`` to its last line, docstring included.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / 'kentreg_ros'
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 100


def python_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob('*.py') if '__pycache__' not in p.parts)


def long_functions(path: Path, limit: int) -> list[str]:
    """``name (lines)`` of every function or method of ``path`` longer than ``limit`` lines."""
    tree = ast.parse(path.read_text(encoding='utf-8'), filename=str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            end = node.end_lineno if node.end_lineno is not None else node.lineno
            length = end - node.lineno + 1
            if length > limit:
                out.append(f'{node.name} ({length})')
    return out


def test_long_functions_counts_from_def_to_the_last_line(tmp_path: Path) -> None:
    src = tmp_path / 'm.py'
    body = '\n'.join(f'    x{i} = {i}' for i in range(4))
    src.write_text(f'def short():\n    return 1\n\n\ndef five():\n{body}\n')
    assert long_functions(src, 4) == ['five (5)']
    assert long_functions(src, 5) == []


@pytest.mark.parametrize('path', python_files(PACKAGE), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_no_module_over_600_lines_and_no_function_over_100(path: Path) -> None:
    n_lines = len(path.read_text(encoding='utf-8').splitlines())
    assert n_lines <= MAX_MODULE_LINES, f'{path.name}: {n_lines} lines'
    assert long_functions(path, MAX_FUNCTION_LINES) == []
