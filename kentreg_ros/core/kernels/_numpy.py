"""The per-point loops in numpy: what runs without numba, and the reference the compiled
kernels of :mod:`._jit` repeat operation by operation (``test/core/test_kernels.py``).

Each function has the signature and the results of the kernel of the same name.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import csr_matrix

from kentreg_ros.core.geometry import cross_rows, row_norms

FloatArray = NDArray[np.float64]


def _neighbour_average_operator(neighbors: NDArray[np.intp], n_columns: int) -> csr_matrix:
    """Sparse (N, n_columns) matrix whose product with an array averages over neighbourhoods."""
    n, k = neighbors.shape
    return csr_matrix(
        (np.full(n * k, 1.0 / k), neighbors.ravel(), np.arange(0, n * k + 1, k)),
        shape=(n, n_columns),
    )


def _row_norms(v: FloatArray) -> FloatArray:
    out: FloatArray = np.sqrt(np.einsum('ij,ij->i', v, v))
    return out


def neighbourhood_covariances(centred: FloatArray, neighbors: NDArray[np.intp]) -> FloatArray:
    x, y, z = centred[:, 0], centred[:, 1], centred[:, 2]
    monomials = np.column_stack([x, y, z, x * x, x * y, x * z, y * y, y * z, z * z])
    moments = np.asarray(_neighbour_average_operator(neighbors, len(centred)) @ monomials)
    mx, my, mz = moments[:, 0], moments[:, 1], moments[:, 2]
    out: FloatArray = moments[:, 3:] - np.column_stack(
        [mx * mx, mx * my, mx * mz, my * my, my * mz, mz * mz]
    )
    return out


def smallest_eigenpairs_3x3(
    cov: FloatArray, gap_ratio: float
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
    a, b, c, d, e, f = (cov[:, i] for i in range(6))
    m = (a + d + f) / 3.0
    a1, d1, f1 = a - m, d - m, f - m
    p2 = (a1 * a1 + d1 * d1 + f1 * f1 + 2.0 * (b * b + c * c + e * e)) / 6.0
    p = np.sqrt(p2)
    det = a1 * (d1 * f1 - e * e) - b * (b * f1 - e * c) + c * (b * e - d1 * c)
    safe_p = np.where(p > 0.0, p, 1.0)
    phi = np.arccos(np.clip(0.5 * det / safe_p**3, -1.0, 1.0)) / 3.0
    l_max = m + 2.0 * p * np.cos(phi)
    l_min = m + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    l_mid = 3.0 * m - l_max - l_min
    r0 = np.column_stack([a - l_min, b, c])
    r1 = np.column_stack([b, d - l_min, e])
    r2 = np.column_stack([c, e, f - l_min])
    crosses = np.stack([cross_rows(r0, r1), cross_rows(r0, r2), cross_rows(r1, r2)])  # (3, N, 3)
    norms2 = np.einsum('cni,cni->cn', crosses, crosses)
    best = np.argmax(norms2, axis=0)
    rows = np.arange(len(cov))
    vec = crosses[best, rows]
    vec_norm = np.sqrt(norms2[best, rows])
    scale = np.maximum(np.abs(l_max), np.abs(l_min))
    hard = (p <= 0.0) | (l_mid - l_min <= gap_ratio * scale) | ~(vec_norm > 0.0)
    evecs = vec / np.where(hard, 1.0, vec_norm)[:, None]
    return l_min, evecs, l_mid, hard


def normal_consistency(normals: FloatArray, neighbors: NDArray[np.intp]) -> FloatArray:
    mean = np.asarray(_neighbour_average_operator(neighbors, len(normals)) @ normals)
    norm = np.linalg.norm(mean, axis=1)
    out: FloatArray = np.einsum('ij,ij->i', normals, mean) / np.maximum(norm, 1e-12)
    return out


def assign_and_sum(
    xs: FloatArray, weighted: FloatArray, centers: FloatArray
) -> tuple[NDArray[np.intp], FloatArray]:
    k = len(centers)
    labels = np.argmax(xs @ centers.T, axis=1)
    sums = np.zeros((k, 3))
    for axis in range(3):
        sums[:, axis] = np.bincount(labels, weights=weighted[axis], minlength=k)
    return labels, sums


def lloyd_steps(
    xs: FloatArray,
    weighted: FloatArray,
    centers: FloatArray,
    labels: NDArray[np.intp],
    iterations: int,
) -> tuple[NDArray[np.intp], FloatArray, FloatArray, NDArray[np.intp], int, int]:
    # (labels, centers, sums, new_labels, state, steps): state 0 the labels repeated, 1 the
    # iterations ran out, 2 a cluster came out empty at the last step (labels and centers as
    # before it; its sums and new labels for the caller to re-seed).
    for it in range(iterations):
        new_labels, sums = assign_and_sum(xs, weighted, centers)
        norms = row_norms(sums)
        if (norms < 1e-12).any():
            return labels, centers, sums, new_labels, 2, it + 1
        centers = sums / norms[:, None]
        if np.array_equal(new_labels, labels):
            return labels, centers, sums, new_labels, 0, it + 1
        labels = new_labels
    return labels, centers, np.zeros_like(centers), labels, 1, iterations


def certified_distances(
    x: FloatArray,
    x0: FloatArray,
    radius: FloatArray,
    cand: NDArray[np.intp],
    target: FloatArray,
    gate: float,
) -> tuple[FloatArray, NDArray[np.intp], NDArray[np.bool_]]:
    lower = radius - _row_norms(x - x0)  # every non-candidate target point is at least this far
    has = cand >= 0
    # Distance to each candidate (index 0 as a placeholder where there is none).
    d = np.column_stack(
        [_row_norms(x - np.take(target, np.where(has[:, j], cand[:, j], 0), axis=0))
         for j in range(cand.shape[1])]
    )  # fmt: skip
    d[~has] = np.inf
    col = np.argmin(d, axis=1)
    rows = np.arange(len(x))
    dist = d[rows, col]
    nearest = np.where(np.isfinite(dist), cand[rows, col], -1)
    valid = (dist <= lower) | (gate < lower)
    return dist, nearest, valid


def cluster_moments(
    normals: FloatArray, labels: NDArray[np.intp], k: int
) -> tuple[FloatArray, FloatArray, FloatArray]:
    mass: FloatArray = np.bincount(labels, minlength=k).astype(np.float64)
    xsum: FloatArray = np.column_stack(
        [np.bincount(labels, weights=normals[:, a], minlength=k) for a in range(3)]
    )
    scatter = np.empty((k, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            col = np.bincount(labels, weights=normals[:, a] * normals[:, b], minlength=k)
            scatter[:, a, b] = scatter[:, b, a] = col
    return mass, xsum, scatter


def argsort_keys(keys: NDArray[np.int64]) -> NDArray[np.intp]:
    # numpy sorts 16-bit integers stably by radix sort; one such pass per digit.
    order = np.argsort((keys & 0xFFFF).astype(np.uint16), kind='stable')
    rest = keys >> 16
    while rest.any():
        order = order[np.argsort((rest[order] & 0xFFFF).astype(np.uint16), kind='stable')]
        rest = rest >> 16
    return order


#: What :func:`voxel_admission` returns: keep (N,), new keys, positions, present, added (G,).
Admission = tuple[
    NDArray[np.bool_], NDArray[np.int64], NDArray[np.intp], NDArray[np.bool_], NDArray[np.intp]
]


def normal_bin_keys(
    normals: FloatArray, cells: FloatArray, groups: NDArray[np.intp], span: int
) -> NDArray[np.int64]:
    keys = np.floor(normals / cells[:, None]).astype(np.int64)
    width = 2 * span + 1
    flat: NDArray[np.int64] = ((keys[:, 0] + span) * width + keys[:, 1] + span) * width + (
        keys[:, 2] + span
    )
    if len(groups):
        flat = flat + groups.astype(np.int64) * width**3
    return flat


def run_starts(ordered: NDArray[np.int64]) -> tuple[NDArray[np.intp], FloatArray]:
    if not len(ordered):
        return np.zeros(0, dtype=np.intp), np.zeros(0)
    starts = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]])
    counts: FloatArray = np.diff(np.r_[starts, len(ordered)]).astype(np.float64)
    return starts, counts


def sorted_positions(
    haystack: NDArray[np.int64], needles: NDArray[np.int64], right: bool
) -> NDArray[np.intp]:
    out: NDArray[np.intp] = np.searchsorted(haystack, needles, side='right' if right else 'left')
    return out


def voxel_admission(
    sorted_keys: NDArray[np.int64],
    voxel_keys: NDArray[np.int64],
    voxel_counts: NDArray[np.int64],
    max_points: int,
) -> Admission:
    starts_mask = np.empty(len(sorted_keys), dtype=bool)
    starts_mask[0] = True
    np.not_equal(sorted_keys[1:], sorted_keys[:-1], out=starts_mask[1:])
    starts = np.flatnonzero(starts_mask)
    group = np.cumsum(starts_mask) - 1
    rank = np.arange(len(sorted_keys)) - starts[group]
    new_voxels = sorted_keys[starts]
    pos = np.searchsorted(voxel_keys, new_voxels)
    present = np.zeros(len(new_voxels), dtype=bool)
    if len(voxel_keys):
        present = voxel_keys[np.minimum(pos, len(voxel_keys) - 1)] == new_voxels
    existing = np.zeros(len(new_voxels), dtype=np.int64)
    existing[present] = voxel_counts[pos[present]]
    keep = rank + existing[group] < max_points
    added = np.bincount(group[keep], minlength=len(new_voxels))
    return keep, new_voxels, pos, present, added


def voxel_keys(
    points: FloatArray, voxel_size: float, corner: FloatArray, span: FloatArray
) -> NDArray[np.int64]:
    f = np.floor(points / voxel_size)
    f -= corner
    keys: NDArray[np.int64] = ((f[:, 0] * span[1] + f[:, 1]) * span[2] + f[:, 2]).astype(np.int64)
    return keys


def voxel_centroids(
    points: FloatArray,
    order: NDArray[np.intp],
    starts: NDArray[np.intp],
    counts: NDArray[np.intp],
    min_points: int,
) -> FloatArray:
    keep = counts >= min_points
    # np.take gathers rows several times faster than fancy indexing here.
    sums = np.add.reduceat(np.take(points, order, axis=0), starts, axis=0)
    out: FloatArray = np.ascontiguousarray(sums[keep] / counts[keep, None])
    return out


def plane_residuals(
    x: FloatArray,
    idx: NDArray[np.intp],
    n_target: int,
    target: FloatArray,
    target_normals: FloatArray,
    source_normals: FloatArray,
    R: FloatArray,
) -> tuple[NDArray[np.intp], FloatArray, FloatArray]:
    ok = np.flatnonzero(idx < n_target)
    j = idx[ok]
    e = np.take(target, j, axis=0) - np.take(x, ok, axis=0)
    nq = np.take(target_normals, j, axis=0)
    r = np.einsum('ij,ij->i', nq, e)
    cos = np.einsum('ij,ij->i', nq, np.take(source_normals, ok, axis=0) @ R.T)
    return ok, r, cos


def plane_normal_equations(
    x: FloatArray,
    idx: NDArray[np.intp],
    ok: NDArray[np.intp],
    target_normals: FloatArray,
    r: FloatArray,
    w: FloatArray,
) -> tuple[FloatArray, FloatArray, float, float]:
    nq = np.take(target_normals, idx[ok], axis=0)
    Jn = np.empty((len(ok), 6))  # n^T [hat(x), -I]: the left perturbation (omega, v)
    Jn[:, :3] = cross_rows(nq, np.take(x, ok, axis=0))
    np.negative(nq, out=Jn[:, 3:])
    Jw = Jn * w[:, None]
    return Jw.T @ Jn, Jw.T @ r, float(np.sum(w * r**2)), float(w.sum())


def offset_residuals(
    x: FloatArray,
    idx: NDArray[np.intp],
    n_target: int,
    target: FloatArray,
    target_normals: FloatArray,
) -> tuple[NDArray[np.intp], FloatArray]:
    ok = np.flatnonzero(idx < n_target)
    j = idx[ok]
    q = np.take(target, j, axis=0)
    nq = np.take(target_normals, j, axis=0)
    return ok, np.einsum('ij,ij->i', nq, np.take(x, ok, axis=0) - q)


def offset_normal_equations(
    idx: NDArray[np.intp],
    ok: NDArray[np.intp],
    target_normals: FloatArray,
    r: FloatArray,
    w: FloatArray,
) -> tuple[FloatArray, FloatArray, float, float]:
    nq = np.take(target_normals, idx[ok], axis=0)
    nw = nq * w[:, None]
    return nw.T @ nq, nw.T @ r, float(np.sum(w * r * r)), float(np.sum(w))


def bin_moments(
    normals: FloatArray, order: NDArray[np.intp], starts: NDArray[np.intp]
) -> tuple[FloatArray, FloatArray]:
    """Per run ``starts`` of ``order``: the sum of the normals (B, 3) and of their outer
    products (B, 9, row-major)."""
    ordered = normals[order]
    sums = np.add.reduceat(ordered, starts, axis=0)
    outer = (ordered[:, :, None] * ordered[:, None, :]).reshape(-1, 9)
    return sums, np.add.reduceat(outer, starts, axis=0)


def map_merge(
    target: NDArray[np.intp],
    pts: FloatArray,
    nrm: FloatArray,
    has_normals: bool,
    merged: FloatArray,
    sums: FloatArray,
    normal_sums: FloatArray,
    points: FloatArray,
    normals: FloatArray,
) -> None:
    """Average ``pts`` (and ``nrm``, turned to agree in sign with the normal they join) into
    the map rows ``target``, in place: ``merged`` counts, ``sums`` and ``normal_sums`` the
    running sums, ``points`` and ``normals`` their means."""
    n = len(points)
    added = np.bincount(target, minlength=n)
    touched = np.flatnonzero(added)
    merged[touched] += added[touched]
    for axis in range(3):
        sums[touched, axis] += np.bincount(target, pts[:, axis], n)[touched]
    points[touched] = sums[touched] / merged[touched, None]
    if has_normals:
        agree = np.einsum('ij,ij->i', normals[target], nrm) >= 0.0
        turned = np.where(agree[:, None], nrm, -nrm)
        for axis in range(3):
            normal_sums[touched, axis] += np.bincount(target, turned[:, axis], n)[touched]
        grown = normal_sums[touched]
        normals[touched] = grown / np.linalg.norm(grown, axis=1, keepdims=True)


def kent_frames(
    xbar: FloatArray, scatter: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    r1: FloatArray = np.linalg.norm(xbar, axis=1)
    m = np.where((r1 > 0.0)[:, None], xbar / np.where(r1 > 0.0, r1, 1.0)[:, None], [1.0, 0, 0])
    # Kent's H with first column m = (cos t, sin t cos p, sin t sin p).
    c = m[:, 0]
    s = np.hypot(m[:, 1], m[:, 2])
    safe = s > 0.0
    cp = np.where(safe, m[:, 1] / np.where(safe, s, 1.0), 1.0)
    sp = np.where(safe, m[:, 2] / np.where(safe, s, 1.0), 0.0)
    zero = np.zeros_like(c)
    h: FloatArray = np.stack(
        [
            np.stack([c, -s, zero], axis=1),
            np.stack([s * cp, c * cp, -sp], axis=1),
            np.stack([s * sp, c * sp, cp], axis=1),
        ],
        axis=1,
    )
    b = np.einsum('kia,kij,kjb->kab', h, scatter, h)
    diff: FloatArray = b[:, 1, 1] - b[:, 2, 2]
    off: FloatArray = 2.0 * b[:, 1, 2]
    return r1, h, diff, off


def kent_finish(
    r1: FloatArray,
    h: FloatArray,
    cos_psi: FloatArray,
    sin_psi: FloatArray,
    r2: FloatArray,
    scatter: FloatArray,
    kappa_max: float,
    max_beta_ratio: float,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    cps, sps = cos_psi[:, None], sin_psi[:, None]
    g1 = cps * h[:, :, 1] + sps * h[:, :, 2]
    g2 = -sps * h[:, :, 1] + cps * h[:, :, 2]
    gamma: FloatArray = np.stack([h[:, :, 0], g1, g2], axis=2)
    # 1 - r1 from the spread trace(S) - r1^2 = 1 - r1^2 (trace(S) = 1 up to rounding).
    one_minus_r1 = np.maximum(np.trace(scatter, axis1=1, axis2=2) - r1 * r1, 0.0) / (1.0 + r1)
    d_minus = np.maximum(2.0 * one_minus_r1 - r2, 0.5 / kappa_max)
    d_plus = np.maximum(2.0 * one_minus_r1 + r2, 0.5 / kappa_max)
    kappa: FloatArray = np.minimum(1.0 / d_minus + 1.0 / d_plus, kappa_max)
    resolved = one_minus_r1 > 64.0 * np.finfo(np.float64).eps
    ratio = np.where(resolved, r2 / (4.0 * np.where(resolved, one_minus_r1, 1.0)), 0.0)
    beta: FloatArray = np.minimum(ratio, max_beta_ratio) * kappa
    return kappa, beta, gamma


def bin_group_moments(
    labels: NDArray[np.intp],
    posterior: FloatArray,
    weights: FloatArray,
    resultants: FloatArray,
    scatters: FloatArray,
    k: int,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    member = np.zeros((k, len(labels)))
    member[labels, np.arange(len(labels))] = 1.0
    weighted: FloatArray = (member * posterior) @ scatters
    return weighted, member @ weights, member @ resultants, member @ scatters


def e_step(
    z: FloatArray,
    assign: NDArray[np.intp],
    wx: FloatArray,
    resultants: FloatArray,
    y: FloatArray,
    ym: FloatArray,
    off: NDArray[np.intp],
    log_pi: FloatArray,
    log_c: FloatArray,
    kappa: FloatArray,
    beta: FloatArray,
    gamma: FloatArray,
    log_out: float,
) -> tuple[FloatArray, float, FloatArray, FloatArray]:
    k = len(kappa)
    order = np.argsort(assign, kind='stable')
    bounds = np.searchsorted(assign[order], np.arange(k + 1))
    Cs = np.zeros((k, 3, 3))
    loglik = 0.0
    tn = np.zeros(len(z))
    t_unit = np.zeros(len(z))  # posterior mass per normal of each bin
    for j in range(k):
        idx = order[bounds[j] : bounds[j + 1]]
        ys = slice(off[j], off[j + 1])
        if len(idx) == 0 or off[j + 1] == off[j]:
            continue
        zj, wj = z[idx], wx[idx]
        # One (model bins x observed bins) array, updated in place: the same values as the
        # expressions written out (IEEE addition commutes), without a temporary per operation.
        logits = y[ys] @ zj.T
        logits *= kappa[j]
        logits += (log_pi[ys] - log_c[j])[:, None]
        if beta[j] > 0.0:
            g1, g2 = gamma[j][:, 1], gamma[j][:, 2]
            logits += beta[j] * ((zj @ g1) ** 2 - (zj @ g2) ** 2)[None, :]
        top = logits.max(axis=0)
        np.maximum(top, log_out, out=top)
        logits -= top
        share = np.exp(logits, out=logits)
        total = share.sum(axis=0)
        total += np.exp(log_out - top)
        loglik += float(np.dot(wj, top + np.log(total)))
        # Posteriors per normal (constant across a bin), summed over the bin's normals
        # through its exact moments: sum_i tau x_i = (tau / w) * resultant.
        share /= total
        t_n = share.sum(axis=0)  # posterior mass per normal of bin n
        tn[idx] = t_n * wj
        t_unit[idx] = t_n
        Cs[j] = kappa[j] * (resultants[idx].T @ (share.T @ ym[ys]))
    return Cs, loglik, tn, t_unit
