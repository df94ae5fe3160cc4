"""The configuration tree: defaults, metadata and validation (its YAML: test_io_params.py)."""

from __future__ import annotations

import pytest

from kentreg_ros.core.config import KentRegConfig, iter_fields
from kentreg_ros.core.errors import ConfigError


def test_every_field_has_a_description_and_a_range_or_choices_or_is_bool() -> None:
    for name, value, f in iter_fields(KentRegConfig()):
        assert f.metadata.get('description'), name
        assert isinstance(value, bool) or 'range' in f.metadata or 'choices' in f.metadata, name


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
