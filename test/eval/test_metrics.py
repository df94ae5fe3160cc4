"""Tests of kentreg_ros.eval.metrics and eval.kitti on synthetic trajectories with known errors."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kentreg_ros.core import DegenerateSceneError
from kentreg_ros.eval.alignment import align_umeyama, ate
from kentreg_ros.eval.kitti import (
    KITTI_LENGTHS,
    drift_per_metre,
    kitti_segment_errors,
    scaled_lengths,
)
from kentreg_ros.eval.metrics import (
    FAIL_ROTATION_DEG,
    FAIL_TRANSLATION_M,
    as_poses,
    failed_pairs,
    pair_errors,
    relative_poses,
    rotation_error_deg,
    rpe,
    rpe_per_metre,
    summarize,
    translation_error,
)


def make_poses(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = t
    return T


def random_poses(rng: np.random.Generator, n: int, spread: float = 10.0) -> np.ndarray:
    R = Rotation.random(n, random_state=rng).as_matrix()
    return make_poses(R, rng.uniform(-spread, spread, size=(n, 3)))


def random_walk(rng: np.random.Generator, n: int, step_m: float = 1.0) -> np.ndarray:
    """A planar-ish vehicle path: forward steps with small random turns, pitch and roll."""
    rpy = np.cumsum(rng.normal(0.0, [0.005, 0.005, 0.05], size=(n, 3)), axis=0)
    R = Rotation.from_euler('xyz', rpy).as_matrix()
    forward = R[:, :, 0] * rng.uniform(0.8 * step_m, 1.2 * step_m, size=(n, 1))
    t = np.concatenate(([np.zeros(3)], np.cumsum(forward[:-1], axis=0)))
    return make_poses(R, t)


def perturb_trajectory(rng: np.random.Generator, T_gt: np.ndarray) -> np.ndarray:
    """Integrate noisy relative motions: an estimate with drift, like odometry."""
    rel = np.linalg.inv(T_gt[:-1]) @ T_gt[1:]
    noise = make_poses(
        Rotation.from_rotvec(rng.normal(0.0, 0.002, size=(len(rel), 3))).as_matrix(),
        rng.normal(0.0, 0.02, size=(len(rel), 3)),
    )
    rel_est = rel @ noise
    T_est = [T_gt[0]]
    for T_prev_curr in rel_est:
        T_est.append(T_est[-1] @ T_prev_curr)
    return np.stack(T_est)


def straight_line(n: int, step_m: float) -> np.ndarray:
    t = np.zeros((n, 3))
    t[:, 0] = step_m * np.arange(n)
    return make_poses(np.eye(3), t)


# --------------------------------------------------------------------------------------------
# Per-pair errors


def test_rotation_error_of_axis_angle_perturbation_equals_angle() -> None:
    rng = np.random.default_rng(0)
    n = 200
    angles = np.concatenate(([1e-3, 0.5, 90.0, 179.0], rng.uniform(0.0, 179.0, n - 4)))
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    R_true = Rotation.random(n, random_state=rng).as_matrix()
    R_delta = Rotation.from_rotvec(np.radians(angles)[:, None] * axes).as_matrix()
    # Perturbing on either side gives the same angle.
    np.testing.assert_allclose(rotation_error_deg(R_true @ R_delta, R_true), angles, atol=1e-6)
    np.testing.assert_allclose(rotation_error_deg(R_delta @ R_true, R_true), angles, atol=1e-6)


def test_rotation_error_broadcasts_and_never_returns_nan() -> None:
    R = Rotation.random(5, random_state=1).as_matrix()
    e = rotation_error_deg(R, R[0])
    assert e.shape == (5,)
    assert e[0] == pytest.approx(0.0, abs=1e-6)
    # Round-off pushing the cosine slightly past 1 is clipped instead of giving NaN.
    assert rotation_error_deg(np.eye(3) * (1.0 + 1e-12), np.eye(3)) == 0.0
    assert rotation_error_deg(np.diag([1.0 - 1e-12, -1.0, -1.0]), np.eye(3)) == 180.0


def test_translation_error_is_euclidean_norm() -> None:
    e = translation_error([[3.0, 4.0, 0.0], [1.0, 1.0, 1.0]], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(e, [5.0, np.sqrt(3.0)])


def test_pair_errors_are_zero_on_identical_stacks() -> None:
    T = random_poses(np.random.default_rng(2), 50)
    e_R, e_t = pair_errors(T, T.copy())
    assert e_R.shape == e_t.shape == (50,)
    # arccos resolves angles near 0 to about sqrt(eps) rad, i.e. a few 1e-6 degrees.
    np.testing.assert_allclose(e_R, 0.0, atol=1e-5)
    np.testing.assert_array_equal(e_t, 0.0)


def test_pair_errors_of_known_perturbation() -> None:
    T_true = random_poses(np.random.default_rng(3), 4)
    T_est = T_true.copy()
    T_est[:, :3, :3] = T_true[:, :3, :3] @ Rotation.from_euler('z', 2.0, degrees=True).as_matrix()
    T_est[:, :3, 3] += [0.3, 0.0, 0.4]
    e_R, e_t = pair_errors(T_est, T_true)
    np.testing.assert_allclose(e_R, 2.0, atol=1e-9)
    np.testing.assert_allclose(e_t, 0.5, atol=1e-12)


# --------------------------------------------------------------------------------------------
# Trajectories


def test_failed_pairs_use_the_papers_thresholds_and_fail_nan() -> None:
    assert (FAIL_ROTATION_DEG, FAIL_TRANSLATION_M) == (2.0, 0.2)
    e_R = np.array([0.1, 2.0, 2.01, 0.1, np.nan, 0.1, np.inf])
    e_t = np.array([0.01, 0.2, 0.0, 0.21, 0.0, np.nan, 0.0])
    np.testing.assert_array_equal(
        failed_pairs(e_R, e_t), [False, False, True, True, True, True, True]
    )
    with pytest.raises(ValueError, match='broadcastable'):
        failed_pairs(np.zeros(3), np.zeros(2))


def test_relative_poses_chain_back_to_absolute_trajectory() -> None:
    T_world_lidar = random_poses(np.random.default_rng(4), 30)
    T_prev_curr = relative_poses(T_world_lidar)
    assert T_prev_curr.shape == (29, 4, 4)
    chained = [T_world_lidar[0]]
    for T in T_prev_curr:
        chained.append(chained[-1] @ T)
    np.testing.assert_allclose(np.stack(chained), T_world_lidar, atol=1e-9)


def test_relative_poses_map_current_points_into_previous_frame() -> None:
    T_world_lidar = random_poses(np.random.default_rng(5), 2)
    p_curr = np.array([1.0, -2.0, 3.0, 1.0])
    p_world = T_world_lidar[1] @ p_curr
    p_prev = relative_poses(T_world_lidar)[0] @ p_curr
    np.testing.assert_allclose(T_world_lidar[0] @ p_prev, p_world, atol=1e-9)


def test_summarize_reports_known_statistics() -> None:
    s = summarize(np.arange(1.0, 101.0))
    assert s['count'] == 100
    assert s['mean'] == pytest.approx(50.5)
    assert s['median'] == pytest.approx(50.5)
    assert s['rmse'] == pytest.approx(np.sqrt(np.mean(np.arange(1.0, 101.0) ** 2)))
    assert s['p95'] == pytest.approx(95.05)
    assert s['max'] == 100.0
    empty = summarize([])
    assert empty['count'] == 0 and np.isnan(empty['mean'])


def test_rpe_is_zero_for_a_rigidly_moved_trajectory() -> None:
    rng = np.random.default_rng(6)
    T_gt = random_walk(rng, 40)
    T_est = random_poses(rng, 1)[0] @ T_gt  # another world frame, same motion
    result = rpe(T_est, T_gt, delta=3)
    assert result['e_R_deg'].shape == result['e_t'].shape == (37,)
    assert result['rotation_deg']['max'] < 1e-5
    assert result['translation_m']['max'] < 1e-9


def test_rpe_per_metre_of_straight_line_with_scale_drift_gives_the_drift() -> None:
    T_gt = straight_line(50, step_m=1.0)
    T_est = straight_line(50, step_m=1.02)  # 2 % scale drift
    for delta in (1, 5):
        result = rpe_per_metre(T_est, T_gt, delta=delta)
        np.testing.assert_allclose(result['e_t_pct'], 2.0, rtol=1e-9)
        assert result['translation_pct']['mean'] == pytest.approx(2.0)
        assert result['n_skipped'] == 0
        np.testing.assert_allclose(result['distance_m'], float(delta))


def test_rpe_per_metre_skips_pairs_without_motion() -> None:
    T_gt = straight_line(10, step_m=1.0)
    T_gt[5:, :3, 3] = T_gt[4, :3, 3]  # stands still from frame 4 on
    T_est = T_gt.copy()
    T_est[:, 0, 3] *= 1.1
    result = rpe_per_metre(T_est, T_gt, min_distance=0.05)
    assert result['n_skipped'] == 5
    np.testing.assert_array_equal(result['index'], [0, 1, 2, 3])
    np.testing.assert_allclose(result['e_t_pct'], 10.0)


# --------------------------------------------------------------------------------------------
# Alignment and ATE


@pytest.mark.parametrize('with_scale', [False, True])
def test_umeyama_recovers_known_transform_from_noisy_points(with_scale: bool) -> None:
    rng = np.random.default_rng(7)
    R = Rotation.random(random_state=rng).as_matrix()
    t = rng.uniform(-20.0, 20.0, 3)
    scale = 2.5 if with_scale else 1.0
    src = rng.normal(0.0, 5.0, size=(300, 3))
    dst = scale * src @ R.T + t + rng.normal(0.0, 0.01, size=src.shape)
    T = align_umeyama(src, dst, with_scale=with_scale)
    scale_est = np.cbrt(np.linalg.det(T[:3, :3]))
    assert scale_est == pytest.approx(scale, rel=1e-3)
    assert rotation_error_deg(T[:3, :3] / scale_est, R) < 0.05
    np.testing.assert_allclose(T[:3, 3], t, atol=0.02)
    np.testing.assert_array_equal(T[3], [0.0, 0.0, 0.0, 1.0])


def test_umeyama_returns_a_proper_rotation_for_planar_points() -> None:
    rng = np.random.default_rng(8)
    src = np.column_stack((rng.uniform(-10, 10, size=(50, 2)), np.zeros(50)))
    R = Rotation.from_euler('zyx', [40.0, 10.0, -5.0], degrees=True).as_matrix()
    T = align_umeyama(src, src @ R.T + [1.0, 2.0, 3.0])
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    assert rotation_error_deg(T[:3, :3], R) < 1e-6


def test_umeyama_rejects_too_few_points() -> None:
    with pytest.raises(DegenerateSceneError, match='at least 3 points, got 2'):
        align_umeyama(np.zeros((2, 3)), np.zeros((2, 3)))


def test_ate_is_zero_for_rigidly_moved_ground_truth() -> None:
    rng = np.random.default_rng(9)
    T_gt = random_walk(rng, 60)
    T_world_gt = random_poses(rng, 1)[0]
    T_est = T_world_gt @ T_gt
    result = ate(T_est, T_gt)
    assert result['rmse'] < 1e-9
    assert result['count'] == 60
    # The alignment undoes the rigid motion: T_gt_est = T_world_gt^-1.
    np.testing.assert_allclose(result['T_gt_est'], np.linalg.inv(T_world_gt), atol=1e-9)
    assert ate(T_est, T_gt, align=False)['rmse'] > 1.0


def test_ate_without_alignment_equals_constant_offset() -> None:
    T_gt = random_walk(np.random.default_rng(10), 30)
    T_est = T_gt.copy()
    T_est[:, :3, 3] += [0.6, -0.8, 0.0]
    unaligned = ate(T_est, T_gt, align=False)
    np.testing.assert_allclose(unaligned['errors'], 1.0)
    assert unaligned['rmse'] == pytest.approx(1.0)
    assert ate(T_est, T_gt)['rmse'] < 1e-9


def test_ate_after_alignment_equals_known_radial_offset() -> None:
    # Ground truth on a circle of radius 10, estimate on a concentric circle of radius 10.5
    # seen from another world frame: the best SE(3) alignment is the concentric one, so every
    # position is off by exactly 0.5 m; Sim(3) alignment removes the error.
    rng = np.random.default_rng(11)
    theta = np.linspace(0.0, 2.0 * np.pi, 72, endpoint=False)
    circle = np.column_stack((np.cos(theta), np.sin(theta), np.zeros_like(theta)))
    T_gt = make_poses(np.eye(3), 10.0 * circle)
    T_world_gt = random_poses(rng, 1)[0]
    T_est = T_world_gt @ make_poses(np.eye(3), 10.5 * circle)
    result = ate(T_est, T_gt)
    np.testing.assert_allclose(result['errors'], 0.5, atol=1e-9)
    assert result['rmse'] == pytest.approx(0.5) and result['max'] == pytest.approx(0.5)
    sim3 = ate(T_est, T_gt, with_scale=True)
    assert sim3['rmse'] < 1e-9
    assert sim3['scale'] == pytest.approx(10.0 / 10.5)


# --------------------------------------------------------------------------------------------
# KITTI


def kitti_reference(
    T_est: np.ndarray, T_gt: np.ndarray, lengths: tuple[float, ...], step: int = 10
) -> tuple[float, float, int]:
    """Slow transcription of the devkit's calcSequenceErrors + saveStats (plain loops)."""
    dist = [0.0]
    for i in range(1, len(T_gt)):
        dist.append(dist[-1] + float(np.linalg.norm(T_gt[i, :3, 3] - T_gt[i - 1, :3, 3])))
    t_sum, r_sum, count = 0.0, 0.0, 0
    for first in range(0, len(T_gt), step):
        for length in lengths:
            last = -1
            for i in range(first, len(dist)):
                if dist[i] > dist[first] + length:
                    last = i
                    break
            if last == -1:
                continue
            delta_gt = np.linalg.inv(T_gt[first]) @ T_gt[last]
            delta_est = np.linalg.inv(T_est[first]) @ T_est[last]
            pose_error = np.linalg.inv(delta_est) @ delta_gt
            d = 0.5 * (pose_error[0, 0] + pose_error[1, 1] + pose_error[2, 2] - 1.0)
            r_err = np.arccos(max(min(d, 1.0), -1.0))
            t_err = np.linalg.norm(pose_error[:3, 3])
            t_sum += t_err / length
            r_sum += r_err / length
            count += 1
    return 100.0 * t_sum / count, np.degrees(r_sum / count), count


def test_kitti_returns_none_when_run_is_shorter_than_shortest_segment() -> None:
    T_gt = straight_line(51, step_m=1.0)  # 50 m
    assert kitti_segment_errors(T_gt, T_gt) is None
    # The devkit needs the distance to exceed the length strictly.
    T_gt = straight_line(101, step_m=1.0)  # exactly 100 m
    assert kitti_segment_errors(T_gt, T_gt) is None


def test_kitti_with_short_custom_lengths_gives_finite_errors() -> None:
    rng = np.random.default_rng(12)
    T_gt = random_walk(rng, 51)  # about 50 m
    T_est = perturb_trajectory(rng, T_gt)
    assert kitti_segment_errors(T_est, T_gt) is None
    result = kitti_segment_errors(T_est, T_gt, lengths=(5, 10, 20, 40))
    assert result is not None
    assert np.isfinite(result['t_err_pct']) and result['t_err_pct'] > 0.0
    assert np.isfinite(result['r_err_deg_per_m']) and result['r_err_deg_per_m'] > 0.0
    assert set(result['per_length']) == {5.0, 10.0, 20.0, 40.0}
    assert result['n_segments'] == sum(r['n_segments'] for r in result['per_length'].values())


def test_kitti_of_straight_line_with_scale_drift_follows_devkit_segments() -> None:
    # 3 % scale drift at 1 m per frame. The devkit ends a segment of length L at the first frame
    # *beyond* L (here L + 1 m away) but divides by L: L=10 gives 3.3 % on 5 segments (first
    # frames 0..40), L=20 gives 3.15 % on 4 segments (first frames 0..30).
    result = kitti_segment_errors(straight_line(60, 1.03), straight_line(60, 1.0), (10, 20))
    assert result is not None
    assert result['per_length'][10.0] == pytest.approx(
        {'n_segments': 5, 't_err_pct': 3.3, 'r_err_deg_per_m': 0.0}, abs=1e-9
    )
    assert result['per_length'][20.0]['t_err_pct'] == pytest.approx(3.15)
    assert result['n_segments'] == 9
    assert result['t_err_pct'] == pytest.approx((5 * 3.3 + 4 * 3.15) / 9)
    np.testing.assert_array_equal(result['first_frame'], [0, 10, 20, 30, 40, 0, 10, 20, 30])
    np.testing.assert_array_equal(
        result['last_frame'] - result['first_frame'], [11] * 5 + [21] * 4
    )


@pytest.mark.parametrize(
    ('n_frames', 'lengths'), [(900, KITTI_LENGTHS), (90, (5.0, 10.0, 20.0, 40.0))]
)
def test_kitti_matches_slow_devkit_reference_on_noisy_random_walk(
    n_frames: int, lengths: tuple[float, ...]
) -> None:
    rng = np.random.default_rng(13)
    T_gt = random_walk(rng, n_frames)
    T_est = perturb_trajectory(rng, T_gt)
    result = kitti_segment_errors(T_est, T_gt, lengths=lengths)
    assert result is not None
    t_ref, r_ref, count_ref = kitti_reference(T_est, T_gt, lengths)
    assert result['n_segments'] == count_ref
    assert result['t_err_pct'] == pytest.approx(t_ref, rel=1e-9)
    assert result['r_err_deg_per_m'] == pytest.approx(r_ref, rel=1e-7)


# --------------------------------------------------------------------------------------------
# Validation


@pytest.mark.parametrize(
    ('call', 'match'),
    [
        (
            lambda: pair_errors(np.eye(3), np.eye(4)[None]),
            r'^Expected `T_est` to have shape \(N, 4, 4\), got \(3, 3\)\.$',
        ),
        (lambda: pair_errors(np.eye(4)[None], np.eye(3)[None]), r'`T_true`.*got \(1, 3, 3\)'),
        (lambda: pair_errors(np.eye(4), np.eye(4)[None]), r'`T_est`.*\(N, 4, 4\), got \(4, 4\)'),
        (lambda: relative_poses(np.eye(3)), r'`T_world_sensor`.*\(N, 4, 4\), got \(3, 3\)\.'),
        (lambda: relative_poses(np.eye(4)[None]), r'at least 2 pose\(s\), got 1'),
        (
            lambda: rotation_error_deg(np.eye(3), np.eye(4)),
            r'`R_true`.*\(\.\.\., 3, 3\).*\(4, 4\)',
        ),
        (lambda: rotation_error_deg(np.zeros((2, 3, 3)), np.zeros((3, 3, 3))), 'broadcastable'),
        (lambda: translation_error(np.zeros(2), np.zeros(3)), r'`t_est`.*\(\.\.\., 3\)'),
        (lambda: align_umeyama(np.zeros((5, 2)), np.zeros((5, 3))), r'`src`.*\(N, 3\)'),
        (lambda: align_umeyama(np.zeros((5, 3)), np.zeros((4, 3))), 'same number of points'),
        (lambda: ate(np.tile(np.eye(4), (3, 1, 1)), np.tile(np.eye(4), (4, 1, 1))), '3 and 4'),
        (lambda: rpe(np.tile(np.eye(4), (3, 1, 1)), np.tile(np.eye(4), (3, 1, 1)), 3), 'delta'),
        (lambda: rpe(np.tile(np.eye(4), (3, 1, 1)), np.tile(np.eye(4), (3, 1, 1)), 0), 'delta'),
        (
            lambda: kitti_segment_errors(np.tile(np.eye(4), (3, 1, 1)), np.eye(4)[None]),
            'same number of poses',
        ),
        (lambda: kitti_segment_errors(np.eye(4)[None], np.eye(4)[None], ()), 'non-empty'),
        (lambda: kitti_segment_errors(np.eye(4)[None], np.eye(4)[None], (10, -1)), 'positive'),
        (lambda: kitti_segment_errors(np.eye(4)[None], np.eye(4)[None], (5, 5)), 'distinct'),
        (lambda: kitti_segment_errors(np.eye(4)[None], np.eye(4)[None], step=0), '`step`'),
        (lambda: summarize([1.0, np.nan]), 'NaN or inf'),
    ],
)
def test_bad_inputs_raise_value_error_with_message(call: Callable[[], object], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        call()


def test_as_poses_rejects_nonfinite_and_transposed_matrices() -> None:
    T = np.tile(np.eye(4), (5, 1, 1))
    T[3, 0, 3] = np.nan
    with pytest.raises(ValueError, match=r'`T_est` has 1 pose\(s\) with NaN.*at index 3\)'):
        as_poses(T, 'T_est')
    T = np.tile(np.eye(4), (5, 1, 1))
    T[2, :3, 3] = [1.0, 2.0, 3.0]
    with pytest.raises(ValueError, match=r'last row of every `T_gt`.*index 2 \(transposed'):
        as_poses(T.transpose(0, 2, 1), 'T_gt')
    with pytest.raises(ValueError, match='Expected `T_est` to have shape \\(N, 4, 4\\), got'):
        as_poses([[1, 2], [3, 4]], 'T_est')


def test_scaled_lengths_keep_kittis_proportions_below_1600_m() -> None:
    assert scaled_lengths(5000.0) == KITTI_LENGTHS
    assert scaled_lengths(1600.0) == pytest.approx(KITTI_LENGTHS)
    short = scaled_lengths(9.75)
    assert short[-1] == pytest.approx(9.75 / 2.0)
    assert np.allclose(np.array(short) / short[0], np.array(KITTI_LENGTHS) / KITTI_LENGTHS[0])


def test_drift_per_metre_of_a_scale_drift_on_a_short_run() -> None:
    # 3 % scale drift on a 59 m line: every segment is 3 % off in translation, whatever its
    # length (the devkit's "first frame beyond L" adds 1 m / L), no rotation error.
    drift = drift_per_metre(straight_line(60, 1.03), straight_line(60, 1.0))
    assert drift is not None
    assert drift['lengths_m'] == pytest.approx(scaled_lengths(59.0))
    assert drift['n_segments'] > 8 * 30
    assert 3.0 < drift['translation_pct'] < 3.0 * (1.0 + 1.0 / drift['lengths_m'][0])
    assert drift['rotation_deg_per_m'] == pytest.approx(0.0, abs=1e-9)
    assert drift_per_metre(straight_line(60, 1.0), straight_line(60, 1.0))['translation_pct'] == (
        pytest.approx(0.0, abs=1e-9)
    )
    stand_still = np.repeat(np.eye(4)[None], 5, axis=0)
    assert drift_per_metre(stand_still, stand_still) is None
