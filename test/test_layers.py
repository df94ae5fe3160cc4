"""One direction of traffic: which kentreg_ros packages each package may import.

The imports are read from the source (every ``import`` and ``from ... import`` statement,
also those inside functions and under ``if TYPE_CHECKING:``), so a lazy import counts too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / 'kentreg_ros'
BENCHMARKS = PACKAGE.parent / 'benchmarks'


def imported_modules(path: Path, package: str) -> set[str]:
    """Absolute names of every module ``path`` imports (relative imports resolved)."""
    tree = ast.parse(path.read_text(encoding='utf-8'), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split('.')
                base = parts[: len(parts) - node.level + 1]
                module = '.'.join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ''
            names.add(module)
            names.update(f'{module}.{alias.name}' for alias in node.names)
    return names


def kentreg_imports(path: Path) -> set[str]:
    package = '.'.join(path.relative_to(PACKAGE.parent).with_suffix('').parts[:-1])
    return {n for n in imported_modules(path, package) if n.split('.')[0] == 'kentreg_ros'}


def modules(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob('*.py') if '__pycache__' not in p.parts)


def test_imported_modules_resolves_relative_and_lazy_imports(tmp_path: Path) -> None:
    src = tmp_path / 'm.py'
    src.write_text(
        'from . import errors\nfrom ..io import bags\n'
        'def f():\n    import kentreg_ros.eval.metrics as m\n'
    )
    names = imported_modules(src, 'kentreg_ros.core')
    assert {'kentreg_ros.core.errors', 'kentreg_ros.io.bags', 'kentreg_ros.eval.metrics'} <= names


@pytest.mark.parametrize('path', modules(PACKAGE / 'core'), ids=lambda p: p.name)
def test_core_imports_nothing_from_kentreg_ros_outside_core(path: Path) -> None:
    outside = sorted(n for n in kentreg_imports(path) if not n.startswith('kentreg_ros.core'))
    assert outside == [], f'{path.name} imports {outside}'


#: The rooms of the core, each importing only the ones before it (and itself): the floor
#: (configuration, errors, SO(3)/SE(3), the Kent distribution, the per-point kernels, the
#: stopwatch of stage timings), the prepared scan, the registration, the odometry, the
#: localization in a saved map.
CORE_ROOMS = (
    (
        'config',
        'errors',
        'fields',
        'geometry',
        'kent',
        'kent_sampling',
        'kernels',
        'stopwatch',
        'localization_config',
        'odometry_config',
    ),
    ('scan',),
    ('registration',),
    ('odometry',),
    ('localization',),
)


def _facade_names(path: Path) -> list[str]:
    """Names ``path`` imports from ``kentreg_ros.core`` itself that are not its modules."""
    tree = ast.parse(path.read_text(encoding='utf-8'))
    core = PACKAGE / 'core'
    return [
        alias.name
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and node.module == 'kentreg_ros.core'
        for alias in node.names
        if not ((core / alias.name).is_dir() or (core / f'{alias.name}.py').is_file())
    ]


def _room(module: str) -> int | None:
    """Index in :data:`CORE_ROOMS` of ``kentreg_ros.core.<x>...`` (None for the facade)."""
    parts = module.split('.')
    if parts[:2] != ['kentreg_ros', 'core'] or len(parts) < 3:
        return None
    return next((i for i, room in enumerate(CORE_ROOMS) if parts[2] in room), None)


@pytest.mark.parametrize(
    'path',
    [p for p in modules(PACKAGE / 'core') if p.name != '__init__.py' or p.parent.name != 'core'],
    ids=lambda p: str(p.relative_to(PACKAGE / 'core')),
)
def test_core_rooms_import_only_the_rooms_below_them(path: Path) -> None:
    """floor <- scan <- registration <- odometry, and never the facade from inside."""
    module = '.'.join(path.relative_to(PACKAGE.parent).with_suffix('').parts)
    own = _room(module)
    assert own is not None, f'{module} is in no room of CORE_ROOMS'
    names = {n for n in kentreg_imports(path) if n.split('.')[:2] == ['kentreg_ros', 'core']}
    assert not _facade_names(path), f'{module} imports {_facade_names(path)} from the facade'
    for name in names - {'kentreg_ros.core'}:
        room = _room(name)
        if room is None:  # ``from kentreg_ros.core import kernels`` names a floor module
            continue
        assert room <= own, f'{module} (room {CORE_ROOMS[own]}) imports {name}'


def test_the_rooms_exist_as_the_layout_describes() -> None:
    for room in CORE_ROOMS[1:]:
        assert (PACKAGE / 'core' / room[0] / '__init__.py').is_file(), room
    assert (PACKAGE / 'core' / 'kernels' / '_numpy.py').is_file()


@pytest.mark.parametrize(
    'path',
    [p for p in modules(PACKAGE) if p.relative_to(PACKAGE).parts[0] != 'core'],
    ids=lambda p: str(p.relative_to(PACKAGE)),
)
def test_outside_core_reaches_it_through_its_facade(path: Path) -> None:
    """Only ``kentreg_ros.core`` (and its configuration module) are the core's public face: its
    rooms may move without the node, the command lines or the evaluation noticing."""
    bad = sorted(
        n
        for n in kentreg_imports(path)
        if n.startswith('kentreg_ros.core.')
        and not n.startswith('kentreg_ros.core.config')
        and n.count('.') > 2  # kentreg_ros.core.<name> may be a facade name
    )
    assert bad == [], f'{path.relative_to(PACKAGE)} imports {bad}'


#: What runs processes: the process pipeline's plumbing, which lives in kentreg_ros/runtime/.
_PROCESS_MODULES = ('subprocess', 'multiprocessing', 'fcntl', 'signal')


@pytest.mark.parametrize('path', modules(PACKAGE / 'core'), ids=lambda p: p.name)
def test_core_runs_no_processes_and_never_imports_the_runtime(path: Path) -> None:
    """The core is numpy/scipy registration and odometry: a worker process, its messages and
    its hand-over files are the runtime's (kentreg_ros/runtime/)."""
    names = imported_modules(path, 'kentreg_ros.core')
    bad = sorted(n for n in names if n.split('.')[0] in _PROCESS_MODULES)
    bad += sorted(n for n in names if n.startswith('kentreg_ros.runtime'))
    assert bad == [], f'{path.name} imports {bad}'


@pytest.mark.parametrize('path', modules(PACKAGE / 'runtime'), ids=lambda p: p.name)
def test_the_runtime_imports_only_the_core_through_its_facade(path: Path) -> None:
    """core <- runtime <- ros: the runtime runs the core's odometry on more than one core and
    knows nothing of the node, the evaluation, the inputs or the command lines."""
    outside = sorted(
        n
        for n in kentreg_imports(path)
        if not n.startswith(('kentreg_ros.core', 'kentreg_ros.runtime'))
    )
    assert outside == [], f'runtime/{path.name} imports {outside}'


@pytest.mark.parametrize(
    ('folder', 'forbidden'),
    [
        ('io', ('kentreg_ros.eval', 'kentreg_ros.cli', 'kentreg_ros.ros', 'kentreg_ros.runtime')),
        ('eval', ('kentreg_ros.cli', 'kentreg_ros.ros', 'kentreg_ros.runtime')),
        ('batch', ('kentreg_ros.cli', 'kentreg_ros.ros', 'kentreg_ros.runtime')),
    ],
)
def test_io_eval_and_batch_never_import_the_command_lines_or_the_node(
    folder: str, forbidden: tuple[str, ...]
) -> None:
    for path in modules(PACKAGE / folder):
        bad = sorted(n for n in kentreg_imports(path) if n.startswith(forbidden))
        assert bad == [], f'{folder}/{path.name} imports {bad}'


@pytest.mark.parametrize('path', modules(BENCHMARKS), ids=lambda p: p.name)
def test_benchmarks_never_import_a_command_line(path: Path) -> None:
    names = imported_modules(path, 'benchmarks')
    bad = sorted(n for n in names if n.startswith('kentreg_ros.cli') or n == 'scenes')
    assert bad == [], f'{path.name} imports {bad}'


#: Smoke alarms on the benchmarks, with headroom (not targets): one small harness (datasets,
#: methods, pipelines, perturbations, one runner, one renderer; ~2,200 lines when set) and
#: every benchmark a short spec on it, under the package's module limit. A script that grows
#: past it holds a second concern that belongs in the harness.
HARNESS_LINES = 3000
BENCHMARK_SCRIPT_LINES = 600


def test_the_benchmark_harness_stays_small_and_every_benchmark_a_short_spec() -> None:
    harness = sum(len(p.read_text().splitlines()) for p in (BENCHMARKS / 'harness').rglob('*.py'))
    assert harness < HARNESS_LINES, f'benchmarks/harness has {harness} lines'
    long = {
        p.name: n
        for p in BENCHMARKS.glob('*.py')
        if (n := len(p.read_text().splitlines())) >= BENCHMARK_SCRIPT_LINES
    }
    assert long == {}, f'benchmark scripts of {BENCHMARK_SCRIPT_LINES}+ lines: {long}'


#: Top-level names of ROS 2 Python packages: rclpy and the message/service packages.
_ROS_PACKAGES = ('rclpy', 'rcl_interfaces', 'builtin_interfaces', 'std_srvs', 'tf2_ros')


def _is_ros_package(module: str) -> bool:
    top = module.split('.')[0]
    return top in _ROS_PACKAGES or top.endswith('_msgs')


@pytest.mark.parametrize(
    'path',
    [p for p in modules(PACKAGE) if 'ros' not in p.relative_to(PACKAGE).parts[:-1]],
    ids=lambda p: str(p.relative_to(PACKAGE)),
)
def test_only_the_ros_package_imports_rclpy_or_ros_messages(path: Path) -> None:
    package = '.'.join(path.relative_to(PACKAGE.parent).with_suffix('').parts[:-1])
    bad = sorted(n for n in imported_modules(path, package) if _is_ros_package(n))
    assert bad == [], (
        f'{path.relative_to(PACKAGE)} imports {bad}: that belongs in kentreg_ros/ros/'
    )


def test_the_ros_package_is_where_rclpy_is_imported() -> None:
    # The check above must look at something: the node and the player do import rclpy.
    for name in ('node.py', 'play.py'):
        names = imported_modules(PACKAGE / 'ros' / name, 'kentreg_ros.ros')
        assert any(n.split('.')[0] == 'rclpy' for n in names), name


@pytest.mark.parametrize('folder', ['core', 'io', 'eval', 'cli', 'runtime'])
def test_no_other_package_imports_the_ros_package(folder: str) -> None:
    for path in modules(PACKAGE / folder):
        bad = sorted(n for n in kentreg_imports(path) if n.startswith('kentreg_ros.ros'))
        assert bad == [], f'{folder}/{path.name} imports {bad}'
