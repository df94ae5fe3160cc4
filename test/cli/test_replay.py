"""Tests of the ``kentreg_replay`` CLI: real runs on the BALM sample bag and a scan folder.

The metrics are checked against an independent computation from the written ``poses_tum.txt``
and BALM's own pose file, parsed here with numpy only.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from optional import import_open3d
from recordings import bag_with_malformed_clouds
from scipy.spatial.transform import Rotation

from kentreg_ros.cli.replay import main
from kentreg_ros.core import KentRegConfig
from kentreg_ros.eval.groundtruth import associate
from kentreg_ros.io.paramfile import dump_config, load_config

pytest.importorskip('rosbags', reason='the replay CLI reads bags with rosbags')
# The odometry tests' trajectory helpers (test/core/test_odometry.py), importable when this file
# runs alone too (the full run has put test/core on the path by then).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'core'))
pytest.importorskip('mcap', reason='the output is checked with the mcap reader')

SAMPLE_SCANS = 8


def run_cli(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (s) and poses (N, 4, 4) of a TUM file, with numpy and scipy only."""
    rows = np.loadtxt(path, ndmin=2)
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(rows[:, 4:8]).as_matrix()
    T[:, :3, 3] = rows[:, 1:4]
    return rows[:, 0], T


def read_balm_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (s) and ``T_world_lidar`` (N, 4, 4) of BALM's alidarPose.csv."""
    values = np.array(
        [[float(v) for v in line.split(',') if v.strip()] for line in path.read_text().split()]
    ).reshape(-1, 4, 4)
    stamps = values[:, 3, 3].copy()
    values[:, 3] = [0.0, 0.0, 0.0, 1.0]
    # The file prints rotations with 6 decimals: use the nearest rotation matrices.
    values[:, :3, :3] = Rotation.from_matrix(values[:, :3, :3]).as_matrix()
    return stamps, values


def independent_pair_errors(T_est: np.ndarray, T_gt: np.ndarray) -> tuple[np.ndarray, ...]:
    rel_est = np.linalg.inv(T_est[:-1]) @ T_est[1:]
    rel_gt = np.linalg.inv(T_gt[:-1]) @ T_gt[1:]
    e_R = np.array([
        np.degrees(np.arccos(np.clip((np.trace(g[:3, :3].T @ e[:3, :3]) - 1) / 2, -1, 1)))
        for e, g in zip(rel_est, rel_gt, strict=True)
    ])  # fmt: skip
    e_t = np.linalg.norm(rel_est[:, :3, 3] - rel_gt[:, :3, 3], axis=1)
    return e_R, e_t


def mcap_messages(path: Path) -> dict[str, list[object]]:
    """Deserialised messages per topic, read with rosbags from the standalone MCAP file."""
    from rosbags.highlevel import AnyReader

    out: dict[str, list[object]] = {}
    with AnyReader([path]) as reader:
        for connection, _, raw in reader.messages():
            msg = reader.deserialize(raw, connection.msgtype)
            out.setdefault(connection.topic, []).append(msg)
    return out


def stamp_ns(msg: object) -> int:
    stamp = msg.header.stamp  # type: ignore[attr-defined]
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


@pytest.fixture(scope='module')
def sample_bag(repo_root: Path) -> Path:
    bag = repo_root / 'bags' / 'balm_50'
    if not bag.is_dir():
        pytest.skip(f'sample bag {bag} is absent')
    return bag


@pytest.fixture(scope='module')
def sample_run(sample_bag: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    out = tmp_path_factory.mktemp('replay') / 'run'
    code, stdout, stderr = run_cli(
        [str(sample_bag), '--max-scans', str(SAMPLE_SCANS), '--out', str(out), '--no-progress']
    )
    return {'code': code, 'stdout': stdout, 'stderr': stderr, 'out': out}


@pytest.mark.integration
def test_replay_sample_writes_every_output(sample_run: dict[str, object]) -> None:
    assert sample_run['code'] == 0, sample_run['stderr']
    out = sample_run['out']
    assert isinstance(out, Path)
    names = {p.name for p in out.iterdir()}
    assert names == {
        'odometry.mcap',
        'poses_tum.txt',
        'poses_kitti.txt',
        'ground_truth_tum.txt',
        'config.yaml',
        'metrics.json',
        'trajectory.png',
    }
    assert (out / 'trajectory.png').read_bytes().startswith(b'\x89PNG')
    assert load_config(out / 'config.yaml') == KentRegConfig()
    kitti = np.loadtxt(out / 'poses_kitti.txt', ndmin=2)
    _, T_tum = read_tum(out / 'poses_tum.txt')
    np.testing.assert_allclose(kitti.reshape(-1, 3, 4), T_tum[:, :3, :], atol=1e-6)
    stdout = str(sample_run['stdout'])
    for text in ('ms/scan', 'scans/s', 'pair e_R', 'ATE', 'KITTI'):
        assert text in stdout


@pytest.mark.integration
def test_replay_sample_mcap_has_one_message_per_scan(
    sample_run: dict[str, object], sample_bag: Path
) -> None:
    from mcap.reader import make_reader

    out = sample_run['out']
    assert isinstance(out, Path)
    with (out / 'odometry.mcap').open('rb') as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    counts = {
        summary.channels[cid].topic: n
        for cid, n in summary.statistics.channel_message_counts.items()
    }
    n = SAMPLE_SCANS
    assert counts == {
        '/kentreg/odometry': n,
        '/kentreg/pose': n,
        '/tf': n,
        '/kentreg/cloud_registered': n,
        '/kentreg/path': 1,
        '/kentreg/map': 1,
    }
    types = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert types['/kentreg/odometry'] == 'nav_msgs/msg/Odometry'
    assert types['/kentreg/pose'] == 'geometry_msgs/msg/PoseStamped'
    assert types['/kentreg/path'] == 'nav_msgs/msg/Path'
    assert types['/kentreg/cloud_registered'] == 'sensor_msgs/msg/PointCloud2'

    messages = mcap_messages(out / 'odometry.mcap')
    input_stamps = [stamp_ns(m) for m in mcap_messages(sample_bag / 'balm_50.mcap')['/points']]
    odometry = messages['/kentreg/odometry']
    assert [stamp_ns(m) for m in odometry] == input_stamps[:n]
    assert {m.header.frame_id for m in odometry} == {'odom'}  # type: ignore[attr-defined]
    assert {m.child_frame_id for m in odometry} == {'lidar'}  # type: ignore[attr-defined]
    # The node's names and frames (kentreg_node with no parameters publishes the same).
    from kentreg_ros.io import names

    for name in (names.ODOMETRY, names.POSE, names.PATH, names.CLOUD_REGISTERED, names.MAP):
        assert names.absolute(name) in counts
    clouds = messages['/kentreg/cloud_registered']
    assert [stamp_ns(m) for m in clouds] == input_stamps[:n]
    assert {m.header.frame_id for m in clouds} == {'odom'}  # type: ignore[attr-defined]
    path = messages['/kentreg/path'][0]
    positions = [(p.pose.position.x, p.pose.position.y) for p in path.poses]  # type: ignore[attr-defined]
    _, T_tum = read_tum(out / 'poses_tum.txt')
    np.testing.assert_allclose(positions, T_tum[:, :2, 3], atol=1e-6)


@pytest.mark.integration
def test_replay_sample_metrics_match_independent_computation(
    sample_run: dict[str, object], shared_data: Path
) -> None:
    out = sample_run['out']
    assert isinstance(out, Path)
    report = json.loads((out / 'metrics.json').read_text())
    stamps, T_est = read_tum(out / 'poses_tum.txt')
    gt_stamps, T_gt_all = read_balm_csv(shared_data / 'balm' / 'alidarPose.csv')
    rows = [int(np.argmin(np.abs(gt_stamps - s))) for s in stamps]
    assert np.max(np.abs(gt_stamps[rows] - stamps)) < 1e-4
    e_R, e_t = independent_pair_errors(T_est, T_gt_all[rows])

    pairs = report['ground_truth']['pairs']
    np.testing.assert_allclose(pairs['e_R_deg'], e_R, atol=2e-4)
    np.testing.assert_allclose(pairs['e_t_m'], e_t, atol=1e-6)
    assert pairs['rotation_deg']['median'] == pytest.approx(np.median(e_R), abs=2e-4)
    assert pairs['translation_m']['median'] == pytest.approx(np.median(e_t), abs=1e-6)
    # The bar on the real sample: <= 0.1 deg / 1 cm median, no failed pair.
    assert np.median(e_R) <= 0.1 and np.median(e_t) <= 0.01
    assert pairs['n_failed'] == 0 and np.all(e_R <= 2.0) and np.all(e_t <= 0.2)
    assert report['ground_truth']['rpe']['translation_m']['rmse'] == pytest.approx(
        np.sqrt(np.mean(e_t**2)), abs=1e-6
    )
    ate = report['ground_truth']['ate']
    assert ate is not None and 0.0 <= ate['rmse'] < 0.05
    assert report['ground_truth']['kitti'] is None  # a few metres cannot fill 100 m segments
    # On the sample no step is doubtful, the first included (its fit is above doubt_ratio,
    # which stands in for the missing history), so none pays for the start-free search.
    assert report['health'] == {
        'first': 1, 'ok': SAMPLE_SCANS - 1, 'recovered': 0, 'degenerate': 0, 'ambiguous': 0,
        'fell_back': 0, 'rejected': 0,
    }  # fmt: skip
    assert report['n_searched'] == 0
    speed = report['speed']
    assert speed['n_scans'] == SAMPLE_SCANS and speed['scans_per_s'] > 0
    assert speed['ms_per_scan']['p95'] >= speed['ms_per_scan']['median'] > 0
    assert len(report['steps']) == SAMPLE_SCANS


def test_replay_stride_processes_every_third_scan_with_original_stamps(
    sample_bag: Path, shared_data: Path, tmp_path: Path
) -> None:
    out = tmp_path / 'stride'
    code, stdout, stderr = run_cli(
        [str(sample_bag), '--stride', '3', '--max-scans', '5', '--out', str(out),
         '--no-progress', '--no-plot']
    )  # fmt: skip
    assert code == 0, stderr
    report = json.loads((out / 'metrics.json').read_text())
    assert report['input']['stride'] == 3
    # --max-scans counts processed scans: 0, 3, 6, 9, 12.
    assert [s['input_index'] for s in report['steps']] == [0, 3, 6, 9, 12]
    assert [s['index'] for s in report['steps']] == [0, 1, 2, 3, 4]
    input_stamps = [stamp_ns(m) for m in mcap_messages(sample_bag / 'balm_50.mcap')['/points']]
    assert [s['stamp_ns'] for s in report['steps']] == input_stamps[0:13:3]
    stamps, T_est = read_tum(out / 'poses_tum.txt')
    np.testing.assert_allclose(stamps, np.array(input_stamps[0:13:3]) * 1e-9, atol=1e-6)
    # Pairs join consecutive processed scans: (0, 3), (3, 6), ... against the poses of 0, 3, ...
    gt_stamps, T_gt_all = read_balm_csv(shared_data / 'balm' / 'alidarPose.csv')
    e_R, e_t = independent_pair_errors(T_est, T_gt_all[0:13:3])
    np.testing.assert_allclose(gt_stamps[0:13:3], stamps, atol=1e-4)
    pairs = report['ground_truth']['pairs']
    assert pairs['count'] == 4 and report['ground_truth']['n_matched'] == 5
    np.testing.assert_allclose(pairs['e_R_deg'], e_R, atol=2e-4)
    np.testing.assert_allclose(pairs['e_t_m'], e_t, atol=1e-6)
    first_line = stdout.splitlines()[0]
    assert '5 scans' in first_line and 'stride 3 (one scan in 3)' in first_line
    assert 'failed pairs' in stdout


def test_run_odometry_stride_selects_start_plus_multiples() -> None:
    from kentreg_ros.eval.run import run_odometry
    from kentreg_ros.io.sources import Scan

    class Recorder:
        """Stands in for Odometry: records what it was given."""

        n_failed = 0

        def __init__(self) -> None:
            self.stamps: list[int] = []

        def step(
            self,
            points: np.ndarray,
            stamp_ns: int,
            frame_id: str | None = None,
            point_times: np.ndarray | None = None,
        ) -> SimpleNamespace:
            self.stamps.append(stamp_ns)
            return SimpleNamespace(health='ok', message='', timings={'total': 0.0})

    scans = [Scan(1000 * i, 'lidar', np.zeros((1, 3)), {}) for i in range(10)]
    odom = Recorder()
    run = run_odometry(scans, odom, start=1, stride=4)  # type: ignore[arg-type]
    assert run.input_indices == [1, 5, 9] and odom.stamps == [1000, 5000, 9000]
    odom = Recorder()
    run = run_odometry(scans, odom, start=2, stride=3, max_scans=2)  # type: ignore[arg-type]
    assert run.input_indices == [2, 5] and odom.stamps == [2000, 5000]
    odom = Recorder()
    run = run_odometry(scans, odom, start=9, stride=5)  # type: ignore[arg-type]
    assert run.input_indices == [9]
    seen: list[object] = []
    run = run_odometry(scans, Recorder(), stride=3, on_step=seen.append)  # type: ignore[arg-type]
    assert run.input_indices == [0, 3, 6, 9] and seen == run.steps
    with pytest.raises(ValueError, match='start 10: the input has only 10 scans'):
        run_odometry(scans, Recorder(), start=10)  # type: ignore[arg-type]
    for stride in (0, True, 1.5):
        with pytest.raises(ValueError, match='stride: expected a positive integer'):
            run_odometry(scans, Recorder(), stride=stride)  # type: ignore[arg-type]


def test_run_odometry_stops_at_a_scan_that_does_not_continue_the_trajectory() -> None:
    """A stamp that repeats (or goes back) ends the run there, as a damaged bag does: the scans
    before it are kept and the odometry's reason is the run's error (the replay then writes
    what it has and exits 2)."""
    from test_odometry import STEP_NS, observe, true_trajectory

    from kentreg_ros.core import Odometry
    from kentreg_ros.eval.run import run_odometry
    from kentreg_ros.io.sources import Scan

    rng = np.random.default_rng(2)
    clouds = [observe(rng, T) for T in true_trajectory(4)]
    stamps = [0, STEP_NS, STEP_NS, 3 * STEP_NS]
    scans = [Scan(t, 'lidar', c, {}) for t, c in zip(stamps, clouds, strict=True)]
    run = run_odometry(scans, Odometry())
    assert len(run.steps) == 2 and run.input_indices == [0, 1]
    assert run.error is not None and run.error.startswith(
        "scan 2: The scan repeats the last scan's stamp"
    )


@pytest.mark.integration
def test_replay_paper_mode_config_runs_end_to_end(sample_bag: Path, tmp_path: Path) -> None:
    config = tmp_path / 'paper.yaml'
    config.write_text(dump_config(KentRegConfig.paper()))
    out = tmp_path / 'paper'
    code, stdout, stderr = run_cli(
        [str(sample_bag), '--config', str(config), '--max-scans', '3', '--out', str(out),
         '--no-progress', '--no-plot']
    )  # fmt: skip
    assert code == 0, stderr
    report = json.loads((out / 'metrics.json').read_text())
    assert report['mode'] == 'paper' and 'mode paper' in stdout
    assert load_config(out / 'config.yaml').mode == 'paper'
    assert report['ground_truth']['pairs']['count'] == 2
    assert report['speed']['n_scans'] == 3
    assert not (out / 'trajectory.png').exists()


def test_replay_scan_folder_uses_pose_file_beside_scans(shared_data: Path, tmp_path: Path) -> None:
    out = tmp_path / 'folder'
    code, stdout, stderr = run_cli(
        [str(shared_data / 'balm'), '--start', '20', '--max-scans', '3', '--out', str(out),
         '--no-progress', '--no-plot', '--child-frame', 'base_link']
    )  # fmt: skip
    assert code == 0, stderr
    report = json.loads((out / 'metrics.json').read_text())
    assert [s['input_index'] for s in report['steps']] == [20, 21, 22]
    assert report['ground_truth']['source'].endswith('alidarPose.csv')
    assert report['ground_truth']['n_matched'] == 3
    gt_stamps, _ = read_balm_csv(shared_data / 'balm' / 'alidarPose.csv')
    stamps, _ = read_tum(out / 'poses_tum.txt')
    np.testing.assert_allclose(stamps, gt_stamps[20:23], atol=1e-6)
    assert report['odometry_mcap']['child_frame'] == 'base_link'


def test_replay_counts_rejected_scan_of_synthetic_bag(tmp_path: Path) -> None:
    from test_odometry import STEP_NS, observe, true_trajectory

    from kentreg_ros.io.bagwriter import BagWriter

    rng = np.random.default_rng(11)
    T_true = true_trajectory(4)
    bag = tmp_path / 'synthetic'
    with BagWriter(bag) as writer:
        for i, T in enumerate(T_true):
            points = observe(rng, T) if i != 2 else observe(rng, T)[:5]
            writer.write_pointcloud('/cloud', (i + 1) * STEP_NS, points, frame_id='velodyne')
            writer.write_pose('/ground_truth', (i + 1) * STEP_NS, T, frame_id='world')
    out = tmp_path / 'out'
    code, stdout, stderr = run_cli([str(bag), '--out', str(out), '--no-progress', '--no-plot'])
    assert code == 0, stderr
    report = json.loads((out / 'metrics.json').read_text())
    # The synthetic room is centrally symmetric up to its boxes: the first pair, searched when
    # it fits below doubt_ratio, may be flagged ambiguous (the pose nearest the prediction).
    healths = [s['health'] for s in report['steps']]
    assert healths in (['first', 'ok', 'rejected', 'ok'], ['first', 'ambiguous', 'rejected', 'ok'])
    assert report['n_failed_steps'] == 1 and 'rejected 1' in stdout
    assert 'Rejected the scan' in stderr  # logged as a warning, the run goes on
    assert report['odometry_mcap']['child_frame'] == 'velodyne'
    # Scan 2's pose is the prediction; scan 3 was registered against scan 1 and is accurate.
    _, T_est = read_tum(out / 'poses_tum.txt')
    rel_est = np.linalg.inv(T_est[1]) @ T_est[3]
    rel_true = np.linalg.inv(T_true[1]) @ T_true[3]
    e_R = Rotation.from_matrix(rel_true[:3, :3].T @ rel_est[:3, :3]).magnitude()
    assert np.degrees(e_R) < 0.1
    np.testing.assert_allclose(rel_est[:3, 3], rel_true[:3, 3], atol=0.01)


def test_replay_default_out_dir_and_latest_link(
    sample_bag: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    code, stdout, stderr = run_cli(
        [str(sample_bag), '--max-scans', '2', '--no-progress', '--no-plot']
    )
    assert code == 0, stderr
    runs = [p for p in (tmp_path / 'results').iterdir() if p.name != 'latest']
    assert len(runs) == 1
    latest = tmp_path / 'results' / 'latest'
    assert latest.is_symlink() and latest.resolve() == runs[0].resolve()
    assert (latest / 'metrics.json').is_file()
    assert f'{runs[0]}' in stdout or str(runs[0].relative_to(tmp_path)) in stdout


def test_replay_interrupted_writes_scans_so_far(
    sample_bag: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from kentreg_ros.core import Odometry

    real_step = Odometry.step

    def step_then_ctrl_c(self: Odometry, *args: object, **kwargs: object) -> object:
        if self.n_steps == 2:
            raise KeyboardInterrupt
        return real_step(self, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(Odometry, 'step', step_then_ctrl_c)
    out = tmp_path / 'out'
    code, stdout, stderr = run_cli(
        [str(sample_bag), '--out', str(out), '--no-progress', '--no-plot']
    )
    assert code == 130
    assert 'interrupted after 2 scans' in stderr
    report = json.loads((out / 'metrics.json').read_text())
    assert report['complete'] is False and report['speed']['n_scans'] == 2
    assert len(np.loadtxt(out / 'poses_tum.txt', ndmin=2)) == 2


@pytest.mark.parametrize(
    ('argv', 'match'),
    [
        (['{tmp}/missing.mcap'], 'no such file'),
        (['{bag}', '--set', 'em.no_such_key=1'], 'Unknown parameter'),
        (['{bag}', '--config', '{tmp}/bad.yaml'], 'Unknown parameter'),
        (['{bag}', '--set', 'mode=fast'], 'mode'),
        (['{bag}', '--start', '50'], 'only 50 scans'),
        (['{bag}', '--max-scans', '0'], 'positive integer'),
        (['{bag}', '--stride', '0'], 'positive integer'),
        (['{bag}', '--stride', '-2'], 'expected a positive integer (>= 1)'),
        (['{bag}', '--stride', '1.5'], 'expected an integer'),
        (['{bag}', '--stride', 'two'], 'expected an integer'),
        (['{bag}', '--topic', '/ground_truth'], 'not sensor_msgs/msg/PointCloud2'),
    ],
)
def test_replay_bad_input_exits_2_with_one_line(
    argv: list[str], match: str, sample_bag: Path, tmp_path: Path
) -> None:
    (tmp_path / 'bad.yaml').write_text(
        'kentreg_node:\n  ros__parameters:\n    em:\n      nope: 1\n'
    )
    args = [a.format(tmp=tmp_path, bag=sample_bag) for a in argv]
    code, stdout, stderr = run_cli([*args, '--out', str(tmp_path / 'out'), '--no-progress'])
    assert code == 2
    assert stdout == ''
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('kentreg_replay: error: ')
    assert match in lines[0]
    assert not (tmp_path / 'out').exists()


@pytest.mark.integration
def test_replay_module_subprocess_bad_input(repo_root: Path, tmp_path: Path) -> None:
    env = {**os.environ, 'PYTHONPATH': os.pathsep.join([str(repo_root), *sys.path])}
    proc = subprocess.run(
        [sys.executable, '-m', 'kentreg_ros.cli.replay', str(tmp_path / 'nothing_here')],
        capture_output=True, text=True, env=env, timeout=60, check=False,
    )  # fmt: skip
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f'kentreg_replay: error: {tmp_path / "nothing_here"}: no such file or folder'
    ]


@pytest.mark.integration
def test_installed_console_script_runs_sample(sample_bag: Path, tmp_path: Path) -> None:
    script = shutil.which('kentreg_replay')
    if script is None:
        pytest.skip('kentreg_replay is not installed (pip install -e .[io])')
    proc = subprocess.run(
        [script, str(sample_bag), '--max-scans', '2', '--out', str(tmp_path / 'o'),
         '--no-progress', '--no-plot'],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / 'o' / 'odometry.mcap').is_file()


def test_associate_by_stamp_and_by_index() -> None:
    from kentreg_ros.io.poses import Trajectory

    T = np.tile(np.eye(4), (4, 1, 1))
    gt = Trajectory(np.array([100, 200, 300, 400]) * 10_000_000, T)
    stamps = np.array([201, 299, 350, 401], dtype=np.int64) * 10_000_000
    scan_rows, gt_rows = associate(stamps, [0, 1, 2, 3], gt)
    assert scan_rows.tolist() == [0, 1, 3] and gt_rows.tolist() == [1, 2, 3]
    scan_rows, gt_rows = associate(stamps, [2, 3, 4, 5], Trajectory(None, T))
    assert scan_rows.tolist() == [0, 1] and gt_rows.tolist() == [2, 3]


def test_replay_hands_a_bags_per_point_times_to_the_odometry(tmp_path: Path) -> None:
    """A bag whose clouds carry a `t` field (Ouster-style nanoseconds) reaches Odometry.step as
    point_times, aligned with the finite points (the NaN point is dropped from both)."""
    from kentreg_ros.eval.run import run_odometry
    from kentreg_ros.io.bagwriter import BagWriter
    from kentreg_ros.io.recordings import open_recording

    points = np.array([[1.0, 0, 0], [np.nan, 0, 0], [0, 2.0, 0], [0, 0, 3.0]])
    t = np.array([0, 25_000_000, 50_000_000, 75_000_000], dtype=np.uint32)
    bag = tmp_path / 'timed'
    with BagWriter(bag) as writer:
        for i in range(2):
            writer.write_pointcloud('/cloud', (i + 1) * 100_000_000, points, extra={'t': t})
    given: list[np.ndarray | None] = []

    class Recorder:
        n_failed = 0

        def step(
            self,
            points: np.ndarray,
            stamp_ns: int,
            frame_id: str | None = None,
            point_times: np.ndarray | None = None,
        ) -> SimpleNamespace:
            given.append(point_times)
            return SimpleNamespace(health='ok', message='', timings={'total': 0.0})

    recording = open_recording(bag, fields=None)  # what kentreg_replay opens
    run_odometry(recording.source, Recorder())  # type: ignore[arg-type]
    assert len(given) == 2
    for times in given:
        assert times is not None
        np.testing.assert_array_equal(times, [0, 50_000_000, 75_000_000])


def test_replay_writes_the_map_as_ply_and_into_the_mcap(sample_bag: Path, tmp_path: Path) -> None:
    from scenes import read_ply_xyz

    from kentreg_ros.io.pointcloud2 import pointcloud2_to_array

    out, map_path = tmp_path / 'run', tmp_path / 'maps' / 'map.ply'
    voxel = 0.2
    argv = [str(sample_bag), '--max-scans', '4', '--out', str(out), '--no-progress']
    argv += ['--no-plot', '--set', 'odometry.model=local_map', '--map', str(map_path)]
    code, _, stderr = run_cli([*argv, '--map-voxel', str(voxel)])
    assert code == 0, stderr
    ply = read_ply_xyz(map_path)
    report = json.loads((out / 'metrics.json').read_text())
    assert report['map'] == {'path': str(map_path), 'points': len(ply), 'voxel_size': voxel}
    # One point per voxel, and many more points than one downsampled scan.
    cells = np.floor(ply.astype(np.float64) / voxel)
    assert len(np.unique(cells, axis=0)) >= 0.99 * len(ply) and len(ply) > 10_000
    # The map is in the odometry frame: around the first scan's origin (the sample spans ~25 m).
    assert np.linalg.norm(np.median(ply, axis=0)) < 25.0
    messages = mcap_messages(out / 'odometry.mcap')
    (cloud,) = messages['/kentreg/map']
    assert cloud.header.frame_id == 'odom'  # type: ignore[attr-defined]
    assert stamp_ns(cloud) == stamp_ns(messages['/kentreg/pose'][-1])
    np.testing.assert_array_equal(pointcloud2_to_array(cloud).points, ply)  # type: ignore[arg-type]
    o3d = import_open3d()  # skips when Open3D is missing or cannot load
    assert len(o3d.io.read_point_cloud(str(map_path)).points) == len(ply)


def test_replay_refuses_a_map_file_of_unknown_kind(sample_bag: Path, tmp_path: Path) -> None:
    code, _, stderr = run_cli([str(sample_bag), '--map', str(tmp_path / 'map.las')])
    assert code == 2 and '--map' in stderr and '.ply or .pcd' in stderr


@pytest.mark.integration
def test_replay_prints_only_its_own_lines(
    repo_root: Path, sample_bag: Path, tmp_path: Path
) -> None:
    """A user sees the program's lines and nothing of its libraries: run as a user runs it (a
    process of its own, so a library's log record reaches the terminal as it would, not
    pytest's capture), with the plot. Before, matplotlib's "Ignoring fixed x limits to
    fulfill fixed data aspect ..." came twice on every run."""
    pytest.importorskip('matplotlib', reason='the plot is what logged')
    env = {**os.environ, 'PYTHONPATH': os.pathsep.join([str(repo_root), *sys.path])}
    out = tmp_path / 'run'
    proc = subprocess.run(
        [sys.executable, '-m', 'kentreg_ros.cli.replay', str(sample_bag), '--max-scans', '4',
         '--out', str(out), '--no-progress'],
        capture_output=True, text=True, env=env, timeout=300, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert (out / 'trajectory.png').is_file()
    lines = [line for line in (proc.stdout + proc.stderr).splitlines() if line.strip()]
    foreign = [line for line in lines if not line.startswith(('kentreg_replay', '  '))]
    assert foreign == [], foreign
    assert proc.stderr == ''


def test_replay_skips_a_malformed_cloud_counts_it_and_names_it(
    sample_bag: Path, tmp_path: Path
) -> None:
    """One PointCloud2 that cannot be decoded among good ones: skipped (the node does the same),
    counted and named (input index, stamp, reason) in the summary and metrics.json; the other
    scans are processed and evaluated and the run exits 0. It stopped the run with exit 2."""
    bag = tmp_path / 'one_bad'
    stamps = bag_with_malformed_clouds(sample_bag, bag, 6, {2})
    out = tmp_path / 'out'
    code, stdout, stderr = run_cli([str(bag), '--out', str(out), '--no-progress', '--no-plot'])
    assert code == 0, stderr
    assert stderr == ''
    report = json.loads((out / 'metrics.json').read_text())
    assert [s['input_index'] for s in report['steps']] == [0, 1, 3, 4, 5]
    assert report['complete'] is True and report['speed']['n_scans'] == 5
    (skipped,) = report['skipped']['first']
    assert report['skipped']['count'] == 1
    assert skipped['input_index'] == 2 and skipped['stamp_ns'] == stamps[2]
    assert 'expected row_step * height' in skipped['reason']
    assert report['ground_truth']['n_matched'] == 5
    assert len(np.loadtxt(out / 'poses_tum.txt', ndmin=2)) == 5
    line = next(line for line in stdout.splitlines() if line.strip().startswith('skipped'))
    assert '1 scan' in line
    assert f'input 2 (stamp {stamps[2] * 1e-9:.3f} s)' in stdout
    assert 'expected row_step * height' in stdout


def test_replay_of_nothing_but_malformed_clouds_exits_2_with_one_line(
    sample_bag: Path, tmp_path: Path
) -> None:
    bag = tmp_path / 'all_bad'
    bag_with_malformed_clouds(sample_bag, bag, 3, {0, 1, 2})
    out = tmp_path / 'out'
    code, stdout, stderr = run_cli([str(bag), '--out', str(out), '--no-progress', '--no-plot'])
    assert code == 2 and stdout == ''
    (line,) = stderr.strip().splitlines()
    assert line.startswith('kentreg_replay: error: ') and 'none of the 3 scans' in line
    assert 'input 0' in line and 'expected row_step * height' in line
    assert not out.exists()
