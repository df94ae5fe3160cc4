"""How well a pose explains the target: the balanced fit, a score a symmetric twin cannot fake.

A rigid pose is judged by the share of source points that land on the target's surfaces:
within :attr:`FitGates.distance` of a target point whose normal agrees with the source point's
rotated normal to within :attr:`FitGates.normal_angle_deg`. The share is taken per target normal
cluster (the group of surfaces facing one way) and averaged over the clusters, so that a pose
which matches only the ground, or only one family of walls, scores low even if those surfaces
hold most of the points. In a corridor or a room, a wrong shift along the walls or a rotation
onto a symmetric twin leaves some family of surfaces unmatched; the point-to-plane residual of
the same poses does not show it (it is small on whatever does match).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core.errors import InvalidInputError
from kentreg_ros.core.registration.correspondence import NearestNeighborCache
from kentreg_ros.core.scan.neighbors import NeighborIndex

FloatArray = NDArray[np.float64]
P = TypeVar('P')

#: Distance gate of a match in voxel edges: two independent voxel samplings of the same surface
#: put centroids up to about one voxel apart, plus noise, so at the reference pose of real scan
#: pairs nearly all nearest neighbours lie within two (docs/notes-registration.md).
FIT_DISTANCE_VOXELS = 2.0
#: Normal agreement of a match: wide enough to keep most true matches of PCA normals over 15
#: voxel neighbours at the reference pose of real scans, whose disagreement has a long tail,
#: while surfaces turned by more stop matching (docs/notes-registration.md).
FIT_NORMAL_ANGLE_DEG = 20.0
#: A target cluster enters the average when it holds at least this share of the matched source
#: points' normals (smaller groups are a handful of points whose share is noise).
FIT_MIN_CLUSTER_SHARE = 0.02
#: A ray passed through a target point when its return lies beyond the point by more than this
#: share of the return's range or the fit's distance gate, whichever is larger: a surface at a
#: grazing angle spreads over range along a spacing's width.
FREE_SPACE_RANGE_SHARE = 0.05
#: Target points the free-space test looks at, at most (every n-th of those within reach): a
#: share of 20,000 is known to within half a percent.
FREE_SPACE_SAMPLE = 20_000


@dataclass(frozen=True)
class FitGates:
    """What counts as a match for :func:`balanced_fit`.

    Attributes
    ----------
    distance : float
        Largest point-to-point distance (same unit as the points).
    normal_angle_deg : float
        Largest angle between the two normals.
    """

    distance: float
    normal_angle_deg: float = FIT_NORMAL_ANGLE_DEG

    @classmethod
    def for_spacing(cls, spacing: float) -> FitGates:
        """Gates for clouds sampled every ``spacing`` (the voxel edge)."""
        return cls(distance=FIT_DISTANCE_VOXELS * spacing)


@dataclass(frozen=True)
class Fit:
    """Outcome of :func:`balanced_fit`.

    Attributes
    ----------
    score : float
        Mean over target normal clusters of the share of source points matched, in [0, 1].
    matched : float
        Share of all source points matched.
    per_cluster : ndarray, shape (K,)
        Matched share per target cluster (NaN for clusters below the minimum share).
    """

    score: float
    matched: float
    per_cluster: FloatArray


def balanced_fit(
    T_target_source: FloatArray,
    source_points: FloatArray,
    source_normals: FloatArray,
    target_normals: FloatArray,
    target_centers: FloatArray,
    gates: FitGates,
    *,
    target_tree: NeighborIndex | None = None,
    target_points: FloatArray | None = None,
    neighbors: NearestNeighborCache | None = None,
) -> Fit:
    """Balanced fit of a pose: the matched share of source points per target normal cluster.

    Parameters
    ----------
    T_target_source : ndarray, shape (4, 4)
    source_points, source_normals : ndarray, shape (N, 3)
    target_normals : ndarray, shape (M, 3)
    target_centers : ndarray, shape (K, 3)
        Mean directions of the target's normal clusters; a source point belongs to the
        cluster whose centre is nearest its rotated normal.
    gates : FitGates
    target_tree, target_points : NeighborIndex and ndarray (M, 3), optional
        The target's tree and points, when ``neighbors`` is not given.
    neighbors : NearestNeighborCache, optional
        A correspondence cache over the target for these source points (e.g. the
        refinement's): most points then need no new query.

    Returns
    -------
    Fit
    """
    R = T_target_source[:3, :3]
    x = source_points @ R.T + T_target_source[:3, 3]
    if neighbors is not None:
        dist, idx = neighbors.query(x, gates.distance)
    else:
        if target_tree is None:
            raise InvalidInputError('Expected `target_tree` or `neighbors`.')
        dist, idx = target_tree.query(x, distance_upper_bound=gates.distance)
    n_target = len(target_normals)
    found = idx < n_target
    rotated = source_normals @ R.T
    cos = np.zeros(len(x))
    j = idx[found]
    cos[found] = np.einsum('ij,ij->i', rotated[found], np.take(target_normals, j, axis=0))
    matched = found & (cos >= np.cos(np.radians(gates.normal_angle_deg)))
    groups = np.argmax(rotated @ target_centers.T, axis=1)
    k = len(target_centers)
    size = np.bincount(groups, minlength=k).astype(np.float64)
    hits = np.bincount(groups, weights=matched.astype(np.float64), minlength=k)
    used = size >= max(FIT_MIN_CLUSTER_SHARE * len(x), 1.0)
    per = np.full(k, np.nan)
    per[used] = hits[used] / size[used]
    score = float(np.mean(per[used])) if used.any() else 0.0
    return Fit(score=score, matched=float(matched.mean()) if len(x) else 0.0, per_cluster=per)


def rms_displacement(points: FloatArray, T_a: FloatArray, T_b: FloatArray) -> float:
    """RMS distance between ``points`` (N, 3) moved by ``T_a`` and by ``T_b`` (4, 4).

    From the points' first and second moments: ``E|A p + b|^2 = tr(A S A^T) + 2 b^T A m +
    |b|^2`` with ``A = R_a - R_b``, ``b = t_a - t_b``, ``m`` the mean and ``S`` the mean of
    ``p p^T``.
    """
    A = T_a[:3, :3] - T_b[:3, :3]
    b = T_a[:3, 3] - T_b[:3, 3]
    n = max(len(points), 1)
    mean = points.sum(axis=0) / n
    second = points.T @ points / n
    value = float(np.trace(A @ second @ A.T) + 2.0 * b @ A @ mean + b @ b)
    return float(np.sqrt(max(value, 0.0)))


@dataclass(frozen=True, eq=False)
class Candidate(Generic[P]):
    """A pose under consideration and what produced it.

    Attributes
    ----------
    T : ndarray, shape (4, 4)
        The pose (``T_target_source``).
    fit : float
        Its balanced fit (NaN where nothing judged it, e.g. the paper's recipe).
    origin : P
        What produced it (a stage's record, a registration result), handed back with it.
    searched : bool
        It came from the start-free search.
    """

    T: FloatArray
    fit: float
    origin: P
    searched: bool = False


@dataclass(frozen=True, eq=False)
class Choice(Generic[P]):
    """What :func:`choose_pose` chose.

    Attributes
    ----------
    chosen : Candidate
    best_fit : float
        The best fit among the candidates (non-finite fits count as 0).
    distinct : list of Candidate
        Every other candidate whose points land more than the gate away from the chosen's.
    rivals : list of Candidate
        Those of them that fit nearly as well as the best (``>= ratio x best_fit``): the
        choice is ambiguous when there is one.
    """

    chosen: Candidate[P]
    best_fit: float
    distinct: list[Candidate[P]]
    rivals: list[Candidate[P]]


def choose_pose(
    candidates: Sequence[Candidate[P]],
    points: FloatArray,
    *,
    gate: float,
    ratio: float,
    prior: FloatArray | None = None,
    preferred: Candidate[P] | None = None,
) -> Choice[P]:
    """The rule that chooses between poses, for the registration and the odometry alike.

    The candidates fitting at least ``ratio`` times the best fit are *near*: the data cannot
    tell them apart by fit. Among them the one whose ``points`` land nearest where the ``prior``
    puts them wins (RMS displacement, :func:`rms_displacement`), or the first best-fitting one
    without a prior. A ``preferred`` candidate (the registration from the prior) replaces the
    winner when their points land within ``gate`` of each other: the search confirmed it.

    Parameters
    ----------
    candidates : sequence of Candidate
        At least one.
    points : ndarray, shape (N, 3)
        The source points the poses move (for the displacements).
    gate : float
        Displacement beyond which two poses are distinct (twice the fit's distance gate).
    ratio : float
        Share of the best fit a pose must reach to be near (``search.ambiguity_ratio``).
    """
    fits = np.array([c.fit if np.isfinite(c.fit) else 0.0 for c in candidates])
    best_fit = float(fits.max())
    near = [c for c, f in zip(candidates, fits, strict=True) if f >= ratio * best_fit]
    if prior is None:
        chosen = candidates[int(np.argmax(fits))]
    else:
        chosen = min(near, key=lambda c: rms_displacement(points, c.T, prior))
    distinct = [
        c for c in candidates if c is not chosen and rms_displacement(points, c.T, chosen.T) > gate
    ]
    near_ids = {id(c) for c in near}
    rivals = [c for c in distinct if id(c) in near_ids]
    if (
        preferred is not None
        and preferred is not chosen
        and rms_displacement(points, preferred.T, chosen.T) <= gate
    ):
        chosen = preferred
    return Choice(chosen, best_fit, distinct, rivals)


def free_space_violation(
    source_points: FloatArray,
    target_points: FloatArray,
    T_target_source: FloatArray,
    spacing: float,
) -> tuple[float, int]:
    """Share of the target points the source's rays pass through, among those its rays reach:
    evidence on the points that a pose is wrong, which a fit on matches cannot give.

    The source's rays run from its origin (its sensor) to its points. A target point within the
    source's reach is *reached* by the ray nearest its direction when the ray passes through
    its voxel (within half of ``spacing``; a point between the rays of a sparse scan is no
    evidence either way) and its return lies no nearer than the point by more than the margin
    (:data:`FREE_SPACE_RANGE_SHARE` of the range, or the fit's distance gate); it is *passed
    through* when the return lies beyond it by more than that margin: the source saw empty
    space where the target has a surface. A scan placed in the wrong place sees through the
    target's walls; in the right place only moving objects, glass and thin structures do.

    Parameters
    ----------
    source_points : ndarray, shape (N, 3)
        In the source's sensor frame (its origin the sensor).
    target_points : ndarray, shape (M, 3)
    T_target_source : ndarray, shape (4, 4)
    spacing : float
        The sampling spacing (the coarser voxel edge of the two clouds).

    Returns
    -------
    violation : float
        Passed through / reached (1.0 when nothing is reached).
    reached : int
        Target points reached.
    """
    R, t = T_target_source[:3, :3], T_target_source[:3, 3]
    r_src = np.sqrt(np.einsum('ij,ij->i', source_points, source_points))
    if not len(r_src):
        return 1.0, 0
    reach = float(r_src.max())
    d2 = np.einsum('ij,ij->i', target_points - t, target_points - t)
    rows = np.flatnonzero(d2 <= reach * reach)
    rows = rows[:: max(1, len(rows) // FREE_SPACE_SAMPLE)]  # a share needs no more
    q = (target_points[rows] - t) @ R  # target points in the source's frame
    r_tgt = np.sqrt(np.einsum('ij,ij->i', q, q))
    ok = r_tgt > 1e-6
    q, r_tgt = q[ok], r_tgt[ok]
    if not len(q):
        return 1.0, 0
    rays = source_points / np.maximum(r_src, 1e-9)[:, None]
    chord, nearest = NeighborIndex(rays).query(q / r_tgt[:, None], k=1)
    chord, nearest = np.asarray(chord).reshape(-1), np.asarray(nearest).reshape(-1)
    r_ret = r_src[nearest]
    margin = np.maximum(FREE_SPACE_RANGE_SHARE * r_ret, FIT_DISTANCE_VOXELS * spacing)
    on_ray = chord * r_tgt <= 0.5 * spacing  # the ray passes through the point's voxel
    reached = on_ray & (r_ret >= r_tgt - margin)
    through = on_ray & (r_ret > r_tgt + margin)
    n = int(np.count_nonzero(reached))
    if n == 0:
        return 1.0, 0
    return float(np.count_nonzero(through)) / n, n
