"""launch/kentreg.launch.py and the installed package: what a user of ``ros2 launch`` relies on.

``launch``/``launch_ros`` are not on PyPI. Without them the launch file is read as a syntax tree:
it must declare the arguments and defaults docs/ros.md documents, start an executable the
package really installs, and name only ROS packages that package.xml declares. Where
launch_ros and an installed kentreg_ros exist (a sourced Jazzy install), it is loaded for real;
under ``colcon test`` (test/colcon_check.sh) the install tree is checked through the ament index.
"""

from __future__ import annotations

import ast
import importlib.metadata
import importlib.util
import os
import re
import sys
from pathlib import Path
from typing import Any

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
LAUNCH_FILE = REPO_ROOT / 'launch' / 'kentreg.launch.py'
ROS_PAGE = REPO_ROOT / 'docs' / 'ros.md'


def _installed_prefix() -> Path | None:
    """Install prefix of kentreg_ros in the ament index (colcon test, sourced install)."""
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_prefix
    except ImportError:
        return None
    try:
        return Path(get_package_prefix('kentreg_ros'))
    except (PackageNotFoundError, LookupError, OSError):
        return None


def _tree() -> ast.Module:
    return ast.parse(LAUNCH_FILE.read_text(encoding='utf-8'), filename=str(LAUNCH_FILE))


def _calls(tree: ast.AST, name: str) -> list[ast.Call]:
    return [
        n
        for n in ast.walk(tree)
        if isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id == name
    ]


def _keywords(call: ast.Call) -> dict[str, ast.expr]:
    return {k.arg: k.value for k in call.keywords if k.arg is not None}


def _declared_arguments() -> dict[str, ast.expr]:
    """``{argument name: its default_value expression}`` in declaration order."""
    out = {}
    for call in _calls(_tree(), 'DeclareLaunchArgument'):
        name = call.args[0]
        assert isinstance(name, ast.Constant), ast.dump(call)
        out[name.value] = _keywords(call)['default_value']
    return out


def _value(expr: ast.expr) -> Any:
    """A literal, or a name bound to a literal at the top of the launch file."""
    if isinstance(expr, ast.Name):
        constants = {
            t.id: n.value
            for n in _tree().body
            if isinstance(n, ast.Assign)
            for t in n.targets
            if isinstance(t, ast.Name)
        }
        expr = constants[expr.id]
    return ast.literal_eval(expr)


def _config_default_parts() -> tuple[str, list[str]]:
    """The ``config_file`` default ``os.path.join(get_package_share_directory(PKG), *parts)``
    as ``(PKG, parts)``."""
    tree = _tree()
    default = _declared_arguments()['config_file']
    if isinstance(default, ast.Name):  # a local variable: find its assignment
        default = next(
            n.value
            for n in ast.walk(tree)
            if isinstance(n, ast.Assign)
            and any(isinstance(t, ast.Name) and t.id == default.id for t in n.targets)
        )
    assert isinstance(default, ast.Call) and ast.unparse(default.func) == 'os.path.join'
    share, *rest = default.args
    assert isinstance(share, ast.Call) and ast.unparse(share.func) == 'get_package_share_directory'
    (package,) = share.args
    return _value(package), [_value(p) for p in rest]


def _documented_defaults() -> dict[str, str]:
    """The launch arguments of docs/ros.md: ``{name: default}`` from "`name` (default ...)"."""
    text = ROS_PAGE.read_text(encoding='utf-8')
    paragraph = text.split('**Launch** (`launch/kentreg.launch.py`):', 1)[1].split('\n\n', 1)[0]
    found = re.findall(r'`(\w+)` \(default ([^)]*)\)', ' '.join(paragraph.split()))
    return {name: default for name, default in found}


def _nodes() -> dict[str, ast.Call]:
    """The ``Node(...)`` actions by package."""
    return {_value(_keywords(n)['package']): n for n in _calls(_tree(), 'Node')}


def _executable() -> str:
    kwargs = _keywords(_nodes()['kentreg_ros'])
    return str(_value(kwargs['executable']))


#: The arguments, in declaration order.
ARGUMENTS = ['topic', 'config_file', 'use_sim_time', 'rviz', 'bag', 'odom_frame', 'base_frame']


def test_launch_arguments_and_defaults_are_the_documented_ones() -> None:
    declared = _declared_arguments()
    documented = _documented_defaults()
    assert list(declared) == list(documented) == ARGUMENTS
    for name in ARGUMENTS:
        if name == 'config_file':
            continue
        value = _value(declared[name])
        assert documented[name] == (f'`{value}`' if value else 'empty'), name
    package, parts = _config_default_parts()
    assert documented['config_file'] == (f'the installed `share/{package}/{"/".join(parts)}`'), (
        documented['config_file']
    )
    # The default file exists in the source tree (setup.py installs config/*.yaml there).
    assert (REPO_ROOT.joinpath(*parts)).is_file()


def test_launch_starts_an_installed_console_script_running_the_node() -> None:
    executable = _executable()
    scripts = {
        ep.name: ep
        for ep in importlib.metadata.entry_points(group='console_scripts')
        if ep.value.startswith('kentreg_ros.')
    }
    if not scripts:
        pytest.skip('kentreg_ros is not installed (pip install -e .)')
    assert executable in scripts, sorted(scripts)
    from kentreg_ros.ros import node

    assert scripts[executable].load() is node.main


@pytest.mark.integration
@pytest.mark.skipif(
    importlib.util.find_spec('launch_ros') is None,
    reason='launch_ros is not installed (not on PyPI; source a ROS 2 Jazzy install)',
)
def test_launch_file_loads_with_real_launch_ros() -> None:
    if _installed_prefix() is None:
        pytest.skip('kentreg_ros is not in the ament index (colcon build and source it)')
    from launch.launch_description_sources import get_launch_description_from_python_launch_file

    description = get_launch_description_from_python_launch_file(str(LAUNCH_FILE))
    assert [a.name for a in description.get_launch_arguments()] == list(_declared_arguments())


@pytest.mark.integration
def test_installed_package_has_marker_manifest_config_launch_and_executable() -> None:
    prefix = _installed_prefix()
    if prefix is None:
        pytest.skip('kentreg_ros is not installed in an ament prefix (runs under colcon test)')
    from ament_index_python.packages import get_package_share_directory

    share = prefix / 'share' / 'kentreg_ros'
    assert (
        prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'kentreg_ros'
    ).is_file()
    for relative in ('package.xml', 'launch/kentreg.launch.py', 'rviz/kentreg.rviz'):
        assert (share / relative).is_file(), relative
    # What `ros2 launch` starts: the executable the launch file names, where ros2 run looks.
    executable = prefix / 'lib' / 'kentreg_ros' / _executable()
    assert executable.is_file() and os.access(executable, os.X_OK)
    # The launch file's default parameter file, resolved through the ament index as it does.
    package, parts = _config_default_parts()
    assert Path(get_package_share_directory(package)).joinpath(*parts).is_file()


def test_rviz_starts_only_with_rviz_true_and_shows_the_package_configuration() -> None:
    rviz = _keywords(_nodes()['rviz2'])
    assert ast.unparse(rviz['condition']) == "IfCondition(LaunchConfiguration('rviz'))"
    assert _value(_declared_arguments()['rviz']) == 'false'
    # ['-d', rviz_config], rviz_config = os.path.join(share, 'rviz', 'kentreg.rviz')
    arguments = rviz['arguments']
    assert isinstance(arguments, ast.List) and _value(arguments.elts[0]) == '-d'
    (assign,) = [
        n.value
        for n in ast.walk(_tree())
        if isinstance(n, ast.Assign)
        and any(isinstance(t, ast.Name) and t.id == 'rviz_config' for t in n.targets)
    ]
    assert isinstance(assign, ast.Call) and ast.unparse(assign.func) == 'os.path.join'
    parts = [_value(a) for a in assign.args[1:]]
    assert parts == ['rviz', 'kentreg.rviz'] and REPO_ROOT.joinpath(*parts).is_file()


def test_a_bag_is_played_with_ros2_bag_or_kentreg_play_only_when_given() -> None:
    source = LAUNCH_FILE.read_text(encoding='utf-8')
    (function,) = [
        n
        for n in ast.walk(_tree())
        if isinstance(n, ast.FunctionDef) and n.name == '_node_and_bag'
    ]
    text = ast.unparse(function)
    assert 'if bag:' in text and "shutil.which('ros2')" in text
    assert "['ros2', 'bag', 'play', bag, '--clock']" in text
    assert "['kentreg_play', bag, '--clock'" in text
    # Only the frames given on the command line override the parameter file.
    assert '{name: value for name, value in frames.items() if value}' in text
    assert 'OpaqueFunction(function=_node_and_bag)' in source


#: Top-level imports that are not ROS packages (standard library, kentreg_ros, pip packages).
_NOT_ROS = {'kentreg_ros', 'numpy', 'scipy', 'yaml', 'rosbags', 'mcap', 'tqdm', 'matplotlib'}


def _top_level_imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding='utf-8'))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name.split('.')[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split('.')[0])
    return names - set(sys.stdlib_module_names) - _NOT_ROS


def test_package_xml_declares_every_ros_package_the_ros_modules_and_launch_import() -> None:
    import xml.etree.ElementTree as ET

    manifest = ET.parse(REPO_ROOT / 'package.xml').getroot()
    assert manifest.get('format') == '3'
    assert manifest.findtext('name') == 'kentreg_ros'
    assert manifest.findtext('export/build_type') == 'ament_python'
    exec_depends = {e.text for e in manifest.findall('exec_depend')}
    modules: list[Any] = sorted((REPO_ROOT / 'kentreg_ros' / 'ros').glob('*.py'))
    modules.append(LAUNCH_FILE)
    imported: set[str] = set()
    for module in modules:
        imported |= _top_level_imports(module)
    assert {'rclpy', 'sensor_msgs', 'geometry_msgs', 'launch_ros', 'rosgraph_msgs'} <= imported
    assert sorted(imported - exec_depends) == []
    assert {e.text for e in manifest.findall('test_depend')} == {'python3-pytest'}
