"""Candidate poses of a scan in a map, without a start: rotations from the Kent mixtures, then
for each the translations from a correlation of the normal channels' occupancy.

Rotations: the twist hypotheses of :mod:`kentreg_ros.core.registration.search` between the
scan's mixture and the map's (normals and their opposites when the map has no viewpoints),
and the mixtures of the places along its recorded path, ranked by the mixtures' overlap, the
distinct best refined by a few passes of the shared-rotation EM against the mixture that
proposed them. A window (a start and how far it may be off) keeps the hypotheses within it.

Translations: for a rotation R, the scan's points (within :data:`~.pointmap.SEARCH_REACH` of
its sensor) turned by R are binned per normal axis like the map's, and the correlation
``c(s) = sum_axis sum_u map_axis(u + s) scan_axis(u)`` over every shift s of the grid comes
from one product of spectra per axis and one inverse FFT; its highest peaks, at least two cells
apart, are the candidate translations. Only the cells' coincidence is scored here: the
registration from each candidate and its fit decide.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft
from numpy.typing import NDArray

from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.geometry import exp_so3, make_transform, rotation_angle
from kentreg_ros.core.localization.pointmap import AXIAL_ROTATIONS_FACTOR, SEARCH_REACH, PointMap
from kentreg_ros.core.registration.em import shared_rotation_em
from kentreg_ros.core.registration.search import distinct_best, mixture_overlap, twist_hypotheses
from kentreg_ros.core.scan import PreparedScan
from kentreg_ros.core.scan.clusters import ModelClusters

FloatArray = NDArray[np.float64]

#: EM passes refining a rotation hypothesis (the search's, see ``robust.SEARCH_EM_PASSES``).
EM_PASSES = 6
#: Correlation values examined for peaks, best first (the suppression keeps a few of them).
PEAK_POOL = 4096
#: Peaks of one rotation closer than this many cells are one peak.
PEAK_SEPARATION_CELLS = 2.0


@dataclass(frozen=True)
class Window:
    """How far a start may be off: the search keeps to rotations within ``angle_deg`` of the
    start's and translations within ``distance`` (m) of its position."""

    distance: float
    angle_deg: float


@dataclass(frozen=True, eq=False)
class Hypothesis:
    """A candidate pose ``T_map_scan`` and its correlation score (cells in agreement)."""

    T: FloatArray
    score: float


def rotations(
    scan: PreparedScan,
    pmap: PointMap,
    config: KentRegConfig,
    *,
    start: FloatArray | None = None,
    window: Window | None = None,
) -> list[FloatArray]:
    """Distinct rotation hypotheses ``R_map_scan``, best overlap first (within the window of
    ``start`` when both are given)."""
    scfg = config.search
    cap = 1.0 / np.radians(scfg.twist_step_deg) ** 2
    count = config.localization.rotations * (1 if pmap.oriented else AXIAL_ROTATIONS_FACTOR)
    pool: list[tuple[float, FloatArray, ModelClusters]] = []
    for mixture in [pmap.clusters, *pmap.places]:
        hyp = twist_hypotheses(scan.clusters, mixture, scfg.twist_step_deg)
        if start is not None and window is not None:
            near = _angles(hyp, start[:3, :3]) <= np.radians(window.angle_deg)
            hyp = np.concatenate([start[None, :3, :3], hyp[near]])
        scores = mixture_overlap(hyp, scan.clusters, mixture, cap)
        for i in distinct_best(hyp, scores, count, scfg.min_separation_deg):
            pool.append((float(scores[i]), hyp[i], mixture))
    pool.sort(key=lambda h: -h[0])
    em_cfg = config.em
    out: list[FloatArray] = []
    tried: list[FloatArray] = []
    min_angle = np.radians(scfg.min_separation_deg)
    for _, R0, mixture in pool:
        if len(tried) >= count:
            break
        if any(rotation_angle(R0.T @ Q) < min_angle for Q in tried):
            continue  # another mixture's hypothesis already covers it
        tried.append(R0)
        em = shared_rotation_em(
            scan.clusters.bins,
            mixture,
            R0,
            outlier_weight=em_cfg.outlier_weight,
            use_beta=em_cfg.kent_beta,
            rotation=em_cfg.rotation,
            kappa_cap_start=em_cfg.kappa_cap_start,
            kappa_cap_end=em_cfg.kappa_cap_end,
            kappa_cap_growth=em_cfg.kappa_cap_growth,
            max_iterations=EM_PASSES,
            tolerance=em_cfg.tolerance,
        )
        R = em.R
        if start is not None and window is not None:
            if rotation_angle(start[:3, :3].T @ R) > np.radians(window.angle_deg):
                R = R0  # the EM left the window: keep the hypothesis itself
        if all(rotation_angle(R.T @ Q) >= min_angle for Q in out):
            out.append(R)
    return out


def _subcell(corr: NDArray[np.float32], index: NDArray[np.intp]) -> FloatArray:
    """Parabolic interpolation of a correlation peak along each axis (cells, within +-0.5)."""
    out = np.zeros(3)
    for axis in range(3):
        lo, hi = index.copy(), index.copy()
        lo[axis] = (index[axis] - 1) % corr.shape[axis]
        hi[axis] = (index[axis] + 1) % corr.shape[axis]
        a, b, c = float(corr[tuple(lo)]), float(corr[tuple(index)]), float(corr[tuple(hi)])
        denom = a - 2.0 * b + c
        if denom < 0.0:
            out[axis] = float(np.clip(0.5 * (a - c) / denom, -0.5, 0.5))
    return out


def _angles(rotations: FloatArray, R: FloatArray) -> FloatArray:
    """Angles between every rotation (H, 3, 3) and ``R``."""
    cos = (np.einsum('ab,hab->h', R, rotations) - 1.0) / 2.0
    out: FloatArray = np.arccos(np.clip(cos, -1.0, 1.0))
    return out


def scan_spectra(
    ijk: NDArray[np.intp], channel: NDArray[np.intp], n_channels: int, shape: tuple[int, ...]
) -> NDArray[np.complex64]:
    """``rfftn`` over ``shape`` of each channel's occupancy of cells ``ijk`` (N, 3), all at or
    above 0: shape (C, shape[0], shape[1], shape[2] // 2 + 1).

    The scan occupies only the corner box of the cells it reaches (a few tens of cells a side
    in a grid of about a hundred), and a transform of zeros is zeros: the transform runs
    along the last axis over the box's lines only, then along the middle axis over the
    box's rows only, then along the first over everything, each padding with zeros as the
    full grid would. The same spectrum as ``rfftn`` of the padded grid, at about a third of
    its cost on the Avia keyframes' grids."""
    ok = np.all(ijk < np.array(shape), axis=1)
    ijk, channel = ijk[ok], channel[ok]
    box = ijk.max(axis=0) + 1 if len(ijk) else np.ones(3, dtype=np.intp)
    occupied = np.zeros((n_channels, *box), dtype=np.float32)
    occupied[channel, ijk[:, 0], ijk[:, 1], ijk[:, 2]] = 1.0
    out = sfft.rfft(occupied, n=shape[2], axis=3, workers=1)
    out = sfft.fft(out, n=shape[1], axis=2, workers=1)
    spectra: NDArray[np.complex64] = sfft.fft(out, n=shape[0], axis=1, workers=1)
    return spectra


def translations(
    scan: PreparedScan,
    R: FloatArray,
    pmap: PointMap,
    n_peaks: int,
    *,
    start: FloatArray | None = None,
    window: Window | None = None,
) -> list[Hypothesis]:
    """The best translations for rotation ``R`` (module docstring), as poses with scores."""
    grid = pmap.grid
    near = np.einsum('ij,ij->i', scan.points, scan.points) <= SEARCH_REACH**2
    x = scan.points[near] @ R.T
    n = scan.normals[near] @ R.T
    if len(x) == 0:
        return []
    channel = pmap.channel_of(n)
    lo_scan = x.min(axis=0)
    ijk = np.floor((x - lo_scan) / grid.cell).astype(np.intp)
    product = scan_spectra(ijk, channel, len(grid.spectra), grid.shape)
    np.conjugate(product, out=product)
    product *= grid.spectra  # in place: the grid-sized products cost as much as a transform
    total = product.sum(axis=0)
    corr = sfft.irfftn(total, grid.shape, workers=1)
    shape = np.array(grid.shape)

    def translation(flat: int) -> FloatArray:
        s = np.array(np.unravel_index(flat, grid.shape), dtype=np.float64)
        s += _subcell(corr, np.array(np.unravel_index(flat, grid.shape)))
        s = np.where(s >= grid.map_cells, s - shape, s)  # wrapped: a negative shift
        t: FloatArray = grid.lo + s * grid.cell - lo_scan
        return t

    values = corr.ravel()
    pool = min(PEAK_POOL, values.size)
    top = np.argpartition(values, values.size - pool)[values.size - pool :]
    top = top[np.argsort(values[top])[::-1]]
    out: list[Hypothesis] = []
    for flat in top:
        t = translation(int(flat))
        if start is not None and window is not None:
            if np.linalg.norm(t - start[:3, 3]) > window.distance + grid.cell:
                continue
        if all(np.linalg.norm(t - h.T[:3, 3]) > PEAK_SEPARATION_CELLS * grid.cell for h in out):
            out.append(Hypothesis(make_transform(R, t), float(values[flat])))
            if len(out) >= n_peaks:
                break
    return out


#: Scan points used by :func:`polish_pose` (every n-th: enough to weigh each surface).
POLISH_POINTS = 2000
#: Passes of :func:`polish_pose`; the correspondence gate shrinks by :data:`POLISH_SHRINK` each
#: pass from 1.5 search cells to :data:`POLISH_MIN_GATE` (m).
POLISH_PASSES = 10
POLISH_SHRINK = 0.75
POLISH_MIN_GATE = 0.3


def polish_pose(scan: PreparedScan, pmap: PointMap, T: FloatArray) -> FloatArray:
    """``T`` after a few passes of point-to-plane Gauss-Newton against the map's points
    (Cauchy weights, a correspondence gate shrinking from 1.5 search cells).

    A correlation peak is placed to a cell, and a plane that fills one layer of cells (a
    floor, a ceiling) gives no sub-cell slope: measured on the quick_shack room, the peak of
    the true rotation lay 0.8-0.9 m below the truth, and a box twin of a registered rotation is
    3-4 deg off the truth it stands for; from there the registration turned away (9-18 deg),
    from the polished start it reached the truth."""
    R = T[:3, :3].copy()
    t = T[:3, 3].copy()
    x0 = scan.points[:: max(1, len(scan.points) // POLISH_POINTS)]
    gate = 1.5 * pmap.grid.cell
    for _ in range(POLISH_PASSES):
        x = x0 @ R.T + t
        dist, idx = pmap.tree.query(x, 1, distance_upper_bound=gate)
        ok = np.isfinite(dist)
        if np.count_nonzero(ok) < 3 * POLISH_POINTS // 100:
            break
        n = pmap.normals[idx[ok]]
        r = np.einsum('ij,ij->i', pmap.points[idx[ok]] - x[ok], n)
        J = np.hstack([np.cross(x[ok], n), n])
        w = 1.0 / (1.0 + (r / (0.25 * gate)) ** 2)
        step = np.linalg.solve((J * w[:, None]).T @ J + 1e-6 * np.eye(6), (J * w[:, None]).T @ r)
        turn = exp_so3(step[:3])
        R = turn @ R
        t = turn @ t + step[3:]
        gate = max(POLISH_MIN_GATE, gate * POLISH_SHRINK)
        if np.linalg.norm(step) < 1e-3:
            break
    return make_transform(R, t)


#: Points within this distance (m) of the map are on it, for :func:`closer_start`.
CLOSE_M = 0.2


def closer_start(scan: PreparedScan, pmap: PointMap, start: Hypothesis) -> Hypothesis:
    """``start`` or its :func:`polish_pose`, whichever puts more of the scan's points
    within :data:`CLOSE_M` of the map. The polish mostly helps (a correlation peak 0.9 m below
    a floor came to 0.5 m, and the registration then converged), but not always: in a corner
    seen from one side it can slide (0.7 to 0.8 m, 4 to 13 deg measured)."""
    polished = polish_pose(scan, pmap, start.T)
    x = scan.points[:: max(1, len(scan.points) // POLISH_POINTS)]
    share = [
        np.count_nonzero(np.isfinite(pmap.tree.query(x @ T[:3, :3].T + T[:3, 3], 1,
                                                     distance_upper_bound=CLOSE_M)[0]))
        for T in (start.T, polished)
    ]  # fmt: skip
    return Hypothesis(polished, start.score) if share[1] > share[0] else start
