"""The datasets registry: a name (or a path) in; raw scans, stamps and reference poses out.

:func:`load_dataset` names: ``balm`` (``../shared/data/balm``, 50 raw BALM scans), ``balm_50``
(the sample bag ``bags/balm_50``), ``balm_or_sample`` (the first when present),
``small_gicp_pair``, ``kitti_raw_hdl64`` (no poses), ``eth:<folder>`` (Pomerleau et al. 2012,
local-frame CSV), ``simulated:<step>:<seed>`` (``harness/simulator.py``, exact poses), and any
path ``kentreg_replay`` reads (a bag with ``/ground_truth``, a scan folder with a pose file).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core import drop_nonfinite, project_to_so3
from kentreg_ros.eval import GroundTruth, associate, orthonormalize
from kentreg_ros.io import list_scans, read_poses, read_scan
from kentreg_ros.io.sources import Scan

FloatArray = NDArray[np.float64]

ROOT = Path(__file__).resolve().parents[2]
SHARED_DATA = Path(os.environ.get('KENTREG_SHARED_DATA', ROOT.parent / 'shared' / 'data'))
SAMPLE_BAG = ROOT / 'bags' / 'balm_50'


@dataclass
class Sequence:
    """Raw scans (sensor frame, non-finite points dropped, extra fields kept) and reference
    ``T_world_lidar`` (N, 4, 4) per scan, or None. Pair ``i`` is target scan ``i``, source scan
    ``i + 1``; ``pair_truth`` overrides the poses of some pairs (single-pair data sets).
    ``note`` says where the reference comes from, ``description`` what was read."""

    name: str
    scans: list[Scan]
    T_world: FloatArray | None
    note: str = ''
    description: str = ''
    pair_truth: dict[int, FloatArray] = field(default_factory=dict)
    paths: list[Path] = field(default_factory=list)

    @property
    def n_pairs(self) -> int:
        return len(self.scans) - 1

    def raw(self, index: int) -> FloatArray:
        """The raw points (N, 3) of scan ``index`` as float64."""
        return np.asarray(self.scans[index].points, dtype=np.float64)

    def relative(self, target: int, source: int) -> FloatArray:
        """Reference ``T_target_source`` between two scans."""
        if self.T_world is None:
            raise ValueError(f'{self.name}: no reference poses.')
        return np.asarray(np.linalg.inv(self.T_world[target]) @ self.T_world[source])

    def truth(self, pair: int) -> FloatArray:
        """True ``T_target_source`` of pair ``pair``."""
        return self.pair_truth[pair] if pair in self.pair_truth else self.relative(pair, pair + 1)

    def constant_velocity(self, pair: int) -> FloatArray:
        """The previous pair's true motion (a constant-velocity prior); identity for pair 0."""
        return np.eye(4) if pair == 0 or self.T_world is None else self.truth(pair - 1)


def _file_scans(paths: list[Path], period_s: float = 0.1) -> list[Scan]:
    """Scans read from files (x, y, z; non-finite points dropped), stamped every ``period_s``."""
    points = (drop_nonfinite(read_scan(p, fields=()).points)[0] for p in paths)
    return [Scan(int(round(i * period_s * 1e9)), 'lidar', p, {}) for i, p in enumerate(points)]


def load_recording(path: Path, *, name: str | None = None, topic: str | None = None) -> Sequence:
    """Every scan of a bag or scan folder, each with its reference pose associated by stamp,
    as ``kentreg_replay`` reads them (:func:`kentreg_ros.io.recordings.open_recording`)."""
    from kentreg_ros.io.recordings import open_recording

    source, reference, origin = open_recording(path, topic=topic, fields=None)
    if reference is None:
        raise ValueError(f'{path}: no reference poses (a pose file beside the scans or a bag)')
    gt = GroundTruth(reference, origin)
    scans = list(source)
    stamps = np.array([s.stamp_ns for s in scans], dtype=np.int64)
    rows, gt_rows = associate(stamps, list(range(len(scans))), gt.trajectory)
    if len(rows) != len(scans):
        raise ValueError(f'{path}: only {len(rows)} of {len(scans)} scans have a reference pose')
    T_world = np.asarray(gt.trajectory.T_world_sensor, dtype=np.float64)[gt_rows]
    return Sequence(name or Path(path).name, scans, T_world, gt.origin, source.description)


def load_balm(folder: Path = SHARED_DATA / 'balm') -> Sequence:
    """The 50 real BALM scans ``full0..49.pcd`` and ``alidarPose.csv``."""
    seq = load_recording(folder, name='balm')
    seq.note = 'BALM 2.0 real sequence; reference = LiDAR-inertial poses (the input of its BA)'
    seq.paths = list_scans(folder, suffixes=['.pcd'])
    return seq


def load_small_gicp_pair(folder: Path = SHARED_DATA / 'small_gicp_pair') -> Sequence:
    """The real small_gicp pair; scan 0 = target.ply, scan 1 = source.ply."""
    T = np.loadtxt(folder / 'T_target_source.txt').reshape(4, 4)
    T[:3, :3] = project_to_so3(T[:3, :3])
    paths = [folder / 'target.ply', folder / 'source.ply']
    note = "small_gicp's own GICP result at 0.1 m voxels (good to ~0.2 deg / 2 cm)"
    return Sequence('small_gicp_pair', _file_scans(paths), None, note, str(folder), {0: T}, paths)


def load_kitti_hdl64(folder: Path = SHARED_DATA / 'kitti_raw_hdl64') -> Sequence:
    """50 KITTI raw HDL-64E street frames at 10 Hz (no reference poses)."""
    paths = sorted(folder.glob('*.bin'))
    return Sequence('kitti_raw_hdl64', _file_scans(paths), None, '', str(folder), paths=paths)


def load_eth(folder: Path) -> Sequence:
    """An ETH "challenging data sets" sequence: ``Hokuyo_<i>.csv`` scans (natural order) and
    ``pose_scanner_leica.csv`` (``poseId, timestamp, T00..T33`` per scan, ``T_world_scanner``)."""
    folder = Path(folder)
    pose_file = folder / 'pose_scanner_leica.csv'
    if not pose_file.is_file():
        raise ValueError(f'{folder}: no pose_scanner_leica.csv.')
    scans = list_scans(folder, suffixes=['.csv'])
    paths = [p for p in scans if p.name.lower().startswith('hokuyo_')]
    if len(paths) < 2:
        raise ValueError(
            f'{folder}: expected at least two Hokuyo_<i>.csv scans, got {len(paths)}.'
        )
    poses = orthonormalize(read_poses(pose_file, format='eth'), str(pose_file)).T_world_sensor
    if len(poses) != len(paths):
        found = f'{len(paths)} Hokuyo scans but {len(poses)} poses'
        raise ValueError(f'{folder}: {found} in {pose_file.name}.')
    T = np.asarray(poses, dtype=np.float64)
    note = 'ETH local-frame scans, Leica-tracked poses'
    return Sequence(f'eth:{folder.name}', _file_scans(paths), T, note, str(folder), paths=paths)


_WORLDS: dict[float, Any] = {}


def load_simulated(step: float, seed: int, *, sweep_s: float = 0.0) -> Sequence:
    """The sample's scene re-simulated at ``step`` m per scan (exact poses)."""
    from .simulator import WORLD_VOXEL, Sensor, build_world, simulate

    if WORLD_VOXEL not in _WORLDS:
        _WORLDS[WORLD_VOXEL] = build_world(SAMPLE_BAG, WORLD_VOXEL)
    scans, gt = simulate(_WORLDS[WORLD_VOXEL], step, seed, Sensor(sweep_period=sweep_s))
    T = np.asarray(gt.trajectory.T_world_sensor, dtype=np.float64)
    return Sequence(f'simulated:{step}:{seed}', scans, T, gt.origin, 'simulated')


def default_balm() -> Path:
    """``../shared/data/balm`` when present, else the repository's ``bags/balm_50``."""
    return SHARED_DATA / 'balm' if (SHARED_DATA / 'balm').is_dir() else SAMPLE_BAG


#: Every named data set.
DATASETS: dict[str, Callable[[], Sequence]] = {
    'balm': load_balm,
    'balm_50': lambda: load_recording(SAMPLE_BAG, name='balm_50'),
    'balm_or_sample': lambda: load_recording(default_balm()),
    'small_gicp_pair': load_small_gicp_pair,
    'kitti_raw_hdl64': load_kitti_hdl64,
}


def load_dataset(name: str | Path) -> Sequence:
    """The data set of a registry name, ``eth:<folder>``, ``simulated:<step>:<seed>`` or a path."""
    text = str(name)
    kind, _, rest = text.partition(':')
    if text in DATASETS:
        return DATASETS[text]()
    if kind == 'eth':
        return load_eth(Path(rest))
    if kind == 'simulated':
        step, _, seed = rest.partition(':')
        return load_simulated(float(step), int(seed or 0))
    if Path(text).exists():
        return load_recording(Path(text))
    raise ValueError(f'Unknown data set {text!r}; names: {sorted(DATASETS)}, eth:, simulated:.')
