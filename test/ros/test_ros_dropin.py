"""kentreg_node as a ROS user drops it in: no parameters, the sample bag, RViz.

The node is real rclpy, constructed in this process (as in ``test_ros_node.py``: nothing spins
it, its timers are cancelled) and fed the scans of ``bags/balm_50`` (frame ``lidar``, no
``/tf``) the way its subscription callback is; its topics are read back from the ROS graph, its
messages from its publishers. The graph is the domain's, which other test runs on this machine
may share: every node here has a name of its own, and the graph is asked about that node.
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip('rclpy', reason="rclpy is not installed (pip install -e '.[ros]')")

from builtin_interfaces.msg import Time  # noqa: E402
from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import ReliabilityPolicy  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402
from sensor_msgs.msg import PointCloud2, PointField  # noqa: E402
from std_msgs.msg import Header  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from kentreg_ros.core import KentRegConfig, Odometry, prepare_scan  # noqa: E402
from kentreg_ros.eval.run import run_odometry  # noqa: E402
from kentreg_ros.io import names  # noqa: E402
from kentreg_ros.io.params import NodeSettings  # noqa: E402
from kentreg_ros.io.pointcloud2 import (  # noqa: E402
    array_to_pointcloud2,
    pointcloud2_to_array,
    rclpy_factory,
)
from kentreg_ros.io.sources import open_scan_source  # noqa: E402
from kentreg_ros.ros import node as node_module  # noqa: E402
from kentreg_ros.ros.messages import pose_from_msg, pose_to_msg  # noqa: E402

#: rclpy nodes (DDS participants) in this process: the integration tier.
pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / 'bags' / 'balm_50'
RVIZ = REPO / 'rviz' / 'kentreg.rviz'
FACTORY = rclpy_factory(PointCloud2, PointField, Header, Time)
TIMEOUT_S = 60.0


@pytest.fixture(scope='module')
def scans() -> list[Any]:
    return list(open_scan_source(BAG))[:4]


@pytest.fixture
def make_node(rclpy_context: Any) -> Iterator[Callable[..., Any]]:
    """KentRegNode in a private context under a name of its own, its timers cancelled (the
    tests send the path and the map themselves); destroyed afterwards."""
    nodes: list[Any] = []

    def make(**kwargs: Any) -> Any:
        kwargs.setdefault('node_name', unique_name())
        node = node_module.KentRegNode(context=rclpy_context, **kwargs)
        nodes.append(node)
        for timer in node.timers:
            timer.cancel()
        return node

    yield make
    for node in nodes:
        if node.handle is not None:
            node.destroy_node()


def unique_name() -> str:
    """A node name no other node in the domain has (another test run may run a kentreg_node)."""
    return f'kentreg_test_{uuid.uuid4().hex[:8]}'


def published(node: Any) -> int:
    """Scans whose outputs went out (the worker counts ``processed`` before them)."""
    return int(node._counters.total['published'])


def feed(node: Any, scan: Any) -> None:
    """Hand one bag scan to the node as its subscription does; wait until its outputs are out."""
    before = published(node)
    node._on_points(
        array_to_pointcloud2(
            scan.points, stamp_ns=scan.stamp_ns, frame_id=scan.frame_id, factory=FACTORY
        )
    )
    deadline = time.monotonic() + TIMEOUT_S
    while published(node) == before:
        assert time.monotonic() < deadline, 'the scan was not processed'
        time.sleep(0.01)


def capture(monkeypatch: pytest.MonkeyPatch, publisher: Any) -> list[Any]:
    sent: list[Any] = []
    monkeypatch.setattr(publisher, 'publish', sent.append)
    return sent


def stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * 10**9 + int(stamp.nanosec)


def published_topics(node: Any) -> set[str]:
    return {t for t, _ in node.get_publisher_names_and_types_by_node(node.get_name(), '/')}


def test_with_no_parameters_the_cloud_frame_moves_under_one_prefix(
    make_node: Any, scans: list[Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A bare bag (frame ``lidar``, no /tf): the odometry's child frame is the cloud's, so the
    input cloud can be drawn; no ``/odom`` (a robot's wheel odometry) is taken; a registered
    cloud per scan at its stamp; diagnostics on /diagnostics."""
    node = make_node()
    odoms = capture(monkeypatch, node._outputs.odom)
    clouds = capture(monkeypatch, node._outputs.cloud)
    for scan in scans:
        feed(node, scan)
    assert {m.child_frame_id for m in odoms} == {'lidar'}
    assert {m.header.frame_id for m in odoms} == {'odom'}
    topics = published_topics(node)
    expected = {names.ODOMETRY, names.POSE, names.PATH, names.CLOUD_REGISTERED, names.MAP}
    assert {names.absolute(n) for n in expected} | {'/diagnostics'} <= topics
    assert not {'/odom', '/pose', '/path', '/map'} & topics, topics
    # One registered cloud per scan, at its stamp, in odom: the first is the first scan's
    # prepared points (its pose is the identity).
    assert [stamp_ns(c.header.stamp) for c in clouds] == [s.stamp_ns for s in scans]
    assert {c.header.frame_id for c in clouds} == {'odom'}
    first = prepare_scan(np.asarray(scans[0].points, dtype=np.float64)).points
    np.testing.assert_allclose(pointcloud2_to_array(clouds[0]).points, first, atol=1e-5)
    # Later clouds are the scan's prepared points moved by the published pose.
    T = pose_from_msg(odoms[-1].pose.pose)
    last = pointcloud2_to_array(clouds[-1]).points
    in_sensor = (last - T[:3, 3]) @ T[:3, :3]
    assert np.abs(in_sensor).max() < 200.0 and len(last) > 1000


def test_the_registered_cloud_can_be_in_the_sensor_frame(
    make_node: Any, scans: list[Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    node = make_node(parameter_overrides=[Parameter('registered_cloud', value='sensor')])
    clouds = capture(monkeypatch, node._outputs.cloud)
    feed(node, scans[0])
    (cloud,) = clouds
    assert cloud.header.frame_id == 'lidar'


def _initial_pose(T: np.ndarray, frame: str = 'odom') -> Any:
    msg = PoseWithCovarianceStamped()
    msg.header.frame_id = frame
    msg.pose.pose = pose_to_msg(T)
    return msg


def test_an_initial_pose_moves_the_next_pose_and_the_path(
    make_node: Any, scans: list[Any], monkeypatch: pytest.MonkeyPatch,
    capfd: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    """RViz's "2D Pose Estimate" (geometry_msgs/PoseWithCovarianceStamped on initialpose):
    the latest pose becomes the one given and the next scan follows from it by its motion; the
    path is moved along. A pose in a frame tf2 cannot relate to odom is refused, said."""
    node = make_node()
    odoms = capture(monkeypatch, node._outputs.odom)
    paths = capture(monkeypatch, node._outputs.path)
    assert {t for t, _ in node.get_subscriber_names_and_types_by_node(node.get_name(), '/')} >= {
        '/initialpose',
        '/points',
    }
    for scan in scans[:2]:
        feed(node, scan)
    T_before = [pose_from_msg(m.pose.pose) for m in odoms]
    P = np.eye(4)
    P[:3, :3] = Rotation.from_euler('z', 90, degrees=True).as_matrix()
    P[:3, 3] = [10.0, -5.0, 0.0]
    node._on_initial_pose(_initial_pose(P, frame='map'))  # no tf2: cannot be used
    assert 'Ignored an initialpose message' in capfd.readouterr().err
    node._on_initial_pose(_initial_pose(P))
    feed(node, scans[2])
    T_next = pose_from_msg(odoms[-1].pose.pose)
    # The motion from scan 1 to scan 2 (from the odometry alone) is kept, now starting at P.
    reference = run_odometry(scans[:3], Odometry(KentRegConfig()))
    T_wl = reference.poses
    np.testing.assert_allclose(T_before[1], T_wl[1], atol=1e-9)
    np.testing.assert_allclose(T_next, P @ np.linalg.inv(T_wl[1]) @ T_wl[2], atol=1e-9)
    assert np.linalg.norm(T_next[:3, 3] - P[:3, 3]) < 0.1
    # The path was redrawn: its pose of scan 1 is now P.
    assert node._outputs.publish_path(node._worker.settings, force=True)
    poses = [pose_from_msg(p.pose) for p in paths[-1].poses]
    assert len(poses) == 3
    np.testing.assert_allclose(poses[1], P, atol=1e-9)


def test_save_map_writes_the_map_of_the_whole_run_and_the_trajectory(
    make_node: Any, scans: list[Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """~/save_map writes map.ply (read back by plyfile, an independent reader) and a TUM
    trajectory, and answers with their paths; the map is the replay's map of the same scans
    (one map class, the same points), the published map a view of it around the sensor."""
    plyfile = pytest.importorskip('plyfile')
    node = make_node(
        parameter_overrides=[
            Parameter('map_directory', value=str(tmp_path / 'maps')),
            Parameter('map_radius', value=10.0),
        ]
    )
    maps = capture(monkeypatch, node._outputs.map)
    answer = node._on_save_map(Trigger.Request(), Trigger.Response())
    assert not answer.success and 'no scan' in answer.message
    for scan in scans:
        feed(node, scan)
    answer = node._on_save_map(Trigger.Request(), Trigger.Response())
    assert answer.success, answer.message
    (folder,) = (tmp_path / 'maps').iterdir()
    ply_path, tum_path = folder / 'map.ply', folder / 'trajectory_tum.txt'
    assert str(ply_path) in answer.message and str(tum_path) in answer.message
    vertex = plyfile.PlyData.read(str(ply_path))['vertex']
    saved = np.column_stack([vertex['x'], vertex['y'], vertex['z']])
    # The replay's map of the same scans: identical.
    from kentreg_ros.cli.replay import MAP_VOXEL_SIZE

    assert MAP_VOXEL_SIZE == NodeSettings().map_voxel_size
    run = run_odometry(scans, Odometry(KentRegConfig()), map_voxel_size=MAP_VOXEL_SIZE)
    assert run.map is not None and len(saved) == len(run.map) > 10_000
    np.testing.assert_array_equal(saved, run.map.points)
    tum = np.loadtxt(tum_path, ndmin=2)
    np.testing.assert_allclose(tum[:, 0], [s.stamp_ns * 1e-9 for s in scans], atol=1e-6)
    np.testing.assert_allclose(tum[:, 1:4], run.poses[:, :3, 3], atol=1e-6)
    # A second save goes to a new folder.
    assert node._on_save_map(Trigger.Request(), Trigger.Response()).success
    assert len(list((tmp_path / 'maps').iterdir())) == 2
    # The published map: the saved map's points within map_radius of the sensor.
    assert node._outputs.publish_map(node._worker.settings, force=True)
    shown = pointcloud2_to_array(maps[-1]).points
    assert maps[-1].header.frame_id == 'odom' and 0 < len(shown) < len(saved)
    assert np.linalg.norm(shown - run.poses[-1][:3, 3], axis=1).max() <= 10.0 + 1e-4
    near = np.linalg.norm(saved - run.poses[-1][:3, 3], axis=1) <= 10.0 - 1e-4
    assert len(shown) >= np.count_nonzero(near)


def test_qos_overrides_apply_to_the_input_and_the_outputs(make_node: Any) -> None:
    """``qos_overrides.<topic>.<entity>.<policy>`` (rclpy's QoSOverridingOptions) reach the
    endpoints: the input's reliability as DDS sees it, the depths as rclpy created them."""
    node = make_node(
        parameter_overrides=[
            Parameter('qos_overrides./points.subscription.reliability', value='reliable'),
            Parameter('qos_overrides./points.subscription.depth', value=7),
            Parameter('qos_overrides./kentreg/odometry.publisher.depth', value=3),
        ]
    )
    (info,) = [
        i
        for i in node.get_subscriptions_info_by_topic('/points')
        if (i.node_name, i.node_namespace) == (node.get_name(), node.get_namespace())
    ]
    assert info.qos_profile.reliability == ReliabilityPolicy.RELIABLE
    assert node._sub.qos_profile.depth == 7
    assert node._outputs.odom.qos_profile.depth == 3
    default = make_node()
    assert default._sub.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
    assert default._sub.qos_profile.depth == NodeSettings().qos_depth
    bad = [Parameter('qos_overrides./points.subscription.reliability', value='fifo')]
    with pytest.raises(node_module.StartupError, match='qos_overrides.*fifo'):
        make_node(parameter_overrides=bad)


def _rviz_topics(config: Any) -> dict[str, str]:
    """``{display class: topic}`` of every display with a topic (groups flattened)."""
    out: dict[str, str] = {}

    def walk(displays: list[Any]) -> None:
        for d in displays:
            if 'Displays' in d:
                walk(d['Displays'])
            topic = d.get('Topic')
            if isinstance(topic, dict) and topic.get('Value'):
                out.setdefault(topic['Value'], d['Class'])

    walk(config['Visualization Manager']['Displays'])
    return out


def test_the_rviz_file_parses_and_shows_what_the_node_publishes(make_node: Any) -> None:
    config = yaml.safe_load(RVIZ.read_text(encoding='utf-8'))
    manager = config['Visualization Manager']
    assert manager['Global Options']['Fixed Frame'] == NodeSettings().odom_frame
    shown = _rviz_topics(config)
    node = make_node()
    subscribed = {t for t, _ in node.get_subscriber_names_and_types_by_node(node.get_name(), '/')}
    assert set(shown) <= published_topics(node) | subscribed, shown
    classes = {
        names.absolute(names.ODOMETRY): 'rviz_default_plugins/Odometry',
        names.absolute(names.PATH): 'rviz_default_plugins/Path',
        names.absolute(names.CLOUD_REGISTERED): 'rviz_default_plugins/PointCloud2',
        names.absolute(names.MAP): 'rviz_default_plugins/PointCloud2',
        names.absolute(names.POINTS): 'rviz_default_plugins/PointCloud2',
    }
    assert {t: shown.get(t) for t in classes} == classes
    displays = [d['Class'] for d in manager['Displays']]
    assert 'rviz_default_plugins/TF' in displays
    # The map is latched: RViz must ask for transient-local to get it when it starts late.
    map_display = next(
        d for d in manager['Displays'] if d.get('Topic', {}).get('Value') == '/kentreg/map'
    )
    assert map_display['Topic']['Durability Policy'] == 'Transient Local'
    # The 2D Pose Estimate tool publishes on the node's initialpose.
    tools = {t['Class']: t for t in manager['Tools']}
    pose_tool = tools['rviz_default_plugins/SetInitialPose']
    assert pose_tool['Topic']['Value'] == names.absolute(names.INITIAL_POSE)
