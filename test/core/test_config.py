"""The configuration tree: defaults, metadata and validation (its YAML: test_io_params.py)."""

from __future__ import annotations

import pytest

from kentreg_ros.core import ConfigError, KentRegConfig, iter_fields


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


@pytest.mark.parametrize(
    ('section', 'kwargs', 'match'),
    [
        ('EMConfig', {'kent_beta': 'no'}, '`em.kent_beta` to be true or false'),
        ('EMConfig', {'max_iterations': 2.5}, '`em.max_iterations` to be an integer'),
        ('EMConfig', {'rotation': 'mean'}, '`em.rotation` to be one of'),
        ('NormalsConfig', {'k_neighbors': 3}, r'`normals.k_neighbors` in \[5, 100\]'),
        ('OdometryConfig', {'constant_velocity': 1}, 'true or false'),
        ('RefineConfig', {'method': None}, '`refine.method` to be one of'),
        ('PreprocessConfig', {'voxel_size': '0.1'}, '`preprocess.voxel_size` to be a number'),
    ],
)
def test_sections_built_directly_are_validated_like_any_other_way(
    section: str, kwargs: dict, match: str
) -> None:
    import kentreg_ros.core.config as config

    with pytest.raises(ConfigError, match=match):
        getattr(config, section)(**kwargs)


def test_numbers_are_coerced_to_the_fields_type_however_the_config_is_made() -> None:
    from kentreg_ros.core.config import EMConfig

    em = EMConfig(max_iterations=30.0, tolerance=1)
    assert em.max_iterations == 30 and isinstance(em.max_iterations, int)
    assert em.tolerance == 1.0 and isinstance(em.tolerance, float)
    assert KentRegConfig(em=em) == KentRegConfig().with_updates(
        {'em.max_iterations': 30, 'em.tolerance': 1.0}
    )
    with pytest.raises(ConfigError, match='`em` to be a EMConfig'):
        KentRegConfig(em='fast')  # type: ignore[arg-type]


@pytest.mark.parametrize('make', ['direct', 'updates', 'dict'])
def test_min_range_must_stay_below_max_range(make: str) -> None:
    from kentreg_ros.core.config import PreprocessConfig

    match = r'preprocess.min_range < preprocess.max_range .*min_range=5.0 >= max_range=2.0'
    with pytest.raises(ConfigError, match=match):
        if make == 'direct':
            PreprocessConfig(min_range=5.0, max_range=2.0)
        elif make == 'updates':
            KentRegConfig().with_updates({'preprocess.min_range': 5, 'preprocess.max_range': 2})
        else:
            KentRegConfig.from_dict({'preprocess': {'min_range': 5.0, 'max_range': 2.0}})
    # max_range 0 means no limit: any min_range is fine with it.
    assert KentRegConfig().with_updates({'preprocess.min_range': 5.0}).preprocess.max_range == 0
