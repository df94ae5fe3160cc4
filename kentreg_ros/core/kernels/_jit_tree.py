"""A compiled k-d tree: exact k-nearest-neighbour queries (imported only through
:mod:`kentreg_ros.core.kernels`).

The tree is nanoflann's kind (as in small_gicp's ``KdTree``, which this one replaces where the
kernels are compiled): each internal node splits its points at the middle of their extent along
the axis of largest extent, leaves hold at most ``leaf`` points, and a node keeps the largest
coordinate of its left child and the smallest of its right child along the split axis, so a
query carries its squared distance to the node's region incrementally (one axis changes per
level). The points are copied into the tree's order while it is built, so a leaf's points lie
together in memory. What it is for: the local map is indexed anew every step, and this build
costs a third of small_gicp's or less on the same points (map points in voxel-key order: 26k
street 1.1 against 3.2 ms, 36k BALM 1.9 against 4.7 ms; the queries take the same time, 3-NN
and 15-NN). Squared distances are summed as small_gicp's
(Eigen's SSE reduction of a 4-vector: ``(dx² + dz²) + dy²``), so the two give the same
distances bit for bit.

A midpoint split can leave one side almost empty (points spread over orders of magnitude); a
node whose smaller side would hold less than 1/16 of its points is split at its median instead,
which bounds the depth by ``log(n) / log(16/15)`` and the build by ``O(n log n)``. The median
is found by selection (:func:`_select`), not by sorting the node: on maps of walls and floors
many nodes fall back, and the sort was half of the build (36k BALM map points 2.9 against
1.9 ms).
"""

from __future__ import annotations

import numba
import numpy as np

_jit = numba.njit(cache=True, nogil=True, fastmath=False, error_model='numpy')


@_jit
def _swap(tp, perm, i, j):  # type: ignore[no-untyped-def]
    """Swap rows ``i`` and ``j`` of ``tp`` and ``perm``."""
    perm[i], perm[j] = perm[j], perm[i]
    for a in range(3):
        tp[i, a], tp[j, a] = tp[j, a], tp[i, a]


@_jit
def _select(tp, perm, s, e, k, d):  # type: ignore[no-untyped-def]
    """Reorder rows ``[s, e)`` of ``tp`` (and ``perm`` with them) so that row ``k`` holds the
    coordinate along ``d`` a sort would put there, no row before it a larger one and no row
    after it a smaller one (Hoare's selection, Wirth's form: linear on average, where a sort
    of the rows cost half of a map's build)."""
    lo = s
    hi = e - 1
    while lo < hi:
        x = tp[k, d]
        i = lo
        j = hi
        while True:
            while tp[i, d] < x:
                i += 1
            while x < tp[j, d]:
                j -= 1
            if i <= j:
                _swap(tp, perm, i, j)
                i += 1
                j -= 1
            if i > j:
                break
        if j < k:
            lo = i
        if k < i:
            hi = j


@_jit
def _split(tp, perm, s, e):  # type: ignore[no-untyped-def]
    """Split rows ``[s, e)`` of ``tp`` (and ``perm`` with them) at the middle of their extent
    along the axis of largest extent (at the median where that is lopsided): ``(m, axis,
    left_max, right_min)``, the left side being ``[s, m)``."""
    lo0 = np.inf
    lo1 = np.inf
    lo2 = np.inf
    hi0 = -np.inf
    hi1 = -np.inf
    hi2 = -np.inf
    for i in range(s, e):
        x = tp[i, 0]
        y = tp[i, 1]
        z = tp[i, 2]
        lo0 = min(lo0, x)
        hi0 = max(hi0, x)
        lo1 = min(lo1, y)
        hi1 = max(hi1, y)
        lo2 = min(lo2, z)
        hi2 = max(hi2, z)
    d = 0
    span = hi0 - lo0
    mid = 0.5 * (lo0 + hi0)
    if hi1 - lo1 > span:
        d = 1
        span = hi1 - lo1
        mid = 0.5 * (lo1 + hi1)
    if hi2 - lo2 > span:
        d = 2
        mid = 0.5 * (lo2 + hi2)
    # Partition [s, e) into coordinates below the middle, then the others; the largest left
    # and smallest right coordinate are taken as the elements settle.
    left_max = -np.inf
    right_min = np.inf
    i = s
    j = e - 1
    while True:
        while i <= j:
            v = tp[i, d]
            if v >= mid:
                break
            left_max = max(left_max, v)
            i += 1
        while i <= j:
            v = tp[j, d]
            if v < mid:
                break
            right_min = min(right_min, v)
            j -= 1
        if i >= j:
            break
        _swap(tp, perm, i, j)
        left_max = max(left_max, tp[i, d])
        right_min = min(right_min, tp[j, d])
        i += 1
        j -= 1
    m = i
    if min(m - s, e - m) < max((e - s) // 16, 1):
        # Lopsided (or a zero extent): split at the median along the axis instead.
        m = (s + e) // 2
        _select(tp, perm, s, e, m, d)
        left_max = -np.inf
        for r in range(s, m):
            left_max = max(left_max, tp[r, d])
        right_min = np.inf
        for r in range(m, e):
            right_min = min(right_min, tp[r, d])
    return m, d, left_max, right_min


@_jit
def _grown_int(a, cap, fill):  # type: ignore[no-untyped-def]
    """``a`` copied into an integer array of ``cap`` entries, the new ones ``fill``."""
    out = np.full(cap, fill, dtype=np.intp)
    out[: a.shape[0]] = a
    return out


@_jit
def _grown_float(a, cap):  # type: ignore[no-untyped-def]
    """``a`` copied into a float array of ``cap`` entries, the new ones 0."""
    out = np.zeros(cap)
    out[: a.shape[0]] = a
    return out


@_jit
def kdtree_build(points, leaf):  # type: ignore[no-untyped-def]
    """The tree on ``points`` (N, 3): ``(perm, tree_points, child, axis, low, high, start,
    end, depth)``. ``tree_points = points[perm]``; node 0 is the root; an internal node's
    children are ``child`` and ``child + 1`` (-1 at a leaf, whose points are
    ``tree_points[start:end]``); ``low`` / ``high``: the left child's largest and the right
    child's smallest coordinate along ``axis``; ``depth``: the number of levels."""
    n = points.shape[0]
    perm = np.arange(n)
    tp = points.copy()
    # A first guess of the node count (leaves about half full); a split may leave one point on
    # a side (a node of 17-31 points may give its 1/16 away), so the arrays grow when a split
    # needs more room: numba does not check bounds, and writing past them crashed the process
    # (a trajectory that stands still, its positions clustered, as map viewpoints).
    cap = 2 * (n // max(leaf // 2, 1)) + 3
    child = np.full(cap, -1, dtype=np.intp)
    axis = np.zeros(cap, dtype=np.intp)
    low = np.zeros(cap)
    high = np.zeros(cap)
    start = np.zeros(cap, dtype=np.intp)
    end = np.zeros(cap, dtype=np.intp)
    level = np.zeros(cap, dtype=np.intp)
    stack = np.empty(64, dtype=np.intp)
    start[0] = 0
    end[0] = n
    count = 1
    depth = 1
    top = 1
    stack[0] = 0
    while top > 0:
        top -= 1
        node = stack[top]
        s = start[node]
        e = end[node]
        if e - s <= leaf:
            continue
        m, d, left_max, right_min = _split(tp, perm, s, e)
        if count + 2 > child.shape[0]:
            cap = 2 * child.shape[0]
            child = _grown_int(child, cap, -1)
            axis = _grown_int(axis, cap, 0)
            start = _grown_int(start, cap, 0)
            end = _grown_int(end, cap, 0)
            level = _grown_int(level, cap, 0)
            low = _grown_float(low, cap)
            high = _grown_float(high, cap)
        c = count
        count += 2
        child[node] = c
        axis[node] = d
        low[node] = left_max
        high[node] = right_min
        start[c] = s
        end[c] = m
        start[c + 1] = m
        end[c + 1] = e
        level[c] = level[c + 1] = level[node] + 1
        depth = max(depth, level[node] + 2)
        if top + 2 > stack.shape[0]:
            grown = np.empty(2 * stack.shape[0], dtype=np.intp)
            grown[:top] = stack[:top]
            stack = grown
        stack[top] = c
        stack[top + 1] = c + 1
        top += 2
    return (
        perm,
        tp,
        child[:count].copy(),
        axis[:count].copy(),
        low[:count].copy(),
        high[:count].copy(),
        start[:count].copy(),
        end[:count].copy(),
        depth,
    )


@_jit
def kdtree_knn(  # type: ignore[no-untyped-def]
    tp, child, axis, low, high, start, end, depth, queries, k, bound2
):
    """The ``k`` nearest tree points of every query (M, 3) with a squared distance below
    ``bound2``: squared distances (M, k) ascending (inf where fewer were found) and their rows
    of ``tp`` (-1 there). Depth-first, nearer child first; the other child is visited only if
    the query's squared distance to its region is below the k-th best so far."""
    m = queries.shape[0]
    out_d = np.full((m, k), np.inf)
    out_i = np.full((m, k), -1, dtype=np.intp)
    size = depth + 2
    s_node = np.empty(size, dtype=np.intp)
    s_dist = np.empty(size)
    s_off = np.empty((size, 3))
    best_d = np.empty(k)
    best_i = np.empty(k, dtype=np.intp)
    off = np.empty(3)
    for q in range(m):
        qx = queries[q, 0]
        qy = queries[q, 1]
        qz = queries[q, 2]
        for j in range(k):
            best_d[j] = np.inf
            best_i[j] = -1
        worst = bound2
        node = 0
        dist = 0.0
        off[0] = 0.0
        off[1] = 0.0
        off[2] = 0.0
        top = 0
        while True:
            c = child[node]
            if c < 0:
                for i in range(start[node], end[node]):
                    dx = tp[i, 0] - qx
                    dy = tp[i, 1] - qy
                    dz = tp[i, 2] - qz
                    d2 = (dx * dx + dz * dz) + dy * dy
                    if d2 < worst:
                        j = k - 1
                        while j > 0 and best_d[j - 1] > d2:
                            best_d[j] = best_d[j - 1]
                            best_i[j] = best_i[j - 1]
                            j -= 1
                        best_d[j] = d2
                        best_i[j] = i
                        worst = min(bound2, best_d[k - 1])
            else:
                a = axis[node]
                v = qx if a == 0 else (qy if a == 1 else qz)
                below = v - low[node]
                above = v - high[node]
                if below + above < 0.0:
                    near = c
                    far = c + 1
                    cut = above * above
                else:
                    near = c + 1
                    far = c
                    cut = below * below
                far_dist = dist + cut - off[a]
                if far_dist < worst:
                    s_node[top] = far
                    s_dist[top] = far_dist
                    s_off[top, 0] = off[0]
                    s_off[top, 1] = off[1]
                    s_off[top, 2] = off[2]
                    s_off[top, a] = cut
                    top += 1
                node = near
                continue
            found = False
            while top > 0:
                top -= 1
                if s_dist[top] < worst:
                    node = s_node[top]
                    dist = s_dist[top]
                    off[0] = s_off[top, 0]
                    off[1] = s_off[top, 1]
                    off[2] = s_off[top, 2]
                    found = True
                    break
            if not found:
                break
        for j in range(k):
            out_d[q, j] = best_d[j]
            out_i[q, j] = best_i[j]
    return out_d, out_i
