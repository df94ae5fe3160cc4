"""launch/kentreg.launch.py: arguments, node, remapping and parameters; the installed package.

``launch``/``launch_ros`` are not on PyPI, so the launch file is checked three ways: its syntax
tree; running ``generate_launch_description`` against small stand-ins for the launch classes
that record what they are given; and, where launch_ros and an installed kentreg_ros exist
(a sourced Jazzy install, or ``colcon test``), loading it for real.
"""

from __future__ import annotations

import ast
import importlib.util
import os
import runpy
import sys
import types
from pathlib import Path
from typing import Any

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
LAUNCH_FILE = REPO_ROOT / 'launch' / 'kentreg.launch.py'
ARGUMENTS = ['topic', 'config_file', 'use_sim_time']


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


class _Recorded:
    """Stand-in for a launch class: keeps its constructor arguments."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.args = args
        self.kwargs = kwargs

    def __eq__(self, other: object) -> bool:
        return (
            type(self) is type(other)
            and self.args == other.args  # type: ignore[attr-defined]
            and self.kwargs == other.kwargs  # type: ignore[attr-defined]
        )

    def __repr__(self) -> str:
        return f'{type(self).__name__}{self.args}{self.kwargs}'


def _stub_modules(share_dir: Path | None) -> dict[str, types.ModuleType]:
    classes = {
        'launch.launch_description': ['LaunchDescription'],
        'launch.actions': ['DeclareLaunchArgument'],
        'launch.substitutions': ['LaunchConfiguration'],
        'launch_ros.actions': ['Node'],
        'launch_ros.parameter_descriptions': ['ParameterValue'],
    }
    modules: dict[str, types.ModuleType] = {
        'launch': types.ModuleType('launch'),
        'launch_ros': types.ModuleType('launch_ros'),
    }
    for module_name, names in classes.items():
        module = types.ModuleType(module_name)
        for name in names:
            setattr(module, name, type(name, (_Recorded,), {}))
        modules[module_name] = module
    if share_dir is not None:
        packages = types.ModuleType('ament_index_python.packages')

        def get_package_share_directory(package: str) -> str:
            assert package == 'kentreg_ros'
            return str(share_dir)

        packages.get_package_share_directory = get_package_share_directory  # type: ignore[attr-defined]
        modules['ament_index_python'] = types.ModuleType('ament_index_python')
        modules['ament_index_python.packages'] = packages
    return modules


def _run_with_stubs(monkeypatch: pytest.MonkeyPatch, share_dir: Path | None) -> Any:
    modules = _stub_modules(share_dir)
    for name, module in modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    namespace = runpy.run_path(str(LAUNCH_FILE))
    return namespace['generate_launch_description'](), modules


def test_launch_file_parses_and_declares_topic_config_file_and_use_sim_time() -> None:
    tree = ast.parse(LAUNCH_FILE.read_text(encoding='utf-8'), filename=str(LAUNCH_FILE))
    compile(tree, str(LAUNCH_FILE), 'exec')
    declared = [
        node.args[0].value
        for node in ast.walk(tree)
        if isinstance(node, ast.Call)
        and isinstance(node.func, ast.Name)
        and node.func.id == 'DeclareLaunchArgument'
        and isinstance(node.args[0], ast.Constant)
    ]
    assert declared == ARGUMENTS
    functions = [n.name for n in tree.body if isinstance(n, ast.FunctionDef)]
    assert 'generate_launch_description' in functions


def test_launch_description_starts_the_node_with_remap_parameters_and_defaults(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    description, m = _run_with_stubs(monkeypatch, tmp_path / 'share' / 'kentreg_ros')
    LaunchConfiguration = m['launch.substitutions'].LaunchConfiguration
    ParameterValue = m['launch_ros.parameter_descriptions'].ParameterValue
    (entities,) = description.args
    arguments = [e for e in entities if type(e).__name__ == 'DeclareLaunchArgument']
    nodes = [e for e in entities if type(e).__name__ == 'Node']
    assert [a.args[0] for a in arguments] == ARGUMENTS
    defaults = {a.args[0]: a.kwargs['default_value'] for a in arguments}
    assert defaults == {
        'topic': 'points',
        'config_file': str(tmp_path / 'share' / 'kentreg_ros' / 'config' / 'kentreg.yaml'),
        'use_sim_time': 'false',
    }
    assert all(a.kwargs.get('description') for a in arguments)
    (node,) = nodes
    assert node.kwargs['package'] == 'kentreg_ros'
    assert node.kwargs['executable'] == 'kentreg_node'
    assert node.kwargs['name'] == 'kentreg_node'
    assert node.kwargs['remappings'] == [('points', LaunchConfiguration('topic'))]
    assert node.kwargs['parameters'] == [
        LaunchConfiguration('config_file'),
        {'use_sim_time': ParameterValue(LaunchConfiguration('use_sim_time'), value_type=bool)},
    ]


def test_launch_refers_to_files_and_executable_the_package_installs() -> None:
    setup_py = (REPO_ROOT / 'setup.py').read_text(encoding='utf-8')
    assert "'kentreg_node = kentreg_ros.ros.node:main'" in setup_py
    assert "glob('launch/*.py')" in setup_py and "glob('config/*.yaml')" in setup_py
    assert (REPO_ROOT / 'config' / 'kentreg.yaml').is_file()
    assert (REPO_ROOT / 'resource' / 'kentreg_ros').is_file()


@pytest.mark.skipif(
    importlib.util.find_spec('launch_ros') is None,
    reason='launch_ros is not installed (not on PyPI; source a ROS 2 Jazzy install)',
)
def test_launch_file_loads_with_real_launch_ros() -> None:
    if _installed_prefix() is None:
        pytest.skip('kentreg_ros is not in the ament index (colcon build and source it)')
    from launch.launch_description_sources import get_launch_description_from_python_launch_file

    description = get_launch_description_from_python_launch_file(str(LAUNCH_FILE))
    assert [a.name for a in description.get_launch_arguments()] == ARGUMENTS


def test_installed_package_has_marker_manifest_config_launch_and_executable(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    prefix = _installed_prefix()
    if prefix is None:
        pytest.skip('kentreg_ros is not installed in an ament prefix (runs under colcon test)')
    share = prefix / 'share' / 'kentreg_ros'
    assert (
        prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'kentreg_ros'
    ).is_file()
    for relative in ('package.xml', 'config/kentreg.yaml', 'launch/kentreg.launch.py'):
        assert (share / relative).is_file(), relative
    executable = prefix / 'lib' / 'kentreg_ros' / 'kentreg_node'
    assert executable.is_file() and os.access(executable, os.X_OK)
    # The launch file's default parameter file is the installed one.
    description, _ = _run_with_stubs(monkeypatch, None)
    (entities,) = description.args
    config_default = next(
        e.kwargs['default_value'] for e in entities if e.args and e.args[0] == 'config_file'
    )
    assert Path(config_default) == share / 'config' / 'kentreg.yaml'


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


def test_package_xml_declares_every_ros_package_the_node_player_and_launch_import() -> None:
    import xml.etree.ElementTree as ET

    manifest = ET.parse(REPO_ROOT / 'package.xml').getroot()
    assert manifest.get('format') == '3'
    assert manifest.findtext('name') == 'kentreg_ros'
    assert manifest.findtext('export/build_type') == 'ament_python'
    exec_depends = {e.text for e in manifest.findall('exec_depend')}
    imported = set()
    for module in (
        'kentreg_ros/ros/node.py',
        'kentreg_ros/ros/play.py',
        'launch/kentreg.launch.py',
    ):
        if (REPO_ROOT / module).is_file():
            imported |= _top_level_imports(REPO_ROOT / module)
    assert {'rclpy', 'sensor_msgs', 'launch_ros', 'rosgraph_msgs'} <= imported
    assert sorted(imported - exec_depends) == []
    assert {e.text for e in manifest.findall('test_depend')} == {'python3-pytest'}
