"""Robustness benchmark: kentreg at its defaults against GICP, point-to-plane ICP and KISS-ICP.

Three stress tests on the 50 real BALM scans (``../shared/data/balm``, or the repository's
``bags/balm_50`` when the shared data are absent), every method at the settings a user gets:

``kentreg``
    ``KentRegConfig()`` as is: :class:`~kentreg_ros.core.odometry.loop.Odometry` for the strides
    (run by :func:`kentreg_ros.eval.run_odometry`, i.e. what ``kentreg_replay --stride N``
    does) and ``register(source_raw, target_raw, init=...)`` for the pairs, on the *raw* scans,
    with its own automatic preprocessing (voxel size chosen per scan for
    ``preprocess.target_points``, normals, normal-outlier test). The pairs call
    :func:`~kentreg_ros.core.prepare_scan` on both raw scans and then ``register`` on the
    prepared scans, which is what ``register`` does with raw arrays, split so that the voxel
    it chose can be reported.
``gicp``, ``icp_pt2pl``, ``kiss_icp`` (and any other name of ``benchmarks/methods.py``)
    The benchmark registry's methods: the raw scan voxel-downsampled (centroids) at the one
    voxel of the data set (the edge giving about 10,000 points on the first scan: 0.25 m on
    BALM), then the method's own preparation and registration with the registry's shared
    settings (gate 4 voxels, 15 neighbours, iterate to convergence). ``kiss_icp`` is KISS-ICP's
    registration core against a voxel map of the target scan (see ``methods.py``).

The tests:

1. **strides** — odometry over the sample taking every N-th scan (N = 1..4; stamps unchanged).
   kentreg: its ``Odometry`` (scan-to-previous-scan, constant-velocity prediction). The peers:
   scan-to-previous-scan with their registration, each started from *its own* previous
   estimate (constant velocity; identity for the first pair), poses chained. Per stride:
   failed pairs (e_R > 2 deg or e_t > 0.2 m between consecutive processed scans), median and
   max e_R and e_t, ATE rmse after SE(3) alignment (``kentreg_replay``'s own evaluation).
2. **outliers** — outliers injected into the *raw* scans, before any downsampling, as dust,
   rain or multipath returns arrive: ``K = round(N f / (1 - f))`` points for ``N`` raw points,
   so they are exactly the share ``f`` of the contaminated raw cloud (to ``0.5 / (N + K)``),
   uniform in the raw scan's bounding box (``--shell-share`` moves a share of them into the
   sensor's range shell instead), shuffled in, fresh and seeded per trial and level. Every
   method then runs at its defaults on the contaminated raw scans. Pairs are drawn from the 49
   consecutive pairs *without replacement* (seeded; the same pairs at every level) and each
   registration starts from the reference perturbed by a fixed offset: 5 deg about a seeded
   random axis and 0.2 m in a seeded random direction, so that the identity is not the
   answer. Per level and method: median and mean e_R and e_t, failures, and the ratio of the
   median e_R to the method's own outlier-free median. Uniform raw outliers are mostly alone
   in their voxel, so downsampling *raises* their share; the share among each method's
   downsampled points is measured and reported.
3. **turned** — real consecutive pairs whose source scan is turned by 30, 60, ..., 180 deg
   about a seeded random axis through the sensor origin (``T_turn`` applied to the raw source
   points, so every point moves by up to ``2 r sin(theta / 2)``; the reference becomes
   ``T_true T_turn^-1``); every method starts from the identity. Per angle and method: the
   recovered fraction (pairs not failed).

Every method runs in this one process pinned to ``--threads`` CPUs (default 1;
:func:`benchmarks.methods.limit_threads`), interleaved pair by pair, so a change in the load of
the shared machine hits every method alike. Each test records its command, commit, machine,
load and date (``common.machine_info``); ``--only`` reruns some tests and keeps the others'
results (with their own metadata) from an existing ``robustness.json`` in ``--out``.

Usage::

    nice python3 benchmarks/robustness.py            # full run -> benchmarks/results/
    python3 benchmarks/robustness.py --quick         # smoke test, a few minutes -> /tmp
    python3 benchmarks/robustness.py --only turned --methods kentreg gicp

Writes ``robustness.json``, ``robustness.md`` and ``robustness.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.common import (  # noqa: E402
    RESULTS,
    SHARED_DATA,
    errors,
    failure_mask,
    fmt,
    git_describe,
    machine_info,
    summarize,
    timed,
    write_json,
)
from benchmarks.methods import (  # noqa: E402
    ALL_METHODS,
    Method,
    limit_threads,
    make_methods,
    paper_voxel,
    voxel_downsample,
)
from kentreg_ros.eval.metrics import FAIL_ROTATION_DEG, FAIL_TRANSLATION_M  # noqa: E402

logger = logging.getLogger('robustness')

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

TESTS = ('strides', 'outliers', 'turned')
#: kentreg at its defaults plus the three peers people use today.
DEFAULT_METHODS = ('kentreg', 'gicp', 'icp_pt2pl', 'kiss_icp')
METHOD_CHOICES = ('kentreg', *ALL_METHODS)
STRIDES = (1, 2, 3, 4)
LEVELS = (0.0, 0.1, 0.2, 0.3, 0.4)
ANGLES_DEG = (30.0, 60.0, 90.0, 120.0, 150.0, 180.0)
#: Start offset of the outlier test: a few times BALM's median inter-scan motion (6.5 deg /
#: 5 cm), so a method must move to the answer, and well inside every method's basin on clean
#: pairs (all converge from the identity on BALM, up to 29 deg away, in paper_table.py).
START_OFFSET_DEG = 5.0
START_OFFSET_M = 0.2
#: Pairs per test in a full run, for a run of about 30 min on one loaded core (measured with
#: --quick: ~40 s per outlier pair over the 5 levels, the peers registering ~60k mostly-outlier
#: points at 40 % with up to 16 s per KISS-ICP pair; ~38 s per turned pair over the 6 angles,
#: failing peers iterating to the 500-iteration cap). 20 pairs resolve failure rates to 5 %.
OUTLIER_PAIRS = 20
TURNED_PAIRS = 20
#: --quick: every code path once, in a few minutes (strides over the first 25 scans).
QUICK = {'max_input_scans': 25, 'outlier_pairs': 3, 'turned_pairs': 2}
DEFAULT_DATA = SHARED_DATA / 'balm'
FALLBACK_DATA = ROOT / 'bags' / 'balm_50'


# --------------------------------------------------------------------------------------------
# Data


@dataclass
class Sample:
    """Raw scans (in memory) with one reference pose each.

    Attributes
    ----------
    scans : list of kentreg_ros.io.sources.Scan
        Every scan of the input, raw (non-finite points dropped), with its stamp.
    T_world : ndarray, shape (N, 4, 4)
        Reference ``T_world_lidar`` of every scan (rotations projected onto SO(3)).
    description : str
    ground_truth : str
        Where the reference poses come from.
    """

    scans: list[Any]
    T_world: FloatArray
    description: str
    ground_truth: str

    def raw(self, index: int) -> FloatArray:
        """The raw points of scan ``index`` as float64."""
        return np.asarray(self.scans[index].points, dtype=np.float64)

    def truth(self, target: int, source: int) -> FloatArray:
        """Reference ``T_target_source`` between two scans."""
        return np.asarray(np.linalg.inv(self.T_world[target]) @ self.T_world[source])


def load_sample(path: Path) -> Sample:
    """Every scan and its reference pose from a scan folder with a pose file, or a bag.

    The input is opened as ``kentreg_replay`` opens it
    (:func:`kentreg_ros.io.recordings.open_recording`) and the poses are associated by stamp as it
    does.

    Raises
    ------
    SystemExit
        No reference poses, or a scan without one.
    """
    from kentreg_ros.eval import GroundTruth, associate
    from kentreg_ros.io.recordings import open_recording

    source, reference, origin = open_recording(path)
    if reference is None:
        raise SystemExit(f'{path}: no reference poses (a pose file beside the scans or a bag)')
    gt = GroundTruth(reference, origin)
    scans = list(source)
    stamps = np.array([s.stamp_ns for s in scans], dtype=np.int64)
    rows, gt_rows = associate(stamps, list(range(len(scans))), gt.trajectory)
    if len(rows) != len(scans):
        raise SystemExit(f'{path}: only {len(rows)} of {len(scans)} scans have a reference pose')
    T_world = np.asarray(gt.trajectory.T_world_sensor, dtype=np.float64)[gt_rows]
    return Sample(scans, T_world, source.description, gt.origin)


def default_data() -> Path:
    """``../shared/data/balm`` when present, else the repository's ``bags/balm_50``."""
    return DEFAULT_DATA if DEFAULT_DATA.is_dir() else FALLBACK_DATA


# --------------------------------------------------------------------------------------------
# Perturbations


def inject_raw_outliers(
    points: FloatArray,
    fraction: float,
    rng: np.random.Generator,
    *,
    shell_share: float = 0.0,
) -> tuple[FloatArray, BoolArray]:
    """A raw scan with uniform outliers making up exactly ``fraction`` of the returned cloud.

    ``K = round(N f / (1 - f))`` outliers are added to the ``N`` raw points, so
    ``K / (N + K)`` equals ``f`` to within ``0.5 / (N + K)``. They are drawn uniformly in the
    raw scan's axis-aligned bounding box, except a share ``shell_share`` of them drawn in the
    sensor's range shell: directions uniform within the scan's elevation band, ranges uniform
    between its nearest and farthest return (a spurious return is as likely at any range along
    a beam, as rain or dust returns are). The cloud is shuffled, as a sensor interleaves such
    returns with the real ones; nothing is downsampled here.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Raw scan, sensor frame (sensor at the origin).
    fraction : float
        Outlier share of the returned cloud, in [0, 1).
    rng : numpy.random.Generator
        Source of every random draw (positions and the shuffle).
    shell_share : float
        Share of the outliers drawn in the range shell instead of the box, in [0, 1].

    Returns
    -------
    cloud : ndarray, shape (N + K, 3)
    is_outlier : ndarray of bool, shape (N + K,)
        True for the injected points.

    Raises
    ------
    ValueError
        ``fraction`` outside [0, 1), ``shell_share`` outside [0, 1], or an empty scan.
    """
    pts = np.asarray(points, dtype=np.float64)
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f'Expected `fraction` in [0, 1), got {fraction}.')
    if not 0.0 <= shell_share <= 1.0:
        raise ValueError(f'Expected `shell_share` in [0, 1], got {shell_share}.')
    if pts.ndim != 2 or pts.shape[1] != 3 or not len(pts):
        raise ValueError(f'Expected a non-empty (N, 3) scan, got shape {pts.shape}.')
    n = len(pts)
    k = int(round(n * fraction / (1.0 - fraction)))
    n_shell = int(round(k * shell_share))
    box = rng.uniform(pts.min(axis=0), pts.max(axis=0), size=(k - n_shell, 3))
    r = np.linalg.norm(pts, axis=1)
    seen = r > 0.0
    sin_el = pts[seen, 2] / r[seen]
    sin_lo, sin_hi = (float(sin_el.min()), float(sin_el.max())) if seen.any() else (-1.0, 1.0)
    z = rng.uniform(sin_lo, sin_hi, n_shell)  # uniform on the sphere's band between elevations
    azimuth = rng.uniform(0.0, 2.0 * np.pi, n_shell)
    ranges = rng.uniform(float(r.min()), float(r.max()), n_shell)
    horizontal = np.sqrt(np.clip(1.0 - z**2, 0.0, None))
    shell = ranges[:, None] * np.column_stack(
        [horizontal * np.cos(azimuth), horizontal * np.sin(azimuth), z]
    )
    cloud = np.concatenate([pts, box, shell])
    is_outlier = np.arange(len(cloud)) >= n
    order = rng.permutation(len(cloud))
    return cloud[order], is_outlier[order]


def outlier_voxel_share(cloud: FloatArray, is_outlier: BoolArray, voxel: float) -> float:
    """Share of the occupied voxels (edge ``voxel``, origin-anchored) holding only outliers.

    After centroid downsampling at that voxel these are the points that are pure outliers; a
    voxel shared with real points only nudges a real centroid.
    """
    if not len(cloud):
        return float('nan')
    ijk = np.floor(cloud / voxel).astype(np.int64)
    _, inverse = np.unique(ijk, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    real = np.bincount(inverse, weights=~is_outlier).astype(np.int64)
    return float(np.mean(real == 0))


def offset_transform(rng: np.random.Generator, degrees: float, metres: float) -> FloatArray:
    """A rotation of ``degrees`` about a random axis and a translation of ``metres``.

    ``T_true @ offset_transform(...)`` is a start whose errors against ``T_true`` are exactly
    ``degrees`` (e_R) and ``metres`` (e_t).
    """
    axis, direction = _unit(rng), _unit(rng)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(degrees) * axis).as_matrix()
    T[:3, 3] = metres * direction
    return T


def turn_transform(rng: np.random.Generator, degrees: float) -> FloatArray:
    """A rotation of ``degrees`` about a random axis through the origin (the sensor)."""
    return offset_transform(rng, degrees, 0.0)


def _unit(rng: np.random.Generator) -> FloatArray:
    v = rng.normal(size=3)
    return np.asarray(v / np.linalg.norm(v), dtype=np.float64)


def transform(T: FloatArray, points: FloatArray) -> FloatArray:
    """``T`` applied to ``points`` (N, 3)."""
    return np.asarray(points @ T[:3, :3].T + T[:3, 3], dtype=np.float64)


def draw_pairs(n_pairs: int, count: int, seed: int, test: int) -> list[int]:
    """``count`` distinct pair indices of ``n_pairs``, drawn without replacement (seeded)."""
    count = min(count, n_pairs)
    rng = np.random.default_rng([seed, test])
    return sorted(int(p) for p in rng.choice(n_pairs, size=count, replace=False))


# --------------------------------------------------------------------------------------------
# Methods at their defaults


@dataclass
class Runner:
    """A method as every test calls it: raw scan in, ``T_target_source`` out.

    Attributes
    ----------
    name : str
    prepare : callable
        ``prepare(raw points (N, 3)) -> prep``: the method's own preprocessing of a raw scan.
    register : callable
        ``register(source_prep, target_prep, init (4, 4)) -> (T_target_source, info)``; info
        holds what the method reports (kentreg: its status).
    voxel : callable
        ``voxel(prep) -> float``: the voxel edge the preprocessing used.
    params : dict
        Settings, for the JSON.
    """

    name: str
    prepare: Callable[[FloatArray], Any]
    register: Callable[[Any, Any, FloatArray | None], tuple[FloatArray, dict[str, Any]]]
    voxel: Callable[[Any], float]
    params: dict[str, Any] = field(default_factory=dict)


def kentreg_runner() -> Runner:
    """kentreg with ``KentRegConfig()`` on raw scans (its automatic preprocessing)."""
    from kentreg_ros.core import KentRegConfig, prepare_scan, register

    cfg = KentRegConfig()

    def prepare(points: FloatArray) -> Any:
        return prepare_scan(points, config=cfg)

    def run(
        source: Any, target: Any, init: FloatArray | None
    ) -> tuple[FloatArray, dict[str, Any]]:
        result = register(source, target, init=init, config=cfg)
        info = {'status': result.status, 'fit': result.fit, 'ambiguous': result.ambiguous}
        return np.array(result.T_target_source, dtype=np.float64), info

    return Runner(
        'kentreg',
        prepare,
        run,
        lambda prep: float(prep.voxel_size),
        {
            'config': 'KentRegConfig() defaults',
            'mode': cfg.mode,
            'preprocess.voxel_size': cfg.preprocess.voxel_size,
            'preprocess.target_points': cfg.preprocess.target_points,
            'input': 'raw scans',
        },
    )


def peer_runner(method: Method, voxel: float) -> Runner:
    """A registry method on the raw scan downsampled at the data set's fixed ``voxel``."""

    def prepare(points: FloatArray) -> Any:
        return method.prepare(voxel_downsample(points, voxel))

    def run(
        source: Any, target: Any, init: FloatArray | None
    ) -> tuple[FloatArray, dict[str, Any]]:
        return method.register(source, target, np.eye(4) if init is None else init), {}

    return Runner(
        method.name,
        prepare,
        run,
        lambda prep: voxel,
        {'library': method.library, 'voxel_m': voxel, **method.params},
    )


def make_runners(names: Sequence[str], voxel: float, threads: int) -> list[Runner]:
    """The runners of ``names`` in that order; a peer whose library is missing is left out."""
    peers = {
        m.name: m
        for m in make_methods([n for n in names if n != 'kentreg'], voxel=voxel, threads=threads)
    }
    out = []
    for name in names:
        if name == 'kentreg':
            out.append(kentreg_runner())
        elif name in peers:
            out.append(peer_runner(peers[name], voxel))
    return out


def register_pair(
    runner: Runner, source_raw: FloatArray, target_prep: Any, init: FloatArray | None
) -> dict[str, Any]:
    """Prepare the raw source, register it; errors as NaN (a failure) when the method raises.

    Returns
    -------
    dict
        ``T`` (None when the method raised), ``prep`` (the prepared source, None when its
        preparation raised), ``ms`` (source preparation + registration), the source's
        ``voxel_m`` and the method's ``info``.
    """
    src = None
    try:
        src, prep_ms = timed(runner.prepare, source_raw)
        (T, info), reg_ms = timed(runner.register, src, target_prep, init)
        return {
            'T': T,
            'prep': src,
            'ms': prep_ms + reg_ms,
            'voxel_m': runner.voxel(src),
            'info': info,
        }
    except Exception as exc:  # a method that raises fails the pair
        logger.warning('%s raised: %s', runner.name, exc)
        return _raised(exc, src)


def _raised(exc: BaseException | str, prep: Any = None) -> dict[str, Any]:
    text = exc if isinstance(exc, str) else f'{type(exc).__name__}: {exc}'
    return {
        'T': None,
        'prep': prep,
        'ms': float('nan'),
        'voxel_m': float('nan'),
        'info': {'error': text},
    }


def _summary(records: list[dict[str, Any]]) -> dict[str, Any]:
    """:func:`benchmarks.common.summarize`, with times over the pairs that ran.

    A method that raised has no time (NaN); ``summarize`` would report a NaN median as soon as
    one pair raised. Its count stays in ``n_errors`` (and in ``failures``).
    """
    summ = summarize(records)
    ms = np.array([r['ms'] for r in records], dtype=np.float64)
    ms = ms[np.isfinite(ms)]
    summ['ms'] = {
        'median': float(np.median(ms)) if len(ms) else float('nan'),
        'mean': float(ms.mean()) if len(ms) else float('nan'),
    }
    return summ


def _raised_note(summary: dict[str, Any]) -> str:
    """' (k raised)' when the method raised on some pairs, else ''."""
    return f' ({summary["n_errors"]} raised)' if summary['n_errors'] else ''


def _pair_record(rec: dict[str, Any], truth: FloatArray, **extra: Any) -> dict[str, Any]:
    e_R, e_t = (float('nan'),) * 2 if rec['T'] is None else errors(rec['T'], truth)
    return {
        **extra,
        'e_R_deg': e_R,
        'e_t_m': e_t,
        'ms': rec['ms'],
        'voxel_m': rec['voxel_m'],
        **rec['info'],
    }


# --------------------------------------------------------------------------------------------
# 1. Strides


def _motion_stats(T_world: FloatArray) -> dict[str, float]:
    rel = np.linalg.inv(T_world[:-1]) @ T_world[1:]
    angle = np.degrees(Rotation.from_matrix(rel[:, :3, :3]).magnitude())
    dist = np.linalg.norm(rel[:, :3, 3], axis=1)
    return {
        'rotation_deg_median': float(np.median(angle)),
        'rotation_deg_max': float(angle.max()),
        'translation_m_median': float(np.median(dist)),
        'translation_m_max': float(dist.max()),
    }


def _kentreg_odometry(
    scans: list[Any], stride: int
) -> tuple[FloatArray, FloatArray, dict[str, Any]]:
    from kentreg_ros.core import HEALTHS, KentRegConfig, Odometry
    from kentreg_ros.eval import run_odometry

    run = run_odometry(scans, Odometry(KentRegConfig()), stride=stride)
    if run.error is not None:
        raise RuntimeError(run.error)
    ms = np.array([s.timings['total'] for s in run.steps])
    health = {k: sum(s.health == k for s in run.steps) for k in HEALTHS}
    return run.poses, ms, {'health': health}


def _peer_odometry(
    runner: Runner, scans: list[Any], stride: int
) -> tuple[FloatArray, FloatArray, dict[str, Any]]:
    """Scan-to-previous-scan with ``runner``, started from its own previous estimate.

    The new scan, prepared once, is the next target. A registration that raises keeps the
    prediction (the last motion repeated), as an odometry would, and is counted.
    """
    first = np.asarray(scans[0].points, dtype=np.float64)
    previous, t_first = timed(runner.prepare, first)
    poses, ms = [np.eye(4)], [t_first]
    motion = np.eye(4)
    n_raised = 0
    for scan in scans[stride::stride]:
        rec = register_pair(runner, np.asarray(scan.points, dtype=np.float64), previous, motion)
        if rec['T'] is None:
            n_raised += 1
        else:
            motion = rec['T']
        if rec['prep'] is not None:
            previous = rec['prep']
        poses.append(poses[-1] @ motion)
        ms.append(rec['ms'])
    return np.stack(poses), np.array(ms), {'n_raised': n_raised}


def run_strides(
    sample: Sample, runners: Sequence[Runner], strides: Sequence[int], max_input_scans: int | None
) -> dict[str, Any]:
    """Odometry of every method over every ``stride``-th scan, evaluated like the replay."""
    from kentreg_ros.eval import evaluate

    scans = sample.scans[:max_input_scans]
    out: dict[str, Any] = {}
    for stride in strides:
        idx = np.arange(0, len(scans), stride)
        T_gt = sample.T_world[idx]
        block: dict[str, Any] = {
            'input_indices': idx.tolist(),
            'reference_motion': _motion_stats(T_gt),
            'methods': {},
        }
        for runner in runners:
            t0 = time.perf_counter()
            try:
                if runner.name == 'kentreg':
                    poses, ms, extra = _kentreg_odometry(scans, stride)
                else:
                    poses, ms, extra = _peer_odometry(runner, scans, stride)
            except Exception as exc:  # a crashing pipeline is a result
                logger.exception('%s stride %d failed', runner.name, stride)
                block['methods'][runner.name] = {'error': f'{type(exc).__name__}: {exc}'}
                continue
            result = evaluate(poses, T_gt)
            pairs = result['pairs']
            e_R = np.asarray(pairs['e_R_deg'], dtype=np.float64)
            e_t = np.asarray(pairs['e_t_m'], dtype=np.float64)
            failed = failure_mask(e_R, e_t)
            block['methods'][runner.name] = {
                'n_pairs': len(e_R),
                'failed': int(failed.sum()),
                'failed_pairs': [[int(idx[i]), int(idx[i + 1])] for i in np.flatnonzero(failed)],
                'e_R_deg': {'median': float(np.median(e_R)), 'max': float(e_R.max())},
                'e_t_m': {'median': float(np.median(e_t)), 'max': float(e_t.max())},
                'ate_rmse_m': None if result['ate'] is None else result['ate']['rmse'],
                'ms_per_scan_median': float(np.median(ms)),
                'per_pair': {'e_R_deg': e_R.tolist(), 'e_t_m': e_t.tolist()},
                **extra,
            }
            logger.info(
                'strides: N=%d %s: %d/%d failed, ATE %.3f m (%.1f s)',
                stride,
                runner.name,
                failed.sum(),
                len(e_R),
                result['ate']['rmse'] if result['ate'] else float('nan'),
                time.perf_counter() - t0,
            )
        out[str(stride)] = block
    return out


# --------------------------------------------------------------------------------------------
# 2. Raw outliers


def run_outliers(
    sample: Sample,
    runners: Sequence[Runner],
    levels: Sequence[float],
    pairs: Sequence[int],
    seed: int,
    shell_share: float,
) -> dict[str, Any]:
    """Per level and method, the per-pair records, their summary and the clean-median ratio."""
    out: dict[str, Any] = {}
    for level in levels:
        t_level = time.perf_counter()
        rows: dict[str, list[dict[str, Any]]] = {r.name: [] for r in runners}
        realised, shares = [], {r.name: [] for r in runners}
        for trial, pair in enumerate(pairs):
            truth = sample.truth(pair, pair + 1)
            init = truth @ offset_transform(
                np.random.default_rng([seed, 2, trial]), START_OFFSET_DEG, START_OFFSET_M
            )
            rng = np.random.default_rng([seed, 2, trial, int(round(level * 1000))])
            target, tgt_out = inject_raw_outliers(
                sample.raw(pair), level, rng, shell_share=shell_share
            )
            source, src_out = inject_raw_outliers(
                sample.raw(pair + 1), level, rng, shell_share=shell_share
            )
            realised += [tgt_out.mean(), src_out.mean()]
            for runner in runners:
                try:
                    tgt = runner.prepare(target)
                except Exception as exc:
                    logger.warning('%s cannot prepare the target: %s', runner.name, exc)
                    rec = _raised(exc)
                else:
                    rec = register_pair(runner, source, tgt, init)
                row = _pair_record(rec, truth, trial=trial, pair=pair)
                if np.isfinite(row['voxel_m']):
                    row['outlier_share_after_downsampling'] = outlier_voxel_share(
                        source, src_out, row['voxel_m']
                    )
                    shares[runner.name].append(row['outlier_share_after_downsampling'])
                rows[runner.name].append(row)
        block: dict[str, Any] = {
            'realised_share': {
                'mean': float(np.mean(realised)),
                'min': float(np.min(realised)),
                'max': float(np.max(realised)),
            },
            'methods': {},
        }
        for name, recs in rows.items():
            summ = _summary(recs)
            summ['reported_failed'] = sum(r.get('status') == 'failed' for r in recs)
            summ['outlier_share_after_downsampling'] = (
                float(np.mean(shares[name])) if shares[name] else float('nan')
            )
            voxels = [r['voxel_m'] for r in recs if np.isfinite(r['voxel_m'])]
            summ['voxel_m_median'] = float(np.median(voxels)) if voxels else float('nan')
            block['methods'][name] = {'summary': summ, 'pairs': recs}
        out[f'{level:.2f}'] = block
        logger.info(
            'outliers: %.0f %% done in %.0f s: %s',
            100 * level,
            time.perf_counter() - t_level,
            ', '.join(
                f'{n} {b["summary"]["e_R_deg"]["median"]:.3f} deg ({b["summary"]["failures"]} '
                'failed)'
                for n, b in block['methods'].items()
            ),
        )
    clean = out.get(f'{min(levels):.2f}') if levels else None
    for block in out.values():
        for name, entry in block['methods'].items():
            base = clean['methods'][name]['summary']['e_R_deg']['median'] if clean else None
            med = entry['summary']['e_R_deg']['median']
            entry['summary']['median_e_R_ratio_to_clean'] = (
                med / base if base and np.isfinite(base) and np.isfinite(med) else float('nan')
            )
    return out


# --------------------------------------------------------------------------------------------
# 3. Turned pairs


def run_turned(
    sample: Sample,
    runners: Sequence[Runner],
    angles: Sequence[float],
    pairs: Sequence[int],
    seed: int,
) -> dict[str, Any]:
    """Per angle and method, the records of pairs whose source was turned, from the identity."""
    rows: dict[str, dict[str, list[dict[str, Any]]]] = {
        f'{a:g}': {r.name: [] for r in runners} for a in angles
    }
    reference_angle: dict[str, list[float]] = {f'{a:g}': [] for a in angles}
    t0 = time.perf_counter()
    for trial, pair in enumerate(pairs):
        target_raw, source_raw = sample.raw(pair), sample.raw(pair + 1)
        truth = sample.truth(pair, pair + 1)
        targets: dict[str, Any] = {}
        for runner in runners:
            try:
                targets[runner.name] = runner.prepare(target_raw)
            except Exception as exc:
                logger.warning('%s cannot prepare target %d: %s', runner.name, pair, exc)
        for angle in angles:
            T_turn = turn_transform(np.random.default_rng([seed, 3, trial, int(angle)]), angle)
            turned = transform(T_turn, source_raw)
            ref = truth @ np.linalg.inv(T_turn)
            key = f'{angle:g}'
            reference_angle[key].append(
                float(np.degrees(Rotation.from_matrix(ref[:3, :3]).magnitude()))
            )
            for runner in runners:
                if runner.name in targets:
                    # No prior at all: kentreg's register() without init (which searches
                    # SO(3) when it has no start), the peers from the identity.
                    rec = register_pair(runner, turned, targets[runner.name], None)
                else:
                    rec = _raised('the target could not be prepared')
                rows[key][runner.name].append(_pair_record(rec, ref, trial=trial, pair=pair))
        logger.info(
            'turned: pair %d (%d/%d) done, %.0f s',
            pair,
            trial + 1,
            len(pairs),
            time.perf_counter() - t0,
        )
    out: dict[str, Any] = {}
    for key, by_method in rows.items():
        ref_angles = np.array(reference_angle[key])
        block: dict[str, Any] = {
            'reference_rotation_deg': {
                'min': float(ref_angles.min()),
                'median': float(np.median(ref_angles)),
                'max': float(ref_angles.max()),
            },
            'methods': {},
        }
        for name, recs in by_method.items():
            summ = _summary(recs)
            summ['recovered'] = summ['n'] - summ['failures']
            summ['recovered_fraction'] = summ['recovered'] / summ['n'] if summ['n'] else None
            summ['reported_failed'] = sum(r.get('status') == 'failed' for r in recs)
            block['methods'][name] = {'summary': summ, 'pairs': recs}
        out[key] = block
    return out


# --------------------------------------------------------------------------------------------
# Report


def _commit(meta: dict[str, Any]) -> str:
    return str(meta['machine'].get('git') or meta['machine'].get('git_commit') or '?')


def markdown(results: dict[str, Any]) -> str:
    """Tables of every test present in ``results`` (the numbers of the JSON, rounded)."""
    lines: list[str] = []
    fail_rule = f'e_R > {FAIL_ROTATION_DEG:g}° or e_t > {FAIL_TRANSLATION_M:g} m'
    strides = results.get('strides')
    if strides:
        meta = strides['meta']
        lines += [
            f'**Strides** ({meta["input"]}, every N-th of {meta["n_input_scans"]} scans, stamps '
            'unchanged). kentreg: its `Odometry` with `KentRegConfig()` (what `kentreg_replay '
            '--stride N` runs); peers: scan-to-previous-scan, each started from its own previous '
            'estimate (constant velocity; identity for the first pair). A pair joins consecutive '
            f'processed scans and fails when {fail_rule}; ATE after SE(3) alignment.',
            '',
            '| N | reference motion per pair: median / max | method | failed pairs '
            '| median e_R (°) | max e_R (°) | median e_t (m) | max e_t (m) | ATE rmse (m) '
            '| median ms/scan |',
            '|---|---|---|---|---|---|---|---|---|---|',
        ]
        for n, block in strides['strides'].items():
            ref = block['reference_motion']
            motion = (
                f'{ref["rotation_deg_median"]:.1f}° / {ref["rotation_deg_max"]:.1f}°, '
                f'{ref["translation_m_median"]:.2f} / {ref["translation_m_max"]:.2f} m'
            )
            for i, (name, m) in enumerate(block['methods'].items()):
                head = f'| {n} | {motion if i == 0 else ""} | {name} '
                if 'error' in m:
                    lines.append(head + f'| error: {m["error"]} | | | | | | |')
                    continue
                lines.append(
                    head + f'| {m["failed"]}/{m["n_pairs"]} '
                    f'| {fmt(m["e_R_deg"]["median"], ".3f")} | {fmt(m["e_R_deg"]["max"], ".2f")} '
                    f'| {fmt(m["e_t_m"]["median"], ".4f")} | {fmt(m["e_t_m"]["max"], ".3f")} '
                    f'| {fmt(m["ate_rmse_m"], ".3f")} | {fmt(m["ms_per_scan_median"], ".0f")} |'
                )
        health = [
            f'N={n}: '
            + ', '.join(f'{k} {v}' for k, v in b['methods']['kentreg']['health'].items() if v)
            for n, b in strides['strides'].items()
            if 'health' in b['methods'].get('kentreg', {})
        ]
        if health:
            lines += ['', "kentreg's odometry health per stride: " + '; '.join(health) + '.']
        lines += ['', f'Run at {_commit(meta)}: `{meta["command"]}`.', '']
    outliers = results.get('outliers')
    if outliers:
        meta = outliers['meta']
        levels = outliers['levels']
        names = list(next(iter(levels.values()))['methods'])
        head = '| method | ' + ' | '.join(f'{float(k) * 100:.0f} %' for k in levels) + ' |'
        rule = '|---|' + '---|' * len(levels)
        shell = (
            f', {meta["shell_share"] * 100:.0f} % of them in the range shell'
            if meta['shell_share']
            else ''
        )
        lines += [
            f'**Raw outliers** ({meta["n_pairs"]} of the {meta["n_available_pairs"]} consecutive '
            'pairs, drawn without replacement, seed '
            f'{meta["seed"]}; the same pairs at every level). Outliers uniform in each raw '
            f"scan's bounding box{shell}, added before any downsampling as the stated share of "
            'the raw cloud (realised: '
            + ', '.join(
                f'{float(k) * 100:.0f} % → {v["realised_share"]["mean"] * 100:.2f} %'
                for k, v in levels.items()
            )
            + '); every method at its defaults on the contaminated raw scans; start = reference '
            f'perturbed by {meta["start_offset"]["degrees"]:g}° about a random axis and '
            f'{meta["start_offset"]["metres"]:g} m.',
            '',
            "*e_R (°): median (× the method's own outlier-free median) / mean*",
            '',
            head,
            rule,
        ]
        for n in names:
            cells = []
            for block in levels.values():
                s = block['methods'][n]['summary']
                cells.append(
                    f'{fmt(s["e_R_deg"]["median"], ".3f")} '
                    f'({fmt(s["median_e_R_ratio_to_clean"], ".1f")}×) / '
                    f'{fmt(s["e_R_deg"]["mean"], ".3f")}'
                )
            lines.append(f'| {n} | ' + ' | '.join(cells) + ' |')
        lines += ['', '*e_t (m): median / mean*', '', head, rule]
        for n in names:
            cells = [
                f'{fmt(b["methods"][n]["summary"]["e_t_m"]["median"], ".4f")} / '
                f'{fmt(b["methods"][n]["summary"]["e_t_m"]["mean"], ".4f")}'
                for b in levels.values()
            ]
            lines.append(f'| {n} | ' + ' | '.join(cells) + ' |')
        lines += [
            '',
            f'*Failures ({fail_rule}; "raised": the method threw an exception, counted as '
            'failed); outlier share among the points the method downsampled to; median ms per '
            'pair that ran (source preparation + registration)*',
            '',
            head,
            rule,
        ]
        for n in names:
            cells = []
            for b in levels.values():
                s = b['methods'][n]['summary']
                cells.append(
                    f'{s["failures"]}/{s["n"]}{_raised_note(s)}, '
                    f'{fmt(100 * s["outlier_share_after_downsampling"], ".0f")} %, '
                    f'{fmt(s["ms"]["median"], ".0f")} ms'
                )
            lines.append(f'| {n} | ' + ' | '.join(cells) + ' |')
        flagged = [
            f'{float(k) * 100:.0f} %: {b["methods"]["kentreg"]["summary"]["reported_failed"]}'
            for k, b in levels.items()
            if 'kentreg' in b['methods']
        ]
        if flagged:
            voxel = ', '.join(
                f'{float(k) * 100:.0f} % → '
                f'{fmt(b["methods"]["kentreg"]["summary"]["voxel_m_median"], ".2f")} m'
                for k, b in levels.items()
            )
            lines += [
                '',
                "kentreg's own `status == 'failed'` per level: " + ', '.join(flagged) + '. '
                f'Its automatic voxel (median over the source scans): {voxel}; the peers use '
                f'{meta["peer_voxel_m"]:.2f} m throughout.',
            ]
        lines += [
            '',
            'Downsampled outlier share: voxels (origin-anchored grid at the voxel the method '
            'used) holding only injected points, among all occupied voxels of the source scan; '
            'for kentreg before its normal-based outlier test.',
            '',
            f'Run at {_commit(meta)}: `{meta["command"]}`.',
            '',
        ]
    turned = results.get('turned')
    if turned:
        meta = turned['meta']
        angles = turned['angles']
        names = list(next(iter(angles.values()))['methods'])
        lines += [
            f'**Turned pairs** ({meta["n_pairs"]} of the {meta["n_available_pairs"]} consecutive '
            'pairs, drawn without replacement, seed '
            f'{meta["seed"]}): the raw source scan turned about a seeded random axis through the '
            'sensor origin, every method started from the identity (kentreg: `register()` '
            'without `init`, which searches rotations); recovered = not failed '
            f'({fail_rule}); median ms per pair (source preparation + registration).',
            '',
            '| method | ' + ' | '.join(f'{k}°' for k in angles) + ' |',
            '|---|' + '---|' * len(angles),
        ]
        for n in names:
            cells = []
            for b in angles.values():
                s = b['methods'][n]['summary']
                share = fmt(100 * s['recovered_fraction'], '.0f')
                ms = fmt(s['ms']['median'], '.0f')
                cells.append(f'{s["recovered"]}/{s["n"]} ({share} %), {ms} ms{_raised_note(s)}')
            lines.append(f'| {n} | ' + ' | '.join(cells) + ' |')
        lines += [
            '| *reference rotation (median)* | '
            + ' | '.join(f'{b["reference_rotation_deg"]["median"]:.0f}°' for b in angles.values())
            + ' |',
        ]
        flagged = [
            f'{k}°: {b["methods"]["kentreg"]["summary"]["reported_failed"]}'
            for k, b in angles.items()
            if 'kentreg' in b['methods']
        ]
        if flagged:
            lines += [
                '',
                "kentreg's own `status == 'failed'` per angle: " + ', '.join(flagged) + '.',
            ]
        lines += ['', f'Run at {_commit(meta)}: `{meta["command"]}`.', '']
    meta = results['meta']
    machine = meta['machine']
    lines.append(
        f'Methods pinned to {meta["threads"]} thread(s); {machine["cpu"]}, load average '
        f'{machine["load_avg_at_start"][0]:.1f} at the start of the last run ({machine["date"]}).'
    )
    return '\n'.join(lines) + '\n'


def plot(results: dict[str, Any], path: Path) -> None:
    """Strides (failures, ATE), outliers (median e_R, failures) and turned (recovered)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(15, 9), layout='constrained')
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, 3)
    colours: dict[str, Any] = {}

    def colour(name: str) -> Any:
        if name not in colours:
            colours[name] = f'C{len(colours)}'
        return colours[name]

    def style(name: str) -> str:
        return '-' if name.startswith('kentreg') else '--'

    strides = results.get('strides')
    if strides:
        blocks = strides['strides']
        x = np.array([int(n) for n in blocks])
        names = list(next(iter(blocks.values()))['methods'])
        for name in names:
            ok = [b['methods'][name] for b in blocks.values()]
            fail = [100 * m['failed'] / m['n_pairs'] if 'failed' in m else np.nan for m in ok]
            ate = [m.get('ate_rmse_m') or np.nan for m in ok]
            worst = [m['e_R_deg']['max'] if 'e_R_deg' in m else np.nan for m in ok]
            axes[0, 0].plot(x, fail, style(name), marker='o', color=colour(name), label=name)
            axes[1, 2].semilogy(x, worst, style(name), marker='o', color=colour(name), label=name)
            axes[0, 1].semilogy(x, ate, style(name), marker='o', color=colour(name), label=name)
        axes[0, 0].set(
            xlabel='stride N (every N-th scan)',
            ylabel='failed pairs (%)',
            title='strides: failed pairs',
            xticks=x,
            ylim=(-2, 102),
        )
        axes[0, 1].set(xlabel='stride N', ylabel='ATE rmse (m)', title='strides: ATE', xticks=x)
        axes[1, 2].set(
            xlabel='stride N', ylabel='e_R (deg)', title='strides: worst pair e_R', xticks=x
        )
    outliers = results.get('outliers')
    if outliers:
        levels = outliers['levels']
        x = np.array([100 * float(k) for k in levels])
        names = list(next(iter(levels.values()))['methods'])
        for name in names:
            s = [levels[k]['methods'][name]['summary'] for k in levels]
            med = [v['e_R_deg']['median'] for v in s]
            q90 = [v['e_R_deg']['p90'] for v in s]
            fail = [100 * v['failure_rate'] for v in s]
            axes[0, 2].semilogy(x, med, style(name), marker='o', color=colour(name), label=name)
            axes[0, 2].semilogy(x, q90, ':', color=colour(name), alpha=0.6)
            axes[1, 0].plot(x, fail, style(name), marker='o', color=colour(name), label=name)
        axes[0, 2].set(
            xlabel='outliers in the raw scan (%)',
            ylabel='e_R (deg)',
            title='raw outliers: median (line) and p90 (dotted) e_R',
            xticks=x,
        )
        axes[1, 0].set(
            xlabel='outliers in the raw scan (%)',
            ylabel='failed pairs (%)',
            title='raw outliers: failures',
            xticks=x,
            ylim=(-2, 102),
        )
    turned = results.get('turned')
    if turned:
        angles = turned['angles']
        x = np.array([float(k) for k in angles])
        names = list(next(iter(angles.values()))['methods'])
        for name in names:
            frac = [
                100 * (angles[k]['methods'][name]['summary']['recovered_fraction'] or 0.0)
                for k in angles
            ]
            axes[1, 1].plot(x, frac, style(name), marker='o', color=colour(name), label=name)
        axes[1, 1].set(
            xlabel='turn of the source scan (deg)',
            ylabel='recovered (%)',
            title='turned pairs from the identity',
            xticks=x,
            ylim=(-2, 102),
        )
    for ax in axes.ravel():
        ax.grid(True, which='both', alpha=0.3)
        if ax.has_data():
            ax.legend(fontsize=8, loc='best')
    fig.suptitle(
        'kentreg_ros robustness (BALM): kentreg at KentRegConfig() defaults (solid) against '
        'the benchmarks/methods.py peers (dashed)\nfailure: '
        f'e_R > {FAIL_ROTATION_DEG:g} deg or e_t > {FAIL_TRANSLATION_M:g} m; '
        f'{results["meta"]["threads"]} thread(s)'
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)


# --------------------------------------------------------------------------------------------
# Entry point


def _tests(text: str) -> list[str]:
    names = [t.strip() for t in text.split(',') if t.strip()]
    bad = [t for t in names if t not in TESTS]
    if bad or not names:
        raise argparse.ArgumentTypeError(
            f'expected a comma-separated subset of {",".join(TESTS)}, got {text!r}'
        )
    return names


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface (see the module docstring)."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        '--quick',
        action='store_true',
        help=f'smoke test: strides over the first {QUICK["max_input_scans"]} '
        f'scans, {QUICK["outlier_pairs"]} outlier pairs, {QUICK["turned_pairs"]} '
        'turned pairs; writes to a temporary folder unless --out is given',
    )
    parser.add_argument(
        '--only',
        type=_tests,
        default=list(TESTS),
        metavar='TESTS',
        help='comma-separated subset of strides,outliers,turned (default all); '
        "the other tests' results are kept from an existing robustness.json",
    )
    parser.add_argument(
        '--methods',
        nargs='+',
        choices=METHOD_CHOICES,
        default=list(DEFAULT_METHODS),
        help=f'default {" ".join(DEFAULT_METHODS)}',
    )
    parser.add_argument('--seed', type=int, default=0, help='seed of every random draw')
    parser.add_argument('--out', type=Path, help='output folder (default benchmarks/results)')
    parser.add_argument(
        '--data',
        type=Path,
        help='scan folder with poses, or a bag with '
        '/ground_truth (default ../shared/data/balm, else bags/balm_50)',
    )
    parser.add_argument('--threads', type=int, default=1, help='CPUs every method may use')
    parser.add_argument('--strides', nargs='+', type=int, default=list(STRIDES))
    parser.add_argument(
        '--levels',
        nargs='+',
        type=float,
        default=list(LEVELS),
        help='outlier shares of the raw cloud, in [0, 1)',
    )
    parser.add_argument('--angles', nargs='+', type=float, default=list(ANGLES_DEG))
    parser.add_argument('--outlier-pairs', type=int, help=f'default {OUTLIER_PAIRS}')
    parser.add_argument('--turned-pairs', type=int, help=f'default {TURNED_PAIRS}')
    parser.add_argument(
        '--shell-share',
        type=float,
        default=0.0,
        help="share of the outliers drawn in the sensor's range shell instead of "
        'the bounding box (default 0)',
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the selected tests, write JSON, markdown and plot; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.threads < 1 or min(args.strides) < 1:
        parser.error('--threads and --strides must be >= 1')
    if not all(0.0 <= f < 1.0 for f in args.levels) or not 0.0 <= args.shell_share <= 1.0:
        parser.error('--levels must be in [0, 1) and --shell-share in [0, 1]')
    logging.basicConfig(level=logging.INFO, format='%(name)s: %(message)s')
    limit_threads(args.threads)
    out = args.out or (Path(tempfile.gettempdir()) / 'robustness_quick' if args.quick else RESULTS)
    data = args.data or default_data()
    sample = load_sample(data)
    voxel = paper_voxel(sample.raw(0))
    runners = make_runners(args.methods, voxel, args.threads)
    n_pairs = len(sample.scans) - 1
    outlier_pairs = args.outlier_pairs or (QUICK['outlier_pairs'] if args.quick else OUTLIER_PAIRS)
    turned_pairs = args.turned_pairs or (QUICK['turned_pairs'] if args.quick else TURNED_PAIRS)
    max_input = QUICK['max_input_scans'] if args.quick else None
    command = ' '.join(['python3', 'benchmarks/robustness.py', *argv])
    previous = out / 'robustness.json'
    results: dict[str, Any] = {}
    if set(args.only) != set(TESTS) and previous.is_file():
        import json

        kept = json.loads(previous.read_text())
        results.update({t: kept[t] for t in TESTS if t in kept and t not in args.only})
    machine = machine_info()
    common_meta = {
        'command': command,
        'machine': machine,
        'input': sample.description,
        'ground_truth': sample.ground_truth,
        'seed': args.seed,
        'threads': args.threads,
        'quick': args.quick,
        'peer_voxel_m': voxel,
        'methods': {r.name: r.params for r in runners},
    }
    t_all = time.perf_counter()
    for test in TESTS:
        if test not in args.only:
            continue
        t0 = time.perf_counter()
        if test == 'strides':
            body = run_strides(sample, runners, args.strides, max_input)
            meta = {
                'n_input_scans': len(sample.scans[:max_input]),
                'strides': args.strides,
                'peer_start': 'own previous estimate (constant velocity), identity first',
            }
            results[test] = {'meta': {**common_meta, **meta}, 'strides': body}
        elif test == 'outliers':
            pairs = draw_pairs(n_pairs, outlier_pairs, args.seed, 2)
            body = run_outliers(sample, runners, args.levels, pairs, args.seed, args.shell_share)
            meta = {
                'n_pairs': len(pairs),
                'n_available_pairs': n_pairs,
                'pairs': pairs,
                'pair_draw': 'without replacement, seeded',
                'shell_share': args.shell_share,
                'start_offset': {'degrees': START_OFFSET_DEG, 'metres': START_OFFSET_M},
            }
            results[test] = {'meta': {**common_meta, **meta}, 'levels': body}
        else:
            pairs = draw_pairs(n_pairs, turned_pairs, args.seed, 3)
            body = run_turned(sample, runners, args.angles, pairs, args.seed)
            meta = {
                'n_pairs': len(pairs),
                'n_available_pairs': n_pairs,
                'pairs': pairs,
                'pair_draw': 'without replacement, seeded',
                'start': 'identity',
            }
            results[test] = {'meta': {**common_meta, **meta}, 'angles': body}
        results[test]['meta']['wall_s'] = time.perf_counter() - t0
        logger.info('%s done in %.0f s', test, time.perf_counter() - t0)
    machine['load_avg_at_end'] = list(os.getloadavg())
    machine['git_at_end'] = git_describe()
    if machine['git_at_end'] != machine['git']:
        logger.warning(
            'The checkout changed during the run (%s -> %s).',
            machine['git'],
            machine['git_at_end'],
        )
    results['meta'] = {
        **common_meta,
        'tests_run': args.only,
        'wall_s': time.perf_counter() - t_all,
    }
    out.mkdir(parents=True, exist_ok=True)
    write_json(
        previous, {'meta': results['meta'], **{t: results[t] for t in TESTS if t in results}}
    )
    text = markdown(results)
    (out / 'robustness.md').write_text(text)
    plot(results, out / 'robustness.png')
    print(text)
    print(f'wrote {out}/robustness.json, robustness.md, robustness.png')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
