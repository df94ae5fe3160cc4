"""The pair-registration methods: same input, same budget, one API (``prepare``, ``register``).

Every method gets the same voxel-downsampled clouds (:func:`voxel_downsample`, voxel centroids)
and is a :class:`Method`: ``prepare(points) -> prep`` (the per-scan work an odometry caches:
normals, covariances, trees, grids, kentreg's ``prepare_scan``) and
``register(source_prep, target_prep, init) -> T_target_source``. Shared settings derive from the
voxel edge ``v``, never tuned per data set: gate ``4 v``, :data:`NORMAL_NEIGHBORS` neighbours,
iterate to each method's own convergence test (:data:`MAX_ITERATIONS` only guards: a cap of 50
measured as a handicap for point-to-point ICP and KISS-ICP on BALM's 20-29 deg pairs); CICP ends
below a tenth of the voxel; NDT and CICP use the paper's settings (benchmarks/README.md).
:func:`at_defaults` wraps a method for raw scans (kentreg: its own automatic preprocessing).
:func:`fpfh_ransac` is the one global registration (Open3D's FPFH + RANSAC, no start).
Libraries are imported inside the factories, so a missing one removes only its methods.
"""

from __future__ import annotations

import functools
import logging
import os
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core import KentRegConfig, choose_voxel_size, prepare_scan, register
from kentreg_ros.core import voxel_downsample as _core_voxel_downsample

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: Correspondence gate in voxel edges, shared by every method that gates correspondences.
GATE_VOXELS = 4.0
#: Safety cap on iterations (KISS-ICP's default); convergence tests end the methods first.
MAX_ITERATIONS = 500
#: CICP stops when its kernel width falls below this many voxel edges.
CICP_MIN_SIGMA_VOXELS = 0.1
#: Neighbours for normals / covariances (the paper's 15).
NORMAL_NEIGHBORS = 15
#: Points per scan the paper downsamples to ("about 10,000 points").
PAPER_POINTS = 10_000

#: Methods other than kentreg's ablations, in table order.
BASE_METHODS: tuple[str, ...] = ('icp_pt2pt', 'icp_pt2pl', 'cicp', 'gicp', 'ndt', 'kiss_icp',
                                 'kentreg_paper', 'kentreg_robust')  # fmt: skip

#: kentreg robust ablations: one switch of docs/method.md's "robust vs paper" table each.
ABLATIONS: dict[str, dict[str, Any]] = {
    'kent_beta': {'em.kent_beta': True},  # the paper's beta term in the E-step kernels
    'averaged': {'em.rotation': 'averaged'},
    'no_anneal': {'em.kappa_cap_start': 2000.0, 'em.kappa_cap_end': 2000.0},
    'centroid': {'translation.method': 'centroid'},
    'no_xcorr': {'translation.cross_correlation': False},
    'pl2pl': {'refine.method': 'plane_to_plane'},
    'no_normal_weight': {'refine.normal_weight': False},
    'no_refine': {'refine.method': 'none'},
    # The rotation stage alone with the paper's per-cluster EM + averaging instead of the
    # shared M-step (same likelihood, same partition): where the paper's recipe loses accuracy.
    'averaged_no_refine': {'em.rotation': 'averaged', 'refine.method': 'none'},
    # Every source point in the translation and refinement instead of the normal-space sample
    # (refine.max_cluster_points): what the sampling costs in accuracy.
    'all_points': {'refine.max_cluster_points': 0},
}

ALL_METHODS: tuple[str, ...] = BASE_METHODS + tuple(f'kentreg_robust-{a}' for a in ABLATIONS)

_ALLOWED_CPUS = tuple(sorted(os.sched_getaffinity(0)))


@dataclass(frozen=True)
class Method:
    """A pair-registration method: ``prepare(points (N, 3)) -> prep`` (the per-scan work an
    odometry caches) and ``register(source_prep, target_prep, init (4, 4)) -> T_target_source``;
    ``library`` is 'open3d', 'small_gicp', 'kiss_icp', 'kentreg' or 'baseline' (NDT, CICP here);
    ``params`` the settings, for the results JSON."""

    name: str
    library: str
    prepare: Callable[[FloatArray], Any]
    register: Callable[[Any, Any, FloatArray], FloatArray]
    params: Mapping[str, Any] = field(default_factory=dict)


#: The one downsampling every method gets: the float64 centroid (M, 3) of each occupied voxel
#: of edge ``voxel`` (origin-anchored, so downsampling the result again is a no-op).
voxel_downsample = _core_voxel_downsample


def paper_voxel(
    points: FloatArray, target_points: int = PAPER_POINTS, step: float = 0.05
) -> float:
    """Voxel edge giving about ``target_points`` points (the paper's ~10,000), rounded to
    ``step``; computed once per data set on its first scan, so every scan and method share it."""
    size = choose_voxel_size(np.asarray(points, dtype=np.float64), target_points)
    return step if size <= 0.0 else max(step, round(size / step) * step)


THREAD_ENV = ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS')
PINNED_ENV = 'KENTREG_BENCH_THREADS'


def limit_threads(threads: int) -> None:
    """Pin this process to its first ``threads`` allowed CPUs (bounding numpy/BLAS, scipy's
    ``workers=-1`` and native thread pools) and set the OpenMP/BLAS variables for libraries
    imported afterwards; Open3D and small_gicp also get the count from the factories."""
    if threads < 1:
        raise ValueError(f'Expected `threads` >= 1, got {threads}.')
    for var in THREAD_ENV:
        os.environ[var] = str(threads)
    os.sched_setaffinity(0, set(_ALLOWED_CPUS[:threads]))


def pin_threads(threads: int, argv: Sequence[str], script: str) -> None:
    """Make this process run on at most ``threads`` cores, re-executing ``script`` with ``argv``
    once so that the BLAS/OpenMP variables apply before numpy loads; the second call (marked
    by ``KENTREG_BENCH_THREADS``) only sets the CPU affinity."""
    if os.environ.get(PINNED_ENV) != str(threads):
        env = dict(os.environ) | {name: str(threads) for name in (*THREAD_ENV, PINNED_ENV)}
        sys.stdout.flush()
        sys.stderr.flush()
        os.execve(sys.executable, [sys.executable, str(script), *argv], env)
    os.sched_setaffinity(0, sorted(os.sched_getaffinity(0))[:threads])


# --------------------------------------------------------------------------------------------
# Open3D


def _open3d_methods(names: Sequence[str], voxel: float, threads: int | None) -> list[Method]:
    import open3d as o3d  # OMP_NUM_THREADS is set by make_methods (limit_threads)

    if threads is not None:
        o3d.utility.set_max_threads(threads)
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    reg, gate = o3d.pipelines.registration, GATE_VOXELS * voxel
    criteria = reg.ICPConvergenceCriteria(
        relative_fitness=1e-6, relative_rmse=1e-6, max_iteration=MAX_ITERATIONS
    )

    def prepare(points: FloatArray, normals: bool) -> Any:
        pcd = o3d.geometry.PointCloud()
        pcd.points = o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64))
        if normals:
            pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(NORMAL_NEIGHBORS))
        return pcd

    def make(name: str, estimation: Any, more: dict[str, Any]) -> Method:
        def run(source: Any, target: Any, init: FloatArray) -> FloatArray:
            result = reg.registration_icp(source, target, gate, init, estimation, criteria)
            return np.array(result.transformation, dtype=np.float64)

        params = {'max_correspondence_distance': gate, 'max_iterations': MAX_ITERATIONS,
                  'relative_fitness': 1e-6, 'relative_rmse': 1e-6,
                  'open3d': o3d.__version__}  # fmt: skip
        normals = name == 'icp_pt2pl'
        return Method(name, 'open3d', functools.partial(prepare, normals=normals), run,
                      params | more)  # fmt: skip

    variants = {
        'icp_pt2pt': (reg.TransformationEstimationPointToPoint(), {}),
        'icp_pt2pl': (reg.TransformationEstimationPointToPlane(),
                      {'normal_neighbors': NORMAL_NEIGHBORS}),
    }  # fmt: skip
    return [make(n, *variants[n]) for n in variants if n in names]


# --------------------------------------------------------------------------------------------
# small_gicp


def _small_gicp_methods(names: Sequence[str], voxel: float, threads: int | None) -> list[Method]:
    import small_gicp

    n_threads = threads or 1
    gate = GATE_VOXELS * voxel

    def prepare(points: FloatArray) -> Any:
        cloud = small_gicp.PointCloud(np.asarray(points, dtype=np.float64))
        tree = small_gicp.KdTree(cloud, num_threads=n_threads)
        small_gicp.estimate_covariances(cloud, tree, NORMAL_NEIGHBORS, n_threads)
        return cloud, tree

    def run(source: Any, target: Any, init: FloatArray) -> FloatArray:
        T = np.asarray(init, dtype=np.float64)
        result = small_gicp.align(
            target[0], source[0], target[1], init_T_target_source=T, registration_type='GICP',
            max_correspondence_distance=gate, num_threads=n_threads, max_iterations=MAX_ITERATIONS,
        )  # fmt: skip
        return np.array(result.T_target_source, dtype=np.float64)

    params = {'max_correspondence_distance': gate, 'max_iterations': MAX_ITERATIONS,
              'covariance_neighbors': NORMAL_NEIGHBORS, 'threads': n_threads,
              'convergence': 'small_gicp defaults (0.1 deg, 1 mm)'}  # fmt: skip
    return [Method('gicp', 'small_gicp', prepare, run, params)]


# --------------------------------------------------------------------------------------------
# KISS-ICP (its registration core on one target scan, not its whole odometry pipeline)


def _kiss_icp_methods(names: Sequence[str], voxel: float, threads: int | None) -> list[Method]:
    from kiss_icp.mapping import VoxelHashMap
    from kiss_icp.registration import Registration

    gate = GATE_VOXELS * voxel
    map_voxel = 2.0 * voxel
    registration = Registration(max_num_iterations=MAX_ITERATIONS, convergence_criterion=1e-4,
                                max_num_threads=threads or 0)  # fmt: skip

    def prepare(points: FloatArray) -> Any:
        pts = np.asarray(points, dtype=np.float64)
        voxel_map = VoxelHashMap(voxel_size=map_voxel, max_distance=1e6, max_points_per_voxel=20)
        voxel_map.add_points(pts)
        return pts, voxel_map

    def run(source: Any, target: Any, init: FloatArray) -> FloatArray:
        T = np.asarray(init, dtype=np.float64)
        return np.array(
            registration.align_points_to_map(source[0], target[1], T, gate, gate / 3.0)
        )

    note = ("KISS-ICP's registration (point-to-point, Geman-McClure kernel = gate / 3 as "
            'KISS-ICP sets it) against a voxel hash map of the target scan')  # fmt: skip
    params = {'max_correspondence_distance': gate, 'kernel': gate / 3.0, 'map_voxel': map_voxel,
              'max_iterations': MAX_ITERATIONS, 'convergence_criterion': 1e-4,
              'note': note}  # fmt: skip
    return [Method('kiss_icp', 'kiss_icp', prepare, run, params)]


# --------------------------------------------------------------------------------------------
# This folder's baselines (numpy/scipy)


def _baseline_methods(names: Sequence[str], voxel: float, threads: int | None) -> list[Method]:
    from benchmarks.harness.baselines import cicp, ndt

    more = {'cicp': {'min_sigma': CICP_MIN_SIGMA_VOXELS * voxel}}
    table: dict[str, tuple[Callable[..., Any], Callable[..., FloatArray], dict[str, Any]]] = {
        'ndt': (ndt.ndt_prepare, ndt.ndt_register, ndt.NDT_DEFAULTS),
        'cicp': (cicp.cicp_prepare, cicp.cicp_register, cicp.CICP_DEFAULTS),
    }
    out = []
    for name in names:
        prepare, register, defaults = table[name]
        settings = {'max_iterations': MAX_ITERATIONS, **more.get(name, {})}
        run = functools.partial(register, **settings)
        out.append(Method(name, 'baseline', prepare, run, {**defaults, **settings}))
    return out


# --------------------------------------------------------------------------------------------
# kentreg


def kentreg_config(name: str, voxel: float) -> KentRegConfig:
    """The :class:`KentRegConfig` of a kentreg method name at voxel edge ``voxel``."""
    if name == 'kentreg_paper':
        return KentRegConfig.paper().with_updates({'preprocess.voxel_size': voxel})
    base, _, ablation = name.partition('-')
    if base != 'kentreg_robust' or (ablation and ablation not in ABLATIONS):
        raise ValueError(f'Unknown kentreg method {name!r}.')
    gate = GATE_VOXELS * voxel
    updates: dict[str, Any] = {'preprocess.voxel_size': voxel,
                               'translation.max_correspondence_distance': gate,
                               'refine.max_correspondence_distance': gate,
                               'refine.max_iterations': MAX_ITERATIONS}  # fmt: skip
    return KentRegConfig().with_updates(updates | ABLATIONS.get(ablation, {}))


def _kentreg_register(
    source: Any, target: Any, init: FloatArray | None, config: KentRegConfig
) -> tuple[FloatArray, Any]:
    result = register(source, target, init=init, config=config)
    return np.array(result.T_target_source, dtype=np.float64), result


def _kentreg_methods(names: Sequence[str], voxel: float, threads: int | None) -> list[Method]:
    out, defaults = [], KentRegConfig().to_flat_dict()
    for name in (n for n in names if n.startswith('kentreg')):
        cfg = kentreg_config(name, voxel)

        def run(source: Any, target: Any, init: FloatArray, cfg: KentRegConfig = cfg) -> Any:
            return _kentreg_register(source, target, init, cfg)[0]

        changed = {k: v for k, v in cfg.to_flat_dict().items() if defaults.get(k) != v}
        prepare = functools.partial(prepare_scan, config=cfg)
        out.append(Method(name, 'kentreg', prepare, run, {'config_changes': changed}))
    return out


_FACTORIES: tuple[tuple[str, tuple[str, ...], Callable[..., list[Method]]], ...] = (
    ('open3d', ('icp_pt2pt', 'icp_pt2pl'), _open3d_methods),
    ('small_gicp', ('gicp',), _small_gicp_methods),
    ('kiss_icp', ('kiss_icp',), _kiss_icp_methods),
    ('baseline', ('ndt', 'cicp'), _baseline_methods),
    ('kentreg', tuple(n for n in ALL_METHODS if n.startswith('kentreg')), _kentreg_methods),
)


def make_methods(
    names: Sequence[str] | None = None, *, voxel: float, threads: int | None = 1
) -> list[Method]:
    """The methods ``names`` (default :data:`ALL_METHODS`) in that order, gates derived from
    the shared ``voxel`` (m); ``threads`` pins the process and the libraries
    (:func:`limit_threads`; None: library defaults). A method whose library cannot be imported
    is left out with a logged warning; an unknown name raises ``ValueError``."""
    wanted = list(ALL_METHODS if names is None else names)
    unknown = [n for n in wanted if n not in ALL_METHODS]
    if unknown:
        raise ValueError(f'Unknown method(s) {unknown}; valid names are {list(ALL_METHODS)}.')
    if not voxel > 0.0:
        raise ValueError(f'Expected `voxel` > 0, got {voxel!r}.')
    if threads is not None:
        limit_threads(threads)
    built: dict[str, Method] = {}
    for library, provided, factory in _FACTORIES:
        mine = [n for n in wanted if n in provided]
        if not mine:
            continue
        try:
            methods = factory(mine, voxel, threads)
        except ImportError as exc:
            logger.warning('Left out %s: %s cannot be imported (%s); see benchmarks/README.md',
                           ', '.join(mine), library, exc)  # fmt: skip
            continue
        built.update({m.name: m for m in methods})
    return [built[n] for n in wanted if n in built]


@dataclass
class RawMethod:
    """A method as a user runs it: ``prepare(raw points (N, 3)) -> prep`` (its own
    preprocessing), ``register(source_prep, target_prep, init or None) -> (T_target_source,
    info)`` (info: what it reports, e.g. kentreg's status), ``voxel(prep)`` (the voxel edge it
    used) and ``params`` (settings, for the JSON)."""

    name: str
    prepare: Callable[[FloatArray], Any]
    register: Callable[[Any, Any, FloatArray | None], tuple[FloatArray, dict[str, Any]]]
    voxel: Callable[[Any], float]
    params: dict[str, Any] = field(default_factory=dict)


def kentreg_at_defaults() -> RawMethod:
    """kentreg with ``KentRegConfig()`` on raw scans (its automatic preprocessing)."""
    cfg = KentRegConfig()

    def run(source: Any, target: Any, init: FloatArray | None) -> tuple[FloatArray, dict]:
        T, result = _kentreg_register(source, target, init, cfg)
        return T, {'status': result.status, 'fit': result.fit, 'ambiguous': result.ambiguous}

    params = {'config': 'KentRegConfig() defaults', 'mode': cfg.mode,
              'preprocess.voxel_size': cfg.preprocess.voxel_size,
              'preprocess.target_points': cfg.preprocess.target_points,
              'input': 'raw scans'}  # fmt: skip
    prepare = functools.partial(prepare_scan, config=cfg)
    return RawMethod('kentreg', prepare, run, lambda prep: float(prep.voxel_size), params)


def at_fixed_voxel(method: Method, voxel: float, *, downsample: bool = True) -> RawMethod:
    """A registry method on the raw scan downsampled at the data set's fixed ``voxel`` (without
    ``downsample``: on points already downsampled at it)."""

    def run(source: Any, target: Any, init: FloatArray | None) -> tuple[FloatArray, dict]:
        return method.register(source, target, np.eye(4) if init is None else init), {}

    def prepare(points: FloatArray) -> Any:
        return method.prepare(voxel_downsample(points, voxel) if downsample else points)

    params = {'library': method.library, 'voxel_m': voxel, **method.params}
    return RawMethod(method.name, prepare, run, lambda prep: voxel, params)


def at_defaults(names: Sequence[str], voxel: float, threads: int) -> list[RawMethod]:
    """``kentreg`` (:func:`kentreg_at_defaults`) and registry methods at ``voxel``, in the
    order of ``names``; a method whose library is missing is left out."""
    built = make_methods([n for n in names if n != 'kentreg'], voxel=voxel, threads=threads)
    peers = {m.name: at_fixed_voxel(m, voxel) for m in built}
    return [kentreg_at_defaults() if n == 'kentreg' else peers[n] for n in names
            if n == 'kentreg' or n in peers]  # fmt: skip


# --------------------------------------------------------------------------------------------
# Global registration (no start)


#: Open3D's global registration as its tutorial sets it, in voxel edges: normals within 2 (30
#: neighbours at most), FPFH within 5 (100), RANSAC on mutual feature matches with inliers within
#: 1.5 (edge-length check 0.9), at most 100,000 iterations at confidence 0.999; then
#: point-to-plane ICP within 1 (the tutorial's 0.4 is on the full-resolution clouds).
FPFH = {'normal_radius_voxels': 2.0, 'normal_max_nn': 30, 'feature_radius_voxels': 5.0,
        'feature_max_nn': 100, 'ransac_distance_voxels': 1.5, 'edge_length': 0.9,
        'ransac_iterations': 100_000, 'ransac_confidence': 0.999,
        'icp_distance_voxels': 1.0}  # fmt: skip


def fpfh_ransac(voxel: float, *, threads: int | None = 1, seed: int = 0) -> RawMethod:
    """Open3D FPFH + RANSAC global registration, then point-to-plane ICP (:data:`FPFH`), on
    clouds downsampled at ``voxel``: no start (``init`` is ignored). Its info: the RANSAC
    ``fitness`` (0 when no hypothesis had an inlier: no answer) and the ICP's."""
    import open3d as o3d

    if threads is not None:
        o3d.utility.set_max_threads(threads)
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    o3d.utility.random.seed(seed)
    # Any: Open3D 0.20's stubs make compute_fpfh_feature's optional `indices` required.
    reg: Any = o3d.pipelines.registration
    search = o3d.geometry.KDTreeSearchParamHybrid
    f = FPFH

    def prepare(points: FloatArray) -> Any:
        pcd = o3d.geometry.PointCloud()
        pcd.points = o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64))
        down = pcd.voxel_down_sample(voxel)
        down.estimate_normals(search(f['normal_radius_voxels'] * voxel, f['normal_max_nn']))
        feature_search = search(f['feature_radius_voxels'] * voxel, f['feature_max_nn'])
        return down, reg.compute_fpfh_feature(down, feature_search)

    def run(source: Any, target: Any, init: FloatArray | None) -> tuple[FloatArray, dict]:
        distance = f['ransac_distance_voxels'] * voxel
        checkers = [reg.CorrespondenceCheckerBasedOnEdgeLength(f['edge_length']),
                    reg.CorrespondenceCheckerBasedOnDistance(distance)]  # fmt: skip
        criteria = reg.RANSACConvergenceCriteria(f['ransac_iterations'], f['ransac_confidence'])
        found = reg.registration_ransac_based_on_feature_matching(
            source[0], target[0], source[1], target[1], True, distance,
            reg.TransformationEstimationPointToPoint(False), 3, checkers, criteria,
        )  # fmt: skip
        refined = reg.registration_icp(
            source[0], target[0], f['icp_distance_voxels'] * voxel, found.transformation,
            reg.TransformationEstimationPointToPlane(),
        )  # fmt: skip
        T = np.array(refined.transformation, dtype=np.float64)
        return T, {'fitness': float(found.fitness), 'icp_fitness': float(refined.fitness)}

    params = {'library': 'open3d', 'open3d': o3d.__version__, 'voxel_m': voxel, 'seed': seed,
              **FPFH}  # fmt: skip
    return RawMethod('fpfh_ransac', prepare, run, lambda prep: voxel, params)
