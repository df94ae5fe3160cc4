"""kentreg_node's localization mode over DDS: a node subprocess with a ``map_file``.

The map holds the sample bag's even scans at their reference poses (written with the package's
writers, with its trajectory beside it); the odd scans are published at about their recorded
pace, so the localization's hand-over skips what it cannot take. The node's ``~/state`` and
``~/pose`` are subscribed, ``initialpose`` published and ``~/relocalize`` called over DDS (the
harness of ``test_node.py``: loopback, a test-only domain, every name under a prefix of the
test's own). Without tf2_ros (not on PyPI) the node sends no /tf: ``map -> odom`` is checked by
``test_ros_localization.py`` with stand-in broadcasters.
"""

from __future__ import annotations

import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy', reason="rclpy is not installed (pip install -e '.[ros]')")

from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import String  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from test_node import Harness, NodeProcess, cloud_msg, pose_matrix, stamp_ns  # noqa: E402

from kentreg_ros.core import exp_so3, make_transform, rotation_angle  # noqa: E402
from kentreg_ros.io.mapfile import write_map  # noqa: E402
from kentreg_ros.io.poses import write_tum  # noqa: E402
from kentreg_ros.io.recordings import open_recording  # noqa: E402
from kentreg_ros.ros.messages import pose_to_msg  # noqa: E402

#: Node subprocesses over DDS: the integration tier.
pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / 'bags' / 'balm_50'
#: The localization's names, remapped under the test's prefix like the others.
LOCALIZATION_NAMES = ('/kentreg_node/pose', '/kentreg_node/state', '/kentreg_node/relocalize')
#: Seconds between published scans: the odd scans are a second apart in the recording.
PACE_S = 1.0


@pytest.fixture
def harness(tmp_path: Path) -> Iterator[Harness]:
    h = Harness(tmp_path)
    try:
        yield h
    finally:
        h.close()


@pytest.fixture(scope='module')
def site(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[Any], np.ndarray, Path]:
    """The sample's scans, their reference poses, and the map of the even ones."""
    rec = open_recording(BAG)
    scans = list(rec.source)
    assert rec.reference is not None
    T = np.asarray(rec.reference.T_world_sensor, dtype=np.float64)
    even = list(range(0, len(scans), 2))
    world = np.concatenate(
        [np.asarray(scans[i].points) @ T[i, :3, :3].T + T[i, :3, 3] for i in even]
    )
    folder = tmp_path_factory.mktemp('site')
    write_map(folder / 'map.ply', world)
    write_tum(folder / 'trajectory_tum.txt', np.array([scans[i].stamp_ns for i in even]), T[even])
    return scans, T, folder / 'map.ply'


def errors(T: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    D = np.linalg.inv(truth) @ T
    return float(np.linalg.norm(D[:3, 3])), float(np.degrees(rotation_angle(D[:3, :3])))


def test_node_localizes_takes_an_initial_pose_and_relocalizes_over_dds(
    harness: Harness, site: tuple[list[Any], np.ndarray, Path]
) -> None:
    scans, T_ref, map_file = site
    remaps = [a for name in LOCALIZATION_NAMES for a in ('-r', f'{name}:={harness.name(name)}')]
    proc = harness.start_node('-p', f'map_file:={map_file}', '-p', 'qos_reliability:=reliable',
                              *remaps)  # fmt: skip
    out = harness.connect(proc)
    node = harness.node
    states: list[str] = []
    poses: list[Any] = []
    latched = QoSProfile(
        depth=1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
    node.create_subscription(
        String, harness.name('/kentreg_node/state'), lambda m: states.append(m.data), latched
    )
    node.create_subscription(
        PoseWithCovarianceStamped, harness.name('/kentreg_node/pose'), poses.append,
        QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE),
    )  # fmt: skip
    # Transient-local: the state published at start-up reaches this late subscriber.
    assert harness.spin_until(lambda: states == ['searching'], 20.0, proc), (states, proc.log())
    assert harness.spin_until(lambda: ' ready: ' in proc.log(), 60.0, proc), proc.log()

    odd = iter(range(1, len(scans), 2))
    sent: list[int] = []

    def publish_until(done: Callable[[], bool], what: str) -> None:
        """Publish the next odd scans, one per :data:`PACE_S`, until ``done``."""
        for i in odd:
            t0 = time.monotonic()
            out.pub.publish(cloud_msg(scans[i].points, scans[i].stamp_ns, scans[i].frame_id))
            sent.append(i)
            assert harness.spin_until(lambda: len(out.odom) == len(sent), 30.0, proc), proc.log()
            harness.spin_until(done, max(PACE_S - (time.monotonic() - t0), 0.0), proc)
            if done():
                return
        raise AssertionError(f'ran out of scans before {what}: {states}\n{proc.log()}')

    # From no start: searching, then localized once enough scans agree.
    publish_until(lambda: bool(states) and states[-1] == 'localized', 'the first localization')
    assert states == ['searching', 'localized'], states
    assert harness.spin_until(lambda: bool(poses), 10.0, proc), proc.log()
    by_stamp = {s.stamp_ns: i for i, s in enumerate(scans)}
    for msg in poses:
        assert msg.header.frame_id == 'map'
        i = by_stamp[stamp_ns(msg.header.stamp)]
        e_t, e_r = errors(pose_matrix(msg.pose.pose), T_ref[i])
        assert e_t < 0.5 and e_r < 2.0, (i, e_t, e_r)
        assert all(np.isfinite(msg.pose.covariance)) and msg.pose.covariance[0] > 0

    # An initial pose (as RViz's 2D Pose Estimate sends it): searched within its window.
    pose_pub = node.create_publisher(PoseWithCovarianceStamped, harness.name('/initialpose'), 10)
    assert harness.spin_until(lambda: pose_pub.get_subscription_count() >= 1, 10.0, proc)
    latest = T_ref[sent[-1]] @ make_transform(exp_so3([0.0, 0.0, np.radians(5.0)]), [0.5, 0, 0])
    msg = PoseWithCovarianceStamped()
    msg.header.frame_id = 'map'
    msg.pose.pose = pose_to_msg(latest)
    msg.pose.covariance = [float(v) for v in np.diag([0.25, 0.25, 0, 0, 0, 0.07]).ravel()]
    pose_pub.publish(msg)
    assert harness.spin_until(lambda: 'Initial pose in map' in proc.log(), 10.0, proc)
    assert 'within 1.50 m' in proc.log()
    publish_until(lambda: states[-2:] == ['searching', 'localized'] and len(states) == 4,
                  'the localization from the initial pose')  # fmt: skip

    # ~/relocalize: a search from no start; the state goes back to searching, then localized.
    client = node.create_client(Trigger, harness.name('/kentreg_node/relocalize'))
    assert client.wait_for_service(timeout_sec=10.0)
    future = client.call_async(Trigger.Request())
    assert harness.spin_until(future.done, 30.0, proc), proc.log()
    assert future.result().success, future.result().message
    publish_until(lambda: len(states) == 6, 'the relocalization')
    assert states == ['searching', 'localized'] * 3, states
    last = poses[-1]
    e_t, e_r = errors(pose_matrix(last.pose.pose), T_ref[by_stamp[stamp_ns(last.header.stamp)]])
    assert e_t < 0.5 and e_r < 2.0, (e_t, e_r)
    assert 'Traceback' not in proc.log()
    assert proc.stop() == 0, proc.log()


def test_node_exits_1_naming_a_map_file_that_does_not_exist(harness: Harness) -> None:
    proc: NodeProcess = harness.start_node('-p', 'map_file:=/nonexistent/site.ply')
    try:
        code = proc.proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        pytest.fail(f'kentreg_node kept running without its map:\n{proc.log()}')
    log = proc.log()
    assert code == 1, log
    assert "map_file '/nonexistent/site.ply': no such file" in log, log
    assert 'Traceback' not in log
