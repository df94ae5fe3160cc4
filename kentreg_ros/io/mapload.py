"""Open a saved map for localization: the point cloud, the trajectory it was recorded along
(when it lies beside it), and a cache of the prepared map beside the file.

What ``~/save_map`` writes (``map.ply`` and ``trajectory_tum.txt`` in one folder), what
``kentreg_replay --map FILE --out DIR`` writes (``poses_tum.txt`` in ``DIR``), or any PLY/PCD
map with or without a trajectory: :func:`load_point_map` finds the trajectory beside the map
(or takes ``trajectory``) and orients the map's normals toward its positions; without one
the map's normals are axes (see :mod:`kentreg_ros.core.localization.pointmap`).

The cache (``<map>.kentreg-<voxel>.npz``) holds the downsampled points and normals, the part
that costs seconds on a large map; it is used when it is newer than the map and the trajectory
and was made at the same ``localization.map_voxel_size``, and rewritten otherwise (a folder
that cannot be written only loses the cache, with an INFO line).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from kentreg_ros.core import InvalidPointCloudError, KentRegConfig, PointMap
from kentreg_ros.io.errors import PoseFileError, ScanFileError
from kentreg_ros.io.poses import read_poses
from kentreg_ros.io.scanfiles import read_scan

logger = logging.getLogger(__name__)

#: Trajectory files looked for beside a map, in order (``~/save_map``'s, the replay's).
TRAJECTORY_NAMES = ('trajectory_tum.txt', 'poses_tum.txt')


def trajectory_beside(map_path: str | Path) -> Path | None:
    """The trajectory file beside a map (:data:`TRAJECTORY_NAMES`), or None."""
    folder = Path(map_path).parent
    for name in TRAJECTORY_NAMES:
        if (folder / name).is_file():
            return folder / name
    return None


def cache_path(map_path: str | Path, config: KentRegConfig) -> Path:
    """Where the prepared map of ``map_path`` is cached."""
    p = Path(map_path)
    return p.with_name(f'{p.name}.kentreg-{config.localization.map_voxel_size:g}.npz')


def load_point_map(
    map_path: str | Path,
    *,
    config: KentRegConfig | None = None,
    trajectory: str | Path | None = None,
    use_cache: bool = True,
) -> PointMap:
    """The map at ``map_path`` prepared for localization (module docstring).

    Parameters
    ----------
    map_path : str or Path
        A PLY or PCD point cloud (or any scan file :func:`~kentreg_ros.io.read_scan` reads).
    config : KentRegConfig, optional
    trajectory : str or Path, optional
        The poses the map was recorded from (any pose file); default: one beside the map.
    use_cache : bool
        Read and write the cache beside the map.

    Raises
    ------
    ScanFileError
        The map cannot be read.
    PoseFileError
        A ``trajectory`` given that cannot be read.
    InvalidPointCloudError
        Too few surfaces in the map.
    """
    cfg = config or KentRegConfig()
    path = Path(map_path)
    if not path.is_file():
        raise ScanFileError(f'{path}: no such map file.')
    traj = Path(trajectory) if trajectory is not None else trajectory_beside(path)
    cache = cache_path(path, cfg)
    newest = max(path.stat().st_mtime, traj.stat().st_mtime if traj is not None else 0.0)
    if use_cache and cache.is_file() and cache.stat().st_mtime >= newest:
        try:
            cached = PointMap.load(cache, config=cfg)
        except (InvalidPointCloudError, OSError, KeyError, ValueError) as exc:
            logger.info('Map cache %s not used (%s); preparing the map again.', cache, exc)
        else:
            if cached.oriented == (traj is not None):
                return cached
            logger.info('Map cache %s made %s a trajectory; preparing the map again.', cache,
                        'with' if cached.oriented else 'without')  # fmt: skip
    points = np.asarray(read_scan(path, fields=()).points, dtype=np.float64)
    points = points[np.isfinite(points).all(axis=1)]
    viewpoints = None
    if traj is not None:
        try:
            viewpoints = read_poses(traj).T_world_sensor[:, :3, 3]
        except (PoseFileError, ValueError) as exc:
            if trajectory is not None:
                raise
            logger.warning('The trajectory beside the map (%s) is not used: %s', traj, exc)
    if viewpoints is None:
        logger.info(
            'No trajectory beside %s: its normals are taken as axes (slower, weaker search).',
            path,
        )
    pmap = PointMap.from_points(points, config=cfg, viewpoints=viewpoints)
    if use_cache:
        try:
            pmap.save(cache)
        except OSError as exc:
            logger.info('Could not write the map cache %s: %s', cache, exc)
    return pmap
