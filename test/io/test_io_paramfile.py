"""Parameter files (kentreg_ros.io.paramfile): the ROS 2 YAML form, round trip, overrides."""

from __future__ import annotations

from pathlib import Path

import pytest

from kentreg_ros.core import ConfigError, KentRegConfig
from kentreg_ros.io.paramfile import (
    dump_config,
    effective_config,
    load_config,
    parameters_from_yaml,
)
from kentreg_ros.io.params import NodeSettings
from kentreg_ros.io.yamlfile import parse_overrides

REPO = Path(__file__).resolve().parents[2]


def test_shipped_yaml_equals_the_defaults() -> None:
    assert load_config(REPO / 'config' / 'kentreg.yaml') == KentRegConfig()


def test_round_trip_through_yaml(tmp_path: Path) -> None:
    cfg = KentRegConfig().with_updates({'em.max_iterations': 7, 'mode': 'paper'})
    path = tmp_path / 'c.yaml'
    path.write_text(dump_config(cfg))
    assert load_config(path) == cfg


def test_plain_and_dotted_yaml_forms(tmp_path: Path) -> None:
    path = tmp_path / 'c.yaml'
    path.write_text('em.max_iterations: 9\nnormals:\n  k_neighbors: 20\n')
    cfg = load_config(path)
    assert cfg.em.max_iterations == 9 and cfg.normals.k_neighbors == 20
    assert parameters_from_yaml(path) == {'em.max_iterations': 9, 'normals.k_neighbors': 20}


@pytest.mark.parametrize('key', ['kentreg_node', '/kentreg_node', '/robot1/kentreg_node',
                                 '/**/kentreg_node', '/**'])  # fmt: skip
def test_ros_parameter_file_node_keys(tmp_path: Path, key: str) -> None:
    path = tmp_path / 'c.yaml'
    other = 'other_node:\n  ros__parameters:\n    em:\n      max_iterations: 3\n'
    path.write_text(f'{other}{key!r}:\n  ros__parameters:\n    em:\n      max_iterations: 9\n')
    assert parameters_from_yaml(path) == {'em.max_iterations': 9}


def test_missing_and_invalid_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match='Cannot read'):
        load_config(tmp_path / 'missing.yaml')
    bad = tmp_path / 'bad.yaml'
    bad.write_text('em: [1, 2\n')
    with pytest.raises(ConfigError, match='not valid YAML'):
        load_config(bad)


def test_overrides_are_yaml_scalars_and_text_otherwise() -> None:
    assert parse_overrides(
        ['em.max_iterations=30', ' refine.normal_weight = false', 'mode=paper', 'x=', 'y=[1, 2']
    ) == {
        'em.max_iterations': 30,
        'refine.normal_weight': False,
        'mode': 'paper',
        'x': '',
        'y': '[1, 2',
    }


@pytest.mark.parametrize('item', ['mode', '=paper', ' =1'])
def test_override_without_key_or_equals_is_rejected(item: str) -> None:
    with pytest.raises(ConfigError, match=f'Expected KEY=VALUE, got {item!r}'):
        parse_overrides([item])


def test_effective_config_applies_overrides_on_top_of_the_file(tmp_path: Path) -> None:
    path = tmp_path / 'c.yaml'
    path.write_text(dump_config(KentRegConfig.paper()))
    cfg = effective_config(path, ['em.max_iterations=7'])
    assert cfg.mode == 'paper' and cfg.em.max_iterations == 7
    assert effective_config() == KentRegConfig()
    assert effective_config(None, {'normals.k_neighbors': 20}).normals.k_neighbors == 20
    with pytest.raises(ConfigError, match=r'Unknown parameter\(s\) \[.em.no_such_key.\]'):
        effective_config(None, ['em.no_such_key=1'])


@pytest.mark.parametrize(
    ('text', 'value'),
    [
        ('1e-3', 1e-3),
        ('1E-3', 1e-3),
        ('.5', 0.5),
        ('1e3', 1000.0),
        ('-2E-2', -0.02),
        ('+1.5e+2', 150.0),
        ('3', 3),
        ('1e-3x', '1e-3x'),
    ],
)
def test_numbers_read_as_a_user_writes_them(text: str, value: object, tmp_path: Path) -> None:
    """YAML 1.1 (PyYAML) reads 1e-3 as a string; rcl, which reads the node's files, and YAML
    1.2 read it as a number: --set and parameter files must agree with the node."""
    assert parse_overrides([f'em.tolerance={text}']) == {'em.tolerance': value}
    path = tmp_path / 'c.yaml'
    path.write_text(f'/**:\n  ros__parameters:\n    em:\n      tolerance: {text}\n')
    assert parameters_from_yaml(path) == {'em.tolerance': value}
    if isinstance(value, float) and 0 <= value <= 1:
        assert load_config(path).em.tolerance == value


def test_the_replay_takes_exponent_numbers_from_set(tmp_path: Path) -> None:
    import contextlib
    import io

    pytest.importorskip('rosbags', reason='rosbags is not installed (pip install -e .[io])')
    from kentreg_ros.cli.replay import main

    out = tmp_path / 'run'
    argv = [str(REPO / 'bags' / 'balm_50'), '--max-scans', '2', '--no-progress', '--no-plot']
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        code = main([*argv, '--out', str(out), '--set', 'em.tolerance=1e-3'])
    assert code == 0, err.getvalue()
    assert load_config(out / 'config.yaml').em.tolerance == 1e-3


@pytest.mark.parametrize(('text', 'expected'), [('off', 'off'), ('on', 'on'), ("'off'", 'off')])
def test_off_and_on_unquoted_in_yaml_are_the_choices_they_spell(
    text: str, expected: str, tmp_path: Path
) -> None:
    """YAML 1.1 (ROS parameter files, ``-p name:=value``) reads an unquoted off/on as a boolean:
    ``deskew: off`` must still be the choice 'off', not an error about False."""
    path = tmp_path / 'c.yaml'
    path.write_text(f'/**:\n  ros__parameters:\n    odometry:\n      deskew: {text}\n')
    assert load_config(path).odometry.deskew == expected
    assert KentRegConfig().with_updates({'odometry.deskew': expected == 'on'}).odometry.deskew == (
        expected
    )


def test_node_parameters_take_an_unquoted_off() -> None:
    settings = NodeSettings(registered_cloud=False)  # what `-p registered_cloud:=off` gives
    assert settings.registered_cloud == 'off'
    with pytest.raises(ConfigError, match='one of'):
        NodeSettings(pipeline=False)  # no 'off' among its choices: still an error
