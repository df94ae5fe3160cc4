"""numba-compiled loops behind :mod:`kentreg_ros.core.kernels` (imported only through it).

Each kernel performs the same floating-point operations in the same order as the numpy expression
it replaces (no fast-math, so no fused multiply-add; a three-term ``einsum`` is summed as numpy's
x86-64 build sums it, ``(x + z) + y``). Only IEEE-exact operations (+, -, *, /, sqrt) and
``hypot`` (the C library's, which numpy calls too) run here: what numpy computes with its own SIMD
routines, which round differently by CPU (``**``, ``arccos``, ``cos``, ``exp``), stays in numpy.
Only the Gauss-Newton normal equations and the EM's sums of bins per cluster sum their rows in
another order than numpy's matrix products (which are BLAS's). On this project's machines the poses
with the previous scan are bit-identical with and without the other kernels, and within 1e-14 with
all of them (the local map carries the difference on, see the package's docstring); the tests
compare them within bounds that hold on any CPU. They are written for one thread (``nogil``: the
node's worker releases the GIL while one runs).
"""

from __future__ import annotations

import numba
import numpy as np

_jit = numba.njit(cache=True, nogil=True, fastmath=False, error_model='numpy')


@_jit
def neighbourhood_covariances(c, neighbors):  # type: ignore[no-untyped-def]
    """Covariance entries ``(xx, xy, xz, yy, yz, zz)`` of each row of ``neighbors`` over the
    centred points ``c``: the neighbourhood average of the monomials, accumulated term by
    term with weight ``1 / k`` as the sparse product does, minus the outer product of the
    mean."""
    n, k = neighbors.shape
    inv = 1.0 / k
    out = np.empty((n, 6))
    for i in range(n):
        sx = 0.0
        sy = 0.0
        sz = 0.0
        sxx = 0.0
        sxy = 0.0
        sxz = 0.0
        syy = 0.0
        syz = 0.0
        szz = 0.0
        for j in range(k):
            q = neighbors[i, j]
            x = c[q, 0]
            y = c[q, 1]
            z = c[q, 2]
            sx += inv * x
            sy += inv * y
            sz += inv * z
            sxx += inv * (x * x)
            sxy += inv * (x * y)
            sxz += inv * (x * z)
            syy += inv * (y * y)
            syz += inv * (y * z)
            szz += inv * (z * z)
        out[i, 0] = sxx - sx * sx
        out[i, 1] = sxy - sx * sy
        out[i, 2] = sxz - sx * sz
        out[i, 3] = syy - sy * sy
        out[i, 4] = syz - sy * sz
        out[i, 5] = szz - sz * sz
    return out


@_jit
def normal_consistency(normals, neighbors):  # type: ignore[no-untyped-def]
    """Cosine between each normal and the mean normal of its neighbourhood."""
    n, k = neighbors.shape
    inv = 1.0 / k
    out = np.empty(n)
    for i in range(n):
        mx = 0.0
        my = 0.0
        mz = 0.0
        for j in range(k):
            q = neighbors[i, j]
            mx += inv * normals[q, 0]
            my += inv * normals[q, 1]
            mz += inv * normals[q, 2]
        norm = np.sqrt(mx * mx + my * my + mz * mz)
        dot = (normals[i, 0] * mx + normals[i, 2] * mz) + normals[i, 1] * my  # einsum's order
        out[i] = dot / max(norm, 1e-12)
    return out


@_jit
def assign_and_sum(xs, weighted, centers):  # type: ignore[no-untyped-def]
    """One Lloyd step of spherical k-means: the centre of largest cosine for each row of
    ``xs`` (the first on ties, as ``argmax``) and the per-centre sums of the rows of
    ``weighted`` (the weighted vectors, (3, N)) in row order, as ``bincount`` sums them."""
    n = xs.shape[0]
    k = centers.shape[0]
    labels = np.empty(n, dtype=np.intp)
    sums = np.zeros((k, 3))
    for i in range(n):
        best = 0
        best_sim = -np.inf
        for j in range(k):
            s = xs[i, 0] * centers[j, 0] + xs[i, 1] * centers[j, 1] + xs[i, 2] * centers[j, 2]
            if s > best_sim:
                best_sim = s
                best = j
        labels[i] = best
        sums[best, 0] += weighted[0, i]
        sums[best, 1] += weighted[1, i]
        sums[best, 2] += weighted[2, i]
    return labels, sums


@_jit
def lloyd_steps(xs, weighted, centers, labels, iterations):  # type: ignore[no-untyped-def]
    """Up to ``iterations`` Lloyd steps of spherical k-means from ``centers`` (see the numpy
    twin for the contract), each an :func:`assign_and_sum` and the normalised sums as the new
    centres (norms as ``geometry.row_norms``), until the labels repeat."""
    k = centers.shape[0]
    n = xs.shape[0]
    norms = np.empty(k)
    for it in range(iterations):
        new_labels, sums = assign_and_sum(xs, weighted, centers)
        empty = False
        for j in range(k):
            norms[j] = np.sqrt(
                (sums[j, 0] * sums[j, 0] + sums[j, 1] * sums[j, 1]) + sums[j, 2] * sums[j, 2]
            )
            empty = empty or norms[j] < 1e-12
        if empty:
            return labels, centers, sums, new_labels, 2, it + 1
        updated = np.empty((k, 3))
        for j in range(k):
            for a in range(3):
                updated[j, a] = sums[j, a] / norms[j]
        centers = updated
        same = True
        for i in range(n):
            if new_labels[i] != labels[i]:
                same = False
                break
        if same:
            return labels, centers, sums, new_labels, 0, it + 1
        labels = new_labels
    return labels, centers, np.zeros((k, 3)), labels, 1, iterations


@_jit
def certified_distances(x, x0, radius, cand, target, gate):  # type: ignore[no-untyped-def]
    """For :class:`~kentreg_ros.core.registration.correspondence.NearestNeighborCache`: the
    nearest of each query point's cached candidates (index -1 and distance inf without one) and
    whether the cache certifies it (see that module): ``d <= radius - |x - x0|``, or
    ``gate < radius - |x - x0|`` (then no other target point is within the gate)."""
    n = x.shape[0]
    c = cand.shape[1]
    dist = np.empty(n)
    nearest = np.empty(n, dtype=np.intp)
    valid = np.empty(n, dtype=np.bool_)
    for i in range(n):
        dx = x[i, 0] - x0[i, 0]
        dy = x[i, 1] - x0[i, 1]
        dz = x[i, 2] - x0[i, 2]
        lower = radius[i] - np.sqrt((dx * dx + dz * dz) + dy * dy)  # einsum's order
        best = np.inf
        best_q = -1
        for j in range(c):
            q = cand[i, j]
            if q >= 0:
                ex = x[i, 0] - target[q, 0]
                ey = x[i, 1] - target[q, 1]
                ez = x[i, 2] - target[q, 2]
                d = np.sqrt((ex * ex + ez * ez) + ey * ey)
                if d < best:
                    best = d
                    best_q = q
        dist[i] = best
        nearest[i] = best_q
        valid[i] = best <= lower or gate < lower
    return dist, nearest, valid


@_jit
def cluster_moments(normals, labels, k):  # type: ignore[no-untyped-def]
    """Per-cluster count, resultant (K, 3) and scatter (K, 3, 3) of unit normals, each summed
    in row order as ``bincount`` sums it."""
    mass = np.zeros(k)
    xsum = np.zeros((k, 3))
    scatter = np.zeros((k, 3, 3))
    for i in range(normals.shape[0]):
        j = labels[i]
        mass[j] += 1.0
        for a in range(3):
            xsum[j, a] += normals[i, a]
            for b in range(a, 3):
                scatter[j, a, b] += normals[i, a] * normals[i, b]
    for j in range(k):
        for a in range(3):
            for b in range(a + 1, 3):
                scatter[j, b, a] = scatter[j, a, b]
    return mass, xsum, scatter


@_jit
def normal_bin_keys(normals, cells, groups, span):  # type: ignore[no-untyped-def]
    """The flat key of every normal's cell (edge ``cells[i]``) on the cubic grid around the
    unit sphere, offset by its group (if ``groups`` is not empty): the numpy twin's integer
    arithmetic in one pass."""
    n = normals.shape[0]
    width = 2 * span + 1
    cube = width * width * width
    flat = np.empty(n, dtype=np.int64)
    grouped = groups.shape[0] > 0
    for i in range(n):
        c = cells[i]
        k0 = np.int64(np.floor(normals[i, 0] / c))
        k1 = np.int64(np.floor(normals[i, 1] / c))
        k2 = np.int64(np.floor(normals[i, 2] / c))
        f = ((k0 + span) * width + k1 + span) * width + (k2 + span)
        if grouped:
            f += groups[i] * cube
        flat[i] = f
    return flat


@_jit
def run_starts(ordered):  # type: ignore[no-untyped-def]
    """Where each run of equal values of ``ordered`` starts, and its length (as float64)."""
    n = ordered.shape[0]
    starts = np.empty(n, dtype=np.intp)
    m = 0
    for i in range(n):
        if i == 0 or ordered[i] != ordered[i - 1]:
            starts[m] = i
            m += 1
    counts = np.empty(m)
    for j in range(m):
        counts[j] = (starts[j + 1] if j + 1 < m else n) - starts[j]
    return starts[:m].copy(), counts


@_jit
def voxel_keys(points, voxel_size, corner, span):  # type: ignore[no-untyped-def]
    """Linear voxel index of every point, in float64 arithmetic as the numpy expression
    ``((f0 * span1 + f1) * span2 + f2)`` with ``f = floor(p / size) - corner``."""
    n = points.shape[0]
    keys = np.empty(n, dtype=np.int64)
    for i in range(n):
        f0 = np.floor(points[i, 0] / voxel_size) - corner[0]
        f1 = np.floor(points[i, 1] / voxel_size) - corner[1]
        f2 = np.floor(points[i, 2] / voxel_size) - corner[2]
        keys[i] = np.int64((f0 * span[1] + f1) * span[2] + f2)
    return keys


@_jit
def argsort_keys(keys):  # type: ignore[no-untyped-def]
    """Stable argsort of non-negative int64 keys: an LSD radix sort over 16-bit digits, the
    same passes as the numpy twin's, each a counting sort (count, prefix sum, scatter)."""
    n = keys.shape[0]
    order = np.arange(n)
    spare = np.empty(n, dtype=np.intp)
    counts = np.empty(65536, dtype=np.intp)
    top = 0
    for i in range(n):
        top = max(top, keys[i])
    shift = 0
    while True:
        counts[:] = 0
        for i in range(n):
            counts[(keys[i] >> shift) & 0xFFFF] += 1
        total = 0
        for d in range(65536):
            c = counts[d]
            counts[d] = total
            total += c
        for i in range(n):
            o = order[i]
            d = (keys[o] >> shift) & 0xFFFF
            spare[counts[d]] = o
            counts[d] += 1
        order, spare = spare, order
        shift += 16
        if shift >= 64 or (top >> shift) == 0:  # a shift by 64 is undefined in LLVM
            return order


@_jit
def voxel_centroids(points, order, starts, counts, min_points):  # type: ignore[no-untyped-def]
    """Centroids of the voxels (runs ``starts``/``counts`` of ``order``) holding at least
    ``min_points`` points, each summed in run order, as ``add.reduceat`` sums it."""
    kept = 0
    for v in range(starts.shape[0]):
        if counts[v] >= min_points:
            kept += 1
    out = np.empty((kept, 3))
    row = 0
    for v in range(starts.shape[0]):
        c = counts[v]
        if c < min_points:
            continue
        s0 = starts[v]
        p = order[s0]
        sx = points[p, 0]
        sy = points[p, 1]
        sz = points[p, 2]
        for j in range(s0 + 1, s0 + c):
            p = order[j]
            sx += points[p, 0]
            sy += points[p, 1]
            sz += points[p, 2]
        out[row, 0] = sx / c
        out[row, 1] = sy / c
        out[row, 2] = sz / c
        row += 1
    return out


@_jit
def eigen_cubic(cov):  # type: ignore[no-untyped-def]
    """First part of :func:`~kentreg_ros.core.scan.normals.smallest_eigenpairs_3x3` per matrix:
    the mean eigenvalue ``m``, ``p`` and the determinant of ``A - m I`` (numpy takes the
    power and the arccos, whose numpy implementations round differently from libm's)."""
    n = cov.shape[0]
    m_out = np.empty(n)
    p_out = np.empty(n)
    det_out = np.empty(n)
    for i in range(n):
        a = cov[i, 0]
        b = cov[i, 1]
        c = cov[i, 2]
        d = cov[i, 3]
        e = cov[i, 4]
        f = cov[i, 5]
        m = (a + d + f) / 3.0
        a1 = a - m
        d1 = d - m
        f1 = f - m
        p2 = (a1 * a1 + d1 * d1 + f1 * f1 + 2.0 * (b * b + c * c + e * e)) / 6.0
        m_out[i] = m
        p_out[i] = np.sqrt(p2)
        det_out[i] = a1 * (d1 * f1 - e * e) - b * (b * f1 - e * c) + c * (b * e - d1 * c)
    return m_out, p_out, det_out


@_jit
def eigen_vectors(cov, m, p, cos_max, cos_min, gap_ratio):  # type: ignore[no-untyped-def]
    """Second half: the smallest and middle eigenvalues, the eigenvector as the largest cross
    product of two rows of ``A - lambda_min I``, and which matrices need ``eigh``; the cosines
    of the cubic's angles come from numpy, so only IEEE-exact operations remain here."""
    n = cov.shape[0]
    evals = np.empty(n)
    mid = np.empty(n)
    vecs = np.empty((n, 3))
    hard = np.empty(n, dtype=np.bool_)
    for i in range(n):
        a = cov[i, 0]
        b = cov[i, 1]
        c = cov[i, 2]
        d = cov[i, 3]
        e = cov[i, 4]
        f = cov[i, 5]
        l_max = m[i] + 2.0 * p[i] * cos_max[i]
        l_min = m[i] + 2.0 * p[i] * cos_min[i]
        l_mid = 3.0 * m[i] - l_max - l_min
        r00 = a - l_min
        r11 = d - l_min
        r22 = f - l_min
        # cross(r0, r1), cross(r0, r2), cross(r1, r2) with r0 = (r00, b, c), r1 = (b, r11, e),
        # r2 = (c, e, r22), as cross_rows computes them.
        x0 = b * e - c * r11
        y0 = c * b - r00 * e
        z0 = r00 * r11 - b * b
        x1 = b * r22 - c * e
        y1 = c * c - r00 * r22
        z1 = r00 * e - b * c
        x2 = r11 * r22 - e * e
        y2 = e * c - b * r22
        z2 = b * e - r11 * c
        n0 = (x0 * x0 + z0 * z0) + y0 * y0  # einsum's order of the three terms
        n1 = (x1 * x1 + z1 * z1) + y1 * y1
        n2 = (x2 * x2 + z2 * z2) + y2 * y2
        if n0 >= n1 and n0 >= n2:
            vx, vy, vz, nn = x0, y0, z0, n0
        elif n1 >= n2:
            vx, vy, vz, nn = x1, y1, z1, n1
        else:
            vx, vy, vz, nn = x2, y2, z2, n2
        norm = np.sqrt(nn)
        scale = max(abs(l_max), abs(l_min))
        h = p[i] <= 0.0 or l_mid - l_min <= gap_ratio * scale or not norm > 0.0
        div = 1.0 if h else norm
        vecs[i, 0] = vx / div
        vecs[i, 1] = vy / div
        vecs[i, 2] = vz / div
        evals[i] = l_min
        mid[i] = l_mid
        hard[i] = h
    return evals, vecs, mid, hard


@_jit
def matched_rows(idx, n_target):  # type: ignore[no-untyped-def]
    """Indices of the rows whose correspondence exists (``idx < n_target``), in order."""
    count = 0
    for i in range(idx.shape[0]):
        if idx[i] < n_target:
            count += 1
    ok = np.empty(count, dtype=np.intp)
    k = 0
    for i in range(idx.shape[0]):
        if idx[i] < n_target:
            ok[k] = i
            k += 1
    return ok


@_jit
def plane_residuals(x, idx, n_target, target, target_normals, source_normals, R):  # type: ignore[no-untyped-def]
    """For the refinement's Gauss-Newton step: the source points with a correspondence
    (``idx < n_target``), their point-to-plane residuals ``n_q . (q - x)`` and the cosines
    between the target normal and the rotated source normal ``n_q . R n_p``."""
    ok = matched_rows(idx, n_target)
    r = np.empty(ok.shape[0])
    cos = np.empty(ok.shape[0])
    for k in range(ok.shape[0]):
        i = ok[k]
        q = idx[i]
        nx = target_normals[q, 0]
        ny = target_normals[q, 1]
        nz = target_normals[q, 2]
        r[k] = (
            nx * (target[q, 0] - x[i, 0])
            + ny * (target[q, 1] - x[i, 1])
            + nz * (target[q, 2] - x[i, 2])
        )
        px = source_normals[i, 0]
        py = source_normals[i, 1]
        pz = source_normals[i, 2]
        rx = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz
        ry = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz
        rz = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz
        cos[k] = nx * rx + ny * ry + nz * rz
    return ok, r, cos


@_jit
def plane_normal_equations(x, idx, ok, target_normals, r, w):  # type: ignore[no-untyped-def]
    """``H = sum w J^T J`` (6, 6), ``g = sum w J^T r`` (6,), ``sum w r^2`` and ``sum w`` of the
    point-to-plane rows ``J = [n_q x x, -n_q]`` (left perturbation ``(omega, v)``)."""
    H = np.zeros((6, 6))
    g = np.zeros(6)
    wrr = 0.0
    wsum = 0.0
    J = np.empty(6)
    for k in range(ok.shape[0]):
        i = ok[k]
        q = idx[i]
        nx = target_normals[q, 0]
        ny = target_normals[q, 1]
        nz = target_normals[q, 2]
        J[0] = ny * x[i, 2] - nz * x[i, 1]
        J[1] = nz * x[i, 0] - nx * x[i, 2]
        J[2] = nx * x[i, 1] - ny * x[i, 0]
        J[3] = -nx
        J[4] = -ny
        J[5] = -nz
        wk = w[k]
        for a in range(6):
            wa = wk * J[a]
            g[a] += wa * r[k]
            for b in range(a, 6):
                H[a, b] += wa * J[b]
        wrr += wk * r[k] * r[k]
        wsum += wk
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]
    return H, g, wrr, wsum


@_jit
def offset_residuals(x, idx, n_target, target, target_normals):  # type: ignore[no-untyped-def]
    """For the translation stage: the rows with a correspondence and their signed offsets
    from the target planes, ``n_q . (x - q)``."""
    ok = matched_rows(idx, n_target)
    r = np.empty(ok.shape[0])
    for k in range(ok.shape[0]):
        i = ok[k]
        q = idx[i]
        r[k] = (
            target_normals[q, 0] * (x[i, 0] - target[q, 0])
            + target_normals[q, 1] * (x[i, 1] - target[q, 1])
            + target_normals[q, 2] * (x[i, 2] - target[q, 2])
        )
    return ok, r


@_jit
def offset_normal_equations(idx, ok, target_normals, r, w):  # type: ignore[no-untyped-def]
    """``H = sum w n n^T`` (3, 3), ``g = sum w n r`` (3,), ``sum w r^2`` and ``sum w``."""
    H = np.zeros((3, 3))
    g = np.zeros(3)
    wrr = 0.0
    wsum = 0.0
    for k in range(ok.shape[0]):
        q = idx[ok[k]]
        wk = w[k]
        for a in range(3):
            wa = wk * target_normals[q, a]
            g[a] += wa * r[k]
            for b in range(a, 3):
                H[a, b] += wa * target_normals[q, b]
        wrr += wk * r[k] * r[k]
        wsum += wk
    for a in range(3):
        for b in range(a):
            H[a, b] = H[b, a]
    return H, g, wrr, wsum


@_jit
def bin_moments(normals, order, starts):  # type: ignore[no-untyped-def]
    """Per run ``starts`` of ``order``: the sum of the normals (B, 3) and of their outer
    products (B, 9, row-major), each summed in run order (``add.reduceat`` vectorises its
    loop: the sums agree to rounding, ~1e-14)."""
    n_bins = starts.shape[0]
    n = order.shape[0]
    sums = np.empty((n_bins, 3))
    scatters = np.empty((n_bins, 9))
    for b in range(n_bins):
        s0 = starts[b]
        s1 = starts[b + 1] if b + 1 < n_bins else n
        p = order[s0]
        for a in range(3):
            sums[b, a] = normals[p, a]
            for c in range(3):
                scatters[b, 3 * a + c] = normals[p, a] * normals[p, c]
        for j in range(s0 + 1, s1):
            p = order[j]
            for a in range(3):
                sums[b, a] += normals[p, a]
                for c in range(3):
                    scatters[b, 3 * a + c] += normals[p, a] * normals[p, c]
    return sums, scatters


# The EM's, the local map's and the k-d tree's kernels live in their own modules; the package
# reaches every kernel through this one.
from kentreg_ros.core.kernels._jit_em import (  # noqa: E402, F401
    bin_group_moments,
    e_logits,
    e_moments,
    e_totals,
    kent_finish,
    kent_frames,
)
from kentreg_ros.core.kernels._jit_map import (  # noqa: E402, F401
    map_merge,
    sorted_positions,
    voxel_admission,
)
from kentreg_ros.core.kernels._jit_tree import kdtree_build, kdtree_knn  # noqa: E402, F401
