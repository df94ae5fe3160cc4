"""The map and the trajectory of a run, built once for the node and the replay alike.

:class:`RunMap` accumulates the registered points of every scan whose pose was registered (and
of the first scan) at that pose, one point per voxel, bounded by a number of points.
``kentreg_node`` publishes a cropped view of it around the sensor (``kentreg/map``) and writes
the whole of it with ``~/save_map``; ``kentreg_replay`` writes the whole of it to its MCAP and
to ``--map``. Both feed it the same points, :attr:`~kentreg_ros.core.OdometryStep.points`: the
scan's *prepared* points (voxel centroids at the scan's resolution, isolated returns and normal
outliers removed, deskewed when deskewing ran), which are what the registration aligned:

- deskewed, so a map built while moving is not smeared by the sweep's motion (the raw points
  of a 10 Hz scan at 1 m/s lie up to 10 cm from where the pose puts them);
- without the stray returns (dust, rain, multipath) the preparation drops, which a map would
  keep forever;
- a few thousand per scan instead of the sensor's 30k-300k, so adding a scan costs a node at
  sensor rate little, and the map shows exactly what the odometry saw.

Scans that fell back to the prediction or were rejected stay out: their pose is only a guess.

:class:`TrajectoryLog` keeps every pose of a run (stamp and 4x4), for ``~/save_map``'s TUM
file. :func:`save_run` writes both.

Memory is bounded: when the map reaches ``max_points`` its voxel edge doubles and the map is
re-voxelised (the first point of each coarser voxel stays), with a warning; so a map of a long
run stays the map of the *whole* run, coarser, instead of losing its beginning.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core import InvalidInputError, as_points

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
#: Bits per axis of a voxel key (three axes in one int64, with a sign offset).
KEY_BITS = 21
_OFFSET = 1 << (KEY_BITS - 1)
#: Points a map holds before its voxel edge doubles, unless told otherwise: 2 million points
#: are about 60 MB (float32 points, int64 keys) and a 24 MB PLY; at 0.1 m voxels that is a few
#: square kilometres of streets or a large building.
DEFAULT_MAX_POINTS = 2_000_000


def voxel_keys(points: FloatArray, voxel_size: float) -> tuple[NDArray[np.int64], NDArray]:
    """The voxel key of each point and the mask of the points a key can hold.

    Returns
    -------
    keys : ndarray of int64, shape (K,)
        Keys of the points inside ``mask`` (``floor(p / voxel_size)`` per axis, packed).
    mask : ndarray of bool, shape (N,)
        Points within ``2**20`` voxels of the origin along every axis (±105 km at 0.1 m).
    """
    grid = np.floor(points / voxel_size)
    mask = np.all((grid >= -_OFFSET) & (grid < _OFFSET), axis=1)
    g = grid[mask].astype(np.int64) + _OFFSET
    return (g[:, 0] << (2 * KEY_BITS)) | (g[:, 1] << KEY_BITS) | g[:, 2], mask


class RunMap:
    """Points of the registered scans of a run, one per voxel, in the odometry frame.

    Adding a scan costs its own points (a sort of their keys and a binary search in a few
    sorted runs of the map's keys, merged as they grow: log-structured, so the cost per point
    is logarithmic in the map, not linear), never a copy of the whole map. Safe to read
    (:attr:`points`, :meth:`around`) from one thread while another adds.

    Parameters
    ----------
    voxel_size : float
        Voxel edge (m, > 0): the first point to reach a voxel keeps it.
    max_points : int
        Points kept at most (> 0): beyond them the voxel edge doubles (see the module notes).

    Examples
    --------
    >>> m = RunMap(0.5)
    >>> m.add(np.array([[0.1, 0, 0], [0.2, 0, 0], [2.0, 0, 0]]))
    2
    >>> len(m), m.around(np.zeros(3), 1.0).shape
    (2, (1, 3))
    """

    def __init__(self, voxel_size: float, *, max_points: int = DEFAULT_MAX_POINTS) -> None:
        if not (np.isfinite(voxel_size) and voxel_size > 0.0):
            raise InvalidInputError(f'Expected `voxel_size` > 0, got {voxel_size!r}.')
        if isinstance(max_points, bool) or int(max_points) < 1:
            raise InvalidInputError(f'Expected `max_points` >= 1, got {max_points!r}.')
        self.initial_voxel_size = float(voxel_size)
        self.max_points = int(max_points)
        self._lock = threading.Lock()
        self.clear()

    def clear(self) -> None:
        """Forget every point (and any coarsening)."""
        with self._lock:
            self.voxel_size = self.initial_voxel_size
            #: Times the voxel edge doubled to stay within ``max_points``.
            self.n_coarsened = 0
            #: Points dropped because they lay beyond the reach of a key.
            self.n_out_of_reach = 0
            self._buffer = np.zeros((1024, 3), dtype=np.float32)
            self._n = 0
            self._runs: list[NDArray[np.int64]] = []

    def __len__(self) -> int:
        return self._n

    @property
    def points(self) -> NDArray[np.float32]:
        """Every point of the map, shape (M, 3) float32 (a copy)."""
        with self._lock:
            return self._buffer[: self._n].copy()

    @property
    def nbytes(self) -> int:
        """Bytes held by the map (its point buffer and its keys)."""
        return int(self._buffer.nbytes + sum(r.nbytes for r in self._runs))

    def around(self, center: ArrayLike, radius: float) -> NDArray[np.float32]:
        """The points within ``radius`` of ``center``, shape (K, 3) float32 (a copy): the view
        a display wants around the sensor, while the map keeps the whole run."""
        c = np.asarray(center, dtype=np.float64).reshape(3)
        with self._lock:
            pts = self._buffer[: self._n]
            inside = np.sum((pts - c.astype(np.float32)) ** 2, axis=1) <= radius * radius
            return pts.take(np.flatnonzero(inside), axis=0)  # ~4x faster than pts[inside]

    def add(self, points: ArrayLike, T_map_sensor: ArrayLike | None = None) -> int:
        """Add ``points`` (sensor frame, moved by ``T_map_sensor``; default: already in the
        map's frame); return how many found a voxel of their own (the others are dropped).

        Parameters
        ----------
        points : array_like, shape (N, 3)
            Finite points.
        T_map_sensor : array_like, shape (4, 4), optional
            Pose of the sensor in the map's frame.
        """
        pts = as_points(points)
        if T_map_sensor is not None:
            T = np.asarray(T_map_sensor, dtype=np.float64)
            pts = pts @ T[:3, :3].T + T[:3, 3]
        if not len(pts):
            return 0
        with self._lock:
            added = self._insert(pts)
            if self._n > self.max_points:
                self._coarsen()
        return added

    def _insert(self, pts: FloatArray) -> int:
        keys, inside = voxel_keys(pts, self.voxel_size)
        if not inside.all():
            self.n_out_of_reach += int(np.count_nonzero(~inside))
            pts = pts[inside]
        # The first point of each voxel of the scan, then those whose voxel the map lacks.
        keys, first = np.unique(keys, return_index=True)
        fresh = np.ones(len(keys), dtype=bool)
        for run in self._runs:
            pos = np.minimum(np.searchsorted(run, keys), len(run) - 1)
            fresh &= run[pos] != keys
        keys, first = keys[fresh], first[fresh]
        if not len(keys):
            return 0
        self._append(pts[np.sort(first)])
        self._runs.append(keys)
        # Merge the newest runs while the last is at least half the one before it: a few runs
        # of geometrically growing sizes, each point merged O(log M) times.
        while len(self._runs) > 1 and 2 * len(self._runs[-1]) >= len(self._runs[-2]):
            last = self._runs.pop()
            self._runs[-1] = np.sort(np.concatenate([self._runs[-1], last]), kind='stable')
        return len(keys)

    def _append(self, pts: FloatArray) -> None:
        need = self._n + len(pts)
        if need > len(self._buffer):
            grown = np.zeros((max(need, 2 * len(self._buffer)), 3), dtype=np.float32)
            grown[: self._n] = self._buffer[: self._n]
            self._buffer = grown
        self._buffer[self._n : need] = pts
        self._n = need

    def _coarsen(self) -> None:
        """Double the voxel edge until the map holds at most ``max_points`` (the first point
        of each coarser voxel stays)."""
        while self._n > self.max_points:
            self.voxel_size *= 2.0
            self.n_coarsened += 1
            pts = self._buffer[: self._n].astype(np.float64)
            keys, first = np.unique(voxel_keys(pts, self.voxel_size)[0], return_index=True)
            order = np.sort(first)
            self._buffer = np.ascontiguousarray(self._buffer[order])
            self._n = len(order)
            self._runs = [keys]
            logger.warning(
                'The map reached %d points (map_max_points): its voxel edge doubles to %g m, so '
                'it keeps the whole run, coarser (%d points now).',
                self.max_points,
                self.voxel_size,
                self._n,
            )


class TrajectoryLog:
    """Every pose of a run, in order: ``(stamp_ns, T)`` appended by one thread, read by another.

    Grows by doubling (8 floats per pose), so a 10 Hz run of ten hours holds 23 MB.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.clear()

    def clear(self) -> None:
        """Forget every pose."""
        with self._lock:
            self._stamps = np.zeros(256, dtype=np.int64)
            self._poses = np.zeros((256, 4, 4))
            self._n = 0

    def __len__(self) -> int:
        return self._n

    def append(self, stamp_ns: int, T: ArrayLike) -> None:
        """Add the pose ``T`` (4, 4) at ``stamp_ns``."""
        with self._lock:
            if self._n == len(self._stamps):
                self._stamps = np.concatenate([self._stamps, np.zeros_like(self._stamps)])
                self._poses = np.concatenate([self._poses, np.zeros_like(self._poses)])
            self._stamps[self._n] = stamp_ns
            self._poses[self._n] = T
            self._n += 1

    def snapshot(self, last: int | None = None) -> tuple[NDArray[np.int64], FloatArray]:
        """Copies of the stamps (N,) and poses (N, 4, 4), all or the ``last`` ones."""
        with self._lock:
            start = 0 if last is None else max(self._n - last, 0)
            return self._stamps[start : self._n].copy(), self._poses[start : self._n].copy()


@dataclass(frozen=True)
class SavedRun:
    """What :func:`save_run` wrote."""

    map_path: Path
    trajectory_path: Path
    n_points: int
    n_poses: int
    voxel_size: float


def save_run(
    directory: str | Path,
    points: ArrayLike,
    stamps_ns: ArrayLike,
    poses: ArrayLike,
    *,
    voxel_size: float,
    map_name: str = 'map.ply',
    trajectory_name: str = 'trajectory_tum.txt',
) -> SavedRun:
    """Write a map (PLY or PCD, by ``map_name``'s suffix) and a TUM trajectory into
    ``directory`` (created, with its parents).

    Raises
    ------
    OSError
        The directory or a file cannot be written.
    """
    from kentreg_ros.io.mapfile import write_map
    from kentreg_ros.io.poses import write_tum

    folder = Path(directory).expanduser()
    folder.mkdir(parents=True, exist_ok=True)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    map_path = folder / map_name
    trajectory_path = folder / trajectory_name
    write_map(map_path, pts)
    T = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    write_tum(trajectory_path, np.asarray(stamps_ns, dtype=np.int64), T)
    return SavedRun(map_path, trajectory_path, len(pts), len(T), float(voxel_size))
