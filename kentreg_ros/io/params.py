"""The parameters an operator sets: what they are, their defaults and validation.

The product surface is small and flat (ROS names such as ``odom_frame``, ``max_range``): the
core's operator settings (:data:`CORE_PARAMETERS`, each the flat name of a
:class:`~kentreg_ros.core.config.KentRegConfig` field, which gives it its default, range and
description) and the node's own (:class:`NodeSettings`). :data:`PARAMETERS` lists them all, in
the order of the shipped file ``config/kentreg.yaml`` (``/**: ros__parameters:``, so any node
name and namespace picks it up) and of the table in docs/configuration.md.

The research configuration (the paper's recipe, every ablation: ``mode``, ``em.*``,
``refine.*`` ...) is :class:`~kentreg_ros.core.config.KentRegConfig` itself, reached from
Python, the benchmarks and the command lines' ``--set em.tolerance=1e-3`` (dotted names);
the node declares none of it. A parameter file may carry dotted research keys for the command
lines (the replay writes the ones that differ from the defaults into its ``config.yaml``); the
node warns about them once, as about any name that is not its own. The parameter file they are
read from and written to is :mod:`kentreg_ros.io.paramfile`.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from enum import StrEnum
from typing import Any

from kentreg_ros.core import (
    ConfigError,
    KentRegConfig,
    Section,
    coerce_value,
    flatten_keys,
    iter_fields,
    nest_keys,
    plain_value,
)
from kentreg_ros.io.errors import ParameterError

#: The node's name: the top key of the parameter file.
NODE_NAME = 'kentreg_node'


# --------------------------------------------------------------------------------------------
# The product surface


class PipelineMode(StrEnum):
    """How the node's odometry uses the cores."""

    PROCESS = 'process'
    SEQUENTIAL = 'sequential'


class QosReliability(StrEnum):
    """Reliability of the input subscription."""

    BEST_EFFORT = 'best_effort'
    RELIABLE = 'reliable'


class RegisteredCloud(StrEnum):
    """Where the registered cloud of each scan is published."""

    ODOM = 'odom'
    SENSOR = 'sensor'
    OFF = 'off'


#: The core's operator settings: flat parameter name -> the research field behind it (its
#: default, range and description are that field's).
CORE_PARAMETERS: dict[str, str] = {
    'voxel_size': 'preprocess.voxel_size',
    'min_range': 'preprocess.min_range',
    'max_range': 'preprocess.max_range',
    'model': 'odometry.model',
    'local_map_radius': 'odometry.map_radius',
    'deskew': 'odometry.deskew',
    'point_time_unit': 'odometry.point_time_unit',
    'point_time_reference': 'odometry.point_time_reference',
    'max_linear_speed': 'odometry.max_linear_speed',
    'max_angular_speed_deg': 'odometry.max_angular_speed_deg',
}


def _param(
    default: Any,
    description: str,
    *,
    range: tuple[float, float] | None = None,
    read_only: bool = False,
) -> Any:
    """A :class:`NodeSettings` field: the metadata of a configuration field (``description``,
    ``range``; ``choices`` from a :class:`~enum.StrEnum` default), plus ``read_only`` (set at
    start-up only)."""
    meta: dict[str, Any] = {'description': description}
    if range is not None:
        meta['range'] = range
    if isinstance(default, StrEnum):
        meta['choices'] = tuple(m.value for m in type(default))
    if read_only:
        meta['read_only'] = True
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class NodeSettings(Section):
    """The node's own parameters (frames, TF, input QoS, queue, outputs), validated like every
    configuration section (:class:`~kentreg_ros.core.config.Section`).

    Raises
    ------
    ConfigError
        A value out of range, not among its choices or of the wrong type, ``base_to_lidar``
        not 6 numbers, an empty ``odom_frame``, or the same name for both frames.
    """

    odom_frame: str = _param(
        'odom',
        'Fixed frame of the odometry (REP-105): header.frame_id of the odometry, pose, path, '
        'registered cloud and map.',
    )
    base_frame: str = _param(
        '',
        "Moving frame: child_frame_id of the odometry and of the TF. Empty: the cloud's own "
        'frame, so a bag without /tf gives odom -> <cloud frame>. Set (base_link) and unlike '
        'the cloud frame: base <- sensor comes from tf2, looked up on every scan, so one that '
        'appears or changes later is used, else from base_to_lidar.',
    )
    base_to_lidar: tuple[float, ...] = _param(
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        'Pose of the sensor in base_frame as [x, y, z, roll, pitch, yaw] (m, rad), used while '
        'tf2 has no base_frame <- sensor transform after tf_wait (or tf2 is missing); then '
        'also broadcast as that static transform, so the tree is whole. Zeros: the sensor '
        'frame is the base frame.',
    )
    publish_tf: bool = _param(
        True,
        'Broadcast odom_frame -> the moving frame on /tf (needs tf2_ros; logged once if missing).',
    )
    invert_tf: bool = _param(
        False,
        'Broadcast the inverse, moving frame -> odom_frame, for a robot whose odom -> base '
        "transform is another node's (wheel odometry, an EKF): a frame has one parent in tf, "
        "so kentreg's odometry frame hangs below the base (name it apart: odom_frame: "
        'kentreg_odom).',
    )
    tf_wait: float = _param(
        1.0,
        'Seconds to wait for the base_frame <- sensor transform in tf2 before using '
        'base_to_lidar (scans that arrive meanwhile are dropped and counted).',
        range=(0.0, 60.0),
    )
    publish_path: bool = _param(
        True, 'Publish nav_msgs/Path (the last path_length poses) once a second when it grew.'
    )
    path_length: int = _param(
        1000,
        'Most recent poses kept in the published path (bounded memory).',
        range=(1, 1_000_000),
    )
    registered_cloud: RegisteredCloud = _param(
        RegisteredCloud.ODOM,
        "Publish each scan's registered points (deskewed, downsampled, outliers removed: "
        "what was aligned) on kentreg/cloud_registered at the scan's stamp, in odom_frame "
        "(odom), in the cloud's own frame (sensor), or not (off).",
    )
    diagnostics_period: float = _param(
        1.0,
        'Seconds between diagnostics messages (rates are measured over this window).',
        range=(0.1, 3600.0),
        read_only=True,
    )
    queue_size: int = _param(
        1,
        'Scans waiting for the worker at most; when full the oldest is dropped (and counted), '
        'so the odometry never lags the sensor: 1 keeps only the newest.',
        range=(1, 1000),
    )
    pipeline: PipelineMode = _param(
        PipelineMode.PROCESS,
        'How the odometry uses the cores: process prepares each scan (deskew, voxels, '
        'normals, clusters) in a worker process while the node registers the scan before: '
        'the same poses as sequential, on two cores (it pays when scans come faster than one '
        "core keeps up with). sequential runs every stage in the node's worker thread, on one "
        'core.',
        read_only=True,
    )
    qos_reliability: QosReliability = _param(
        QosReliability.BEST_EFFORT,
        'Reliability of the input subscription: best_effort (sensor-data QoS, matches every '
        'publisher) or reliable. qos_overrides.<topic>.subscription.reliability overrides it.',
        read_only=True,
    )
    qos_depth: int = _param(
        5,
        'History depth of the input subscription (qos_overrides.<topic>.subscription.depth '
        'overrides it).',
        range=(1, 1000),
        read_only=True,
    )
    map_period: float = _param(
        2.0,
        'Seconds between publications of the map around the sensor on kentreg/map '
        '(transient-local, so a viewer that starts later gets the latest); 0: not published '
        '(~/save_map still has the map). A map changes little between scans and is large.',
        range=(0.0, 3600.0),
    )
    map_voxel_size: float = _param(
        0.1,
        'Voxel edge of the map (m), one point per voxel, published and saved alike (the '
        "replay's --map default): fine enough for walls, poles and doorways, coarse enough "
        'that a street-sized map stays a few million points.',
        range=(0.01, 10.0),
        read_only=True,
    )
    map_radius: float = _param(
        50.0,
        'The published map shows the points within this distance of the sensor (m): what a '
        'viewer wants around the robot, at a bounded message size; ~/save_map writes all of '
        'it. Beyond the range of most spinning LiDARs indoors and in streets.',
        range=(1.0, 10000.0),
    )
    map_max_points: int = _param(
        2_000_000,
        'Points the map of the run keeps at most: beyond them its voxel edge doubles, so it '
        'stays the map of the whole run, coarser (2 million: about 60 MB, a 24 MB PLY).',
        range=(1000, 100_000_000),
        read_only=True,
    )
    map_directory: str = _param(
        '',
        'Folder ~/save_map writes into (a new sub-folder per call: map.ply, '
        'trajectory_tum.txt); ~ is expanded. Empty: $ROS_HOME/kentreg_maps (~/.ros/'
        'kentreg_maps).',
    )
    map_file: str = _param(
        '',
        'A saved map to localize in (PLY or PCD: what ~/save_map or kentreg_replay --map '
        'writes): the node then publishes map_frame -> odom_frame, takes initialpose in '
        'map_frame (its covariance bounds the search) and offers ~/relocalize '
        '(docs/localization.md). The trajectory beside it (trajectory_tum.txt, poses_tum.txt) '
        'orients its normals; it is prepared in the background at start-up and cached beside '
        'it. A path that is no map file stops the node at start-up. Empty: odometry only.',
        read_only=True,
    )
    map_frame: str = _param(
        'map',
        'Frame of the saved map (REP-105): parent of odom_frame on /tf, header.frame_id of '
        '~/pose and of the initialpose the node takes when map_file is set.',
        read_only=True,
    )

    def check(self) -> None:
        values = self.base_to_lidar
        if isinstance(values, str | bytes) or not isinstance(values, Sequence):
            raise ConfigError(f'Expected `base_to_lidar` to be a list of numbers, got {values!r}.')
        numbers = tuple(
            coerce_value(f'base_to_lidar[{i}]', v, float) for i, v in enumerate(values)
        )
        if len(numbers) != 6:
            raise ConfigError(
                f'Expected `base_to_lidar` to be a list of 6 numbers, got {list(values)!r}.'
            )
        object.__setattr__(self, 'base_to_lidar', numbers)
        if not self.odom_frame.strip():
            raise ConfigError('Expected `odom_frame` to be a non-empty frame name.')
        if self.odom_frame == self.base_frame:
            raise ConfigError(
                f'`odom_frame` and `base_frame` are both {self.odom_frame!r}; they must differ.'
            )
        if not self.map_frame.strip():
            raise ConfigError('Expected `map_frame` to be a non-empty frame name.')
        if self.map_frame in (self.odom_frame, self.base_frame):
            raise ConfigError(
                f'`map_frame` is {self.map_frame!r}, the name of another of its frames; the '
                'map, odometry and moving frames must differ.'
            )
        if self.map_file.strip() and self.invert_tf:
            raise ConfigError(
                '`invert_tf` with a `map_file`: the map -> odom transform would give odom_frame '
                'a second parent in tf (it hangs below the moving frame); localize without '
                'invert_tf, or leave map_file empty.'
            )

    def with_updates(self, values: Mapping[str, Any]) -> NodeSettings:
        """A copy with ``{name: value}`` applied and validated.

        Raises
        ------
        ConfigError
            An unknown name (the message lists the valid ones) or a bad value.
        """
        valid = sorted(f.name for f in fields(NodeSettings))
        unknown = sorted(set(values) - set(valid))
        if unknown:
            raise ConfigError(f'Unknown node parameter(s) {unknown}; valid ones are {valid}.')
        return dataclasses.replace(self, **values)

    def to_parameters(self) -> dict[str, Any]:
        """``{name: value}`` as ROS parameters and YAML hold them (lists, plain strings)."""
        return {
            name: list(value) if isinstance(value, tuple) else plain_value(value)
            for name, value, _ in iter_fields(self)
        }


@dataclass(frozen=True)
class Parameter:
    """One parameter as the node declares it and docs/configuration.md documents it.

    ``field`` is the research field behind a core parameter ('' for the node's own)."""

    name: str
    default: Any
    description: str
    range: tuple[float, float] | None = None
    choices: tuple[str, ...] | None = None
    read_only: bool = False
    field: str = ''

    @property
    def metadata(self) -> dict[str, Any]:
        """The metadata :func:`~kentreg_ros.core.config.validate_value` reads."""
        meta: dict[str, Any] = {'description': self.description, 'read_only': self.read_only}
        if self.range is not None:
            meta['range'] = self.range
        if self.choices is not None:
            meta['choices'] = self.choices
        return meta


def _parameters() -> tuple[Parameter, ...]:
    research = {name: (value, f) for name, value, f in iter_fields(KentRegConfig())}
    out = []
    for name, path in CORE_PARAMETERS.items():
        value, f = research[path]
        meta = f.metadata
        out.append(
            Parameter(
                name,
                plain_value(value),
                meta['description'],
                meta.get('range'),
                meta.get('choices'),
                field=path,
            )
        )
    for name, value, f in iter_fields(NodeSettings()):
        meta = f.metadata
        default = list(value) if isinstance(value, tuple) else plain_value(value)
        out.append(
            Parameter(
                name,
                default,
                meta['description'],
                meta.get('range'),
                meta.get('choices'),
                bool(meta.get('read_only', False)),
            )
        )
    return tuple(out)


#: Every parameter an operator sets: the core's, then the node's own.
PARAMETERS: tuple[Parameter, ...] = _parameters()
_NODE_NAMES = frozenset(f.name for f in fields(NodeSettings))
_RESEARCH_NAMES = frozenset(name for name, _, _ in iter_fields(KentRegConfig()))


@dataclass(frozen=True)
class Settings:
    """A run's configuration: the core's (research tree) and the node's."""

    config: KentRegConfig
    node: NodeSettings
    #: Names given that are neither a parameter nor a research field (the node warns).
    unknown: tuple[str, ...] = ()


def apply_parameters(
    values: Mapping[str, Any],
    *,
    config: KentRegConfig | None = None,
    node: NodeSettings | None = None,
    research: bool = True,
    strict: bool = True,
) -> Settings:
    """``values`` (flat parameter names; with ``research``, dotted research names too) applied
    on top of ``config`` and ``node`` (default: the defaults), validated.

    Parameters
    ----------
    research : bool
        Whether dotted research names (``em.tolerance``) are taken (the command lines) or are
        unknown (the node).
    strict : bool
        Unknown names are an error listing the valid ones (True), or returned in
        :attr:`Settings.unknown` (False, the node: a shared bringup file holds other nodes'
        keys).

    Raises
    ------
    ParameterError
        A bad value, a broken cross-field rule, or (``strict``) an unknown name; its ``names``
        are the parameters the reason names (the one given, when it names none).
    """
    try:
        flat = flatten_keys(nest_keys(values))
    except ConfigError as exc:
        raise ParameterError(str(exc)) from exc
    core: dict[str, Any] = {}
    own: dict[str, Any] = {}
    unknown: list[str] = []
    for name, value in flat.items():
        if name in CORE_PARAMETERS:
            core[CORE_PARAMETERS[name]] = value
        elif name in _NODE_NAMES:
            own[name] = value
        elif research and name in _RESEARCH_NAMES:
            core[name] = value
        else:
            unknown.append(name)
    if unknown and strict:
        valid = [p.name for p in PARAMETERS]
        extra = ' or a research field (dotted, e.g. em.tolerance)' if research else ''
        raise ParameterError(
            f'Unknown parameter(s) {sorted(unknown)}; expected one of {valid}{extra}.',
            names=tuple(sorted(unknown)),
        )
    cfg = config if config is not None else KentRegConfig()
    settings = node if node is not None else NodeSettings()
    try:
        return Settings(
            cfg.with_updates(core) if core else cfg,
            settings.with_updates(own) if own else settings,
            tuple(sorted(unknown)),
        )
    except ConfigError as exc:
        given = [name for name in flat if name not in unknown]
        raise ParameterError(str(exc), names=named_in(str(exc), given)) from exc


def named_in(reason: str, names: Iterable[str]) -> tuple[str, ...]:
    """The parameters among ``names`` that ``reason`` names, by their own name or by the
    research field behind them (``max_range`` by ``preprocess.max_range``); the one name
    given when there is one and the reason names none."""
    given = list(names)
    tokens = set(re.findall(r'[A-Za-z_][\w.]*[\w]', reason))
    named = tuple(n for n in given if n in tokens or CORE_PARAMETERS.get(n) in tokens)
    return named if named or len(given) != 1 else tuple(given)


def product_values(config: KentRegConfig, node: NodeSettings) -> dict[str, Any]:
    """``{name: value}`` of every parameter (:data:`PARAMETERS` order) for ``config`` and
    ``node``."""
    research = config.to_flat_dict()
    own = node.to_parameters()
    return {p.name: research[p.field] if p.field else own[p.name] for p in PARAMETERS}
