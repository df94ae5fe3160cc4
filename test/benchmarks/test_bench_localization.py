"""benchmarks/localization.py: its starts, its scoring and its table; the FPFH + RANSAC peer.

The bookkeeping needs no peer library; the FPFH + RANSAC test skips without Open3D.
"""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from optional import import_open3d

REPO_ROOT = Path(__file__).resolve().parents[2]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from scenes import box_room, random_transform, transform_points  # noqa: E402

from benchmarks.harness.methods import fpfh_ransac  # noqa: E402
from benchmarks.harness.runner import errors  # noqa: E402
from benchmarks.localization import (  # noqa: E402
    NO_START,
    WINDOW_FACTOR,
    Outcome,
    _starts,
    _summary,
    keep_methods,
    markdown,
)
from kentreg_ros.core import make_transform  # noqa: E402


def test_starts_are_off_by_the_perturbation_and_their_windows_cover_it() -> None:
    truth = make_transform(np.eye(3), [3.0, -2.0, 0.5])
    args = SimpleNamespace(distances=[1.0, 20.0], angles=[10.0, 180.0])
    starts = _starts(truth, 7, args)
    assert [s[0] for s in starts] == [
        NO_START, '1 m / 10 deg', '1 m / 180 deg', '20 m / 10 deg', '20 m / 180 deg',
    ]  # fmt: skip
    assert starts[0][1] is None and starts[0][2] is None
    levels = [(1, 10), (1, 180), (20, 10), (20, 180)]
    for (_, start, window), (d, a) in zip(starts[1:], levels, strict=True):
        e_r, e_t = errors(start, truth)
        assert abs(e_r - a) < 1e-6 and abs(e_t - d) < 1e-9
        assert window.distance == WINDOW_FACTOR * d
        assert window.angle_deg == min(180.0, WINDOW_FACTOR * a)
    again = _starts(truth, 7, args)
    assert all(np.array_equal(a[1], b[1]) for a, b in zip(starts, again, strict=True)), 'seeded'


def test_the_summary_counts_successes_false_accepts_and_any_pose_elsewhere() -> None:
    truth = np.eye(4)
    near = make_transform(np.eye(3), [0.3, 0.0, 0.0])
    far = make_transform(np.eye(3), [0.6, 0.0, 0.0])
    outcomes = [
        (1, Outcome(near, 'localized', 10.0), truth),
        (3, Outcome(far, 'localized', 20.0), truth),
        (5, Outcome(None, 'ambiguous', 30.0), truth),
        (7, Outcome(near, 'localized', 40.0), None),  # another place: any pose is wrong
    ]
    s = _summary(outcomes)
    assert (s['n'], s['localized'], s['success'], s['false_accepts']) == (4, 3, 1, 2)
    assert s['statuses'] == {'localized': 3, 'ambiguous': 1}
    assert [m['index'] for m in s['misses']] == [3, 5, 7]
    assert s['misses'][0]['e_t_m'] == 0.6 and s['misses'][2]['e_t_m'] is None
    assert s['ms_p50'] == 25.0


def test_the_table_renders_from_the_results_alone() -> None:
    entry = _summary([(1, Outcome(np.eye(4), 'localized', 900.0), np.eye(4))])
    elsewhere = _summary([(0, Outcome(None, 'not_found', 800.0), None)])
    site = {
        'name': 'balm_50', 'reference': '/ground_truth', 'step': 1, 'held_out': [1],
        'map': {'scans': 25, 'points': 1000, 'kentreg_points': 500},
        'other_place': {'name': 'kitti_raw_hdl64', 'n': 1, 'methods': {'kentreg': elsewhere}},
        'starts': {NO_START: {'methods': {'kentreg': entry}}},
    }  # fmt: skip
    doc = {
        'bars': {'rotation_deg': 2.0, 'translation_m': 0.5}, 'seed': 39, 'window_factor': 1.5,
        'peer_voxel_m': 0.5, 'machine': {'git': 'abc1234'}, 'date': 'today', 'sites': [site],
    }  # fmt: skip
    text = markdown(doc)
    assert '| none | 100 % (1/1), 0 | 900 / 900 |' in text
    assert '| kitti_raw_hdl64 (1 scans): localized | 0/1 | 800 / 800 |' in text
    assert 'kentreg from no start: localized 1; kitti_raw_hdl64: not_found 1.' in text


def _site_doc(methods: dict[str, float], commit: str) -> dict:
    """A one-site results file whose methods each localized scan 1 in ``ms``."""
    entries = {
        m: _summary([(1, Outcome(np.eye(4), 'localized', ms), np.eye(4))])
        for m, ms in methods.items()
    }
    site = {
        'name': 'balm_50', 'reference': '/ground_truth', 'step': 1, 'held_out': [1],
        'map': {'scans': 25, 'points': 1000, 'kentreg_points': 500},
        'other_place': {'name': 'kitti_raw_hdl64', 'n': 1, 'methods': dict(entries)},
        'starts': {NO_START: {'methods': dict(entries)}},
    }  # fmt: skip
    return {
        'bars': {'rotation_deg': 2.0, 'translation_m': 0.5}, 'seed': 39, 'step': 2,
        'window_factor': 1.5, 'peer_voxel_m': 0.5, 'machine': {'git': commit}, 'date': commit,
        'sites': [site],
    }  # fmt: skip


def test_kept_rows_fill_only_the_methods_not_run_and_say_where_they_came_from() -> None:
    new = _site_doc({'kentreg': 100.0}, 'new1234')
    old = _site_doc({'kentreg': 900.0, 'gicp': 30.0}, 'old5678')
    keep_methods(new, old, 'old.json')
    got = new['sites'][0]['starts'][NO_START]['methods']
    assert got['kentreg']['ms_p50'] == 100.0, 'the rows run now win'
    assert got['gicp']['ms_p50'] == 30.0
    assert new['sites'][0]['other_place']['methods']['gicp']['ms_p50'] == 30.0
    assert new['kept'] == {'methods': ['gicp'], 'commit': 'old5678', 'date': 'old5678'}
    assert 'GICP are kept from the run at old5678' in markdown(new)
    other = _site_doc({'gicp': 30.0}, 'old5678')
    other['sites'][0]['held_out'] = [3]
    with pytest.raises(SystemExit, match='held-out scans of balm_50'):
        keep_methods(_site_doc({'kentreg': 1.0}, 'x'), other, 'old.json')


def test_fpfh_ransac_places_a_room_without_a_start() -> None:
    import_open3d()
    rng = np.random.default_rng(8)
    room = box_room(rng, 40_000, boxes=6)
    T = random_transform(rng, 120.0, 3.0)
    method = fpfh_ransac(0.25, seed=1)
    target = method.prepare(room)
    source = method.prepare(transform_points(np.linalg.inv(T), room))
    T_est, info = method.register(source, target, None)
    assert info['fitness'] > 0.5, info
    e_r, e_t = errors(T_est, T)
    assert e_r < 2.0 and e_t < 0.2, (e_r, e_t)
