"""``mode='robust'``: the rotation from the Kent mixture EM (one rotation shared by all
clusters), the translation from plane offsets and point-to-plane, the joint refinement, the
balanced fit; without a start, the rotation hypotheses of
:mod:`kentreg_ros.core.registration.search` are verified the same way and the best-fitting
pose wins."""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.geometry import make_transform, rotation_angle, row_norms
from kentreg_ros.core.registration.correspondence import NearestNeighborCache
from kentreg_ros.core.registration.em import EMResult, shared_rotation_em
from kentreg_ros.core.registration.refine import RefineResult, refine_joint
from kentreg_ros.core.registration.result import (
    PoseEvidence,
    information_to_covariance,
    rotation_degenerate,
)
from kentreg_ros.core.registration.search import distinct_best, mixture_overlap, twist_hypotheses
from kentreg_ros.core.registration.translation import (
    centroid_translation,
    degenerate_directions,
    plane_offset_translation,
    point_to_plane_translation,
)
from kentreg_ros.core.registration.uncertainty import inflate_degenerate, pose_covariance
from kentreg_ros.core.registration.verify import (
    Candidate,
    Fit,
    FitGates,
    balanced_fit,
    choose_pose,
)
from kentreg_ros.core.scan.prepared import PreparedScan
from kentreg_ros.core.scan.sampling import stratified_sample
from kentreg_ros.core.stopwatch import Stopwatch

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


#: Nearest-neighbour gates shrink to this many sampling spacings: two samplings of one surface
#: put corresponding points up to about one spacing apart, so two keep every true match while
#: a point off the surface by more finds none.
GATE_FLOOR_SPACINGS = 2.0
#: The robust (Geman-McClure) scale never drops below this share of the spacing: voxel
#: centroids of two scans of one plane scatter about it by the sensor noise averaged over a
#: voxel's returns, a few percent of the spacing for LiDARs (1-3 cm of noise, tens of returns
#: per 0.1-0.5 m voxel); the floor keeps a noise-free synthetic scene from shrinking the kernel
#: to nothing.
NOISE_FLOOR_SPACINGS = 1.0 / 32.0
#: Target points sampled to measure the spacing of a cloud with no voxel grid.
SPACING_SAMPLE = 500


def sampling_spacing(src: PreparedScan, tgt: PreparedScan) -> float:
    """The clouds' sampling step: the larger voxel edge, or (no voxel grid) the median distance
    between neighbouring target points."""
    voxel = max(src.voxel_size, tgt.voxel_size)
    if voxel > 0.0:
        return voxel
    step = max(1, len(tgt) // SPACING_SAMPLE)
    d = tgt.tree.query(tgt.points[::step], k=2)[0][:, 1]
    return float(np.median(d))


@dataclass
class _Local:
    """A pose from the local stages (rotation EM, translation, refinement) and what they found."""

    T: FloatArray
    em: EMResult
    fit: Fit
    stages: dict[str, FloatArray]
    iterations: int
    converged: bool
    inlier: float
    H_trans: FloatArray
    source: PreparedScan
    neighbors: NearestNeighborCache
    refinement: RefineResult | None = None
    stage_covariance: FloatArray | None = None


@dataclass(frozen=True)
class _Gates:
    """Scales of one registration, from the sampling spacing (see the constants above)."""

    spacing: float
    max_gate: float
    min_gate: float
    noise_floor: float
    fit: FitGates

    @property
    def distinct(self) -> float:
        """Displacement beyond which two poses are distinct: twice the fit's distance gate, so
        that the two cannot match the same target points."""
        return 2.0 * self.fit.distance


def _gates(src: PreparedScan, tgt: PreparedScan, cfg: KentRegConfig) -> _Gates:
    spacing = sampling_spacing(src, tgt)
    min_gate = GATE_FLOOR_SPACINGS * spacing
    max_gate = max(cfg.refine.max_correspondence_distance, min_gate)
    noise_floor = NOISE_FLOOR_SPACINGS * spacing
    return _Gates(spacing, max_gate, min_gate, noise_floor, FitGates.for_spacing(spacing))


#: EM passes for ranking a search hypothesis: the annealing from ``em.kappa_cap_start`` = 20 by
#: doubling reaches the concentrations of real normal clusters (up to a few hundred) in 4-5
#: passes, which brings a hypothesis within a degree or so of its optimum: enough for the fit
#: gates (20 deg, 2 voxels) to tell right from wrong. The winners' EM is then continued.
SEARCH_EM_PASSES = 6


def _rotation_stage(
    src: PreparedScan,
    tgt: PreparedScan,
    R0: FloatArray,
    cfg: KentRegConfig,
    *,
    max_iterations: int | None = None,
    anneal: bool = True,
) -> EMResult:
    em_cfg = cfg.em
    return shared_rotation_em(
        src.clusters.bins,
        tgt.clusters,
        R0,
        outlier_weight=em_cfg.outlier_weight,
        use_beta=em_cfg.kent_beta,
        rotation=em_cfg.rotation,
        kappa_cap_start=em_cfg.kappa_cap_start if anneal else em_cfg.kappa_cap_end,
        kappa_cap_end=em_cfg.kappa_cap_end,
        kappa_cap_growth=em_cfg.kappa_cap_growth,
        max_iterations=max_iterations or em_cfg.max_iterations,
        tolerance=em_cfg.tolerance,
    )


@dataclass(frozen=True)
class _Translation:
    """What the translation stage found: ``t``, its normal matrix and residual variance (None
    and 0 for the centroid translation), the gate it ended at (where the refinement goes on),
    its inlier share (None: the centroid's, the EM's stands) and its iterations."""

    t: FloatArray
    hessian: FloatArray | None
    sigma2: float
    refine_gate: float
    inlier: float | None
    iterations: int


def _translation_starts(
    src: PreparedScan,
    tgt: PreparedScan,
    R: FloatArray,
    T0: FloatArray,
    cfg: KentRegConfig,
    gates: _Gates,
    stages: dict[str, FloatArray],
) -> list[FloatArray]:
    """Where the point-to-plane translation starts: the plane-offset cross-correlation's
    translation (recorded in ``stages``), and the prior's own when the two are distinct.

    The cross-correlation searches each cluster direction on its own, so a direction held by a
    few dozen scattered points (a sparse, narrow view: bushes, a far facade's edge) can put
    its peak metres off, and the least squares over the directions hands that error on to
    the weakly held axis, where the refinement's basin is narrow. A start farther from the
    prior's than the correspondence floor (two sampling spacings, the fit's distance gate:
    beyond it the points leave the surfaces they matched at the prior) is therefore a claim
    against the prior, which the fit of the two placed poses settles (:func:`_local`). Within
    that gate the correlation's start is used alone, as before: a step whose prediction is
    that good registers exactly as it did.
    """
    t = T0[:3, 3].copy()
    if not cfg.translation.cross_correlation:
        return [t]
    t_xc, _ = plane_offset_translation(
        R,
        t,
        src.points,
        src.normals,
        tgt.points,
        tgt.normals,
        tgt.centers,
        bin_size=0.5 * gates.min_gate / GATE_FLOOR_SPACINGS,  # half a spacing
        max_shift=cfg.translation.max_shift,
    )
    stages['cross_correlation'] = make_transform(R, t_xc)
    if float(np.linalg.norm(t_xc - t)) <= gates.min_gate:
        return [t_xc]
    return [t_xc, t]


def _translation_stage(
    src: PreparedScan,
    tgt: PreparedScan,
    R: FloatArray,
    t_start: FloatArray,
    cfg: KentRegConfig,
    gates: _Gates,
    neighbors: NearestNeighborCache,
) -> _Translation:
    """Robust point-to-plane translation with ``R`` fixed, from ``t_start``."""
    tr_cfg = cfg.translation
    tres = point_to_plane_translation(
        R,
        t_start,
        src.points,
        tgt.points,
        tgt.normals,
        tgt.tree,
        max_iterations=tr_cfg.max_iterations,
        max_distance=max(tr_cfg.max_correspondence_distance, gates.min_gate),
        min_distance=gates.min_gate,
        noise_floor=gates.noise_floor,
        degeneracy_ratio=tr_cfg.degeneracy_ratio,
        tolerance=tr_cfg.tolerance,
        neighbors=neighbors,
    )
    # One gate schedule across both stages: the translation stage has shrunk the gate while it
    # placed the source; the refinement goes on from there instead of re-opening it to
    # max_gate: the same errors for less time (docs/notes-registration.md).
    refine_gate = min(gates.max_gate, max(tres.gate, gates.min_gate))
    return _Translation(
        tres.t, tres.hessian, tres.sigma2, refine_gate, tres.inlier_fraction, tres.iterations
    )


#: (omega, v) -> (v, omega), i.e. (x, y, z, roll, pitch, yaw).
_TO_XYZ = [3, 4, 5, 0, 1, 2]


def _covariance(local: _Local, spacing: float) -> tuple[FloatArray, FloatArray]:
    """Covariance (x, y, z, roll, pitch, yaw) of a pose and its resolution: for a refinement,
    :func:`~kentreg_ros.core.registration.uncertainty.pose_covariance` and the first-order
    least-squares covariance ``sigma^2 H^-1`` of the last iteration (independent residuals of
    one variance); without one, the stages' (both the same). Only the chosen pose's is
    computed."""
    ref = local.refinement
    if ref is None:
        assert local.stage_covariance is not None  # a pose is refined or has the stages'
        return local.stage_covariance, local.stage_covariance
    info = ref.hessian[np.ix_(_TO_XYZ, _TO_XYZ)]
    resolution = max(ref.sigma2, 1e-12) * information_to_covariance(info)
    if ref.residuals is None:
        return resolution, resolution
    return pose_covariance(ref.residuals, spacing), resolution


def _stage_covariance(
    em: EMResult, trans: _Translation, src: PreparedScan
) -> tuple[FloatArray, FloatArray]:
    """Covariance and translation normal matrix without a refinement: the EM's rotation block,
    the translation stage's (or the points' spread over their number, for the centroids), to
    first order (an ablation's: the calibrated model is the refinement's)."""
    covariance = np.zeros((6, 6))
    covariance[3:, 3:] = information_to_covariance(em.hessian)
    if trans.hessian is not None:
        covariance[:3, :3] = max(trans.sigma2, 1e-12) * information_to_covariance(trans.hessian)
        return covariance, trans.hessian
    covariance[:3, :3] = np.eye(3) * float(np.var(src.points)) / len(src)
    return covariance, np.eye(3)


def _local(
    src: PreparedScan,
    tgt: PreparedScan,
    T0: FloatArray,
    cfg: KentRegConfig,
    gates: _Gates,
    watch: Stopwatch,
    *,
    em: EMResult | None = None,
    refine: bool = True,
    sample: PreparedScan | None = None,
) -> _Local:
    """Rotation EM from ``T0`` (unless ``em`` is given), translation, refinement, fit.

    The rotation stage uses every normal of ``src``; the position stages use its
    :func:`position_sample` (the centroid translation, the paper's, uses every point), given as
    ``sample`` when the caller registers the same source several times. When the
    cross-correlation's start and the prior's are distinct (:func:`_translation_starts`), both
    are placed and refined, and :func:`choose_pose` takes the better fit, the one nearer the
    prior when they fit about equally."""
    stages: dict[str, FloatArray] = {}
    if em is None:
        with watch('rotation'):
            em = _rotation_stage(src, tgt, T0[:3, :3], cfg)
    R = em.R
    stages['rotation'] = make_transform(R, T0[:3, 3])
    full = src
    src = sample if sample is not None else position_sample(src, cfg.refine.max_cluster_points)
    if cfg.translation.method == 'centroid':
        t = centroid_translation(R, full.points, tgt.points)
        trans = _Translation(t, None, 0.0, gates.max_gate, None, 0)
        neighbors = NearestNeighborCache(tgt.tree, tgt.points, len(src))
        return _placed(src, tgt, em, trans, cfg, gates, watch, stages, neighbors, refine)
    with watch('translation'):
        starts = _translation_starts(src, tgt, R, T0, cfg, gates, stages)
    placed: list[_Local] = []
    for t_start in starts:
        # One correspondence cache per start for the translation and refinement loops (same
        # source points, same target tree): points that moved less than their certified
        # radius skip the query.
        neighbors = NearestNeighborCache(tgt.tree, tgt.points, len(src))
        with watch('translation'):
            trans = _translation_stage(src, tgt, R, t_start, cfg, gates, neighbors)
        placed.append(
            _placed(src, tgt, em, trans, cfg, gates, watch, dict(stages), neighbors, refine)
        )
    if len(placed) == 1:
        return placed[0]
    return max(placed, key=lambda c: c.fit.score)


def _placed(
    src: PreparedScan,
    tgt: PreparedScan,
    em: EMResult,
    trans: _Translation,
    cfg: KentRegConfig,
    gates: _Gates,
    watch: Stopwatch,
    stages: dict[str, FloatArray],
    neighbors: NearestNeighborCache,
    refine: bool,
) -> _Local:
    """The pose of one translation: refined (unless ``refine`` is off) and fitted."""
    R = em.R
    T = make_transform(R, trans.t)
    stages['translation'] = T
    iterations, converged, inlier = (
        em.iterations + trans.iterations,
        em.converged,
        em.inlier_fraction,
    )
    if trans.inlier is not None:
        inlier = trans.inlier
    refined = refine and cfg.refine.method != 'none'
    with watch('refine'):
        if refined:
            ref = refine_joint(
                T,
                src.points,
                src.normals,
                tgt.points,
                tgt.normals,
                tgt.tree,
                method=cfg.refine.method,
                normal_weight=cfg.refine.normal_weight,
                max_iterations=cfg.refine.max_iterations,
                max_distance=trans.refine_gate,
                min_distance=gates.min_gate,
                tolerance=cfg.refine.tolerance,
                noise_floor=gates.noise_floor,
                neighbors=neighbors,
                max_step_scale=cfg.refine.max_step_scale,
            )
            T = ref.T
            stages['refine'] = T
            iterations += ref.iterations
            converged = ref.converged
            inlier = ref.inlier_fraction
            H_trans = ref.hessian[np.ix_(_TO_XYZ, _TO_XYZ)][:3, :3]
            stage_covariance = None
        else:
            ref = None
            stage_covariance, H_trans = _stage_covariance(em, trans, src)
    with watch('fit'):
        fit = balanced_fit(
            T, src.points, src.normals, tgt.normals, tgt.centers, gates.fit, neighbors=neighbors
        )
    return _Local(
        T=T,
        em=em,
        fit=fit,
        stages=stages,
        iterations=iterations,
        converged=converged,
        inlier=inlier,
        H_trans=H_trans,
        source=src,
        neighbors=neighbors,
        refinement=ref,
        stage_covariance=stage_covariance,
    )


def _search_candidates(
    src: PreparedScan,
    tgt: PreparedScan,
    T_init: FloatArray,
    cfg: KentRegConfig,
    gates: _Gates,
    watch: Stopwatch,
) -> tuple[list[_Local], int]:
    """Start-free search: twist hypotheses ranked by the mixture overlap, the distinct best
    refined by the EM and placed by the translation stage, then verified by their fit; every
    candidate that fits nearly as well as the best is refined in full."""
    sample = position_sample(src, cfg.refine.max_cluster_points)  # once for every candidate
    scfg = cfg.search
    with watch('search'):
        hyp = twist_hypotheses(src.clusters, tgt.clusters, scfg.twist_step_deg)
        cap = 1.0 / np.radians(scfg.twist_step_deg) ** 2
        scores = mixture_overlap(hyp, src.clusters, tgt.clusters, cap)
        chosen = distinct_best(hyp, scores, scfg.candidates, scfg.min_separation_deg)
        starts = [T_init[:3, :3]] + [hyp[i] for i in chosen]
    cheap: list[_Local] = []
    seen: list[FloatArray] = []
    for R0 in starts:
        with watch('rotation'):
            em = _rotation_stage(src, tgt, R0, cfg, max_iterations=SEARCH_EM_PASSES)
        if any(rotation_angle(em.R.T @ R) < np.radians(scfg.min_separation_deg) for R in seen):
            continue  # converged onto a rotation already under consideration
        seen.append(em.R)
        T0 = make_transform(em.R, T_init[:3, 3])
        cheap.append(_local(src, tgt, T0, cfg, gates, watch, em=em, refine=False, sample=sample))
    best_cheap = max(c.fit.score for c in cheap)
    out: list[_Local] = []
    for cand in sorted(cheap, key=lambda c: -c.fit.score):
        if cand.fit.score >= scfg.ambiguity_ratio * best_cheap or not out:
            with watch('rotation'):
                em = _rotation_stage(src, tgt, cand.em.R, cfg, anneal=False)
            T0 = make_transform(em.R, T_init[:3, 3])
            out.append(_local(src, tgt, T0, cfg, gates, watch, em=em, sample=sample))
    return out, len(hyp)


def _unresolved(
    directions: FloatArray, best: _Local, tgt: PreparedScan, gates: _Gates, ratio: float
) -> FloatArray:
    """The weakly held translation directions along which the data cannot tell the pose apart
    from one moved along them: the pose moved by :attr:`_Gates.distinct` either way fits at
    least ``ratio`` times as well (the ambiguity rule of
    :func:`~kentreg_ros.core.registration.verify.choose_pose`, applied along a line).

    The eigenvalue test on the normal matrix (``translation.degeneracy_ratio``) only nominates
    directions: its weights are the robust kernel's and the normals' agreement, which shrink
    on sparse or noisy surfaces (a narrow view with a few dozen points on its side surfaces
    holds a direction to centimetres with 1-2 % of the largest eigenvalue), while in a corridor
    or on a single plane the points slide along the direction and keep matching surfaces.
    """
    src = best.source
    R, t = best.T[:3, :3], best.T[:3, 3]
    kept = []
    for d in directions:
        shifted = [
            balanced_fit(
                make_transform(R, t + sign * gates.distinct * d),
                src.points,
                src.normals,
                tgt.normals,
                tgt.centers,
                gates.fit,
                neighbors=best.neighbors,
            ).score
            for sign in (-1.0, 1.0)
        ]
        if max(shifted) >= ratio * best.fit.score:
            kept.append(d)
    return np.array(kept).reshape(-1, 3)


def _degeneracy(
    local: _Local, tgt: PreparedScan, gates: _Gates, cfg: KentRegConfig
) -> tuple[FloatArray, bool]:
    """``local``'s translation directions the fit cannot resolve (:func:`_unresolved`) and
    whether its rotation is degenerate."""
    ratio = cfg.translation.degeneracy_ratio
    dirs = degenerate_directions(local.H_trans, ratio)
    if len(dirs) and np.isfinite(local.fit.score):
        dirs = _unresolved(dirs, local, tgt, gates, cfg.search.ambiguity_ratio)
    return dirs, rotation_degenerate(local.em.hessian, ratio)


def _inflated(
    best: _Local,
    covariance: FloatArray,
    directions: FloatArray,
    rot_degenerate: bool,
    gates: _Gates,
) -> FloatArray:
    """``best``'s ``covariance`` inflated where the data cannot tell the pose apart from one moved
    by :attr:`_Gates.distinct`: by that distance along each unresolved translation direction,
    and, when the rotation is degenerate, about the EM's weakest axis by the angle that moves
    the source's points that far at their RMS range
    (:func:`~kentreg_ros.core.registration.uncertainty.inflate_degenerate`)."""
    axis, sigma_rotation = None, 0.0
    if rot_degenerate:
        _, evecs = np.linalg.eigh(0.5 * (best.em.hessian + best.em.hessian.T))
        axis = best.em.R @ evecs[:, 0]  # the EM's right perturbation, into the target frame
        radius = float(np.sqrt(np.mean(row_norms(best.source.points) ** 2)))
        sigma_rotation = gates.distinct / max(radius, gates.distinct)
    return inflate_degenerate(
        covariance,
        directions,
        gates.distinct,
        rotation_axis=axis,
        sigma_rotation=sigma_rotation,
    )


def position_sample(scan: PreparedScan, cap: int) -> PreparedScan:
    """``scan`` with its points and normals reduced to :func:`stratified_sample` of its normal
    clusters (at most ``cap`` per cluster) for the position stages; its clusters, which the
    rotation stage and the search use, are those of every normal."""
    idx = stratified_sample(scan.labels, cap)
    if len(idx) == len(scan):
        return scan
    return replace(
        scan, points=scan.points[idx], normals=scan.normals[idx], labels=scan.labels[idx]
    )


def register_robust(
    src: PreparedScan,
    tgt: PreparedScan,
    T_init: FloatArray,
    cfg: KentRegConfig,
    *,
    watch: Stopwatch,
    search: bool,
) -> PoseEvidence:
    """The robust recipe's pose (see the module docstring): from ``T_init``, or with
    ``search`` the best-fitting of the start-free search's candidates, with its degenerate
    directions those the fit cannot resolve (:func:`_unresolved`). Stages are timed on
    ``watch``."""
    gates = _gates(src, tgt, cfg)
    n_hypotheses = 0
    if search:
        candidates, n_hypotheses = _search_candidates(src, tgt, T_init, cfg, gates, watch)
    else:
        candidates = [_local(src, tgt, T_init, cfg, gates, watch)]
    candidates.sort(key=lambda c: -c.fit.score)
    choice = choose_pose(
        [Candidate(c.T, c.fit.score, c) for c in candidates],
        src.points,
        gate=gates.distinct,
        ratio=cfg.search.ambiguity_ratio,
    )
    best = choice.chosen.origin
    deg_dirs, rot_degenerate = _degeneracy(best, tgt, gates, cfg)
    with watch('covariance'):
        covariance, resolution = _covariance(best, gates.spacing)
        covariance = _inflated(best, covariance, deg_dirs, rot_degenerate, gates)
    others = []
    for c in choice.distinct:  # the search's other poses, only when it ran and found some
        dirs, rot = _degeneracy(c.origin, tgt, gates, cfg)
        with watch('covariance'):
            own, _ = _covariance(c.origin, gates.spacing)
            others.append(_inflated(c.origin, own, dirs, rot, gates))
    return PoseEvidence(
        T_target_source=best.T,
        converged=best.converged,
        iterations=best.iterations,
        kappa=best.em.kappa,
        beta=best.em.beta,
        log_likelihood=tuple(best.em.log_likelihood),
        inlier_fraction=best.inlier,
        covariance=covariance,
        degenerate_directions=deg_dirs,
        rotation_degenerate=rot_degenerate,
        stages=best.stages,
        fit=best.fit.score,
        hypotheses=n_hypotheses,
        ambiguous=bool(choice.rivals),
        alternatives=tuple((c.T, c.fit) for c in choice.distinct),
        alternative_covariances=tuple(others),
        resolution=resolution,
    )
