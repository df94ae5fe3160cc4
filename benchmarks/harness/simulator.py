"""Re-simulate the sample's scene along faster trajectories, with exact reference poses.

The sample (``bags/balm_50``) moves 5 cm per scan and its reference is good to a few mm; this
builds sequences with neither limit: (1) the world: the 50 scans posed by their reference,
merged and thinned to one point per ``WORLD_VOXEL`` cube (its blur is the same for every
simulated scan); (2) the trajectory: the sample's path at ``step`` metres per scan with the
reference's orientation (slerp) turned by an optional yaw oscillation; (3) the scans: what a
360 deg spinning LiDAR sees from each pose (points in range and in the sample's elevation band,
occlusion per direction bin with a tolerance for grazing surfaces, one point per beam bin drawn
at random, Gaussian range noise), optionally over a sweep with every point timed. The poses
are exact: they define the sequence. ``simulated.py --write`` writes one as a scan folder.
:func:`corridor_world` is a world of its own: a featureless corridor whose axis no scan holds
(``calibration.py``'s degenerate condition).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import expm, logm
from scipy.spatial.transform import Rotation, Slerp

from kentreg_ros.eval import GroundTruth
from kentreg_ros.io import open_recording
from kentreg_ros.io.poses import Trajectory
from kentreg_ros.io.sources import Scan

from .perturb import transform

FloatArray = NDArray[np.float64]

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_INPUT = ROOT / 'bags' / 'balm_50'
#: Thinning of the merged world (m): finer than the simulated beams' footprint at 4 m
#: (0.5 deg -> 3.5 cm), so the beams, not the world's grid, set a scan's sampling.
WORLD_VOXEL = 0.03
#: Elevation band of the sample's sensor (deg): what the simulated sensor sees.
ELEVATION_DEG = (-45.0, 45.0)
#: Time slices of a sweep: the points of a slice share the pose of its middle (at 10 Hz,
#: 0.5 ms: 0.6 mm at 1.2 m/s, 0.2 mm per 10 m at 30 deg/s).
SWEEP_SLICES = 200


@dataclass(frozen=True)
class Sensor:
    """The simulated spinning LiDAR (see the module's description; angles in degrees)."""

    occlusion_bin: float = 1.0
    beam_bin: float = 0.5
    range_noise: float = 0.02
    min_range: float = 1.0
    max_range: float = 30.0
    #: Duration of one sweep (s); 0 takes every point at the scan's stamp. With a sweep, the
    #: sensor turns once, ending at the stamp (azimuth -180 deg first), moving meanwhile with
    #: the velocity that brought it from the previous scan, and every point carries its time
    #: in the field ``t`` (s from the stamp, negative).
    sweep_period: float = 0.0


@dataclass
class World:
    """The merged cloud, the reference poses its path is taken from and its scan period (s)."""

    points: FloatArray
    T_ref: FloatArray
    period: float


def thin(points: FloatArray, voxel: float) -> FloatArray:
    """One point (the first) per cube of edge ``voxel``."""
    grid = np.floor(points / voxel).astype(np.int64)
    grid -= grid.min(axis=0)
    span = grid.max(axis=0) + 1
    keys = (grid[:, 0] * span[1] + grid[:, 1]) * span[2] + grid[:, 2]
    _, first = np.unique(keys, return_index=True)
    return points[np.sort(first)]


def build_world(path: Path, voxel: float) -> World:
    """The merged, thinned world cloud, the reference poses it was merged with and the
    recording's scan period (the median interval of the reference's stamps)."""
    recording = open_recording(path)
    if recording.reference is None:
        raise SystemExit(f'{path}: no reference poses to merge the scans with')
    T = np.asarray(recording.reference.T_world_sensor, dtype=np.float64)
    scans = list(recording.source)
    if len(scans) != len(T):
        raise SystemExit(f'{path}: {len(scans)} scans but {len(T)} reference poses')
    parts = [transform(Ti, s.points) for s, Ti in zip(scans, T, strict=True)]
    stamps = recording.reference.stamps_ns
    period = float(np.median(np.diff(stamps))) * 1e-9 if stamps is not None else 0.1
    return World(thin(np.concatenate(parts), voxel), T, period)


def _plane(origin: FloatArray, u: FloatArray, v: FloatArray, size: tuple[float, float],
           spacing: float) -> FloatArray:  # fmt: skip
    """Points every ``spacing`` on the rectangle ``origin + a u + b v``, ``0 <= a, b < size``."""
    a, b = np.meshgrid(np.arange(0.0, size[0], spacing), np.arange(0.0, size[1], spacing))
    return origin + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v


def corridor_world(length: float = 110.0, width: float = 2.4, height: float = 2.6,
                   spacing: float = 0.04, period: float = 0.1) -> World:  # fmt: skip
    """A straight corridor along x (floor, ceiling and two walls, no doors) and a path along
    its middle 40 m, 1.3 m above the floor, wavering 0.25 m across it: its ends stay beyond the
    sensor's range, so nothing holds a translation along x (a degenerate axis)."""
    ex, ey, ez = np.eye(3)
    floor = -1.3
    corner = np.array([0.0, -width / 2, floor])
    parts = [_plane(corner + z * ez, ex, ey, (length, width), spacing) for z in (0.0, height)]
    parts += [_plane(corner + y * ey, ex, ez, (length, height), spacing) for y in (0.0, width)]
    x = np.arange(length / 2 - 20.0, length / 2 + 20.0, 0.05)
    T = np.tile(np.eye(4), (len(x), 1, 1))
    T[:, 0, 3], T[:, 1, 3] = x, 0.25 * np.sin(2.0 * np.pi * x / 8.0)
    return World(np.concatenate(parts), T, period)


def trajectory(
    T_ref: FloatArray, step: float, yaw_amplitude_deg: float, yaw_period: float
) -> FloatArray:
    """Poses every ``step`` metres along the reference path (see the module's description)."""
    positions = T_ref[:, :3, 3]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])
    s = np.arange(0.0, arc[-1] + 1e-9, step)
    xyz = np.stack([np.interp(s, arc, positions[:, k]) for k in range(3)], axis=1)
    # Slerp needs strictly increasing times: drop reference poses that did not move.
    keep = np.concatenate([[True], np.diff(arc) > 1e-6])
    slerp = Slerp(arc[keep], Rotation.from_matrix(T_ref[keep, :3, :3]))
    k = np.arange(len(s))
    yaw = np.deg2rad(yaw_amplitude_deg) * np.sin(2.0 * np.pi * k / yaw_period)
    R = slerp(s) * Rotation.from_euler('z', yaw[:, None])
    T = np.tile(np.eye(4), (len(s), 1, 1))
    T[:, :3, :3] = R.as_matrix()
    T[:, :3, 3] = xyz
    return T


def direction_bins(q: FloatArray, r: FloatArray, size_deg: float) -> NDArray[np.int64]:
    """Index of the azimuth x elevation bin of ``size_deg`` of each sensor-frame point."""
    az = np.degrees(np.arctan2(q[:, 1], q[:, 0])) + 180.0
    el = np.degrees(np.arcsin(np.clip(q[:, 2] / r, -1.0, 1.0))) + 90.0
    n_az = int(np.ceil(360.0 / size_deg))
    return np.asarray(np.floor(el / size_deg) * n_az + np.floor(az / size_deg), dtype=np.int64)


def simulate_scan(
    world: FloatArray, T: FloatArray, rng: np.random.Generator, args: Sensor,
    twist: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:  # fmt: skip
    """The points a spinning LiDAR at pose ``T`` sees of ``world`` (sensor frame), and their
    times from the stamp (s). With ``args.sweep_period > 0`` and the ``twist`` (4x4 ``se(3)``
    body velocity per second), a point taken at ``tau`` is in the frame of the pose
    ``T exp(tau twist)``; which points are visible is decided from ``T``."""
    q = (world - T[:3, 3]) @ T[:3, :3]
    r = np.linalg.norm(q, axis=1)
    el = np.degrees(np.arcsin(np.clip(q[:, 2] / np.maximum(r, 1e-12), -1.0, 1.0)))
    inside = (r >= args.min_range) & (r <= args.max_range)
    inside &= (el >= ELEVATION_DEG[0]) & (el <= ELEVATION_DEG[1])
    q, r = q[inside], r[inside]
    # Occlusion: the nearest range per coarse direction bin hides what lies well behind it.
    coarse = direction_bins(q, r, args.occlusion_bin)
    nearest = np.full(coarse.max() + 1, np.inf)
    np.minimum.at(nearest, coarse, r)
    visible = r <= nearest[coarse] + 0.1 + 0.05 * r
    q, r = q[visible], r[visible]
    # The sensor's angular resolution: one visible point per beam bin, drawn at random (the
    # nearest would pull a surface towards the sensor by the world's blur, differently from
    # every viewpoint), so that two scans from near poses do not share their points.
    beam = direction_bins(q, r, args.beam_bin)
    order = np.lexsort((rng.random(len(r)), beam))
    first = np.ones(len(order), dtype=bool)
    first[1:] = beam[order][1:] != beam[order][:-1]
    chosen = order[first]
    q, r = q[chosen], r[chosen]
    times = np.zeros(len(q))
    if args.sweep_period > 0.0 and twist is not None:
        azimuth = np.arctan2(q[:, 1], q[:, 0]) + np.pi  # 0 .. 2 pi
        slot = np.minimum(
            (azimuth / (2.0 * np.pi) * SWEEP_SLICES).astype(np.intp), SWEEP_SLICES - 1
        )
        times = ((slot + 0.5) / SWEEP_SLICES - 1.0) * args.sweep_period
        for k in np.unique(slot):
            M = expm(twist * times[slot == k][0])  # pose at tau in the frame at the stamp
            sel = slot == k
            q[sel] = (q[sel] - M[:3, 3]) @ M[:3, :3]
        r = np.linalg.norm(q, axis=1)
    noisy = r + rng.normal(0.0, args.range_noise, len(r))
    return q * (noisy / r)[:, None], times


def simulate(
    world: World, step: float, seed: int, sensor: Sensor = Sensor(), *,
    yaw_amplitude: float = 0.0, yaw_period: float = 9.0,
) -> tuple[list[Scan], GroundTruth]:  # fmt: skip
    """The scans of a sensor travelling the world's path at ``step`` metres per scan, and
    their exact poses (stamped at the world's scan period from 1e9 s after the epoch)."""
    T = trajectory(world.T_ref, step, yaw_amplitude, yaw_period)
    rng = np.random.default_rng(seed)
    start_ns = 10**18
    stamps = start_ns + np.round(np.arange(len(T)) * world.period * 1e9).astype(np.int64)
    # Body velocity of each scan's sweep, which ends at its stamp: the motion from the previous
    # scan over the period (the first scan takes the next one's), constant within the sweep.
    twists = [
        np.real(logm(np.linalg.solve(T[i - 1], T[i]))) / world.period for i in range(1, len(T))
    ]
    twists.insert(0, twists[0] if twists else np.zeros((4, 4)))
    scans = []
    for ts, Ti, twist in zip(stamps, T, twists, strict=True):
        points, times = simulate_scan(world.points, Ti, rng, sensor, twist)
        extras = {'t': times.astype(np.float32)} if sensor.sweep_period > 0.0 else {}
        scans.append(Scan(int(ts), 'lidar', points, extras))
    origin = f'simulated: step {step} m, seed {seed}'
    return scans, GroundTruth(Trajectory(stamps, T), origin)


def motion_stats(T: FloatArray) -> dict[str, float]:
    """Median step (m) and median / max rotation (deg) between consecutive poses."""
    rel = np.einsum('nji,njk->nik', T[:-1, :3, :3], T[1:, :3, :3])  # R_i^T R_{i+1}
    angles = np.degrees(Rotation.from_matrix(rel).magnitude())
    steps = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    return {'step_median_m': float(np.median(steps)),
            'rotation_median_deg': float(np.median(angles)),
            'rotation_max_deg': float(angles.max()), 'path_m': float(steps.sum())}  # fmt: skip
