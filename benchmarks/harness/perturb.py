"""Perturbations that compose: what an experiment does to scans, pairs and starts.

On scan lists, composed with :func:`compose`: :func:`stride` (frame skipping), :func:`raw_outliers`
and :func:`merge` (denser scans); sweeps are the simulated sensor's (``Sensor.sweep_period``).
On points and poses: the two outlier models (a share of the raw cloud, a share of the
downsampled cloud), :func:`offset_transform` (a start off by exact errors), :func:`turn_transform`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from kentreg_ros.core import make_transform, voxel_downsample
from kentreg_ros.io.sources import Scan

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
Perturbation = Callable[[list[Scan]], list[Scan]]


def compose(*steps: Perturbation) -> Perturbation:
    """The perturbations applied left to right."""

    def run(scans: list[Scan]) -> list[Scan]:
        for step in steps:
            scans = step(scans)
        return scans

    return run


def stride(n: int) -> Perturbation:
    """Every ``n``-th scan, stamps unchanged (the motion between scans grows ``n`` times)."""
    if n < 1:
        raise ValueError(f'Expected `n` >= 1, got {n}.')
    return lambda scans: scans[::n]


def raw_outliers(
    fraction: float, rng: np.random.Generator, *, shell_share: float = 0.0
) -> Perturbation:
    """:func:`inject_raw_outliers` on every scan in turn (one ``rng``); the extra fields are
    dropped (an outlier has no time)."""

    def one(scan: Scan) -> Scan:
        points = np.asarray(scan.points, dtype=np.float64)
        noisy, _ = inject_raw_outliers(points, fraction, rng, shell_share=shell_share)
        return Scan(scan.stamp_ns, scan.frame_id, noisy, {})

    return lambda scans: [one(s) for s in scans]


def merge(k: int, T_world: FloatArray) -> Perturbation:
    """Scan ``i`` joined with scans ``i-k+1 .. i-1`` moved into its frame by the reference
    poses ``T_world`` (from scan ``k-1`` on): denser real scans with the same motion."""

    def one(scans: list[Scan], i: int) -> Scan:
        inv = np.linalg.inv(T_world[i])
        parts = [np.asarray(scans[i].points, dtype=np.float64)]
        parts += [transform(inv @ T_world[j], scans[j].points) for j in range(i - k + 1, i)]
        points = np.ascontiguousarray(np.vstack(parts))
        return Scan(scans[i].stamp_ns, scans[i].frame_id, points, {})

    return lambda scans: [one(scans, i) for i in range(k - 1, len(scans))]


def inject_raw_outliers(
    points: FloatArray, fraction: float, rng: np.random.Generator, *, shell_share: float = 0.0
) -> tuple[FloatArray, BoolArray]:
    """A raw scan (N, 3), sensor at the origin, with ``K = round(N f / (1 - f))`` uniform
    outliers (``fraction`` of the result to ``0.5 / (N + K)``) in its bounding box, a share
    ``shell_share`` of them in the sensor's range shell instead (the scan's elevation band and
    range span, as rain or dust returns are), shuffled in; the cloud and its outlier mask."""
    pts = np.asarray(points, dtype=np.float64)
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f'Expected `fraction` in [0, 1), got {fraction}.')
    if not 0.0 <= shell_share <= 1.0:
        raise ValueError(f'Expected `shell_share` in [0, 1], got {shell_share}.')
    if pts.ndim != 2 or pts.shape[1] != 3 or not len(pts):
        raise ValueError(f'Expected a non-empty (N, 3) scan, got shape {pts.shape}.')
    n = len(pts)
    k = int(round(n * fraction / (1.0 - fraction)))
    n_shell = int(round(k * shell_share))
    box = rng.uniform(pts.min(axis=0), pts.max(axis=0), size=(k - n_shell, 3))
    r = np.linalg.norm(pts, axis=1)
    seen = r > 0.0
    sin_el = pts[seen, 2] / r[seen]
    sin_lo, sin_hi = (float(sin_el.min()), float(sin_el.max())) if seen.any() else (-1.0, 1.0)
    z = rng.uniform(sin_lo, sin_hi, n_shell)  # uniform on the sphere's band between elevations
    azimuth = rng.uniform(0.0, 2.0 * np.pi, n_shell)
    ranges = rng.uniform(float(r.min()), float(r.max()), n_shell)
    horizontal = np.sqrt(np.clip(1.0 - z**2, 0.0, None))
    directions = [horizontal * np.cos(azimuth), horizontal * np.sin(azimuth), z]
    shell = ranges[:, None] * np.column_stack(directions)
    cloud = np.concatenate([pts, box, shell])
    is_outlier = np.arange(len(cloud)) >= n
    order = rng.permutation(len(cloud))
    return cloud[order], is_outlier[order]


def inject_free_voxel_outliers(
    points: FloatArray, fraction: float, voxel: float, rng: np.random.Generator
) -> tuple[FloatArray, float]:
    """The raw scan downsampled at ``voxel`` to ``M`` points plus ``K = round(M f / (1 - f))``
    uniform outliers, one per voxel the scan does not occupy (so each survives downsampling and
    the share is exact: the paper's protocol), and the realised share ``K / (M + K)``."""
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f'Expected `fraction` in [0, 1), got {fraction}.')
    clean = voxel_downsample(points, voxel)
    n_out = int(round(len(clean) * fraction / (1.0 - fraction)))
    if n_out == 0:
        return clean, 0.0
    lo, hi = points.min(axis=0), points.max(axis=0)
    grid = (lo, hi)  # every point lies in the raw box, so keys on its grid name voxels alike
    chosen = np.empty((0, 3))
    taken = np.unique(_cell_keys(clean, voxel, grid))
    for _ in range(100):
        draw = rng.uniform(lo, hi, size=(2 * (n_out - len(chosen)) + 16, 3))
        keys = _cell_keys(draw, voxel, grid)
        free = ~np.isin(keys, taken)
        _, first = np.unique(keys[free], return_index=True)
        new = draw[free][np.sort(first)][: n_out - len(chosen)]
        chosen = np.concatenate([chosen, new])
        taken = np.union1d(taken, _cell_keys(new, voxel, grid))
        if len(chosen) == n_out:
            break
    else:
        raise ValueError('The bounding box has too few free voxels for the requested outliers.')
    cloud = voxel_downsample(np.concatenate([points, chosen]), voxel)
    return cloud, (len(cloud) - len(clean)) / len(cloud)


def _cell_keys(points: FloatArray, voxel: float, grid: tuple[FloatArray, FloatArray]) -> Any:
    """Linear index of each point's voxel in the grid spanning ``grid = (lo, hi)``, numbered as
    kentreg's voxel downsampling numbers them (``floor(p / voxel)``, x then y then z)."""
    corner = np.floor(grid[0] / voxel)
    span = np.floor(grid[1] / voxel) - corner + 1.0
    f = np.floor(points / voxel) - corner
    return ((f[:, 0] * span[1] + f[:, 1]) * span[2] + f[:, 2]).astype(np.int64)


def outlier_voxel_share(cloud: FloatArray, is_outlier: BoolArray, voxel: float) -> float:
    """Share of the occupied voxels (edge ``voxel``, origin-anchored) holding only outliers:
    the pure outliers after centroid downsampling at that voxel."""
    if not len(cloud):
        return float('nan')
    ijk = np.floor(cloud / voxel).astype(np.int64)
    _, inverse = np.unique(ijk, axis=0, return_inverse=True)
    real = np.bincount(inverse.ravel(), weights=~is_outlier).astype(np.int64)
    return float(np.mean(real == 0))


def offset_transform(rng: np.random.Generator, degrees: float, metres: float) -> FloatArray:
    """A rotation of ``degrees`` about a random axis and a translation of ``metres``: a start
    ``T_true @ offset_transform(...)`` is off by exactly that (e_R, e_t)."""
    axis, direction = _unit(rng), _unit(rng)
    rotation = Rotation.from_rotvec(np.radians(degrees) * axis).as_matrix()
    return make_transform(rotation, metres * direction)


def turn_transform(rng: np.random.Generator, degrees: float) -> FloatArray:
    """A rotation of ``degrees`` about a random axis through the origin (the sensor)."""
    return offset_transform(rng, degrees, 0.0)


def _unit(rng: np.random.Generator) -> FloatArray:
    v = rng.normal(size=3)
    return np.asarray(v / np.linalg.norm(v), dtype=np.float64)


def transform(T: FloatArray, points: Any) -> FloatArray:
    """``T`` applied to ``points`` (N, 3), as float64."""
    pts = np.asarray(points, dtype=np.float64)
    return np.asarray(pts @ T[:3, :3].T + T[:3, 3], dtype=np.float64)


def draw_pairs(n_pairs: int, count: int, seed: int, test: int) -> list[int]:
    """``count`` distinct pair indices of ``n_pairs``, drawn without replacement (seeded)."""
    count = min(count, n_pairs)
    rng = np.random.default_rng([seed, test])
    return sorted(int(p) for p in rng.choice(n_pairs, size=count, replace=False))


def draw_trials(n_pairs: int, trials: int, seed: int) -> list[int]:
    """The pair of every trial (seeded, with replacement)."""
    return [int(p) for p in np.random.default_rng(seed).integers(0, n_pairs, size=trials)]


def select_pairs(n_pairs: int, count: int | None) -> list[int]:
    """``count`` evenly spread pair indices of ``n_pairs`` (all when ``count`` is None)."""
    if count is None or count >= n_pairs:
        return list(range(n_pairs))
    return sorted({int(round(v)) for v in np.linspace(0, n_pairs - 1, max(count, 1))})
