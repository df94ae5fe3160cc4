"""The box twins of a localization (issue #39): a narrow view of a room is localized only after
the twins of its answer were searched."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from kentreg_ros.core import KentRegConfig, exp_so3, prepare_scan
from kentreg_ros.core.geometry import rotation_angle
from kentreg_ros.core.localization import PointMap, localize
from kentreg_ros.core.localization.search import Window
from kentreg_ros.core.localization.twins import box_twins, is_narrow
from kentreg_ros.core.scan.clusters import cluster_normals

LIVOX = Path(os.environ.get('KENTREG_SHARED_DATA', '/work/shared/data')) / 'livox_avia'


def _room_normals(R: np.ndarray) -> np.ndarray:
    rng = np.random.default_rng(39)
    axes = np.concatenate([np.eye(3), -np.eye(3)]) @ R.T
    n = np.repeat(axes, [400, 300, 500, 350, 250, 450], axis=0)
    n += 0.05 * rng.standard_normal(n.shape)
    return n / np.linalg.norm(n, axis=1)[:, None]


def test_the_box_twins_turn_the_rooms_axes_onto_each_other() -> None:
    R = exp_so3([0.3, -0.2, 0.7])
    _, _, mixture = cluster_normals(_room_normals(R), KentRegConfig())
    twins = box_twins(mixture)
    assert len(twins) == 23
    angles = sorted(round(np.degrees(rotation_angle(Q))) for Q in twins)
    assert angles.count(180) == 9 and angles.count(90) == 6 and angles.count(120) == 8
    for Q in twins:  # each takes every axis of the room onto an axis, either way
        turned = (Q @ R).T @ R
        assert np.allclose(np.sort(np.abs(turned), axis=1), [[0, 0, 1]] * 3, atol=0.05)


def test_a_narrow_view_is_told_from_an_all_round_one() -> None:
    rng = np.random.default_rng(3)
    rays = rng.standard_normal((4000, 3))
    rays /= np.linalg.norm(rays, axis=1)[:, None]
    all_round = rays * rng.uniform(2.0, 10.0, (4000, 1))
    cone = all_round[rays[:, 0] > np.cos(np.radians(35.0))]
    cfg = KentRegConfig()
    assert is_narrow(prepare_scan(cone, config=cfg))
    assert not is_narrow(prepare_scan(all_round, config=cfg))


@pytest.mark.integration
@pytest.mark.skipif(not (LIVOX / 'quick_shack').is_dir(), reason='no Livox Avia keyframes')
def test_a_box_twin_of_a_narrow_scan_is_not_localized() -> None:
    """quick_shack keyframe 125 against a map of the even keyframes, from a start 1 m and
    90 deg off (the benchmark's, seed 39) with a 1.5 m / 135 deg window: the search proposed a
    91 deg twin 5.7 m off (fit 0.59) and localized it; the truth fits 0.62 and is a twin of it.
    """
    from benchmarks.harness import datasets, perturb

    seq = datasets.load_recording(LIVOX / 'quick_shack' / 'velodyne', name='quick_shack')
    assert seq.T_world is not None
    T = seq.T_world
    even = list(range(0, len(T), 2))
    world = np.concatenate([perturb.transform(T[i], seq.scans[i].points) for i in even])
    cfg = KentRegConfig()
    pmap = PointMap.from_points(world, config=cfg, viewpoints=T[even, :3, 3])
    start = T[125] @ perturb.offset_transform(np.random.default_rng([39, 125, 1]), 90.0, 1.0)
    result = localize(seq.raw(125), pmap, init=start, window=Window(1.5, 135.0), config=cfg)
    if result.localized:
        assert result.T_map_scan is not None
        assert np.degrees(rotation_angle(result.T_map_scan[:3, :3].T @ T[125][:3, :3])) < 2.0
        assert np.linalg.norm(result.T_map_scan[:3, 3] - T[125][:3, 3]) < 0.5
