"""``localize(scan, map)``: where a scan is in a saved map, or that it cannot say.

Candidates come from :mod:`~kentreg_ros.core.localization.search` (or the start, with a tight
window); each is registered against the map around it (:func:`register_in_map`: the map's
points within the scan's reach, their normal axes oriented toward the candidate's sensor, the
robust registration from the candidate) and judged on the points:

- its balanced fit (:func:`~kentreg_ros.core.registration.verify.balanced_fit`) at least
  ``localization.min_fit``;
- free space (:func:`free_space_violation`): map points the scan should see, lying clearly in
  front of what it measured along the same ray, at most ``localization.max_violation`` of
  those in view (a scan placed in the wrong place sees through the map's walls);
- no distinct pose (points moved by more than twice the fit's distance gate) fitting
  ``search.ambiguity_ratio`` as well, whether it passes the free-space test or not: then the
  result is ``ambiguous`` and no pose is given.

The result is ``localized`` only when a candidate passes all three; otherwise ``ambiguous`` or
``not_found``. The search of a scan with a narrow view takes the box twins of its best rotation
as rotation hypotheses (:mod:`~kentreg_ros.core.localization.twins`), and the scan is
localized only when none of their translation peaks outscores the answer's own. A single scan
is all this function sees; agreement over consecutive scans is
:class:`~kentreg_ros.core.localization.tracker.Localizer`'s.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from enum import StrEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.errors import InvalidPointCloudError, KentRegError
from kentreg_ros.core.geometry import check_transform, rotation_angle
from kentreg_ros.core.localization.pointmap import PointMap
from kentreg_ros.core.localization.search import (
    Hypothesis,
    Window,
    closer_start,
    rotations,
    translations,
)
from kentreg_ros.core.localization.twins import is_narrow, twin_rotations, twin_starts
from kentreg_ros.core.registration import RegistrationResult, Status, register
from kentreg_ros.core.registration.verify import FIT_DISTANCE_VOXELS, rms_displacement
from kentreg_ros.core.registration.verify import free_space_violation as see_through
from kentreg_ros.core.scan import PreparedScan, prepare_scan
from kentreg_ros.core.scan.clusters import cluster_normals
from kentreg_ros.core.scan.neighbors import NeighborIndex

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: Candidates registered in full (with the joint refinement), best coarse fit first.
FULLY_REGISTERED = 3
#: Candidates whose starts lie within this many search cells and
#: ``search.min_separation_deg`` of a better one are the same candidate.
SAME_START_CELLS = 1.5


class LocalizationStatus(StrEnum):
    """What :func:`localize` could say."""

    LOCALIZED = 'localized'
    AMBIGUOUS = 'ambiguous'
    NOT_FOUND = 'not_found'


@dataclass(frozen=True, eq=False)
class Candidate:
    """A pose considered, registered against the map and judged.

    Attributes
    ----------
    T_map_scan : ndarray, shape (4, 4)
    fit : float
        Balanced fit of the registered pose (0 when the registration failed).
    violation : float
        Share of the map points in view that the scan saw through (1 when none in view).
    visible : int
        Map points in the scan's view.
    score : float
        The search's correlation score of its start.
    valid : bool
        Fit and free space within the gates.
    result : RegistrationResult or None
    """

    T_map_scan: FloatArray
    fit: float
    violation: float
    visible: int
    score: float
    valid: bool
    result: RegistrationResult | None = None


@dataclass(frozen=True, eq=False)
class LocalizationResult:
    """Outcome of :func:`localize`.

    Attributes
    ----------
    status : LocalizationStatus
    T_map_scan : ndarray, shape (4, 4), or None
        The pose when ``localized``, else None.
    covariance : ndarray, shape (6, 6), or None
        Its covariance (x, y, z, roll, pitch, yaw about the map's axes), as a registration's.
    candidates : list of Candidate
        Every pose judged, best fit first (valid ones first).
    message : str
    timings : dict
        Milliseconds: ``prepare``, ``search``, ``register``, ``twins`` (when searched),
        ``total``.
    """

    status: LocalizationStatus
    T_map_scan: FloatArray | None
    covariance: FloatArray | None
    candidates: list[Candidate]
    message: str
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def localized(self) -> bool:
        return self.status is LocalizationStatus.LOCALIZED

    @property
    def best(self) -> Candidate | None:
        return self.candidates[0] if self.candidates else None


def localize(
    scan: ArrayLike | PreparedScan,
    pmap: PointMap,
    *,
    init: ArrayLike | None = None,
    window: Window | None = None,
    config: KentRegConfig | None = None,
) -> LocalizationResult:
    """Localize ``scan`` in ``pmap``: its pose ``T_map_scan``, or that it cannot say which.

    Parameters
    ----------
    scan : array_like, shape (N, 3), or PreparedScan
        Points in the sensor frame, or a scan prepared with the same configuration.
    pmap : PointMap
    init : array_like, shape (4, 4), optional
        A start. Without ``window`` the registration from it is the only candidate (tracking);
        with one the search keeps within it.
    window : Window, optional
        How far ``init`` may be off (needs ``init``).
    config : KentRegConfig, optional

    Returns
    -------
    LocalizationResult
        Never raises for a scan that cannot be localized: that is ``not_found``.

    Raises
    ------
    InvalidPointCloudError
        A malformed or unusable scan.
    """
    cfg = config or KentRegConfig()
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    start = None if init is None else check_transform(init, 'init')
    if window is not None and start is None:
        raise KentRegError('A search `window` needs an `init` pose.')
    prepared = scan if isinstance(scan, PreparedScan) else prepare_scan(scan, config=cfg)
    timings['prepare'] = _ms(t_start)
    t0 = time.perf_counter()
    window_search = start is None or window is not None
    narrow = window_search and is_narrow(prepared)
    if start is not None and window is None:
        search = _Search([Hypothesis(start, float('inf'))], [], [])
    else:
        search = _search(prepared, pmap, cfg, start, window, twins=narrow)
    timings['search'] = _ms(t0)
    t0 = time.perf_counter()
    candidates = _register_candidates(prepared, pmap, search.starts, cfg)
    timings['register'] = _ms(t0)
    result = decide(candidates, prepared, pmap, cfg)
    if result.status is LocalizationStatus.LOCALIZED and narrow:
        t0 = time.perf_counter()
        result = _check_twins(prepared, pmap, candidates, result, search, cfg, start, window)
        timings['twins'] = _ms(t0)
    timings['total'] = _ms(t_start)
    return LocalizationResult(
        result.status, result.T_map_scan, result.covariance, result.candidates,
        result.message, timings,
    )  # fmt: skip


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3


def _check_twins(
    scan: PreparedScan,
    pmap: PointMap,
    candidates: list[Candidate],
    result: _Decision,
    search: _Search,
    cfg: KentRegConfig,
    start: FloatArray | None,
    window: Window | None,
) -> _Decision:
    """``result`` unless a box twin of its answer outscores it in the translation search:
    then ambiguous, though no registration from the twin fits as well.

    The twins of the answer are those of the search's best rotation (:func:`_search` searched
    them all) when the answer's rotation is one of them; otherwise they are searched here
    (:func:`~.twins.twin_starts`) and their best starts registered and judged with the other
    candidates.

    The correlation is what the search ranks translations by: a twin whose peak outscores
    the answer's is a pose the scan's surfaces support at least as well, and a registration
    that did not reach it from its start does not refute it (measured: a quick_shack keyframe
    localized at a 91 deg twin, fit 0.32, while the start of the truth's twin, 4 deg and 1 m
    off, scored 80 cells and its registrations turned 12 deg away)."""
    assert result.T_map_scan is not None
    T = result.T_map_scan
    min_angle = np.radians(cfg.search.min_separation_deg)
    decision = result
    if any(rotation_angle(T[:3, :3].T @ R) < min_angle for R in search.orbit):
        rivals = [h.score for h in search.peaks if _angle(h.T, T) >= min_angle]
    else:
        twins = twin_starts(scan, pmap, T[:3, :3], cfg, start=start, window=window)
        judged = [judge(scan, pmap, h, cfg) for h in twins]
        decision = decide(candidates + judged, scan, pmap, cfg)
        rivals = [h.score for h in twins]
    if decision.status is not LocalizationStatus.LOCALIZED or not rivals:
        return decision
    assert decision.T_map_scan is not None
    T = decision.T_map_scan
    near = Window(pmap.grid.cell, 0.0)
    own = translations(scan, T[:3, :3], pmap, 1, start=T, window=near)
    own_score = own[0].score if own else 0.0
    best_twin = max(rivals)
    if best_twin <= own_score:
        return decision
    message = (
        f'Ambiguous: a box twin of the pose scores {best_twin:.0f} cells in the translation '
        f'search against its {own_score:.0f}, and no registration from it settles which.'
    )
    return replace(decision, status=LocalizationStatus.AMBIGUOUS, T_map_scan=None,
                   covariance=None, message=message)  # fmt: skip


def _angle(A: FloatArray, B: FloatArray) -> float:
    """The angle between the rotations of two poses (rad)."""
    return rotation_angle(A[:3, :3].T @ B[:3, :3])


@dataclass(frozen=True, eq=False)
class _Search:
    """What :func:`_search` found: the starts to register, every correlation peak of every
    rotation searched, and the rotations of the box-twin orbit searched (empty when none)."""

    starts: list[Hypothesis]
    peaks: list[Hypothesis]
    orbit: list[FloatArray]


def _search(
    scan: PreparedScan,
    pmap: PointMap,
    cfg: KentRegConfig,
    start: FloatArray | None,
    window: Window | None,
    *,
    twins: bool = False,
) -> _Search:
    """The candidates' starts: the best correlation peaks of every rotation hypothesis (and,
    with ``twins``, of every box twin of the best of them: :func:`~.twins.twin_rotations`),
    the same start once, at most ``localization.refined`` of them, each polished onto the map
    when that brings more of the scan onto it (:func:`~.search.closer_start`): a peak is
    placed to a search cell, and from a start a metre off along a weakly held direction the
    registration settles in the wrong place (hku_2 keyframes 85, 113 and 117 from no start:
    0.9-1.5 m off at fits 0.39-0.40 from their peaks, at the truth with 0.52-0.58 from the
    polished ones), and from one turned 8 deg it can stay turned (keyframe 193: its best peaks
    8 deg off, its registration 8.3 deg and 1.5 m off at a fit of 0.40 with 29 % seen through,
    localized; polished, its best start lay 0.05 deg and 1 cm off)."""
    loc = cfg.localization
    rots = rotations(scan, pmap, cfg, start=start, window=window)
    orbit: list[FloatArray] = []
    if twins and rots:
        orbit = [rots[0], *twin_rotations(scan, pmap, rots[0], cfg, start=start, window=window)]
    min_angle = np.radians(cfg.search.min_separation_deg)
    searched = rots + [R for R in orbit[1:] if all(_rad(R, Q) >= min_angle for Q in rots)]
    hyps: list[Hypothesis] = []
    for R in searched:
        hyps += translations(scan, R, pmap, loc.peaks, start=start, window=window)
    hyps.sort(key=lambda h: -h.score)
    kept: list[Hypothesis] = []
    cell = pmap.grid.cell * SAME_START_CELLS
    for h in hyps:
        same = any(
            np.linalg.norm(h.T[:3, 3] - k.T[:3, 3]) < cell and _angle(h.T, k.T) < min_angle
            for k in kept
        )
        if not same:
            kept.append(h)
        if len(kept) >= loc.refined:
            break
    return _Search([closer_start(scan, pmap, h) for h in kept], hyps, orbit)


def _rad(A: FloatArray, B: FloatArray) -> float:
    """The angle between two rotations (rad)."""
    return rotation_angle(A.T @ B)


def _register_candidates(
    scan: PreparedScan, pmap: PointMap, starts: list[Hypothesis], cfg: KentRegConfig
) -> list[Candidate]:
    """Every start registered without the joint refinement (rotation EM, translation, fit), then
    the :data:`FULLY_REGISTERED` best of those in full, from their starts, each against the
    map around its start made once for both: the refinement is most of a registration's cost,
    and a start whose coarse pose fits poorly does not turn into the best by refining.

    The full registration starts from the start, not from the coarse pose: without the
    refinement's joint step the coarse registration can slide along a weakly held direction
    (hku_2 keyframe 113: from a polished start 0.8 m off to 2.7 m off; from the start itself
    the full registration reached the truth)."""
    if len(starts) <= FULLY_REGISTERED:
        return [judge(scan, pmap, h, cfg) for h in starts]
    coarse_cfg = cfg.with_updates({'refine.method': 'none'})
    targets = [map_around(scan, pmap, h.T[:3, 3], cfg) for h in starts]
    coarse = [
        judge(scan, pmap, h, coarse_cfg, target=target)
        for h, target in zip(starts, targets, strict=True)
    ]
    order = sorted(range(len(starts)), key=lambda i: -coarse[i].fit)
    full = set(order[:FULLY_REGISTERED])
    out = list(coarse)
    for i in full:
        out[i] = judge(scan, pmap, starts[i], cfg, target=targets[i])
    return out


def register_in_map(
    scan: PreparedScan,
    pmap: PointMap,
    T0: FloatArray,
    config: KentRegConfig,
    *,
    target: PreparedScan | None = None,
) -> RegistrationResult | None:
    """The robust registration of ``scan`` against the map around ``T0`` (module docstring;
    ``target``: :func:`map_around` a nearby position, made already); None when the map holds
    too little there."""
    if target is None:
        target = map_around(scan, pmap, T0[:3, 3], config)
    if target is None:
        return None
    try:
        return register(scan, target, init=T0, config=config, global_search=False)
    except (InvalidPointCloudError, np.linalg.LinAlgError) as exc:
        logger.info('Registration in the map from a candidate failed: %s', exc)
        return None


def map_around(
    scan: PreparedScan, pmap: PointMap, t: FloatArray, config: KentRegConfig
) -> PreparedScan | None:
    """The map's points within the scan's reach of ``t`` plus two search cells, their normal
    axes oriented toward ``t``, clustered and indexed: the target of a registration from a
    candidate there (and from any pose it moves to within those two cells). None when the map
    holds too little there."""
    reach = float(np.sqrt(np.max(np.einsum('ij,ij->i', scan.points, scan.points))))
    d2 = np.einsum('ij,ij->i', pmap.points - t, pmap.points - t)
    rows = np.flatnonzero(d2 <= (reach + 2.0 * pmap.grid.cell) ** 2)
    need = max(config.normals.k_neighbors, 4 * config.clustering.n_clusters, 50)
    if len(rows) < need:
        return None
    points = pmap.points[rows]
    normals = pmap.normals[rows]
    away = np.einsum('ij,ij->i', normals, t - points) < 0.0
    normals[away] *= -1.0  # the surfaces the sensor sees face it
    labels, centers, clusters = cluster_normals(normals, config)
    return PreparedScan(
        points=points,
        normals=normals,
        labels=labels,
        centers=centers,
        clusters=clusters,
        tree=NeighborIndex(points).build(),
        voxel_size=pmap.voxel_size,
        viewpoint=t.copy(),
        n_input=len(points),
        n_isolated=0,
        min_voxel_points=1,
        n_normal_outliers=0,
    )


def judge(
    scan: PreparedScan,
    pmap: PointMap,
    start: Hypothesis,
    config: KentRegConfig,
    *,
    target: PreparedScan | None = None,
) -> Candidate:
    """Register from ``start`` (against ``target`` when given: :func:`register_in_map`); the
    pose and its fit (its free space is judged later, by :func:`decide`, for the few
    candidates that need it)."""
    result = register_in_map(scan, pmap, start.T, config, target=target)
    if result is None or result.status == Status.FAILED:
        return Candidate(start.T, 0.0, 1.0, 0, start.score, False, result)
    fit = float(result.fit) if np.isfinite(result.fit) else 0.0
    return Candidate(result.T_target_source, fit, float('nan'), 0, start.score, False, result)


def _with_free_space(
    scan: PreparedScan, pmap: PointMap, c: Candidate, config: KentRegConfig
) -> Candidate:
    """``c`` with its free-space test done and its validity set."""
    if c.result is None or not np.isnan(c.violation):
        return c
    loc = config.localization
    violation, visible = free_space_violation(scan, pmap, c.T_map_scan)
    valid = c.fit >= loc.min_fit and violation <= loc.max_violation
    valid &= visible >= loc.min_visible
    return replace(c, violation=violation, visible=visible, valid=valid)


def free_space_violation(
    scan: PreparedScan, pmap: PointMap, T_map_scan: FloatArray
) -> tuple[float, int]:
    """:func:`~kentreg_ros.core.registration.verify.free_space_violation` of a scan posed in
    the map: the share of the map points its rays pass through, and how many they reach."""
    spacing = max(scan.voxel_size, pmap.voxel_size)
    return see_through(scan.points, pmap.points, T_map_scan, spacing)


@dataclass(frozen=True, eq=False)
class _Decision:
    status: LocalizationStatus
    T_map_scan: FloatArray | None
    covariance: FloatArray | None
    candidates: list[Candidate]
    message: str


def decide(
    candidates: list[Candidate], scan: PreparedScan, pmap: PointMap, config: KentRegConfig
) -> _Decision:
    """The gates of the module docstring over the judged candidates; the free-space test
    runs on those that fit well enough, best first, until the decision is made."""
    loc = config.localization
    ratio = config.search.ambiguity_ratio
    gate = 2.0 * FIT_DISTANCE_VOXELS * max(scan.voxel_size, pmap.voxel_size, 1e-6)
    ranked = sorted(candidates, key=lambda c: -c.fit)
    best: Candidate | None = None
    for i, c in enumerate(ranked):
        if c.fit < loc.min_fit:
            break
        ranked[i] = c = _with_free_space(scan, pmap, c, config)
        if c.valid:
            best = c
            break
    rivals: list[Candidate] = []
    if best is not None:
        # Any distinct pose fitting about as well, refused by the free-space test or not, makes
        # the answer ambiguous: a better-fitting pose that sees through the map is no proof
        # that the valid one is right.
        rivals = [
            c
            for c in ranked
            if c is not best
            and c.fit >= ratio * best.fit
            and rms_displacement(scan.points, c.T_map_scan, best.T_map_scan) > gate
        ]
    ranked.sort(key=lambda c: (not c.valid, -c.fit))
    if best is None:
        top = ranked[0] if ranked else None
        why = (
            'no candidate pose' if top is None
            else f'the best pose fits {top.fit:.2f} (localization.min_fit={loc.min_fit})'
            + ('' if np.isnan(top.violation) else f' and its scan sees through '
               f'{top.violation:.0%} of the {top.visible} map points in view '
               f'(localization.max_violation={loc.max_violation})')
        )  # fmt: skip
        return _Decision(LocalizationStatus.NOT_FOUND, None, None, ranked, f'Not found: {why}.')
    if rivals:
        message = (
            f'Ambiguous: {len(rivals) + 1} distinct poses fit about equally '
            f'({best.fit:.2f} and {rivals[0].fit:.2f}, search.ambiguity_ratio={ratio}).'
        )
        return _Decision(LocalizationStatus.AMBIGUOUS, None, None, ranked, message)
    assert best.result is not None
    message = (
        f'Localized: fit {best.fit:.2f}, its scan sees through {best.violation:.1%} of '
        f'{best.visible} map points in view.'
    )
    cov = np.asarray(best.result.covariance, dtype=np.float64)
    return _Decision(LocalizationStatus.LOCALIZED, best.T_map_scan, cov, ranked, message)
