"""``kentreg_replay``: offline odometry over a bag or a scan folder, with evaluation and a plot.

Every scan is processed, in order, at CPU speed (none is dropped), by the same
:class:`~kentreg_ros.core.odometry.Odometry` the ROS node runs. Then the run is written out and,
when ground truth is known, evaluated. ``--stride N`` processes only every N-th scan (``start,
start + N, ...``), keeping their stamps: a frame-skipping stress test in which the odometry sees
N times the gaps and the evaluation joins consecutive *processed* scans.

Examples
--------
The sample recording (BALM, 50 real scans with reference poses on ``/ground_truth``)::

    kentreg_replay bags/balm_50

A scan folder with its pose file found beside the scans, the paper's recipe, 10 scans::

    kentreg_replay ../shared/data/balm --set mode=paper --max-scans 10

Every third scan of the sample (scans 0, 3, 6, ...; three times the motion per pair)::

    kentreg_replay bags/balm_50 --stride 3

Outputs in ``--out`` (default ``results/<timestamp>/``, with ``results/latest`` pointing there)
-------------------------------------------------------------------------------------------------
``odometry.mcap``
    One MCAP file (``ros2 bag play``, Foxglove): per scan a nav_msgs/Odometry on
    ``/kentreg/odometry``, a geometry_msgs/PoseStamped on ``/kentreg/pose`` and a
    tf2_msgs/TFMessage on ``/tf`` (``odom`` -> sensor frame), header stamps from the input
    scans; at the end one nav_msgs/Path on ``/kentreg/path``.
``poses_tum.txt``, ``poses_kitti.txt``
    The trajectory ``T_odom_lidar`` (TUM with the scan stamps: ``evo_ape tum``).
``ground_truth_tum.txt``
    With ground truth: the reference poses associated with the scans (TUM), for evo.
``config.yaml``
    The effective configuration (loadable by ``--config`` and by the node).
``metrics.json``
    Health counts, timings, per-scan steps and, with ground truth, the metrics below.
``trajectory.png``
    Top view of the estimate (aligned onto the ground truth when known) and per-pair errors.

Metrics (with ``--gt POSES`` or a ``/ground_truth`` topic in the bag)
----------------------------------------------------------------------
Per consecutive pair, the errors of Fahandezh-Saadi et al.: ``e_R = arccos((tr(R^T R_est) - 1)
/ 2)`` and ``e_t = ||t_est - t||`` (a pair *fails* when ``e_R > 2 deg`` or ``e_t > 0.2 m``);
RPE per frame and per metre travelled; ATE after SE(3) (Umeyama) alignment; and the KITTI
segment metric when the run is long enough to fill its 100 m segments. See
:mod:`kentreg_ros.eval.metrics`.

Exit status: 0 on success, 2 on bad input (one line on stderr), 130 when interrupted (the scans
processed so far are still written out).
"""

from __future__ import annotations

import argparse
import datetime
import itertools
import json
import logging
import os
import shutil
import sys
import time
from collections.abc import Generator, Iterator, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kentreg_ros import __version__
from kentreg_ros.cli_args import non_negative_int, positive_int
from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.errors import KentRegError
from kentreg_ros.core.odometry import HEALTHS, Odometry, OdometryStep
from kentreg_ros.eval import kitti, metrics
from kentreg_ros.io.params import dump_config, load_config

logger = logging.getLogger('kentreg_ros.replay')  # also when run as __main__

PROG = 'kentreg_replay'
EXIT_OK = 0
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130

ODOMETRY_TOPIC = '/kentreg/odometry'
POSE_TOPIC = '/kentreg/pose'
PATH_TOPIC = '/kentreg/path'
TF_TOPIC = '/tf'
GROUND_TRUTH_TOPIC = '/ground_truth'

#: Largest stamp difference for a scan and a ground-truth pose to be associated.
GT_TOLERANCE_S = 0.01
#: File names of pose files looked for beside the scans of a folder.
POSE_FILES_BESIDE_SCANS = ('alidarPose.csv', 'pose_scanner_leica.csv', 'poses.csv')

FloatArray = NDArray[np.float64]


class InputError(Exception):
    """Bad command-line input; the message is shown as one line and the exit code is 2."""


class _ArgumentParser(argparse.ArgumentParser):
    def error(self, message: str) -> Any:
        raise InputError(message)


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface of ``kentreg_replay``."""
    parser = _ArgumentParser(
        prog=PROG,
        description='Run kentreg odometry over a bag or a scan folder; write the trajectory '
        '(MCAP, TUM, KITTI), the metrics against ground truth and a plot.',
    )
    parser.add_argument(
        'input',
        metavar='BAG_OR_FOLDER',
        help='rosbag2 folder or .mcap/.db3/.bag file with one PointCloud2 topic (or --topic), '
        'or a folder of scan files (.pcd, .ply, .bin, .csv) in natural order',
    )
    parser.add_argument('--topic', help='PointCloud2 topic, when the bag has several')
    parser.add_argument(
        '--config',
        type=Path,
        help="parameter file (the node's YAML, e.g. config/kentreg.yaml); default: the "
        'built-in defaults, which that file repeats',
    )
    parser.add_argument(
        '--set',
        dest='overrides',
        action='append',
        default=[],
        metavar='KEY=VALUE',
        help='override one parameter, e.g. --set mode=paper --set odometry.constant_velocity='
        'false (repeatable)',
    )
    parser.add_argument(
        '--out',
        type=Path,
        help='output folder (default: results/<timestamp>/, and results/latest points to it)',
    )
    parser.add_argument(
        '--gt',
        type=Path,
        metavar='POSES',
        help='ground-truth poses (TUM, KITTI, BALM alidarPose.csv, ETH pose_scanner_leica.csv); '
        f"default: the bag's {GROUND_TRUTH_TOPIC} topic, or a pose file beside the scans",
    )
    parser.add_argument(
        '--gt-topic',
        default=GROUND_TRUTH_TOPIC,
        help=f'ground-truth topic of the bag (default {GROUND_TRUTH_TOPIC})',
    )
    parser.add_argument(
        '--max-scans', type=positive_int, metavar='N', help='process N scans (after --stride)'
    )
    parser.add_argument(
        '--start', type=non_negative_int, default=0, metavar='N', help='skip the first N scans'
    )
    parser.add_argument(
        '--stride',
        type=positive_int,
        default=1,
        metavar='N',
        help='process every N-th scan only (start, start+N, ...), stamps unchanged: a '
        'frame-skipping stress test; pairs and metrics join consecutive processed scans '
        '(default 1: every scan)',
    )
    parser.add_argument(
        '--odom-frame', default='odom', help='frame of the output poses (default odom)'
    )
    parser.add_argument(
        '--child-frame',
        help="child frame of the output poses (default: the scans' sensor frame; the lidar "
        'pose is written as is, so give base_link only if the two frames coincide)',
    )
    parser.add_argument('--no-plot', action='store_true', help='do not write trajectory.png')
    parser.add_argument('--no-progress', action='store_true', help='no progress bar')
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument('-v', '--verbose', action='store_true', help='log every step')
    verbosity.add_argument('-q', '--quiet', action='store_true', help='log errors only')
    parser.add_argument('--version', action='version', version=f'%(prog)s {__version__}')
    return parser


# --------------------------------------------------------------------------------------------
# Configuration and inputs


def effective_config(path: Path | None, overrides: Sequence[str]) -> KentRegConfig:
    """The configuration of a run: a parameter file (or the defaults) plus ``KEY=VALUE`` items.

    Raises
    ------
    ConfigError
        Unreadable file, unknown key or invalid value.
    InputError
        An override without ``=``.
    """
    import yaml

    cfg = load_config(path) if path is not None else KentRegConfig()
    updates: dict[str, Any] = {}
    for item in overrides:
        key, sep, text = item.partition('=')
        if not sep or not key.strip():
            raise InputError(f'--set expects KEY=VALUE, got {item!r}')
        try:
            updates[key.strip()] = yaml.safe_load(text) if text.strip() else ''
        except yaml.YAMLError:
            updates[key.strip()] = text
    return cfg.with_updates(updates) if updates else cfg


@dataclass
class GroundTruth:
    """Reference poses and where they came from."""

    trajectory: Any  # kentreg_ros.io.poses.Trajectory
    origin: str

    def __post_init__(self) -> None:
        self.trajectory = orthonormalize(self.trajectory, self.origin)


def orthonormalize(trajectory: Any, origin: str) -> Any:
    """The trajectory with every rotation block replaced by the nearest rotation (SVD).

    Pose files print rotations with few decimals (BALM: 6), so ``R^T R`` misses the identity by
    up to about 1e-6. The pair error ``arccos((tr(R^T R_est) - 1) / 2)`` of a 0.04 deg error
    compares ``1 - cos`` values of about 2.4e-7, so unprojected rotations would dominate it.
    """
    T = np.array(trajectory.T_world_sensor, dtype=np.float64)
    U, _, Vt = np.linalg.svd(T[:, :3, :3])
    fix = np.ones((len(T), 3))
    fix[:, 2] = np.sign(np.linalg.det(U @ Vt))
    R = (U * fix[:, None, :]) @ Vt
    deviation = float(np.abs(R - T[:, :3, :3]).max()) if len(T) else 0.0
    if deviation > 1e-9:
        logger.info(
            'Projected the rotations of %s onto SO(3) (max change %.1e).', origin, deviation
        )
    T[:, :3, :3] = R
    return type(trajectory)(trajectory.stamps_ns, T)


def _pose_file_beside(folder: Path) -> Path | None:
    for name in POSE_FILES_BESIDE_SCANS:
        for candidate in (folder / name, folder / name.lower()):
            if candidate.is_file():
                return candidate
    return None


def open_input(args: argparse.Namespace) -> tuple[Any, GroundTruth | None]:
    """Open the scan source and find the ground truth (``--gt``, bag topic, file beside scans).

    Returns
    -------
    source : kentreg_ros.io.bags.ScanSource
    ground_truth : GroundTruth or None
    """
    from kentreg_ros.io.bags import bag_topics, is_bag, open_scan_source, read_ground_truth
    from kentreg_ros.io.poses import read_poses

    path = Path(args.input)
    if not path.exists():
        raise InputError(f'{path}: no such file or folder')
    gt: GroundTruth | None = None
    if args.gt is not None:
        if not args.gt.is_file():
            raise InputError(f'--gt {args.gt}: no such file')
        gt = GroundTruth(read_poses(args.gt), str(args.gt))
    if is_bag(path):
        source = open_scan_source(path, topic=args.topic, fields=())
        if gt is None:
            try:
                gt = GroundTruth(read_ground_truth(path, topic=args.gt_topic), args.gt_topic)
            except KentRegError as exc:
                # A bag without the topic is common (logged quietly); an unreadable topic is
                # worth a warning, but the odometry can still run.
                missing = args.gt_topic not in bag_topics(path)
                level = logging.INFO if missing else logging.WARNING
                logger.log(level, 'No ground truth from the bag: %s', _one_line(exc))
        return source, gt
    if args.topic is not None:
        raise InputError(f'--topic applies to bags; {path} is not a bag')
    if gt is None and path.is_dir():
        beside = _pose_file_beside(path)
        if beside is not None:
            try:
                gt = GroundTruth(read_poses(beside), str(beside))
                logger.info('Ground truth: %s (found beside the scans).', beside)
            except KentRegError as exc:
                logger.warning('Ignoring %s: %s', beside, exc)
    poses = None
    if gt is not None and gt.trajectory.stamps_ns is not None and path.is_dir():
        from kentreg_ros.io.scanfiles import list_scans

        if len(list_scans(path)) == len(gt.trajectory.T_world_sensor):
            poses = gt.trajectory  # one pose per scan: its times stamp the scans
    return open_scan_source(path, fields=(), poses=poses), gt


# --------------------------------------------------------------------------------------------
# The run


@dataclass
class ReplayRun:
    """What the odometry did with the scans of one input."""

    steps: list[OdometryStep] = field(default_factory=list)
    input_indices: list[int] = field(default_factory=list)
    read_ms: list[float] = field(default_factory=list)
    elapsed_s: float = 0.0
    interrupted: bool = False
    error: str | None = None

    @property
    def poses(self) -> FloatArray:
        if not self.steps:
            return np.zeros((0, 4, 4))
        return np.stack([s.T_world_lidar for s in self.steps])

    @property
    def stamps_ns(self) -> NDArray[np.int64]:
        return np.array([s.stamp_ns for s in self.steps], dtype=np.int64)


def _progress_bar(total: int | None, enabled: bool) -> Any:
    if not enabled:
        return None
    try:
        from tqdm import tqdm
    except ImportError:
        logger.info('tqdm is not installed: no progress bar (pip install tqdm).')
        return None
    return tqdm(
        total=total,
        unit='scan',
        desc=PROG,
        file=sys.stderr,
        dynamic_ncols=True,
        mininterval=0.5,
        leave=True,
    )


def _logging_redirect(bar: Any) -> AbstractContextManager[Any]:
    if bar is None:
        return nullcontext()
    from tqdm.contrib.logging import logging_redirect_tqdm

    return logging_redirect_tqdm(loggers=[logging.getLogger('kentreg_ros')])


def run_odometry(
    source: Any,
    odometry: Odometry,
    *,
    start: int = 0,
    max_scans: int | None = None,
    stride: int = 1,
    progress: bool = True,
) -> ReplayRun:
    """Feed the scans ``start, start + stride, ...`` of ``source`` (at most ``max_scans``).

    The scans in between are read and skipped (a bag is sequential); the processed scans keep
    their own stamps, so the odometry sees ``stride`` times the gaps. ``max_scans`` counts
    processed scans, and :attr:`ReplayRun.input_indices` records which input scans they were.

    A read error in the middle of the input (a damaged bag) ends the run early; the scans read
    before it are kept and the error is recorded in :attr:`ReplayRun.error`. Ctrl-C does the
    same with :attr:`ReplayRun.interrupted`.

    Raises
    ------
    InputError
        ``start`` beyond the input, or ``stride`` < 1.
    """
    if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
        raise InputError(f'--stride: expected a positive integer (>= 1), got {stride!r}')
    run = ReplayRun()
    n_total = len(source)
    if start >= n_total:
        raise InputError(f'--start {start}: the input has only {n_total} scans')
    indices = range(start, n_total, stride)
    if max_scans is not None:
        indices = indices[:max_scans]
    reader: Iterator[Any] = iter(source)
    scans = itertools.islice(reader, indices.start, indices.stop, indices.step)
    bar = _progress_bar(len(indices), progress)
    t_run = time.perf_counter()
    try:
        with _logging_redirect(bar):
            for index in indices:
                t0 = time.perf_counter()
                try:
                    scan = next(scans)
                except StopIteration:
                    break
                except KentRegError as exc:
                    run.error = _one_line(exc)
                    break
                run.read_ms.append((time.perf_counter() - t0) * 1e3)
                step = odometry.step(scan.points, scan.stamp_ns, frame_id=scan.frame_id)
                run.steps.append(step)
                run.input_indices.append(index)
                if bar is not None:
                    bar.update(1)
                    if odometry.n_failed:
                        bar.set_postfix(failed=odometry.n_failed, refresh=False)
                logger.debug(
                    'Scan %d: %s in %.0f ms (%s)',
                    index,
                    step.health,
                    step.timings['total'],
                    step.message,
                )
    except KeyboardInterrupt:
        run.interrupted = True
    finally:
        if bar is not None:
            bar.close()
        if isinstance(reader, Generator):
            reader.close()  # close the bag now, not at garbage collection
    run.elapsed_s = time.perf_counter() - t_run
    return run


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


# --------------------------------------------------------------------------------------------
# Evaluation


def associate(
    stamps_ns: NDArray[np.int64],
    input_indices: Sequence[int],
    ground_truth: Any,
    *,
    tolerance_s: float = GT_TOLERANCE_S,
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Pair scans with ground-truth poses: by nearest stamp, or by scan index without stamps.

    Returns
    -------
    scan_rows : ndarray of int, shape (M,)
        Rows of the run's steps that have a reference pose.
    gt_rows : ndarray of int, shape (M,)
        The matching rows of ``ground_truth.T_world_sensor``.
    """
    n_gt = len(ground_truth.T_world_sensor)
    if ground_truth.stamps_ns is None:
        idx = np.asarray(input_indices, dtype=np.intp)
        keep = idx < n_gt
        return np.flatnonzero(keep), idx[keep]
    gt_stamps = np.asarray(ground_truth.stamps_ns, dtype=np.int64)
    order = np.argsort(gt_stamps, kind='stable')
    sorted_stamps = gt_stamps[order]
    pos = np.clip(np.searchsorted(sorted_stamps, stamps_ns), 1, max(len(sorted_stamps) - 1, 1))
    left = sorted_stamps[pos - 1]
    right = sorted_stamps[np.minimum(pos, len(sorted_stamps) - 1)]
    use_left = np.abs(stamps_ns - left) <= np.abs(right - stamps_ns)
    nearest = np.where(use_left, pos - 1, np.minimum(pos, len(sorted_stamps) - 1))
    diff = np.abs(sorted_stamps[nearest] - stamps_ns)
    keep = diff <= int(tolerance_s * 1e9)
    return np.flatnonzero(keep), order[nearest[keep]]


def evaluate(T_est: FloatArray, T_gt: FloatArray) -> dict[str, Any]:
    """Pair errors, RPE (per frame, per metre), ATE (SE(3)) and, if long enough, KITTI.

    Parameters
    ----------
    T_est, T_gt : ndarray, shape (M, 4, 4)
        Associated estimated and reference poses ``T_world_lidar``, ``M >= 2``.

    Returns
    -------
    dict
        JSON-ready (arrays as lists); ``ate`` is None below 3 poses and ``kitti`` None when the
        run does not fill a 100 m segment (``kitti_note`` says why).
    """
    e_R, e_t = metrics.pair_errors(metrics.relative_poses(T_est), metrics.relative_poses(T_gt))
    failed = metrics.failed_pairs(e_R, e_t)
    out: dict[str, Any] = {
        'n_poses': len(T_est),
        'pairs': {
            'count': len(e_R),
            'rotation_deg': metrics.summarize(e_R),
            'translation_m': metrics.summarize(e_t),
            'n_failed': int(failed.sum()),
            'failed_if': (
                f'e_R > {metrics.FAIL_ROTATION_DEG} deg or e_t > {metrics.FAIL_TRANSLATION_M} m'
            ),
            'failed_pairs': np.flatnonzero(failed).tolist(),
            'e_R_deg': e_R.tolist(),
            'e_t_m': e_t.tolist(),
        },
    }
    result = metrics.rpe(T_est, T_gt, delta=1)
    out['rpe'] = {
        'delta': 1,
        'rotation_deg': result['rotation_deg'],
        'translation_m': result['translation_m'],
    }
    per_metre = metrics.rpe_per_metre(T_est, T_gt, delta=1)
    out['rpe_per_metre'] = {
        'delta': 1,
        'min_distance_m': per_metre['min_distance'],
        'n_skipped': per_metre['n_skipped'],
        'translation_pct': per_metre['translation_pct'],
    }
    gt_distance = float(np.sum(np.linalg.norm(np.diff(T_gt[:, :3, 3], axis=0), axis=1)))
    out['gt_distance_m'] = gt_distance
    out['ate'] = None
    if len(T_est) >= 3:
        ate = metrics.ate(T_est, T_gt, align=True)
        out['ate'] = {
            'alignment': 'SE(3)',
            'count': ate['count'],
            'mean': ate['mean'],
            'median': ate['median'],
            'rmse': ate['rmse'],
            'p95': ate['p95'],
            'max': ate['max'],
            'T_gt_est': ate['T_gt_est'].tolist(),
        }
    segments = kitti.kitti_segment_errors(T_est, T_gt)
    out['kitti'] = None
    if segments is None:
        out['kitti_note'] = (
            f'not computed: {gt_distance:.2f} m of ground truth, shorter than a '
            f'{kitti.KITTI_LENGTHS[0]:g} m segment'
        )
    else:
        out['kitti'] = {
            't_err_pct': segments['t_err_pct'],
            'r_err_deg_per_100m': 100.0 * segments['r_err_deg_per_m'],
            'n_segments': segments['n_segments'],
            'lengths_m': list(segments['per_length']),
        }
    return out


def speed_summary(run: ReplayRun) -> dict[str, Any]:
    """Milliseconds per scan (mean, p95, ...), registration and read times, scans per second."""
    total = np.array([s.timings['total'] for s in run.steps])
    register = np.array([s.timings['register'] for s in run.steps if 'register' in s.timings])
    return {
        'n_scans': len(run.steps),
        'ms_per_scan': metrics.summarize(total),
        'register_ms_per_pair': metrics.summarize(register),
        'preprocess_ms_per_scan': metrics.summarize(
            [s.timings.get('preprocess', 0.0) for s in run.steps]
        ),
        'read_ms_per_scan': metrics.summarize(run.read_ms),
        'wall_s': run.elapsed_s,
        'scans_per_s': len(run.steps) / run.elapsed_s if run.elapsed_s > 0 else float('nan'),
    }


def _step_record(step: OdometryStep, input_index: int) -> dict[str, Any]:
    rec: dict[str, Any] = {
        'index': step.index,
        'input_index': input_index,
        'stamp_ns': step.stamp_ns,
        'health': step.health,
        'message': step.message,
        'timings_ms': {k: round(v, 3) for k, v in step.timings.items()},
        'n_points': step.n_points,
        'n_prepared': step.n_prepared,
        'fit': step.fit if np.isfinite(step.fit) else None,
        'searched': step.searched,
    }
    if step.result is not None:
        rec.update(
            status=step.result.status,
            iterations=step.result.iterations,
            inlier_fraction=step.result.inlier_fraction,
        )
    return rec


# --------------------------------------------------------------------------------------------
# Outputs


def default_out_dir(root: Path = Path('results')) -> Path:
    """``results/<YYYYmmdd-HHMMSS>`` (with ``-2``, ``-3``, ... if taken)."""
    stamp = datetime.datetime.now().strftime('%Y%m%d-%H%M%S')
    out = root / stamp
    n = 2
    while out.exists():
        out = root / f'{stamp}-{n}'
        n += 1
    return out


def _link_latest(out: Path) -> None:
    link = out.parent / 'latest'
    tmp = out.parent / f'.latest-{os.getpid()}'
    try:
        if tmp.is_symlink():
            tmp.unlink()
        tmp.symlink_to(out.name, target_is_directory=True)
        os.replace(tmp, link)
    except OSError as exc:
        logger.warning('Cannot point %s at %s: %s', link, out, exc)


def write_odometry_mcap(
    path: Path,
    steps: Sequence[OdometryStep],
    *,
    odom_frame: str,
    child_frame: str,
) -> dict[str, int]:
    """Write the run as one MCAP file; return the message count per topic.

    Per scan: nav_msgs/Odometry (with the chained pose covariance), geometry_msgs/PoseStamped
    and the ``odom_frame`` -> ``child_frame`` transform on ``/tf``, stamped with the scan's
    header stamp; then one nav_msgs/Path of every pose.
    """
    from kentreg_ros.io.bagwriter import BagWriter

    tmp = path.parent / f'.{path.stem}-{os.getpid()}'
    if tmp.exists():
        shutil.rmtree(tmp)
    with BagWriter(tmp, compress=True) as writer:
        for step in steps:
            writer.write_odometry(
                ODOMETRY_TOPIC,
                step.stamp_ns,
                step.T_world_lidar,
                frame_id=odom_frame,
                child_frame_id=child_frame,
                pose_covariance=step.covariance,
            )
            writer.write_pose(POSE_TOPIC, step.stamp_ns, step.T_world_lidar, frame_id=odom_frame)
            writer.write_transform(
                step.stamp_ns,
                step.T_world_lidar,
                frame_id=odom_frame,
                child_frame_id=child_frame,
                topic=TF_TOPIC,
            )
        if steps:
            writer.write_path(
                PATH_TOPIC,
                steps[-1].stamp_ns,
                [s.stamp_ns for s in steps],
                np.stack([s.T_world_lidar for s in steps]),
                frame_id=odom_frame,
            )
        counts = dict(writer.counts)
    # A single self-contained MCAP file: rosbag2 (ros2 bag play/info) and Foxglove open it as is.
    os.replace(writer.mcap_path, path)
    shutil.rmtree(tmp)
    return counts


def jsonable(value: Any) -> Any:
    """``value`` with numpy scalars/arrays as Python values and NaN/inf as None (JSON-ready)."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, np.generic):
        return jsonable(value.item())
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


@dataclass
class Evaluation:
    """Ground-truth comparison of a run (rows of the run's steps and of the reference)."""

    scan_rows: NDArray[np.intp]
    T_gt: FloatArray
    stamps_ns: NDArray[np.int64]
    metrics: dict[str, Any]


def evaluate_run(run: ReplayRun, gt: GroundTruth | None) -> tuple[Evaluation | None, str]:
    """Associate the run with the ground truth and evaluate; '' or why it was not evaluated."""
    if gt is None:
        return None, 'no ground truth (give --gt POSES, or a bag with /ground_truth)'
    scan_rows, gt_rows = associate(run.stamps_ns, run.input_indices, gt.trajectory)
    if len(scan_rows) < 2:
        return None, (
            f'{len(scan_rows)} of {len(run.steps)} scans matched a pose of {gt.origin} '
            f'(stamps within {GT_TOLERANCE_S * 1e3:g} ms); need 2'
        )
    T_gt = np.asarray(gt.trajectory.T_world_sensor, dtype=np.float64)[gt_rows]
    result = evaluate(run.poses[scan_rows], T_gt)
    result['source'] = gt.origin
    result['n_matched'] = len(scan_rows)
    if len(scan_rows) < len(run.steps):
        logger.warning(
            'Only %d of %d scans have a ground-truth pose in %s; pairs join consecutive '
            'matched scans.',
            len(scan_rows),
            len(run.steps),
            gt.origin,
        )
    return Evaluation(scan_rows, T_gt, run.stamps_ns[scan_rows], result), ''


def write_outputs(
    out: Path,
    run: ReplayRun,
    cfg: KentRegConfig,
    evaluation: Evaluation | None,
    report: dict[str, Any],
    *,
    odom_frame: str,
    child_frame: str,
    plot: bool,
    title: str,
) -> list[str]:
    """Write every output file into ``out``; return the names written."""
    from kentreg_ros.io.poses import write_kitti, write_tum

    out.mkdir(parents=True, exist_ok=True)
    written = []
    counts = write_odometry_mcap(
        out / 'odometry.mcap', run.steps, odom_frame=odom_frame, child_frame=child_frame
    )
    report['odometry_mcap'] = {
        'topics': counts,
        'odom_frame': odom_frame,
        'child_frame': child_frame,
    }
    written.append('odometry.mcap')
    write_tum(out / 'poses_tum.txt', run.stamps_ns, run.poses)
    write_kitti(out / 'poses_kitti.txt', run.poses)
    written += ['poses_tum.txt', 'poses_kitti.txt']
    if evaluation is not None:
        write_tum(out / 'ground_truth_tum.txt', evaluation.stamps_ns, evaluation.T_gt)
        written.append('ground_truth_tum.txt')
    (out / 'config.yaml').write_text(dump_config(cfg))
    written.append('config.yaml')
    if plot and run.steps:
        png = _plot(out / 'trajectory.png', run, evaluation, title)
        if png:
            written.append('trajectory.png')
    report['files'] = written + ['metrics.json']
    (out / 'metrics.json').write_text(json.dumps(jsonable(report), indent=2) + '\n')
    written.append('metrics.json')
    return written


def _plot(path: Path, run: ReplayRun, evaluation: Evaluation | None, title: str) -> bool:
    try:
        from kentreg_ros.eval.plotting import plot_trajectory

        if evaluation is None:
            plot_trajectory(path, run.poses, title=title)
            return True
        ate = evaluation.metrics['ate']
        T_gt_est = np.asarray(ate['T_gt_est']) if ate is not None else np.eye(4)
        pairs = evaluation.metrics['pairs']
        plot_trajectory(
            path,
            T_gt_est @ run.poses[evaluation.scan_rows],
            evaluation.T_gt,
            e_R_deg=pairs['e_R_deg'],
            e_t=pairs['e_t_m'],
            title=title,
        )
        return True
    except ImportError as exc:
        logger.warning('No trajectory.png: %s (pip install matplotlib).', exc)
        return False


# --------------------------------------------------------------------------------------------
# Summary


def _fmt(value: Any, spec: str) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return '-'
    return format(value, spec)


def _stride_text(stride: int) -> str:
    """'stride 1 (every scan)' or 'stride 3 (one scan in 3)' for the summary and plot title."""
    return 'stride 1 (every scan)' if stride == 1 else f'stride {stride} (one scan in {stride})'


def format_summary(report: dict[str, Any], out: Path | None) -> str:
    """The short table printed at the end of a run."""
    speed = report['speed']
    health = report['health']
    lines = [
        f'{PROG}: {speed["n_scans"]} scans of {report["input"]["description"]}, '
        f'{_stride_text(report["input"].get("stride", 1))}, mode {report["mode"]}',
        '  health     '
        + ', '.join(f'{k} {health[k]}' for k in HEALTHS)
        + f' (start-free search on {report.get("n_searched", 0)} scans)',
        f'  speed      {_fmt(speed["ms_per_scan"]["mean"], ".1f")} ms/scan mean, '
        f'{_fmt(speed["ms_per_scan"]["p95"], ".1f")} ms p95, '
        f'{_fmt(speed["scans_per_s"], ".2f")} scans/s (wall, with reading)',
    ]
    gt = report.get('ground_truth')
    if gt is None:
        lines.append(f'  metrics    {report.get("ground_truth_note", "no ground truth")}')
    else:
        pairs = gt['pairs']
        rot, tra = pairs['rotation_deg'], pairs['translation_m']
        per_metre = gt['rpe_per_metre']['translation_pct']
        skipped = gt['rpe_per_metre']['n_skipped']
        min_distance = gt['rpe_per_metre']['min_distance_m']
        lines += [
            f'  vs ground truth ({gt["source"]}, {gt["n_matched"]} scans, '
            f'{gt["gt_distance_m"]:.2f} m travelled)',
            '                      median      mean       p95       max',
            '  pair e_R [deg] '
            + ''.join(f'{_fmt(rot[k], ".4f"):>10}' for k in ('median', 'mean', 'p95', 'max')),
            '  pair e_t [m]   '
            + ''.join(f'{_fmt(tra[k], ".4f"):>10}' for k in ('median', 'mean', 'p95', 'max')),
            f'  failed pairs   {pairs["n_failed"]} of {pairs["count"]} ({pairs["failed_if"]})',
            f'  RPE/frame      rmse {_fmt(gt["rpe"]["rotation_deg"]["rmse"], ".4f")} deg, '
            f'{_fmt(gt["rpe"]["translation_m"]["rmse"], ".4f")} m',
            '  RPE/metre      '
            + (
                f'median {per_metre["median"]:.2f} %, rmse {per_metre["rmse"]:.2f} % '
                f'({skipped} pairs under {min_distance:g} m skipped)'
                if per_metre['count']
                else f'not computed (every pair moved less than {min_distance:g} m)'
            ),
        ]
        ate = gt['ate']
        lines.append(
            '  ATE (SE(3))    '
            + (
                f'rmse {ate["rmse"]:.4f} m, max {ate["max"]:.4f} m'
                if ate is not None
                else 'not computed (fewer than 3 poses)'
            )
        )
        segments = gt['kitti']
        lines.append(
            '  KITTI          '
            + (
                f'{segments["t_err_pct"]:.2f} %, {segments["r_err_deg_per_100m"]:.3f} deg/100 m '
                f'({segments["n_segments"]} segments)'
                if segments is not None
                else gt['kitti_note']
            )
        )
    if out is not None:
        lines.append(f'  output     {out}/')
    return '\n'.join(lines)


# --------------------------------------------------------------------------------------------
# Entry point


def _configure_logging(verbose: bool, quiet: bool) -> logging.Handler:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(f'{PROG}: %(levelname)s: %(message)s'))
    package = logging.getLogger('kentreg_ros')
    package.addHandler(handler)
    package.setLevel(logging.DEBUG if verbose else logging.ERROR if quiet else logging.WARNING)
    return handler


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``kentreg_replay``; returns the exit status (see the module docstring)."""
    handler: logging.Handler | None = None
    try:
        args = build_parser().parse_args(argv)
        handler = _configure_logging(args.verbose, args.quiet)
        return _replay(args, argv)
    except (InputError, KentRegError, ValueError, OSError) as exc:
        print(f'{PROG}: error: {_one_line(exc)}', file=sys.stderr)
        return EXIT_BAD_INPUT
    finally:
        if handler is not None:
            logging.getLogger('kentreg_ros').removeHandler(handler)


def _replay(args: argparse.Namespace, argv: Sequence[str] | None) -> int:
    cfg = effective_config(args.config, args.overrides)
    source, gt = open_input(args)
    out = args.out if args.out is not None else default_out_dir()
    logger.info('Reading %s', source.description)
    run = run_odometry(
        source,
        Odometry(cfg),
        start=args.start,
        max_scans=args.max_scans,
        stride=args.stride,
        progress=not args.no_progress,
    )
    if not run.steps:
        raise InputError(run.error or f'{args.input}: no scan was read')
    child_frame = args.child_frame or run.steps[0].frame_id or 'base_link'
    evaluation, note = evaluate_run(run, gt)
    health = {k: sum(s.health == k for s in run.steps) for k in HEALTHS}
    report: dict[str, Any] = {
        'kentreg_version': __version__,
        'command': [PROG, *(sys.argv[1:] if argv is None else argv)],
        'input': {
            'path': str(args.input),
            'description': source.description,
            'start': args.start,
            'stride': args.stride,
            'n_scans': len(run.steps),
            'n_nonfinite_dropped': int(getattr(source, 'n_dropped', 0)),
            'frame_id': run.steps[0].frame_id,
        },
        'mode': cfg.mode,
        'config': str(args.config) if args.config else 'defaults',
        'overrides': list(args.overrides),
        'complete': not run.interrupted and run.error is None,
        'error': run.error,
        'health': health,
        'n_failed_steps': health['fell_back'] + health['rejected'],
        'n_searched': sum(s.searched for s in run.steps),
        'speed': speed_summary(run),
    }
    if evaluation is not None:
        report['ground_truth'] = evaluation.metrics
    else:
        report['ground_truth'] = None
        report['ground_truth_note'] = note
    report['steps'] = [
        _step_record(s, i) for s, i in zip(run.steps, run.input_indices, strict=True)
    ]
    title = f'kentreg ({cfg.mode}): {Path(args.input).name}'
    if args.stride > 1:
        title += f', {_stride_text(args.stride)}'
    write_outputs(
        out,
        run,
        cfg,
        evaluation,
        report,
        odom_frame=args.odom_frame,
        child_frame=child_frame,
        plot=not args.no_plot,
        title=title,
    )
    if args.out is None:
        _link_latest(out)
    print(format_summary(report, out))
    if run.error is not None:
        print(
            f'{PROG}: error: {run.error} (results of the {len(run.steps)} scans read are in '
            f'{out}/)',
            file=sys.stderr,
        )
        return EXIT_BAD_INPUT
    if run.interrupted:
        print(f'{PROG}: interrupted after {len(run.steps)} scans', file=sys.stderr)
        return EXIT_INTERRUPTED
    return EXIT_OK


if __name__ == '__main__':
    sys.exit(main())
