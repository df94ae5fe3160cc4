"""Tests of kentreg_ros.core.odometry.localmap and of the odometry's ``local_map`` model."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_odometry import STEP_NS, healths, observe, run, true_trajectory

from kentreg_ros.core import (
    InvalidInputError,
    InvalidPointCloudError,
    KentRegConfig,
    Odometry,
    invert_transform,
    prepare_scan,
    register,
    rotation_angle,
)
from kentreg_ros.core.odometry.localmap import LocalMap, VoxelMap, nearest_spacing
from kentreg_ros.eval.metrics import rpe

LOCAL_MAP = KentRegConfig().with_updates({'odometry.model': 'local_map'})


def test_voxel_map_keeps_the_first_points_of_each_voxel_up_to_its_cap() -> None:
    rng = np.random.default_rng(0)
    voxel, cap = 0.5, 3
    vmap = VoxelMap(voxel, max_points_per_voxel=cap)
    first = rng.uniform(-2.0, 2.0, (2000, 3))
    second = rng.uniform(-2.0, 2.0, (2000, 3))
    added = vmap.insert(first) + vmap.insert(second)
    assert added == len(vmap)
    # Brute force: per voxel, the first `cap` points of the concatenated stream.
    stream = np.concatenate([first, second])
    cells = np.floor(stream / voxel).astype(int)
    _, inverse = np.unique(cells, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    rank = np.array([np.count_nonzero(inverse[:i] == inverse[i]) for i in range(len(stream))])
    expected = stream[rank < cap]
    assert vmap.n_voxels == len(np.unique(inverse))
    np.testing.assert_array_equal(
        np.sort(vmap.points.view('f8,f8,f8'), axis=0), np.sort(expected.view('f8,f8,f8'), axis=0)
    )
    # A voxel never holds more than `cap` points, however often it is filled again.
    vmap.insert(first)
    counts = np.unique(np.floor(vmap.points / voxel), axis=0, return_counts=True)[1]
    assert counts.max() == cap
    full = VoxelMap(voxel, max_points_per_voxel=1)
    full.insert(first)
    assert full.insert(first) == 0


def test_voxel_map_crop_drops_points_beyond_the_radius_and_frees_their_voxels() -> None:
    rng = np.random.default_rng(1)
    vmap = VoxelMap(0.2)
    points = rng.uniform(-10.0, 10.0, (5000, 3))
    vmap.insert(points)
    n_before = len(vmap)
    center = np.array([1.0, -2.0, 0.5])
    removed = vmap.crop(center, 4.0)
    assert removed > 0 and len(vmap) == n_before - removed
    assert np.all(np.linalg.norm(vmap.points - center, axis=1) <= 4.0)
    # The freed voxels take points again.
    far = np.array([[9.9, 9.9, 9.9]])
    assert vmap.insert(far) == 1
    # With several points per voxel a crop through a voxel keeps its count exact: refilled
    # densely, every voxel holds exactly its cap again (a count left too high would hold back
    # points, one too low would let a voxel overflow).
    cap, voxel = 3, 0.5
    dense = VoxelMap(voxel, max_points_per_voxel=cap)
    dense.insert(rng.uniform(-3.0, 3.0, (4000, 3)))
    dense.crop(np.zeros(3), 2.0)
    dense.insert(rng.uniform(-3.0, 3.0, (40000, 3)))
    counts = np.unique(np.floor(dense.points / voxel), axis=0, return_counts=True)[1]
    assert counts.min() == counts.max() == cap
    assert dense.n_voxels == len(counts)


def test_averaging_voxel_map_keeps_the_running_mean_of_each_voxel() -> None:
    vmap = VoxelMap(1.0, with_normals=True, average=True)
    up, tilted = np.array([0.0, 0.0, 1.0]), np.array([0.6, 0.0, 0.8])
    # Two points in voxel (0, 0, 0) in one insertion, one in (2, 0, 0).
    assert vmap.insert([[0.1, 0.2, 0.3], [0.3, 0.4, 0.5], [2.5, 0.5, 0.5]], [up, up, up]) == 2
    np.testing.assert_allclose(vmap.points[0], [0.2, 0.3, 0.4], rtol=0, atol=1e-15)
    # A later point merges; its normal, pointing the other way, is turned to agree first.
    assert vmap.insert([[0.5, 0.0, 0.1]], [-tilted]) == 0
    np.testing.assert_allclose(vmap.points[0], [0.3, 0.2, 0.3], rtol=0, atol=1e-15)
    expected = (2 * up + tilted) / np.linalg.norm(2 * up + tilted)
    np.testing.assert_allclose(vmap.normals[0], expected, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(vmap.points[1], [2.5, 0.5, 0.5])  # untouched
    assert len(vmap) == 2 and vmap.n_voxels == 2


def test_averaging_voxel_map_merges_into_the_nearest_point_and_survives_crops() -> None:
    vmap = VoxelMap(1.0, max_points_per_voxel=2, average=True)
    vmap.insert([[0.1, 0.1, 0.1], [0.9, 0.9, 0.9], [5.5, 0.5, 0.5]])
    vmap.insert([[0.2, 0.1, 0.1], [0.8, 0.9, 0.9], [0.7, 0.7, 0.7]])
    np.testing.assert_allclose(vmap.points[0], [0.15, 0.1, 0.1], rtol=0, atol=1e-15)
    np.testing.assert_allclose(vmap.points[1], [0.8, 0.8333333333333334, 0.8333333333333334])
    # Cropping drops the far voxel; the sums of the kept points stay theirs.
    assert vmap.crop(np.zeros(3), 3.0) == 1
    vmap.insert([[0.3, 0.1, 0.1]])
    np.testing.assert_allclose(vmap.points[0], [0.2, 0.1, 0.1], rtol=0, atol=1e-15)
    assert len(vmap) == 2 and vmap.n_voxels == 1
    # The default map drops what does not fit instead.
    plain = VoxelMap(1.0)
    plain.insert([[0.1, 0.1, 0.1]])
    assert plain.insert([[0.9, 0.9, 0.9]]) == 0
    np.testing.assert_array_equal(plain.points, [[0.1, 0.1, 0.1]])


def test_averaging_map_holds_a_resampled_noisy_surface_closer_than_one_scan() -> None:
    # Ten noisy samplings of the plane z = 0.1 (1 cm along z), in the middle of a layer of
    # 0.2 m voxels: the averaged map's points lie about 1/sqrt(samples) as far from the plane as
    # one scan's, which the first-wins map keeps. (A surface on a voxel face would be split in
    # two layers at about +-0.8 sigma, the means of the noise on either side.)
    rng = np.random.default_rng(5)
    maps = {avg: VoxelMap(0.2, with_normals=True, average=avg) for avg in (False, True)}
    for _ in range(10):
        pts = np.column_stack([rng.uniform(-3, 3, (4000, 2)), rng.normal(0.1, 0.01, 4000)])
        nrm = np.tile([0.0, 0.0, 1.0], (4000, 1)) + rng.normal(0.0, 0.05, (4000, 3))
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        for vmap in maps.values():
            vmap.insert(pts, nrm)
    rms = {avg: float(np.sqrt(np.mean((m.points[:, 2] - 0.1) ** 2))) for avg, m in maps.items()}
    assert len(maps[True]) == len(maps[False])
    assert rms[True] < 0.5 * rms[False]
    tilt = {avg: float(np.median(np.abs(m.normals[:, :2]))) for avg, m in maps.items()}
    assert tilt[True] < 0.5 * tilt[False]


def test_voxel_map_rejects_bad_input() -> None:
    with pytest.raises(InvalidInputError, match='voxel_size'):
        VoxelMap(0.0)
    with pytest.raises(InvalidInputError, match='max_points_per_voxel'):
        VoxelMap(1.0, max_points_per_voxel=0)
    with pytest.raises(InvalidInputError, match='normals'):
        VoxelMap(1.0, with_normals=True).insert(np.zeros((3, 3)))
    with pytest.raises(InvalidInputError, match='no normals'):
        VoxelMap(1.0).insert(np.zeros((3, 3)), np.ones((3, 3)))
    far = VoxelMap(0.01)  # beyond the keys' reach: dropped and counted, not raised
    assert far.insert(np.array([[1e5, 0.0, 0.0]])) == 0 and far.n_out_of_reach == 1
    with pytest.raises(InvalidPointCloudError, match=r'shape \(N, 3\)'):
        VoxelMap(1.0).insert(np.zeros((3, 2)))


def test_local_map_memory_is_bounded_by_its_radius_not_the_run_length() -> None:
    """A sensor driving 120 m down an endless corridor: the map stops growing once the
    corridor behind it leaves the radius."""
    rng = np.random.default_rng(2)
    radius = 10.0
    lmap = LocalMap(0.25, max_points_per_voxel=1)
    sizes = []
    cfg = KentRegConfig()
    for i in range(120):
        T = np.eye(4)
        T[0, 3] = float(i)  # 1 m per scan along x
        # Walls y = +-2, floor z = -1, seen from the sensor out to 12 m ahead and behind.
        x = rng.uniform(-12.0, 12.0, 6000)
        side = rng.integers(0, 3, 6000)
        pts = np.stack([x, rng.uniform(-2.0, 2.0, 6000), rng.uniform(-1.0, 2.0, 6000)], axis=1)
        pts[side == 0, 1] = -2.0
        pts[side == 1, 1] = 2.0
        pts[side == 2, 2] = -1.0
        scan = prepare_scan(pts, config=cfg)
        lmap.insert_scan(scan, T, radius=radius)
        sizes.append(len(lmap))
        assert np.all(np.linalg.norm(lmap.points - T[:3, 3], axis=1) <= radius + 1e-9)
    # Steady state: the last 60 scans hold as many points as the ball allows, no more.
    assert max(sizes[60:]) <= 1.1 * min(sizes[60:])
    assert max(sizes) < 2.0 * sizes[15]
    # The map spans one radius of corridor on each side of the sensor.
    assert np.ptp(lmap.points[:, 0]) <= 2 * radius + 1e-9


def test_local_map_target_is_the_map_in_the_given_frame() -> None:
    rng = np.random.default_rng(3)
    T_true = true_trajectory(2)
    cfg = KentRegConfig()
    scan = prepare_scan(observe(rng, T_true[0]), config=cfg)
    lmap = LocalMap(scan.voxel_size or nearest_spacing(scan.points), max_points_per_voxel=1)
    lmap.insert_scan(scan, T_true[0], radius=100.0)
    target = lmap.target(T_true[1], rotation_model=scan, config=cfg)
    # The map holds one point per voxel, the mean of the scan's points posed in the world in
    # that voxel ...
    in_world = scan.points @ T_true[0][:3, :3].T + T_true[0][:3, 3]
    keys = lmap.voxels.keys_of(in_world)
    unique, inverse = np.unique(keys, return_inverse=True)
    means = (
        np.stack([np.bincount(inverse, weights=in_world[:, k]) for k in range(3)], axis=1)
        / np.bincount(inverse)[:, None]
    )
    assert 0 < len(lmap) == len(unique) <= len(scan)
    order = np.argsort(lmap.voxels.keys_of(lmap.points))
    np.testing.assert_allclose(lmap.points[order], means, rtol=0, atol=1e-12)
    # ... and the target is the map in frame 1: p_1 = T_1^-1 p_w.
    T_1w = invert_transform(T_true[1])
    np.testing.assert_allclose(target.points, lmap.points @ T_1w[:3, :3].T + T_1w[:3, 3])
    np.testing.assert_allclose(np.linalg.norm(target.normals, axis=1), 1.0)
    assert target.voxel_size == lmap.voxel_size
    # Its normals' mixture is the given scan's (already in frame 1 in the odometry), each map
    # point labelled with the nearest of its centres.
    assert target.clusters is scan.clusters
    np.testing.assert_array_equal(target.centers, scan.centers)
    assert np.array_equal(target.labels, np.argmax(target.normals @ scan.centers.T, axis=1))
    # A scan taken at pose 1 registers against it from identity to the true motion (identity).
    source = prepare_scan(observe(rng, T_true[1]), config=cfg)
    result = register(source, target, init=np.eye(4), config=cfg, global_search=False)
    assert np.degrees(rotation_angle(result.T_target_source[:3, :3])) < 0.1
    assert np.linalg.norm(result.T_target_source[:3, 3]) < 0.01
    with pytest.raises(InvalidPointCloudError, match='map points'):
        LocalMap(0.1, max_points_per_voxel=1).target(np.eye(4), rotation_model=scan, config=cfg)


def test_local_map_odometry_recovers_known_trajectory() -> None:
    rng = np.random.default_rng(7)
    T_true = true_trajectory(8)
    clouds = [observe(rng, T_i) for T_i in T_true]
    odom = Odometry(LOCAL_MAP, initial_pose=T_true[0])
    steps = run(odom, clouds)
    assert healths(steps) == ['first'] + ['ok'] * 7
    errors = rpe(odom.poses, T_true)
    assert errors['rotation_deg']['max'] < 0.1
    assert errors['translation_m']['max'] < 0.01
    np.testing.assert_allclose(odom.poses[:, :3, 3], T_true[:, :3, 3], atol=0.02)
    lmap = odom.local_map
    assert lmap is not None and len(lmap) > 0
    # Every accepted scan is in the map; the model is the map in the last pose's frame.
    assert [s.model_index for s in steps] == [-1, *range(7)]
    # Each step ran the map's upkeep and timed its parts.
    upkeep = {'model.map_insert', 'model.map_frame', 'model.map_tree'}
    assert all(upkeep <= set(s.timings) for s in steps)
    # The room is 20 x 14 m: the map radius (the reach of the last scan) keeps it whole, and
    # the map is denser than one scan but bounded by the voxel count, not by 8 scans.
    assert len(lmap) < 8 * steps[-1].n_prepared
    # Its voxel is the first scan's spacing (odometry.map_voxel_size = 0; this room is sparse
    # enough to be used as given, so its points' own spacing); an explicit size is kept.
    first = prepare_scan(clouds[0], config=LOCAL_MAP)
    assert lmap.voxel_size == pytest.approx(first.voxel_size or nearest_spacing(first.points))
    fixed = Odometry(LOCAL_MAP.with_updates({'odometry.map_voxel_size': 0.3}))
    run(fixed, clouds[:2])
    assert fixed.local_map is not None and fixed.local_map.voxel_size == 0.3


def test_local_map_leaves_fallen_back_and_rejected_scans_out() -> None:
    rng = np.random.default_rng(8)
    T_true = true_trajectory(6)
    clouds = [observe(rng, T_i) for T_i in T_true]
    clouds[2] = clouds[2][:5]  # rejected: too few points
    odom = Odometry(LOCAL_MAP, initial_pose=T_true[0])
    steps = run(odom, clouds[:2])
    lmap = odom.local_map
    assert lmap is not None
    before = lmap.points.copy()
    steps.append(odom.step(clouds[2], 2 * STEP_NS))
    assert steps[-1].health == 'rejected'
    assert not any(k.startswith('model.') for k in steps[-1].timings)  # no upkeep ran
    np.testing.assert_array_equal(lmap.points, before)
    # An implausible limit makes the next steps fall back: the map does not change either.
    odom.reconfigure(LOCAL_MAP.with_updates({'odometry.max_angular_speed_deg': 1.0}))
    for i in (3, 4):
        steps.append(odom.step(clouds[i], i * STEP_NS))
        assert steps[-1].health == 'fell_back'
        np.testing.assert_array_equal(odom.local_map.points, before)  # type: ignore[union-attr]
    # Back to sane limits: scan 5 is registered against the map from the last accepted pose
    # (scan 1), across the gap, and enters the map.
    odom.reconfigure(LOCAL_MAP)
    last = odom.step(clouds[5], 5 * STEP_NS)
    assert last.ok and last.model_index == 1
    assert len(odom.local_map) > len(before)  # type: ignore[arg-type]
    e_R = np.degrees(rotation_angle(T_true[5][:3, :3].T @ last.T_world_lidar[:3, :3]))
    assert e_R < 0.2
    np.testing.assert_allclose(last.T_world_lidar[:3, 3], T_true[5][:3, 3], atol=0.03)


def test_previous_scan_model_keeps_no_map() -> None:
    rng = np.random.default_rng(9)
    T_true = true_trajectory(3)
    odom = Odometry(KentRegConfig(), initial_pose=T_true[0])
    run(odom, [observe(rng, T_i) for T_i in T_true])
    assert odom.local_map is None


def test_local_map_on_the_sample_bag_tracks_without_failures(repo_root: Path) -> None:
    """Real scans (BALM, 2 Hz, rotation-heavy hand-held motion): 20 scans against the map."""
    bag = repo_root / 'bags' / 'balm_50'
    if not bag.exists():
        pytest.skip('bags/balm_50 is absent')
    from kentreg_ros.eval.alignment import ate
    from kentreg_ros.eval.groundtruth import associate
    from kentreg_ros.io.recordings import open_recording

    recording = open_recording(bag)
    assert recording.reference is not None
    odom = Odometry(LOCAL_MAP)
    for i, scan in enumerate(recording.source):
        if i == 20:
            break
        step = odom.step(scan.points, scan.stamp_ns)
        assert step.ok, step.message
        reach_last = float(np.linalg.norm(scan.points, axis=1).max())
    rows, gt_rows = associate(odom.stamps_ns, range(20), recording.reference)
    assert len(rows) == 20
    T_gt = recording.reference.T_world_sensor[gt_rows]
    errors = rpe(odom.poses, T_gt)
    # The reference is good to ~0.04 deg / 4 mm per pair (see ../shared/data/README.md).
    assert errors['rotation_deg']['max'] < 0.3
    assert errors['translation_m']['max'] < 0.03
    assert ate(odom.poses, T_gt)['rmse'] < 0.03
    lmap = odom.local_map
    assert lmap is not None
    reach = np.linalg.norm(lmap.points - odom.poses[-1][:3, 3], axis=1)
    # The radius (the last scan's reach) bounds the map.
    assert reach.max() <= reach_last + 1e-6


def test_local_map_keeps_tracking_with_raw_outliers_and_skipped_frames(repo_root: Path) -> None:
    """The previous-scan model's robustness carries over: every 2nd sample scan (up to ~50 deg
    between them) with clutter added to each raw cloud, uniform in its bounding box, before any
    preprocessing: 40 % of the contaminated cloud."""
    bag = repo_root / 'bags' / 'balm_50'
    if not bag.exists():
        pytest.skip('bags/balm_50 is absent')
    from kentreg_ros.eval.groundtruth import associate
    from kentreg_ros.eval.metrics import failed_pairs, pair_errors, relative_poses
    from kentreg_ros.io.recordings import open_recording

    recording = open_recording(bag)
    assert recording.reference is not None
    rng = np.random.default_rng(4)
    odom = Odometry(LOCAL_MAP)
    used = []
    for i, scan in enumerate(recording.source):
        if i % 2 or i >= 30:
            continue
        pts = scan.points
        clutter = rng.uniform(pts.min(axis=0), pts.max(axis=0), size=(len(pts) * 2 // 3, 3))
        step = odom.step(np.vstack([pts, clutter]), scan.stamp_ns)
        assert step.ok, step.message
        used.append(i)
    rows, gt_rows = associate(odom.stamps_ns, used, recording.reference)
    assert len(rows) == len(used) == 15
    T_gt = recording.reference.T_world_sensor[gt_rows]
    e_R, e_t = pair_errors(relative_poses(odom.poses), relative_poses(T_gt))
    assert not failed_pairs(e_R, e_t).any()
    # Clean consecutive pairs are good to ~0.04 deg / 4 mm (the reference's own level).
    assert np.median(e_R) < 0.2 and np.median(e_t) < 0.02


@pytest.mark.parametrize('cap', [1, 3])
def test_voxel_map_key_order_kept_through_inserts_and_crops_is_a_stable_sort(cap: int) -> None:
    """The key order the map keeps up to date (instead of sorting every merge) is at every
    step the stable argsort of its points' keys, so merges find the same points as before."""
    rng = np.random.default_rng(4)
    vmap = VoxelMap(0.3, max_points_per_voxel=cap, with_normals=True, average=True)
    for i in range(12):
        pts = rng.uniform(-3.0, 3.0, (800, 3)) + [0.4 * i, 0.0, 0.0]
        nrm = rng.normal(size=(800, 3))
        vmap.insert(pts, nrm / np.linalg.norm(nrm, axis=1, keepdims=True))
        vmap.crop([0.4 * i, 0.0, 0.0], 3.5)
        keys = vmap.keys_of(np.asarray(vmap._sums / vmap._merged[:, None]))
        assert np.array_equal(vmap._order, np.argsort(vmap._keys, kind='stable'))
        assert np.array_equal(vmap._sorted_keys, vmap._keys[vmap._order])
        # Averaging keeps every point in the voxel it was first put in.
        assert np.array_equal(keys, vmap._keys)


def test_local_map_target_neighbours_are_exact_against_brute_force(repo_root: Path) -> None:
    """After incremental insertions and crops, the target's neighbour answers (what the
    registration queries: nearest two within a gate) are those of a brute-force search over
    the map points in the target frame."""
    pytest.importorskip('rosbags', reason='rosbags is not installed (pip install -e .[io])')
    from kentreg_ros.io import open_scan_source

    source = open_scan_source(repo_root / 'bags' / 'balm_50')
    sample_scans = [s.points for _, s in zip(range(4), source, strict=False)]
    lmap = LocalMap(0.2, max_points_per_voxel=1)
    T = np.eye(4)
    for i, points in enumerate(sample_scans):
        T[:3, 3] = [0.05 * i, 0.0, 0.0]
        scan = prepare_scan(points, config=LOCAL_MAP)
        lmap.insert_scan(scan, T, radius=15.0)
    target = lmap.target(T, rotation_model=scan, config=LOCAL_MAP)
    rng = np.random.default_rng(1)
    queries = target.points[rng.choice(len(target), 300)] + rng.normal(0.0, 0.1, (300, 3))
    gate = 0.3
    dist, idx = target.tree.query(queries, k=2, distance_upper_bound=gate)
    brute = np.linalg.norm(queries[:, None, :] - target.points[None, :, :], axis=2)
    order = np.argsort(brute, axis=1)[:, :2]
    want = np.take_along_axis(brute, order, axis=1)
    within = want <= gate
    assert np.allclose(np.where(within, want, np.inf), dist, rtol=0, atol=1e-12)
    assert np.array_equal(np.where(within, order, len(target)), idx)
