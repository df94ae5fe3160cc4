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
import time
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from kentreg_ros.core.clustering import spherical_kmeans
from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.correspondence import NearestNeighborCache
from kentreg_ros.core.em import (
    EMResult,
    ModelClusters,
    NormalBins,
    bin_cell_for,
    paper_cluster_em,
    shared_rotation_em,
)
from kentreg_ros.core.errors import InvalidInputError, InvalidPointCloudError, KentRegError
from kentreg_ros.core.kent import fit_kent_moments_batch
from kentreg_ros.core.normals import estimate_normals, normal_inlier_mask, planar_mask
from kentreg_ros.core.preprocess import as_points, crop_range, downsample
from kentreg_ros.core.refine import refine_joint
from kentreg_ros.core.rotations import (
    average_rotations,
    check_transform,
    make_transform,
    rotation_angle,
)
from kentreg_ros.core.search import distinct_best, mixture_overlap, twist_hypotheses
from kentreg_ros.core.translation import (
    centroid_translation,
    degenerate_directions,
    plane_offset_translation,
    point_to_plane_translation,
)
from kentreg_ros.core.verify import Fit, FitGates, balanced_fit, rms_displacement

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

MIN_POINTS = 20
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
#: Below this share of source points with a correspondence the clouds do not overlap at the
#: pose found: the result is 'failed'. Scan-to-scan overlap is rarely under a half; a twentieth
#: is left by a pose that matches a single surface by accident.
MIN_INLIER_FRACTION = 0.05

STATUS_CONVERGED = 'converged'
STATUS_MAX_ITERATIONS = 'max_iterations'
STATUS_DEGENERATE = 'degenerate'
STATUS_FAILED = 'failed'


@dataclass(frozen=True, eq=False)
class PreparedScan:
    """A scan preprocessed once and reusable as source or target of many registrations.

    Attributes
    ----------
    points : ndarray, shape (N, 3)
        Downsampled points whose normals passed the outlier test.
    normals : ndarray, shape (N, 3)
        Unit normals oriented toward ``viewpoint``.
    labels : ndarray of int, shape (N,)
        Spherical k-means cluster of every normal.
    centers : ndarray, shape (K, 3)
        Cluster mean directions.
    clusters : ModelClusters
        Kent frames of the clusters (used when this scan is the model).
    tree : cKDTree
        Tree on ``points``.
    voxel_size : float
        Voxel edge used (0 if the input was used as is).
    viewpoint : ndarray, shape (3,)
    n_input : int
        Points given.
    n_isolated : int
        Input points dropped as isolated returns (their voxel held too few returns).
    min_voxel_points : int
        Returns a voxel needed to be kept (the isolated-return floor used).
    n_normal_outliers : int
        Points removed by the cosine-similarity normal test.
    timings : dict
        Milliseconds per preprocessing stage.
    """

    points: FloatArray
    normals: FloatArray
    labels: NDArray[np.intp]
    centers: FloatArray
    clusters: ModelClusters
    tree: cKDTree
    voxel_size: float
    viewpoint: FloatArray
    n_input: int
    n_isolated: int
    min_voxel_points: int
    n_normal_outliers: int
    timings: dict[str, float] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.points)


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
        Balanced fit of the pose in [0, 1] (:func:`kentreg_ros.core.verify.balanced_fit`):
        the share of source points landing on a target surface of the same orientation,
        averaged over the target's normal clusters. NaN in paper mode.
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
        return self.status != STATUS_FAILED


def elapsed_ms(t0: float) -> float:
    """Milliseconds since ``t0`` (a ``time.perf_counter()`` reading)."""
    return (time.perf_counter() - t0) * 1e3


def prepare_scan(
    points: ArrayLike,
    *,
    config: KentRegConfig | None = None,
    viewpoint: ArrayLike = (0.0, 0.0, 0.0),
    normals: ArrayLike | None = None,
    voxel_size_hint: float = 0.0,
) -> PreparedScan:
    """Preprocess a scan once: crop, downsample, normals, outlier removal, clustering.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Finite points in the sensor frame (drop NaN/inf first).
    config : KentRegConfig, optional
    viewpoint : array_like, shape (3,)
        Sensor origin in the points' frame; normals face it.
    normals : array_like, shape (N, 3), optional
        Precomputed normals for ``points``; then ``points`` are used as given (no cropping or
        downsampling) and only the cosine outlier test and clustering run.
    voxel_size_hint : float
        With automatic voxel sizing (``preprocess.voxel_size = 0``), start the size search
        here, e.g. at the previous scan's ``voxel_size``: usually one counting pass instead of
        four.

    Raises
    ------
    InvalidPointCloudError
        Wrong shape, NaN/inf, or too few points for the neighbourhood size.
    """
    cfg = config or KentRegConfig()
    timings: dict[str, float] = {}
    t_start = time.perf_counter()
    pts = as_points(points)
    vp = np.asarray(viewpoint, dtype=np.float64).reshape(3)
    if not np.isfinite(vp).all():
        raise InvalidInputError(f'Expected a finite `viewpoint`, got {vp}.')
    n_input = len(pts)
    k = cfg.normals.k_neighbors
    voxel = 0.0
    n_isolated = 0
    floor = 1
    if normals is None:
        t0 = time.perf_counter()
        pts = crop_range(pts, cfg.preprocess.min_range, cfg.preprocess.max_range, vp)
        pts, grid = downsample(
            pts,
            voxel_size=cfg.preprocess.voxel_size,
            target_points=cfg.preprocess.target_points,
            voxel_size_hint=voxel_size_hint,
            min_voxel_points=cfg.preprocess.min_voxel_points,
        )
        voxel, n_isolated, floor = grid.size, grid.n_isolated, grid.min_points
        timings['downsample'] = elapsed_ms(t0)
        if len(pts) < max(k, MIN_POINTS):
            raise InvalidPointCloudError(
                f'Expected at least {max(k, MIN_POINTS)} points after preprocessing '
                f'(k_neighbors={k}), got {len(pts)} (from {n_input} input points).'
            )
        t0 = time.perf_counter()
        tree = cKDTree(pts)
        est = estimate_normals(pts, k, viewpoint=vp, tree=tree)
        nrm, flat, nbrs = est.normals, est.flatness, est.neighbors
        timings['normals'] = elapsed_ms(t0)
    else:
        nrm = as_points(normals, 'normals')
        if nrm.shape != pts.shape:
            raise InvalidPointCloudError(
                f'Expected `normals` to have the shape of `points` {pts.shape}, got {nrm.shape}.'
            )
        lengths = np.linalg.norm(nrm, axis=1)
        if np.any(lengths < 1e-9):
            raise InvalidPointCloudError('`normals` contains zero-length vectors.')
        nrm = nrm / lengths[:, None]
        if len(pts) < max(k, MIN_POINTS):
            raise InvalidPointCloudError(
                f'Expected at least {max(k, MIN_POINTS)} points, got {len(pts)}.'
            )
        t0 = time.perf_counter()
        tree = cKDTree(pts)
        _, nbrs = tree.query(pts, k=k, workers=-1)
        flat = np.zeros(len(pts))  # given normals are trusted
        timings['normals'] = elapsed_ms(t0)
    t0 = time.perf_counter()
    keep = normal_inlier_mask(nrm, np.asarray(nbrs, dtype=np.intp), cfg.normals.outlier_cosine)
    keep &= planar_mask(flat, cfg.normals.max_flatness)
    n_out = int((~keep).sum())
    if keep.sum() < MIN_POINTS:
        raise InvalidPointCloudError(
            f'Only {int(keep.sum())} of {len(pts)} normals passed the planarity and outlier '
            f'tests (normals.max_flatness={cfg.normals.max_flatness}, '
            f'normals.outlier_cosine={cfg.normals.outlier_cosine}); need {MIN_POINTS}.'
        )
    if n_out:
        pts, nrm = pts[keep], nrm[keep]
        tree = cKDTree(pts)
    timings['outliers'] = elapsed_ms(t0)
    t0 = time.perf_counter()
    labels, centers = spherical_kmeans(
        nrm,
        cfg.clustering.n_clusters,
        max_iterations=cfg.clustering.max_iterations,
        rng=cfg.clustering.seed,
        restarts=cfg.clustering.restarts,
        sample_size=cfg.clustering.restart_sample,
    )
    onehot = (labels[None, :] == np.arange(len(centers))[:, None]).astype(np.float64)
    kappa_clusters, _, _ = fit_kent_moments_batch(nrm, onehot)
    bins = NormalBins.from_normals(nrm, bin_cell_for(kappa_clusters)[labels], labels)
    clusters = ModelClusters.from_bins(bins, centers)
    timings['clustering'] = elapsed_ms(t0)
    timings['total'] = elapsed_ms(t_start)
    return PreparedScan(
        points=pts,
        normals=nrm,
        labels=labels,
        centers=centers,
        clusters=clusters,
        tree=tree,
        voxel_size=voxel,
        viewpoint=vp,
        n_input=n_input,
        n_isolated=n_isolated,
        min_voxel_points=floor,
        n_normal_outliers=n_out,
        timings=timings,
    )


def _as_prepared(
    scan: ArrayLike | PreparedScan,
    normals: ArrayLike | None,
    cfg: KentRegConfig,
    viewpoint: ArrayLike,
    name: str,
) -> PreparedScan:
    if isinstance(scan, PreparedScan):
        if normals is not None:
            raise InvalidInputError(
                f'`{name}_normals` cannot be given with a PreparedScan `{name}`.'
            )
        return scan
    try:
        return prepare_scan(scan, config=cfg, viewpoint=viewpoint, normals=normals)
    except InvalidPointCloudError as exc:
        raise InvalidPointCloudError(f'{name}: {exc}') from exc


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
        Search SO(3) from the two clouds' normal mixtures (:mod:`kentreg_ros.core.search`)
        instead of starting only from ``init``. Default from ``search.mode``: with 'auto',
        search when ``init`` is not given. Robust mode only.

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
    t_start = time.perf_counter()
    T_init = np.eye(4) if init is None else check_transform(init, 'init')
    t0 = time.perf_counter()
    src = _as_prepared(source, source_normals, cfg, viewpoint, 'source')
    t_src = elapsed_ms(t0)
    t0 = time.perf_counter()
    tgt = _as_prepared(target, target_normals, cfg, viewpoint, 'target')
    t_tgt = elapsed_ms(t0)
    timings = {'prepare_source': t_src, 'prepare_target': t_tgt}
    if cfg.mode == 'paper':
        result = _register_paper(src, tgt, T_init, cfg, timings)
    else:
        if global_search is None:
            global_search = cfg.search.mode == 'always' or (
                cfg.search.mode == 'auto' and init is None
            )
        result = _register_robust(src, tgt, T_init, cfg, timings, global_search)
    timings['total'] = elapsed_ms(t_start)
    return result


def sampling_spacing(src: PreparedScan, tgt: PreparedScan) -> float:
    """The clouds' sampling step: the larger voxel edge, or (no voxel grid) the median distance
    between neighbouring target points."""
    voxel = max(src.voxel_size, tgt.voxel_size)
    if voxel > 0.0:
        return voxel
    step = max(1, len(tgt) // SPACING_SAMPLE)
    d = tgt.tree.query(tgt.points[::step], k=2)[0][:, 1]
    return float(np.median(d))


def _rotation_degenerate(H: FloatArray, ratio: float) -> bool:
    """True when the rotation information matrix has an eigenvalue below ``ratio`` x largest."""
    evals = np.linalg.eigvalsh(0.5 * (H + H.T))
    return bool(evals[0] < ratio * max(float(evals[-1]), 1e-300))


def _information_to_covariance(H: FloatArray) -> FloatArray:
    """Pseudo-inverse of an information matrix; null directions get a variance of 1e6."""
    Hs = 0.5 * (H + H.T)
    evals, evecs = np.linalg.eigh(Hs)
    inv = np.where(
        evals > 1e-9 * max(float(evals[-1]), 1e-300), 1.0 / np.maximum(evals, 1e-300), 1e6
    )
    return (evecs * inv) @ evecs.T


@dataclass
class _Candidate:
    """One pose under consideration, with what its stages found."""

    T: FloatArray
    em: EMResult
    fit: Fit
    stages: dict[str, FloatArray]
    iterations: int
    converged: bool
    inlier: float
    covariance: FloatArray
    H_trans: FloatArray
    refined: bool = False


@dataclass(frozen=True)
class _Gates:
    """Scales of one registration, from the sampling spacing (see the constants above)."""

    max_gate: float
    min_gate: float
    noise_floor: float
    fit: FitGates


def _gates(src: PreparedScan, tgt: PreparedScan, cfg: KentRegConfig) -> _Gates:
    spacing = sampling_spacing(src, tgt)
    min_gate = GATE_FLOOR_SPACINGS * spacing
    max_gate = max(cfg.refine.max_correspondence_distance, min_gate)
    noise_floor = NOISE_FLOOR_SPACINGS * spacing
    return _Gates(max_gate, min_gate, noise_floor, FitGates.for_spacing(spacing))


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


def _local(
    src: PreparedScan,
    tgt: PreparedScan,
    T0: FloatArray,
    cfg: KentRegConfig,
    gates: _Gates,
    timings: dict[str, float],
    *,
    em: EMResult | None = None,
    refine: bool = True,
) -> _Candidate:
    """Rotation EM from ``T0`` (unless ``em`` is given), translation, refinement, fit."""
    stages: dict[str, FloatArray] = {}
    if em is None:
        t0 = time.perf_counter()
        em = _rotation_stage(src, tgt, T0[:3, :3], cfg)
        timings['rotation'] = timings.get('rotation', 0.0) + elapsed_ms(t0)
    R = em.R
    stages['rotation'] = make_transform(R, T0[:3, 3])
    iterations = em.iterations
    t0 = time.perf_counter()
    tr_cfg = cfg.translation
    H_t: FloatArray | None = None
    sigma2_t = 0.0
    # One correspondence cache for the translation and refinement loops (same source points,
    # same target tree): points that moved less than their certified radius skip the query.
    neighbors = NearestNeighborCache(tgt.tree, tgt.points, len(src))
    inlier = em.inlier_fraction
    if tr_cfg.method == 'centroid':
        t = centroid_translation(R, src.points, tgt.points)
    else:
        t = T0[:3, 3].copy()
        if tr_cfg.cross_correlation:
            t, _ = plane_offset_translation(
                R,
                t,
                src.points,
                src.normals,
                tgt.points,
                tgt.normals,
                tgt.centers,
                bin_size=0.5 * gates.min_gate / GATE_FLOOR_SPACINGS,  # half a spacing
                max_shift=tr_cfg.max_shift,
            )
            stages['cross_correlation'] = make_transform(R, t)
        tres = point_to_plane_translation(
            R,
            t,
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
        t, H_t, sigma2_t = tres.t, tres.hessian, tres.sigma2
        inlier = tres.inlier_fraction
        iterations += tres.iterations
    timings['translation'] = timings.get('translation', 0.0) + elapsed_ms(t0)
    T = make_transform(R, t)
    stages['translation'] = T
    converged = em.converged
    t0 = time.perf_counter()
    refined = refine and cfg.refine.method != 'none'
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
            max_distance=gates.max_gate,
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
        # (omega, v) -> (v, omega), i.e. (x, y, z, roll, pitch, yaw).
        perm = [3, 4, 5, 0, 1, 2]
        info = ref.hessian[np.ix_(perm, perm)]
        covariance = max(ref.sigma2, 1e-12) * _information_to_covariance(info)
        H_trans = info[:3, :3]
    else:
        covariance = np.zeros((6, 6))
        covariance[3:, 3:] = _information_to_covariance(em.hessian)
        if H_t is not None:
            covariance[:3, :3] = max(sigma2_t, 1e-12) * _information_to_covariance(H_t)
        else:
            covariance[:3, :3] = np.eye(3) * float(np.var(src.points)) / len(src)
        H_trans = H_t if H_t is not None else np.eye(3)
    timings['refine'] = timings.get('refine', 0.0) + elapsed_ms(t0)
    t0 = time.perf_counter()
    fit = balanced_fit(
        T, src.points, src.normals, tgt.normals, tgt.centers, gates.fit, neighbors=neighbors
    )
    timings['fit'] = timings.get('fit', 0.0) + elapsed_ms(t0)
    return _Candidate(
        T, em, fit, stages, iterations, converged, inlier, covariance, H_trans, refined
    )


def _search_candidates(
    src: PreparedScan,
    tgt: PreparedScan,
    T_init: FloatArray,
    cfg: KentRegConfig,
    gates: _Gates,
    timings: dict[str, float],
) -> tuple[list[_Candidate], int]:
    """Start-free search: twist hypotheses ranked by the mixture overlap, the distinct best
    refined by the EM and placed by the translation stage, then verified by their fit; every
    candidate that fits nearly as well as the best is refined in full."""
    scfg = cfg.search
    t0 = time.perf_counter()
    hyp = twist_hypotheses(src.clusters, tgt.clusters, scfg.twist_step_deg)
    cap = 1.0 / np.radians(scfg.twist_step_deg) ** 2
    scores = mixture_overlap(hyp, src.clusters, tgt.clusters, cap)
    chosen = distinct_best(hyp, scores, scfg.candidates, scfg.min_separation_deg)
    starts = [T_init[:3, :3]] + [hyp[i] for i in chosen]
    timings['search'] = elapsed_ms(t0)
    cheap: list[_Candidate] = []
    seen: list[FloatArray] = []
    for R0 in starts:
        t0 = time.perf_counter()
        em = _rotation_stage(src, tgt, R0, cfg, max_iterations=SEARCH_EM_PASSES)
        timings['rotation'] = timings.get('rotation', 0.0) + elapsed_ms(t0)
        if any(rotation_angle(em.R.T @ R) < np.radians(scfg.min_separation_deg) for R in seen):
            continue  # converged onto a rotation already under consideration
        seen.append(em.R)
        T0 = make_transform(em.R, T_init[:3, 3])
        cheap.append(_local(src, tgt, T0, cfg, gates, timings, em=em, refine=False))
    best_cheap = max(c.fit.score for c in cheap)
    out: list[_Candidate] = []
    for cand in sorted(cheap, key=lambda c: -c.fit.score):
        if cand.fit.score >= scfg.ambiguity_ratio * best_cheap or not out:
            t0 = time.perf_counter()
            em = _rotation_stage(src, tgt, cand.em.R, cfg, anneal=False)
            timings['rotation'] += elapsed_ms(t0)
            T0 = make_transform(em.R, T_init[:3, 3])
            out.append(_local(src, tgt, T0, cfg, gates, timings, em=em))
    return out, len(hyp)


def _register_robust(
    src: PreparedScan,
    tgt: PreparedScan,
    T_init: FloatArray,
    cfg: KentRegConfig,
    timings: dict[str, float],
    search: bool,
) -> RegistrationResult:
    gates = _gates(src, tgt, cfg)
    n_hypotheses = 0
    if search:
        candidates, n_hypotheses = _search_candidates(src, tgt, T_init, cfg, gates, timings)
    else:
        candidates = [_local(src, tgt, T_init, cfg, gates, timings)]
    candidates.sort(key=lambda c: -c.fit.score)
    best = candidates[0]
    distinct = [
        c
        for c in candidates[1:]
        if rms_displacement(src.points, c.T, best.T) > 2.0 * gates.fit.distance
    ]
    ambiguous = any(c.fit.score >= cfg.search.ambiguity_ratio * best.fit.score for c in distinct)
    tr_cfg = cfg.translation
    deg_dirs = degenerate_directions(best.H_trans, tr_cfg.degeneracy_ratio)
    rot_degenerate = _rotation_degenerate(best.em.hessian, tr_cfg.degeneracy_ratio)
    degenerate = len(deg_dirs) > 0 or rot_degenerate
    result = _finish(
        best.T,
        best.converged,
        best.iterations,
        best.em,
        best.inlier,
        best.covariance,
        degenerate,
        deg_dirs,
        rot_degenerate,
        timings,
        best.stages,
        'robust',
        src,
        tgt,
        list(best.em.log_likelihood),
    )
    return replace(
        result,
        fit=best.fit.score,
        hypotheses=n_hypotheses,
        ambiguous=ambiguous,
        alternatives=tuple((c.T, c.fit.score) for c in distinct),
    )


def _finish(
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
        status, message = STATUS_FAILED, 'The estimate is not finite.'
        T = np.full((4, 4), np.nan)
    elif inlier < MIN_INLIER_FRACTION:
        status = STATUS_FAILED
        message = (
            f'Only {inlier:.1%} of the source points found a correspondence; the clouds '
            'do not overlap at this pose.'
        )
    elif degenerate:
        status = STATUS_DEGENERATE
        parts = []
        if len(deg_dirs):
            dirs = ', '.join(np.array2string(d, precision=2) for d in deg_dirs)
            parts.append(f'translation along {dirs} is poorly constrained')
        if rot_degenerate:
            parts.append('rotation about one axis is poorly constrained by the normals')
        message = 'Degenerate scene: ' + '; '.join(parts) + '.'
    elif converged:
        status, message = STATUS_CONVERGED, 'Converged.'
    else:
        status = STATUS_MAX_ITERATIONS
        message = 'Stopped at the iteration limit before meeting the tolerance.'
    return RegistrationResult(
        T_target_source=T,
        converged=bool(converged and status != STATUS_FAILED),
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


def _subsample(idx: NDArray[np.intp], limit: int, rng: np.random.Generator) -> NDArray[np.intp]:
    if len(idx) <= limit:
        return idx
    return np.sort(rng.choice(idx, size=limit, replace=False))


def _register_paper(
    src: PreparedScan,
    tgt: PreparedScan,
    T_init: FloatArray,
    cfg: KentRegConfig,
    timings: dict[str, float],
) -> RegistrationResult:
    """Algorithms 1 and 2 of the paper, as written."""
    em_cfg = cfg.em
    R0 = T_init[:3, :3]
    rng = np.random.default_rng(cfg.clustering.seed)
    t0 = time.perf_counter()
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
    timings['rotation'] = elapsed_ms(t0)
    t0 = time.perf_counter()
    t = centroid_translation(R, src.points, tgt.points)
    timings['translation'] = elapsed_ms(t0)
    timings['refine'] = 0.0
    T = make_transform(R, t)
    H_rot = np.sum([r.hessian for r in results], axis=0)
    covariance = np.zeros((6, 6))
    covariance[3:, 3:] = _information_to_covariance(H_rot)
    cov_t = np.cov(tgt.points.T) / len(tgt) + R @ np.cov(src.points.T) @ R.T / len(src)
    covariance[:3, :3] = cov_t
    rot_degenerate = _rotation_degenerate(H_rot, cfg.translation.degeneracy_ratio)
    em = EMResult(
        R=R,
        kappa=np.concatenate([r.kappa for r in results]),
        beta=np.concatenate([r.beta for r in results]),
        log_likelihood=[],
        iterations=sum(r.iterations for r in results),
        converged=all(r.converged for r in results),
        inlier_fraction=float(np.mean([r.inlier_fraction for r in results])),
        hessian=H_rot,
    )
    history = [v for r in results for v in r.log_likelihood]
    spread = max(rotation_angle(r.R.T @ R) for r in results)
    stages = {'rotation': make_transform(R, T_init[:3, 3]), 'translation': T}
    res = _finish(
        T,
        em.converged,
        em.iterations,
        em,
        em.inlier_fraction,
        covariance,
        rot_degenerate,
        np.zeros((0, 3)),
        rot_degenerate,
        timings,
        stages,
        'paper',
        src,
        tgt,
        history,
    )
    if spread > np.radians(2.0):
        logger.debug(
            'Paper mode: per-cluster rotations spread %.2f deg before averaging.',
            np.degrees(spread),
        )
    return res
