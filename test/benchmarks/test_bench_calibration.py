"""benchmarks/calibration.py: NEES and coverage of the registration's covariance.

The summary is checked on errors drawn from their own covariance (a calibrated covariance
reads as one), and the whole chain on a few scans of the simulated corridor: the odometry's
steps are flagged degenerate along its axis and the table renders them.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from benchmarks import calibration  # noqa: E402
from benchmarks.harness import simulator  # noqa: E402


def _records(rng: np.random.Generator, n: int) -> list[dict[str, Any]]:
    out = []
    for i in range(n):
        L = np.diag([1e-3] * 3 + [1e-4] * 3) @ (np.eye(6) + 0.3 * rng.normal(size=(6, 6)))
        S = L @ L.T
        out.append({
            'index': i + 1, 'model_index': i, 'd': rng.multivariate_normal(np.zeros(6), S),
            'S': S, 'T': np.eye(4), 'degenerate': np.zeros((0, 3)), 'covariance_ms': 0.5,
            'step_ms': 50.0,
        })  # fmt: skip
    return out


def test_errors_drawn_from_their_covariance_read_as_calibrated() -> None:
    summary = calibration.summarize(_records(np.random.default_rng(0), 3000))
    assert abs(summary['nees']['median'] - calibration.CHI2_6_MEDIAN) < 0.4
    assert abs(summary['nees']['under_p95'] - 0.95) < 0.02
    assert np.allclose(summary['coverage']['2sigma'], 0.954, atol=0.02)
    assert np.allclose(summary['coverage']['1sigma'], 0.683, atol=0.03)


def test_the_translation_across_a_tilted_flagged_axis_is_judged_on_its_own() -> None:
    """Errors drawn from S, a flagged direction a little off x with a large variance along it:
    across it the 2-DOF NEES is chi-square's (median 1.39), and a lateral error ten times its
    sigma reads as one, though the y axis's own sigma borrows from the flagged variance."""
    rng = np.random.default_rng(2)
    u = np.array([1.0, 0.01, 0.0]) / np.hypot(1.0, 0.01)
    S = np.diag([1e-6] * 3 + [1e-8] * 3)
    S[:3, :3] += 0.4**2 * np.outer(u, u)
    records = _records(rng, 2000)
    for r in records:
        r['S'], r['degenerate'] = S, u[None]
        r['d'] = rng.multivariate_normal(np.zeros(6), S)
    deg = calibration.summarize(records)['degenerate']
    assert abs(deg['across_nees_median'] - 1.386) < 0.15
    assert abs(deg['across_under_p95'] - 0.95) < 0.02
    for r in records:
        r['d'] = r['d'] + np.array([0.0, 0.01, 0.0, 0.0, 0.0, 0.0])  # 10 mm across, sigma 1 mm
    deg = calibration.summarize(records)['degenerate']
    assert deg['across_under_p95'] < 0.01


def test_a_reference_noise_added_to_the_covariance_lowers_the_nees() -> None:
    records = _records(np.random.default_rng(1), 500)
    for r in records:
        r['d'] = r['d'] + np.random.default_rng(r['index']).normal(0.0, 3e-3, 6)
    ref = np.eye(6) * 3e-3**2
    summary = calibration.summarize(records, ref)
    assert summary['nees']['median'] > 10.0
    assert abs(summary['nees_with_reference']['median'] - calibration.CHI2_6_MEDIAN) < 1.0


@pytest.mark.integration
def test_the_corridor_is_flagged_along_its_axis_and_rendered() -> None:
    world = simulator.corridor_world()
    scans, gt = simulator.simulate(world, 0.3, 0, simulator.Sensor())
    T = np.asarray(gt.trajectory.T_world_sensor, dtype=np.float64)
    seq = calibration.Sequence('corridor:0', scans[:4], T[:4], 'corridor', True)
    records = calibration.run_odometry(seq, 'previous_scan')
    assert len(records) == 3
    assert all(len(r['degenerate']) and abs(r['degenerate'][0][0]) > 0.95 for r in records)
    assert all(r['S'][0, 0] > 100 * r['S'][1, 1] for r in records)
    summary = calibration.summarize(records)
    assert summary['degenerate']['steps'] == 3
    entry = {'name': 'corridor', 'note': 'test', 'models': {'previous_scan': summary}}
    constants = {'calibration': 1.6, 'cell_spacings': 8.0}
    doc = {'constants': constants, 'seeds': 1, 'real': [], 'simulated': [entry]}
    text = calibration.markdown(doc)
    assert '| corridor (test) | previous_scan | 3 |' in text
