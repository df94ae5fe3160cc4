"""Is the registration's covariance calibrated? NEES and per-axis coverage against exact poses.

Per odometry step, ``d`` is the step's error as a 6-vector in the convention of
``RegistrationResult.covariance`` (``exp(d) = T_true T_est^-1``, ``d = (v, w)``, target frame;
the target is the model's frame, ``model_index``'s pose) and ``S`` that covariance;
``NEES = d^T S^-1 d`` is chi-square with 6 degrees of freedom when ``S`` is right (median 5.35,
95 % under 12.59), and each axis's ``|d_k| / sqrt(S_kk)`` lies within 1, 2, 3 in 68, 95, 99.7 %
of the steps. Simulated sequences (``harness/simulator.py``, exact poses): the sample's scene
at ``--step`` m per scan with the sensor's range noise at 1, 2 and 5 cm, 40 % raw outliers,
sparse scans (2 deg beams, 1/16 of the points) and a featureless corridor (whose axis the
degeneracy test flags: coverage along the flagged direction too). Real sequences: the 50 BALM
scans and the Livox Avia keyframes, whose references have errors of their own: a three-cornered
hat with GICP (small_gicp) estimates the reference's per-axis noise, and the NEES is given with
it added to ``S`` too. Both odometry models, one thread.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import logging
import sys
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository

from benchmarks.harness import datasets, methods, perturb, report, simulator  # noqa: E402
from kentreg_ros.core import KentRegConfig, Odometry, log_so3  # noqa: E402
from kentreg_ros.core.registration import uncertainty  # noqa: E402
from kentreg_ros.io.sources import Scan  # noqa: E402

FloatArray = NDArray[np.float64]
MODELS = ('previous_scan', 'local_map')
#: The 6-DOF chi-square's median and 95th percentile.
CHI2_6_MEDIAN, CHI2_6_P95 = 5.348, 12.592
#: The 2-DOF chi-square's 95th percentile (the translation across a flagged direction).
CHI2_2_P95 = 5.991
AXES = ('x', 'y', 'z', 'roll', 'pitch', 'yaw')
#: Millimetres and millidegrees per metre and radian, for the tables.
UNITS = np.array([1e3] * 3 + [np.degrees(1.0) * 1e3] * 3)
SIMULATED = ('clean', 'noise_1cm', 'noise_5cm', 'outliers_40', 'sparse', 'corridor')
REAL = ('balm', 'hku_2', 'quick_shack')
#: GICP's voxel for the reference's noise (the Livox benchmark's; BALM's voxels are ~0.2 m).
GICP_VOXEL_M = 0.25


@dataclasses.dataclass
class Sequence:
    """Scans, exact or reference poses, and what they are."""

    name: str
    scans: list[Scan]
    T_world: FloatArray
    note: str
    simulated: bool


def simulated(name: str, step: float, corridor_step: float, seed: int) -> Sequence:
    """One simulated condition's sequence for ``seed`` (see the module docstring)."""
    sensor = simulator.Sensor()
    if name == 'corridor':
        scans, gt = simulator.simulate(simulator.corridor_world(), corridor_step, seed, sensor)
        note = f'featureless corridor, {corridor_step} m per scan at 10 Hz'
    else:
        world = _balm_world()
        sensor = {
            'noise_1cm': dataclasses.replace(sensor, range_noise=0.01),
            'noise_5cm': dataclasses.replace(sensor, range_noise=0.05),
            'sparse': dataclasses.replace(sensor, beam_bin=2.0),
        }.get(name, sensor)
        scans, gt = simulator.simulate(world, step, seed, sensor)
        if name == 'outliers_40':
            scans = perturb.raw_outliers(0.4, np.random.default_rng([seed, 1]))(scans)
        note = (f'sample scene, {step} m per scan, range noise {100 * sensor.range_noise:g} cm, '
                f'{sensor.beam_bin:g} deg beams' + (', 40 % raw outliers' if 'outl' in name
                                                    else ''))  # fmt: skip
    T = np.asarray(gt.trajectory.T_world_sensor, dtype=np.float64)
    return Sequence(f'{name}:{seed}', scans, T, note, True)


_WORLD: list[simulator.World] = []


def _balm_world() -> simulator.World:
    if not _WORLD:
        _WORLD.append(simulator.build_world(simulator.DEFAULT_INPUT, simulator.WORLD_VOXEL))
    return _WORLD[0]


def real(name: str) -> Sequence:
    """The 50 BALM scans (the sample bag when ../shared/data is absent) or a Livox sequence."""
    if name == 'balm':
        folder = datasets.SHARED_DATA / 'balm'
        seq = datasets.load_balm() if folder.is_dir() else datasets.DATASETS['balm_50']()
        note = 'BALM 2.0, LiDAR-inertial reference (the BA input)'
    else:
        path = datasets.SHARED_DATA / 'livox_avia' / name / 'velodyne'
        seq = datasets.load_recording(path, name=name)
        note = 'Livox Avia keyframes, FAST-LIO2 reference'
    assert seq.T_world is not None  # both loaders refuse a recording without a reference
    return Sequence(name, seq.scans, seq.T_world, note, False)


def step_error(T_true: FloatArray, T_est: FloatArray) -> FloatArray:
    """``d`` with ``exp(d) = T_true T_est^-1``: ``(t_true - dR t_est, log dR)``."""
    E = T_true @ np.linalg.inv(T_est)
    return np.concatenate([E[:3, 3], log_so3(E[:3, :3])])


def run_odometry(seq: Sequence, model: str) -> list[dict[str, Any]]:
    """Per registered step: its error, covariance, degenerate directions and timings.

    The step's estimate is the pose the odometry chose, in the model's frame: on a step the
    verify stage recovered with the search, that can be one of the search's alternatives
    rather than its best (``result.T_target_source``, which the speed limits may have refused:
    in the simulated corridor its 180 degree twin); ``alternative`` marks those steps."""
    odo = Odometry(KentRegConfig.from_dict({'odometry': {'model': model}}))
    records = []
    for index, scan in enumerate(seq.scans):
        times = scan.extras.get('t') if scan.extras else None
        step = odo.step(scan.points, scan.stamp_ns, frame_id=scan.frame_id, point_times=times)
        result = step.result
        if result is None or not step.ok or index == 0 or step.model_index < 0:
            continue
        T_true = np.linalg.inv(seq.T_world[step.model_index]) @ seq.T_world[index]
        T_est = np.linalg.inv(odo.poses[step.model_index]) @ step.T_world_lidar
        alternative = not np.allclose(T_est, result.T_target_source, rtol=0.0, atol=1e-6)
        records.append({
            'index': index, 'model_index': step.model_index, 'health': str(step.health),
            'd': step_error(T_true, T_est), 'S': np.array(result.covariance), 'T': T_est,
            'alternative': alternative, 'degenerate': np.array(result.degenerate_directions),
            'covariance_ms': result.timings.get('covariance', float('nan')),
            'step_ms': step.timings['total'],
        })  # fmt: skip
    return records


def coverage(z: FloatArray) -> dict[str, list[float]]:
    """Share of ``|z| <= k`` for k = 1, 2, 3, per column of ``z`` (steps x axes)."""
    return {f'{k}sigma': [float(v) for v in (np.abs(z) <= k).mean(axis=0)] for k in (1, 2, 3)}


def summarize(records: list[dict[str, Any]], ref: FloatArray | None = None) -> dict[str, Any]:
    """NEES, per-axis coverage, sigma against error, the degenerate steps' coverage along the
    flagged direction, and the covariance's cost; with ``ref`` (a reference's covariance) the
    NEES of ``S + ref`` too."""
    if not records:
        return {'steps': 0}
    d = np.array([r['d'] for r in records])
    S = np.array([r['S'] for r in records])
    nees = np.einsum('ni,ni->n', d, np.linalg.solve(S, d[:, :, None])[:, :, 0])
    sigma = np.sqrt(np.einsum('nii->ni', S))
    out: dict[str, Any] = {
        'steps': len(records),
        'nees': {'median': float(np.median(nees)), 'mean': float(nees.mean()),
                 'under_p95': float(np.mean(nees <= CHI2_6_P95))},
        'coverage': coverage(d / sigma),
        'sigma_median': [float(v) for v in np.median(sigma, axis=0) * UNITS],
        'error_median': [float(v) for v in np.median(np.abs(d), axis=0) * UNITS],
        'covariance_ms_median': float(np.nanmedian([r['covariance_ms'] for r in records])),
        'step_ms_median': float(np.median([r['step_ms'] for r in records])),
        'alternatives': int(sum(bool(r.get('alternative')) for r in records)),
    }  # fmt: skip
    flagged = [(r['d'][:3], r['S'][:3, :3], r['degenerate'][0]) for r in records
               if len(r['degenerate'])]  # fmt: skip
    if flagged:
        z = np.array([[u @ e / np.sqrt(u @ C @ u)] for e, C, u in flagged])
        across = np.array([_across_nees(e, C, u) for e, C, u in flagged])
        out['degenerate'] = {'steps': len(flagged), 'coverage': coverage(z),
                             'error_median_m': float(np.median(np.abs(z[:, 0]) * [
                                 np.sqrt(u @ C @ u) for _, C, u in flagged])),
                             'across_nees_median': float(np.median(across)),
                             'across_under_p95': float(np.mean(across <= CHI2_2_P95))}  # fmt: skip
    if ref is not None:
        with_ref = np.einsum('ni,ni->n', d, np.linalg.solve(S + ref, d[:, :, None])[:, :, 0])
        out['nees_with_reference'] = {
            'median': float(np.median(with_ref)), 'mean': float(with_ref.mean()),
            'under_p95': float(np.mean(with_ref <= CHI2_6_P95)),
            'coverage': coverage(d / np.sqrt(np.einsum('nii->ni', S + ref))),
        }  # fmt: skip
    return out


def _across_nees(e: FloatArray, C: FloatArray, u: FloatArray) -> float:
    """NEES of the translation error ``e`` across the flagged direction ``u`` (the plane
    orthogonal to it; chi-square with 2 degrees of freedom): the per-axis coverage of a
    direction near ``u`` borrows the large variance along it when ``u`` is a little tilted."""
    P = np.linalg.svd(np.eye(3) - np.outer(u, u) / (u @ u))[0][:, :2]  # a basis across u
    a = P.T @ e
    return float(a @ np.linalg.solve(P.T @ C @ P, a))


def reference_noise(seq: Sequence, records: list[dict[str, Any]]) -> dict[str, Any] | None:
    """Per-axis noise of the reference's relative poses by a three-cornered hat: with kentreg
    (K), GICP (G) and the reference (R) erring independently, ``var(R) = (var(K-R) +
    var(G-R) - var(K-G)) / 2`` (robust variances, 1.4826 MAD squared); errors K and G share
    (the same scans) raise it, so it is an upper bound. None without small_gicp."""
    try:
        import small_gicp
    except ImportError:
        return None
    clouds: dict[int, Any] = {}

    def prepared(i: int) -> Any:
        if i not in clouds:
            points = np.asarray(seq.scans[i].points, dtype=np.float64)
            clouds[i] = small_gicp.preprocess_points(
                points, downsampling_resolution=GICP_VOXEL_M, num_threads=1
            )
        return clouds[i]

    KR, GR, KG = [], [], []
    for r in records:
        (target, target_tree), (source, _) = prepared(r['model_index']), prepared(r['index'])
        found = small_gicp.align(
            target, source, target_tree, init_T_target_source=r['T'], registration_type='GICP',
            max_correspondence_distance=4 * GICP_VOXEL_M, num_threads=1,
        )  # fmt: skip
        T_gicp = np.array(found.T_target_source)
        T_true = _relative(seq, r['model_index'], r['index'])
        KR.append(r['d'])
        GR.append(step_error(T_true, T_gicp))
        KG.append(step_error(T_gicp, r['T']))

    def var(a: list[FloatArray]) -> FloatArray:
        x = np.array(a)
        return np.asarray((1.4826 * np.median(np.abs(x - np.median(x, 0)), 0)) ** 2)

    v_kr, v_gr, v_kg = var(KR), var(GR), var(KG)
    v_ref = np.maximum((v_kr + v_gr - v_kg) / 2, 0.0)
    v_kent = np.maximum((v_kr + v_kg - v_gr) / 2, 0.0)
    return {'pairs': len(KR), 'variance': [float(v) for v in v_ref],
            'sigma': [float(v) for v in np.sqrt(v_ref) * UNITS],
            'kentreg_sigma': [float(v) for v in np.sqrt(v_kent) * UNITS]}  # fmt: skip


def _relative(seq: Sequence, target: int, source: int) -> FloatArray:
    return np.asarray(np.linalg.inv(seq.T_world[target]) @ seq.T_world[source])


def run(args: argparse.Namespace, argv: list[str]) -> dict[str, Any]:
    methods.pin_threads(1, argv, __file__)
    logging.basicConfig(level=logging.ERROR, format='%(name)s: %(levelname)s: %(message)s')
    doc: dict[str, Any] = {
        'benchmark': 'calibration', 'command': ['python3', 'benchmarks/calibration.py', *argv],
        'date': datetime.datetime.now().isoformat(timespec='seconds'),
        'machine': report.machine_info(), 'seeds': args.seeds, 'step_m': args.step,
        'corridor_steps_m': args.corridor_steps, 'models': args.models,
        'constants': {'calibration': uncertainty.CALIBRATION,
                      'cell_spacings': uncertainty.CELL_SPACINGS,
                      'curvature_floor': uncertainty.CURVATURE_FLOOR},
        'simulated': [], 'real': [],
    }  # fmt: skip
    pooled: list[float] = []
    for name in args.simulated:
        steps = args.corridor_steps if name == 'corridor' else [args.step]
        for step in steps:
            seqs = [simulated(name, step, step, seed) for seed in range(args.seeds)]
            entry: dict[str, Any] = {'name': name, 'note': seqs[0].note, 'models': {}}
            for model in args.models:
                records = [r for s in seqs for r in run_odometry(s, model)]
                entry['models'][model] = summarize(records)
                if name != 'corridor':
                    pooled += [_nees(r) for r in records if not len(r['degenerate'])]
            doc['simulated'].append(entry)
    if pooled:
        doc['fitted_calibration'] = uncertainty.CALIBRATION * float(
            np.median(pooled) / CHI2_6_MEDIAN
        )
    for name in args.real:
        seq = real(name)
        entry = {'name': name, 'note': seq.note, 'scans': len(seq.scans), 'models': {}}
        runs = {model: run_odometry(seq, model) for model in args.models}
        first = runs[args.models[0]]
        hat = reference_noise(seq, first) if args.reference else None
        entry['reference'] = hat
        ref = None if hat is None else np.diag(hat['variance'])
        entry['models'] = {model: summarize(recs, ref) for model, recs in runs.items()}
        doc['real'].append(entry)
    report.finish_machine(doc['machine'])
    return doc


def _nees(r: dict[str, Any]) -> float:
    return float(r['d'] @ np.linalg.solve(r['S'], r['d']))


def _axes(values: list[float], spec: str = '.2f') -> str:
    return ' / '.join(format(v, spec) for v in values)


def _row(label: str, model: str, s: dict[str, Any], nees_key: str = 'nees') -> list[str]:
    if not s.get('steps'):
        return [label, model, '0', *[''] * 7]
    n = s[nees_key]
    cov = n.get('coverage', s['coverage'])
    sig, err = s['sigma_median'], s['error_median']
    deg = s.get('degenerate')
    deg_cell = '–'
    if deg is not None:
        c1, c2, c3 = (100 * deg['coverage'][f'{k}sigma'][0] for k in (1, 2, 3))
        deg_cell = f'{deg["steps"]}: {c2:.0f} % (1σ {c1:.0f}, 3σ {c3:.0f})'
        if 'across_nees_median' in deg:  # results written before it was measured lack it
            deg_cell += (f'; across it NEES median {deg["across_nees_median"]:.1f}, '
                         f'{100 * deg["across_under_p95"]:.0f} % ≤ {CHI2_2_P95}')  # fmt: skip
    return [label, model, str(s['steps']), f'{n["median"]:.1f} / {n["mean"]:.1f}',
            f'{100 * n["under_p95"]:.0f} %', _axes([100 * c for c in cov['2sigma']], '.0f'),
            f'{100 * min(cov["1sigma"]):.0f} / {100 * min(cov["3sigma"]):.0f}',
            f'{_axes(sig[:3], ".2g")} mm, {_axes(sig[3:], ".2g")} mdeg',
            f'{_axes(err[:3], ".2g")} mm, {_axes(err[3:], ".2g")} mdeg', deg_cell]  # fmt: skip


HEAD = ['data', 'model', 'steps', 'NEES median / mean', 'NEES ≤ 12.6',
        '2σ coverage x / y / z / roll / pitch / yaw [%]', '1σ / 3σ coverage, worst axis [%]',
        'σ median (x / y / z, roll / pitch / yaw)', '|error| median',
        'degenerate steps: 2σ coverage along the flagged axis; across it (2-DOF NEES, '
        'median 1.39)']  # fmt: skip


def markdown(doc: dict[str, Any]) -> str:
    lines = [
        f'Odometry steps against exact (simulated) and reference (real) poses; NEES of the '
        f'6-DOF step error with `RegistrationResult.covariance` (consistent: median '
        f'{CHI2_6_MEDIAN}, 95 % ≤ {CHI2_6_P95}; per axis 68 / 95 / 99.7 % within 1 / 2 / 3 σ). '
        f'Constants: calibration {doc["constants"]["calibration"]}, cells of '
        f'{doc["constants"]["cell_spacings"]:g} spacings.',
        '',
        f'**Simulated** ({doc["seeds"]} seeds per condition, exact poses)',
        '',
    ]
    rows = []
    for e in doc['simulated']:
        label = f'{e["name"]} ({e["note"]})'
        rows += [_row(label, m, s) for m, s in e['models'].items()]
    lines += report.table(HEAD, rows)
    alt = [f'{e["name"]} ({e["note"]}) {m}: {s["alternatives"]}' for e in doc['simulated']
           for m, s in e['models'].items() if s.get('alternatives')]  # fmt: skip
    if alt:
        lines += ['', 'Steps whose pose is an alternative of their registration (the search '
                  "recovered them; the covariance is that pose's own since 2026-12-08, the "
                  "search's best pose's before): " + '; '.join(alt) + '.']  # fmt: skip
    if 'fitted_calibration' in doc:
        lines += [
            '',
            f'The variance factor that puts the median NEES of the pooled simulated '
            f'steps (corridor and degenerate steps aside) at {CHI2_6_MEDIAN}: '
            f'{doc["fitted_calibration"]:.2f} (in use: {doc["constants"]["calibration"]}).',
        ]
    if doc['real']:
        lines += [
            '',
            '**Real** (reference poses with errors of their own: rows "+ reference" '
            'add the reference noise below to S)',
            '',
        ]
        rows = []
        for e in doc['real']:
            for m, s in e['models'].items():
                rows.append(_row(f'{e["name"]} ({e["note"]})', m, s))
                if 'nees_with_reference' in s:
                    rows.append(_row(f'{e["name"]} + reference', m, s, 'nees_with_reference'))
        lines += report.table(HEAD, rows)
        lines += [
            '',
            'Reference noise per axis (three-cornered hat with GICP at '
            f"{GICP_VOXEL_M} m, an upper bound), and kentreg's own by the same hat:",
            '',
        ]
        lines += report.table(
            ['data', 'pairs', 'reference σ (mm, mdeg)', 'kentreg σ by the hat (mm, mdeg)'],
            [[e['name'], e['reference']['pairs'], _axes(e['reference']['sigma'], '.2g'),
              _axes(e['reference']['kentreg_sigma'], '.2g')]
             for e in doc['real'] if e.get('reference')],
        )  # fmt: skip
    cost = [s for e in doc['simulated'] + doc['real'] for s in e['models'].values()
            if s.get('steps')]  # fmt: skip
    if cost:
        share = [s['covariance_ms_median'] / s['step_ms_median'] for s in cost]
        lines += [
            '',
            f'The covariance costs {min(share):.2%}–{max(share):.2%} of a step '
            "(medians per row: its stage over the step's total).",
        ]
    if doc.get('machine', {}).get('git'):
        lines += ['', f'Run at {doc["machine"]["git"]}: `{" ".join(doc.get("command", []))}`.']
    return '\n'.join(lines) + '\n'


OPTIONS: list[report.Option] = [
    ('--simulated', {'nargs': '*', 'choices': SIMULATED, 'default': list(SIMULATED)}),
    ('--real', {'nargs': '*', 'choices': REAL, 'default': list(REAL)}),
    ('--models', {'nargs': '+', 'choices': MODELS, 'default': list(MODELS)}),
    ('--seeds', {'type': int, 'default': 3, 'help': 'sequences per condition (default 3)'}),
    ('--step', {'type': float, 'default': 0.15, 'help': 'm per scan (default 0.15)'}),
    ('--corridor-steps', {'type': float, 'nargs': '+', 'default': [0.15, 0.3], 'metavar': 'M',
                          'help': 'm per scan in the corridor (default 0.15 0.3)'}),
    ('--no-reference', {'dest': 'reference', 'action': 'store_false',
                        'help': 'skip the reference noise (GICP) on the real sequences'}),
]  # fmt: skip

if __name__ == '__main__':
    raise SystemExit(report.experiment_main(__doc__, 'calibration', OPTIONS, run, markdown))
