"""Write the map of a run (an (N, 3) point array) as a PLY or PCD file for a viewer.

PLY is written binary little-endian with float32 ``x y z`` (what Open3D, CloudCompare, MeshLab
and Blender read); PCD v0.7 ``DATA binary`` through :func:`~kentreg_ros.io.scanfiles.write_pcd`
(PCL, Open3D, CloudCompare). Both are read back by :func:`~kentreg_ros.io.scanfiles.read_scan`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from kentreg_ros.core import as_points
from kentreg_ros.io.errors import ScanFileError
from kentreg_ros.io.scanfiles import write_pcd

#: File suffixes :func:`write_map` writes.
MAP_SUFFIXES = ('.ply', '.pcd')


def write_ply(path: str | Path, points: ArrayLike) -> None:
    """Write points as a binary little-endian PLY with float32 ``x y z`` vertices.

    Parameters
    ----------
    path : str or Path
    points : array_like, shape (N, 3)
        Finite points.
    """
    pts = as_points(points)
    head = (
        'ply\nformat binary_little_endian 1.0\ncomment written by kentreg_ros\n'
        f'element vertex {len(pts)}\n'
        'property float x\nproperty float y\nproperty float z\nend_header\n'
    ).encode('ascii')
    Path(path).write_bytes(head + pts.astype('<f4').tobytes())


def write_map(path: str | Path, points: ArrayLike) -> None:
    """Write a map as PLY or PCD, chosen by the suffix of ``path``.

    Parameters
    ----------
    path : str or Path
        Ends in ``.ply`` or ``.pcd`` (case-insensitive); its folder must exist.
    points : array_like, shape (N, 3)
        Finite points, e.g. the voxel map of a run in the odometry frame.

    Raises
    ------
    ScanFileError
        Another suffix.
    InvalidPointCloudError
        ``points`` not of shape (N, 3) or not finite.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in MAP_SUFFIXES:
        raise ScanFileError(
            f'{p}: expected a map file ending in {" or ".join(MAP_SUFFIXES)}, got {suffix!r}.'
        )
    pts = as_points(points)
    if suffix == '.ply':
        write_ply(p, pts)
    else:
        write_pcd(p, np.asarray(pts, dtype=np.float32))
