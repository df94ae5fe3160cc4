"""The outcome of a registration: :class:`RegistrationResult`, its statuses, and the
covariance and degeneracy read off the final information matrices."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core.config import Mode

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
    #: Found without a start, but a distinct pose fits about as well (``alternatives``): the
    #: data cannot say which; the best-fitting one is given.
    AMBIGUOUS = 'ambiguous'
    #: Found without a start, but the points do not vouch for it: too little of the source
    #: lands on matching surfaces, or its rays pass through the target's surfaces (a missed
    #: translation, a place it is not in). The estimate is given, not to be trusted.
    UNVERIFIED = 'unverified'
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
    status : Status
        ``CONVERGED``, ``MAX_ITERATIONS``, ``DEGENERATE`` or ``FAILED`` (a ``StrEnum``: it
        compares equal to ``'converged'``, ...).
    message : str
        Human-readable explanation of the status.
    kappa, beta : ndarray, shape (K,)
        Final Kent concentration and ovalness per cluster.
    log_likelihood : tuple of float
        EM log-likelihood history (concatenated over clusters in paper mode).
    inlier_fraction : float
        Fraction of source points kept as inliers by the last stage.
    covariance : ndarray, shape (6, 6)
        Covariance of the estimate's error in the order (x, y, z, roll, pitch, yaw) of
        nav_msgs/Odometry, for the left perturbation ``T_true = exp(delta) T_target_source``
        in the target frame: ``delta = (t_true - dR t, log(dR))`` with
        ``dR = R_true R^T``. Robust mode: the final fit's robust-cost curvature and the
        scatter of its residuals, counted per surface patch and calibrated on simulated
        sequences with exact poses, inflated along the directions the degeneracy test leaves
        unresolved (:mod:`~kentreg_ros.core.registration.uncertainty`; docs/covariance.md).
    degenerate : bool
        True when some direction of motion is not constrained by the scene.
    degenerate_directions : ndarray, shape (D, 3)
        Translation directions (target frame) that are poorly constrained.
    timings : dict of str to float
        Milliseconds per stage: ``prepare_source`` and ``prepare_target`` (about 0 for a
        scan given prepared), ``rotation``, ``translation``, ``refine``, ``covariance`` and
        ``fit`` (robust mode), ``search`` (when the start-free search ran) and ``total``; a
        stage run more than once (for several candidate poses) reports the sum.
    stages : dict
        ``T_target_source`` after each stage (rotation, translation, refine).
    mode : Mode
        The recipe that ran (``ROBUST`` or ``PAPER``).
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
    alternative_covariances : tuple of ndarray (6, 6)
        The covariance of each of ``alternatives``, made as ``covariance`` is for this pose
        (a caller that takes an alternative reports that pose's uncertainty, not this one's).
    resolution : ndarray, shape (6, 6) or None
        How finely the fit locates its minimum: the first-order least-squares covariance
        ``sigma^2 H^-1`` of the final iteration (independent residuals of one variance, the
        IRLS information), in the order of ``covariance``; several times smaller than the
        pose's error, which ``covariance`` gives. None: as ``covariance``.
    """

    T_target_source: FloatArray
    converged: bool
    iterations: int
    status: Status
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
    mode: Mode
    n_source: int
    n_target: int
    fit: float = float('nan')
    hypotheses: int = 0
    ambiguous: bool = False
    alternatives: tuple[tuple[FloatArray, float], ...] = ()
    alternative_covariances: tuple[FloatArray, ...] = ()
    resolution: FloatArray | None = None

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


@dataclass(frozen=True, eq=False)
class PoseEvidence:
    """What a recipe (:mod:`.robust`, :mod:`.paper`) found for its pose: the evidence
    :func:`finish_result` judges into a status and a message.

    Attributes
    ----------
    T_target_source : ndarray, shape (4, 4)
    converged : bool
        The last stage met its tolerance.
    iterations : int
        EM plus translation and refinement iterations.
    kappa, beta : ndarray, shape (K,)
        The EM's Kent concentration and ovalness per cluster.
    log_likelihood : tuple of float
        The EM's log-likelihood history.
    inlier_fraction : float
        Share of the source points with a correspondence at the last stage.
    covariance : ndarray, shape (6, 6)
        Order (x, y, z, roll, pitch, yaw).
    degenerate_directions : ndarray, shape (D, 3)
        Poorly constrained translation directions (target frame).
    rotation_degenerate : bool
        The rotation information has a near-null direction.
    stages : dict of str to ndarray (4, 4)
        ``T_target_source`` after each stage.
    fit, hypotheses, ambiguous, alternatives, alternative_covariances, resolution
        As in :class:`RegistrationResult` (robust mode; the defaults in paper mode).
    """

    T_target_source: FloatArray
    converged: bool
    iterations: int
    kappa: FloatArray
    beta: FloatArray
    log_likelihood: tuple[float, ...]
    inlier_fraction: float
    covariance: FloatArray
    degenerate_directions: FloatArray
    rotation_degenerate: bool
    stages: dict[str, FloatArray]
    fit: float = float('nan')
    hypotheses: int = 0
    ambiguous: bool = False
    alternatives: tuple[tuple[FloatArray, float], ...] = ()
    alternative_covariances: tuple[FloatArray, ...] = ()
    resolution: FloatArray | None = None

    @property
    def degenerate(self) -> bool:
        """Some translation direction or the rotation is poorly constrained."""
        return len(self.degenerate_directions) > 0 or self.rotation_degenerate


def finish_result(
    evidence: PoseEvidence,
    *,
    mode: Mode,
    n_source: int,
    n_target: int,
    timings: dict[str, float],
) -> RegistrationResult:
    """The :class:`RegistrationResult` of ``evidence``: its status and message.

    A pose that is not finite, or at which fewer than :data:`MIN_INLIER_FRACTION` of the
    source points found a correspondence, is ``FAILED`` (its ``T_target_source`` NaN when not
    finite); else a degenerate one is ``DEGENERATE``; else ``CONVERGED`` or
    ``MAX_ITERATIONS``.
    """
    ev = evidence
    T, inlier, deg_dirs = ev.T_target_source, ev.inlier_fraction, ev.degenerate_directions
    if not np.isfinite(T).all():
        status, message = Status.FAILED, 'The estimate is not finite.'
        T = np.full((4, 4), np.nan)
    elif inlier < MIN_INLIER_FRACTION:
        status = Status.FAILED
        message = (
            f'Only {inlier:.1%} of the source points found a correspondence; the clouds '
            'do not overlap at this pose.'
        )
    elif ev.degenerate:
        status = Status.DEGENERATE
        parts = []
        if len(deg_dirs):
            dirs = ', '.join(np.array2string(d, precision=2) for d in deg_dirs)
            parts.append(f'translation along {dirs} is poorly constrained')
        if ev.rotation_degenerate:
            parts.append('rotation about one axis is poorly constrained by the normals')
        message = 'Degenerate scene: ' + '; '.join(parts) + '.'
    elif ev.converged:
        status, message = Status.CONVERGED, 'Converged.'
    else:
        status = Status.MAX_ITERATIONS
        message = 'Stopped at the iteration limit before meeting the tolerance.'
    return RegistrationResult(
        T_target_source=T,
        converged=bool(ev.converged and status != Status.FAILED),
        iterations=int(ev.iterations),
        status=status,
        message=message,
        kappa=ev.kappa,
        beta=ev.beta,
        log_likelihood=ev.log_likelihood,
        inlier_fraction=float(inlier),
        covariance=ev.covariance,
        degenerate=ev.degenerate,
        degenerate_directions=deg_dirs,
        timings=timings,
        stages=ev.stages,
        mode=mode,
        n_source=n_source,
        n_target=n_target,
        fit=ev.fit,
        hypotheses=ev.hypotheses,
        ambiguous=ev.ambiguous,
        alternatives=ev.alternatives,
        alternative_covariances=ev.alternative_covariances,
        resolution=ev.resolution,
    )
