"""The ROS node's own parameters (``node.*``), kept free of rclpy so docs and tools can read them.

The registration parameters are the :class:`~kentreg_ros.core.config.KentRegConfig` fields; the
node adds the ones below (frames, queue, QoS, outputs). All of them live in one parameter file,
``config/kentreg.yaml``, in the ``kentreg_node: ros__parameters:`` form that ``kentreg_replay
--config`` also reads (it skips the ``node`` section).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.errors import ConfigError
from kentreg_ros.io.params import NODE_NAME

__all__ = [
    'NODE_PARAMETERS',
    'NodeParameter',
    'NodeSettings',
    'dump_parameter_file',
    'node_settings',
]


@dataclass(frozen=True)
class NodeParameter:
    """One ``node.*`` parameter: name, default, description and constraints."""

    name: str
    default: Any
    description: str
    range: tuple[float, float] | None = None
    choices: tuple[str, ...] | None = None
    read_only: bool = False

    def validate(self, value: Any) -> None:
        """Raise :class:`ConfigError` naming the parameter when ``value`` is not allowed."""
        kind = type(self.default)
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if kind is list:
            if not isinstance(value, list | tuple) or len(value) != len(self.default):
                raise ConfigError(
                    f'Expected `{self.name}` to be a list of {len(self.default)} numbers, '
                    f'got {value!r}.'
                )
            return
        if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
            raise ConfigError(
                f'Expected `{self.name}` to be of type {kind.__name__}, got {value!r}.'
            )
        if self.choices is not None and value not in self.choices:
            raise ConfigError(
                f'Expected `{self.name}` to be one of {list(self.choices)}, got {value!r}.'
            )
        if self.range is not None and not self.range[0] <= value <= self.range[1]:
            lo, hi = self.range
            raise ConfigError(f'Expected `{self.name}` in [{lo}, {hi}], got {value!r}.')


NODE_PARAMETERS: tuple[NodeParameter, ...] = (
    NodeParameter(
        'node.odom_frame',
        'odom',
        'Fixed frame of the odometry (REP-105): header.frame_id of odom, pose and path.',
    ),
    NodeParameter(
        'node.base_frame',
        'base_link',
        'Robot body frame (REP-105): child_frame_id of odom and of the odom->base TF.',
    ),
    NodeParameter(
        'node.base_to_lidar',
        [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        'Pose of the sensor in base_frame as [x, y, z, roll, pitch, yaw] (m, rad), used when '
        'tf2 is not available or has no base_frame<-sensor transform within node.tf_wait. All '
        'zeros: the sensor frame is the base frame.',
    ),
    NodeParameter(
        'node.use_tf',
        True,
        'Look the static base_frame<-sensor transform up in tf2 (when tf2_ros is installed).',
        read_only=True,
    ),
    NodeParameter(
        'node.tf_wait',
        1.0,
        'Seconds to wait for the base_frame<-sensor transform in tf2 before using '
        'node.base_to_lidar (scans that arrive meanwhile are dropped and counted).',
        range=(0.0, 60.0),
    ),
    NodeParameter(
        'node.publish_tf',
        True,
        'Broadcast odom_frame->base_frame on /tf (needs tf2_ros; logged once if missing).',
    ),
    NodeParameter(
        'node.publish_path',
        True,
        'Publish nav_msgs/Path on `path` after every scan.',
    ),
    NodeParameter(
        'node.path_length',
        1000,
        'Most recent poses kept in the published path (bounded memory).',
        range=(1, 1_000_000),
    ),
    NodeParameter(
        'node.publish_diagnostics',
        True,
        'Publish diagnostic_msgs/DiagnosticArray on `diagnostics` every diagnostics_period.',
    ),
    NodeParameter(
        'node.diagnostics_period',
        1.0,
        'Seconds between diagnostics messages (rates are measured over this window).',
        range=(0.1, 3600.0),
        read_only=True,
    ),
    NodeParameter(
        'node.queue_size',
        1,
        'Scans waiting for the worker at most; 1 keeps only the newest (the worker never '
        'falls behind the sensor). Scans pushed out are dropped and counted.',
        range=(1, 1000),
    ),
    NodeParameter(
        'node.queue_policy',
        'drop_oldest',
        'When the queue is full: drop_oldest (latest wins, for live use) or drop_newest '
        '(the incoming scan is dropped).',
        choices=('drop_oldest', 'drop_newest'),
    ),
    NodeParameter(
        'node.qos_reliability',
        'best_effort',
        'Reliability of the `points` subscription: best_effort (sensor-data QoS, matches '
        'every publisher) or reliable.',
        choices=('best_effort', 'reliable'),
        read_only=True,
    ),
    NodeParameter(
        'node.qos_depth',
        5,
        'History depth of the `points` subscription.',
        range=(1, 1000),
        read_only=True,
    ),
)

_BY_NAME = {p.name: p for p in NODE_PARAMETERS}


@dataclass(frozen=True)
class NodeSettings:
    """Validated values of the ``node.*`` parameters."""

    odom_frame: str
    base_frame: str
    base_to_lidar: tuple[float, ...]
    use_tf: bool
    tf_wait: float
    publish_tf: bool
    publish_path: bool
    path_length: int
    publish_diagnostics: bool
    diagnostics_period: float
    queue_size: int
    queue_policy: str
    qos_reliability: str
    qos_depth: int


def node_settings(values: Mapping[str, Any]) -> NodeSettings:
    """Validate ``{'node.x': value}`` (missing names take defaults) into :class:`NodeSettings`.

    Raises
    ------
    ConfigError
        An unknown ``node.*`` name, a wrong type, a value out of range or not among the
        choices, or an empty frame name.
    """
    unknown = sorted(set(values) - set(_BY_NAME))
    if unknown:
        raise ConfigError(
            f'Unknown node parameter(s) {unknown}; valid ones are {sorted(_BY_NAME)}.'
        )
    merged: dict[str, Any] = {}
    for param in NODE_PARAMETERS:
        value = values.get(param.name, param.default)
        param.validate(value)
        if isinstance(param.default, float):
            value = float(value)
        if isinstance(param.default, list):
            value = tuple(float(v) for v in value)
        merged[param.name.removeprefix('node.')] = value
    for key in ('odom_frame', 'base_frame'):
        if not merged[key].strip():
            raise ConfigError(f'Expected `node.{key}` to be a non-empty frame name.')
    if merged['odom_frame'] == merged['base_frame']:
        raise ConfigError(
            f'`node.odom_frame` and `node.base_frame` are both {merged["odom_frame"]!r}; '
            'they must differ.'
        )
    return NodeSettings(**merged)


def dump_parameter_file(
    config: KentRegConfig | None = None,
    node: Sequence[NodeParameter] = NODE_PARAMETERS,
    node_name: str = NODE_NAME,
) -> str:
    """The shipped parameter file: every registration and node parameter with its default."""
    import yaml

    cfg = config if config is not None else KentRegConfig()
    params: dict[str, Any] = cfg.to_dict()
    params['node'] = {p.name.removeprefix('node.'): p.default for p in node}
    header = (
        '# kentreg parameters: read by kentreg_node (ros2 run / launch) and by kentreg_replay\n'
        '# --config (which ignores the node section). Every key is documented in README.md\n'
        '# (parameter table), kentreg_ros/core/config.py and kentreg_ros/ros/params.py.\n'
        '# Regenerate: python3 -m kentreg_ros.ros.params > config/kentreg.yaml\n'
    )
    body = yaml.safe_dump({node_name: {'ros__parameters': params}}, sort_keys=False)
    return header + body


if __name__ == '__main__':
    print(dump_parameter_file(), end='')
