"""The product parameters (rclpy-free): the shipped file, validation, the research split."""

from __future__ import annotations

from pathlib import Path

import pytest

from kentreg_ros.core import ConfigError, KentRegConfig
from kentreg_ros.io.errors import ParameterError
from kentreg_ros.io.paramfile import (
    dump_parameter_file,
    load_config,
    load_settings,
    parameters_from_yaml,
)
from kentreg_ros.io.params import (
    CORE_PARAMETERS,
    PARAMETERS,
    NodeSettings,
    apply_parameters,
    product_values,
)

REPO = Path(__file__).resolve().parents[2]
SHIPPED = REPO / 'config' / 'kentreg.yaml'


def test_shipped_parameter_file_is_the_generated_one() -> None:
    assert SHIPPED.read_text() == dump_parameter_file(), (
        'config/kentreg.yaml is stale: python3 -m kentreg_ros.docs --parameter-file > '
        'config/kentreg.yaml'
    )


def test_the_product_surface_is_small_flat_and_under_any_node_name() -> None:
    # The odometry's 29 and the localization's two (map_file, map_frame): each one more is a
    # choice an operator has to understand.
    assert len(PARAMETERS) <= 31
    assert all('.' not in p.name for p in PARAMETERS)  # flat ROS names
    assert {'odom_frame', 'base_frame', 'publish_tf'} <= {p.name for p in PARAMETERS}
    text = SHIPPED.read_text()
    assert '\n/**:\n  ros__parameters:\n' in text
    params = parameters_from_yaml(SHIPPED, node_name='any_other_name')
    assert params == {p.name: p.default for p in PARAMETERS}
    settings = load_settings(SHIPPED)
    assert settings.config == KentRegConfig() and settings.node == NodeSettings()


def test_core_parameters_are_research_fields_with_their_metadata() -> None:
    fields = KentRegConfig().to_flat_dict()
    for p in PARAMETERS:
        if p.field:
            assert CORE_PARAMETERS[p.name] == p.field and fields[p.field] == p.default
    settings = apply_parameters({'max_range': 80, 'model': 'local_map', 'odom_frame': 'map2'})
    assert settings.config.preprocess.max_range == 80.0
    assert settings.config.odometry.model == 'local_map'
    assert settings.node.odom_frame == 'map2'
    assert product_values(settings.config, settings.node)['max_range'] == 80.0


def test_research_fields_reach_the_command_lines_not_the_node() -> None:
    lab = apply_parameters({'em.tolerance': 1e-3, 'mode': 'paper'})
    assert lab.config.em.tolerance == 1e-3 and lab.config.mode == 'paper'
    node = apply_parameters(
        {'em.tolerance': 1e-3, 'other_node_key': 1}, research=False, strict=False
    )
    assert node.config == KentRegConfig() and node.unknown == ('em.tolerance', 'other_node_key')
    with pytest.raises(ConfigError, match=r"Unknown parameter\(s\) \['bogus'\]; expected one of"):
        apply_parameters({'bogus': 1})


def test_a_parameter_file_round_trips_research_fields(tmp_path: Path) -> None:
    cfg = KentRegConfig().with_updates(
        {'em.max_iterations': 7, 'mode': 'paper', 'preprocess.max_range': 40}
    )
    path = tmp_path / 'c.yaml'
    path.write_text(dump_parameter_file(cfg))
    assert load_config(path) == cfg
    assert '    max_range: 40.0\n' in path.read_text()  # a product parameter, by its flat name
    assert '    em.max_iterations: 7\n' in path.read_text()  # research: dotted, after them


@pytest.mark.parametrize(
    ('values', 'match'),
    [
        ({'bogus': 1}, r"Unknown parameter\(s\) \['bogus'\]"),
        ({'queue_size': 0}, r'^Expected `queue_size` in \[1, 1000\], got 0\.$'),
        ({'queue_size': 2.5}, r'^Expected `queue_size` to be an integer, got 2\.5\.$'),
        ({'publish_tf': 1}, '`publish_tf` to be true or false'),
        ({'qos_reliability': 'fast'}, "one of \\['best_effort', 'reliable'\\]"),
        ({'base_to_lidar': [0.0, 1.0]}, 'list of 6 numbers'),
        ({'base_to_lidar': 'up'}, 'list of numbers'),
        ({'base_to_lidar': [0.0, 'a', 0, 0, 0, 0]}, r'`base_to_lidar\[1\]`'),
        ({'odom_frame': ' '}, 'non-empty frame name'),
        ({'base_frame': 'odom'}, 'must differ'),
        ({'map_frame': 'odom'}, 'the map, odometry and moving frames must differ'),
        ({'map_frame': ''}, '`map_frame` to be a non-empty frame name'),
        ({'map_file': 'site.ply', 'invert_tf': True}, 'a second parent in tf'),
        ({'max_range': -1}, r'`preprocess.max_range` in \[0.0, 10000.0\]'),
        ({'min_range': 5, 'max_range': 2}, 'min_range < preprocess.max_range'),
        ({'model': 'map'}, "one of \\['previous_scan', 'local_map'\\]"),
    ],
)
def test_bad_values_are_refused_with_the_reason(values: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        apply_parameters(values)


@pytest.mark.parametrize(
    ('values', 'names'),
    [
        ({'max_range': -1}, ('max_range',)),  # named by its research field
        ({'path_length': 0, 'max_range': 3.0}, ('path_length',)),
        ({'min_range': 5, 'max_range': 2}, ('min_range', 'max_range')),  # a rule of two
        ({'base_to_lidar': [0.0, 'a', 0, 0, 0, 0]}, ('base_to_lidar',)),
        ({'em.tolerance': -1.0}, ('em.tolerance',)),
        ({'bogus': 1, 'max_range': 3.0}, ('bogus',)),
        ({'map_frame': 'odom', 'max_range': 3.0}, ('map_frame',)),
    ],
)
def test_a_refused_parameter_is_named_with_the_reason(values: dict, names: tuple) -> None:
    with pytest.raises(ParameterError) as caught:
        apply_parameters(values)
    assert caught.value.names == names
    assert str(caught.value) == caught.value.reason
    assert isinstance(caught.value, ConfigError)  # callers catching ConfigError still do


def test_node_settings_validate_on_construction_like_the_config() -> None:
    with pytest.raises(ConfigError, match=r'`tf_wait` in \[0.0, 60.0\]'):
        NodeSettings(tf_wait=-1.0)
    settings = NodeSettings().with_updates({'tf_wait': 2, 'base_to_lidar': [1, 0, 0, 0, 0, 3]})
    assert settings.tf_wait == 2.0 and isinstance(settings.tf_wait, float)
    assert settings.base_to_lidar == (1.0, 0.0, 0.0, 0.0, 0.0, 3.0)


def test_parameters_fixed_at_start_up_are_declared_read_only() -> None:
    """The node reads these once (timer period, subscription QoS, the voxel and the bound of
    the map of the run, which a change would have to throw away, the pipeline, whose
    worker process starts with the node, and the saved map of the localization and its frame,
    which the node loads and publishes from start-up)."""
    read_only = {p.name for p in PARAMETERS if p.read_only}
    assert read_only == {
        'diagnostics_period', 'qos_reliability', 'qos_depth', 'map_voxel_size', 'map_max_points',
        'pipeline', 'map_file', 'map_frame',
    }  # fmt: skip
