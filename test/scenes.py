"""Seeded synthetic scenes with known ground truth for the tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core import exp_so3, make_transform

FloatArray = NDArray[np.float64]

SHARED_DATA = Path(__file__).resolve().parents[2] / 'shared' / 'data'
SMALL_GICP_PAIR = SHARED_DATA / 'small_gicp_pair'
BALM = SHARED_DATA / 'balm'


def _plane(
    rng: np.random.Generator, origin: FloatArray, u: FloatArray, v: FloatArray, n: int
) -> FloatArray:
    a = rng.random((n, 1))
    b = rng.random((n, 1))
    return origin + a * u + b * v


def box_room(
    rng: np.random.Generator,
    n: int = 10000,
    *,
    size: tuple[float, float, float] = (8.0, 6.0, 3.0),
    noise: float = 0.01,
    boxes: int = 3,
) -> FloatArray:
    """Points on the walls, floor and ceiling of a room plus a few boxes, centred on the origin.

    The scene has planes of many orientations (room, and boxes rotated about z), so it fully
    constrains rotation and translation.
    """
    sx, sy, sz = size
    lo = np.array([-sx / 2, -sy / 2, -1.0])
    ex, ey, ez = np.array([sx, 0, 0.0]), np.array([0, sy, 0.0]), np.array([0, 0, sz])
    faces = [
        (lo, ex, ey),
        (lo + ez, ex, ey),  # floor, ceiling
        (lo, ex, ez),
        (lo + ey, ex, ez),  # walls
        (lo, ey, ez),
        (lo + ex, ey, ez),
    ]
    for i in range(boxes):
        c = np.array([rng.uniform(-sx / 3, sx / 3), rng.uniform(-sy / 3, sy / 3), -1.0])
        R = exp_so3(np.array([0.0, 0.0, rng.uniform(0, np.pi / 2)]) + 0.05 * i)
        a, b, h = R @ np.array([0.8, 0, 0]), R @ np.array([0, 0.6, 0]), np.array([0, 0, 1.0])
        faces += [(c, a, h), (c + b, a, h), (c, b, h), (c + a, b, h), (c + h, a, b)]
    areas = np.array([np.linalg.norm(np.cross(u, v)) for _, u, v in faces])
    counts = rng.multinomial(n, areas / areas.sum())
    pts = np.concatenate(
        [_plane(rng, o, u, v, c) for (o, u, v), c in zip(faces, counts, strict=True)]
    )
    return pts + rng.normal(scale=noise, size=pts.shape)


def corridor(rng: np.random.Generator, n: int = 8000, noise: float = 0.01) -> FloatArray:
    """A long corridor along x: translation along x is unconstrained."""
    length, width, height = 60.0, 2.0, 2.5
    lo = np.array([-length / 2, -width / 2, -1.0])
    ex, ey, ez = np.array([length, 0, 0.0]), np.array([0, width, 0.0]), np.array([0, 0, height])
    faces = [(lo, ex, ey), (lo + ez, ex, ey), (lo, ex, ez), (lo + ey, ex, ez)]
    counts = rng.multinomial(n, [0.25] * 4)
    pts = np.concatenate(
        [_plane(rng, o, u, v, c) for (o, u, v), c in zip(faces, counts, strict=True)]
    )
    return pts + rng.normal(scale=noise, size=pts.shape)


def add_outliers(rng: np.random.Generator, points: FloatArray, fraction: float) -> FloatArray:
    """Append uniform outliers in the bounding box: ``fraction`` of the result's points."""
    if fraction <= 0:
        return points
    m = int(round(len(points) * fraction / (1.0 - fraction)))
    lo, hi = points.min(axis=0), points.max(axis=0)
    return np.concatenate([points, rng.uniform(lo, hi, size=(m, 3))])


def random_transform(rng: np.random.Generator, angle_deg: float, distance: float) -> FloatArray:
    """A transform with a random axis of the given angle and a random direction of given length."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    return make_transform(exp_so3(axis * np.radians(angle_deg)), d * distance)


def transform_points(T: FloatArray, points: FloatArray) -> FloatArray:
    return points @ T[:3, :3].T + T[:3, 3]


def pose_errors(T_est: FloatArray, T_true: FloatArray) -> tuple[float, float]:
    """(rotation error in degrees, translation error in metres) of the paper."""
    dR = T_true[:3, :3].T @ T_est[:3, :3]
    e_r = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
    return e_r, float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))


def read_ply_xyz(path: Path) -> FloatArray:
    """Minimal reader for the binary little-endian PLY files of small_gicp_pair (test-only,
    independent of kentreg_ros.io)."""
    raw = path.read_bytes()
    end = raw.index(b'end_header\n') + len(b'end_header\n')
    header = raw[:end].decode('ascii').splitlines()
    count = next(int(line.split()[2]) for line in header if line.startswith('element vertex'))
    names = [line.split()[2] for line in header if line.startswith('property')]
    data = np.frombuffer(raw[end:], dtype='<f4', count=count * len(names))
    data = data.reshape(count, len(names))
    return data[:, [names.index('x'), names.index('y'), names.index('z')]].astype(np.float64)
