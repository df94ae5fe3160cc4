"""The command lines' shared parts (kentreg_ros.cli.common), ``kentreg`` and ``kentreg_register``.

``kentreg_replay`` and ``kentreg_convert`` have their own tests (test_replay.py,
test_convert.py).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scenes import box_room, random_transform, transform_points

from kentreg_ros.cli import common
from kentreg_ros.cli.__main__ import main as kentreg_main
from kentreg_ros.cli.register import main as register_main
from kentreg_ros.core import ConfigError, KentRegConfig
from kentreg_ros.io.paramfile import dump_config
from kentreg_ros.io.scanfiles import write_pcd


def test_run_main_turns_bad_input_into_one_line_and_status_2(
    capsys: pytest.CaptureFixture[str],
) -> None:
    def fail(exc: BaseException) -> int:
        raise exc

    cases: list[BaseException] = [
        common.CliError('--gt x: no such file'),
        ConfigError('Unknown configuration key(s)\nvalid keys are ...'),
        ValueError(''),
        OSError('disk full'),
    ]
    for exc in cases:
        assert common.run_main('prog', lambda exc=exc: fail(exc)) == common.EXIT_BAD_INPUT
        err = capsys.readouterr().err
        assert err.count('\n') == 1 and err.startswith('prog: error: ')
    assert common.run_main('prog', lambda: fail(ValueError(''))) == 2
    assert capsys.readouterr().err == 'prog: error: ValueError\n'
    assert common.run_main('prog', lambda: 0) == common.EXIT_OK


def test_run_main_exits_130_on_ctrl_c_and_lets_bugs_through(
    capsys: pytest.CaptureFixture[str],
) -> None:
    def interrupted() -> int:
        raise KeyboardInterrupt

    assert common.run_main('prog', interrupted) == common.EXIT_INTERRUPTED
    assert capsys.readouterr().err == 'prog: interrupted\n'
    assert common.run_main('prog', interrupted, interrupted='stopped early') == 130
    assert capsys.readouterr().err == 'prog: stopped early\n'

    def bug() -> int:
        raise TypeError('a bug')

    with pytest.raises(TypeError, match='a bug'):
        common.run_main('prog', bug)


@pytest.mark.parametrize(
    ('argv', 'match'),
    [
        (['--n', '-1'], "argument --n: expected a positive integer (>= 1), got '-1'"),
        (['--n', 'x'], "argument --n: expected an integer, got 'x'"),
        (['--x', 'nan'], "argument --x: expected a finite number, got 'nan'"),
        (['--x', '-0.5'], "argument --x: expected a finite number >= 0, got '-0.5'"),
        (['--set', 'mode'], "argument --set: expected KEY=VALUE, got 'mode'"),
        (['--set', '=paper'], "argument --set: expected KEY=VALUE, got '=paper'"),
        (['--bogus'], 'unrecognized arguments: --bogus'),
    ],
)
def test_parser_errors_raise_cli_error_naming_the_option(argv: list[str], match: str) -> None:
    parser = common.ArgumentParser(prog='prog')
    parser.add_argument('--n', type=common.positive_int)
    parser.add_argument('--x', type=common.non_negative_float)
    common.add_config_options(parser)
    with pytest.raises(common.CliError) as exc:
        parser.parse_args(argv)
    assert str(exc.value) == match


def test_config_options_read_the_file_then_the_overrides(tmp_path: Path) -> None:
    path = tmp_path / 'c.yaml'
    path.write_text(dump_config(KentRegConfig.paper()))
    parser = common.ArgumentParser(prog='prog')
    common.add_config_options(parser)
    args = parser.parse_args(['--config', str(path), '--set', 'em.max_iterations=7'])
    cfg = common.config_from_args(args)
    assert cfg.mode == 'paper' and cfg.em.max_iterations == 7
    assert common.config_from_args(parser.parse_args([])) == KentRegConfig()


def test_kentreg_dispatches_to_the_same_mains(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    missing = tmp_path / 'nothing_here'
    assert kentreg_main(['replay', str(missing)]) == 2
    assert capsys.readouterr().err == (
        f'kentreg_replay: error: {missing}: no such file or folder\n'
    )
    assert kentreg_main(['register', str(missing), str(missing)]) == 2
    assert 'kentreg_register: error: No such scan file' in capsys.readouterr().err
    assert kentreg_main(['fly']) == 2
    assert "kentreg: error: unknown command 'fly'" in capsys.readouterr().err
    assert kentreg_main(['--help']) == 0
    out = capsys.readouterr().out
    assert all(name in out for name in ('replay', 'register', 'convert'))
    assert kentreg_main([]) == 2
    with pytest.raises(SystemExit) as exc:
        kentreg_main(['convert', '--help'])
    assert exc.value.code == 0 and 'kentreg_convert' in capsys.readouterr().out


@pytest.fixture(scope='module')
def room_pair(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, np.ndarray]:
    """Two PCD views of a synthetic room and the true ``T_target_source``."""
    rng = np.random.default_rng(3)
    folder = tmp_path_factory.mktemp('pair')
    target = box_room(rng, 12000)
    T = random_transform(rng, 8.0, 0.3)
    # source = T^-1 target: then T maps source points onto the target.
    source = transform_points(np.linalg.inv(T), target)
    write_pcd(folder / 'target.pcd', target.astype(np.float32))
    write_pcd(folder / 'source.pcd', source.astype(np.float32))
    np.savetxt(folder / 'T.txt', T)
    return folder / 'source.pcd', folder / 'target.pcd', T


def test_register_reads_config_set_and_mode_and_reports_the_error(
    room_pair: tuple[Path, Path, np.ndarray], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    source, target, _ = room_pair
    config = tmp_path / 'c.yaml'
    config.write_text(dump_config(KentRegConfig.paper()))
    argv = [str(source), str(target), '--ref', str(source.parent / 'T.txt')]
    assert register_main([*argv, '--config', str(config), '--mode', 'robust']) == 0
    out = capsys.readouterr().out
    assert out.startswith('mode: robust ')
    match = re.search(r'error vs reference: rotation ([\d.]+) deg, translation ([\d.]+) m', out)
    assert match is not None, out
    assert float(match[1]) < 0.5 and float(match[2]) < 0.05
    overrides = ['--set', 'refine.method=none', '--set', 'em.max_iterations=5']
    assert register_main([*argv, *overrides]) == 0
    assert 'mode: robust' in capsys.readouterr().out


@pytest.mark.parametrize(
    ('extra', 'match'),
    [
        (['--set', 'em.nope=1'], 'Unknown parameter'),
        (['--set', 'nope'], "argument --set: expected KEY=VALUE, got 'nope'"),
        (['--init', '{missing}'], 'Cannot read initial transform'),
        (['--mode', 'fast'], "argument --mode: invalid choice: 'fast'"),
    ],
)
def test_register_bad_input_exits_2_with_one_line(
    room_pair: tuple[Path, Path, np.ndarray],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    extra: list[str],
    match: str,
) -> None:
    source, target, _ = room_pair
    args = [a.format(missing=tmp_path / 'missing.txt') for a in extra]
    assert register_main([str(source), str(target), *args]) == 2
    captured = capsys.readouterr()
    assert captured.out == ''
    assert captured.err.count('\n') == 1 and captured.err.startswith('kentreg_register: error: ')
    assert match in captured.err


@pytest.mark.integration
@pytest.mark.parametrize('script', ['kentreg', 'kentreg_register', 'kentreg_convert'])
def test_installed_console_scripts_fail_in_one_line(script: str, tmp_path: Path) -> None:
    path = shutil.which(script)
    if path is None:
        pytest.skip(f'{script} is not installed (pip install -e .)')
    argv = {'kentreg': ['fly'], 'kentreg_register': ['a', 'b'], 'kentreg_convert': ['a']}
    proc = subprocess.run(
        [path, *argv[script]], capture_output=True, text=True, timeout=60, check=False
    )
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1


@pytest.mark.integration
def test_python_m_kentreg_ros_cli_runs_the_dispatcher(repo_root: Path, tmp_path: Path) -> None:
    env = {**os.environ, 'PYTHONPATH': os.pathsep.join([str(repo_root), *sys.path])}
    proc = subprocess.run(
        [sys.executable, '-m', 'kentreg_ros.cli', 'replay', str(tmp_path / 'nothing_here')],
        capture_output=True, text=True, env=env, timeout=60, check=False,
    )  # fmt: skip
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f'kentreg_replay: error: {tmp_path / "nothing_here"}: no such file or folder'
    ]


@pytest.mark.integration
@pytest.mark.parametrize('script', ['kentreg_node', 'kentreg_play'])
def test_ros_console_scripts_answer_help_at_once_with_status_0(
    script: str, repo_root: Path
) -> None:
    """``--help`` prints the usage (with where the ROS arguments go) and exits 0 without
    starting ROS: before, ``kentreg_node --help`` started the node and never returned. Run as
    the console script when it is installed, else as ``python -m`` of its module."""
    pytest.importorskip('rclpy', reason='rclpy is not installed (pip install -e .[ros])')
    path = shutil.which(script)
    module = {'kentreg_node': 'kentreg_ros.ros.node', 'kentreg_play': 'kentreg_ros.ros.play'}
    cmd = [path] if path is not None else [sys.executable, '-m', module[script]]
    env = {**os.environ, 'PYTHONPATH': os.pathsep.join([str(repo_root), *sys.path])}
    try:
        proc = subprocess.run(
            [*cmd, '--help'], capture_output=True, text=True, env=env, timeout=60, check=False
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f'{script} --help did not return within 60 s (it started the node?)')
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(f'usage: {script}') and '--ros-args' in proc.stdout
    assert proc.stderr == ''
