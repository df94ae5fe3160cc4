"""Localization in a saved map (issue 39): kentreg's localize() against FPFH + RANSAC and GICP.

Per recording: a map of its even scans (keyframes) at their reference poses, with those poses as
its trajectory (what ``~/save_map`` writes beside a map); its odd scans (every ``--step``-th of
them on the Livox keyframes) held out and localized (a) from no start and (b) from starts
perturbed by every pair of ``--distances`` (m) and ``--angles`` (deg), a random direction and
axis per scan (seeded), kentreg's search window 1.5x the perturbation (angles capped at 180 deg).
Success: within 0.5 m and 2 deg of the reference; a false accept: ``localized`` but farther off.
Another place, the scans of another recording against the same map from no start, must never be
localized (the KITTI street frames against the BALM map; Avia keyframes of one sequence against
the other's map). Time per localization, the scan's preparation included and the map's not, one
thread.

Peers at ``--peer-voxel``, scored the same way: Open3D FPFH + RANSAC then point-to-plane ICP
(global registration: it takes no start, so its one answer per scan is scored under every
start), and small_gicp GICP against the map from the start (the identity without one). Neither
has a gate: every answer counts as localized (an FPFH answer without a RANSAC inlier is none),
so their false accepts are their wrong answers.
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository

from benchmarks.harness import datasets, methods, perturb, report  # noqa: E402
from kentreg_ros.core import (  # noqa: E402
    KentRegConfig,
    PointMap,
    Window,
    localize,
    prepare_scan,
)
from kentreg_ros.eval.localization import MAX_ROTATION_DEG, MAX_TRANSLATION_M  # noqa: E402
from kentreg_ros.eval.metrics import pair_errors  # noqa: E402

METHODS = ('kentreg', 'fpfh_ransac', 'gicp')
LABELS = {'kentreg': 'kentreg', 'fpfh_ransac': 'FPFH + RANSAC', 'gicp': 'GICP'}
DISTANCES_M = (1.0, 5.0, 20.0)
ANGLES_DEG = (10.0, 90.0, 180.0)
#: kentreg's search window as a multiple of the start's perturbation.
WINDOW_FACTOR = 1.5
SEED = 39
NO_START = 'none'
LIVOX = datasets.SHARED_DATA / 'livox_avia'


@dataclass(frozen=True)
class Site:
    """A recording whose map is made, and the other place whose scans must not be localized
    in it; ``stepped``: ``--step`` thins its held-out scans (and the other place's)."""

    load: Callable[[], datasets.Sequence]
    other: str
    load_other: Callable[[], datasets.Sequence]
    stepped: bool


def _livox(name: str) -> Callable[[], datasets.Sequence]:
    return lambda: datasets.load_recording(LIVOX / name / 'velodyne', name=name)


SITES = {
    'balm_50': Site(
        lambda: datasets.load_recording(datasets.SAMPLE_BAG, name='balm_50'),
        'kitti_raw_hdl64', datasets.load_kitti_hdl64, stepped=False,
    ),
    'hku_2': Site(_livox('hku_2'), 'quick_shack', _livox('quick_shack'), stepped=True),
    'quick_shack': Site(_livox('quick_shack'), 'hku_2', _livox('hku_2'), stepped=True),
}  # fmt: skip


def start_label(distance: float, angle: float) -> str:
    return f'{distance:g} m / {angle:g} deg'


@dataclass
class Outcome:
    """One localization: the pose given (None: none), kentreg's status, milliseconds."""

    T: np.ndarray | None
    status: str
    ms: float


class Localizers:
    """The three methods against one map: ``run(name, raw scan, start or None)``; the scan's
    preparation is done once per method and scan and counted in every localization's time."""

    def __init__(self, world: np.ndarray, views: np.ndarray, args: argparse.Namespace) -> None:
        self.cfg = KentRegConfig()
        self.names = args.methods
        t0 = time.perf_counter()
        self.pmap = PointMap.from_points(world, config=self.cfg, viewpoints=views)
        self.map_s = {'kentreg': time.perf_counter() - t0}
        self.peers: dict[str, methods.RawMethod] = {}
        if 'fpfh_ransac' in self.names:
            self.peers['fpfh_ransac'] = methods.fpfh_ransac(args.peer_voxel, seed=SEED)
        if 'gicp' in self.names:
            gicp = methods.make_methods(['gicp'], voxel=args.peer_voxel, threads=1)
            self.peers.update({m.name: methods.at_fixed_voxel(m, args.peer_voxel) for m in gicp})
        self.maps: dict[str, Any] = {}
        for name, method in self.peers.items():
            t0 = time.perf_counter()
            self.maps[name] = method.prepare(world)
            self.map_s[name] = time.perf_counter() - t0
        self._prepared: dict[str, tuple[Any, float]] = {}

    def new_scan(self, raw: np.ndarray) -> None:
        """Prepare ``raw`` for every method (timed)."""
        self._prepared = {}
        for name in self.names:
            t0 = time.perf_counter()
            if name == 'kentreg':
                prep: Any = prepare_scan(raw, config=self.cfg)
            else:
                prep = self.peers[name].prepare(raw)
            self._prepared[name] = (prep, (time.perf_counter() - t0) * 1e3)

    def run(self, name: str, start: np.ndarray | None, window: Window | None) -> Outcome:
        prep, prep_ms = self._prepared[name]
        t0 = time.perf_counter()
        if name == 'kentreg':
            result = localize(prep, self.pmap, init=start, window=window, config=self.cfg)
            T, status = result.T_map_scan, str(result.status)
        else:
            T, info = self.peers[name].register(prep, self.maps[name], start)
            answered = info.get('fitness', 1.0) > 0.0
            T, status = (T, 'answer') if answered else (None, 'no_answer')
        return Outcome(T, status, prep_ms + (time.perf_counter() - t0) * 1e3)


def _starts(T_true: np.ndarray, index: int, args: argparse.Namespace) -> list[tuple]:
    """(label, start, window) of every start of scan ``index``: none, then each perturbation."""
    out: list[tuple] = [(NO_START, None, None)]
    level = 0
    for d in args.distances:
        for a in args.angles:
            rng = np.random.default_rng([SEED, index, level])
            level += 1
            start = T_true @ perturb.offset_transform(rng, a, d)
            window = Window(WINDOW_FACTOR * d, min(180.0, WINDOW_FACTOR * a))
            out.append((start_label(d, a), start, window))
    return out


def _summary(outcomes: list[tuple[int, Outcome, np.ndarray | None]]) -> dict[str, Any]:
    """Counts, times and the misses of (scan index, outcome, reference pose or None: another
    place, where any pose is a false accept)."""
    n = len(outcomes)
    statuses: dict[str, int] = {}
    localized = success = false = 0
    misses = []
    for index, o, truth in outcomes:
        statuses[o.status] = statuses.get(o.status, 0) + 1
        e_r: float | None = None
        e_t: float | None = None
        if o.T is not None:
            localized += 1
            ok = False
            if truth is not None:
                er, et = pair_errors(o.T[None], truth[None])
                e_r, e_t = float(er[0]), float(et[0])
                ok = e_r <= MAX_ROTATION_DEG and e_t <= MAX_TRANSLATION_M
            success += ok
            false += not ok
            if ok:
                continue
        misses.append({'index': index, 'status': o.status, 'e_R_deg': e_r, 'e_t_m': e_t})
    ms = np.array([o.ms for _, o, _ in outcomes]) if n else np.zeros(1)
    return {
        'n': n, 'localized': localized, 'success': success, 'false_accepts': false,
        'statuses': statuses, 'ms_p50': float(np.percentile(ms, 50)),
        'ms_p95': float(np.percentile(ms, 95)), 'ms_max': float(ms.max()), 'misses': misses,
    }  # fmt: skip


def _log(site: str, what: str, k: int, n: int, t0: float) -> None:
    print(f'{site}: {what} {k}/{n} ({time.perf_counter() - t0:.0f} s)', flush=True)


def run_site(name: str, args: argparse.Namespace) -> dict[str, Any]:
    site = SITES[name]
    seq = site.load()
    assert seq.T_world is not None  # load_recording refuses a recording without a reference
    T = seq.T_world
    step = args.step if site.stepped else 1
    even, held = list(range(0, len(T), 2)), list(range(1, len(T), 2))[::step][: args.limit]
    world = np.concatenate([perturb.transform(T[i], seq.scans[i].points) for i in even])
    loc = Localizers(world, T[even, :3, 3], args)
    per_start: dict[str, dict[str, list]] = {}
    t0 = time.perf_counter()
    for k, i in enumerate(held):
        loc.new_scan(seq.raw(i))
        for label, start, window in _starts(T[i], i, args):
            block = per_start.setdefault(label, {m: [] for m in args.methods})
            for m in args.methods:
                if m == 'fpfh_ransac' and label != NO_START:  # start-free: the same answer
                    block[m].append(per_start[NO_START][m][-1])
                    continue
                block[m].append((i, loc.run(m, start, window), T[i]))
        _log(name, 'held-out scan', k + 1, len(held), t0)
    other = site.load_other()
    other_rows = range(1, len(other.scans), 2)[::step] if site.stepped else range(len(other.scans))
    other_rows = other_rows[: args.limit]
    elsewhere: dict[str, list] = {m: [] for m in args.methods}
    for k, j in enumerate(other_rows):
        loc.new_scan(other.raw(j))
        for m in args.methods:
            elsewhere[m].append((j, loc.run(m, None, None), None))
        _log(name, f'{site.other} scan', k + 1, len(other_rows), t0)
    return {
        'name': name, 'description': seq.description, 'reference': seq.note,
        'n_scans': len(seq.scans), 'step': step, 'held_out': held,
        'map': {'scans': len(even), 'points': len(world), 'kentreg_points': len(loc.pmap),
                'prepare_s': loc.map_s},
        'other_place': {'name': site.other, 'n': len(other_rows), 'step': step,
                        'methods': {m: _summary(v) for m, v in elsewhere.items()}},
        'starts': {label: {'methods': {m: _summary(v) for m, v in block.items()}}
                   for label, block in per_start.items()},
    }  # fmt: skip


def run(args: argparse.Namespace, argv: list[str]) -> dict[str, Any]:
    methods.pin_threads(1, argv, __file__)
    logging.basicConfig(level=logging.ERROR, format='%(name)s: %(levelname)s: %(message)s')
    doc: dict[str, Any] = {
        'benchmark': 'localization', 'command': ['python3', 'benchmarks/localization.py', *argv],
        'date': datetime.datetime.now().isoformat(timespec='seconds'),
        'machine': report.machine_info(), 'seed': SEED, 'step': args.step,
        'peer_voxel_m': args.peer_voxel, 'window_factor': WINDOW_FACTOR,
        'bars': {'rotation_deg': MAX_ROTATION_DEG, 'translation_m': MAX_TRANSLATION_M},
        'peers': {'fpfh_ransac': methods.FPFH},
        'sites': [run_site(name, args) for name in args.sites],
    }  # fmt: skip
    report.finish_machine(doc['machine'])
    if args.keep_from is not None:
        keep_methods(doc, json.loads(args.keep_from.read_text()), str(args.keep_from))
    return doc


def keep_methods(doc: dict[str, Any], old: dict[str, Any], source: str) -> None:
    """Fill the methods ``doc`` did not run from ``old`` (the same sites, starts and seed: a
    peer's rows need no rerun after a change to kentreg), and record where they came from."""
    if (old['seed'], old['step']) != (doc['seed'], doc['step']):
        raise SystemExit(f'{source}: another seed or step; its rows are not these scans.')
    by_name = {site['name']: site for site in old['sites']}
    kept: set[str] = set()
    for site in doc['sites']:
        was = by_name.get(site['name'])
        if was is None or was['held_out'] != site['held_out']:
            raise SystemExit(f'{source}: no rows for the held-out scans of {site["name"]}.')
        blocks = [(site['other_place'], was['other_place'])] + [
            (block, was['starts'][label]) for label, block in site['starts'].items()
        ]
        for new, prior in blocks:
            for method, entry in prior['methods'].items():
                if method not in new['methods']:
                    new['methods'][method] = entry
                    kept.add(method)
    commit = old['machine'].get('git') or old['machine'].get('git_commit')
    doc['kept'] = {'methods': sorted(kept), 'commit': commit, 'date': old['date']}


def _cell(e: dict[str, Any] | None, other: bool = False) -> list[str]:
    if e is None:
        return ['–', '–']
    n = max(e['n'], 1)
    if other:
        return [f'{e["localized"]}/{e["n"]}', f'{e["ms_p50"]:.0f} / {e["ms_p95"]:.0f}']
    return [
        f'{100 * e["success"] / n:.0f} % ({e["success"]}/{e["n"]}), {e["false_accepts"]}',
        f'{e["ms_p50"]:.0f} / {e["ms_p95"]:.0f}',
    ]


def _statuses(entry: dict[str, Any]) -> str:
    return ', '.join(f'{key} {v}' for key, v in entry['statuses'].items())


def markdown(doc: dict[str, Any]) -> str:
    names = list(doc['sites'][0]['starts'][NO_START]['methods'])
    head = ['start'] + [
        f'{LABELS.get(m, m)}: {col}' for m in names
        for col in ('success, false accepts', 'ms p50 / p95')
    ]  # fmt: skip
    bars = doc['bars']
    lines = [
        f'Localization in a map of the even scans at their reference poses, the odd ones held '
        f'out; success: within {bars["translation_m"]:g} m and {bars["rotation_deg"]:g} deg; '
        f'false accept: a pose given but farther off (every wrong peer answer: peers have no '
        f'gate); starts perturbed by the distance and angle shown (random direction and axis, '
        f'seed {doc["seed"]}), kentreg searching {doc["window_factor"]:g}x that window; '
        f'FPFH + RANSAC takes no start (its answers repeat in every row); peers at '
        f'{doc["peer_voxel_m"]:g} m voxels; one thread, ms include preparing the scan.'
    ]
    for s in doc['sites']:
        m, o = s['map'], s['other_place']
        step = f' (one in {s["step"]} of the odd scans)' if s['step'] > 1 else ''
        lines += [
            '',
            f'**{s["name"]}**: map of {m["scans"]} scans ({m["points"]} points; kentreg '
            f'{m["kentreg_points"]} at its map voxel), {len(s["held_out"])} odd scans held out'
            f'{step}; reference: {s["reference"]}',
            '',
        ]
        rows = []
        for label, block in s['starts'].items():
            got = block['methods']
            rows.append([label, *sum((_cell(got.get(n)) for n in names), [])])
        label = f'{o["name"]} ({o["n"]} scans): localized'
        rows.append([label, *sum((_cell(o['methods'].get(n), other=True) for n in names), [])])
        lines += report.table(head, rows)
        k, elsewhere = s['starts'][NO_START]['methods'].get('kentreg'), o['methods'].get('kentreg')
        if k is not None and elsewhere is not None:
            lines.append(
                f'- kentreg from no start: {_statuses(k)}; {o["name"]}: {_statuses(elsewhere)}.'
            )
    commit = doc['machine'].get('git') or doc['machine'].get('git_commit')
    lines += ['', f'`benchmarks/localization.py` at {commit}, {doc["date"]}.']
    if doc.get('kept'):
        kept = doc['kept']
        lines[-1] += (
            f' The rows of {", ".join(LABELS.get(m, m) for m in kept["methods"])} are kept from '
            f'the run at {kept["commit"]}, {kept["date"]} (`--keep-from`: the same scans and '
            f'starts, not run again).'
        )
    return '\n'.join(lines) + '\n'


OPTIONS: list[report.Option] = [
    ('--sites', {'nargs': '+', 'choices': list(SITES), 'default': list(SITES),
                 'help': 'recordings mapped (default: all)'}),
    ('--methods', {'nargs': '+', 'choices': METHODS, 'default': list(METHODS)}),
    ('--step', {'type': int, 'default': 2,
                'help': 'every N-th odd keyframe of the Livox sequences is held out (and of '
                        'the other place), for time (default 2)'}),
    ('--limit', {'type': int, 'metavar': 'N',
                 'help': 'at most N held-out and N other-place scans per recording'}),
    ('--distances', {'type': float, 'nargs': '*', 'default': list(DISTANCES_M), 'metavar': 'M'}),
    ('--angles', {'type': float, 'nargs': '*', 'default': list(ANGLES_DEG), 'metavar': 'DEG'}),
    ('--peer-voxel', {'type': float, 'default': 0.5, 'metavar': 'M',
                      'help': "the peers' voxel edge (default 0.5)"}),
    ('--keep-from', {'type': Path, 'metavar': 'JSON',
                     'help': 'take the methods not run from an earlier localization.json of '
                             'the same scans (e.g. the peers after a change to kentreg)'}),
]  # fmt: skip


if __name__ == '__main__':
    raise SystemExit(report.experiment_main(__doc__, 'localization', OPTIONS, run, markdown))
