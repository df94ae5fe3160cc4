"""Trajectory and registration error metrics: pair errors and failures, RPE, ATE.

Poses are stacks of homogeneous 4x4 matrices, shape ``(N, 4, 4)``; ``T_world_sensor[i]`` maps
points of scan ``i`` into the world frame. Estimated and ground-truth trajectories are compared
pose by pose, so they must have the same length and be associated (same timestamps) already.

The per-pair error is the metric of Fahandezh-Saadi et al. [1]_, adopted from Wang et al. [2]_:
the rotation angle of ``R_true^T R_est`` and the Euclidean distance of the translations. RPE and
ATE follow Sturm et al. [3]_ and the alignment is Umeyama's [4]_. The KITTI segment metric is in
:mod:`kentreg_ros.eval.kitti`.

References
----------
.. [1] Fahandezh-Saadi, S., Wang, D., Tomizuka, M. Robust feature-based point registration using
   directional mixture model.
.. [2] Wang, D., Xue, J., Tao, Z., Zhong, Y., Cui, D., Du, S., Zheng, N. (2018). Accurate
   mix-norm-based scan matching. IROS, 1665-1671.
.. [3] Sturm, J., Engelhard, N., Endres, F., Burgard, W., Cremers, D. (2012). A benchmark for the
   evaluation of RGB-D SLAM systems. IROS, 573-580.
.. [4] Umeyama, S. (1991). Least-squares estimation of transformation parameters between two
   point patterns. IEEE TPAMI 13(4), 376-380.
"""

from __future__ import annotations

import logging
from typing import TypedDict

import numpy as np
from numpy.typing import ArrayLike, NDArray

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: A registered pair *fails* when its rotation error exceeds this (degrees) or its translation
#: error exceeds :data:`FAIL_TRANSLATION_M`: the thresholds of Fahandezh-Saadi et al. [1]_, used
#: by every report of the package and of its benchmarks (see :func:`failed_pairs`).
FAIL_ROTATION_DEG = 2.0
#: Translation error (metres) beyond which a pair fails (see :data:`FAIL_ROTATION_DEG`).
FAIL_TRANSLATION_M = 0.2

#: Default ``min_distance`` of :func:`rpe_per_metre`, in metres (see there).
RPE_MIN_DISTANCE = 0.05

_BOTTOM_ROW = np.array([0.0, 0.0, 0.0, 1.0])
_BOTTOM_ROW_ATOL = 1e-9


class Summary(TypedDict):
    """Summary statistics of a set of errors (see :func:`summarize`)."""

    count: int
    mean: float
    median: float
    rmse: float
    p95: float
    max: float


class RPEResult(TypedDict):
    """Relative pose error over pairs ``(i, i + delta)`` (see :func:`rpe`)."""

    delta: int
    e_R_deg: FloatArray
    e_t: FloatArray
    rotation_deg: Summary
    translation_m: Summary


class RPEPerMetreResult(TypedDict):
    """Translation RPE relative to the distance travelled (see :func:`rpe_per_metre`)."""

    delta: int
    min_distance: float
    index: IntArray
    distance_m: FloatArray
    e_t_pct: FloatArray
    n_skipped: int
    translation_pct: Summary


# --------------------------------------------------------------------------------------------
# Validation


def _as_float_array(values: ArrayLike, name: str) -> FloatArray:
    try:
        return np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'Expected `{name}` to be numeric, got {exc}.') from exc


def _check_finite(arr: FloatArray, name: str) -> None:
    if not np.isfinite(arr).all():
        n_bad = int((~np.isfinite(arr)).sum())
        raise ValueError(f'`{name}` has {n_bad} NaN or inf entr{"y" if n_bad == 1 else "ies"}.')


def as_poses(T: ArrayLike, name: str = 'T', *, min_poses: int = 1) -> FloatArray:
    """Validate and convert a stack of homogeneous transforms to float64, shape (N, 4, 4).

    Parameters
    ----------
    T : array_like, shape (N, 4, 4)
        Homogeneous transforms; the last row of every matrix must be ``[0, 0, 0, 1]``.
    name : str
        Name used in error messages.
    min_poses : int
        Smallest accepted ``N``.

    Returns
    -------
    ndarray, shape (N, 4, 4)

    Raises
    ------
    ValueError
        Non-numeric data, wrong shape, fewer than ``min_poses`` poses, NaN or inf entries, or a
        last row other than ``[0, 0, 0, 1]`` (e.g. a transposed matrix).
    """
    arr = _as_float_array(T, name)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise ValueError(f'Expected `{name}` to have shape (N, 4, 4), got {arr.shape}.')
    if arr.shape[0] < min_poses:
        raise ValueError(
            f'Expected `{name}` to hold at least {min_poses} pose(s), got {arr.shape[0]}.'
        )
    bad = ~np.isfinite(arr).all(axis=(1, 2))
    if bad.any():
        raise ValueError(
            f'`{name}` has {int(bad.sum())} pose(s) with NaN or inf entries '
            f'(first at index {int(np.argmax(bad))}).'
        )
    bad = ~np.isclose(arr[:, 3, :], _BOTTOM_ROW, rtol=0.0, atol=_BOTTOM_ROW_ATOL).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(
            f'Expected the last row of every `{name}` matrix to be [0, 0, 0, 1], '
            f'got {arr[i, 3].tolist()} at index {i} (transposed matrix?).'
        )
    return arr


def _as_pose_pair(
    T_est: ArrayLike, T_gt: ArrayLike, names: tuple[str, str], *, min_poses: int = 1
) -> tuple[FloatArray, FloatArray]:
    est = as_poses(T_est, names[0], min_poses=min_poses)
    gt = as_poses(T_gt, names[1], min_poses=min_poses)
    if est.shape[0] != gt.shape[0]:
        raise ValueError(
            f'Expected `{names[0]}` and `{names[1]}` to have the same number of poses, '
            f'got {est.shape[0]} and {gt.shape[0]}.'
        )
    return est, gt


def _check_delta(delta: int, n_poses: int) -> int:
    if isinstance(delta, bool) or not isinstance(delta, int | np.integer) or delta < 1:
        raise ValueError(f'Expected `delta` to be a positive integer, got {delta!r}.')
    if delta >= n_poses:
        raise ValueError(
            f'Expected `delta` to be smaller than the number of poses ({n_poses}), got {delta}.'
        )
    return int(delta)


# --------------------------------------------------------------------------------------------
# Per-pair errors


def rotation_error_deg(R_est: ArrayLike, R_true: ArrayLike) -> FloatArray:
    """Angle of the rotation between estimated and true rotations, in degrees.

    ``e_R = arccos((tr(R_true^T R_est) - 1) / 2)``, the metric of Fahandezh-Saadi et al. [1]_
    (from Wang et al. [2]_). The cosine is clipped to ``[-1, 1]`` so that round-off on
    (nearly) orthonormal matrices cannot produce NaN. Being an arccos, the resolution near 0 and
    180 degrees is about ``sqrt(eps)`` rad (a few ``1e-6`` degrees), so identical rotations may
    show such a residual; this is far below any registration error of interest.

    Parameters
    ----------
    R_est, R_true : array_like, shape (..., 3, 3)
        Rotation matrices; the leading dimensions broadcast against each other.

    Returns
    -------
    ndarray, shape (...)
        Angles in ``[0, 180]`` degrees.

    Raises
    ------
    ValueError
        Wrong shapes, shapes that do not broadcast, or non-finite entries.
    """
    est = _as_float_array(R_est, 'R_est')
    true = _as_float_array(R_true, 'R_true')
    for arr, name in ((est, 'R_est'), (true, 'R_true')):
        if arr.ndim < 2 or arr.shape[-2:] != (3, 3):
            raise ValueError(f'Expected `{name}` to have shape (..., 3, 3), got {arr.shape}.')
        _check_finite(arr, name)
    try:
        np.broadcast_shapes(est.shape, true.shape)
    except ValueError:
        raise ValueError(
            f'Expected `R_est` and `R_true` to have broadcastable shapes, '
            f'got {est.shape} and {true.shape}.'
        ) from None
    # tr(R_true^T R_est) = sum_ij R_true[i, j] * R_est[i, j]
    trace = np.sum(true * est, axis=(-2, -1))
    cos = np.clip((trace - 1.0) / 2.0, -1.0, 1.0)
    return np.asarray(np.degrees(np.arccos(cos)), dtype=np.float64)


def translation_error(t_est: ArrayLike, t_true: ArrayLike) -> FloatArray:
    """Euclidean distance ``||t_est - t_true||`` between translations.

    Parameters
    ----------
    t_est, t_true : array_like, shape (..., 3)
        Translation vectors; the leading dimensions broadcast against each other.

    Returns
    -------
    ndarray, shape (...)

    Raises
    ------
    ValueError
        Wrong shapes, shapes that do not broadcast, or non-finite entries.
    """
    est = _as_float_array(t_est, 't_est')
    true = _as_float_array(t_true, 't_true')
    for arr, name in ((est, 't_est'), (true, 't_true')):
        if arr.ndim < 1 or arr.shape[-1] != 3:
            raise ValueError(f'Expected `{name}` to have shape (..., 3), got {arr.shape}.')
        _check_finite(arr, name)
    try:
        diff = est - true
    except ValueError:
        raise ValueError(
            f'Expected `t_est` and `t_true` to have broadcastable shapes, '
            f'got {est.shape} and {true.shape}.'
        ) from None
    return np.asarray(np.linalg.norm(diff, axis=-1), dtype=np.float64)


def _pair_errors(est: FloatArray, true: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Unvalidated :func:`pair_errors` on arrays of shape (M, 4, 4)."""
    trace = np.sum(true[:, :3, :3] * est[:, :3, :3], axis=(1, 2))
    e_R = np.degrees(np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0)))
    e_t = np.linalg.norm(est[:, :3, 3] - true[:, :3, 3], axis=1)
    return np.asarray(e_R, dtype=np.float64), np.asarray(e_t, dtype=np.float64)


def pair_errors(T_est: ArrayLike, T_true: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Rotation and translation errors of estimated against true relative transforms.

    For every pair ``e_R = arccos((tr(R_true^T R_est) - 1) / 2)`` in degrees and
    ``e_t = ||t_est - t_true||`` in the unit of the translations, the metric of
    Fahandezh-Saadi et al. [1]_. ``e_t`` equals the translation norm of the error transform
    ``T_true^-1 T_est`` used by RPE.

    Parameters
    ----------
    T_est, T_true : array_like, shape (N, 4, 4)
        Estimated and true relative transforms (e.g. ``T_prev_curr`` of each scan pair).

    Returns
    -------
    e_R_deg : ndarray, shape (N,)
    e_t : ndarray, shape (N,)

    Raises
    ------
    ValueError
        Wrong shapes, different ``N``, non-finite entries or a last row other than
        ``[0, 0, 0, 1]``.
    """
    est, true = _as_pose_pair(T_est, T_true, ('T_est', 'T_true'))
    return _pair_errors(est, true)


def failed_pairs(e_R_deg: ArrayLike, e_t: ArrayLike) -> NDArray[np.bool_]:
    """Which pairs failed: ``e_R > FAIL_ROTATION_DEG`` or ``e_t > FAIL_TRANSLATION_M``.

    A NaN error (a method that raised instead of returning a transform) counts as failed.

    Parameters
    ----------
    e_R_deg, e_t : array_like, shape (N,)
        Rotation errors in degrees and translation errors in metres (see :func:`pair_errors`).

    Returns
    -------
    ndarray of bool, shape (N,)

    Raises
    ------
    ValueError
        Non-numeric errors or shapes that do not broadcast.
    """
    rot = _as_float_array(e_R_deg, 'e_R_deg')
    tra = _as_float_array(e_t, 'e_t')
    try:
        np.broadcast_shapes(rot.shape, tra.shape)
    except ValueError:
        raise ValueError(
            f'Expected `e_R_deg` and `e_t` to have broadcastable shapes, '
            f'got {rot.shape} and {tra.shape}.'
        ) from None
    with np.errstate(invalid='ignore'):
        failed = (
            ~(np.isfinite(rot) & np.isfinite(tra))
            | (rot > FAIL_ROTATION_DEG)
            | (tra > FAIL_TRANSLATION_M)
        )
    return np.asarray(failed, dtype=np.bool_)


# --------------------------------------------------------------------------------------------
# Trajectories


def _relative(T_world_sensor: FloatArray, delta: int) -> FloatArray:
    """``T_world_sensor[i]^-1 @ T_world_sensor[i + delta]`` for every ``i``, shape (N - delta,)."""
    return np.asarray(
        np.linalg.inv(T_world_sensor[:-delta]) @ T_world_sensor[delta:], dtype=np.float64
    )


def relative_poses(T_world_sensor: ArrayLike) -> FloatArray:
    """Relative transforms ``T_prev_curr`` between consecutive poses.

    ``T_prev_curr[i] = T_world_sensor[i]^-1 @ T_world_sensor[i + 1]`` maps points of scan
    ``i + 1`` into the frame of scan ``i``; chaining them,
    ``T_world_sensor[0] @ T_prev_curr[0] @ ... @ T_prev_curr[k - 1]``, gives back
    ``T_world_sensor[k]``. The general matrix inverse is used, so similarity transforms (e.g. a
    Sim(3)-aligned estimate) are handled too.

    Parameters
    ----------
    T_world_sensor : array_like, shape (N, 4, 4)
        Absolute poses, ``N >= 2``.

    Returns
    -------
    ndarray, shape (N - 1, 4, 4)

    Raises
    ------
    ValueError
        Wrong shape, fewer than 2 poses or invalid matrices (see :func:`as_poses`).
    """
    poses = as_poses(T_world_sensor, 'T_world_sensor', min_poses=2)
    return _relative(poses, 1)


def summarize(values: ArrayLike) -> Summary:
    """Count, mean, median, RMSE, 95th percentile and maximum of a set of errors.

    Parameters
    ----------
    values : array_like, shape (M,)
        Finite errors; other shapes are flattened.

    Returns
    -------
    Summary
        ``{'count', 'mean', 'median', 'rmse', 'p95', 'max'}`` as Python numbers; with no values
        ``count`` is 0 and the statistics are NaN.

    Raises
    ------
    ValueError
        Non-numeric or non-finite values.
    """
    arr = _as_float_array(values, 'values').ravel()
    _check_finite(arr, 'values')
    if arr.size == 0:
        nan = float('nan')
        return Summary(count=0, mean=nan, median=nan, rmse=nan, p95=nan, max=nan)
    return Summary(
        count=int(arr.size),
        mean=float(np.mean(arr)),
        median=float(np.median(arr)),
        rmse=float(np.sqrt(np.mean(arr**2))),
        p95=float(np.percentile(arr, 95.0)),
        max=float(np.max(arr)),
    )


def rpe(T_est: ArrayLike, T_gt: ArrayLike, delta: int = 1) -> RPEResult:
    """Relative pose error over pairs of frames ``delta`` apart (Sturm et al. [3]_).

    For every ``i`` the relative motions ``T_est[i]^-1 T_est[i + delta]`` and
    ``T_gt[i]^-1 T_gt[i + delta]`` are compared with :func:`pair_errors`. The trajectories need
    not share a world frame: only motions are compared.

    Parameters
    ----------
    T_est, T_gt : array_like, shape (N, 4, 4)
        Estimated and ground-truth absolute poses ``T_world_sensor``, associated frame by frame.
    delta : int
        Frame offset of the pairs, ``1 <= delta < N``.

    Returns
    -------
    RPEResult
        ``delta``; ``e_R_deg`` and ``e_t`` of shape ``(N - delta,)`` (degrees, metres) and their
        :func:`summarize` statistics ``rotation_deg`` and ``translation_m``.

    Raises
    ------
    ValueError
        Invalid poses, different lengths or an out-of-range ``delta``.
    """
    est, gt = _as_pose_pair(T_est, T_gt, ('T_est', 'T_gt'), min_poses=2)
    delta = _check_delta(delta, est.shape[0])
    e_R, e_t = _pair_errors(_relative(est, delta), _relative(gt, delta))
    return RPEResult(
        delta=delta,
        e_R_deg=e_R,
        e_t=e_t,
        rotation_deg=summarize(e_R),
        translation_m=summarize(e_t),
    )


def _path_length(T_world_sensor: FloatArray) -> FloatArray:
    """Cumulative distance travelled along the positions, shape (N,), starting at 0."""
    steps = np.linalg.norm(np.diff(T_world_sensor[:, :3, 3], axis=0), axis=1)
    return np.concatenate(([0.0], np.cumsum(steps)))


def rpe_per_metre(
    T_est: ArrayLike,
    T_gt: ArrayLike,
    delta: int = 1,
    *,
    min_distance: float = RPE_MIN_DISTANCE,
) -> RPEPerMetreResult:
    """Translation RPE divided by the ground-truth distance travelled over each pair, in %.

    ``e_t_pct[i] = 100 * e_t[i] / d[i]`` where ``e_t`` is the translation RPE of the pair
    ``(i, i + delta)`` and ``d[i]`` the ground-truth path length from frame ``i`` to
    ``i + delta`` (the sum of the step lengths, as in the KITTI devkit). Pairs with
    ``d[i] < min_distance`` are skipped: when the sensor (nearly) stands still the ratio is
    dominated by ground-truth noise and is meaningless. The default of 5 cm keeps every pair of
    a platform faster than 0.5 m/s at 10 Hz with ``delta=1``.

    Parameters
    ----------
    T_est, T_gt : array_like, shape (N, 4, 4)
        Estimated and ground-truth absolute poses, associated frame by frame.
    delta : int
        Frame offset of the pairs, ``1 <= delta < N``.
    min_distance : float
        Smallest ground-truth distance of a kept pair, in metres (``> 0``).

    Returns
    -------
    RPEPerMetreResult
        ``delta``, ``min_distance``; ``index`` (M,) the first frame of each kept pair,
        ``distance_m`` (M,) its ground-truth distance, ``e_t_pct`` (M,) its error in %,
        ``n_skipped`` the number of skipped pairs and ``translation_pct`` the
        :func:`summarize` of ``e_t_pct`` (count 0 and NaN if every pair was skipped).

    Raises
    ------
    ValueError
        Invalid poses, different lengths, an out-of-range ``delta`` or ``min_distance <= 0``.
    """
    est, gt = _as_pose_pair(T_est, T_gt, ('T_est', 'T_gt'), min_poses=2)
    delta = _check_delta(delta, est.shape[0])
    if not (np.isfinite(min_distance) and min_distance > 0.0):
        raise ValueError(f'Expected `min_distance` to be positive, got {min_distance!r}.')
    _, e_t = _pair_errors(_relative(est, delta), _relative(gt, delta))
    dist = _path_length(gt)
    distance = dist[delta:] - dist[:-delta]
    keep = distance >= min_distance
    n_skipped = int((~keep).sum())
    if n_skipped:
        logger.debug(
            'rpe_per_metre: skipped %d of %d pairs with ground-truth motion below %g m.',
            n_skipped,
            keep.size,
            min_distance,
        )
    e_t_pct = 100.0 * e_t[keep] / distance[keep]
    return RPEPerMetreResult(
        delta=delta,
        min_distance=float(min_distance),
        index=np.flatnonzero(keep).astype(np.int64),
        distance_m=distance[keep],
        e_t_pct=e_t_pct,
        n_skipped=n_skipped,
        translation_pct=summarize(e_t_pct),
    )


# --------------------------------------------------------------------------------------------
# Alignment and ATE
