"""The registration facade: ``register(source, target) -> RegistrationResult``.

Pipeline (``mode='robust'``, the default)::

    prepare_scan (crop, voxel downsample, PCA normals, cosine outlier removal, spherical
    k-means)  ->  rotation: shared-rotation Kent EM over the model's clusters  ->  translation:
    plane-offset cross-correlation start + robust 3-DOF point-to-plane  ->  joint 6-DOF
    refinement on positions and Kent-weighted normals.

``mode='paper'`` runs Algorithms 1 and 2 of Fahandezh-Saadi et al. as written: both clouds
clustered separately and clusters paired, per-cluster EM with per-model-normal Kent components,
rotation averaging (the paper's eq. rot_avg), and ``t = mu_y - R mu_x``.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core.config import KentRegConfig, Mode, SearchMode
from kentreg_ros.core.errors import InvalidInputError
from kentreg_ros.core.geometry import check_transform, make_transform
from kentreg_ros.core.registration.paper import register_paper
from kentreg_ros.core.registration.result import RegistrationResult, Status, finish_result
from kentreg_ros.core.registration.robust import register_robust
from kentreg_ros.core.registration.verify import free_space_violation
from kentreg_ros.core.scan.prepared import PreparedScan, as_prepared
from kentreg_ros.core.stopwatch import Stopwatch

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


__all__ = ['register']


def register(
    source: ArrayLike | PreparedScan,
    target: ArrayLike | PreparedScan,
    *,
    init: ArrayLike | None = None,
    config: KentRegConfig | None = None,
    source_normals: ArrayLike | None = None,
    target_normals: ArrayLike | None = None,
    viewpoint: ArrayLike = (0.0, 0.0, 0.0),
    global_search: bool | None = None,
) -> RegistrationResult:
    """Estimate ``T_target_source``, the rigid transform taking source points into the target.

    In the paper's words the target is the *model* and the source the *observed* cloud.

    Parameters
    ----------
    source, target : array_like, shape (N, 3), or PreparedScan
        Point clouds (finite, same unit), or scans prepared by :func:`prepare_scan` (the
        odometry prepares every scan once and reuses it as the next model).
    init : array_like, shape (4, 4), optional
        Initial guess of ``T_target_source`` (default identity).
    config : KentRegConfig, optional
        Default ``KentRegConfig()`` (robust mode).
    source_normals, target_normals : array_like, shape (N, 3), optional
        Precomputed normals (see :func:`prepare_scan`).
    viewpoint : array_like, shape (3,)
        Sensor origin in each cloud's own frame, used to orient normals.
    global_search : bool, optional
        Search SO(3) from the two clouds' normal mixtures
        (:mod:`kentreg_ros.core.registration.search`) instead of starting only from
        ``init``. Default from ``search.mode``: with 'auto', search when ``init`` is not
        given. Robust mode only.

    Returns
    -------
    RegistrationResult
        Not converging or a degenerate scene is a status, never an exception; a result is
        never silently the identity.

    Raises
    ------
    InvalidPointCloudError
        Malformed clouds: wrong shape, NaN/inf, too few points.
    InvalidInputError
        A malformed ``init``, ``viewpoint`` or ``config``.
    """
    cfg = config or KentRegConfig()
    if not isinstance(cfg, KentRegConfig):
        raise InvalidInputError(
            f'Expected `config` to be a KentRegConfig, got {type(cfg).__name__}.'
        )
    watch = Stopwatch()
    T_init = np.eye(4) if init is None else check_transform(init, 'init')
    with watch('prepare_source'):
        src = as_prepared(source, source_normals, cfg, viewpoint, 'source')
    with watch('prepare_target'):
        tgt = as_prepared(target, target_normals, cfg, viewpoint, 'target')
    if cfg.mode == Mode.PAPER:
        evidence = register_paper(src, tgt, T_init, cfg, watch=watch)
    else:
        if global_search is None:
            global_search = cfg.search.mode == SearchMode.ALWAYS or (
                cfg.search.mode == SearchMode.AUTO and init is None
            )
        evidence = register_robust(src, tgt, T_init, cfg, watch=watch, search=global_search)
    result = finish_result(
        evidence, mode=cfg.mode, n_source=len(src), n_target=len(tgt), timings=watch.as_dict()
    )
    if init is None and global_search and cfg.mode == Mode.ROBUST:
        with watch('vouch'):
            result = _vouched(result, src, tgt, cfg)
    watch.add('total', watch.elapsed_ms())
    return replace(result, timings=watch.as_dict())


def _vouched(
    result: RegistrationResult, src: PreparedScan, tgt: PreparedScan, cfg: KentRegConfig
) -> RegistrationResult:
    """A pose found without any start, judged on the points as a localization is: too little
    of the source on matching surfaces (``localization.min_fit``) or its rays through the
    target's surfaces (``localization.max_violation``) make it ``unverified`` (a missed
    translation, another place); otherwise a distinct rival fitting about as well makes it
    ``ambiguous`` (a twin), unless it is ``degenerate``, which already says which direction is
    not held. Never ``converged`` then.
    """
    if result.status == Status.FAILED:
        return result
    loc = cfg.localization
    T = result.T_target_source @ make_transform(np.eye(3), src.viewpoint)
    spacing = max(src.voxel_size, tgt.voxel_size)
    violation, reached = free_space_violation(src.points - src.viewpoint, tgt.points, T, spacing)
    why = ''
    if not result.fit >= loc.min_fit:
        why = f'only {result.fit:.0%} of the source lands on matching surfaces'
    elif reached >= loc.min_visible and violation > loc.max_violation:
        why = f'the source sees through {violation:.0%} of the target points its rays reach'
    if why:
        message = (
            f'Unverified: found without a start, but {why} (localization.min_fit='
            f'{loc.min_fit}, max_violation={loc.max_violation}): a missed translation or '
            'another place.'
        )
        return replace(result, status=Status.UNVERIFIED, converged=False, message=message)
    if result.ambiguous and result.status != Status.DEGENERATE:
        n = len(result.alternatives)
        message = (
            f'Ambiguous: found without a start, but {n} distinct pose(s) fit about as well '
            f'(fit {result.fit:.2f}; see alternatives).'
        )
        return replace(result, status=Status.AMBIGUOUS, converged=False, message=message)
    return result
