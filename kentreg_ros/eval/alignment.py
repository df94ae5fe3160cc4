"""Absolute trajectory error: the closed-form similarity/rigid alignment of two trajectories
(Umeyama 1991) and the ATE after it."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core import DegenerateSceneError
from kentreg_ros.eval.metrics import (
    Summary,
    _as_float_array,
    _as_pose_pair,
    _check_finite,
    summarize,
)

FloatArray = NDArray[np.float64]


class ATEResult(Summary):
    """Absolute trajectory error: :class:`Summary` of the position errors plus the alignment."""

    errors: FloatArray
    T_gt_est: FloatArray
    scale: float
    aligned: bool


def align_umeyama(src: ArrayLike, dst: ArrayLike, with_scale: bool = False) -> FloatArray:
    """Least-squares rigid (or similarity) transform mapping ``src`` onto ``dst`` (Umeyama [4]_).

    Minimises ``sum_i ||dst_i - (c R src_i + t)||^2`` over rotations ``R`` (``det R = +1``, the
    reflection case is handled as in [4]_), translations ``t`` and, if ``with_scale``, a scale
    ``c > 0`` (Sim(3)); otherwise ``c = 1`` (SE(3)). If the points are collinear the rotation
    about their line is not determined and one minimiser is returned.

    Parameters
    ----------
    src, dst : array_like, shape (N, 3)
        Corresponding points, ``N >= 3``.
    with_scale : bool
        Estimate a scale as well.

    Returns
    -------
    ndarray, shape (4, 4)
        ``T_dst_src`` with top-left block ``c R`` and translation ``t``: ``dst ~ T_dst_src @ src``.

    Raises
    ------
    ValueError
        Wrong shapes, different ``N`` or non-finite entries.
    DegenerateSceneError
        Fewer than 3 points, or all ``src`` points coincide while ``with_scale`` is requested.
    """
    source = _as_float_array(src, 'src')
    target = _as_float_array(dst, 'dst')
    for arr, name in ((source, 'src'), (target, 'dst')):
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise ValueError(f'Expected `{name}` to have shape (N, 3), got {arr.shape}.')
        _check_finite(arr, name)
    if source.shape[0] != target.shape[0]:
        raise ValueError(
            'Expected `src` and `dst` to have the same number of points, '
            f'got {source.shape[0]} and {target.shape[0]}.'
        )
    n = source.shape[0]
    if n < 3:
        raise DegenerateSceneError(f'Umeyama alignment needs at least 3 points, got {n}.')
    mu_src = source.mean(axis=0)
    mu_dst = target.mean(axis=0)
    src_c = source - mu_src
    dst_c = target - mu_dst
    cov = dst_c.T @ src_c / n  # Sigma_xy of [4], eq. (38)
    U, D, Vt = np.linalg.svd(cov)
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        S[2] = -1.0
    R = (U * S) @ Vt
    scale = 1.0
    if with_scale:
        var_src = float(np.mean(np.sum(src_c**2, axis=1)))
        if var_src <= np.finfo(np.float64).eps * max(1.0, float(np.abs(source).max())) ** 2:
            raise DegenerateSceneError(
                'Umeyama alignment with scale needs `src` points that do not all coincide.'
            )
        scale = float(np.dot(D, S)) / var_src
    T = np.eye(4)
    T[:3, :3] = scale * R
    T[:3, 3] = mu_dst - scale * R @ mu_src
    return T


def ate(
    T_est: ArrayLike, T_gt: ArrayLike, align: bool = True, *, with_scale: bool = False
) -> ATEResult:
    """Absolute trajectory error: position error after aligning the estimate to ground truth.

    With ``align`` the estimated positions are first mapped into the ground-truth world frame
    by the SE(3) (Sim(3) with ``with_scale``) transform ``T_gt_est`` of :func:`align_umeyama`
    (Sturm et al. [3]_); only positions enter, as in [3]_.

    Parameters
    ----------
    T_est, T_gt : array_like, shape (N, 4, 4)
        Estimated and ground-truth absolute poses, associated frame by frame; ``N >= 3`` when
        aligning.
    align : bool
        Align before measuring; otherwise ``T_gt_est`` is the identity.
    with_scale : bool
        Also estimate a scale (monocular-style evaluation); ignored without ``align``.

    Returns
    -------
    ATEResult
        The :func:`summarize` keys (``count``, ``mean``, ``median``, ``rmse``, ``p95``, ``max``)
        of the position errors in metres, plus ``errors`` (N,), ``T_gt_est`` (4, 4), ``scale``
        (1.0 unless ``with_scale``) and ``aligned``.

    Raises
    ------
    ValueError
        Invalid poses or different lengths.
    DegenerateSceneError
        Aligning fewer than 3 poses (see :func:`align_umeyama`).
    """
    est, gt = _as_pose_pair(T_est, T_gt, ('T_est', 'T_gt'))
    p_est = est[:, :3, 3]
    p_gt = gt[:, :3, 3]
    if align:
        T_gt_est = align_umeyama(p_est, p_gt, with_scale=with_scale)
        scale = float(np.cbrt(np.linalg.det(T_gt_est[:3, :3]))) if with_scale else 1.0
    else:
        T_gt_est = np.eye(4)
        scale = 1.0
    p_aligned = p_est @ T_gt_est[:3, :3].T + T_gt_est[:3, 3]
    errors = np.linalg.norm(p_aligned - p_gt, axis=1)
    stats = summarize(errors)
    return ATEResult(
        count=stats['count'],
        mean=stats['mean'],
        median=stats['median'],
        rmse=stats['rmse'],
        p95=stats['p95'],
        max=stats['max'],
        errors=errors,
        T_gt_est=T_gt_est,
        scale=scale,
        aligned=bool(align),
    )
