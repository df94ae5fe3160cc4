"""The one runner: pairs through a :class:`~benchmarks.harness.methods.RawMethod` or
:class:`~benchmarks.harness.methods.Method`, scans through a pipeline, errors and summaries.

A method or pipeline that raises is a result, not a stop: its pair gets NaN errors (a failure,
counted in ``n_errors``) and the experiment goes on.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.eval.metrics import failed_pairs, pair_errors
from kentreg_ros.io.sources import Scan

from .methods import RawMethod
from .pipelines import Pipeline

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
T = TypeVar('T')


def timed(fn: Callable[..., T], *args: Any) -> tuple[T, float]:
    """``(fn(*args), milliseconds)``."""
    t0 = time.perf_counter()
    out = fn(*args)
    return out, (time.perf_counter() - t0) * 1e3


def guarded(what: str, fn: Callable[..., T], *args: Any) -> T | dict[str, str]:
    """``fn(*args)``, or ``{'error': 'Type: message'}`` when it raised (logged as ``what``
    failed): a pipeline or method that crashes is a result, not a stop."""
    try:
        return fn(*args)
    except Exception as exc:
        logger.exception('%s failed', what)
        return {'error': f'{type(exc).__name__}: {exc}'}


def errors(T_est: FloatArray, T_true: FloatArray) -> tuple[float, float]:
    """(e_R in degrees, e_t in metres) of the paper (kentreg_ros.eval.metrics.pair_errors)."""
    e_R, e_t = pair_errors(T_est[None], T_true[None])
    return float(e_R[0]), float(e_t[0])


#: Failed pairs of arrays of errors, element by element: e_R > 2 deg or e_t > 0.2 m, or NaN
#: errors (a method that raised).
failure_mask = failed_pairs


def motion_stats(T_rel: FloatArray) -> dict[str, float]:
    """Median and max rotation (deg) and translation (m) of relative motions (P, 4, 4)."""
    angle, dist = pair_errors(T_rel, np.broadcast_to(np.eye(4), T_rel.shape))
    return {'rotation_deg_median': float(np.median(angle)),
            'rotation_deg_max': float(np.max(angle)),
            'translation_m_median': float(np.median(dist)),
            'translation_m_max': float(np.max(dist))}  # fmt: skip


def _stats(v: FloatArray) -> dict[str, float]:
    if not len(v):
        return dict.fromkeys(('mean', 'median', 'p90', 'max'), float('nan'))
    out = {'mean': float(v.mean()), 'median': float(np.median(v))}
    return out | {'p90': float(np.percentile(v, 90)), 'max': float(v.max())}


def summarize(
    records: Iterable[Mapping[str, Any]], *, finite_times: bool = False
) -> dict[str, Any]:
    """Mean/median/p90/max of e_R, e_t, failure count and median time of per-pair records;
    NaN errors (raised) are failures, counted in ``n_errors``, and left out of the statistics;
    ``finite_times``: times over the pairs that ran (else one raised pair makes them NaN)."""
    rows = list(records)
    e_R = np.array([r['e_R_deg'] for r in rows], dtype=np.float64)
    e_t = np.array([r['e_t_m'] for r in rows], dtype=np.float64)
    ms = np.array([r['ms'] for r in rows], dtype=np.float64)
    if finite_times:
        ms = ms[np.isfinite(ms)]
    ok = np.isfinite(e_R) & np.isfinite(e_t)
    fails = int(failure_mask(e_R, e_t).sum())
    nan = float('nan')
    return {
        'n': len(rows), 'n_errors': int((~ok).sum()), 'failures': int(fails),
        'failure_rate': fails / len(rows) if rows else nan,
        'e_R_deg': _stats(e_R[ok]), 'e_t_m': _stats(e_t[ok]),
        'ms': {'median': float(np.median(ms)) if len(ms) else nan,
               'mean': float(ms.mean()) if len(ms) else nan},
    }  # fmt: skip


# --------------------------------------------------------------------------------------------
# Pairs


@dataclass
class Trial:
    """One pair of a pair experiment: raw ``target`` and ``source`` points, the reference
    ``truth``, the ``starts`` (``{name: init}``; None: the method's own) and the fields of its
    records (``extra``). ``keys`` name the two scans when trials share them (a target is
    prepared once per method: the same pair's at several angles, or the previous pair's source);
    ``mark(record)`` adds to each record."""

    target: FloatArray
    source: FloatArray
    truth: FloatArray
    starts: Mapping[str, FloatArray | None]
    extra: dict[str, Any] = field(default_factory=dict)
    keys: tuple[Any, Any] = (None, None)
    mark: Callable[[dict[str, Any]], None] | None = None


def _prepare(method: RawMethod, points: FloatArray) -> tuple[Any, float, str | None]:
    """``(prep, ms, None)``, or ``(None, nan, 'Type: message')`` when the preparation raised."""
    try:
        return (*timed(method.prepare, points), None)
    except Exception as exc:
        logger.warning('%s cannot prepare a scan: %s', method.name, exc)
        return None, float('nan'), f'{type(exc).__name__}: {exc}'


def run_trials(
    built: Sequence[RawMethod], trials: Iterable[Trial]
) -> dict[str, dict[str, list[dict[str, Any]]]]:
    """Every method on every trial from each of its starts, methods inner (every method sees
    the same load): ``{method: {start: records}}``, a record's ``ms`` the source's preparation
    plus the registration; a method that raises fails the pair (NaN errors, no time)."""
    out: dict[str, dict[str, list[dict[str, Any]]]] = {m.name: {} for m in built}
    cache: dict[str, dict[Any, tuple[Any, float, str | None]]] = {m.name: {} for m in built}
    for trial in trials:
        for m in built:
            old, (tkey, skey) = cache[m.name], trial.keys
            tgt = old[tkey] if tkey is not None and tkey in old else _prepare(m, trial.target)
            src = old[skey] if skey is not None and skey in old else _prepare(m, trial.source)
            cache[m.name] = {tkey: tgt, skey: src}
            for start, init in trial.starts.items():
                T: FloatArray | None = None
                info: dict[str, Any] = {'error': tgt[2] or src[2]}
                reg_ms = float('nan')
                if not (tgt[2] or src[2]):
                    try:
                        (T, info), reg_ms = timed(m.register, src[0], tgt[0], init)
                    except Exception as exc:  # a method that raises fails the pair
                        logger.warning('%s raised: %s', m.name, exc)
                        info = {'error': f'{type(exc).__name__}: {exc}'}
                nan = float('nan')
                e_R, e_t = (nan, nan) if T is None else errors(T, trial.truth)
                record = {**trial.extra, 'e_R_deg': e_R, 'e_t_m': e_t, 'ms': src[1] + reg_ms}
                record |= {'prepare_ms': src[1], 'register_ms': reg_ms}
                record |= {'voxel_m': nan if T is None else m.voxel(src[0]), **info}
                if trial.mark is not None:
                    trial.mark(record)
                out[m.name].setdefault(start, []).append(record)
    return out


# --------------------------------------------------------------------------------------------
# Scans through a pipeline


@dataclass
class Run:
    """Poses and per-scan wall times of one pipeline over scans."""

    name: str
    poses: FloatArray
    ms_per_scan: FloatArray
    points_used: FloatArray
    settings: dict[str, Any] = field(default_factory=dict)
    health: dict[str, Any] = field(default_factory=dict)
    step_health: list[str] = field(default_factory=list)


def run_pipeline(make: Callable[[], Pipeline], scans: Sequence[Scan], *, warmup: int = 0) -> Run:
    """Every scan through a fresh pipeline, each step timed (wall clock, reading excluded);
    ``warmup`` > 0: a throwaway pipeline first steps that many scans, untimed."""
    if warmup:
        throwaway = make()
        for scan in scans[:warmup]:
            throwaway.step(scan)
    pipeline = make()
    poses, ms = [], []
    for scan in scans:
        pose, t = timed(pipeline.step, scan)
        poses.append(np.array(pose, dtype=np.float64))
        ms.append(t)
    used = np.array(pipeline.points_used, dtype=np.float64)
    health = dict(pipeline.health)
    return Run(
        pipeline.name,
        np.stack(poses),
        np.array(ms),
        used,
        pipeline.settings,
        health,
        list(pipeline.step_health),
    )


def combine_rounds(runs: list[Run]) -> Run:
    """One run from several rounds: first round's poses (the largest difference from later
    rounds' in ``health``), per-scan median of the times."""
    first = runs[0]
    moved = (float(np.abs(r.poses[:, :3, 3] - first.poses[:, :3, 3]).max()) for r in runs[1:])
    spread = max(moved, default=0.0)
    per_round = [float(r.ms_per_scan.mean()) for r in runs]
    health = {**first.health, 'rounds': len(runs), 'pose_spread_between_rounds_m': spread,
              'mean_ms_per_scan_per_round': per_round}  # fmt: skip
    ms = np.median(np.stack([r.ms_per_scan for r in runs]), axis=0)
    return Run(
        first.name, first.poses, ms, first.points_used, first.settings, health, first.step_health
    )


def rotated(names: Sequence[T], rounds: int) -> list[tuple[int, T]]:
    """``(round, name)`` over ``rounds`` rounds, each in an order rotated by one, so that a
    change in the shared machine's load does not land on one method only."""
    shifts = ((r, r % len(names) if names else 0) for r in range(rounds))
    return [(r, n) for r, k in shifts for n in [*names[k:], *names[:k]]]


#: Frames of the drift segment (RPE over scans i, i + SEGMENT_FRAMES): one second at 10 Hz.
SEGMENT_FRAMES = 10


def evaluate_run(run: Run, T_gt: FloatArray) -> dict[str, Any]:
    """The replay's metrics (:func:`kentreg_ros.eval.evaluate`) of a run against the reference
    poses of its scans, plus rotation RPE per metre, RPE over :data:`SEGMENT_FRAMES` and speed."""
    from kentreg_ros.eval import evaluate, metrics

    result = evaluate(run.poses, T_gt)
    # Rotation RPE per metre over the pairs the translation per-metre figure keeps.
    rpe = metrics.rpe(run.poses, T_gt, delta=1)
    per_metre = metrics.rpe_per_metre(run.poses, T_gt, delta=1)
    deg_per_m = rpe['e_R_deg'][per_metre['index']] / per_metre['distance_m']
    result['rpe_per_metre']['rotation_deg_per_m'] = metrics.summarize(deg_per_m)
    # Drift over a segment, not one step: scan-to-map adds two registration errors between
    # consecutive scans where scan-to-scan has one, but should drift less over a stretch.
    if len(run.poses) > SEGMENT_FRAMES:
        seg = metrics.rpe(run.poses, T_gt, delta=SEGMENT_FRAMES)
        result['rpe_segment'] = {'frames': SEGMENT_FRAMES,
                                 'rotation_deg': metrics.summarize(seg['e_R_deg']),
                                 'translation_m': metrics.summarize(seg['e_t'])}  # fmt: skip
    result['n_matched'] = len(run.poses)
    result['speed'] = {'ms_per_scan': metrics.summarize(run.ms_per_scan),
                       'points_used_per_scan': metrics.summarize(run.points_used)}  # fmt: skip
    return result


def score_pipelines(
    makers: Mapping[str, Callable[[], Pipeline]], scans: Sequence[Scan], T_gt: FloatArray, *,
    rounds: int = 1, warmup: int = 0, combine: bool = False,
    score: Callable[[Run, FloatArray], dict[str, Any]] = evaluate_run,
) -> dict[str, dict[str, Any]]:  # fmt: skip
    """Every pipeline over ``scans`` (:func:`run_pipeline`) in ``rounds`` rotated rounds, its
    run (the rounds' :func:`combine_rounds` with ``combine``, else the first) scored against
    ``T_gt``: ``{name: {'run': Run, 'metrics': score(run, T_gt)}}``, or ``{'error': ...}`` for
    a pipeline that raised (not run again)."""
    runs: dict[str, list[Run]] = {name: [] for name in makers}
    out: dict[str, dict[str, Any]] = {}
    step = functools.partial(run_pipeline, warmup=warmup)
    for _, name in rotated(list(makers), rounds):
        if name not in out:
            run = guarded(name, step, makers[name], scans)
            if isinstance(run, dict):
                out[name] = run
            else:
                runs[name].append(run)

    def scored(runs: list[Run]) -> dict[str, Any]:
        run = combine_rounds(runs) if combine else runs[0]
        return {'run': run, 'metrics': score(run, T_gt)}

    return {n: out[n] if n in out else guarded(n, scored, runs[n]) for n in makers}


def in_subprocess(
    script: str, args: Sequence[str], *, env: dict[str, str] | None = None, timeout: float = 1800
) -> dict[str, Any]:
    """Run ``script --worker OUT *args`` in a fresh interpreter (one library or method per
    process, pinned by the worker itself); its JSON result, or ``{'error': ...}``."""
    with tempfile.TemporaryDirectory(prefix='kentreg-bench-') as tmp:
        out = Path(tmp) / 'result.json'
        cmd = [sys.executable, script, '--worker', str(out), *args]
        try:
            proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            return {'error': f'timed out after {timeout:.0f} s'}
        if proc.returncode != 0 or not out.is_file():
            tail = proc.stderr.strip().splitlines()[-1:] or ['no output']
            return {'error': f'exit {proc.returncode}: {tail[0]}'}
        result: dict[str, Any] = json.loads(out.read_text())
    if proc.stderr.strip():
        result['stderr'] = proc.stderr.strip().splitlines()[-5:]
    return result


def cpu_times() -> list[tuple[int, int]]:
    """(busy, total) jiffies of every core (/proc/stat); busy: all but idle and iowait."""
    lines = Path('/proc/stat').read_text().splitlines()
    per_core = [line for line in lines if line.startswith('cpu') and line[3].isdigit()]
    jiffies = [[int(x) for x in line.split()[1:]] for line in per_core]
    return [(sum(v) - v[3] - v[4], sum(v)) for v in jiffies]


def tree_cpu_s(pid: int) -> float:
    """CPU seconds (user + system) of ``pid`` and its descendants so far."""
    parents: dict[int, int] = {}
    times: dict[int, float] = {}
    for entry in (e for e in Path('/proc').iterdir() if e.name.isdigit()):
        try:
            fields = (entry / 'stat').read_text().rsplit(')', 1)[1].split()
        except OSError:
            continue
        parents[int(entry.name)] = int(fields[1])
        times[int(entry.name)] = (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
    mine, more = {pid}, {pid}
    while more:
        more = {p for p, pp in parents.items() if pp in mine} - mine
        mine |= more
    return sum(times.get(p, 0.0) for p in mine)
