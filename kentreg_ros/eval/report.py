"""The report of an odometry run: metrics against ground truth, speed, per-step records, summary.

:func:`evaluate` turns associated estimated and reference poses into the paper's pair errors
and failures, RPE per frame and per metre, ATE after SE(3) alignment and, when the run is long
enough, the KITTI segment metric (JSON-ready). :func:`evaluate_run` associates an
:class:`~kentreg_ros.eval.run.OdometryRun` with its
:class:`~kentreg_ros.eval.groundtruth.GroundTruth` first. :func:`run_report` gathers what
``metrics.json`` holds of a run and :func:`format_summary` prints its short table.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core import HEALTHS, OdometryStep
from kentreg_ros.eval import alignment, kitti, metrics
from kentreg_ros.eval.groundtruth import GT_TOLERANCE_S, GroundTruth, associate
from kentreg_ros.eval.run import OdometryRun
from kentreg_ros.io.sources import SkippedScan

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


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
    """Ground-truth comparison of a run (rows of the run's steps and of the reference).

    Attributes
    ----------
    scan_rows : ndarray of int, shape (M,)
        Rows of the run's steps that have a reference pose.
    T_gt : ndarray, shape (M, 4, 4)
        Their reference poses.
    stamps_ns : ndarray of int64, shape (M,)
        Their stamps.
    metrics : dict
        :func:`evaluate` of the associated poses, plus ``source`` and ``n_matched``.
    """

    scan_rows: NDArray[np.intp]
    T_gt: FloatArray
    stamps_ns: NDArray[np.int64]
    metrics: dict[str, Any]


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
        run does not fill a 100 m segment (``kitti_note`` says why); ``drift`` is
        :func:`~kentreg_ros.eval.kitti.drift_per_metre` (the same metric at lengths scaled to
        the run; None without a path). A pair fails as
        :func:`~kentreg_ros.eval.metrics.failed_pairs` says.
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
        ate = alignment.ate(T_est, T_gt, align=True)
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
    out['drift'] = kitti.drift_per_metre(T_est, T_gt)
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


def evaluate_run(run: OdometryRun, gt: GroundTruth | None) -> tuple[Evaluation | None, str]:
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


def speed_summary(run: OdometryRun) -> dict[str, Any]:
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


def step_record(step: OdometryStep, input_index: int) -> dict[str, Any]:
    """The JSON record of one step: index, stamp, health, timings, points, fit, status."""
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


def run_report(run: OdometryRun, evaluation: Evaluation | None, note: str = '') -> dict[str, Any]:
    """What ``metrics.json`` holds of a run, after the description of its input.

    ``complete``, ``error``, ``skipped`` (the input scans that could not be decoded:
    ``count`` and the ``first`` few, each ``input_index``, ``stamp_ns``, ``reason``),
    ``health`` (count per health), ``n_failed_steps``, ``n_searched``, ``speed``
    (:func:`speed_summary`), ``ground_truth`` (the evaluation's metrics, or None and
    ``ground_truth_note`` = ``note``) and ``steps`` (:func:`step_record` of each step).
    """
    health = {str(k): sum(s.health == k for s in run.steps) for k in HEALTHS}
    report: dict[str, Any] = {
        'complete': not run.interrupted and run.error is None,
        'error': run.error,
        'skipped': {
            'count': run.n_skipped,
            'first': [skipped_record(k) for k in run.skipped],
        },
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
        step_record(s, i) for s, i in zip(run.steps, run.input_indices, strict=True)
    ]
    return report


def _fmt(value: Any, spec: str) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return '-'
    return format(value, spec)


def stride_text(stride: int) -> str:
    """'stride 1 (every scan)' or 'stride 3 (one scan in 3)' for the summary and plot title."""
    return 'stride 1 (every scan)' if stride == 1 else f'stride {stride} (one scan in {stride})'


def format_summary(report: dict[str, Any], out: Path | None, *, prog: str) -> str:
    """The short table printed at the end of a run (``report`` as written to metrics.json)."""
    speed = report['speed']
    health = report['health']
    lines = [
        f'{prog}: {speed["n_scans"]} scans of {report["input"]["description"]}, '
        f'{stride_text(report["input"].get("stride", 1))}, mode {report["mode"]}',
        '  health     '
        + ', '.join(f'{k} {health[k]}' for k in HEALTHS)
        + f' (start-free search on {report.get("n_searched", 0)} scans)',
        f'  speed      {_fmt(speed["ms_per_scan"]["mean"], ".1f")} ms/scan mean, '
        f'{_fmt(speed["ms_per_scan"]["p95"], ".1f")} ms p95, '
        f'{_fmt(speed["scans_per_s"], ".2f")} scans/s (wall, with reading)',
    ]
    lines += skipped_lines(report.get('skipped'))
    gt = report.get('ground_truth')
    if gt is None:
        lines.append(f'  metrics    {report.get("ground_truth_note", "no ground truth")}')
    else:
        lines += _ground_truth_lines(gt)
    if out is not None:
        lines.append(f'  output     {out}/')
    return '\n'.join(lines)


def skipped_record(skipped: SkippedScan) -> dict[str, Any]:
    """The JSON record of a skipped scan: ``input_index``, ``stamp_ns`` (or None), ``reason``."""
    return {'input_index': skipped.index, 'stamp_ns': skipped.stamp_ns, 'reason': skipped.reason}


def skipped_text(entry: dict[str, Any]) -> str:
    """'input 2 (stamp 1634.250 s): <reason>' for one skipped scan of a report."""
    stamp = entry.get('stamp_ns')
    when = f' (stamp {stamp * 1e-9:.3f} s)' if stamp is not None else ''
    return f'input {entry["input_index"]}{when}: {entry["reason"]}'


def skipped_lines(skipped: dict[str, Any] | None) -> list[str]:
    """The summary's lines on the scans that could not be decoded (none when there were none)."""
    if not skipped or not skipped['count']:
        return []
    count, first = skipped['count'], skipped['first']
    lines = [
        f'  skipped    {count} scan{"s" if count != 1 else ""} that could not be decoded, not '
        'processed (metrics.json: skipped)'
    ]
    lines += [f'               {skipped_text(entry)}' for entry in first]
    if count > len(first):
        lines.append(f'               and {count - len(first)} more')
    return lines


def _ground_truth_lines(gt: dict[str, Any]) -> list[str]:
    pairs = gt['pairs']
    rot, tra = pairs['rotation_deg'], pairs['translation_m']
    per_metre = gt['rpe_per_metre']['translation_pct']
    skipped = gt['rpe_per_metre']['n_skipped']
    min_distance = gt['rpe_per_metre']['min_distance_m']
    lines = [
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
    drift = gt.get('drift')
    if drift is not None:
        lines.append(
            f'  drift/metre    {drift["translation_pct"]:.2f} %, '
            f'{drift["rotation_deg_per_m"]:.4f} deg/m over segments of '
            f'{drift["lengths_m"][0]:.3g}-{drift["lengths_m"][-1]:.3g} m '
            "(KITTI's metric at lengths scaled to the run)"
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
    return lines
