"""Pose files: KITTI, TUM, ETH ``pose_scanner_leica.csv`` and BALM ``alidarPose.csv``.

Every reader returns a :class:`Trajectory`: stamps in integer nanoseconds (None when the format
has no times) and ``T_world_sensor`` (N, 4, 4). Times are parsed from their decimal text
exactly, so a stamp read from a pose file equals the header stamp written from it.

Formats
-------
KITTI odometry (Geiger et al., CVPR 2012)
    One pose per line: 12 numbers, the row-major 3x4 ``[R | t]`` of ``T_world_sensor``. No
    times (KITTI keeps them in ``times.txt``, one number of seconds per line).
TUM RGB-D (Sturm et al., IROS 2012)
    ``timestamp tx ty tz qx qy qz qw`` per line, ``#`` comments; quaternion scalar-last.
ETH (Pomerleau et al., IJRR 2012)
    ``pose_scanner_leica.csv``: a header row, then ``poseId, timestamp, T00, ..., T33`` (the
    row-major 4x4 ``T_world_scanner``). Times are taken as seconds.
BALM (Liu et al., BALM 2.0, 2023)
    ``alidarPose.csv``: 4 lines per pose, each with a trailing comma; lines 1-3 are the 3x4
    ``[R | t]`` of ``T_world_lidar``, line 4 is ``0,0,0,<unix time in s>``.
"""

from __future__ import annotations

import decimal
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from kentreg_ros.io.errors import PoseFileError

logger = logging.getLogger(__name__)

#: Pose file formats :func:`read_poses` knows.
POSE_FORMATS = ('kitti', 'tum', 'eth', 'balm')
#: Names of the pose files :func:`pose_file_beside` looks for in a scan folder (BALM, ETH, other).
POSE_FILES_BESIDE_SCANS = ('alidarPose.csv', 'pose_scanner_leica.csv', 'poses.csv')
#: Names of the pose files :func:`pose_file_beside` looks for beside a KITTI-layout scan folder
#: (``<sequence>/velodyne/*.bin``, poses in ``<sequence>/``): timed TUM first, as its stamps
#: also time the scans.
POSE_FILES_BESIDE_VELODYNE = ('poses_tum.txt', 'poses.txt', 'poses_kitti.txt')
_ROTATION_TOLERANCE = 1e-3


class Trajectory(NamedTuple):
    """Poses of a sensor, optionally timed.

    Attributes
    ----------
    stamps_ns : ndarray of int64, shape (N,), or None
        Times in nanoseconds (None for formats without times, e.g. KITTI).
    T_world_sensor : ndarray, shape (N, 4, 4)
        Sensor poses in the world frame (maps sensor points into the world).
    """

    stamps_ns: NDArray[np.int64] | None
    T_world_sensor: NDArray[np.float64]

    @property
    def stamps(self) -> NDArray[np.float64] | None:
        """Times in seconds (float64), or None."""
        return None if self.stamps_ns is None else self.stamps_ns / 1e9


def seconds_to_ns(text: str) -> int:
    """Parse a time in seconds written in decimal (``'1630577758.569490'``) to exact ns."""
    try:
        value = decimal.Decimal(text.strip())
    except decimal.InvalidOperation as exc:
        raise ValueError(f'not a number: {text!r}') from exc
    if not value.is_finite():
        raise ValueError(f'not a finite time: {text!r}')
    return int((value * 1_000_000_000).to_integral_value(rounding=decimal.ROUND_HALF_EVEN))


def _stamps(path: Path, tokens: Sequence[str]) -> NDArray[np.int64]:
    try:
        return np.array([seconds_to_ns(t) for t in tokens], dtype=np.int64)
    except ValueError as exc:
        raise PoseFileError(f'{path}: bad time ({exc}).') from exc


def _read_rows(path: Path, *, delimiter: str | None, comment: str = '#') -> list[list[str]]:
    """Non-empty, non-comment lines split into tokens (trailing delimiters dropped)."""
    try:
        text = path.read_text(encoding='utf-8', errors='replace')
    except OSError as exc:
        raise PoseFileError(f'{path}: cannot read ({exc.strerror or exc}).') from exc
    rows = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith(comment):
            continue
        if delimiter is None:
            rows.append(line.split())
        else:
            rows.append([t.strip() for t in line.rstrip(delimiter + ' ').split(delimiter)])
    return rows


def _numbers(
    path: Path, rows: Sequence[Sequence[str]], ncols: int, what: str
) -> NDArray[np.float64]:
    bad = [i for i, r in enumerate(rows) if len(r) != ncols]
    if bad:
        raise PoseFileError(
            f'{path}: {what} line {bad[0] + 1} (data line) has {len(rows[bad[0]])} values, '
            f'expected {ncols}.'
        )
    try:
        return np.array(rows, dtype=np.float64).reshape(len(rows), ncols)
    except ValueError as exc:
        raise PoseFileError(f'{path}: {what} holds a value that is not a number ({exc}).') from exc


def _check_poses(path: Path, T: NDArray[np.float64]) -> NDArray[np.float64]:
    if not np.isfinite(T).all():
        bad = int(np.flatnonzero(~np.isfinite(T).all(axis=(1, 2)))[0])
        raise PoseFileError(f'{path}: pose {bad} has NaN or inf entries.')
    if len(T) and not np.allclose(T[:, 3], [0.0, 0.0, 0.0, 1.0]):
        bad = int(np.flatnonzero(~np.isclose(T[:, 3], [0, 0, 0, 1]).all(axis=1))[0])
        raise PoseFileError(f'{path}: pose {bad} has last row {T[bad, 3]}, expected [0 0 0 1].')
    if len(T):
        R = T[:, :3, :3]
        err = np.abs(np.einsum('nji,njk->nik', R, R) - np.eye(3)).max(axis=(1, 2))
        bad_mask = (err > _ROTATION_TOLERANCE) | (np.linalg.det(R) <= 0.0)
        if bad_mask.any():
            bad = int(np.argmax(bad_mask))
            raise PoseFileError(f'{path}: pose {bad} is not a rigid transform (R not a rotation).')
    return T


def _from_3x4(rows: NDArray[np.float64]) -> NDArray[np.float64]:
    T = np.zeros((len(rows), 4, 4))
    T[:, :3, :] = rows.reshape(-1, 3, 4)
    T[:, 3, 3] = 1.0
    return T


def read_kitti_poses(path: str | Path, *, times: str | Path | None = None) -> Trajectory:
    """Read a KITTI pose file (12 numbers per line), optionally with its ``times.txt``.

    Raises
    ------
    PoseFileError
        A line without 12 numbers, a non-rotation, or a times file of another length.
    """
    p = Path(path)
    T = _check_poses(p, _from_3x4(_numbers(p, _read_rows(p, delimiter=None), 12, 'KITTI')))
    stamps = None
    if times is not None:
        tp = Path(times)
        tokens = [r[0] for r in _read_rows(tp, delimiter=None) if len(r) == 1]
        stamps = _stamps(tp, tokens)
        if len(stamps) != len(T):
            raise PoseFileError(f'{tp}: {len(stamps)} times for {len(T)} poses in {p}.')
    return Trajectory(stamps, T)


def read_tum_poses(path: str | Path) -> Trajectory:
    """Read a TUM trajectory (``timestamp tx ty tz qx qy qz qw`` per line)."""
    p = Path(path)
    rows = _read_rows(p, delimiter=None)
    values = _numbers(p, rows, 8, 'TUM')
    q = values[:, 4:8]
    norms = np.linalg.norm(q, axis=1)
    if len(q) and (np.abs(norms - 1.0) > _ROTATION_TOLERANCE).any():
        bad = int(np.argmax(np.abs(norms - 1.0) > _ROTATION_TOLERANCE))
        raise PoseFileError(f'{p}: quaternion of pose {bad} has norm {norms[bad]:.6g}, not 1.')
    T = np.tile(np.eye(4), (len(values), 1, 1))
    if len(values):
        T[:, :3, :3] = Rotation.from_quat(q).as_matrix()
        T[:, :3, 3] = values[:, 1:4]
    return Trajectory(_stamps(p, [r[0] for r in rows]), T)


def read_eth_poses(path: str | Path) -> Trajectory:
    """Read ETH ``pose_scanner_leica.csv`` (header, then ``poseId, timestamp, T00..T33``)."""
    p = Path(path)
    rows = _read_rows(p, delimiter=',')
    if not rows or not rows[0] or not rows[0][0].lower().startswith('pose'):
        raise PoseFileError(f'{p}: ETH pose file must start with a header row "poseId, ...".')
    rows = rows[1:]
    values = _numbers(p, rows, 18, 'ETH pose')
    T = _check_poses(p, values[:, 2:].reshape(-1, 4, 4).copy())
    return Trajectory(_stamps(p, [r[1] for r in rows]), T)


def read_balm_poses(path: str | Path) -> Trajectory:
    """Read BALM ``alidarPose.csv`` (4 lines per pose, line 4 ``0,0,0,<unix time s>``)."""
    p = Path(path)
    rows = _read_rows(p, delimiter=',')
    if len(rows) % 4:
        raise PoseFileError(f'{p}: BALM pose file has {len(rows)} lines, not a multiple of 4.')
    values = _numbers(p, rows, 4, 'BALM pose').reshape(-1, 4, 4)
    if len(values) and not np.allclose(values[:, 3, :3], 0.0):
        bad = int(np.argmax(~np.isclose(values[:, 3, :3], 0.0).all(axis=1)))
        raise PoseFileError(f'{p}: line 4 of pose {bad} must start with 0,0,0.')
    T = values.copy()
    T[:, 3] = [0.0, 0.0, 0.0, 1.0]
    return Trajectory(_stamps(p, [r[3] for r in rows[3::4]]), _check_poses(p, T))


def detect_pose_format(path: str | Path) -> str:
    """Guess a pose file's format from its name and first lines.

    Returns one of :data:`POSE_FORMATS`; raises :class:`PoseFileError` when unsure.
    """
    p = Path(path)
    name = p.name.lower()
    if name == 'pose_scanner_leica.csv':
        return 'eth'
    if name == 'alidarpose.csv':
        return 'balm'
    rows = _read_rows(p, delimiter=',' if p.suffix.lower() == '.csv' else None)[:8]
    if rows and rows[0] and rows[0][0].lower().startswith('pose'):
        return 'eth'
    widths = {len(r) for r in rows}
    if widths == {12}:
        return 'kitti'
    if widths == {8}:
        return 'tum'
    if widths == {4}:
        return 'balm'
    raise PoseFileError(
        f'{p}: cannot tell the pose format (lines with {sorted(widths)} values); pass one of '
        f'{", ".join(POSE_FORMATS)}.'
    )


def read_poses(
    path: str | Path, *, format: str | None = None, times: str | Path | None = None
) -> Trajectory:
    """Read a pose file of any supported format.

    Parameters
    ----------
    path : str or Path
    format : {'kitti', 'tum', 'eth', 'balm'}, optional
        Default: :func:`detect_pose_format`.
    times : str or Path, optional
        KITTI ``times.txt`` (seconds per line); only for the KITTI format.

    Returns
    -------
    Trajectory
    """
    fmt = format or detect_pose_format(path)
    if fmt not in POSE_FORMATS:
        raise PoseFileError(f'Unknown pose format {fmt!r}; expected one of {POSE_FORMATS}.')
    if times is not None and fmt != 'kitti':
        raise PoseFileError(f'A times file is only used with KITTI poses, not {fmt}.')
    if fmt == 'kitti':
        return read_kitti_poses(path, times=times)
    return {'tum': read_tum_poses, 'eth': read_eth_poses, 'balm': read_balm_poses}[fmt](path)


def pose_file_beside(folder: str | Path) -> Path | None:
    """The pose file of a scan folder: the first of :data:`POSE_FILES_BESIDE_SCANS` in it, or,
    for a KITTI-layout folder named ``velodyne``, the first of
    :data:`POSE_FILES_BESIDE_VELODYNE` in the folder that holds it.

    Each name is tried as written, then in lower case; None when there is none.
    """
    folder = Path(folder)
    places = [(folder, POSE_FILES_BESIDE_SCANS)]
    if folder.name == 'velodyne':
        places.append((folder.parent, POSE_FILES_BESIDE_VELODYNE))
    for where, names in places:
        for name in names:
            for candidate in (where / name, where / name.lower()):
                if candidate.is_file():
                    return candidate
    return None


def _as_poses(T_world_sensor: ArrayLike) -> NDArray[np.float64]:
    T = np.asarray(T_world_sensor, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f'Expected `T_world_sensor` to have shape (N, 4, 4), got {T.shape}.')
    return T


def write_tum(path: str | Path, stamps_ns: ArrayLike, T_world_sensor: ArrayLike) -> None:
    """Write a TUM trajectory: ``sec.nanosec tx ty tz qx qy qz qw`` per pose.

    Parameters
    ----------
    path : str or Path
    stamps_ns : array_like of int, shape (N,)
        Times in nanoseconds (written exactly, 9 decimals).
    T_world_sensor : array_like, shape (N, 4, 4)
    """
    T = _as_poses(T_world_sensor)
    stamps = np.asarray(stamps_ns)
    if stamps.shape != (len(T),) or (stamps.size and stamps.dtype.kind not in 'iu'):
        raise ValueError(
            f'Expected `stamps_ns` to be integers of shape ({len(T)},), got {stamps.dtype} '
            f'{stamps.shape}.'
        )
    q = Rotation.from_matrix(T[:, :3, :3]).as_quat() if len(T) else np.empty((0, 4))
    sec, nsec = np.divmod(stamps.astype(np.int64), 1_000_000_000)
    lines = [
        f'{s}.{ns:09d} ' + ' '.join(f'{v:.9g}' for v in (*t, *qq))
        for s, ns, t, qq in zip(sec, nsec, T[:, :3, 3], q, strict=True)
    ]
    Path(path).write_text(''.join(line + '\n' for line in lines))


def write_kitti(path: str | Path, T_world_sensor: ArrayLike) -> None:
    """Write a KITTI pose file: the row-major 3x4 ``[R | t]`` of each pose on one line."""
    T = _as_poses(T_world_sensor)
    np.savetxt(Path(path), T[:, :3, :].reshape(-1, 12), fmt='%.9e')
