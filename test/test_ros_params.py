"""The node's own parameters (rclpy-free) and the shipped parameter file."""

from __future__ import annotations

from pathlib import Path

import pytest

from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.errors import ConfigError
from kentreg_ros.io.params import load_config, parameters_from_yaml
from kentreg_ros.ros.params import NODE_PARAMETERS, dump_parameter_file, node_settings

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
    settings = node_settings(node)
    assert settings.queue_policy == 'drop_oldest' and settings.queue_size == 1
    assert settings.base_to_lidar == (0.0,) * 6


@pytest.mark.parametrize(
    ('values', 'match'),
    [
        ({'node.bogus': 1}, r"Unknown node parameter\(s\) \['node.bogus'\]"),
        ({'node.queue_size': 0}, r'`node.queue_size` in \[1, 1000\], got 0'),
        ({'node.queue_size': 2.5}, '`node.queue_size` to be of type int'),
        ({'node.publish_tf': 1}, '`node.publish_tf` to be of type bool'),
        ({'node.qos_reliability': 'fast'}, "one of \\['best_effort', 'reliable'\\]"),
        ({'node.base_to_lidar': [0.0, 1.0]}, 'list of 6 numbers'),
        ({'node.odom_frame': ' '}, 'non-empty frame name'),
        ({'node.base_frame': 'odom'}, 'must differ'),
    ],
)
def test_node_settings_reject_bad_values(values: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        node_settings(values)


def test_node_settings_accept_integers_for_floats() -> None:
    settings = node_settings({'node.tf_wait': 2, 'node.base_to_lidar': [1, 0, 0, 0, 0, 3]})
    assert settings.tf_wait == 2.0 and isinstance(settings.tf_wait, float)
    assert settings.base_to_lidar == (1.0, 0.0, 0.0, 0.0, 0.0, 3.0)
