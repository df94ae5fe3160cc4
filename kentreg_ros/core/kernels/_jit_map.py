"""The local map's compiled kernels (imported only through :mod:`kentreg_ros.core.kernels`):
where a scan's points find room in the voxel map, and the averaging of the others into it. The
same conventions as :mod:`._jit` (numpy's operations in numpy's order, one thread, ``nogil``).
"""

from __future__ import annotations

import numba
import numpy as np

_jit = numba.njit(cache=True, nogil=True, fastmath=False, error_model='numpy')


@_jit
def sorted_positions(haystack, needles, right):  # type: ignore[no-untyped-def]
    """``np.searchsorted(haystack, needles, side)`` for ascending ``needles``: one merge walk
    through both (linear) instead of a binary search per needle."""
    n = haystack.shape[0]
    out = np.empty(needles.shape[0], dtype=np.intp)
    p = 0
    for i in range(needles.shape[0]):
        v = needles[i]
        if right:
            while p < n and haystack[p] <= v:
                p += 1
        else:
            while p < n and haystack[p] < v:
                p += 1
        out[i] = p
    return out


@_jit
def voxel_admission(sorted_keys, voxel_keys, voxel_counts, max_points):  # type: ignore[no-untyped-def]
    """Which of the new points (keys ascending) find room in their voxel, and per distinct new
    key: the key, its position in ``voxel_keys``, whether that voxel is occupied, and the
    points it admits; one merge walk through the new and the occupied keys."""
    n = sorted_keys.shape[0]
    v = voxel_keys.shape[0]
    keep = np.empty(n, dtype=np.bool_)
    new_voxels = np.empty(n, dtype=np.intp)
    pos = np.empty(n, dtype=np.intp)
    present = np.empty(n, dtype=np.bool_)
    added = np.zeros(n, dtype=np.intp)
    g = -1
    p = 0
    rank = 0
    existing = 0
    for i in range(n):
        key = sorted_keys[i]
        if i == 0 or key != sorted_keys[i - 1]:
            g += 1
            while p < v and voxel_keys[p] < key:
                p += 1
            new_voxels[g] = key
            pos[g] = p
            present[g] = p < v and voxel_keys[p] == key
            existing = voxel_counts[p] if present[g] else 0
            rank = 0
        keep[i] = rank + existing < max_points
        if keep[i]:
            added[g] += 1
        rank += 1
    g += 1
    return keep, new_voxels[:g].copy(), pos[:g].copy(), present[:g].copy(), added[:g].copy()


@_jit
def map_merge(target, pts, nrm, has_normals, merged, sums, normal_sums, points, normals):  # type: ignore[no-untyped-def]
    """In place, as the numpy twin: each map row's additions summed from zero in input order
    (``bincount``), then added to its sums; a normal's sign test by numpy's three-term
    ``einsum`` order, its norm by ``linalg.norm``'s, ``(x x + y y) + z z``."""
    n = points.shape[0]
    count = np.zeros(n, dtype=np.intp)
    acc = np.zeros((n, 3))
    nacc = np.zeros((n, 3))
    for i in range(target.shape[0]):
        t = target[i]
        count[t] += 1
        for a in range(3):
            acc[t, a] += pts[i, a]
        if has_normals:
            dot = (normals[t, 0] * nrm[i, 0] + normals[t, 2] * nrm[i, 2]) + (
                normals[t, 1] * nrm[i, 1]
            )
            for a in range(3):
                nacc[t, a] += nrm[i, a] if dot >= 0.0 else -nrm[i, a]
    for t in range(n):
        if count[t] == 0:
            continue
        merged[t] += count[t]
        for a in range(3):
            sums[t, a] += acc[t, a]
        for a in range(3):
            points[t, a] = sums[t, a] / merged[t]
        if has_normals:
            for a in range(3):
                normal_sums[t, a] += nacc[t, a]
            s0, s1, s2 = normal_sums[t, 0], normal_sums[t, 1], normal_sums[t, 2]
            norm = np.sqrt((s0 * s0 + s1 * s1) + s2 * s2)
            for a in range(3):
                normals[t, a] = normal_sums[t, a] / norm
