"""The sample bags shipped in bags/: contents, stamps, ground truth, licenses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kentreg_ros.io.bags import bag_topics
from kentreg_ros.io.poses import read_poses
from kentreg_ros.io.recordings import read_ground_truth
from kentreg_ros.io.sources import open_scan_source

BALM_FIRST_NS = 1_630_577_758_569_490_000
BALM_LAST_NS = 1_630_577_783_069_794_000


@pytest.fixture(scope='module')
def bags(repo_root: Path) -> Path:
    return repo_root / 'bags'


def test_balm_sample_bag(bags: Path) -> None:
    bag = bags / 'balm_50'
    assert (bag / 'balm_50.mcap').stat().st_size < 15_000_000
    topics = bag_topics(bag)
    assert topics['/points'].msgtype == 'sensor_msgs/msg/PointCloud2'
    assert topics['/ground_truth'].msgtype == 'geometry_msgs/msg/PoseStamped'
    assert (topics['/points'].count, topics['/ground_truth'].count) == (50, 50)
    scans = list(open_scan_source(bag))
    sizes = [len(s.points) for s in scans]
    assert 15_000 <= min(sizes) and max(sizes) <= 26_000
    assert {s.frame_id for s in scans} == {'lidar'}
    assert all(list(s.extras) == ['intensity'] for s in scans)
    stamps = [s.stamp_ns for s in scans]
    assert stamps[0] == BALM_FIRST_NS and stamps[-1] == BALM_LAST_NS
    assert np.all(np.diff(stamps) > 0)
    ranges = np.linalg.norm(scans[0].points, axis=1)
    assert 0.5 < ranges.min() and ranges.max() < 60.0
    gt = read_ground_truth(bag)
    np.testing.assert_array_equal(gt.stamps_ns, stamps)
    # Pose 50 of alidarPose.csv: translation 3.462937, 8.477385, 0.090855.
    np.testing.assert_allclose(gt.T_world_sensor[-1, :3, 3], [3.462937, 8.477385, 0.090855])
    np.testing.assert_allclose(gt.T_world_sensor[0, :3, :3], np.eye(3), atol=3e-3)


def test_balm_sample_matches_its_source(bags: Path, shared_data: Path) -> None:
    ref = read_poses(shared_data / 'balm' / 'alidarPose.csv')
    gt = read_ground_truth(bags / 'balm_50')
    np.testing.assert_array_equal(gt.stamps_ns, ref.stamps_ns)
    # The file's rotations have 6 decimals; PoseStamped stores the nearest true rotation.
    np.testing.assert_allclose(gt.T_world_sensor, ref.T_world_sensor, atol=2e-6)


def test_small_gicp_pair_bag(bags: Path) -> None:
    bag = bags / 'small_gicp_pair'
    scans = list(open_scan_source(bag))
    assert [len(s.points) for s in scans] == [69088, 69792]  # target (scan 0), source (scan 1)
    assert [s.stamp_ns for s in scans] == [1_000_000_000, 2_000_000_000]
    np.testing.assert_allclose(
        scans[0].points[0],
        [0.0031398916617035866, 2.570034980773926, -1.5241568088531494],
        rtol=0,
        atol=0,
    )
    T_target_source = np.loadtxt(bags / 'small_gicp_pair_T_target_source.txt')
    gt = read_ground_truth(bag)
    np.testing.assert_allclose(gt.T_world_sensor[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(gt.T_world_sensor[1], T_target_source, atol=2e-6)
    np.testing.assert_array_equal(gt.stamps_ns, [1_000_000_000, 2_000_000_000])


def test_bags_readme_and_licenses(bags: Path) -> None:
    readme = (bags / 'README.md').read_text()
    assert 'GPL-2.0' in readme and 'MIT' in readme and 'kentreg_convert' in readme
    assert 'GNU GENERAL PUBLIC LICENSE' in (bags / 'LICENSE.balm-GPL-2.0').read_text()
    assert 'MIT License' in (bags / 'LICENSE.small_gicp-MIT').read_text()
