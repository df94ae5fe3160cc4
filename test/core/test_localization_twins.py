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


def test_a_start_a_cell_off_is_polished_onto_the_map() -> None:
    """polish_pose: a start 0.8 m below and 3 deg off a scan of a room comes within 0.2 m and
    1 deg (a correlation peak of a floor is placed to a cell only)."""
    from scenes import box_room

    from kentreg_ros.core import make_transform
    from kentreg_ros.core.localization.search import polish_pose

    rng = np.random.default_rng(8)
    world = box_room(rng, 60_000, size=(12.0, 9.0, 3.0), boxes=4)
    cfg = KentRegConfig()
    pmap = PointMap.from_points(world, config=cfg, viewpoints=np.array([[0.0, 0.0, 0.5]]))
    truth = make_transform(exp_so3([0.0, 0.0, 0.4]), [1.0, -0.5, 0.3])
    local = (world - truth[:3, 3]) @ truth[:3, :3]
    scan = prepare_scan(local[local[:, 0] > 0.5], config=cfg)
    start = make_transform(
        exp_so3([0.03, -0.03, 0.03]) @ truth[:3, :3], truth[:3, 3] + [0.2, 0, -0.8]
    )
    T = polish_pose(scan, pmap, start)
    assert np.degrees(rotation_angle(T[:3, :3].T @ truth[:3, :3])) < 1.0
    assert np.linalg.norm(T[:3, 3] - truth[:3, 3]) < 0.2


@pytest.fixture(scope='module')
def quick_shack() -> tuple[object, PointMap]:
    from benchmarks.harness import datasets, perturb

    seq = datasets.load_recording(LIVOX / 'quick_shack' / 'velodyne', name='quick_shack')
    assert seq.T_world is not None
    T = seq.T_world
    even = list(range(0, len(T), 2))
    world = np.concatenate([perturb.transform(T[i], seq.scans[i].points) for i in even])
    return seq, PointMap.from_points(world, config=KentRegConfig(), viewpoints=T[even, :3, 3])


@pytest.mark.integration
@pytest.mark.skipif(not (LIVOX / 'quick_shack').is_dir(), reason='no Livox Avia keyframes')
@pytest.mark.parametrize(
    ('index', 'angle', 'level'),
    [(125, None, None), (125, 90.0, 1), (117, 180.0, 2)],
)
def test_a_box_twin_of_a_narrow_scan_is_not_localized(
    quick_shack: tuple, index: int, angle: float | None, level: int | None
) -> None:
    """quick_shack keyframes against a map of the even ones, as benchmarks/localization.py
    runs them (starts 1 m off, seed 39, a 1.5x window), that were localized at a box twin of
    the truth: 125 from no start (179 deg, 10.7 m off, fit 0.44), 125 from 1 m / 90 deg (91
    deg, 5.7 m, fit 0.59: the truth fits 0.62), 117 from 1 m / 180 deg (91 deg, 5.8 m, fit
    0.32). Now right or refused."""
    from benchmarks.harness import perturb

    seq, pmap = quick_shack
    truth = seq.T_world[index]
    start = window = None
    if angle is not None:
        rng = np.random.default_rng([39, index, level])
        start = truth @ perturb.offset_transform(rng, angle, 1.0)
        window = Window(1.5, min(180.0, 1.5 * angle))
    result = localize(seq.raw(index), pmap, init=start, window=window, config=KentRegConfig())
    if result.localized:
        assert result.T_map_scan is not None
        assert np.degrees(rotation_angle(result.T_map_scan[:3, :3].T @ truth[:3, :3])) < 2.0
        assert np.linalg.norm(result.T_map_scan[:3, 3] - truth[:3, 3]) < 0.5


def test_the_scans_spectrum_is_the_padded_grids() -> None:
    """scan_spectra transforms only the corner box a scan occupies: the same spectrum as
    ``rfftn`` of its occupancy padded to the whole grid."""
    import scipy.fft as sfft

    from kentreg_ros.core.localization.search import scan_spectra

    rng = np.random.default_rng(5)
    shape = (24, 30, 18)
    ijk = rng.integers(0, [9, 12, 7], size=(300, 3))
    channel = rng.integers(0, 3, size=300)
    padded = np.zeros((3, *shape), dtype=np.float32)
    padded[channel, ijk[:, 0], ijk[:, 1], ijk[:, 2]] = 1.0
    expected = sfft.rfftn(padded, axes=(1, 2, 3))
    assert np.allclose(scan_spectra(ijk, channel, 3, shape), expected, atol=1e-4)


def test_the_twin_rotations_of_a_room_view_are_its_box_twins_within_the_window() -> None:
    """twin_rotations: a view of a room with every wall, the floor and the ceiling overlaps the
    room's mixture about as well turned by any box twin, so all 23 are searched; a window
    keeps those within its angle of the start."""
    from scenes import box_room

    from kentreg_ros.core import make_transform
    from kentreg_ros.core.localization.twins import twin_rotations

    rng = np.random.default_rng(11)
    world = box_room(rng, 40_000, size=(10.0, 10.0, 10.0), boxes=0)
    cfg = KentRegConfig()
    pmap = PointMap.from_points(world, config=cfg, viewpoints=np.zeros((1, 3)))
    R = exp_so3([0.1, -0.2, 0.9])
    scan = prepare_scan(world @ R, config=cfg)  # R_map_scan = R, at the room's centre
    twins = twin_rotations(scan, pmap, R, cfg)
    assert len(twins) == 23
    turned = [Q @ R.T for Q in twins]  # each a box symmetry of the map
    assert all(np.allclose(np.sort(np.abs(Q), axis=1), [[0, 0, 1]] * 3, atol=0.1) for Q in turned)
    start = make_transform(R, [0.0, 0.0, 0.0])
    near = twin_rotations(scan, pmap, R, cfg, start=start, window=Window(1.0, 100.0))
    assert len(near) == 6  # the 90 deg turns about the room's three axes
    for Q in near:
        assert np.degrees(rotation_angle(Q.T @ R)) < 100.0


@pytest.mark.integration
@pytest.mark.skipif(not (LIVOX / 'quick_shack').is_dir(), reason='no Livox Avia keyframes')
@pytest.mark.parametrize('index', [45, 93, 173])
def test_a_narrow_scan_whose_rotations_missed_the_truth_is_localized(
    quick_shack: tuple, index: int
) -> None:
    """quick_shack keyframes from no start whose search rotations held only box twins of the
    truth (90 deg off; the truth's overlap ranked 10th-14th of its 24), not_found before the
    twins became rotation hypotheses: the truth's correlation peak outscores its twins'."""
    seq, pmap = quick_shack
    truth = seq.T_world[index]
    result = localize(seq.raw(index), pmap, config=KentRegConfig())
    assert result.localized, result.message
    assert result.T_map_scan is not None
    assert np.degrees(rotation_angle(result.T_map_scan[:3, :3].T @ truth[:3, :3])) < 2.0
    assert np.linalg.norm(result.T_map_scan[:3, 3] - truth[:3, 3]) < 0.5
