"""kentreg_node with real rclpy over DDS: a node subprocess, a publisher and subscribers here.

Every test starts ``python -m kentreg_ros.ros.node`` with the shipped parameter file, talks to it
over Fast DDS kept on loopback (``test/fastdds_localhost.xml``,
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, see ``test/ros_env.py``) in a test-only ROS
domain, and stops it with SIGINT, checking that it exits cleanly. The node keeps its default
name and namespace (the parameter file is under ``/**``, so any name would do). Its topics and
services are remapped under a prefix of the test's own
(:data:`REMAPPED`), because a domain is not private: there are only 40 test-only ids, and
other test runs on the same machine (other checkouts, CI jobs) use them too; with the
default names their nodes would take our scans and we their diagnostics.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy', reason="rclpy is not installed (pip install -e '.[ros]')")

import ros_env  # noqa: E402  (test/ is on sys.path)
import yaml  # noqa: E402
from builtin_interfaces.msg import Time  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from nav_msgs.msg import Odometry as OdometryMsg  # noqa: E402
from nav_msgs.msg import Path as PathMsg  # noqa: E402
from rclpy.duration import Duration  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter, parameter_value_to_python  # noqa: E402
from rclpy.parameter_client import AsyncParameterClient  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402
from sensor_msgs.msg import PointCloud2, PointField  # noqa: E402
from std_msgs.msg import Header  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from kentreg_ros.eval import metrics  # noqa: E402
from kentreg_ros.eval.groundtruth import GroundTruth  # noqa: E402
from kentreg_ros.io.pointcloud2 import array_to_pointcloud2, rclpy_factory  # noqa: E402
from kentreg_ros.io.recordings import read_ground_truth  # noqa: E402
from kentreg_ros.io.sources import open_scan_source  # noqa: E402

#: Node subprocesses over DDS: the integration tier.
pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / 'bags' / 'balm_50'
PARAMS = REPO / 'config' / 'kentreg.yaml'
GATED_NODE = Path(__file__).resolve().parents[1] / 'gated_node.py'
FACTORY = rclpy_factory(PointCloud2, PointField, Header, Time)
_DOMAINS = itertools.count()
#: The node's topics and services (fully qualified, as in the root namespace), each remapped
#: to ``<prefix><name>`` for a prefix unique to the test.
REMAPPED = (
    '/points', '/initialpose', '/kentreg/odometry', '/kentreg/pose', '/kentreg/path',
    '/kentreg/cloud_registered', '/kentreg/map', '/diagnostics', '/clock', '/tf', '/tf_static',
    '/kentreg_node/reset', '/kentreg_node/save_map',
    *(f'/kentreg_node/{s}' for s in (
        'describe_parameters', 'get_parameter_types', 'get_parameters', 'list_parameters',
        'set_parameters', 'set_parameters_atomically',
    )),
)  # fmt: skip
#: Reliable input, and queue and history deep enough that a burst of test messages is kept.
QUEUE_ALL = (
    '-p',
    'qos_reliability:=reliable',
    '-p',
    'queue_size:=20',
    '-p',
    'qos_depth:=50',
)


def next_domain_id() -> int:
    """A test-only domain for the next test: this session's domain, then the following ones."""
    span = ros_env.DOMAIN_ID_MAX - ros_env.DOMAIN_ID_MIN + 1
    offset = ros_env.domain_id() - ros_env.DOMAIN_ID_MIN + next(_DOMAINS)
    return ros_env.DOMAIN_ID_MIN + offset % span


def ros_environment(domain_id: int) -> dict[str, str]:
    """DDS on loopback only (``test/ros_env.py``), in the test-only domain ``domain_id``."""
    return {**ros_env.ros_env(), 'ROS_DOMAIN_ID': str(domain_id)}


def cloud_msg(points: np.ndarray, stamp_ns: int, frame_id: str = 'lidar') -> Any:
    return array_to_pointcloud2(points, stamp_ns=stamp_ns, frame_id=frame_id, factory=FACTORY)


def stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def pose_matrix(pose: Any) -> np.ndarray:
    T = np.eye(4)
    q = pose.orientation
    T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    T[:3, 3] = [pose.position.x, pose.position.y, pose.position.z]
    return T


class NodeProcess:
    """``kentreg_node`` in a subprocess, with its log kept for failure messages.

    With ``hold_file``, the node is ``test/gated_node.py``: its worker waits before each scan
    while that file exists.
    """

    def __init__(
        self, domain_id: int, args: list[str], log_path: Path, hold_file: Path | None = None
    ) -> None:
        self.log_path = log_path
        self._log = log_path.open('w')
        env = {**os.environ, **ros_environment(domain_id), 'PYTHONUNBUFFERED': '1'}
        if hold_file is None:
            cmd = [sys.executable, '-m', 'kentreg_ros.ros.node', '--ros-args']
        else:
            cmd = [sys.executable, str(GATED_NODE), '--ros-args']
            env['KENTREG_TEST_HOLD_FILE'] = str(hold_file)
        self.proc = subprocess.Popen(
            cmd + args, env=env, stdout=self._log, stderr=subprocess.STDOUT
        )

    def log(self) -> str:
        if not self._log.closed:  # stop() closes it; the log stays readable
            self._log.flush()
        return self.log_path.read_text()

    def alive(self) -> bool:
        return self.proc.poll() is None

    def rss_mb(self) -> float:
        for line in Path(f'/proc/{self.proc.pid}/status').read_text().splitlines():
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024.0
        return float('nan')

    def stop(self, *, repeat: bool = False) -> int:
        """SIGINT (Ctrl-C) and wait for the exit; ``repeat``: SIGINT again every 5 ms until
        the process is gone (a user pressing Ctrl-C again while the node shuts down)."""
        if self.alive():
            self.proc.send_signal(signal.SIGINT)
            deadline = time.monotonic() + 15.0
            while repeat and self.alive() and time.monotonic() < deadline:
                time.sleep(0.005)
                with contextlib.suppress(ProcessLookupError):
                    self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()
        return self.proc.returncode


class Harness:
    """A test-side rclpy node: publishes scans, collects outputs, calls services."""

    def __init__(self, tmp_path: Path) -> None:
        self.tmp_path = tmp_path
        self.domain_id = next_domain_id()
        self.context = rclpy.context.Context()
        rclpy.init(context=self.context, domain_id=self.domain_id)
        self.node = rclpy.create_node(f'kentreg_test_{os.getpid()}', context=self.context)
        #: Prefix of the node's topics and services in this test (see ``REMAPPED``).
        self.prefix = ros_env.unique_topic('x').rpartition('/')[0]
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.processes: list[NodeProcess] = []

    def start_node(
        self, *extra: str, params: Path | None = PARAMS, hold_file: Path | None = None
    ) -> NodeProcess:
        args = (['--params-file', str(params)] if params is not None else []) + list(extra)
        for name in REMAPPED:
            args += ['-r', f'{name}:={self.name(name)}']
        log = self.tmp_path / f'kentreg_node_{len(self.processes)}.log'
        proc = NodeProcess(self.domain_id, args, log, hold_file)
        self.processes.append(proc)
        return proc

    def name(self, name: str) -> str:
        """The name of the node's topic or service ``name`` (one of ``REMAPPED``) in this test."""
        return self.prefix + name

    def connect(self, proc: NodeProcess, *, reliable: bool = True) -> Outputs:
        """Subscribe to the node's outputs and wait until both sides of every topic matched.

        Matching is not symmetric: each side matches the other when its own discovery gets
        there, so seeing the node's endpoints here does not mean the node sees ours. Our
        ``points`` publisher has matched the node's subscription when its subscription count
        is 1 (the node's side may lag: reliable QoS resends what it missed). The node's output
        publishers have matched our subscriptions once a diagnostics message arrived: the node
        discovers our subscriptions in the order we created them (one reliable, ordered
        discovery stream), and ``diagnostics`` is the last, so ``odom``, ``pose`` and ``path``
        were matched before; without this wait the first odometry could go to no one.
        """
        out = Outputs(self, reliable=reliable)
        ok = self.spin_until(
            lambda: (
                out.pub.get_subscription_count() >= 1
                and all(sub.get_publisher_count() >= 1 for sub in out.subscriptions)
                and bool(out.diag)
            ),
            timeout=30.0,
            proc=proc,
        )
        assert ok, f'kentreg_node did not come up:\n{proc.log()}'
        return out

    def spin_until(
        self, done: Callable[[], bool], timeout: float, proc: NodeProcess | None = None
    ) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if done():
                return True
            if proc is not None and not proc.alive():
                return done()
            self.executor.spin_once(timeout_sec=0.02)
        return done()

    def close(self) -> None:
        for proc in self.processes:
            proc.stop()
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


class Outputs:
    """Subscriptions to one kentreg_node's outputs and a publisher to its input."""

    def __init__(self, harness: Harness, *, reliable: bool) -> None:
        node = harness.node
        qos_in = QoSProfile(
            depth=10,
            reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        )
        self.pub = node.create_publisher(PointCloud2, harness.name('/points'), qos_in)
        self.odom: list[Any] = []
        self.pose: list[Any] = []
        self.path: list[Any] = []
        self.diag: list[Any] = []
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        # Diagnostics last: Harness.connect relies on this order.
        self.subscriptions = [
            node.create_subscription(
                OdometryMsg, harness.name('/kentreg/odometry'), self.odom.append, qos
            ),
            node.create_subscription(
                PoseStamped, harness.name('/kentreg/pose'), self.pose.append, qos
            ),
            node.create_subscription(
                PathMsg, harness.name('/kentreg/path'), self.path.append, qos
            ),
            node.create_subscription(
                DiagnosticArray, harness.name('/diagnostics'), self.diag.append, qos
            ),
        ]
        self.reset = node.create_client(Trigger, harness.name('/kentreg_node/reset'))
        self.params = AsyncParameterClient(node, harness.name('/kentreg_node'))

    def diagnostics(self) -> dict[str, str]:
        """Key/values of the latest diagnostics message."""
        return {kv.key: kv.value for kv in self.diag[-1].status[0].values}


@pytest.fixture
def harness(tmp_path: Path) -> Iterator[Harness]:
    # conftest.py has put the loopback DDS settings into os.environ for this process.
    h = Harness(tmp_path)
    try:
        yield h
    finally:
        h.close()


@pytest.fixture(scope='module')
def bag_scans() -> list[Any]:
    return list(open_scan_source(BAG))


def wait_diagnostics(h: Harness, out: Outputs, proc: NodeProcess, predicate: Callable) -> dict:
    """Wait for a diagnostics message whose values satisfy ``predicate``."""
    ok = h.spin_until(
        lambda: bool(out.diag) and predicate(out.diagnostics()), timeout=20.0, proc=proc
    )
    assert ok, f'diagnostics never satisfied the check: {out.diag and out.diagnostics()}'
    return out.diagnostics()


def test_node_tracks_the_sample_bag_like_replay(
    harness: Harness, bag_scans: list[Any], tmp_path: Path
) -> None:
    # Reliable input so that the lockstep publication below loses nothing.
    proc = harness.start_node('-p', 'qos_reliability:=reliable')
    out = harness.connect(proc)
    for i, scan in enumerate(bag_scans):
        out.pub.publish(cloud_msg(scan.points, scan.stamp_ns, scan.frame_id))
        ok = harness.spin_until(lambda i=i: len(out.odom) > i, timeout=30.0, proc=proc)
        assert ok, f'no odom for scan {i}:\n{proc.log()}'
    assert harness.spin_until(lambda: len(out.pose) == len(bag_scans), timeout=30.0, proc=proc)
    assert len(out.odom) == len(out.pose) == len(bag_scans)

    stamps = [s.stamp_ns for s in bag_scans]
    assert [stamp_ns(m.header.stamp) for m in out.odom] == stamps
    assert [stamp_ns(m.header.stamp) for m in out.pose] == stamps
    assert {m.header.frame_id for m in out.odom} == {'odom'}
    # No base_frame (the shipped default): the cloud's own frame moves, as on a bare bag.
    assert {m.child_frame_id for m in out.odom} == {'lidar'}
    assert {m.header.frame_id for m in out.pose} == {'odom'}
    np.testing.assert_allclose(pose_matrix(out.odom[0].pose.pose), np.eye(4), atol=1e-12)

    # The same bounds as the replay on the same bag.
    gt = GroundTruth(read_ground_truth(BAG), 'bag')
    by_stamp = dict(
        zip(gt.trajectory.stamps_ns.tolist(), gt.trajectory.T_world_sensor, strict=True)
    )
    T_gt = np.array([by_stamp[s] for s in stamps])
    T_est = np.array([pose_matrix(m.pose.pose) for m in out.odom])
    e_R, e_t = metrics.pair_errors(metrics.relative_poses(T_est), metrics.relative_poses(T_gt))
    assert np.median(e_R) <= 0.1 and np.median(e_t) <= 0.01
    assert np.all(e_R <= 2.0) and np.all(e_t <= 0.2)
    np.testing.assert_allclose([pose_matrix(m.pose) for m in out.pose], T_est, atol=1e-9)

    # Twist: the motion of the last step over its time gap, in the base frame.
    last, prev = out.odom[-1], out.odom[-2]
    dt = (stamps[-1] - stamps[-2]) * 1e-9
    T_step = np.linalg.inv(T_est[-2]) @ T_est[-1]
    v = T_step[:3, :3].T @ T_step[:3, 3] / dt
    lin = last.twist.twist.linear
    np.testing.assert_allclose([lin.x, lin.y, lin.z], v, atol=1e-6)
    assert prev.pose.covariance[0] > 0 and np.all(np.isfinite(last.pose.covariance))

    # Path and diagnostics. The path goes out on the map's timer (once a second when it grew),
    # so its last poses may come a period after the last odometry.
    assert harness.spin_until(
        lambda: bool(out.path) and len(out.path[-1].poses) == len(stamps), 30.0, proc
    ), [len(p.poses) for p in out.path]
    assert [stamp_ns(p.header.stamp) for p in out.path[-1].poses] == stamps
    diag = wait_diagnostics(harness, out, proc, lambda d: d['total.processed'] == '50')
    assert diag['total.received'] == '50' and diag['total.dropped_queue'] == '0'
    assert diag['total.fell_back'] == '0' and diag['total.malformed'] == '0'
    assert proc.stop() == 0, proc.log()


def test_node_map_reaches_a_late_transient_local_subscriber(
    harness: Harness, bag_scans: list[Any]
) -> None:
    from rclpy.qos import DurabilityPolicy

    from kentreg_ros.io.pointcloud2 import pointcloud2_to_array

    voxel, radius = 0.5, 15.0
    proc = harness.start_node(
        *QUEUE_ALL,
        *('-p', 'map_period:=0.01', '-p', f'map_voxel_size:={voxel}'),
        *('-p', f'map_radius:={radius}'),
    )
    out = harness.connect(proc)
    n = 3
    for scan in bag_scans[:n]:
        out.pub.publish(cloud_msg(scan.points, scan.stamp_ns, scan.frame_id))
    assert harness.spin_until(lambda: len(out.odom) == n, timeout=30.0, proc=proc), proc.log()
    # Subscribe only now: transient-local durability hands over the latest map.
    maps: list[Any] = []
    qos = QoSProfile(
        depth=1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
    harness.node.create_subscription(PointCloud2, harness.name('/kentreg/map'), maps.append, qos)
    # The latest map is handed over at once (it may still be that of the scan before the last:
    # the map goes out on a timer, map_period after the one before), then the last scan's.
    assert harness.spin_until(lambda: bool(maps), timeout=20.0, proc=proc), proc.log()
    last = bag_scans[n - 1].stamp_ns
    assert stamp_ns(maps[0].header.stamp) in {s.stamp_ns for s in bag_scans[:n]}
    assert harness.spin_until(
        lambda: stamp_ns(maps[-1].header.stamp) == last, timeout=20.0, proc=proc
    ), proc.log()
    msg = maps[-1]
    assert msg.header.frame_id == 'odom'
    points = pointcloud2_to_array(msg).points
    # One point per voxel, within the radius of the last sensor position, in the odom frame.
    assert len(points) > 1000
    assert len(np.unique(np.floor(points / voxel), axis=0)) == len(points)
    T_last = pose_matrix(out.odom[-1].pose.pose)
    assert np.linalg.norm(points - T_last[:3, 3], axis=1).max() <= radius + 1e-3
    # The first scan's registered (prepared) points, moved by its pose (the identity), are in
    # the map: the first points to reach a voxel keep it.
    from kentreg_ros.core import prepare_scan

    first = prepare_scan(np.asarray(bag_scans[0].points, dtype=np.float64)).points
    near = np.linalg.norm(first - T_last[:3, 3], axis=1) < radius - 1.0
    cells = {tuple(c) for c in np.floor(points / voxel).astype(int)}
    hits = [tuple(c) in cells for c in np.floor(first[near] / voxel).astype(int)]
    assert len(hits) > 1000 and all(hits)
    assert proc.stop() == 0, proc.log()


def test_node_exits_0_when_ctrl_c_is_pressed_again_while_it_shuts_down(
    harness: Harness, bag_scans: list[Any]
) -> None:
    """Repeated Ctrl-C while the node shuts down (its worker finishing, DDS going away, the
    interpreter finalising) must neither kill it by the signal nor raise in its cleanup."""
    proc = harness.start_node(*QUEUE_ALL)
    out = harness.connect(proc)
    for scan in bag_scans[:2]:
        out.pub.publish(cloud_msg(scan.points, scan.stamp_ns, scan.frame_id))
    assert harness.spin_until(lambda: len(out.odom) == 2, timeout=30.0, proc=proc), proc.log()
    assert proc.stop(repeat=True) == 0, proc.log()
    assert 'Traceback' not in proc.log()


def test_node_overload_drops_oldest_counts_and_stays_responsive(
    harness: Harness, bag_scans: list[Any], tmp_path: Path
) -> None:
    """Scans that arrive while the worker is busy: the oldest are dropped and counted.

    How many scans a node drops under a flood depends on how fast the machine registers them
    compared with the publishing rate, so the worker is held on one scan instead
    (``test/gated_node.py``) while ``n`` more arrive: with ``queue_size`` 1 and
    ``drop_oldest``, exactly the newest stays queued and ``n - 1`` are dropped, on any machine.
    """
    n = 150
    hold = tmp_path / 'hold'
    proc = harness.start_node(
        '-p', 'qos_reliability:=reliable', '-p', f'qos_depth:={n + 10}',
        '-p', 'diagnostics_period:=0.2', hold_file=hold,
    )  # fmt: skip
    out = harness.connect(proc)
    # Let the first scan become the model, then measure memory.
    sent = [1_000_000_000]
    out.pub.publish(cloud_msg(bag_scans[0].points, sent[0]))
    assert harness.spin_until(lambda: len(out.odom) == 1, timeout=30.0, proc=proc), proc.log()
    rss_start = proc.rss_mb()
    try:
        hold.touch()
        # The worker takes the next scan and holds it: received 2, nothing left in the queue.
        sent.append(sent[0] + 100_000_000)
        out.pub.publish(cloud_msg(bag_scans[1].points, sent[1]))
        wait_diagnostics(
            harness,
            out,
            proc,
            lambda d: (d['total.received'], d['queue_length']) == ('2', '0'),
        )
        # The flood. Each message is acknowledged before the next goes out, and the node's
        # subscription keeps n + 10 messages, so DDS loses none however slowly either side
        # runs: the node receives exactly n more.
        assert out.reset.wait_for_service(timeout_sec=30.0)
        reset_future = None
        for k in range(2, n + 2):
            sent.append(sent[0] + k * 100_000_000)
            out.pub.publish(cloud_msg(bag_scans[k % len(bag_scans)].points, sent[-1]))
            assert out.pub.wait_for_all_acked(Duration(seconds=30.0)), proc.log()
            if k == n // 2:
                reset_future = out.reset.call_async(Trigger.Request())
        # The node stays responsive while its worker is busy: the service answered.
        assert reset_future is not None
        assert harness.spin_until(reset_future.done, timeout=30.0, proc=proc), 'no reset answer'
        assert reset_future.result().success
        # Every scan was received; the queue holds the newest, the n - 1 before were dropped.
        diag = wait_diagnostics(harness, out, proc, lambda d: d['total.received'] == str(n + 2))
        assert diag['queue_length'] == '1'
        assert diag['total.dropped_queue'] == str(n - 1)
        assert diag['total.processed'] == '1'
        rss_held = proc.rss_mb()
    finally:
        hold.unlink(missing_ok=True)
    # Released, the worker finishes the scan in hand, then the newest (latest wins), which
    # starts the trajectory anew: the reset is applied between scans.
    assert harness.spin_until(
        lambda: bool(out.odom) and stamp_ns(out.odom[-1].header.stamp) == sent[-1],
        timeout=30.0,
        proc=proc,
    ), proc.log()
    diag = wait_diagnostics(harness, out, proc, lambda d: d['total.processed'] == '3')
    assert diag['total.received'] == str(n + 2) and diag['total.dropped_queue'] == str(n - 1)
    assert diag['total.resets'] == '1' and diag['queue_length'] == '0'
    assert [stamp_ns(m.header.stamp) for m in out.odom] == [sent[0], sent[1], sent[-1]]
    assert all(np.isfinite(pose_matrix(m.pose.pose)).all() for m in out.odom)
    assert not np.allclose(pose_matrix(out.odom[1].pose.pose), np.eye(4), atol=1e-3)
    np.testing.assert_allclose(pose_matrix(out.odom[2].pose.pose), np.eye(4), atol=1e-12)
    # Memory stays bounded while the worker was held. Had the node kept every scan, it would
    # hold n decoded scans (float64 x, y, z) more, ~73 MB: half of that is the bound (measured:
    # +77 MB with queue_size 1000, which keeps them all; +3 MB with queue_size 1).
    all_queued_mb = n * min(len(s.points) for s in bag_scans) * 3 * 8 / 2**20
    assert rss_held - rss_start < 0.5 * all_queued_mb, (rss_start, rss_held, all_queued_mb)
    assert proc.stop() == 0, proc.log()


def _bad_clouds(points: np.ndarray) -> list[tuple[str, Any]]:
    truncated = cloud_msg(points, 2_000_000_000)
    truncated.data = truncated.data[:-7]
    no_z = cloud_msg(points, 3_000_000_000)
    no_z.fields = [f for f in no_z.fields if f.name != 'z']
    beyond = cloud_msg(points, 4_000_000_000)
    beyond.point_step = 8  # the z field lies beyond the point
    beyond.row_step = beyond.width * 8
    return [('truncated data', truncated), ('no z field', no_z), ('field beyond', beyond)]


def test_node_survives_bad_input_and_counts_it(harness: Harness, bag_scans: list[Any]) -> None:
    proc = harness.start_node(*QUEUE_ALL)
    out = harness.connect(proc)
    points = bag_scans[0].points
    out.pub.publish(cloud_msg(points, 1_000_000_000))
    assert harness.spin_until(lambda: len(out.odom) == 1, 30.0, proc), proc.log()
    for _, msg in _bad_clouds(points):
        out.pub.publish(msg)
    with_nan = bag_scans[1].points.copy()
    with_nan[::10] = np.nan
    out.pub.publish(cloud_msg(with_nan, 5_000_000_000))
    out.pub.publish(cloud_msg(np.zeros((0, 3)), 6_000_000_000))  # empty
    out.pub.publish(cloud_msg(np.full((50, 3), np.inf), 7_000_000_000))  # nothing finite
    out.pub.publish(cloud_msg(points[:3], 8_000_000_000))  # too few points
    out.pub.publish(cloud_msg(bag_scans[2].points, 9_000_000_000))
    assert harness.spin_until(
        lambda: bool(out.odom) and stamp_ns(out.odom[-1].header.stamp) == 9_000_000_000,
        timeout=30.0,
        proc=proc,
    ), proc.log()
    assert proc.alive()
    diag = wait_diagnostics(
        harness, out, proc, lambda d: (d['total.received'], d['total.processed']) == ('9', '6')
    )
    assert diag['total.malformed'] == '3'
    assert int(diag['total.nonfinite_points']) == len(with_nan[::10]) + 50
    assert diag['total.rejected'] == '3'
    # Every usable or merely unusable scan got an output; malformed ones did not.
    assert len(out.odom) == 6
    log = proc.log()
    assert 'malformed PointCloud2' in log and 'Rejected the scan' in log
    assert proc.stop() == 0, log


def test_node_validates_runtime_parameter_changes(
    harness: Harness, bag_scans: list[Any], tmp_path: Path
) -> None:
    params = _write_params(tmp_path, max_range=33.0, path_length=7)
    proc = harness.start_node(*QUEUE_ALL, params=params)
    out = harness.connect(proc)
    assert out.params.wait_for_services(timeout_sec=10.0)
    # The parameter file applies (not just the defaults, which would be 50 and 1000).
    future = out.params.get_parameters(['max_range', 'path_length'])
    assert harness.spin_until(future.done, 10.0, proc)
    assert [parameter_value_to_python(v) for v in future.result().values] == [33.0, 7]

    def set_params(*params: Parameter) -> list[Any]:
        future = out.params.set_parameters(list(params))
        assert harness.spin_until(future.done, 10.0, proc)
        return future.result().results

    rejected = [
        Parameter('path_length', value=0),  # below its range
        Parameter('model', value='fast'),  # not a choice
        Parameter('qos_depth', value=3),  # read-only after startup
        Parameter('base_frame', value='odom'),  # the same as the odometry frame
        Parameter('max_range', value='far'),  # wrong type
        Parameter('min_range', value=40.0),  # not below max_range
    ]
    for param in rejected:
        (result,) = set_params(param)
        assert not result.successful and result.reason, param.name
    (ok,) = set_params(Parameter('max_range', value=30))  # an integer for a double
    assert ok.successful
    future = out.params.get_parameters(['max_range', 'model', 'qos_depth', 'min_range'])
    assert harness.spin_until(future.done, 10.0, proc)
    values = [parameter_value_to_python(v) for v in future.result().values]
    assert values == [30, 'previous_scan', 50, 0.0]  # nothing rejected was applied
    # The node still works after the accepted change.
    for k in range(2):
        out.pub.publish(cloud_msg(bag_scans[k].points, (k + 1) * 1_000_000_000))
    assert harness.spin_until(lambda: len(out.odom) == 2, 30.0, proc), proc.log()
    assert proc.stop() == 0


def test_node_restarts_when_time_goes_back_or_frame_changes(
    harness: Harness, bag_scans: list[Any]
) -> None:
    proc = harness.start_node(*QUEUE_ALL)
    out = harness.connect(proc)
    plan = [(0, 1, 'lidar'), (1, 2, 'lidar'), (2, 2, 'lidar'), (3, 1, 'lidar'), (4, 3, 'other')]
    for scan_index, second, frame in plan:
        out.pub.publish(cloud_msg(bag_scans[scan_index].points, second * 10**9, frame))
    assert harness.spin_until(lambda: len(out.odom) == 4, 30.0, proc), proc.log()
    diag = wait_diagnostics(
        harness, out, proc, lambda d: (d['total.received'], d['total.processed']) == ('5', '4')
    )
    # The repeated stamp is dropped; going back and the frame change each restart at identity.
    assert diag['total.dropped_duplicate_stamp'] == '1' and diag['total.resets'] == '2'
    assert [stamp_ns(m.header.stamp) for m in out.odom] == [10**9, 2 * 10**9, 10**9, 3 * 10**9]
    for i in (0, 2, 3):
        np.testing.assert_allclose(pose_matrix(out.odom[i].pose.pose), np.eye(4), atol=1e-12)
    assert not np.allclose(pose_matrix(out.odom[1].pose.pose), np.eye(4), atol=1e-3)
    log = proc.log()
    assert 'Time went backwards' in log and 'sensor frame changed' in log
    assert proc.stop() == 0


def _write_params(tmp_path: Path, **updates: Any) -> Path:
    data = yaml.safe_load(PARAMS.read_text())
    data['/**']['ros__parameters'].update(updates)
    path = tmp_path / 'params.yaml'
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize(
    ('how', 'expected'),
    [
        (['-p', 'path_length:=0'], 'Expected `path_length` in [1, 1000000], got 0.'),
        (['-p', 'model:=fast'], "Expected `odometry.model` to be one of ['previous_scan', "),
        (['-p', 'voxel_size:=true'], 'Expected `preprocess.voxel_size` to be a number'),
        (['-p', 'base_frame:=odom'], 'must differ'),
        ({'min_range': 9.0, 'max_range': 5.0}, 'min_range < preprocess.max_range'),
        ({'qos_reliability': 'fifo'}, 'Expected `qos_reliability` to be one of'),
        (['--params-file', '/nonexistent/params.yaml'], "Couldn't parse params file"),
    ],
)
def test_node_exits_1_with_the_reason_on_bad_startup_parameters(
    harness: Harness, tmp_path: Path, how: Any, expected: str
) -> None:
    if isinstance(how, dict):
        proc = harness.start_node(params=_write_params(tmp_path, **how))
    else:
        proc = harness.start_node(*how, params=None if how[0] == '--params-file' else PARAMS)
    try:
        code = proc.proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        pytest.fail(f'kentreg_node kept running with bad parameters:\n{proc.log()}')
    log = proc.log()
    assert code == 1, log
    assert expected in log, log
    assert 'Traceback' not in log


@pytest.mark.parametrize('shut_down', [True, False])
def test_node_exit_status_when_spin_raises_rclerror(tmp_path: Path, shut_down: bool) -> None:
    """Ctrl-C shuts rclpy down from its signal handler's thread; landing while spin() sets up
    its next wait, that makes spin raise RCLError instead of ExternalShutdownException
    (ros2/rclpy#398; seen once as exit 1 with a traceback at the end of a test here). That is a
    clean shutdown (exit 0); the same error with rclpy still running is not. Reproduced by
    replacing spin() with one that shuts down first (or not), then raises."""
    script = (
        'import rclpy\n'
        'from kentreg_ros.ros import node\n'
        'def spin(n):\n'
        f'    if {shut_down}:\n'
        '        rclpy.shutdown()\n'
        "    raise RuntimeError('failed to initialize wait set: the given context is not valid')\n"
        'rclpy.spin = spin\n'
        f"args = ['kentreg_node', '--ros-args', '--params-file', '{PARAMS}']\n"
        'raise SystemExit(node.main(args))\n'
    )
    proc = subprocess.run(
        [sys.executable, '-c', script],
        env={**os.environ, **ros_environment(next_domain_id())},
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    out = proc.stdout + proc.stderr
    if shut_down:
        assert proc.returncode == 0 and 'Traceback' not in out, out
    else:
        assert proc.returncode == 1 and 'failed to initialize wait set' in out, out


def test_node_honours_use_sim_time(harness: Harness, bag_scans: list[Any]) -> None:
    from rosgraph_msgs.msg import Clock

    proc = harness.start_node('-p', 'use_sim_time:=true', *QUEUE_ALL)
    out = harness.connect(proc)
    clock_pub = harness.node.create_publisher(Clock, harness.name('/clock'), 10)
    sim_ns = 1_000_000 * 10**9  # simulated time: day 12 of 1970
    sim = {'now': sim_ns}

    def tick() -> None:
        sim['now'] += 50_000_000
        msg = Clock()
        msg.clock.sec, msg.clock.nanosec = divmod(sim['now'], 10**9)
        clock_pub.publish(msg)

    timer = harness.node.create_timer(0.05, tick)
    out.pub.publish(cloud_msg(bag_scans[0].points, sim_ns))
    assert harness.spin_until(lambda: len(out.odom) == 1, 30.0, proc), proc.log()

    # Diagnostics are stamped with the node's clock: the simulated one, not the wall clock.
    # The node's /clock subscription (best effort) matches our new publisher when its own
    # discovery gets there, and ticks sent before are lost; so wait for a diagnostics message
    # stamped with simulated time rather than for a number of messages. Until a tick arrives
    # the simulated clock reads 0; at no time may a stamp come from the wall clock (~1.7e18 ns).
    def diag_stamps() -> list[int]:
        return [stamp_ns(d.header.stamp) for d in out.diag]

    assert harness.spin_until(lambda: bool(out.diag) and diag_stamps()[-1] > sim_ns, 20.0, proc), (
        diag_stamps(),
        proc.log(),
    )
    assert all(s == 0 or sim_ns < s <= sim['now'] for s in diag_stamps()), diag_stamps()
    # Outputs carry the scan's stamp whatever the clock says.
    assert stamp_ns(out.odom[0].header.stamp) == sim_ns
    harness.node.destroy_timer(timer)
    assert proc.stop() == 0


def test_node_dropped_in_saves_its_map_and_takes_an_initial_pose_over_dds(
    harness: Harness, bag_scans: list[Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No parameters at all, the sample bag: odometry of the cloud frame; ``~/save_map``
    called over DDS writes map.ply and trajectory_tum.txt under $ROS_HOME/kentreg_maps and
    answers with their paths; an ``initialpose`` sent over DDS moves the next pose."""
    from geometry_msgs.msg import PoseWithCovarianceStamped

    from kentreg_ros.ros.messages import pose_to_msg

    monkeypatch.setenv('ROS_HOME', str(tmp_path / 'ros_home'))  # the node inherits it
    proc = harness.start_node(params=None)
    out = harness.connect(proc, reliable=True)
    for i, scan in enumerate(bag_scans[:3]):
        out.pub.publish(cloud_msg(scan.points, scan.stamp_ns, scan.frame_id))
        assert harness.spin_until(lambda i=i: len(out.odom) > i, 30.0, proc), proc.log()
    assert {m.child_frame_id for m in out.odom} == {'lidar'}
    save = harness.node.create_client(Trigger, harness.name('/kentreg_node/save_map'))
    assert save.wait_for_service(timeout_sec=10.0)
    future = save.call_async(Trigger.Request())
    assert harness.spin_until(future.done, 30.0, proc), proc.log()
    answer = future.result()
    assert answer.success, answer.message
    (run,) = (tmp_path / 'ros_home' / 'kentreg_maps').iterdir()  # ROS keeps its logs beside
    assert str(run / 'map.ply') in answer.message
    assert len(np.loadtxt(run / 'trajectory_tum.txt', ndmin=2)) == 3
    # An initial pose: 10 m along x, turned 90 deg, in odom (what RViz's fixed frame sends).
    P = np.eye(4)
    P[:3, :3] = Rotation.from_euler('z', 90, degrees=True).as_matrix()
    P[:3, 3] = [10.0, 0.0, 0.0]
    pose_pub = harness.node.create_publisher(
        PoseWithCovarianceStamped, harness.name('/initialpose'), 10
    )
    assert harness.spin_until(lambda: pose_pub.get_subscription_count() >= 1, 10.0, proc)
    msg = PoseWithCovarianceStamped()
    msg.header.frame_id = 'odom'
    msg.pose.pose = pose_to_msg(P)
    pose_pub.publish(msg)
    assert harness.spin_until(lambda: 'Initial pose set' in proc.log(), 10.0, proc), proc.log()
    scan = bag_scans[3]
    out.pub.publish(cloud_msg(scan.points, scan.stamp_ns, scan.frame_id))
    assert harness.spin_until(lambda: len(out.odom) == 4, 30.0, proc), proc.log()
    T = pose_matrix(out.odom[-1].pose.pose)
    assert np.linalg.norm(T[:3, 3] - P[:3, 3]) < 0.1  # the sample moves millimetres per scan
    assert Rotation.from_matrix(T[:3, :3] @ P[:3, :3].T).magnitude() < np.radians(1.0)
    assert proc.stop() == 0, proc.log()
