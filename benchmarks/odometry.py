"""Odometry benchmark: kentreg (previous scan and local map) against KISS-ICP and GICP
scan-to-scan, in one process run.

Four pipelines get the same scans (read once into memory, so no pipeline pays for reading) and
are evaluated against the same reference poses with the replay's own metrics
(:func:`kentreg_ros.eval.associate` and :func:`kentreg_ros.eval.evaluate`):

``kentreg``
    :class:`kentreg_ros.core.Odometry` with the configuration ``kentreg_replay`` uses (defaults,
    or ``--config`` / ``--set`` exactly as for the replay), run by
    :func:`kentreg_ros.eval.run_odometry`: scan-to-previous-scan, constant-velocity start.
``kentreg_local_map``
    The same with ``odometry.model = local_map`` (scan-to-local-map; every other setting as for
    ``kentreg``).
``kiss_icp``
    KISS-ICP's Python pipeline, ``kiss_icp.kiss_icp.KissICP``, configured by
    ``kiss_icp.config.load_config(None)`` as its own ``OdometryPipeline`` does: the default
    ``KISSConfig`` (``max_range`` 100 m, ``min_range`` 0 m, ``deskew`` on, adaptive threshold
    starting at 2 m) plus ``voxel_size = max_range / 100 = 1 m``. Only the thread count is set
    (``registration.max_num_threads = --threads``). Scan-to-local-map, constant-velocity start.
    Per-point times are passed when the input has a ``t``/``time``/``timestamp(s)`` field;
    otherwise (the BALM samples: x y z intensity only) an empty array, with which KISS-ICP's
    deskewing does nothing, as in its own pipeline for such clouds.
``gicp``
    small_gicp GICP scan-to-scan: previous scan as target (preprocessed once), constant-velocity
    initial guess, ``preprocess_points`` at the voxel size kentreg picks for the first scan (about
    ``preprocess.target_points`` points, recorded in the JSON), small_gicp's defaults otherwise
    (10 neighbours for covariances, 1 m maximum correspondence distance, 20 iterations). Its
    estimate is used as is, converged or not (the count of non-converged pairs is reported).

Metrics per pipeline: per-pair ``e_R``, ``e_t`` (median, max; a pair fails when ``e_R > 2 deg``
or ``e_t > 0.2 m``), RPE per frame (rotation and translation rmse), RPE per metre (translation
in %, rotation in deg/m, rmse over pairs that moved at least 5 cm), drift per metre over
segments of the path as the KITTI devkit measures it
(:func:`kentreg_ros.eval.kitti.drift_per_metre`), ATE rmse after
SE(3) (Umeyama)
alignment, and milliseconds per scan (mean, p95: everything a pipeline does with one scan,
preprocessing included, reading excluded). Each pipeline first processes the first two scans
once, untimed, on a throwaway instance (imports, allocator and cache warm-up). The pipelines run
``--rounds`` times (default 3) in rotated order, and each scan's time is its median over the
rounds, so a change in the machine's load (it is shared) does not land on one pipeline only.

Threads: ``--threads N`` (default 1) sets ``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS`` and
``MKL_NUM_THREADS`` (the script re-executes itself once so that they apply before numpy loads),
passes N to KISS-ICP and small_gicp, and limits the process's CPU affinity to N cores, which
also bounds kentreg's ``scipy.spatial.cKDTree.query(workers=-1)``.

Usage::

    python3 benchmarks/odometry.py                          # bags/balm_50, 1 thread
    python3 benchmarks/odometry.py --input ../shared/data/balm --threads 2

Writes ``benchmarks/results/odometry.json``, ``odometry.md`` (tables) and ``odometry.png``
(trajectories, top view, each aligned onto the reference by its ATE alignment).
"""

from __future__ import annotations

import argparse
import datetime
import logging
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.common import git_describe, machine_info, write_json  # noqa: E402
from kentreg_ros.core import (  # noqa: E402
    HEALTHS,
    KentRegConfig,  # noqa: E402
    Odometry,
    prepare_scan,  # noqa: E402
)
from kentreg_ros.eval import GroundTruth, associate, evaluate, metrics, run_odometry  # noqa: E402
from kentreg_ros.io.params import effective_config  # noqa: E402
from kentreg_ros.io.recordings import open_recording  # noqa: E402
from kentreg_ros.io.sources import Scan  # noqa: E402

logger = logging.getLogger('benchmarks.odometry')

FloatArray = NDArray[np.float64]

DEFAULT_INPUT = ROOT / 'bags' / 'balm_50'
RESULTS = ROOT / 'benchmarks' / 'results'
METHODS = ('kentreg', 'kentreg_local_map', 'kiss_icp', 'gicp')
#: Frames of the drift segment (RPE over scans i, i + SEGMENT_FRAMES): one second at 10 Hz.
SEGMENT_FRAMES = 10
#: Per-point time fields KISS-ICP's own PointCloud2 reader looks for.
TIME_FIELDS = ('t', 'timestamp', 'time', 'timestamps')
THREAD_ENV = ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS')
PINNED_ENV = 'KENTREG_BENCH_THREADS'
COLOURS = {
    'kentreg': 'tab:blue',
    'kentreg_local_map': 'tab:purple',
    'kiss_icp': 'tab:orange',
    'gicp': 'tab:green',
}


# --------------------------------------------------------------------------------------------
# Threads


def pin_threads(threads: int, argv: Sequence[str], script: Path | None = None) -> None:
    """Make this process run on at most ``threads`` cores (re-executing it once if needed).

    The BLAS/OpenMP variables only take effect before numpy loads, so the first call sets them
    and replaces the process with a fresh interpreter running the same command (``script``,
    default this file, with ``argv``); the second call (marked by ``KENTREG_BENCH_THREADS``)
    only sets the CPU affinity.
    """
    if os.environ.get(PINNED_ENV) != str(threads):
        env = dict(os.environ)
        env.update({name: str(threads) for name in (*THREAD_ENV, PINNED_ENV)})
        sys.stdout.flush()
        sys.stderr.flush()
        path = (script or Path(__file__)).resolve()
        os.execve(sys.executable, [sys.executable, str(path), *argv], env)
    allowed = sorted(os.sched_getaffinity(0))
    os.sched_setaffinity(0, allowed[:threads])


# --------------------------------------------------------------------------------------------
# Input


def read_input(path: Path, topic: str | None) -> tuple[list[Scan], GroundTruth, str]:
    """Every scan of a bag or scan folder (with all extra fields) and its reference poses."""
    # Every per-point field is kept, e.g. times for KISS-ICP's deskewing.
    source, reference, origin = open_recording(path, topic=topic, fields=None)
    if reference is None:
        raise SystemExit(f'{path}: no reference poses (a /ground_truth topic or a pose file)')
    scans = list(source)
    return scans, GroundTruth(reference, origin), source.description


def point_times(scan: Scan) -> FloatArray:
    """Per-point times of a scan for KISS-ICP, or an empty array when it has none."""
    for name in TIME_FIELDS:
        if name in scan.extras:
            return np.asarray(scan.extras[name], dtype=np.float64).ravel()
    return np.zeros(0)


# --------------------------------------------------------------------------------------------
# Pipelines


@dataclass
class PipelineRun:
    """Poses and per-scan times of one pipeline over the scans."""

    name: str
    poses: FloatArray
    ms_per_scan: FloatArray
    points_used: FloatArray
    settings: dict[str, Any]
    health: dict[str, Any] = field(default_factory=dict)


def run_kentreg(scans: list[Scan], cfg: KentRegConfig, name: str = 'kentreg') -> PipelineRun:
    """kentreg's odometry, run by the replay's own loop."""
    run_odometry(scans[:2], Odometry(cfg))  # warm-up, discarded
    run = run_odometry(scans, Odometry(cfg))
    if run.error is not None or len(run.steps) != len(scans):
        raise RuntimeError(f'kentreg stopped after {len(run.steps)} scans: {run.error}')
    health = {k: sum(s.health == k for s in run.steps) for k in HEALTHS}
    return PipelineRun(
        name=name,
        poses=run.poses,
        ms_per_scan=np.array([s.timings['total'] for s in run.steps]),
        points_used=np.array([s.n_prepared for s in run.steps], dtype=np.float64),
        settings={
            'mode': cfg.mode,
            'config': cfg.to_flat_dict(),
            'model': cfg.odometry.model.replace('_', ' '),
            'initial_guess': 'constant velocity'
            if cfg.odometry.constant_velocity
            else 'previous pose',
        },
        health=health,
    )


def run_kiss_icp(scans: list[Scan], threads: int, max_range: float | None = None) -> PipelineRun:
    """KISS-ICP's Python pipeline with the configuration its own OdometryPipeline loads.

    ``max_range`` (default: KISS-ICP's 100 m) is applied as a KISS-ICP YAML file would, so the
    voxel size follows it (``max_range / 100``).
    """
    import tempfile

    from kiss_icp.config import load_config
    from kiss_icp.kiss_icp import KissICP

    def make() -> Any:
        if max_range is None:
            config = load_config(None)
        else:
            with tempfile.TemporaryDirectory() as tmp:
                yaml_file = Path(tmp) / 'kiss_icp.yaml'
                yaml_file.write_text(f'data:\n  max_range: {max_range}\n')
                config = load_config(yaml_file)
        config.registration.max_num_threads = threads
        return KissICP(config=config)

    warm = make()
    for scan in scans[:2]:
        warm.register_frame(np.asarray(scan.points, dtype=np.float64), point_times(scan))
    kiss = make()
    poses, ms, used = [], [], []
    for scan in scans:
        points = np.asarray(scan.points, dtype=np.float64)
        times = point_times(scan)
        t0 = time.perf_counter()
        _, source = kiss.register_frame(points, times)
        ms.append((time.perf_counter() - t0) * 1e3)
        poses.append(np.array(kiss.last_pose, dtype=np.float64))
        used.append(len(source))
    cfg = kiss.config
    has_times = bool(point_times(scans[0]).size)
    return PipelineRun(
        name='kiss_icp',
        poses=np.stack(poses),
        ms_per_scan=np.array(ms),
        points_used=np.array(used, dtype=np.float64),
        settings={
            'config': 'kiss_icp.config.load_config: default KISSConfig'
            + ('' if max_range is None else f' with data.max_range = {max_range}')
            + ', voxel_size = max_range / 100',
            'max_range': cfg.data.max_range,
            'min_range': cfg.data.min_range,
            'deskew': cfg.data.deskew,
            'deskew_effective': bool(cfg.data.deskew and has_times),
            'per_point_times': has_times,
            'voxel_size': cfg.mapping.voxel_size,
            'max_points_per_voxel': cfg.mapping.max_points_per_voxel,
            'initial_threshold': cfg.adaptive_threshold.initial_threshold,
            'max_num_iterations': cfg.registration.max_num_iterations,
            'max_num_threads': cfg.registration.max_num_threads,
            'model': 'local voxel-hash map',
            'initial_guess': 'constant velocity',
        },
    )


def run_gicp(scans: list[Scan], voxel: float, threads: int) -> PipelineRun:
    """small_gicp GICP, each scan against the previous one, constant-velocity initial guess."""
    import small_gicp

    def odometry(batch: list[Scan]) -> tuple[list[FloatArray], list[float], list[int], int]:
        T_world = np.eye(4)
        motion = np.eye(4)
        previous: tuple[Any, Any] | None = None
        poses, ms, used = [], [], []
        n_not_converged = 0
        for scan in batch:
            points = np.asarray(scan.points, dtype=np.float64)
            t0 = time.perf_counter()
            cloud, tree = small_gicp.preprocess_points(
                points, downsampling_resolution=voxel, num_threads=threads
            )
            if previous is not None:
                result = small_gicp.align(
                    previous[0],
                    cloud,
                    previous[1],
                    init_T_target_source=motion,
                    registration_type='GICP',
                    num_threads=threads,
                )
                motion = np.array(result.T_target_source, dtype=np.float64)
                n_not_converged += not result.converged
                T_world = T_world @ motion
            ms.append((time.perf_counter() - t0) * 1e3)
            previous = (cloud, tree)
            poses.append(T_world.copy())
            used.append(cloud.size())
        return poses, ms, used, n_not_converged

    odometry(scans[:2])  # warm-up, discarded
    poses, ms, used, n_not_converged = odometry(scans)
    return PipelineRun(
        name='gicp',
        poses=np.stack(poses),
        ms_per_scan=np.array(ms),
        points_used=np.array(used, dtype=np.float64),
        settings={
            'registration_type': 'GICP',
            'downsampling_resolution': voxel,
            'voxel_choice': "kentreg's automatic voxel size for the first scan",
            'num_neighbors': 10,
            'max_correspondence_distance': 1.0,
            'max_iterations': 20,
            'num_threads': threads,
            'model': 'previous scan',
            'initial_guess': 'constant velocity',
        },
        health={'not_converged': n_not_converged},
    )


def combine_rounds(runs: list[PipelineRun]) -> PipelineRun:
    """One run from several rounds: first round's poses, per-scan median of the times.

    Every pipeline is deterministic, so later rounds repeat the first one's poses; the largest
    difference is recorded in ``health['pose_spread_between_rounds_m']``.
    """
    first = runs[0]
    spread = max(
        (float(np.abs(r.poses[:, :3, 3] - first.poses[:, :3, 3]).max()) for r in runs[1:]),
        default=0.0,
    )
    return PipelineRun(
        name=first.name,
        poses=first.poses,
        ms_per_scan=np.median(np.stack([r.ms_per_scan for r in runs]), axis=0),
        points_used=first.points_used,
        settings=first.settings,
        health={
            **first.health,
            'rounds': len(runs),
            'pose_spread_between_rounds_m': spread,
            'mean_ms_per_scan_per_round': [float(r.ms_per_scan.mean()) for r in runs],
        },
    )


# --------------------------------------------------------------------------------------------
# Evaluation and outputs


def evaluate_pipeline(
    run: PipelineRun, scans: list[Scan], gt: GroundTruth
) -> tuple[dict[str, Any], NDArray[np.intp], FloatArray]:
    """The replay's metrics for one pipeline, plus rotation RPE per metre and speed."""
    stamps = np.array([s.stamp_ns for s in scans], dtype=np.int64)
    scan_rows, gt_rows = associate(stamps, list(range(len(scans))), gt.trajectory)
    T_gt = np.asarray(gt.trajectory.T_world_sensor, dtype=np.float64)[gt_rows]
    T_est = run.poses[scan_rows]
    result = evaluate(T_est, T_gt)
    # Rotation RPE per metre over the pairs the translation per-metre figure keeps.
    rpe = metrics.rpe(T_est, T_gt, delta=1)
    per_metre = metrics.rpe_per_metre(T_est, T_gt, delta=1)
    deg_per_m = rpe['e_R_deg'][per_metre['index']] / per_metre['distance_m']
    result['rpe_per_metre']['rotation_deg_per_m'] = metrics.summarize(deg_per_m)
    # Drift over a segment, not one step: between consecutive scans a scan-to-map pipeline
    # adds two independent registration errors where scan-to-scan has one, but it should
    # drift less over a longer stretch. One second of a 10 Hz sensor (frames, not metres:
    # the sample is under 10 m long, too short for KITTI's 100-800 m segments).
    if len(T_est) > SEGMENT_FRAMES:
        seg = metrics.rpe(T_est, T_gt, delta=SEGMENT_FRAMES)
        result['rpe_segment'] = {
            'frames': SEGMENT_FRAMES,
            'rotation_deg': metrics.summarize(seg['e_R_deg']),
            'translation_m': metrics.summarize(seg['e_t']),
        }
    result['n_matched'] = len(scan_rows)
    result['speed'] = {
        'ms_per_scan': metrics.summarize(run.ms_per_scan),
        'points_used_per_scan': metrics.summarize(run.points_used),
    }
    return result, scan_rows, T_gt


def _num(value: Any, spec: str) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return '-'
    return format(value, spec)


def _drift_text(drift: dict[str, Any] | None) -> str:
    if drift is None:
        return '-'
    return f'{drift["translation_pct"]:.2f}, {drift["rotation_deg_per_m"]:.4f}'


def format_tables(report: dict[str, Any]) -> str:
    """Markdown tables of the report (the same numbers as the JSON, rounded)."""
    rows = report['methods']
    n_pairs = next((m['metrics']['pairs']['count'] for m in rows.values() if 'metrics' in m), 0)
    lines = [
        f'Input: {report["input"]["description"]}, {report["input"]["n_scans"]} scans, '
        f'{n_pairs} consecutive pairs; {report["threads"]} thread(s); ms per scan: per-scan '
        f'median over {report["rounds"]} rounds.',
        '',
        '| method | median e_R [deg] | median e_t [m] | max e_R [deg] | max e_t [m] '
        '| failures (e_R>2 deg or e_t>0.2 m) |',
        '|---|---|---|---|---|---|',
    ]
    for name, entry in rows.items():
        if 'metrics' not in entry:
            lines.append(f'| {name} | error: {entry["error"]} | | | | |')
            continue
        p = entry['metrics']['pairs']
        lines.append(
            f'| {name} | {_num(p["rotation_deg"]["median"], ".3f")} '
            f'| {_num(p["translation_m"]["median"], ".4f")} '
            f'| {_num(p["rotation_deg"]["max"], ".3f")} '
            f'| {_num(p["translation_m"]["max"], ".4f")} '
            f'| {p["n_failed"]} / {p["count"]} |'
        )
    lines += [
        '',
        '| method | RPE/frame rot rmse [deg] | RPE/frame trans rmse [m] '
        '| RPE/m trans rmse [%] | RPE/m rot rmse [deg/m] '
        f'| RPE/{SEGMENT_FRAMES} frames rot rmse [deg] '
        f'| RPE/{SEGMENT_FRAMES} frames trans rmse [m] '
        '| drift (KITTI segments) [%, deg/m] '
        '| ATE rmse [m] (SE(3)) | ms/scan mean | ms/scan p95 | points used/scan |',
        '|---|---|---|---|---|---|---|---|---|---|---|---|',
    ]
    for name, entry in rows.items():
        if 'metrics' not in entry:
            continue
        m = entry['metrics']
        ate = m['ate']['rmse'] if m['ate'] is not None else None
        speed = m['speed']
        seg = m.get('rpe_segment', {})
        lines.append(
            f'| {name} | {_num(m["rpe"]["rotation_deg"]["rmse"], ".3f")} '
            f'| {_num(m["rpe"]["translation_m"]["rmse"], ".4f")} '
            f'| {_num(m["rpe_per_metre"]["translation_pct"]["rmse"], ".2f")} '
            f'| {_num(m["rpe_per_metre"]["rotation_deg_per_m"]["rmse"], ".3f")} '
            f'| {_num(seg.get("rotation_deg", {}).get("rmse"), ".3f")} '
            f'| {_num(seg.get("translation_m", {}).get("rmse"), ".4f")} '
            f'| {_drift_text(m.get("drift"))} '
            f'| {_num(ate, ".4f")} '
            f'| {_num(speed["ms_per_scan"]["mean"], ".1f")} '
            f'| {_num(speed["ms_per_scan"]["p95"], ".1f")} '
            f'| {_num(speed["points_used_per_scan"]["mean"], ".0f")} |'
        )
    return '\n'.join(lines) + '\n'


def run_strides(
    strides: Sequence[int],
    methods: Sequence[str],
    failed: dict[str, str],
    scans: list[Scan],
    gt: GroundTruth,
    runners_for: Callable[[list[Scan]], dict[str, Callable[[], PipelineRun]]],
) -> dict[str, dict[str, Any]]:
    """Every pipeline once on every ``stride``-th scan (frame skipping: the motion between
    the scans it sees grows ``stride`` times; stamps kept), with the main run's metrics."""
    out: dict[str, dict[str, Any]] = {}
    for stride in strides:
        batch = scans[::stride]
        block: dict[str, Any] = {'n_scans': len(batch)}
        runners = runners_for(batch)
        for name in methods:
            if name in failed:
                continue
            try:
                run = runners[name]()
            except Exception as exc:  # a peer crashing is a result to report
                logger.exception('%s failed at stride %d', name, stride)
                block[name] = {'error': f'{type(exc).__name__}: {exc}'}
                continue
            result, _, _ = evaluate_pipeline(run, batch, gt)
            block[name] = {'health': run.health, 'metrics': result}
        out[str(stride)] = block
    return out


def format_stride_table(report: dict[str, Any]) -> str:
    """Markdown table of the frame-skipping runs (empty when there were none)."""
    strides = report.get('strides') or {}
    if not strides:
        return ''
    lines = [
        'Frame skipping: every N-th scan of the same input, one round per pipeline.',
        '',
        '| stride | method | median e_R [deg] | median e_t [m] | failures '
        '| RPE/m trans rmse [%] | ATE rmse [m] | ms/scan mean |',
        '|---|---|---|---|---|---|---|---|',
    ]
    for stride, block in strides.items():
        for name, entry in block.items():
            if name == 'n_scans':
                continue
            if 'metrics' not in entry:
                lines.append(f'| {stride} | {name} | error: {entry["error"]} | | | | | |')
                continue
            m = entry['metrics']
            p = m['pairs']
            ate = m['ate']['rmse'] if m['ate'] is not None else None
            lines.append(
                f'| {stride} | {name} | {_num(p["rotation_deg"]["median"], ".3f")} '
                f'| {_num(p["translation_m"]["median"], ".4f")} '
                f'| {p["n_failed"]} / {p["count"]} '
                f'| {_num(m["rpe_per_metre"]["translation_pct"]["rmse"], ".2f")} '
                f'| {_num(ate, ".4f")} '
                f'| {_num(m["speed"]["ms_per_scan"]["mean"], ".1f")} |'
            )
    return '\n'.join(lines) + '\n'


def plot(
    path: Path, aligned: dict[str, FloatArray], T_gt: FloatArray, errors: dict[str, Any]
) -> None:
    """Top view of every aligned trajectory over the reference, position and per-pair errors."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(13, 9), layout='constrained')
    FigureCanvasAgg(fig)
    (ax_xy, ax_p), (ax_r, ax_t) = fig.subplots(2, 2)
    ax_xy.plot(T_gt[:, 0, 3], T_gt[:, 1, 3], color='black', lw=4, alpha=0.25, label='reference')
    for name, poses in aligned.items():
        colour = COLOURS[name]
        ax_xy.plot(poses[:, 0, 3], poses[:, 1, 3], color=colour, lw=1.2, label=name)
        position_error = np.linalg.norm(poses[:, :3, 3] - T_gt[:, :3, 3], axis=1)
        rmse = errors[name]['ate']['rmse']
        ax_p.plot(position_error, '.-', color=colour, lw=0.8, label=f'{name} (rmse {rmse:.3f} m)')
        pairs = errors[name]['pairs']
        x = np.arange(1, len(pairs['e_R_deg']) + 1)
        ax_r.semilogy(x, np.maximum(pairs['e_R_deg'], 1e-4), '.-', color=colour, lw=0.8)
        ax_t.semilogy(x, np.maximum(pairs['e_t_m'], 1e-5), '.-', color=colour, lw=0.8)
    ax_xy.plot(T_gt[0, 0, 3], T_gt[0, 1, 3], 'ko', label='start')
    ax_xy.set_aspect('equal', adjustable='datalim')
    ax_xy.set(
        xlabel='x [m]', ylabel='y [m]', title='top view, each SE(3)-aligned onto the reference'
    )
    ax_xy.legend(loc='best', fontsize=8)
    ax_p.set(
        xlabel='scan', ylabel='position error [m]', title='ATE: position error after alignment'
    )
    ax_p.legend(loc='best', fontsize=8)
    ax_r.axhline(2.0, color='red', lw=0.8, ls='--', label='failure threshold')
    ax_r.set(xlabel='pair', ylabel='e_R [deg]', title='per-pair rotation error')
    ax_r.legend(loc='best', fontsize=8)
    ax_t.axhline(0.2, color='red', lw=0.8, ls='--')
    ax_t.set(xlabel='pair', ylabel='e_t [m]', title='per-pair translation error')
    for ax in (ax_p, ax_r, ax_t):
        ax.grid(True, which='both', alpha=0.3)
    fig.savefig(path, dpi=100)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        '--input',
        type=Path,
        default=DEFAULT_INPUT,
        metavar='PATH',
        help='bag with /ground_truth, or scan folder with its pose file (default bags/balm_50)',
    )
    parser.add_argument('--topic', help='PointCloud2 topic, when the bag has several')
    parser.add_argument(
        '--threads',
        type=int,
        default=1,
        help='threads/cores for every library (env vars, library arguments, CPU affinity)',
    )
    parser.add_argument(
        '--methods',
        nargs='+',
        choices=METHODS,
        default=list(METHODS),
        help='pipelines to run (default all)',
    )
    parser.add_argument(
        '--kiss-max-range',
        type=float,
        metavar='M',
        help="KISS-ICP's data.max_range (default: its own 100 m; its voxel is max_range / 100)",
    )
    parser.add_argument('--config', type=Path, help="kentreg parameter file (the node's YAML)")
    parser.add_argument(
        '--set',
        dest='overrides',
        action='append',
        default=[],
        metavar='KEY=VALUE',
        help='override one kentreg parameter (repeatable), as for kentreg_replay',
    )
    parser.add_argument(
        '--rounds',
        type=int,
        default=3,
        help='runs of every pipeline, in rotated order; ms per scan is the per-scan median '
        'over rounds (default 3)',
    )
    parser.add_argument(
        '--max-scans', type=int, metavar='N', help='use the first N scans only (development)'
    )
    parser.add_argument(
        '--strides',
        type=int,
        nargs='*',
        default=[2, 3, 4],
        metavar='N',
        help='also run every pipeline once on every N-th scan (frame skipping; default 2 3 4; '
        'none: --strides)',
    )
    parser.add_argument(
        '--out',
        type=Path,
        default=RESULTS,
        help='folder for odometry.json/.md/.png (default benchmarks/results)',
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    if args.threads < 1 or args.rounds < 1 or any(n < 1 for n in args.strides):
        raise SystemExit('--threads, --rounds and --strides must be >= 1')
    pin_threads(args.threads, argv)
    logging.basicConfig(level=logging.WARNING, format='%(name)s: %(levelname)s: %(message)s')
    cfg = effective_config(args.config, args.overrides)
    scans, gt, description = read_input(args.input, args.topic)
    if args.max_scans is not None:
        scans = scans[: args.max_scans]
    voxel = prepare_scan(scans[0].points, config=cfg).voxel_size

    def runners_for(batch: list[Scan]) -> dict[str, Callable[[], PipelineRun]]:
        return {
            'kentreg': lambda: run_kentreg(batch, cfg),
            'kentreg_local_map': lambda: run_kentreg(
                batch, cfg.with_updates({'odometry.model': 'local_map'}), 'kentreg_local_map'
            ),
            'kiss_icp': lambda: run_kiss_icp(batch, args.threads, args.kiss_max_range),
            'gicp': lambda: run_gicp(batch, voxel, args.threads),
        }

    runners = runners_for(scans)
    report: dict[str, Any] = {
        'benchmark': 'odometry',
        'command': ['python3', 'benchmarks/odometry.py', *argv],
        'date': datetime.datetime.now().isoformat(timespec='seconds'),
        'machine': machine_info(),
        'threads': args.threads,
        'thread_pinning': {
            'env': {name: os.environ.get(name) for name in THREAD_ENV},
            'cpu_affinity': sorted(os.sched_getaffinity(0)),
        },
        'input': {
            'path': str(args.input),
            'description': description,
            'n_scans': len(scans),
            'points_per_scan': metrics.summarize([len(s.points) for s in scans]),
            'ground_truth': gt.origin,
        },
        'ms_per_scan_measures': 'wall time of everything a pipeline does with one scan '
        '(preprocessing included, reading excluded), every scan including the first, '
        'after an untimed two-scan warm-up; per scan the median over --rounds rounds, which '
        'run the pipelines in rotated order',
        'rounds': args.rounds,
        'methods': {},
    }
    aligned: dict[str, FloatArray] = {}
    errors: dict[str, Any] = {}
    T_gt_plot = None
    runs: dict[str, list[PipelineRun]] = {name: [] for name in args.methods}
    failed: dict[str, str] = {}
    for r in range(args.rounds):
        k = r % len(args.methods)
        for name in args.methods[k:] + args.methods[:k]:  # rotated: load changes hit everyone
            if name in failed:
                continue
            t0 = time.perf_counter()
            try:
                runs[name].append(runners[name]())
            except Exception as exc:  # a peer crashing is a result to report, not a stop
                logger.exception('%s failed', name)
                failed[name] = f'{type(exc).__name__}: {exc}'
            logger.info('%s round %d done in %.1f s', name, r, time.perf_counter() - t0)
    for name in args.methods:
        if name in failed:
            report['methods'][name] = {'error': failed[name]}
            continue
        run = combine_rounds(runs[name])
        result, rows, T_gt = evaluate_pipeline(run, scans, gt)
        T_gt_plot = T_gt
        if result['ate'] is not None:
            aligned[name] = np.asarray(result['ate']['T_gt_est']) @ run.poses[rows]
        errors[name] = result
        report['methods'][name] = {
            'settings': run.settings,
            'health': run.health,
            'metrics': result,
            'poses_T_world_lidar': run.poses,
        }
    report['strides'] = run_strides(args.strides, args.methods, failed, scans, gt, runners_for)
    report['machine']['load_avg_at_end'] = list(os.getloadavg())
    report['machine']['git_at_end'] = git_describe()
    if report['machine']['git_at_end'] != report['machine']['git']:
        logger.warning(
            'The checkout changed during the run (%s -> %s): rerun for consistent numbers.',
            report['machine']['git'],
            report['machine']['git_at_end'],
        )
    args.out.mkdir(parents=True, exist_ok=True)
    table = format_tables(report)
    strides_table = format_stride_table(report)
    if strides_table:
        table += '\n' + strides_table
    (args.out / 'odometry.md').write_text(table)
    write_json(args.out / 'odometry.json', report)
    if T_gt_plot is not None and aligned:
        plot(args.out / 'odometry.png', aligned, T_gt_plot, errors)
    print(table)
    print(f'wrote {args.out}/odometry.json, odometry.md, odometry.png')
    return 0


if __name__ == '__main__':
    sys.exit(main())
