"""The ROS node's own parameters (``node.*``), kept free of rclpy so docs and tools can read them.

The registration parameters are the :class:`~kentreg_ros.core.config.KentRegConfig` fields; the
node adds the fields of :class:`NodeSettings` (frames, queue, QoS, outputs) as ``node.<field>``.
Both are described the same way (field metadata: description, range, choices) and validated by
the same functions of :mod:`kentreg_ros.core.config`, so a value is accepted or refused with the
same message whichever set it belongs to. All of them live in one parameter file,
``config/kentreg.yaml``, in the ``kentreg_node: ros__parameters:`` form that ``kentreg_replay
--config`` also reads (it skips the ``node`` section).

Regenerate the shipped file with ``python3 -m kentreg_ros.ros.params > config/kentreg.yaml``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, get_type_hints

import yaml

from kentreg_ros.core import ConfigError
from kentreg_ros.core.config import KentRegConfig, coerce_value, iter_fields, validate_value
from kentreg_ros.io.params import NODE_NAME

__all__ = [
    'NODE_PARAMETERS',
    'PREFIX',
    'NodeParameter',
    'NodeSettings',
    'dump_parameter_file',
]

#: The node's own parameters are named ``node.<field of NodeSettings>``.
PREFIX = 'node.'


def _param(
    default: Any,
    description: str,
    *,
    range: tuple[float, float] | None = None,
    choices: tuple[str, ...] | None = None,
    read_only: bool = False,
) -> Any:
    """A :class:`NodeSettings` field. Its metadata has the keys of a
    :class:`~kentreg_ros.core.config.KentRegConfig` field (``description``, ``range``,
    ``choices``), so :func:`~kentreg_ros.core.config.validate_value` checks both, plus
    ``read_only`` (set at start-up only)."""
    meta: dict[str, Any] = {'description': description}
    if range is not None:
        meta['range'] = range
    if choices is not None:
        meta['choices'] = choices
    if read_only:
        meta['read_only'] = True
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class NodeSettings:
    """Values of the ``node.*`` parameters, validated on construction like ``KentRegConfig``.

    Raises
    ------
    ConfigError
        A value out of range or not among its choices, ``base_to_lidar`` not 6 numbers, an
        empty frame name, or the same name for both frames.
    """

    odom_frame: str = _param(
        'odom',
        'Fixed frame of the odometry (REP-105): header.frame_id of odom, pose and path.',
    )
    base_frame: str = _param(
        'base_link',
        'Robot body frame (REP-105): child_frame_id of odom and of the odom->base TF.',
    )
    base_to_lidar: tuple[float, ...] = _param(
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        'Pose of the sensor in base_frame as [x, y, z, roll, pitch, yaw] (m, rad), used when '
        'tf2 is not available or has no base_frame<-sensor transform within node.tf_wait. All '
        'zeros: the sensor frame is the base frame.',
    )
    use_tf: bool = _param(
        True,
        'Look the static base_frame<-sensor transform up in tf2 (when tf2_ros is installed).',
        read_only=True,
    )
    tf_wait: float = _param(
        1.0,
        'Seconds to wait for the base_frame<-sensor transform in tf2 before using '
        'node.base_to_lidar (scans that arrive meanwhile are dropped and counted).',
        range=(0.0, 60.0),
    )
    publish_tf: bool = _param(
        True,
        'Broadcast odom_frame->base_frame on /tf (needs tf2_ros; logged once if missing).',
    )
    publish_path: bool = _param(True, 'Publish nav_msgs/Path on `path` after every scan.')
    path_length: int = _param(
        1000,
        'Most recent poses kept in the published path (bounded memory).',
        range=(1, 1_000_000),
    )
    publish_diagnostics: bool = _param(
        True,
        'Publish diagnostic_msgs/DiagnosticArray on `diagnostics` every diagnostics_period.',
    )
    diagnostics_period: float = _param(
        1.0,
        'Seconds between diagnostics messages (rates are measured over this window).',
        range=(0.1, 3600.0),
        read_only=True,
    )
    queue_size: int = _param(
        1,
        'Scans waiting for the worker at most; 1 keeps only the newest (the worker never '
        'falls behind the sensor). Scans pushed out are dropped and counted.',
        range=(1, 1000),
    )
    queue_policy: str = _param(
        'drop_oldest',
        'When the queue is full: drop_oldest (latest wins, for live use) or drop_newest '
        '(the incoming scan is dropped).',
        choices=('drop_oldest', 'drop_newest'),
    )
    qos_reliability: str = _param(
        'best_effort',
        'Reliability of the `points` subscription: best_effort (sensor-data QoS, matches '
        'every publisher) or reliable.',
        choices=('best_effort', 'reliable'),
        read_only=True,
    )
    qos_depth: int = _param(
        5,
        'History depth of the `points` subscription.',
        range=(1, 1000),
        read_only=True,
    )
    map_period: float = _param(
        2.0,
        'Seconds between publications of the map on `~/map` (sensor_msgs/PointCloud2 in '
        'odom_frame, transient-local so a viewer that starts later gets the latest); 0 keeps '
        'no map. A map changes little between scans and is large: a slow rate saves bandwidth.',
        range=(0.0, 3600.0),
    )
    map_voxel_size: float = _param(
        0.2,
        'Voxel edge of the published map (m), one point per voxel: fine enough to show walls, '
        'poles and doorways, coarse enough that a map of map_radius stays a few hundred '
        'thousand points.',
        range=(0.01, 10.0),
    )
    map_radius: float = _param(
        50.0,
        'Map points farther than this from the sensor are dropped (m): the surroundings a '
        'viewer wants while the memory of a long-running node stays bounded. Beyond the range '
        'of most spinning LiDARs indoors and in streets.',
        range=(1.0, 10000.0),
    )

    def __post_init__(self) -> None:
        for name, value, f in iter_fields(self, PREFIX):
            validate_value(name, value, f.metadata)
        if len(self.base_to_lidar) != 6:
            raise ConfigError(
                f'Expected `node.base_to_lidar` to be a list of 6 numbers, got '
                f'{list(self.base_to_lidar)!r}.'
            )
        for key in ('odom_frame', 'base_frame'):
            if not getattr(self, key).strip():
                raise ConfigError(f'Expected `node.{key}` to be a non-empty frame name.')
        if self.odom_frame == self.base_frame:
            raise ConfigError(
                f'`node.odom_frame` and `node.base_frame` are both {self.odom_frame!r}; '
                'they must differ.'
            )

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> NodeSettings:
        """Settings from ``{'node.x': value}`` (missing names take their defaults)."""
        return cls().with_updates(values)

    def with_updates(self, values: Mapping[str, Any]) -> NodeSettings:
        """A copy with ``{'node.x': value}`` applied, each value converted to the field's type
        by the configuration's own rules (:func:`~kentreg_ros.core.config.coerce_value`).

        Raises
        ------
        ConfigError
            An unknown ``node.*`` name (the message lists the valid ones), a value of the wrong
            type, or one :class:`NodeSettings` rejects.
        """
        valid = sorted(p.name for p in NODE_PARAMETERS)
        unknown = sorted(set(values) - set(valid))
        if unknown:
            raise ConfigError(f'Unknown node parameter(s) {unknown}; valid ones are {valid}.')
        hints = get_type_hints(NodeSettings)
        changes: dict[str, Any] = {}
        for name, value in values.items():
            key = name.removeprefix(PREFIX)
            if hints[key] == tuple[float, ...]:
                changes[key] = _numbers(name, value)
            else:
                changes[key] = coerce_value(name, value, hints[key])
        return dataclasses.replace(self, **changes)

    def to_parameters(self) -> dict[str, Any]:
        """``{'node.x': value}`` as ROS parameters and YAML hold them (lists, not tuples)."""
        return {
            name: list(value) if isinstance(value, tuple) else value
            for name, value, _ in iter_fields(self, PREFIX)
        }


def _numbers(name: str, value: Any) -> tuple[float, ...]:
    if isinstance(value, str | bytes) or not isinstance(value, Sequence):
        raise ConfigError(f'Expected `{name}` to be a list of numbers, got {value!r}.')
    return tuple(coerce_value(f'{name}[{i}]', v, float) for i, v in enumerate(value))


@dataclass(frozen=True)
class NodeParameter:
    """One ``node.*`` parameter as the node declares it and the README documents it."""

    name: str
    default: Any
    description: str
    range: tuple[float, float] | None = None
    choices: tuple[str, ...] | None = None
    read_only: bool = False


#: Every ``node.*`` parameter, read off the :class:`NodeSettings` fields.
NODE_PARAMETERS: tuple[NodeParameter, ...] = tuple(
    NodeParameter(
        name=name,
        default=list(value) if isinstance(value, tuple) else value,
        description=f.metadata['description'],
        range=f.metadata.get('range'),
        choices=f.metadata.get('choices'),
        read_only=bool(f.metadata.get('read_only', False)),
    )
    for name, value, f in iter_fields(NodeSettings(), PREFIX)
)


def dump_parameter_file(
    config: KentRegConfig | None = None,
    node: Sequence[NodeParameter] = NODE_PARAMETERS,
    node_name: str = NODE_NAME,
) -> str:
    """The shipped parameter file: every registration and node parameter with its default."""
    cfg = config if config is not None else KentRegConfig()
    params: dict[str, Any] = cfg.to_dict()
    params['node'] = {p.name.removeprefix(PREFIX): p.default for p in node}
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
