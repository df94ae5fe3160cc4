"""numba-compiled loops of the EM (Kent's moment estimates, the M-step's sums of bins, the
E-step's passes), behind :mod:`kentreg_ros.core.kernels` through :mod:`._jit`, under the same
rules (see :mod:`._jit`: numpy's operations in numpy's order, no fast-math; the E-step's ``exp``
and ``log`` and the estimates' trigonometry stay in numpy)."""

from __future__ import annotations

import numba
import numpy as np

_jit = numba.njit(cache=True, nogil=True, fastmath=False, error_model='numpy')


@_jit
def kent_frames(xbar, scatter):  # type: ignore[no-untyped-def]
    """Kent's frame ``H`` of each mean direction and the tangent block of ``H^T S H``, as the
    numpy twin (its norm ``(x x + y y) + z z``; ``hypot`` is the C library's in both; the
    ``einsum`` summed over ``i`` then ``j``, each term ``(h S) h``)."""
    k = xbar.shape[0]
    r1 = np.empty(k)
    h = np.empty((k, 3, 3))
    diff = np.empty(k)
    off = np.empty(k)
    for c in range(k):
        x0, x1, x2 = xbar[c, 0], xbar[c, 1], xbar[c, 2]
        r = np.sqrt((x0 * x0 + x1 * x1) + x2 * x2)
        r1[c] = r
        if r > 0.0:
            m0, m1, m2 = x0 / r, x1 / r, x2 / r
        else:
            m0, m1, m2 = 1.0, 0.0, 0.0
        s = np.hypot(m1, m2)
        if s > 0.0:
            cp, sp = m1 / s, m2 / s
        else:
            cp, sp = 1.0, 0.0
        h[c, 0, 0], h[c, 0, 1], h[c, 0, 2] = m0, -s, 0.0
        h[c, 1, 0], h[c, 1, 1], h[c, 1, 2] = s * cp, m0 * cp, -sp
        h[c, 2, 0], h[c, 2, 1], h[c, 2, 2] = s * sp, m0 * sp, cp
        b11 = 0.0
        b22 = 0.0
        b12 = 0.0
        for i in range(3):
            for j in range(3):
                sij = scatter[c, i, j]
                b11 += h[c, i, 1] * sij * h[c, j, 1]
                b22 += h[c, i, 2] * sij * h[c, j, 2]
                b12 += h[c, i, 1] * sij * h[c, j, 2]
        diff[c] = b11 - b22
        off[c] = 2.0 * b12
    return r1, h, diff, off


@_jit
def kent_finish(r1, h, cos_psi, sin_psi, r2, scatter, kappa_max, max_beta_ratio):  # type: ignore[no-untyped-def]
    """Kent's axes and moment estimates from the frames and the tangent rotation, as the numpy
    twin (the trace ``(S00 + S11) + S22``; ``np.minimum``/``np.maximum`` for its NaN rules)."""
    k = r1.shape[0]
    gamma = np.empty((k, 3, 3))
    kappa = np.empty(k)
    beta = np.empty(k)
    tiny = 64.0 * np.finfo(np.float64).eps
    for c in range(k):
        cps, sps = cos_psi[c], sin_psi[c]
        for a in range(3):
            gamma[c, a, 0] = h[c, a, 0]
            gamma[c, a, 1] = cps * h[c, a, 1] + sps * h[c, a, 2]
            gamma[c, a, 2] = -sps * h[c, a, 1] + cps * h[c, a, 2]
        trace = (scatter[c, 0, 0] + scatter[c, 1, 1]) + scatter[c, 2, 2]
        omr = np.maximum(trace - r1[c] * r1[c], 0.0) / (1.0 + r1[c])
        d_minus = np.maximum(2.0 * omr - r2[c], 0.5 / kappa_max)
        d_plus = np.maximum(2.0 * omr + r2[c], 0.5 / kappa_max)
        kap = np.minimum(1.0 / d_minus + 1.0 / d_plus, kappa_max)
        ratio = r2[c] / (4.0 * omr) if omr > tiny else 0.0
        kappa[c] = kap
        beta[c] = np.minimum(ratio, max_beta_ratio) * kap
    return kappa, beta, gamma


@_jit
def bin_group_moments(labels, posterior, weights, resultants, scatters, k):  # type: ignore[no-untyped-def]
    """Per group of bins: the posterior-weighted scatter sum (K, 9), and the weight, resultant
    (K, 3) and scatter (K, 9) sums, in row order (the numpy twin's matrix products are BLAS's,
    summed in its order: the sums agree to rounding)."""
    weighted = np.zeros((k, 9))
    wsum = np.zeros(k)
    xsum = np.zeros((k, 3))
    ssum = np.zeros((k, 9))
    for i in range(labels.shape[0]):
        j = labels[i]
        t = posterior[i]
        wsum[j] += weights[i]
        for a in range(3):
            xsum[j, a] += resultants[i, a]
        for a in range(9):
            weighted[j, a] += t * scatters[i, a]
            ssum[j, a] += scatters[i, a]
    return weighted, wsum, xsum, ssum


@_jit
def e_logits(z, assign, yt, off, offset, kappa, beta, g1, g2, log_out):  # type: ignore[no-untyped-def]
    """The E-step's log-posteriors of every observed bin over the model bins of its cluster,
    less their maximum (at least ``log_out``), in one flat array: bin ``n``'s run is
    ``seg[n]:seg[n + 1]`` (empty when its cluster has no model bins). ``yt`` (3, M) are the
    model directions by coordinate and ``offset`` (M,) each model bin's ``log pi_m - log c_k``.
    The products are summed as ``(y0 z0 + y1 z1) + y2 z2`` (BLAS may fuse them: rounding), then
    the numpy twin's in-place steps in its order."""
    n = z.shape[0]
    seg = np.zeros(n + 1, dtype=np.intp)
    for i in range(n):
        j = assign[i]
        seg[i + 1] = seg[i] + (off[j + 1] - off[j])
    buf = np.empty(seg[n])
    top = np.full(n, log_out)
    y0, y1, y2 = yt[0], yt[1], yt[2]
    for i in range(n):
        j = assign[i]
        m0, m1 = off[j], off[j + 1]
        if m1 == m0:
            continue
        z0, z1, z2 = z[i, 0], z[i, 1], z[i, 2]
        kj = kappa[j]
        bj = beta[j]
        row = buf[seg[i] : seg[i + 1]]
        best = -np.inf
        if bj > 0.0:
            a = (z0 * g1[j, 0] + z1 * g1[j, 1]) + z2 * g1[j, 2]
            b = (z0 * g2[j, 0] + z1 * g2[j, 1]) + z2 * g2[j, 2]
            extra = bj * (a * a - b * b)
            for m in range(m0, m1):
                v = ((y0[m] * z0 + y1[m] * z1) + y2[m] * z2) * kj + offset[m]
                v += extra
                row[m - m0] = v
                if v > best:
                    best = v
        else:
            for m in range(m0, m1):
                v = ((y0[m] * z0 + y1[m] * z1) + y2[m] * z2) * kj + offset[m]
                row[m - m0] = v
                if v > best:
                    best = v
        t = np.maximum(best, log_out)
        top[i] = t
        for q in range(m1 - m0):
            row[q] -= t
    return seg, buf, top


@_jit
def e_totals(seg, share, e_out):  # type: ignore[no-untyped-def]
    """Per observed bin, the sum of its run of ``share`` (in run order, as numpy sums an
    array's first axis) plus its outlier term."""
    n = seg.shape[0] - 1
    total = np.empty(n)
    for i in range(n):
        s = 0.0
        for q in range(seg[i], seg[i + 1]):
            s += share[q]
        total[i] = s + e_out[i]
    return total


@_jit
def e_moments(seg, share, total, log_total, top, assign, wx, resultants, ym, off, kappa, k):  # type: ignore[no-untyped-def]
    """The E-step's sums from the posteriors: ``C_k`` (K, 3, 3), the log-likelihood and the
    posterior mass of every observed bin, weighted and per normal (bins of a cluster without
    model bins get none); summed bin by bin (numpy's matrix products sum in BLAS's order)."""
    n = seg.shape[0] - 1
    Cs = np.zeros((k, 3, 3))
    per_cluster = np.zeros(k)
    tn = np.zeros(n)
    t_unit = np.zeros(n)
    for i in range(n):
        if seg[i + 1] == seg[i]:
            continue
        j = assign[i]
        w = wx[i]
        per_cluster[j] += w * (top[i] + log_total[i])
        t = 0.0
        v0 = 0.0
        v1 = 0.0
        v2 = 0.0
        m = off[j]
        tot = total[i]
        for q in range(seg[i], seg[i + 1]):
            s = share[q] / tot
            t += s
            v0 += s * ym[m, 0]
            v1 += s * ym[m, 1]
            v2 += s * ym[m, 2]
            m += 1
        tn[i] = t * w
        t_unit[i] = t
        for a in range(3):
            r = resultants[i, a]
            Cs[j, a, 0] += r * v0
            Cs[j, a, 1] += r * v1
            Cs[j, a, 2] += r * v2
    loglik = 0.0
    for j in range(k):
        loglik += per_cluster[j]
        for a in range(3):
            for b in range(3):
                Cs[j, a, b] *= kappa[j]
    return Cs, loglik, tn, t_unit
