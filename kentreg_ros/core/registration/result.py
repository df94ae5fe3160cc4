"""The outcome of a registration: :class:`RegistrationResult`, its statuses, and the
covariance and degeneracy read off the final information matrices."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core.registration.em import EMResult
from kentreg_ros.core.scan.prepared import PreparedScan

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


#: Below this share of source points with a correspondence the clouds do not overlap at the
#: pose found: the result is 'failed'. Scan-to-scan overlap is rarely under a half; a twentieth
#: is left by a pose that matches a single surface by accident.
MIN_INLIER_FRACTION = 0.05


class Status(StrEnum):
    """Outcome of a registration: a status, never an exception, and never a silent identity."""

    #: The estimate converged.
    CONVERGED = 'converged'
    #: The iteration limit stopped it (the estimate is used).
    MAX_ITERATIONS = 'max_iterations'
    #: Some direction is poorly constrained (the estimate is used, flagged).
    DEGENERATE = 'degenerate'
    #: No usable estimate: no overlap, or not finite.
    FAILED = 'failed'


@dataclass(frozen=True, eq=False)
class RegistrationResult:
    """Outcome of :func:`register`.

    Attributes
    ----------
    T_target_source : ndarray, shape (4, 4)
        Maps source points into the target frame: ``p_target = R p_source + t``.
    converged : bool
    iterations : int
        EM iterations plus translation and refinement iterations.
    status : str
        ``'converged'``, ``'max_iterations'``, ``'degenerate'`` or ``'failed'``.
    message : str
        Human-readable explanation of the status.
    kappa, beta : ndarray, shape (K,)
        Final Kent concentration and ovalness per cluster.
    log_likelihood : tuple of float
        EM log-likelihood history (concatenated over clusters in paper mode).
    inlier_fraction : float
        Fraction of source points kept as inliers by the last stage.
    covariance : ndarray, shape (6, 6)
        Covariance of the estimate in the order (x, y, z, roll, pitch, yaw) of
        nav_msgs/Odometry, from the information matrix of the final fit.
    degenerate : bool
        True when some direction of motion is not constrained by the scene.
    degenerate_directions : ndarray, shape (D, 3)
        Translation directions (target frame) that are poorly constrained.
    timings : dict
        Milliseconds per stage.
    stages : dict
        ``T_target_source`` after each stage (rotation, translation, refine).
    mode : str
    n_source, n_target : int
        Points used after preprocessing.
    fit : float
        Balanced fit of the pose in [0, 1]
        (:func:`kentreg_ros.core.registration.verify.balanced_fit`): the share of source
        points landing on a target surface of the same orientation, averaged over the
        target's normal clusters. NaN in paper mode.
    hypotheses : int
        Rotation hypotheses scored by the start-free search (0 when it did not run).
    ambiguous : bool
        Another pose, distinct from this one, fits nearly as well (``search.ambiguity_ratio``):
        symmetric scenes (rooms, corridors) have such twins.
    alternatives : tuple of (ndarray (4, 4), float)
        The distinct other poses the search refined, with their fits.
    """

    T_target_source: FloatArray
    converged: bool
    iterations: int
    status: str
    message: str
    kappa: FloatArray
    beta: FloatArray
    log_likelihood: tuple[float, ...]
    inlier_fraction: float
    covariance: FloatArray
    degenerate: bool
    degenerate_directions: FloatArray
    timings: dict[str, float]
    stages: dict[str, FloatArray]
    mode: str
    n_source: int
    n_target: int
    fit: float = float('nan')
    hypotheses: int = 0
    ambiguous: bool = False
    alternatives: tuple[tuple[FloatArray, float], ...] = ()

    @property
    def ok(self) -> bool:
        """True unless the status is ``'failed'``."""
        return self.status != Status.FAILED


def rotation_degenerate(H: FloatArray, ratio: float) -> bool:
    """True when the rotation information matrix has an eigenvalue below ``ratio`` x largest."""
    evals = np.linalg.eigvalsh(0.5 * (H + H.T))
    return bool(evals[0] < ratio * max(float(evals[-1]), 1e-300))


def information_to_covariance(H: FloatArray) -> FloatArray:
    """Pseudo-inverse of an information matrix; null directions get a variance of 1e6."""
    Hs = 0.5 * (H + H.T)
    evals, evecs = np.linalg.eigh(Hs)
    inv = np.where(
        evals > 1e-9 * max(float(evals[-1]), 1e-300), 1.0 / np.maximum(evals, 1e-300), 1e6
    )
    return (evecs * inv) @ evecs.T


def finish_result(
    T: FloatArray,
    converged: bool,
    iterations: int,
    em: EMResult,
    inlier: float,
    covariance: FloatArray,
    degenerate: bool,
    deg_dirs: FloatArray,
    rot_degenerate: bool,
    timings: dict[str, float],
    stages: dict[str, FloatArray],
    mode: str,
    src: PreparedScan,
    tgt: PreparedScan,
    history: list[float],
) -> RegistrationResult:
    if not np.isfinite(T).all():
        status, message = Status.FAILED, 'The estimate is not finite.'
        T = np.full((4, 4), np.nan)
    elif inlier < MIN_INLIER_FRACTION:
        status = Status.FAILED
        message = (
            f'Only {inlier:.1%} of the source points found a correspondence; the clouds '
            'do not overlap at this pose.'
        )
    elif degenerate:
        status = Status.DEGENERATE
        parts = []
        if len(deg_dirs):
            dirs = ', '.join(np.array2string(d, precision=2) for d in deg_dirs)
            parts.append(f'translation along {dirs} is poorly constrained')
        if rot_degenerate:
            parts.append('rotation about one axis is poorly constrained by the normals')
        message = 'Degenerate scene: ' + '; '.join(parts) + '.'
    elif converged:
        status, message = Status.CONVERGED, 'Converged.'
    else:
        status = Status.MAX_ITERATIONS
        message = 'Stopped at the iteration limit before meeting the tolerance.'
    return RegistrationResult(
        T_target_source=T,
        converged=bool(converged and status != Status.FAILED),
        iterations=int(iterations),
        status=status,
        message=message,
        kappa=em.kappa,
        beta=em.beta,
        log_likelihood=tuple(history),
        inlier_fraction=float(inlier),
        covariance=covariance,
        degenerate=degenerate,
        degenerate_directions=deg_dirs,
        timings=timings,
        stages=stages,
        mode=mode,
        n_source=len(src),
        n_target=len(tgt),
    )
