"""``mode='paper'``: Algorithms 1 and 2 of Fahandezh-Saadi et al. as written: both clouds
clustered separately and the clusters paired, the per-cluster EM with per-model-normal Kent
components, rotation averaging (the paper's eq. rot_avg) and ``t = mu_y - R mu_x``."""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.errors import KentRegError
from kentreg_ros.core.geometry import make_transform, rotation_angle
from kentreg_ros.core.registration.em import EMResult, paper_cluster_em
from kentreg_ros.core.registration.result import (
    PoseEvidence,
    information_to_covariance,
    rotation_degenerate,
)
from kentreg_ros.core.registration.rotations import average_rotations
from kentreg_ros.core.registration.translation import centroid_translation
from kentreg_ros.core.scan.prepared import PreparedScan
from kentreg_ros.core.stopwatch import Stopwatch

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


def _subsample(idx: NDArray[np.intp], limit: int, rng: np.random.Generator) -> NDArray[np.intp]:
    if len(idx) <= limit:
        return idx
    return np.sort(rng.choice(idx, size=limit, replace=False))


def register_paper(
    src: PreparedScan,
    tgt: PreparedScan,
    T_init: FloatArray,
    cfg: KentRegConfig,
    *,
    watch: Stopwatch,
) -> PoseEvidence:
    """Algorithms 1 and 2 of the paper, as written; stages timed on ``watch``.

    Raises
    ------
    KentRegError
        No pair of clusters has enough normals for the EM.
    """
    em_cfg = cfg.em
    R0 = T_init[:3, :3]
    rng = np.random.default_rng(cfg.clustering.seed)
    with watch('rotation'):
        # Pair the separately clustered partitions by their mean directions under the start.
        sim = tgt.centers @ (src.centers @ R0.T).T
        rows, cols = linear_sum_assignment(-sim)
        results: list[EMResult] = []
        for i, j in zip(rows, cols, strict=True):
            yi = _subsample(np.flatnonzero(tgt.labels == i), em_cfg.max_points_per_cluster, rng)
            xj = _subsample(np.flatnonzero(src.labels == j), em_cfg.max_points_per_cluster, rng)
            if len(yi) < 3 or len(xj) < 3:
                continue
            results.append(
                paper_cluster_em(
                    tgt.normals[yi],
                    src.normals[xj],
                    R0,
                    outlier_weight=em_cfg.outlier_weight,
                    max_iterations=em_cfg.max_iterations,
                    tolerance=em_cfg.tolerance,
                )
            )
        if not results:
            raise KentRegError('No cluster pair had enough normals for the EM.')
        R = average_rotations(np.array([r.R for r in results]))
    with watch('translation'):
        t = centroid_translation(R, src.points, tgt.points)
    watch.add('refine', 0.0)  # the paper has no refinement
    T = make_transform(R, t)
    H_rot = np.sum([r.hessian for r in results], axis=0)
    covariance = np.zeros((6, 6))
    covariance[3:, 3:] = information_to_covariance(H_rot)
    cov_t = np.cov(tgt.points.T) / len(tgt) + R @ np.cov(src.points.T) @ R.T / len(src)
    covariance[:3, :3] = cov_t
    spread = max(rotation_angle(r.R.T @ R) for r in results)
    if spread > np.radians(2.0):
        logger.debug(
            'Paper mode: per-cluster rotations spread %.2f deg before averaging.',
            np.degrees(spread),
        )
    return PoseEvidence(
        T_target_source=T,
        converged=all(r.converged for r in results),
        iterations=sum(r.iterations for r in results),
        kappa=np.concatenate([r.kappa for r in results]),
        beta=np.concatenate([r.beta for r in results]),
        log_likelihood=tuple(v for r in results for v in r.log_likelihood),
        inlier_fraction=float(np.mean([r.inlier_fraction for r in results])),
        covariance=covariance,
        degenerate_directions=np.zeros((0, 3)),
        rotation_degenerate=rotation_degenerate(H_rot, cfg.translation.degeneracy_ratio),
        stages={'rotation': make_transform(R, T_init[:3, 3]), 'translation': T},
    )
