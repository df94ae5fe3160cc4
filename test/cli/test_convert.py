"""kentreg_convert: scan folders and files (+ poses) to rosbag2 MCAP; one-line errors, exit 2."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kentreg_ros.cli.convert import downsample_scan, main
from kentreg_ros.io.bags import bag_topics
from kentreg_ros.io.poses import read_poses, write_kitti, write_tum
from kentreg_ros.io.recordings import read_ground_truth
from kentreg_ros.io.scanfiles import write_pcd
from kentreg_ros.io.sources import open_scan_source


def _folder(tmp_path: Path, n: int = 4, points: int = 3000) -> tuple[Path, list[np.ndarray]]:
    rng = np.random.default_rng(0)
    folder = tmp_path / 'scans'
    folder.mkdir()
    clouds = []
    for i in range(n):
        pts = rng.uniform(-10, 10, size=(points, 3)).astype(np.float32)
        pts[0] = np.nan
        extra = {'intensity': np.arange(points, dtype='f4'), 'curvature': np.zeros(points, 'f4')}
        write_pcd(folder / f'full{i}.pcd', pts, extra)
        clouds.append(pts[1:])
    return folder, clouds


def test_convert_folder_with_tum_poses(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    folder, clouds = _folder(tmp_path)
    T = np.tile(np.eye(4), (4, 1, 1))
    T[:, 0, 3] = np.arange(4) * 0.5
    stamps = 1_630_577_758_569_490_000 + np.arange(4) * 499_457_000
    write_tum(tmp_path / 'gt.tum', stamps, T)
    out = tmp_path / 'out'
    code = main(
        [
            str(folder),
            '--poses',
            str(tmp_path / 'gt.tum'),
            '--fields',
            'intensity',
            '-o',
            str(out),
            '-q',
        ]
    )
    assert code == 0
    topics = bag_topics(out)
    assert (topics['/points'].count, topics['/ground_truth'].count) == (4, 4)
    scans = list(open_scan_source(out))
    assert [s.stamp_ns for s in scans] == list(stamps)
    assert {s.frame_id for s in scans} == {'lidar'}
    for scan, pts in zip(scans, clouds, strict=True):
        np.testing.assert_array_equal(scan.points, pts)
        assert list(scan.extras) == ['intensity']
        np.testing.assert_array_equal(scan.extras['intensity'], np.arange(1, 3000))
    gt = read_ground_truth(out)
    np.testing.assert_array_equal(gt.stamps_ns, stamps)
    np.testing.assert_allclose(gt.T_world_sensor, T, atol=1e-12)
    assert 'kentreg_convert' in (out / 'metadata.yaml').read_text()
    assert capsys.readouterr().err == ''


def test_convert_files_in_given_order_by_rate_with_voxels(tmp_path: Path) -> None:
    folder, clouds = _folder(tmp_path, n=2)
    write_kitti(tmp_path / 'poses.txt', np.tile(np.eye(4), (2, 1, 1)))
    out = tmp_path / 'pair'
    code = main(
        [
            str(folder / 'full1.pcd'),
            str(folder / 'full0.pcd'),
            '--poses',
            str(tmp_path / 'poses.txt'),
            '--rate',
            '2',
            '--start-time',
            '5',
            '--voxel-size',
            '2.0',
            '-o',
            str(out),
            '-q',
        ]
    )
    assert code == 0
    scans = list(open_scan_source(out))
    assert [s.stamp_ns for s in scans] == [5_000_000_000, 5_500_000_000]
    assert len(scans[0].points) < 1500  # downsampled
    # Fields come from the nearest original point: values stay members of the original set.
    assert set(scans[0].extras) == {'intensity', 'curvature'}
    assert np.isin(scans[0].extras['intensity'], np.arange(1, 3000)).all()
    assert read_ground_truth(out).stamps_ns.tolist() == [5_000_000_000, 5_500_000_000]


def test_downsample_scan_keeps_nearest_fields() -> None:
    pts = np.array([[0.01, 0.01, 0.01], [0.02, 0.0, 0.0], [5.0, 5.0, 5.0]])
    ring = np.array([3, 4, 9], dtype=np.uint16)
    centroids, extras = downsample_scan(pts, {'ring': ring}, 1.0)
    assert len(centroids) == 2
    assert sorted(extras['ring'].tolist()) in ([3, 9], [4, 9])
    assert extras['ring'].dtype == np.uint16


def test_convert_real_balm_subset(shared_data: Path, tmp_path: Path) -> None:
    folder = tmp_path / 'balm3'
    folder.mkdir()
    for i in range(3):
        (folder / f'full{i}.pcd').symlink_to(shared_data / 'balm' / f'full{i}.pcd')
    poses = shared_data / 'balm' / 'alidarPose.csv'
    (folder / 'alidarPose.csv').write_text('\n'.join(poses.read_text().splitlines()[:12]) + '\n')
    out = tmp_path / 'balm3_bag'
    assert (
        main(
            [
                str(folder),
                '--poses',
                str(folder / 'alidarPose.csv'),
                '--voxel-size',
                '0.11',
                '--fields',
                'intensity',
                '-o',
                str(out),
                '-q',
            ]
        )
        == 0
    )
    scans = list(open_scan_source(out))
    ref = read_poses(poses)
    assert [s.stamp_ns for s in scans] == ref.stamps_ns[:3].tolist()
    assert all(18_000 < len(s.points) < 26_000 for s in scans)


@pytest.mark.parametrize(
    ('args', 'message'),
    [
        (['--poses', '{tmp}/few.tum'], '1 poses for 4 scans'),
        (['--topic', '/points'], '--topic applies to bags'),
        (['--fields', 'rgb'], "no field 'rgb'"),
    ],
)
def test_convert_errors_are_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture, args: list[str], message: str
) -> None:
    folder, _ = _folder(tmp_path)
    (tmp_path / 'few.tum').write_text('1.0 0 0 0 0 0 0 1\n')
    argv = [str(folder), '-o', str(tmp_path / 'out'), '-q'] + [
        a.format(tmp=tmp_path) for a in args
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and err.startswith('kentreg_convert: error: ')
    assert message in err
    assert not (tmp_path / 'out').exists()  # nothing written, no empty bag left behind


def test_convert_refuses_to_overwrite_and_bad_arguments(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    folder, _ = _folder(tmp_path, n=1)
    out = tmp_path / 'out'
    assert main([str(folder), '-o', str(out), '-q']) == 0
    assert main([str(folder), '-o', str(out), '-q']) == 2
    assert 'exists; not overwriting' in capsys.readouterr().err
    assert main([str(folder), '-o', str(out), '-q', '--overwrite']) == 0
    assert main([str(tmp_path / 'missing'), '-o', str(tmp_path / 'o2'), '-q']) == 2
    assert 'neither a bag' in capsys.readouterr().err
    for bad in (['--rate', '0'], ['--voxel-size', '-1'], ['--times', 't.txt'], ['--bogus']):
        assert main([str(folder), '-o', str(tmp_path / 'o3'), *bad]) == 2
        err = capsys.readouterr().err
        assert err.count('\n') == 1 and err.startswith('kentreg_convert: error: ')
        assert bad[0] in err
    assert not (tmp_path / 'o3').exists()


def test_convert_stops_at_a_bad_scan_and_keeps_what_came_before(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    folder, clouds = _folder(tmp_path)
    raw = (folder / 'full2.pcd').read_bytes()
    (folder / 'full2.pcd').write_bytes(raw[: len(raw) - 100])
    out = tmp_path / 'out'
    assert main([str(folder), '-o', str(out), '-q']) == 2
    err = capsys.readouterr().err
    assert 'full2.pcd: PCD binary data is truncated' in err
    assert f'(2 scan(s) written to {out} before this)' in err
    scans = list(open_scan_source(out))
    assert len(scans) == 2
    np.testing.assert_array_equal(scans[1].points, clouds[1])


def test_convert_truncated_bag_keeps_messages_before_the_cut(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    folder, _ = _folder(tmp_path, n=6, points=20000)  # 400 kB per scan: several MCAP chunks
    full = tmp_path / 'full'
    assert main([str(folder), '--no-compress', '-o', str(full), '-q']) == 0
    raw = (full / 'full.mcap').read_bytes()
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(raw[: int(len(raw) * 0.7)])
    out = tmp_path / 'rescued'
    assert main([str(cut), '-o', str(out), '-q']) == 2
    # The reader says once (a warning, shown with -q too) that it salvages the records; the
    # error that ends the conversion is one line.
    warning, error = capsys.readouterr().err.splitlines()
    assert warning.startswith('kentreg_convert: WARNING: ') and 'one by one' in warning
    assert error.startswith('kentreg_convert: error: ')
    assert 'MCAP file is truncated or corrupt after' in error
    assert 1 <= len(list(open_scan_source(out))) < 6
    cut.write_bytes(raw[:5000])
    assert main([str(cut), '-o', str(tmp_path / 'nothing'), '-q']) == 2
    assert 'truncated or corrupt before any complete chunk' in capsys.readouterr().err
