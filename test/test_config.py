"""The configuration tree: defaults, validation, YAML round trip."""

from __future__ import annotations

from pathlib import Path

import pytest

from kentreg_ros.core.config import (
    KentRegConfig,
    dump_config,
    iter_fields,
    load_config,
    parameters_from_yaml,
)
from kentreg_ros.core.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]


def test_every_field_has_a_description_and_a_range_or_choices_or_is_bool() -> None:
    for name, value, f in iter_fields(KentRegConfig()):
        assert f.metadata.get('description'), name
        assert isinstance(value, bool) or 'range' in f.metadata or 'choices' in f.metadata, name


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


def test_unknown_key_lists_the_valid_ones() -> None:
    with pytest.raises(ConfigError, match=r"Unknown configuration key\(s\) \['em.max_iter'\]"):
        KentRegConfig.from_dict({'em': {'max_iter': 3}})
    with pytest.raises(ConfigError, match='em.max_iterations'):
        KentRegConfig().with_updates({'em.max_iter': 3})


@pytest.mark.parametrize(
    ('update', 'match'),
    [
        ({'em.max_iterations': 0}, r'`em.max_iterations` in \[1, 10000\], got 0'),
        ({'em.outlier_weight': 1.5}, 'em.outlier_weight'),
        ({'mode': 'fast'}, "`mode` to be one of \\['robust', 'paper'\\]"),
        ({'em.kent_beta': 'yes'}, 'true or false'),
        ({'normals.k_neighbors': 'ten'}, 'integer'),
        ({'em.kappa_cap_start': 100.0, 'em.kappa_cap_end': 10.0}, 'kappa_cap_end'),
    ],
)
def test_bad_values_are_rejected_with_the_reason(update: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        KentRegConfig().with_updates(update)


def test_missing_and_invalid_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match='Cannot read'):
        load_config(tmp_path / 'missing.yaml')
    bad = tmp_path / 'bad.yaml'
    bad.write_text('em: [1, 2\n')
    with pytest.raises(ConfigError, match='not valid YAML'):
        load_config(bad)
