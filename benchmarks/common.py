"""Data sets, error summaries and report helpers shared by the benchmark scripts.

A :class:`Sequence` is a list of scans (raw point arrays, loaded lazily) with reference poses;
its pairs are consecutive scans ``(i, i + 1)`` and the true motion of pair ``i`` is
``T_i^-1 T_{i+1}`` (target = scan ``i``, source = scan ``i + 1``, as in odometry).
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core import drop_nonfinite, project_to_so3
from kentreg_ros.eval import jsonable, orthonormalize
from kentreg_ros.eval.metrics import failed_pairs, pair_errors
from kentreg_ros.io import list_scans, read_poses, read_scan
from kentreg_ros.io.poses import Trajectory

FloatArray = NDArray[np.float64]

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get('KENTREG_SHARED_DATA', ROOT.parent / 'shared' / 'data'))
RESULTS = ROOT / 'benchmarks' / 'results'


def load_points(path: Path) -> FloatArray:
    """x, y, z of a scan file (PCD, PLY, KITTI .bin, ETH CSV), non-finite points dropped."""
    points, _ = drop_nonfinite(read_scan(path, fields=()).points)
    return points


@dataclass
class Sequence:
    """Scans and reference poses of one data set.

    Attributes
    ----------
    name : str
    scan_paths : list of Path
    T_world_sensor : ndarray, shape (N, 4, 4) or None
        Reference poses (rotations projected onto SO(3)); None when only ``pair_truth`` is
        known.
    pair_truth : dict of int to ndarray (4, 4), optional
        True ``T_target_source`` of pairs, overriding the poses (single-pair data sets).
    note : str
        Where the reference comes from (for the report).
    """

    name: str
    scan_paths: list[Path]
    T_world_sensor: FloatArray | None
    pair_truth: dict[int, FloatArray] | None = None
    note: str = ''

    @property
    def n_pairs(self) -> int:
        return len(self.scan_paths) - 1

    def truth(self, pair: int) -> FloatArray:
        """True ``T_target_source`` of pair ``pair`` (source ``pair + 1``, target ``pair``)."""
        if self.pair_truth is not None and pair in self.pair_truth:
            return self.pair_truth[pair]
        if self.T_world_sensor is None:
            raise ValueError(f'{self.name}: no reference for pair {pair}.')
        T = self.T_world_sensor
        return np.asarray(np.linalg.inv(T[pair]) @ T[pair + 1], dtype=np.float64)

    def constant_velocity(self, pair: int) -> FloatArray:
        """The previous pair's true motion (a constant-velocity prior); identity for pair 0."""
        if pair == 0 or self.T_world_sensor is None:
            return np.eye(4)
        return self.truth(pair - 1)

    def load(self, index: int) -> FloatArray:
        return load_points(self.scan_paths[index])


def _orthonormal(trajectory: Trajectory, origin: str) -> FloatArray:
    return np.asarray(orthonormalize(trajectory, origin).T_world_sensor, dtype=np.float64)


def load_balm(folder: Path = SHARED_DATA / 'balm') -> Sequence:
    """The 50 real BALM scans ``full0..49.pcd`` and ``alidarPose.csv``."""
    paths = list_scans(folder, suffixes=['.pcd'])
    poses = _orthonormal(read_poses(folder / 'alidarPose.csv'), str(folder))
    poses = poses[: len(paths)]
    return Sequence(
        'balm',
        paths,
        poses,
        note='BALM 2.0 real sequence; reference = LiDAR-inertial bundle-adjusted poses',
    )


def load_small_gicp_pair(folder: Path = SHARED_DATA / 'small_gicp_pair') -> Sequence:
    """The real small_gicp pair; scan 0 = target.ply, scan 1 = source.ply."""
    T = np.loadtxt(folder / 'T_target_source.txt').reshape(4, 4)
    T[:3, :3] = project_to_so3(T[:3, :3])
    return Sequence(
        'small_gicp_pair',
        [folder / 'target.ply', folder / 'source.ply'],
        None,
        pair_truth={0: T},
        note="small_gicp's own GICP result at 0.1 m voxels (good to ~0.2 deg / 2 cm)",
    )


def load_eth(folder: Path) -> Sequence:
    """An ETH "challenging data sets" sequence in its local-frame CSV form.

    ``Hokuyo_<i>.csv`` scans (header row naming x, y, z; read by
    :func:`kentreg_ros.io.read_scan`) ordered naturally, and ``pose_scanner_leica.csv``
    (``poseId, timestamp, T00..T33``, one row per scan, ``T_world_scanner``).

    Raises
    ------
    ValueError
        No Hokuyo scans, no pose file, or scan and pose counts differ.
    """
    folder = Path(folder)
    pose_file = folder / 'pose_scanner_leica.csv'
    if not pose_file.is_file():
        raise ValueError(f'{folder}: no pose_scanner_leica.csv.')
    paths = [
        p for p in list_scans(folder, suffixes=['.csv']) if p.name.lower().startswith('hokuyo_')
    ]
    if len(paths) < 2:
        raise ValueError(
            f'{folder}: expected at least two Hokuyo_<i>.csv scans, got {len(paths)}.'
        )
    poses = _orthonormal(read_poses(pose_file, format='eth'), str(pose_file))
    if len(poses) != len(paths):
        raise ValueError(
            f'{folder}: {len(paths)} Hokuyo scans but {len(poses)} poses in {pose_file.name}.'
        )
    return Sequence(
        f'eth:{folder.name}', paths, poses, note='ETH local-frame scans, Leica-tracked poses'
    )


def select_pairs(n_pairs: int, count: int | None) -> list[int]:
    """``count`` evenly spread pair indices of ``n_pairs`` (all when ``count`` is None)."""
    if count is None or count >= n_pairs:
        return list(range(n_pairs))
    return sorted({int(round(v)) for v in np.linspace(0, n_pairs - 1, max(count, 1))})


def errors(T_est: FloatArray, T_true: FloatArray) -> tuple[float, float]:
    """(e_R in degrees, e_t in metres) of the paper (kentreg_ros.eval.metrics.pair_errors)."""
    e_R, e_t = pair_errors(T_est[None], T_true[None])
    return float(e_R[0]), float(e_t[0])


def is_failure(e_R: float, e_t: float) -> bool:
    """e_R > 2 deg or e_t > 0.2 m, or a method that raised (NaN errors)."""
    return bool(failed_pairs(e_R, e_t))


def failure_mask(e_R: FloatArray, e_t: FloatArray) -> NDArray[np.bool_]:
    """:func:`is_failure` of arrays of errors, element by element (NaN counts as failed)."""
    return failed_pairs(e_R, e_t)


def summarize(records: Iterable[Mapping[str, float]]) -> dict[str, Any]:
    """Mean/median/p90/max of e_R, e_t, failure count and median time of per-pair records.

    Records with NaN errors (the method raised) count as failures and are left out of the
    error statistics (their count is ``n_errors``).
    """
    rows = list(records)
    e_R = np.array([r['e_R_deg'] for r in rows], dtype=np.float64)
    e_t = np.array([r['e_t_m'] for r in rows], dtype=np.float64)
    ms = np.array([r['ms'] for r in rows], dtype=np.float64)
    ok = np.isfinite(e_R) & np.isfinite(e_t)
    fails = sum(is_failure(a, b) for a, b in zip(e_R, e_t, strict=True))

    def stats(v: FloatArray) -> dict[str, float]:
        if not len(v):
            return dict.fromkeys(('mean', 'median', 'p90', 'max'), float('nan'))
        return {
            'mean': float(v.mean()),
            'median': float(np.median(v)),
            'p90': float(np.percentile(v, 90)),
            'max': float(v.max()),
        }

    return {
        'n': len(rows),
        'n_errors': int((~ok).sum()),
        'failures': int(fails),
        'failure_rate': fails / len(rows) if rows else float('nan'),
        'e_R_deg': stats(e_R[ok]),
        'e_t_m': stats(e_t[ok]),
        'ms': {
            'median': float(np.median(ms)) if len(ms) else float('nan'),
            'mean': float(ms.mean()) if len(ms) else float('nan'),
        },
    }


def timed(fn: Callable[..., Any], *args: Any) -> tuple[Any, float]:
    """``(fn(*args), milliseconds)``."""
    import time

    t0 = time.perf_counter()
    out = fn(*args)
    return out, (time.perf_counter() - t0) * 1e3


def git_describe() -> str | None:
    """``git describe --always`` of the repository, ``-dirty`` when a file other than the
    benchmark results differs from it (an earlier benchmark of the same run writing its results
    does not make the code dirty); None outside a checkout."""

    def git(*args: str) -> str:
        return subprocess.run(
            ['git', *args], cwd=ROOT, capture_output=True, text=True, check=False
        ).stdout.strip()

    try:
        out = git('describe', '--always')
        changed = git('status', '--porcelain', '--', '.', ':(exclude)benchmarks/results')
    except OSError:
        return None
    if not out:
        return None
    return f'{out}-dirty' if changed else out


def machine_info() -> dict[str, Any]:
    """CPU, cores, Python and library versions, git commit, date (for every results file)."""
    cpu = platform.processor() or ''
    try:
        for line in Path('/proc/cpuinfo').read_text().splitlines():
            if line.startswith('model name'):
                cpu = line.split(':', 1)[1].strip()
                break
    except OSError:
        pass
    versions = {}
    for mod in ('numpy', 'scipy', 'open3d', 'small_gicp', 'kiss_icp'):
        try:
            from importlib.metadata import version

            dist = {'open3d': 'open3d-cpu', 'small_gicp': 'small_gicp', 'kiss_icp': 'kiss-icp'}
            versions[mod] = version(dist.get(mod, mod))
        except Exception:  # a missing library is reported as such
            versions[mod] = None
    commit = os.environ.get('KENTREG_GIT_COMMIT', '')  # set when running from a `git archive`
    try:
        commit = (
            commit
            or subprocess.run(
                ['git', '-C', str(ROOT), 'rev-parse', '--short', 'HEAD'],
                capture_output=True,
                text=True,
                check=False,
            ).stdout.strip()
        )
    except OSError:
        commit = ''
    return {
        'git': git_describe(),
        'cpu': cpu,
        'cores': os.cpu_count(),
        'cores_used': len(os.sched_getaffinity(0)),
        'load_avg_at_start': list(os.getloadavg()),
        'machine': platform.machine(),
        'system': f'{platform.system()} {platform.release()}',
        'python': platform.python_version(),
        'versions': versions,
        'git_commit': commit,
        'date': datetime.datetime.now(datetime.UTC).isoformat(timespec='seconds'),
    }


def write_json(path: Path, data: Any) -> None:
    """Write ``data`` as indented JSON (numpy values as Python values, NaN written as null)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(jsonable(data), indent=1) + '\n')


def fmt(value: Any, spec: str) -> str:
    """Format a number for a markdown table ('–' for None/NaN)."""
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return '–'
    return format(value, spec)
