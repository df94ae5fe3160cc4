"""The node's own parameters (rclpy-free) and the shipped parameter file."""

from __future__ import annotations

from pathlib import Path

import pytest

from kentreg_ros.core import ConfigError, KentRegConfig
from kentreg_ros.io.params import load_config, parameters_from_yaml
from kentreg_ros.ros.params import NODE_PARAMETERS, NodeSettings, dump_parameter_file

REPO = Path(__file__).resolve().parents[1]


def test_shipped_parameter_file_is_the_generated_one() -> None:
    shipped = (REPO / 'config' / 'kentreg.yaml').read_text()
    assert shipped == dump_parameter_file(), (
        'config/kentreg.yaml is stale: python3 -m kentreg_ros.ros.params > config/kentreg.yaml'
    )


def test_shipped_file_holds_every_node_default_and_replay_ignores_them() -> None:
    params = parameters_from_yaml(REPO / 'config' / 'kentreg.yaml')
    node = {k: v for k, v in params.items() if k.startswith('node.')}
    assert node == {p.name: p.default for p in NODE_PARAMETERS}
    assert load_config(REPO / 'config' / 'kentreg.yaml') == KentRegConfig()
    settings = NodeSettings.from_dict(node)
    assert settings == NodeSettings()
    assert settings.queue_policy == 'drop_oldest' and settings.queue_size == 1
    assert settings.base_to_lidar == (0.0,) * 6


@pytest.mark.parametrize(
    ('values', 'match'),
    [
        ({'node.bogus': 1}, r"Unknown node parameter\(s\) \['node.bogus'\]"),
        ({'node.queue_size': 0}, r'^Expected `node.queue_size` in \[1, 1000\], got 0\.$'),
        ({'node.queue_size': 2.5}, r'^Expected `node.queue_size` to be an integer, got 2\.5\.$'),
        ({'node.publish_tf': 1}, '`node.publish_tf` to be true or false'),
        ({'node.qos_reliability': 'fast'}, "one of \\['best_effort', 'reliable'\\]"),
        ({'node.base_to_lidar': [0.0, 1.0]}, 'list of 6 numbers'),
        ({'node.base_to_lidar': 'up'}, 'list of numbers'),
        ({'node.base_to_lidar': [0.0, 'a', 0, 0, 0, 0]}, r'`node.base_to_lidar\[1\]`'),
        ({'node.odom_frame': ' '}, 'non-empty frame name'),
        ({'node.base_frame': 'odom'}, 'must differ'),
    ],
)
def test_node_settings_reject_bad_values(values: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        NodeSettings.from_dict(values)


def test_node_and_registration_parameters_fail_with_the_same_wording() -> None:
    """One validation system: a range, a choice and a type are refused by the same functions
    (core.config's validate_value and coerce_value), whichever parameter set they belong to."""
    pairs = [
        ({'em.max_iterations': 0}, {'node.queue_size': 0}, 'in [1, '),
        ({'mode': 'x'}, {'node.queue_policy': 'x'}, 'to be one of ['),
        ({'em.max_iterations': 'x'}, {'node.queue_size': 'x'}, 'to be an integer, got '),
        ({'em.kent_beta': 'x'}, {'node.use_tf': 'x'}, 'to be true or false, got '),
        ({'em.tolerance': 'x'}, {'node.tf_wait': 'x'}, 'to be a number, got '),
    ]
    for config_values, node_values, wording in pairs:
        with pytest.raises(ConfigError) as config_error:
            KentRegConfig().with_updates(config_values)
        with pytest.raises(ConfigError) as node_error:
            NodeSettings.from_dict(node_values)
        assert wording in str(config_error.value) and wording in str(node_error.value)


def test_node_settings_validate_on_construction_like_the_config() -> None:
    with pytest.raises(ConfigError, match=r'`node.tf_wait` in \[0.0, 60.0\]'):
        NodeSettings(tf_wait=-1.0)


def test_node_settings_accept_integers_for_floats() -> None:
    settings = NodeSettings.from_dict(
        {'node.tf_wait': 2, 'node.base_to_lidar': [1, 0, 0, 0, 0, 3]}
    )
    assert settings.tf_wait == 2.0 and isinstance(settings.tf_wait, float)
    assert settings.base_to_lidar == (1.0, 0.0, 0.0, 0.0, 0.0, 3.0)


def test_with_updates_changes_only_the_given_parameters() -> None:
    before = NodeSettings.from_dict({'node.path_length': 7})
    after = before.with_updates({'node.queue_size': 3})
    assert (after.path_length, after.queue_size) == (7, 3)
    assert after.to_parameters() == {
        **before.to_parameters(),
        'node.queue_size': 3,
    }


def test_parameters_fixed_at_start_up_are_declared_read_only() -> None:
    """The node reads these once (tf listener, timer period, subscription QoS)."""
    read_only = {p.name for p in NODE_PARAMETERS if p.read_only}
    assert read_only == {
        'node.use_tf',
        'node.diagnostics_period',
        'node.qos_reliability',
        'node.qos_depth',
    }
