"""The odometry pipelines registry: one interface, a frame in and a pose out.

A :class:`Pipeline` takes a :class:`kentreg_ros.io.Scan` per :meth:`~Pipeline.step` and returns
``T_world_lidar`` (4, 4), recording the points it used, its settings and health counters.
:data:`PIPELINES` has them as a user runs them: ``kentreg`` (+ ``_local_map``,
``_local_map_no_deskew``, ``_numpy``: :class:`kentreg_ros.core.Odometry`), ``gicp`` (small_gicp
scan-to-scan at its defaults), ``icp_pt2pl`` (Open3D scan-to-scan at its defaults), ``kiss_icp``
(KISS-ICP's own pipeline and configuration). :func:`scan_to_scan` makes any pair method a
pipeline, each scan against the previous one from its own previous motion.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core import HEALTHS, KentRegConfig, Odometry
from kentreg_ros.io.pointtimes import point_time_field
from kentreg_ros.io.sources import Scan

from .methods import RawMethod

FloatArray = NDArray[np.float64]
#: Per-point time fields KISS-ICP's own PointCloud2 reader looks for.
TIME_FIELDS = ('t', 'timestamp', 'time', 'timestamps')
#: The odometry benchmarks' pipelines, in table order.
ODOMETRY = ('kentreg', 'kentreg_local_map', 'kiss_icp', 'gicp')


class Pipeline(Protocol):
    """A frame in, a pose out."""

    name: str
    points_used: list[int]
    settings: dict[str, Any]
    health: dict[str, Any]
    #: The health of every step, in order (kentreg's; empty for pipelines without one).
    step_health: list[str]

    def step(self, scan: Scan) -> FloatArray:
        """Process one scan; its ``T_world_lidar`` (4, 4)."""
        ...


class KentregPipeline:
    """kentreg's :class:`~kentreg_ros.core.Odometry` as the replay steps it."""

    def __init__(self, config: KentRegConfig, name: str = 'kentreg', **kwargs: Any) -> None:
        self.name = name
        self.odometry = Odometry(config, **kwargs)
        self.points_used: list[int] = []
        self.health: dict[str, Any] = dict.fromkeys(HEALTHS, 0)
        self.step_health: list[str] = []
        initial = 'constant velocity' if config.odometry.constant_velocity else 'previous pose'
        self.settings = {'mode': config.mode, 'config': config.to_flat_dict(),
                         'model': config.odometry.model.replace('_', ' '),
                         'initial_guess': initial}  # fmt: skip

    def step(self, scan: Scan) -> FloatArray:
        times = point_time_field(getattr(scan, 'extras', None))
        step = self.odometry.step(
            scan.points, scan.stamp_ns, frame_id=scan.frame_id, point_times=times
        )
        self.points_used.append(step.n_prepared)
        self.health[step.health] = self.health.get(step.health, 0) + 1
        self.step_health.append(str(step.health))
        return np.asarray(step.T_world_lidar, dtype=np.float64)


@dataclass
class ScanToScan:
    """Each scan against the previous one (prepared once) from the last motion (constant
    velocity, identity first), poses chained. With ``catch``, a step that raises keeps the
    prediction (the last motion repeated), as an odometry would, counted in ``n_raised``."""

    name: str
    prepare: Callable[[FloatArray], Any]
    align: Callable[[Any, Any, FloatArray], FloatArray]
    size: Callable[[Any], int] = lambda prep: 0
    catch: bool = False
    settings: dict[str, Any] = field(default_factory=dict)
    health: dict[str, Any] = field(default_factory=dict)
    points_used: list[int] = field(default_factory=list)
    step_health: list[str] = field(default_factory=list)
    previous: Any = None
    pose: FloatArray = field(default_factory=lambda: np.eye(4))
    motion: FloatArray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self) -> None:
        if self.catch:
            self.health['n_raised'] = 0

    def step(self, scan: Scan) -> FloatArray:
        prep = None
        try:
            prep = self.prepare(np.asarray(scan.points, dtype=np.float64))
            if self.previous is not None:
                self.motion = self.align(prep, self.previous, self.motion)
                self.pose = self.pose @ self.motion
        except Exception:
            if not self.catch or self.previous is None:
                raise
            self.health['n_raised'] += 1
            self.pose = self.pose @ self.motion
        if prep is not None:
            self.previous = prep
            self.points_used.append(self.size(prep))
        return np.array(self.pose)


def scan_to_scan(method: RawMethod) -> ScanToScan:
    """A pair method as an odometry pipeline; a registration that raises is counted."""
    return ScanToScan(
        method.name, method.prepare, lambda s, t, init: method.register(s, t, init)[0], catch=True
    )


def gicp(voxel: float, threads: int = 1) -> ScanToScan:
    """small_gicp GICP scan-to-scan at small_gicp's defaults (see the module docstring)."""
    import small_gicp

    settings = {'registration_type': 'GICP', 'downsampling_resolution': voxel,
                'num_neighbors': 10, 'max_correspondence_distance': 1.0, 'max_iterations': 20,
                'num_threads': threads, 'model': 'previous scan',
                'initial_guess': 'constant velocity'}  # fmt: skip
    health = {'not_converged': 0}

    def prepare(points: FloatArray) -> Any:
        return small_gicp.preprocess_points(
            points, downsampling_resolution=voxel, num_threads=threads
        )

    def align(source: Any, target: Any, init: FloatArray) -> FloatArray:
        result = small_gicp.align(target[0], source[0], target[1], init_T_target_source=init,
                                  registration_type='GICP', num_threads=threads)  # fmt: skip
        health['not_converged'] += not result.converged
        return np.array(result.T_target_source, dtype=np.float64)

    return ScanToScan(
        'gicp', prepare, align, lambda p: p[0].size(), settings=settings, health=health
    )


def icp_pt2pl(voxel: float = 0.25, gate: float = 1.0, neighbors: int = 15) -> ScanToScan:
    """Open3D point-to-plane ICP scan-to-scan at Open3D's defaults (one thread)."""
    import open3d as o3d

    o3d.utility.set_max_threads(1)
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    reg = o3d.pipelines.registration

    def prepare(points: FloatArray) -> Any:
        pcd = o3d.geometry.PointCloud()
        pcd.points = o3d.utility.Vector3dVector(points)
        pcd = pcd.voxel_down_sample(voxel)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(neighbors))
        return pcd

    def align(source: Any, target: Any, init: FloatArray) -> FloatArray:
        estimation = reg.TransformationEstimationPointToPlane()
        return np.array(
            reg.registration_icp(source, target, gate, init, estimation).transformation
        )

    return ScanToScan('icp_pt2pl', prepare, align, size=lambda p: len(p.points))


def point_times(scan: Scan) -> FloatArray:
    """Per-point times of a scan for KISS-ICP, or an empty array when it has none."""
    for name in TIME_FIELDS:
        if name in scan.extras:
            return np.asarray(scan.extras[name], dtype=np.float64).ravel()
    return np.zeros(0)


class KissPipeline:
    """KISS-ICP's Python pipeline with the configuration its own OdometryPipeline loads."""

    def __init__(self, threads: int = 1, max_range: float | None = None) -> None:
        from kiss_icp.config import load_config
        from kiss_icp.kiss_icp import KissICP

        if max_range is None:
            config = load_config(None)
        else:
            with tempfile.TemporaryDirectory() as tmp:
                yaml_file = Path(tmp) / 'kiss_icp.yaml'
                yaml_file.write_text(f'data:\n  max_range: {max_range}\n')
                config = load_config(yaml_file)
        config.registration.max_num_threads = threads
        self.kiss = KissICP(config=config)
        self.name = 'kiss_icp'
        self.points_used: list[int] = []
        self.health: dict[str, Any] = {}
        self.step_health: list[str] = []
        self.has_times = False
        where = '' if max_range is None else f' with data.max_range = {max_range}'
        cfg = self.kiss.config
        self.settings = {
            'config': f'kiss_icp.config.load_config: default KISSConfig{where}, '
            'voxel_size = max_range / 100',
            'max_range': cfg.data.max_range, 'min_range': cfg.data.min_range,
            'deskew': cfg.data.deskew, 'voxel_size': cfg.mapping.voxel_size,
            'max_points_per_voxel': cfg.mapping.max_points_per_voxel,
            'initial_threshold': cfg.adaptive_threshold.initial_threshold,
            'max_num_iterations': cfg.registration.max_num_iterations,
            'max_num_threads': cfg.registration.max_num_threads,
            'model': 'local voxel-hash map', 'initial_guess': 'constant velocity',
        }  # fmt: skip

    def step(self, scan: Scan) -> FloatArray:
        times = point_times(scan)
        if not self.points_used:
            self.has_times = bool(times.size)
            self.settings['per_point_times'] = self.has_times
            self.settings['deskew_effective'] = bool(self.settings['deskew'] and self.has_times)
        _, source = self.kiss.register_frame(np.asarray(scan.points, dtype=np.float64), times)
        self.points_used.append(len(source))
        return np.array(self.kiss.last_pose, dtype=np.float64)


def _kentreg(name: str, updates: dict[str, Any]) -> Callable[..., Pipeline]:
    def make(*, config: KentRegConfig | None = None, **kwargs: Any) -> Pipeline:
        cfg = (config or KentRegConfig()).with_updates(updates)
        return KentregPipeline(cfg, name, **kwargs)

    return make


def _kentreg_numpy(**kwargs: Any) -> Pipeline:
    from kentreg_ros.core import kernels

    os.environ[kernels.DISABLE_ENV] = '1'  # this (worker) process only
    return _kentreg('kentreg_numpy', {})(**kwargs)


#: Every odometry pipeline by name; options: ``config`` (kentreg), ``voxel``, ``threads``,
#: ``max_range`` (KISS-ICP), ``max_history`` (kentreg).
PIPELINES: dict[str, Callable[..., Pipeline]] = {
    'kentreg': _kentreg('kentreg', {}),
    'kentreg_local_map': _kentreg('kentreg_local_map', {'odometry.model': 'local_map'}),
    'kentreg_local_map_no_deskew': _kentreg(
        'kentreg_local_map_no_deskew', {'odometry.model': 'local_map', 'odometry.deskew': 'off'}
    ),
    'kentreg_numpy': _kentreg_numpy,
    'gicp': lambda voxel, threads=1, **_: gicp(voxel, threads),
    'icp_pt2pl': lambda voxel=0.25, **_: icp_pt2pl(voxel),
    'kiss_icp': lambda threads=1, max_range=None, **_: KissPipeline(threads, max_range),
}


def make_pipeline(name: str, **options: Any) -> Pipeline:
    """The pipeline ``name`` of :data:`PIPELINES` with the options it takes (others ignored);
    ``ValueError`` for an unknown name."""
    if name not in PIPELINES:
        raise ValueError(f'Unknown pipeline {name!r}; valid names are {sorted(PIPELINES)}.')
    if name.startswith('kentreg'):
        options = {k: v for k, v in options.items() if k in ('config', 'max_history')}
    return PIPELINES[name](**options)
