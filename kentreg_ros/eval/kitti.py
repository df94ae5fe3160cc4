"""The KITTI odometry benchmark's segment metric: drift over 100 m ... 800 m of travel.

Translation (%) and rotation (deg/m) errors of every segment of a fixed ground-truth path length,
averaged as the devkit of Geiger et al. [1]_ does. The per-pair errors and the validation of the
pose stacks are those of :mod:`kentreg_ros.eval.metrics`.

References
----------
.. [1] Geiger, A., Lenz, P., Urtasun, R. (2012). Are we ready for autonomous driving? The KITTI
   vision benchmark suite. CVPR. Devkit ``evaluate_odometry.cpp``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import TypedDict

import numpy as np
from numpy.typing import ArrayLike

from kentreg_ros.eval.metrics import (
    FloatArray,
    IntArray,
    _as_float_array,
    _as_pose_pair,
    _pair_errors,
    _path_length,
)

logger = logging.getLogger(__name__)

#: Segment lengths of the KITTI odometry benchmark, in metres.
KITTI_LENGTHS: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)


class KittiLengthResult(TypedDict):
    """KITTI errors of the segments of one length."""

    n_segments: int
    t_err_pct: float
    r_err_deg_per_m: float


class KittiResult(TypedDict):
    """KITTI odometry metric (see :func:`kitti_segment_errors`)."""

    t_err_pct: float
    r_err_deg_per_m: float
    n_segments: int
    lengths: tuple[float, ...]
    step: int
    distance_m: float
    per_length: dict[float, KittiLengthResult]
    first_frame: IntArray
    last_frame: IntArray
    length: FloatArray
    segment_t_err_pct: FloatArray
    segment_r_err_deg_per_m: FloatArray


def _segment_lengths(lengths: Sequence[float], step: int) -> FloatArray:
    """``lengths`` as an array, checked with ``step`` (see :func:`kitti_segment_errors`)."""
    lens = _as_float_array(lengths, 'lengths')
    if lens.ndim != 1 or lens.size == 0:
        raise ValueError(
            f'Expected `lengths` to be a non-empty sequence of floats, got shape {lens.shape}.'
        )
    if not (np.isfinite(lens).all() and (lens > 0.0).all()):
        raise ValueError(f'Expected every segment length to be positive, got {lens.tolist()}.')
    if np.unique(lens).size != lens.size:
        raise ValueError(f'Expected distinct segment lengths, got {lens.tolist()}.')
    if isinstance(step, bool) or not isinstance(step, int | np.integer) or step < 1:
        raise ValueError(f'Expected `step` to be a positive integer, got {step!r}.')
    return lens


def _segments(
    est: FloatArray, gt: FloatArray, dist: FloatArray, lens: FloatArray, step: int
) -> tuple[list[IntArray], list[IntArray], list[FloatArray], list[FloatArray], list[FloatArray]]:
    """Per segment length that has segments: their first and last frames, lengths and
    translation (%) and rotation (deg/m) errors (see :func:`kitti_segment_errors`)."""
    n = est.shape[0]
    first_all = np.arange(0, n, step)
    inv_est = np.linalg.inv(est)
    inv_gt = np.linalg.inv(gt)
    firsts: list[IntArray] = []
    lasts: list[IntArray] = []
    seg_lens: list[FloatArray] = []
    t_errs: list[FloatArray] = []
    r_errs: list[FloatArray] = []
    for length in lens:
        # First frame whose distance exceeds dist[first] + length (devkit: strict '>').
        last = np.searchsorted(dist, dist[first_all] + length, side='right')
        ok = last < n
        if not ok.any():
            continue
        f, lf = first_all[ok], last[ok]
        e_R, e_t = _pair_errors(inv_est[f] @ est[lf], inv_gt[f] @ gt[lf])
        firsts.append(f.astype(np.int64))
        lasts.append(lf.astype(np.int64))
        seg_lens.append(np.full(f.size, float(length)))
        t_errs.append(100.0 * e_t / length)
        r_errs.append(e_R / length)
    return firsts, lasts, seg_lens, t_errs, r_errs


def kitti_segment_errors(
    T_est: ArrayLike,
    T_gt: ArrayLike,
    lengths: Sequence[float] = KITTI_LENGTHS,
    *,
    step: int = 10,
) -> KittiResult | None:
    """Translation (%) and rotation (deg/m) drift over fixed-length segments, as the KITTI devkit.

    Follows ``evaluate_odometry.cpp`` of the KITTI odometry devkit [1]_: for every first frame
    ``0, step, 2 step, ...`` and every length ``L``, the last frame is the first one whose
    ground-truth path length from the first frame exceeds ``L`` (strictly); the error transform
    ``(T_est[f]^-1 T_est[l])^-1 (T_gt[f]^-1 T_gt[l])`` gives ``t_err / L`` and ``r_err / L``.
    All segments of all lengths are averaged together, as in the devkit's summary. Segments that
    run past the end of the trajectory are dropped.

    Parameters
    ----------
    T_est, T_gt : array_like, shape (N, 4, 4)
        Estimated and ground-truth absolute poses, associated frame by frame.
    lengths : sequence of float
        Segment lengths in metres, default :data:`KITTI_LENGTHS` (100, 200, ..., 800). Short
        runs can use shorter lengths, e.g. ``(5, 10, 20, 40)`` for a 74 m run; such numbers are
        not comparable with the KITTI leaderboard.
    step : int
        Frame step between first frames (10 in the devkit, one second at 10 Hz).

    Returns
    -------
    KittiResult or None
        None when the run is too short to fill even the shortest segment (ground-truth path
        length not exceeding ``min(lengths)``). Otherwise ``t_err_pct`` (mean ``t_err / L`` in
        %), ``r_err_deg_per_m`` (mean ``r_err / L`` in deg/m; multiply by 100 for the
        leaderboard's deg/100 m), ``n_segments``, ``lengths`` (as requested), ``step``,
        ``distance_m`` (ground-truth path length), ``per_length`` (the same averages for each
        length that has segments) and per-segment arrays of shape (K,): ``first_frame``,
        ``last_frame``, ``length``, ``segment_t_err_pct``, ``segment_r_err_deg_per_m``.

    Raises
    ------
    ValueError
        Invalid poses, different lengths, non-positive or repeated segment lengths, or
        ``step < 1``.
    """
    est, gt = _as_pose_pair(T_est, T_gt, ('T_est', 'T_gt'))
    lens = _segment_lengths(lengths, step)
    dist = _path_length(gt)
    firsts, lasts, seg_lens, t_errs, r_errs = _segments(est, gt, dist, lens, int(step))
    if not firsts:
        logger.debug(
            'kitti_segment_errors: trajectory of %.2f m does not fill the shortest segment '
            '(%g m).',
            dist[-1],
            lens.min(),
        )
        return None

    length_all = np.concatenate(seg_lens)
    t_all = np.concatenate(t_errs)
    r_all = np.concatenate(r_errs)
    per_length: dict[float, KittiLengthResult] = {}
    for length, t_seg, r_seg in zip(seg_lens, t_errs, r_errs, strict=True):
        per_length[float(length[0])] = KittiLengthResult(
            n_segments=int(t_seg.size),
            t_err_pct=float(np.mean(t_seg)),
            r_err_deg_per_m=float(np.mean(r_seg)),
        )
    return KittiResult(
        t_err_pct=float(np.mean(t_all)),
        r_err_deg_per_m=float(np.mean(r_all)),
        n_segments=int(t_all.size),
        lengths=tuple(float(x) for x in lens),
        step=int(step),
        distance_m=float(dist[-1]),
        per_length=per_length,
        first_frame=np.concatenate(firsts),
        last_frame=np.concatenate(lasts),
        length=length_all,
        segment_t_err_pct=t_all,
        segment_r_err_deg_per_m=r_all,
    )


class DriftResult(TypedDict):
    """RPE per metre over segments of the path (see :func:`drift_per_metre`)."""

    lengths_m: list[float]
    n_segments: int
    translation_pct: float
    rotation_deg_per_m: float


def scaled_lengths(path_m: float) -> tuple[float, ...]:
    """KITTI's segment lengths for a trajectory of ``path_m`` metres: 100-800 m from 1.6 km of
    travel on, scaled down in proportion below it (the longest segment half the path, eight
    lengths), e.g. 0.61-4.9 m for a 9.75 m run."""
    scale = min(1.0, float(path_m) / (2.0 * KITTI_LENGTHS[-1]))
    return tuple(scale * length for length in KITTI_LENGTHS)


def drift_per_metre(T_est: ArrayLike, T_gt: ArrayLike) -> DriftResult | None:
    """RPE per metre as the KITTI devkit measures it, on runs of any length.

    :func:`kitti_segment_errors` over :func:`scaled_lengths` of the ground-truth path, every
    frame a first frame: the drift over stretches of the path. On a run shorter than 1.6 km the
    numbers are not comparable with the KITTI leaderboard, but they compare pipelines on the
    same run; unlike the per-metre error of consecutive pairs (:func:`~kentreg_ros.eval.
    metrics.rpe_per_metre`) they are not dominated by the reference's noise when the sensor
    moves centimetres between scans. None when the run has fewer than 2 poses or no path.
    """
    est, gt = _as_pose_pair(T_est, T_gt, ('T_est', 'T_gt'))
    if est.shape[0] < 2:
        return None
    path = float(_path_length(gt)[-1])
    if not path > 0.0:
        return None
    lengths = scaled_lengths(path)
    res = kitti_segment_errors(est, gt, lengths, step=1)
    if res is None:
        return None
    return DriftResult(
        lengths_m=list(lengths),
        n_segments=int(res['n_segments']),
        translation_pct=float(res['t_err_pct']),
        rotation_deg_per_m=float(res['r_err_deg_per_m']),
    )
