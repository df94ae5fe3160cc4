"""Translation with the rotation fixed.

* :func:`centroid_translation`: the paper's eq. (translation) ``t = mu_y - R mu_x``.
* :func:`plane_offset_translation`: a correspondence-free start. For each dominant model normal
  direction, the histograms of plane offsets ``d = mu . p`` of the model points and of the
  rotated observed points are cross-correlated; the best shift is the translation component
  along that direction. The components are combined by weighted least squares.
* :func:`point_to_plane_translation`: robust 3-DOF point-to-plane least squares (IRLS with a
  Geman-McClure kernel) on nearest-neighbour correspondences. The smallest eigenvalue of its
  normal matrix flags directions the scene does not constrain (e.g. a corridor's axis).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core import kernels
from kentreg_ros.core.registration.correspondence import NearestNeighborCache
from kentreg_ros.core.scan.neighbors import NeighborIndex

#: Fewest correspondences for the 3-DOF solve (a few times the unknowns).
MIN_CORRESPONDENCES = 10
#: The correspondence gate shrinks by this factor per iteration down to its floor.
GATE_SHRINK = 0.7
#: A point joins the plane-offset histogram of a direction when its normal is within
#: arccos(0.9) = 26 deg of it: the spread of one cluster of normals around its mean.
PLANE_COSINE = 0.9
#: Fewest points (per cloud) a direction's histogram needs for a usable correlation peak.
PLANE_MIN_POINTS = 50
#: Histogram bins per point (of both clouds) at most, and the floor of that cap. A histogram
#: of n offsets needs resolution only where offsets are; beyond a few bins per point it is
#: mostly empty. The bins are widened where the offsets spread farther than the cap allows
#: (points far beyond any sensor's range, e.g. garbage returns or a wrong deskew), so memory
#: and time follow the point count, never the cloud's extent. Real scans stay far below it
#: (10k points at 0.1 m bins: 8 km).
MAX_BINS_PER_POINT = 8
MIN_MAX_BINS = 4096

FloatArray = NDArray[np.float64]


def centroid_translation(R: FloatArray, source: FloatArray, target: FloatArray) -> FloatArray:
    """``t = mean(target) - R mean(source)`` (the paper's translation)."""
    return target.mean(axis=0) - R @ source.mean(axis=0)


def plane_offset_translation(
    R: FloatArray,
    t0: FloatArray,
    source: FloatArray,
    source_normals: FloatArray,
    target: FloatArray,
    target_normals: FloatArray,
    directions: FloatArray,
    *,
    bin_size: float = 0.05,
    max_shift: float = 2.0,
    min_cosine: float = PLANE_COSINE,
    min_points: int = PLANE_MIN_POINTS,
) -> tuple[FloatArray, int]:
    """Translation from cross-correlated plane-offset histograms per direction.

    Parameters
    ----------
    R : ndarray, shape (3, 3)
        Rotation source -> target.
    t0 : ndarray, shape (3,)
        Prior translation; the search along each direction is within ``max_shift`` of it, and
        directions the clusters do not span keep its component.
    source, source_normals : ndarray, shape (N, 3)
    target, target_normals : ndarray, shape (M, 3)
    directions : ndarray, shape (K, 3)
        Unit directions (the model's cluster mean normals).

    Returns
    -------
    t : ndarray, shape (3,)
    used : int
        Number of directions that contributed.
    """
    src = source @ R.T
    src_n = source_normals @ R.T
    rows: list[FloatArray] = []
    rhs: list[float] = []
    wts: list[float] = []
    # Lags searched on each side of the prior: at least one bin, so a coarse bin (large
    # voxels) still gets a three-point peak to interpolate.
    half = max(int(np.ceil(max_shift / bin_size)), 1)
    for d in directions:
        mt = target_normals @ d > min_cosine
        ms = src_n @ d > min_cosine
        if mt.sum() < min_points or ms.sum() < min_points:
            continue
        # Offsets of every point, then the masked ones: a boolean gather of 1-D rows instead
        # of (N, 3) ones, which numpy does several times more slowly (same values).
        off_t = (target @ d)[mt]
        off_s = (src @ d)[ms] + float(d @ t0)
        # Only source offsets within max_shift of the target's range can enter a searched lag.
        lo, hi = off_t.min() - max_shift, off_t.max() + max_shift
        off_s = off_s[(off_s >= lo) & (off_s <= hi)]
        if len(off_s) < min_points:
            continue
        found = _offset_shift(off_t, off_s, lo, hi, bin_size, max_shift, half)
        if found is None:
            continue
        shift, contrast = found
        # Confidence: the correlation's contrast times the points involved.
        rows.append(d)
        rhs.append(float(d @ t0) + shift)
        wts.append(contrast * min(ms.sum(), mt.sum()))
    if not rows:
        return np.array(t0, dtype=np.float64), 0
    D = np.array(rows)
    s = np.array(rhs)
    w = np.array(wts)
    # Weighted least squares with a weak prior toward t0 for unconstrained directions.
    H = (D * w[:, None]).T @ D
    g = (D * w[:, None]).T @ s
    reg = 1e-6 * max(float(np.trace(H)), 1e-12)
    t = np.linalg.solve(H + reg * np.eye(3), g + reg * t0)
    return t, len(rows)


def _offset_shift(
    off_t: FloatArray,
    off_s: FloatArray,
    lo: float,
    hi: float,
    bin_size: float,
    max_shift: float,
    half: int,
) -> tuple[float, float] | None:
    """The shift along one direction that lines the source's plane offsets ``off_s`` up with
    the target's ``off_t`` (both within ``[lo, hi]``), and its contrast (the correlation's
    peak over its mean); None without a positive peak.

    The offsets are binned (``bin_size``, widened when ``[lo, hi]`` would need more than
    :data:`MAX_BINS_PER_POINT` bins a point), the histograms cross-correlated by FFT at the
    lags within ``max_shift`` (``half`` of them on each side), and the peak placed between
    bins by the parabola through it and its neighbours.
    """
    step, n_lags = bin_size, half
    max_bins = max(MIN_MAX_BINS, MAX_BINS_PER_POINT * (len(off_t) + len(off_s)))
    if (hi - lo) / step + 2 * n_lags > max_bins:
        step = max(step, (hi - lo + 2 * max_shift) / max_bins)
        n_lags = max(int(np.ceil(max_shift / step)), 1)
    edges_n = int(np.ceil((hi - lo) / step)) + 1
    ht = np.bincount(((off_t - lo) / step).astype(np.intp), minlength=edges_n)
    hs = np.bincount(((off_s - lo) / step).astype(np.intp), minlength=edges_n)
    ht = ht.astype(np.float64)
    hs = hs.astype(np.float64)
    lags = np.arange(-n_lags, n_lags + 1)
    size = 1 << int(np.ceil(np.log2(2 * edges_n + 2 * n_lags)))
    corr = np.fft.irfft(np.fft.rfft(ht, size) * np.conj(np.fft.rfft(hs, size)), size)
    shifts = corr[lags % size]  # correlation at each lag (circular index, no wrap-around)
    best = int(np.argmax(shifts))
    peak = shifts[best]
    if peak <= 0:
        return None
    # Parabolic sub-bin interpolation.
    frac = 0.0
    if 0 < best < len(shifts) - 1:
        a, b, c = shifts[best - 1], shifts[best], shifts[best + 1]
        denom = a - 2 * b + c
        if denom < 0:
            frac = 0.5 * (a - c) / denom
    shift = (lags[best] + frac) * step
    contrast = peak / max(float(np.mean(np.abs(shifts))), 1e-12)
    return float(shift), float(contrast)


@dataclass(frozen=True)
class TranslationResult:
    """Outcome of :func:`point_to_plane_translation`.

    Attributes
    ----------
    t : ndarray, shape (3,)
    hessian : ndarray, shape (3, 3)
        Normal matrix ``sum w n n^T`` at the solution.
    sigma2 : float
        Weighted residual variance (m^2).
    iterations : int
    inlier_fraction : float
    degenerate_directions : ndarray, shape (D, 3)
        Unit directions whose eigenvalue ratio is below the threshold.
    gate : float
        The correspondence gate the next iteration would have used (m).
    """

    t: FloatArray
    hessian: FloatArray
    sigma2: float
    iterations: int
    inlier_fraction: float
    degenerate_directions: FloatArray
    gate: float = 0.0


def robust_scale(residuals: FloatArray, floor: float) -> float:
    """Robust standard deviation (1.4826 MAD), at least ``floor``."""
    n = len(residuals)
    if n == 0:
        return floor
    # np.median's value (the middle one, or the mean of the two middle ones) from one partition
    # of |r| in place: np.median copies, checks for NaN and dispatches, which cost as much as
    # the partition on the few thousand residuals of an iteration.
    a = np.abs(residuals)
    h = n // 2
    if n % 2:
        a.partition(h)
        median = float(a[h])
    else:
        a.partition((h - 1, h))
        median = float((a[h - 1] + a[h]) / 2.0)
    return max(1.4826 * median, floor)


def geman_mcclure_weights(r: FloatArray, sigma: float) -> FloatArray:
    """IRLS weights of the Geman-McClure kernel ``rho(r) = r^2 / (r^2 + sigma^2)``."""
    s2 = sigma * sigma
    return (s2 / (s2 + r * r)) ** 2


def degenerate_directions(H: FloatArray, ratio: float) -> FloatArray:
    """Eigenvectors of a symmetric PSD matrix whose eigenvalue is < ``ratio`` * largest."""
    evals, evecs = np.linalg.eigh(H)
    top = max(float(evals[-1]), 1e-300)
    return evecs[:, evals < ratio * top].T


def point_to_plane_translation(
    R: FloatArray,
    t0: FloatArray,
    source: FloatArray,
    target: FloatArray,
    target_normals: FloatArray,
    target_tree: NeighborIndex,
    *,
    max_iterations: int = 20,
    max_distance: float = 1.0,
    min_distance: float = 0.1,
    noise_floor: float = 0.005,
    degeneracy_ratio: float = 0.02,
    tolerance: float = 1e-3,
    neighbors: NearestNeighborCache | None = None,
) -> TranslationResult:
    """Robust 3-DOF point-to-plane least squares for ``t`` with ``R`` fixed.

    The correspondence gate shrinks geometrically from ``max_distance`` toward
    ``min_distance``; residuals are weighted by Geman-McClure with a robust (MAD) scale.
    ``neighbors`` (a cache over ``target_tree`` and ``source``) can be shared with a following
    refinement; correspondences are exact nearest neighbours either way.
    """
    src = source @ R.T
    nn = neighbors or NearestNeighborCache(target_tree, target, len(source))
    t = np.array(t0, dtype=np.float64)
    gate = max_distance
    H = np.zeros((3, 3))
    sigma2 = 0.0
    inlier = 0.0
    it = 0
    for it in range(1, max_iterations + 1):
        moved = src + t
        _, idx = nn.query(moved, gate)
        rows, r = kernels.offset_residuals(moved, idx, target, target_normals)
        if len(rows) < MIN_CORRESPONDENCES:
            break
        w = geman_mcclure_weights(r, robust_scale(r, noise_floor))
        H, g, wrr, wsum = kernels.offset_normal_equations(idx, rows, target_normals, r, w)
        sigma2 = wrr / max(wsum, 1e-12)
        inlier = len(rows) / len(moved)
        reg = 1e-9 * max(float(np.trace(H)), 1e-12)
        dt = -np.linalg.solve(H + reg * np.eye(3), g)
        t = t + dt
        gate = max(gate * GATE_SHRINK, min_distance)
        if np.linalg.norm(dt) < tolerance and gate <= min_distance:
            break
    return TranslationResult(
        t=t,
        hessian=H,
        sigma2=sigma2,
        iterations=it,
        inlier_fraction=inlier,
        degenerate_directions=degenerate_directions(H, degeneracy_ratio),
        gate=gate,
    )
