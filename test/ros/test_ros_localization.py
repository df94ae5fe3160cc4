"""The node's localization mode (``map_file``) in this process, with real rclpy.

A map of the sample bag's even scans at their reference poses (``map.ply`` and
``trajectory_tum.txt``, written with the package's writers into a temporary folder) and the odd
scans fed to an in-process :class:`KentRegNode` as its subscription callback hands them over
(a private rclpy context; the node is not spun, its timers are cancelled). Its ``~/state`` and
``~/pose`` go over DDS (loopback) to a listener node in the same context, spun here; tf2_ros is
not on PyPI, so the TF broadcasters are stand-ins that record what the node sends. Requests
(``initialpose``, ``~/relocalize``, ``~/reset``) go to the node's callbacks as the executor
would hand them over; ``test_node_localization.py`` sends them over DDS to a node subprocess.

The scans are fed in lockstep: the next one when the odometry published the last and the
localization placed it, so none is skipped and the states follow the scans.
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy', reason="rclpy is not installed (pip install -e '.[ros]')")

from builtin_interfaces.msg import Time  # noqa: E402
from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import PointCloud2, PointField  # noqa: E402
from std_msgs.msg import Header, String  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from kentreg_ros.core import (  # noqa: E402
    Preparation,
    PrepareInputs,
    RawScan,
    Window,
    exp_so3,
    log_so3,
    make_transform,
    rotation_angle,
)
from kentreg_ros.io.mapfile import write_map  # noqa: E402
from kentreg_ros.io.pointcloud2 import array_to_pointcloud2, rclpy_factory  # noqa: E402
from kentreg_ros.io.poses import write_tum  # noqa: E402
from kentreg_ros.io.recordings import open_recording  # noqa: E402
from kentreg_ros.ros import node as node_module  # noqa: E402
from kentreg_ros.ros.localization import KeepingPreparer  # noqa: E402
from kentreg_ros.ros.messages import (  # noqa: E402
    covariance_from_msg,
    pose_covariance_in_map,
    pose_from_msg,
    pose_to_msg,
    transform_from_msg,
)
from kentreg_ros.ros.services import (  # noqa: E402
    MIN_WINDOW_ANGLE_DEG,
    MIN_WINDOW_DISTANCE,
    search_window,
)

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / 'bags' / 'balm_50'
FACTORY = rclpy_factory(PointCloud2, PointField, Header, Time)
TIMEOUT_S = 120.0
#: Issue 39's bar for a placement: within 0.5 m and 2 degrees of the reference.
MAX_ERROR_M, MAX_ERROR_DEG = 0.5, 2.0
#: RViz's 2D Pose Estimate: x and y variance 0.25 m^2, yaw 0.0685 rad^2 (15 deg).
RVIZ_COVARIANCE = np.diag([0.25, 0.25, 0.0, 0.0, 0.0, 0.06853891909122467])


@dataclass(frozen=True)
class Sample:
    """The sample bag: its scans, their reference poses, and a map of the even ones."""

    scans: list[Any]
    T_ref: np.ndarray  # (50, 4, 4) T_world_lidar
    map_file: Path


@pytest.fixture(scope='module')
def sample(tmp_path_factory: pytest.TempPathFactory) -> Sample:
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
    return Sample(scans, T, folder / 'map.ply')


class Broadcaster:
    """Records what is sent (tf2_ros's ``sendTransform``)."""

    def __init__(self) -> None:
        self.sent: list[Any] = []

    def sendTransform(self, msg: Any) -> None:  # noqa: N802 - tf2_ros's name
        self.sent.append(msg)

    def transforms(self, parent: str, child: str) -> dict[int, np.ndarray]:
        """``{stamp_ns: T_parent_child}`` of what was sent from ``parent`` to ``child``."""
        return {
            int(m.header.stamp.sec) * 10**9 + int(m.header.stamp.nanosec): transform_from_msg(
                m.transform
            )
            for m in list(self.sent)
            if (m.header.frame_id, m.child_frame_id) == (parent, child)
        }


@dataclass
class Rig:
    """An in-process node in localization mode, its TF stand-in and a listener."""

    node: Any
    tf: Broadcaster
    states: list[str]
    poses: list[Any]
    executor: SingleThreadedExecutor

    @property
    def localization(self) -> Any:
        return self.node._localization

    def count(self, name: str) -> int:
        return int(self.localization.snapshot().counts[name])

    def spin_until(self, done: Callable[[], bool], timeout: float = TIMEOUT_S) -> bool:
        deadline = time.monotonic() + timeout
        while not done():
            if time.monotonic() > deadline:
                return False
            self.executor.spin_once(timeout_sec=0.02)
        return True

    def feed(self, scan: Any) -> None:
        """Hand ``scan`` over as the subscription does; wait until it is published and
        placed."""
        published = int(self.node._counters.total['published'])
        updates = self.count('updates')
        self.node._on_points(
            array_to_pointcloud2(
                np.asarray(scan.points), stamp_ns=scan.stamp_ns, frame_id='lidar',
                factory=FACTORY,
            )
        )  # fmt: skip
        assert self.spin_until(
            lambda: (
                self.node._counters.total['published'] > published
                and self.count('updates') > updates
            )
        ), ('the scan was not published and placed', self.localization.snapshot())

    def wait_map(self) -> None:
        assert self.spin_until(lambda: self.localization.snapshot().map_state != 'loading')
        assert self.localization.snapshot().map_state == 'ready', self.localization.snapshot()


@pytest.fixture
def make_rig(rclpy_context: Any) -> Iterator[Callable[..., Rig]]:
    rigs: list[Rig] = []

    def make(map_file: Path | str, **params: Any) -> Rig:
        name = f'kentreg_loc_{uuid.uuid4().hex[:8]}'
        tf = Broadcaster()
        overrides = [
            Parameter('map_file', value=str(map_file)),
            Parameter('pipeline', value='sequential'),
            *(Parameter(k, value=v) for k, v in params.items()),
        ]
        node = node_module.KentRegNode(
            context=rclpy_context,
            node_name=name,
            parameter_overrides=overrides,
            tf=(tf, Broadcaster(), None),
        )
        for timer in node.timers:
            timer.cancel()
        listener = rclpy.create_node(f'{name}_listener', context=rclpy_context)
        states: list[str] = []
        poses: list[Any] = []
        latched = QoSProfile(
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        listener.create_subscription(
            String, f'/{name}/state', lambda m: states.append(m.data), latched
        )
        listener.create_subscription(
            PoseWithCovarianceStamped, f'/{name}/pose', poses.append, QoSProfile(depth=100)
        )
        executor = SingleThreadedExecutor(context=rclpy_context)
        executor.add_node(listener)
        rig = Rig(node, tf, states, poses, executor)
        rigs.append(rig)
        return rig

    yield make
    for rig in rigs:
        rig.executor.shutdown()
        if rig.node.handle is not None:
            rig.node.destroy_node()


def errors(T: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) of ``T`` from ``truth``."""
    D = np.linalg.inv(truth) @ T
    return float(np.linalg.norm(D[:3, 3])), float(np.degrees(rotation_angle(D[:3, :3])))


def initial_pose(T_map_moving: np.ndarray, covariance: np.ndarray, frame: str = 'map') -> Any:
    msg = PoseWithCovarianceStamped()
    msg.header.frame_id = frame
    msg.pose.pose = pose_to_msg(T_map_moving)
    msg.pose.covariance = [float(v) for v in covariance.ravel()]
    return msg


def trigger(callback: Callable[[Any, Any], Any]) -> Any:
    return callback(Trigger.Request(), Trigger.Response())


# ------------------------------------------------------------------------------------------
# Without a node


def test_an_initial_pose_covariance_gives_a_window_of_three_sigma_with_floors() -> None:
    window = search_window(RVIZ_COVARIANCE.ravel())
    assert isinstance(window, Window)
    assert window.distance == pytest.approx(1.5)  # 3 x 0.5 m
    assert window.angle_deg == pytest.approx(3 * np.degrees(np.sqrt(0.0685389)), abs=0.01)
    wide = np.diag([4.0, 9.0, 100.0, 0.0, 0.0, 100.0])  # the larger of x and y; z not
    assert search_window(wide.ravel()) == Window(9.0, 180.0)
    floor = search_window(np.zeros(36))
    assert floor == Window(MIN_WINDOW_DISTANCE, MIN_WINDOW_ANGLE_DEG)
    assert 'not finite' in str(search_window([float('nan')] * 36))
    assert 'shape' in str(search_window([0.0] * 35))


def test_the_localization_covariance_becomes_a_pose_covariance_in_the_map() -> None:
    """Against finite differences: the registration's left perturbation ``exp(delta) T`` in
    the map frame read as the position and rotation errors of a nav_msgs pose."""
    rng = np.random.default_rng(1)
    T = make_transform(exp_so3(rng.normal(size=3)), [12.0, -7.0, 1.5])

    def perturbed(delta: np.ndarray) -> np.ndarray:
        E = make_transform(exp_so3(delta[3:]), np.zeros(3))
        E[:3, 3] = delta[:3]  # exp's translation to first order
        return E @ T

    J = np.zeros((6, 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = 1e-6
        plus, minus = perturbed(d), perturbed(-d)
        J[:3, k] = (plus[:3, 3] - minus[:3, 3]) / 2e-6
        J[3:, k] = (
            log_so3(plus[:3, :3] @ T[:3, :3].T) - log_so3(minus[:3, :3] @ T[:3, :3].T)
        ) / 2e-6
    L = rng.normal(size=(6, 6))
    cov = L @ L.T
    np.testing.assert_allclose(pose_covariance_in_map(cov, T), J @ cov @ J.T, rtol=1e-5, atol=1e-6)


def test_the_keeping_preparer_hands_over_the_scan_the_last_step_prepared() -> None:
    class Inner:
        expected: Any = None

        def prepare(self, scan: RawScan, inputs: PrepareInputs) -> Preparation:
            return Preparation(None, scan.points, '')  # type: ignore[arg-type]

        def expect(self, inputs: PrepareInputs) -> None:
            self.expected = inputs

    inner = Inner()
    keeper = KeepingPreparer(inner)
    assert keeper.prepared(5) is None
    marker: Any = object()
    keeper.prepare(RawScan(marker, None, 5), None)  # type: ignore[arg-type]
    assert keeper.prepared(5) is marker and keeper.prepared(6) is None
    keeper.expect(marker)
    assert inner.expected is marker


# ------------------------------------------------------------------------------------------
# The node in localization mode


def test_a_map_file_that_is_no_map_stops_the_node_naming_it(
    make_rig: Callable[..., Rig], tmp_path: Path
) -> None:
    missing = tmp_path / 'nowhere' / 'site.ply'
    with pytest.raises(node_module.StartupError, match=f"map_file '{missing}': no such file"):
        make_rig(missing)
    text = tmp_path / 'site.txt'
    text.write_text('not a map')
    with pytest.raises(node_module.StartupError, match='not a point-cloud file') as caught:
        make_rig(text)
    assert caught.value.names == ('map_file',)


def test_a_map_that_cannot_be_read_is_an_error_and_the_odometry_goes_on(
    make_rig: Callable[..., Rig], sample: Sample, tmp_path: Path
) -> None:
    broken = tmp_path / 'broken.ply'
    broken.write_bytes(b'ply\nformat binary_little_endian 1.0\nelement vertex 9\nend_header\n')
    rig = make_rig(broken)
    assert rig.spin_until(lambda: rig.localization.snapshot().map_state == 'failed', 30.0)
    snap = rig.localization.snapshot()
    assert str(broken) in snap.map_message and 'odometry goes on' in snap.map_message
    from kentreg_ros.ros.diagnostics import localization_status

    assert localization_status('n', snap).level == localization_status('n', snap).ERROR
    answer = trigger(rig.node._on_relocalize)
    assert not answer.success and str(broken) in answer.message
    for scan in sample.scans[1:5:2]:
        published = int(rig.node._counters.total['published'])
        rig.node._on_points(
            array_to_pointcloud2(
                np.asarray(scan.points), stamp_ns=scan.stamp_ns, frame_id='lidar',
                factory=FACTORY,
            )
        )  # fmt: skip
        assert rig.spin_until(lambda p=published: rig.node._counters.total['published'] > p)
    assert rig.tf.transforms('odom', 'lidar') and not rig.tf.transforms('map', 'odom')


@pytest.mark.integration
def test_the_node_localizes_after_agreeing_scans_and_publishes_map_to_odom(
    make_rig: Callable[..., Rig], sample: Sample
) -> None:
    rig = make_rig(sample.map_file)
    assert rig.spin_until(lambda: rig.states == ['searching'], 10.0), rig.states  # latched
    rig.wait_map()
    agreement = rig.localization._config.localization.agreement
    odd = list(range(1, 20, 2))
    states = []
    for k, i in enumerate(odd):
        rig.feed(sample.scans[i])
        states.append(rig.localization.state)
        map_odom = rig.tf.transforms('map', 'odom')
        # Never a map -> odom before the first placement; then one with every odometry step
        # (the worker sends it with each step, from the placement of the scans before).
        assert bool(map_odom) == (k >= agreement), (k, states)
    assert states[: agreement - 1] == ['searching'] * (agreement - 1)
    assert states[agreement - 1 :] == ['localized'] * (len(odd) - agreement + 1), states
    assert rig.spin_until(lambda: rig.states[-1] == 'localized', 10.0)
    assert rig.states == ['searching', 'localized']

    # map -> odom composed with odom -> lidar at the same stamp puts each scan at its
    # reference pose.
    map_odom, odom_lidar = rig.tf.transforms('map', 'odom'), rig.tf.transforms('odom', 'lidar')
    placed = [i for i in odd if sample.scans[i].stamp_ns in map_odom]
    assert placed == odd[agreement:]
    for i in placed:
        stamp = sample.scans[i].stamp_ns
        e_t, e_r = errors(map_odom[stamp] @ odom_lidar[stamp], sample.T_ref[i])
        assert e_t < MAX_ERROR_M and e_r < MAX_ERROR_DEG, (i, e_t, e_r)

    # ~/pose: each placed scan's pose in the map, with its covariance.
    n_placed = len(odd) - agreement + 1  # the one that completed the agreement, then tracked
    assert rig.spin_until(lambda: len(rig.poses) == n_placed, 10.0), len(rig.poses)
    by_stamp = {s.stamp_ns: i for i, s in enumerate(sample.scans)}
    for msg in rig.poses:
        assert msg.header.frame_id == 'map'
        i = by_stamp[int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)]
        e_t, e_r = errors(pose_from_msg(msg.pose.pose), sample.T_ref[i])
        assert e_t < MAX_ERROR_M and e_r < MAX_ERROR_DEG, (i, e_t, e_r)
        C = covariance_from_msg(msg.pose.covariance)
        assert np.all(np.diag(C) > 0) and np.allclose(C, C.T)
    counts = rig.localization.snapshot().counts
    assert counts['searched'] == agreement and counts['tracked'] == len(odd) - agreement
    assert counts['skipped'] == 0 and counts['errors'] == 0 and counts['relocalizations'] == 0

    # A restart of the odometry (its frame starts again) withdraws map -> odom: searching.
    trigger(rig.node._on_reset)
    sent = len(rig.tf.transforms('map', 'odom'))
    rig.feed(sample.scans[odd[-1] + 2])
    assert rig.localization.state == 'searching'
    assert len(rig.tf.transforms('map', 'odom')) == sent
    assert rig.spin_until(lambda: rig.states[-1] == 'searching', 10.0), rig.states


@pytest.mark.integration
def test_an_initial_pose_bounds_the_search_and_relocalize_searches_again(
    make_rig: Callable[..., Rig], sample: Sample
) -> None:
    """An initial pose 20 m from the truth with a tight window cannot be placed (a search
    from no start would be); one 0.8 m and 8 deg off with RViz's covariance is; then
    ``~/relocalize`` searches from no start and the state goes back to searching."""
    rig = make_rig(sample.map_file)
    rig.wait_map()
    agreement = rig.localization._config.localization.agreement
    scans, T_ref = sample.scans, sample.T_ref
    far = T_ref[1] @ make_transform(np.eye(3), [20.0, 0.0, 0.0])
    rig.node._on_initial_pose(initial_pose(far, np.diag([0.01, 0.01, 0, 0, 0, 0.001])))
    for i in (1, 3, 5, 7):
        rig.feed(scans[i])
        assert rig.localization.state != 'localized', i
    assert not rig.tf.transforms('map', 'odom')

    near = T_ref[9] @ make_transform(exp_so3([0.0, 0.0, np.radians(8.0)]), [0.8, 0.0, 0.0])
    rig.node._on_initial_pose(initial_pose(near, RVIZ_COVARIANCE))
    odd = list(range(9, 9 + 2 * agreement + 2, 2))  # the agreeing scans, then one tracked
    for i in odd:
        rig.feed(scans[i])
    assert rig.localization.state == 'localized'
    stamp = scans[odd[-1]].stamp_ns
    T = rig.tf.transforms('map', 'odom')[stamp] @ rig.tf.transforms('odom', 'lidar')[stamp]
    e_t, e_r = errors(T, T_ref[odd[-1]])
    assert e_t < MAX_ERROR_M and e_r < MAX_ERROR_DEG, (e_t, e_r)

    answer = trigger(rig.node._on_relocalize)
    assert answer.success, answer.message
    after = list(range(odd[-1] + 2, odd[-1] + 2 + 2 * agreement, 2))
    rig.feed(scans[after[0]])
    assert rig.localization.state == 'searching'
    # The last placement stays published until a new one is taken (the core's rule).
    assert scans[after[0]].stamp_ns in rig.tf.transforms('map', 'odom')
    for i in after[1:]:
        rig.feed(scans[i])
    assert rig.localization.state == 'localized'
    assert rig.spin_until(lambda: rig.states[-1] == 'localized', 10.0)
    assert rig.states[:2] == ['searching', 'localized'] and 'searching' in rig.states[2:]
    counts = rig.localization.snapshot().counts
    assert counts['relocalizations'] == 1  # the second search's, logged with its correction
