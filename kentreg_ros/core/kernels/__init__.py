"""The per-point loops, compiled when numba is installed (the ``fast`` extra), numpy otherwise:
the one place that chooses (callers call the functions here, whichever runs).

Preparing a scan runs a few passes over every point and its 15 neighbours (the neighbourhood
covariances of the normals, the normals' agreement with their neighbourhood) and the spherical
k-means of the normals; registering it, a few Gauss-Newton passes over the sampled points and,
in every EM pass, Kent's moment estimates of a handful of clusters (numpy's ~25 calls on
(K, 3, 3) arrays cost ten times their arithmetic); the local map, the averaging of each scan
into it. In numpy each pass is a chain of whole-array operations whose temporaries (or, on a
handful of clusters, whose calls) cost more than the arithmetic; a compiled loop does the same
operations in one pass. ``benchmarks/per_scan.py`` measures what it pays. Without numba (or
with ``KENTREG_NO_JIT=1`` in the environment) the numpy code runs; both give the same results
(the kernels repeat numpy's operations in numpy's order, except three sums taken in another
order: the Gauss-Newton normal equations and the EM's per-cluster sums of bins, which numpy
takes as BLAS matrix products, and the moments of the normal bins, ``add.reduceat``'s). With the
previous scan the poses agree to ~1e-14; with the local map such differences feed the map and
its clustering, and over 50 scans the poses drifted apart by up to ~1 mm (BALM and the street
frames, 2026-12-06; already so before the EM's sums were compiled), far below the odometry's
error (``test/core/test_kernels.py``). One kernel has no numpy twin: the k-d tree
(:func:`kdtree_build`, :func:`kdtree_knn`), which
:class:`~kentreg_ros.core.scan.neighbors.NeighborIndex` uses when the kernels are compiled and
replaces by small_gicp's or scipy's tree otherwise (exact kNN all three, the same distances).

numba is imported, and every kernel compiled (cached on disk after the first run: 11 s the first
time on this 2-core VM, 6 s before the k-d tree's kernels; 0.6 s after, from the cache), at the
first use, not when :mod:`kentreg_ros.core` is imported; :func:`warm_up`
does it ahead of time (:class:`~kentreg_ros.core.odometry.loop.Odometry` calls it). If numba is
installed but cannot compile or cache them (e.g. an unsupported platform, or no writable cache
directory), one warning is logged and the numpy code runs.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import threading
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core.kernels import _numpy

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: Environment variable that disables the compiled kernels (any value but '' or '0').
DISABLE_ENV = 'KENTREG_NO_JIT'

_module: ModuleType | None = None
_loaded: bool | None = None  # None: not tried yet; then whether the kernels compiled
_compiling = False  # True while _load runs every kernel once (numba compiles at the first call)
_lock = threading.Lock()


def enabled() -> bool:
    """Whether the compiled kernels are used: numba is installed, neither ``KENTREG_NO_JIT``
    nor numba's own ``NUMBA_DISABLE_JIT`` is set, and the kernels compiled (tried once, at the
    first call)."""
    if os.environ.get(DISABLE_ENV, '') not in ('', '0'):
        return False
    if os.environ.get('NUMBA_DISABLE_JIT', '') not in ('', '0'):
        return False  # numba would run the loops as Python: far slower than numpy
    if _loaded is None:
        _load()
    return bool(_loaded)


def _load() -> None:
    global _module, _loaded, _compiling
    with _lock:
        if _loaded is not None:
            return
        if importlib.util.find_spec('numba') is None:
            _loaded = False
            return
        try:
            from kentreg_ros.core.kernels import _jit as module

            _module = module
            _compiling = True
            _compile_all()
        except Exception as exc:  # numba raises several types; any means: use numpy
            _module = None
            _loaded = False
            logger.warning(
                'numba is installed but the compiled kernels are unavailable (%s: %s); using '
                'numpy (same results, slower).',
                type(exc).__name__,
                exc,
            )
            return
        finally:
            _compiling = False
        _loaded = True


def _use_compiled() -> bool:
    return _compiling or enabled()


def _compiled() -> ModuleType:
    if _module is None:
        raise RuntimeError('The compiled kernels are not loaded; check kernels.enabled() first.')
    return _module


def _run(name: str, *args: Any) -> Any:
    """Kernel ``name``: compiled (every array contiguous in the dtype the kernels are compiled
    for, integer arrays as ``intp``, all others as float64; scalars as they are) when
    :func:`enabled`, else its numpy twin in :mod:`._numpy` on the arguments as given."""
    if not _use_compiled():
        return getattr(_numpy, name)(*args)
    converted = [
        (
            np.ascontiguousarray(a, dtype=np.intp if a.dtype.kind in 'iu' else np.float64)
            if isinstance(a, np.ndarray)
            else a
        )
        for a in args
    ]
    return getattr(_compiled(), name)(*converted)


def neighbourhood_covariances(centred: FloatArray, neighbors: NDArray[np.intp]) -> FloatArray:
    """``(xx, xy, xz, yy, yz, zz)`` of each neighbourhood of the centred points (M, 6)."""
    out: FloatArray = _run('neighbourhood_covariances', centred, neighbors)
    return out


def normal_consistency(normals: FloatArray, neighbors: NDArray[np.intp]) -> FloatArray:
    """Cosine between each normal and the mean normal of its neighbourhood (M,)."""
    out: FloatArray = _run('normal_consistency', normals, neighbors)
    return out


def assign_and_sum(
    xs: FloatArray, weighted: FloatArray, centers: FloatArray
) -> tuple[NDArray[np.intp], FloatArray]:
    """Labels (nearest centre by cosine) and per-centre sums of ``weighted`` (3, N)."""
    labels, sums = _run('assign_and_sum', xs, weighted, centers)
    return labels, sums


def lloyd_steps(
    xs: FloatArray,
    weighted: FloatArray,
    centers: FloatArray,
    labels: NDArray[np.intp],
    iterations: int,
) -> tuple[NDArray[np.intp], FloatArray, FloatArray, NDArray[np.intp], int, int]:
    """Up to ``iterations`` Lloyd steps of spherical k-means of the unit rows of ``xs`` (N, 3)
    (``weighted``: their weighted copies, (3, N)) from ``centers`` (K, 3) and the previous
    ``labels`` (N,): ``(labels, centers, sums, new_labels, state, steps)``. ``state`` 0: the
    labels repeated (converged); 1: the iterations ran out; 2: a cluster came out empty at the
    last step, ``labels`` and ``centers`` as before it, ``sums`` and ``new_labels`` that step's
    for the caller to re-seed. ``steps``: the steps taken."""
    out = _run('lloyd_steps', xs, weighted, centers, labels, int(iterations))
    labels_, centers_, sums, new_labels, state, steps = out
    return labels_, centers_, sums, new_labels, int(state), int(steps)


def certified_distances(
    x: FloatArray,
    x0: FloatArray,
    radius: FloatArray,
    cand: NDArray[np.intp],
    target: FloatArray,
    gate: float,
) -> tuple[FloatArray, NDArray[np.intp], NDArray[np.bool_]]:
    """Nearest cached candidate of each query point (``cand`` (N, C), -1 for none): its distance
    (N,) (inf without one), its index (N,) (-1 without one) and whether the cache certifies it
    (N,)."""
    dist, nearest, valid = _run('certified_distances', x, x0, radius, cand, target, float(gate))
    return dist, nearest, valid


def cluster_moments(
    normals: FloatArray, labels: NDArray[np.intp], k: int
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per-cluster count (K,), resultant (K, 3) and scatter (K, 3, 3) of unit normals."""
    mass, xsum, scatter = _run('cluster_moments', normals, labels, int(k))
    return mass, xsum, scatter


def argsort_keys(keys: NDArray[np.int64]) -> NDArray[np.intp]:
    """``np.argsort(keys, kind='stable')`` of non-negative integer keys (N,), as a radix sort
    over 16-bit digits."""
    out: NDArray[np.intp] = _run('argsort_keys', keys)
    return out


def normal_bin_keys(
    normals: FloatArray, cells: FloatArray, groups: NDArray[np.intp] | None, span: int
) -> NDArray[np.int64]:
    """The flat key of every unit normal's cell of edge ``cells`` (N,) on a cubic grid of
    ``2 span + 1`` cells a side around the unit sphere, offset by ``groups`` (N,) (normals of
    different groups never share a key) when given."""
    g = np.zeros(0, dtype=np.intp) if groups is None else np.asarray(groups)
    out: NDArray[np.int64] = _run('normal_bin_keys', normals, cells, g, int(span))
    return out


def run_starts(ordered: NDArray[np.int64]) -> tuple[NDArray[np.intp], FloatArray]:
    """Where each run of equal values of ``ordered`` (N,) starts, and its length as float64
    (none for N = 0)."""
    starts, counts = _run('run_starts', ordered)
    return starts, counts


def sorted_positions(
    haystack: NDArray[np.int64], needles: NDArray[np.int64], *, right: bool = False
) -> NDArray[np.intp]:
    """``np.searchsorted(haystack, needles, side='right' if right else 'left')`` for ascending
    ``needles`` (N,) (a merge walk when compiled: ~0.01 against ~0.13 ms for 10k needles in 22k
    keys)."""
    out: NDArray[np.intp] = _run('sorted_positions', haystack, needles, bool(right))
    return out


def voxel_admission(
    sorted_keys: NDArray[np.int64],
    voxel_keys: NDArray[np.int64],
    voxel_counts: NDArray[np.int64],
    max_points: int,
) -> _numpy.Admission:
    """New points into a voxel map: for their keys sorted ascending (N >= 1), whether each finds
    room (N,) (the first ``max_points`` of a voxel, less the points it holds), and per distinct
    key (G,): the key, its position in the map's sorted ``voxel_keys``, whether the map holds
    that voxel, and how many new points it admits."""
    keep, new_voxels, pos, present, added = _run(
        'voxel_admission', sorted_keys, voxel_keys, voxel_counts, int(max_points)
    )
    return keep, new_voxels, pos, present, added


def voxel_keys(
    points: FloatArray, voxel_size: float, corner: FloatArray, span: FloatArray
) -> NDArray[np.int64]:
    """Linear voxel index of every point in the grid of ``span`` cells from ``corner``."""
    keys: NDArray[np.int64] = _run('voxel_keys', points, float(voxel_size), corner, span)
    return keys


def voxel_centroids(
    points: FloatArray,
    order: NDArray[np.intp],
    starts: NDArray[np.intp],
    counts: NDArray[np.intp],
    min_points: int,
) -> FloatArray:
    """Centroids of the voxels of at least ``min_points`` points (runs of ``order``)."""
    out: FloatArray = _run('voxel_centroids', points, order, starts, counts, int(min_points))
    return out


def smallest_eigenpairs_3x3(
    cov: FloatArray, gap_ratio: float
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
    """Smallest eigenvalue, its unit eigenvector and the middle eigenvalue of each symmetric
    3x3 matrix ``(xx, xy, xz, yy, yz, zz)``, and the matrices whose eigenvector is not
    resolved by the closed form (see
    :func:`~kentreg_ros.core.scan.normals.smallest_eigenpairs_3x3`; compiled, the power, arccos
    and cosines between the two loops are numpy's, so are the numbers)."""
    if not _use_compiled():
        return _numpy.smallest_eigenpairs_3x3(cov, gap_ratio)
    jit = _compiled()
    c = np.ascontiguousarray(cov, dtype=np.float64)
    m, p, det = jit.eigen_cubic(c)
    safe_p = np.where(p > 0.0, p, 1.0)
    phi = np.arccos(np.clip(0.5 * det / safe_p**3, -1.0, 1.0)) / 3.0
    cos_max = np.cos(phi)
    cos_min = np.cos(phi + 2.0 * np.pi / 3.0)
    evals, vecs, mid, hard = jit.eigen_vectors(c, m, p, cos_max, cos_min, float(gap_ratio))
    return evals, vecs, mid, hard


def plane_residuals(
    x: FloatArray,
    idx: NDArray[np.intp],
    target: FloatArray,
    target_normals: FloatArray,
    source_normals: FloatArray,
    R: FloatArray,
) -> tuple[NDArray[np.intp], FloatArray, FloatArray]:
    """Rows of ``x`` with a correspondence (``idx < len(target)``), their residuals
    ``n_q . (q - x)`` and normal cosines ``n_q . R n_p``."""
    args = (x, idx, len(target), target, target_normals, source_normals, R)
    ok, r, cos = _run('plane_residuals', *args)
    return ok, r, cos


def plane_normal_equations(
    x: FloatArray,
    idx: NDArray[np.intp],
    ok: NDArray[np.intp],
    target_normals: FloatArray,
    r: FloatArray,
    w: FloatArray,
) -> tuple[FloatArray, FloatArray, float, float]:
    """Weighted point-to-plane normal equations ``H`` (6, 6), ``g`` (6,), ``sum w r^2``,
    ``sum w`` over the rows ``ok``."""
    H, g, wrr, wsum = _run('plane_normal_equations', x, idx, ok, target_normals, r, w)
    return H, g, float(wrr), float(wsum)


def offset_residuals(
    x: FloatArray, idx: NDArray[np.intp], target: FloatArray, target_normals: FloatArray
) -> tuple[NDArray[np.intp], FloatArray]:
    """Rows of ``x`` with a correspondence and their plane offsets ``n_q . (x - q)``."""
    ok, r = _run('offset_residuals', x, idx, len(target), target, target_normals)
    return ok, r


def offset_normal_equations(
    idx: NDArray[np.intp],
    ok: NDArray[np.intp],
    target_normals: FloatArray,
    r: FloatArray,
    w: FloatArray,
) -> tuple[FloatArray, FloatArray, float, float]:
    """Weighted normal equations of the plane offsets: ``H`` (3, 3), ``g`` (3,), ``sum w r^2``,
    ``sum w`` over the rows ``ok``."""
    H, g, wrr, wsum = _run('offset_normal_equations', idx, ok, target_normals, r, w)
    return H, g, float(wrr), float(wsum)


#: Points per leaf of the compiled k-d tree (:func:`kdtree_build`). Measured on a 22k-point street
#: map and a 13k-point indoor map with the registration's 3-neighbour queries, and on 12k street
#: points with the normals' 15: 16 builds 16 % faster than 8, answers 3-NN within 6 % of it
#: (faster on the street map, slower indoors) and 15-NN 8 % faster; 32 builds faster still but
#: answers the indoor map's queries 7-10 % slower.
KDTREE_LEAF = 16


def kdtree_build(points: FloatArray) -> tuple[Any, ...]:
    """The compiled k-d tree of ``points`` (N, 3) (see :mod:`._jit_tree`); only when
    :func:`enabled`: it has no numpy twin (without numba, a scan's neighbours come from
    small_gicp's or scipy's tree, exact as well)."""
    if not _use_compiled():
        raise RuntimeError('The compiled k-d tree needs the compiled kernels (numba).')
    pts = np.ascontiguousarray(points, dtype=np.float64)
    tree: tuple[Any, ...] = _compiled().kdtree_build(pts, KDTREE_LEAF)
    return tree


def kdtree_knn(
    tree: tuple[Any, ...], queries: FloatArray, k: int, bound2: float
) -> tuple[FloatArray, NDArray[np.intp]]:
    """The ``k`` nearest points of ``tree`` to every query (M, 3) with a squared distance below
    ``bound2``: squared distances (M, k) (inf where none) and indices into the points the tree
    was built on (-1 where none)."""
    perm, tp, child, axis, low, high, start, end, depth = tree
    q = np.ascontiguousarray(queries, dtype=np.float64)
    sq, rows = _compiled().kdtree_knn(
        tp, child, axis, low, high, start, end, depth, q, int(k), float(bound2)
    )
    idx: NDArray[np.intp] = np.where(rows >= 0, perm[np.maximum(rows, 0)], -1)
    return sq, idx


def warm_up() -> bool:
    """Compile (or load from the cache) every kernel now, e.g. when a node starts, so the first
    scan does not wait for it. Returns whether the kernels are used."""
    return enabled()


def bin_moments(
    normals: FloatArray, order: NDArray[np.intp], starts: NDArray[np.intp]
) -> tuple[FloatArray, FloatArray]:
    """Sums of the normals (B, 3) and of their outer products (B, 9) over each run
    ``starts`` of ``order`` (the moments of :class:`~kentreg_ros.core.scan.clusters.NormalBins`:
    one pass instead of an (N, 3, 3) temporary and two ``reduceat``)."""
    sums, scatters = _run('bin_moments', normals, order, starts)
    return sums, scatters


def map_merge(
    target: NDArray[np.intp],
    pts: FloatArray,
    nrm: FloatArray | None,
    merged: FloatArray,
    sums: FloatArray,
    normal_sums: FloatArray,
    points: FloatArray,
    normals: FloatArray,
) -> None:
    """Average ``pts`` (N, 3) and ``nrm`` (their normals, or None) into the rows ``target`` of
    a voxel map, in place (:meth:`~kentreg_ros.core.odometry.localmap.VoxelMap.insert`): the
    map's arrays are updated where they are, so they must be C-contiguous float64 (a copy
    would take the update)."""
    rows = (merged, sums, normal_sums, points, normals)
    for a in rows:
        if a.dtype != np.float64 or not a.flags.c_contiguous:
            raise ValueError('map_merge updates the map in place: C-contiguous float64 only.')
    given = np.zeros((0, 3)) if nrm is None else nrm
    _run('map_merge', target, pts, given, nrm is not None, *rows)


def kent_from_moments(
    xbar: FloatArray, scatter: FloatArray, kappa_max: float, max_beta_ratio: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Kent's moment estimates ``(kappa, beta, gamma)`` of K components from their mean vectors
    (K, 3) and mean scatters (K, 3, 3) (:func:`~kentreg_ros.core.kent.kent_from_moments` says
    what they are): the frames and the estimates compiled, the tangent rotation's ``arctan2``,
    ``hypot``, ``cos`` and ``sin`` between them numpy's, so are the numbers. Called once per EM
    pass and per clustering on a handful of components, where numpy's ~25 calls cost ten times
    the arithmetic."""
    run = _compiled() if _use_compiled() else _numpy
    if run is not _numpy:
        xbar = np.ascontiguousarray(xbar, dtype=np.float64)
        scatter = np.ascontiguousarray(scatter, dtype=np.float64)
    r1, h, diff, off = run.kent_frames(xbar, scatter)
    psi = 0.5 * np.arctan2(off, diff)
    r2 = np.hypot(diff, off)
    kappa, beta, gamma = run.kent_finish(
        r1, h, np.cos(psi), np.sin(psi), r2, scatter, float(kappa_max), float(max_beta_ratio)
    )
    return kappa, beta, gamma


def bin_group_moments(
    labels: NDArray[np.intp],
    posterior: FloatArray,
    weights: FloatArray,
    resultants: FloatArray,
    scatters: FloatArray,
    k: int,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Per group ``labels`` (N,) of normal bins: the sum of ``posterior * scatters`` (K, 9),
    and the sums of ``weights`` (K,), ``resultants`` (K, 3) and ``scatters`` (K, 9) (the EM's
    M-step: its rotation's ``B_k`` and the moments of each cluster's Kent estimate)."""
    out = _run('bin_group_moments', labels, posterior, weights, resultants, scatters, int(k))
    weighted, wsum, xsum, ssum = out
    return weighted, wsum, xsum, ssum


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
    """The EM's E-step over the clusters (the formula is in
    :func:`~kentreg_ros.core.registration.em._shared_e_step`): ``C_k`` (K, 3, 3), the
    log-likelihood, and the posterior mass of every observed bin, weighted and per normal.

    A real scan's E-step has ~6 clusters of a few hundred bins on either side: some 60k terms,
    whose ``exp`` numpy takes in ~0.05 ms, while its ~100 calls per pass (a dozen per cluster)
    cost ten times that. Compiled, the log-posteriors are written for all clusters in one pass,
    numpy takes their ``exp`` and ``log`` (its SIMD routines, as in the numpy code), and one
    more pass sums them: six calls."""
    if not _use_compiled():
        return _numpy.e_step(
            z, assign, wx, resultants, y, ym, off, log_pi, log_c, kappa, beta, gamma, log_out
        )
    jit = _compiled()
    f64 = np.float64
    z = np.ascontiguousarray(z, dtype=f64)
    assign = np.ascontiguousarray(assign, dtype=np.intp)
    off = np.ascontiguousarray(off, dtype=np.intp)
    kappa = np.ascontiguousarray(kappa, dtype=f64)
    g1 = np.ascontiguousarray(gamma[:, :, 1], dtype=f64)
    g2 = np.ascontiguousarray(gamma[:, :, 2], dtype=f64)
    yt = np.ascontiguousarray(np.asarray(y, dtype=f64).T)
    # log pi_m - log c_k of every model bin, as the numpy code adds it to the bin's row.
    offset = np.asarray(log_pi, dtype=f64) - np.repeat(np.asarray(log_c, dtype=f64), np.diff(off))
    beta = np.ascontiguousarray(beta, dtype=f64)
    seg, buf, top = jit.e_logits(z, assign, yt, off, offset, kappa, beta, g1, g2, log_out)
    np.exp(buf, out=buf)
    total = jit.e_totals(seg, buf, np.exp(log_out - top))
    Cs, loglik, tn, t_unit = jit.e_moments(
        seg,
        buf,
        total,
        np.log(total),
        top,
        assign,
        np.ascontiguousarray(wx, dtype=f64),
        np.ascontiguousarray(resultants, dtype=f64),
        np.ascontiguousarray(ym, dtype=f64),
        off,
        kappa,
        len(kappa),
    )
    return Cs, float(loglik), tn, t_unit


def _compile_all() -> None:
    """Run every kernel once on a tiny input (numba compiles at the first call)."""
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(8, 3))
    nbrs = np.tile(np.arange(4, dtype=np.intp), (8, 1))
    smallest_eigenpairs_3x3(neighbourhood_covariances(pts, nbrs), 1e-6)
    unit = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    normal_consistency(unit, nbrs)
    labels, _ = assign_and_sum(unit, np.ascontiguousarray(unit.T), unit[:2])
    lloyd_steps(unit, np.ascontiguousarray(unit.T), unit[:2], np.full(8, -1, dtype=np.intp), 3)
    certified_distances(pts, pts, np.ones(8), np.column_stack([labels, labels - 1]), pts, 1.0)
    cluster_moments(unit, labels, 2)
    bin_moments(unit, np.arange(8, dtype=np.intp), np.array([0, 3], dtype=np.intp))
    keys = voxel_keys(pts, 0.5, np.floor(pts.min(axis=0) / 0.5), np.full(3, 8.0))
    order = argsort_keys(keys)
    run_starts(keys[order])
    normal_bin_keys(unit, np.full(8, 0.1), labels, 12)
    normal_bin_keys(unit, np.full(8, 0.1), np.zeros(0, dtype=np.intp), 12)
    sorted_positions(keys[order], keys[order][::2].copy(), right=True)
    voxel_admission(keys[order], keys[order][::3].copy(), np.ones(3, dtype=np.intp), 2)
    voxel_centroids(pts, order, np.arange(8, dtype=np.intp), np.ones(8, dtype=np.intp), 1)
    ok, r, _ = plane_residuals(pts, labels, pts, unit, unit, np.eye(3))
    plane_normal_equations(pts, labels, ok, unit, r, np.ones(len(ok)))
    ok, r = offset_residuals(pts, labels, pts, unit)
    offset_normal_equations(labels, ok, unit, r, np.ones(len(ok)))
    rows = [np.ones(8), pts.copy(), unit.copy(), pts.copy(), unit.copy()]
    map_merge(labels, pts, unit, *rows)
    scatter = np.einsum('na,nb->nab', unit, unit)
    kent_from_moments(unit[:2], scatter[:2], 1e6, 0.499)
    bin_group_moments(labels, np.ones(8), np.ones(8), unit, scatter.reshape(8, 9), 2)
    gamma = np.tile(np.eye(3), (2, 1, 1))
    off = np.array([0, 3, 8], dtype=np.intp)
    for b in (0.0, 1.0):
        model = (unit, unit, off, np.zeros(8), np.zeros(2), np.ones(2), np.full(2, b), gamma)
        e_step(unit, labels, np.ones(8), unit, *model, -3.0)
    kdtree_knn(kdtree_build(pts), pts, 2, np.inf)
