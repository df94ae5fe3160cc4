"""benchmarks/harness/simulator.py, simulated.py: re-simulated sequences, exact poses.

The simulated sensor is checked on a synthetic room (points on the surfaces within the range
noise, occluded points hidden), the trajectory against its definition, and the whole chain on
the sample's scene: kentreg's odometry on three simulated scans agrees with the exact poses.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from benchmarks.harness import report  # noqa: E402
from benchmarks.harness.simulator import (  # noqa: E402
    Sensor,
    World,
    build_world,
    motion_stats,
    simulate,
    simulate_scan,
    trajectory,
)
from benchmarks.simulated import OPTIONS, format_table, run, summarize_step  # noqa: E402
from kentreg_ros.core import (  # noqa: E402
    Odometry,  # noqa: E402
    exp_so3,
    make_transform,
)
from kentreg_ros.core.odometry import deskew as odometry_module  # noqa: E402
from kentreg_ros.core.odometry.deskew import deskew  # noqa: E402
from kentreg_ros.eval import run_odometry  # noqa: E402
from kentreg_ros.eval.metrics import rpe  # noqa: E402
from kentreg_ros.io import open_recording  # noqa: E402

BAG = REPO_ROOT / 'bags' / 'balm_50'


def _grid_wall(x: float, y: tuple[float, float], z: tuple[float, float], h: float) -> np.ndarray:
    """Points of the plane ``X = x`` every ``h`` metres over the given y and z spans."""
    ys, zs = np.meshgrid(np.arange(*y, h), np.arange(*z, h))
    return np.column_stack([np.full(ys.size, x), ys.ravel(), zs.ravel()])


def test_scan_points_lie_on_the_world_within_the_range_noise() -> None:
    world = _grid_wall(6.0, (-5.0, 5.0), (-3.0, 3.0), 0.02)
    T = make_transform(exp_so3(np.array([0.0, 0.0, 0.3])), np.array([0.5, -0.2, 0.1]))
    sensor = Sensor(range_noise=0.01)
    q, times = simulate_scan(world, T, np.random.default_rng(0), sensor)
    assert not times.any()  # no sweep: every point at the stamp
    p = q @ T[:3, :3].T + T[:3, 3]
    assert len(p) > 1000
    # Noise along the ray: the distance to the plane is at most the range error, 5 sigma.
    assert np.abs(p[:, 0] - 6.0).max() < 5 * sensor.range_noise
    assert abs(np.std(p[:, 0] - 6.0) - 0.01) < 0.002  # cos(ray, normal) ~ 1 near the axis
    # One point per beam bin: never more points than bins could hold.
    assert len(p) <= world.shape[0]


def test_occluded_points_are_hidden_and_grazing_ones_kept() -> None:
    far = _grid_wall(8.0, (-4.0, 4.0), (-2.0, 2.0), 0.02)
    near = _grid_wall(3.0, (-0.5, 0.5), (-0.5, 0.5), 0.01)  # a panel in front of the wall
    world = np.concatenate([far, near])
    q, _ = simulate_scan(world, np.eye(4), np.random.default_rng(1), Sensor(range_noise=0.0))
    on_far = q[np.abs(q[:, 0] - 8.0) < 1e-6]
    # The panel's shadow on the far wall spans |y|, |z| < 0.5 * 8 / 3 = 1.33 m.
    in_shadow = (np.abs(on_far[:, 1]) < 1.2) & (np.abs(on_far[:, 2]) < 1.2)
    assert not in_shadow.any()
    outside = (np.abs(on_far[:, 1]) > 1.5) | (np.abs(on_far[:, 2]) > 1.5)
    assert outside.sum() > 1000
    assert (np.abs(q[:, 0] - 3.0) < 1e-6).sum() > 100  # the panel itself is seen


def test_a_sweep_distorts_by_the_twist_and_deskewing_undoes_it() -> None:
    # A room seen while moving at 1.2 m/s and turning at 30 deg/s over a 0.1 s sweep.
    room = np.concatenate(
        [
            _grid_wall(6.0, (-6.0, 6.0), (-2.0, 2.0), 0.03),
            _grid_wall(-6.0, (-6.0, 6.0), (-2.0, 2.0), 0.03),
            _grid_wall(6.0, (-6.0, 6.0), (-2.0, 2.0), 0.03)[:, [1, 0, 2]],
            _grid_wall(-6.0, (-6.0, 6.0), (-2.0, 2.0), 0.03)[:, [1, 0, 2]],
        ]
    )
    omega, v = np.array([0.0, 0.0, np.radians(30.0)]), np.array([1.2, 0.0, 0.0])
    twist = np.zeros((4, 4))
    twist[:3, :3] = [[0.0, -omega[2], 0.0], [omega[2], 0.0, 0.0], [0.0, 0.0, 0.0]]
    twist[:3, 3] = v
    sensor = Sensor(range_noise=0.0, sweep_period=0.1)
    still, _ = simulate_scan(room, np.eye(4), np.random.default_rng(4), Sensor(range_noise=0.0))
    swept, times = simulate_scan(room, np.eye(4), np.random.default_rng(4), sensor, twist)
    assert len(swept) == len(still)
    assert -0.1 < times.min() and times.max() < 0.0  # the sweep ends at the stamp
    moved = np.linalg.norm(swept - still, axis=1)
    assert np.percentile(moved, 99) > 0.05  # up to 12 cm and 3 deg over the sweep
    fixed = deskew(swept, times, np.concatenate([omega, v]))
    # Both take the pose at tau to be the exact SE(3) exponential, and every point's time is
    # that of its slice's pose: the round trip is exact up to rounding (of 6 m coordinates).
    np.testing.assert_allclose(fixed, still, rtol=0, atol=1e-12 * 6.0 * 100)


def test_trajectory_steps_along_the_path_with_its_orientations() -> None:
    T_ref = np.tile(np.eye(4), (5, 1, 1))
    T_ref[:, 0, 3] = [0.0, 1.0, 2.0, 3.0, 4.0]
    for i in range(5):
        T_ref[i, :3, :3] = exp_so3(np.array([0.0, 0.0, 0.1 * i]))
    T = trajectory(T_ref, 0.5, 0.0, 9.0)
    assert len(T) == 9
    np.testing.assert_allclose(np.diff(T[:, 0, 3]), 0.5, atol=1e-12)
    # Half way between reference poses 1 and 2 the orientation is half way (slerp).
    np.testing.assert_allclose(T[3, :3, :3], exp_so3(np.array([0.0, 0.0, 0.15])), atol=1e-12)
    stats = motion_stats(T)
    assert stats['step_median_m'] == pytest.approx(0.5)
    assert stats['rotation_median_deg'] == pytest.approx(np.degrees(0.05))


def test_summary_ratios_are_per_seed_and_failures_add_up() -> None:
    def entry(ate_k: float, ate_m: float, failed: int) -> dict[str, object]:
        base = {'drift_pct': 1.0, 'rpe_frame_m': 0.002, 'n_pairs': 10, 'ms_per_scan_mean': 5.0}
        return {
            'methods': {
                'kentreg': {**base, 'ate_m': ate_k, 'n_failed': 0},
                'kentreg_local_map': {**base, 'ate_m': ate_m, 'n_failed': failed},
            }
        }

    runs = [entry(0.004, 0.002, 0), entry(0.002, 0.002, 1), entry(0.010, 0.003, 0)]
    summary = summarize_step(runs, ['kentreg', 'kentreg_local_map'])
    ratio = summary['kentreg_local_map']['ate_ratio_to_kentreg']
    assert (ratio['median'], ratio['min'], ratio['max']) == pytest.approx((0.5, 0.3, 1.0))
    assert summary['kentreg_local_map']['failed_pairs'] == 1
    assert summary['kentreg_local_map']['pairs'] == 30
    report = {
        'seeds': 3,
        'steps': [
            {
                'step_m': 0.6,
                'n_scans': 11,
                'motion': {'rotation_median_deg': 8.0, 'rotation_max_deg': 40.0},
                'summary': summary,
            }
        ],
    }
    table = format_table(report)
    assert (
        '| 0.6 | clean | 11 | 8.0, 40.0 | kentreg_local_map | 2.00 | 0.50 (0.30–1.00) |' in table
    )


@pytest.fixture(scope='module')
def world() -> World:
    return build_world(BAG, 0.05)


@pytest.mark.integration
def test_odometry_on_simulated_scans_matches_the_exact_poses(world: World) -> None:
    scans, gt = simulate(world, 0.6, 0, Sensor())
    scans, T_true = scans[:4], gt.trajectory.T_world_sensor[:4]
    run = run_odometry(scans, Odometry())
    assert run.error is None
    errors = rpe(run.poses, T_true, delta=1)
    # The pairs turn by up to 43 deg and move 0.6 m; against the exact poses the errors are
    # what registration of scans with 2 cm range noise leaves (measured: 0.01-0.02 deg,
    # 2-3 mm), far below a failure (2 deg, 0.2 m).
    assert errors['e_R_deg'].max() < 0.1
    assert errors['e_t'].max() < 0.01
    stats = motion_stats(T_true)
    assert stats['step_median_m'] == pytest.approx(0.6, rel=0.05)


@pytest.mark.integration
def test_deskewing_follows_a_sudden_change_of_velocity(
    world: World, monkeypatch: pytest.MonkeyPatch
) -> None:
    # 100 ms sweeps ending at each stamp, the sensor turning 14-44 deg between scans 0.5 s
    # apart with a velocity that changes at every scan: the first deskewing (the previous
    # motion) is off by the change, and the deskew-and-register rounds must converge.
    scans, gt = simulate(world, 0.6, 0, Sensor(sweep_period=0.1))
    scans, T_true = scans[:6], gt.trajectory.T_world_sensor[:6]
    errors = {}
    for rounds in (1, odometry_module.MAX_DESKEW_ITERATIONS):
        monkeypatch.setattr(odometry_module, 'MAX_DESKEW_ITERATIONS', rounds)
        run = run_odometry(scans, Odometry())
        assert run.error is None
        errors[rounds] = float(np.median(rpe(run.poses, T_true, delta=1)['e_R_deg']))
    # Measured: 0.2 deg after one round, 0.02 after three (0.01-0.02 without sweeps).
    assert errors[odometry_module.MAX_DESKEW_ITERATIONS] < 0.05 < errors[1]


@pytest.mark.integration
def test_simulate_writes_a_folder_the_replay_reads(tmp_path: Path) -> None:
    out = tmp_path / 'sim'
    argv = ['--input', str(BAG), '--write', str(out), '--steps', '3.0', '--seed', '2']
    with pytest.raises(SystemExit) as done:
        report.experiment_main('', 'simulated', OPTIONS, run, format_table, argv=argv)
    assert done.value.code == 0
    recording = open_recording(out)
    scans = list(recording.source)
    assert recording.reference is not None
    T = np.asarray(recording.reference.T_world_sensor)
    assert len(scans) == len(T) >= 3
    # 3 m along the curved path: the straight line between two poses is at most that.
    chords = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    assert np.all(chords <= 3.0 + 1e-9) and np.all(chords[:-1] > 2.0)
    stamps = np.array([s.stamp_ns for s in scans])
    np.testing.assert_array_equal(stamps, recording.reference.stamps_ns)
