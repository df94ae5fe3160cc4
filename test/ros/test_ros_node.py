"""kentreg_ros.ros.node in this process: its frame maths, its threads and its start-up checks.

``test_node.py`` runs the node as a subprocess over DDS; the tests here construct
:class:`KentRegNode` in this process (a private rclpy context, nothing spun), hand it scans the
way the subscription callback does, and look at what the worker thread did. That makes
ownership between the executor thread and the worker, and shutdown with a busy worker,
testable without depending on how fast this machine registers scans.

Two rules keep these tests independent of timing. No executor spins the node, and its timers
are cancelled (:func:`make_node`): the map's timer never sends the path or the map behind a
test's back, so the tests call ``publish_path``, ``publish_map`` and ``_publish_diagnostics``
themselves. And a test waits for the state its assertions read: the worker counts a scan
``processed`` when the odometry has stepped, before its outputs (odometry, pose, the path's
pose) go out, and ``published`` after them, so a test that looks at outputs waits on
:func:`handled` (``published``, or ``errors`` for a scan skipped by an error), never on
``processed``.
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy', reason="rclpy is not installed (pip install -e '.[ros]')")

from builtin_interfaces.msg import Time  # noqa: E402
from rclpy.exceptions import ParameterNotDeclaredException  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from scenes import box_room  # noqa: E402
from sensor_msgs.msg import PointCloud2, PointField  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from kentreg_ros.core import (  # noqa: E402
    KentRegError,  # noqa: E402
    exp_so3,
    log_so3,
    make_transform,
)
from kentreg_ros.io.errors import ParameterError  # noqa: E402
from kentreg_ros.io.params import apply_parameters  # noqa: E402
from kentreg_ros.io.pointcloud2 import array_to_pointcloud2, rclpy_factory  # noqa: E402
from kentreg_ros.ros import node as node_module  # noqa: E402
from kentreg_ros.ros import outputs as outputs_module  # noqa: E402
from kentreg_ros.ros import parameters as parameters_module  # noqa: E402
from kentreg_ros.ros import worker as worker_module  # noqa: E402
from kentreg_ros.ros.messages import pose_covariance_in_base  # noqa: E402

#: rclpy nodes (DDS participants) in this process: the integration tier.
pytestmark = pytest.mark.integration

FACTORY = rclpy_factory(PointCloud2, PointField, Header, Time)
ROOM = box_room(np.random.default_rng(0), 4000)
TIMEOUT_S = 60.0


def feed(node: Any, k: int) -> None:
    """Hand scan ``k`` to the node as its subscription callback does: the room seen from 5 cm
    further along x per scan, stamped ``k + 1`` seconds."""
    points = ROOM - [0.05 * k, 0.0, 0.0]
    node._on_points(
        array_to_pointcloud2(points, stamp_ns=(k + 1) * 10**9, frame_id='lidar', factory=FACTORY)
    )


def total(node: Any, name: str) -> int:
    """A cumulative counter of the node (what diagnostics report as ``total.<name>``)."""
    return int(node._counters.total[name])


def handled(node: Any) -> int:
    """Scans the worker is done with: ``published`` (counted after the scan's outputs went out,
    where ``processed`` is counted before them) plus ``errors`` (a scan skipped by an error;
    counted first, before its log and any restart, so a test that reads those waits for a
    later scan). The worker takes one scan at a time, in order: once ``handled`` reaches ``n``,
    everything the first ``n - 1`` scans did is done too."""
    return total(node, 'published') + total(node, 'errors')


def wait_until(done: Callable[[], bool], timeout: float = TIMEOUT_S) -> bool:
    deadline = time.monotonic() + timeout
    while not done():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * 10**9 + int(stamp.nanosec)


def _random_transform(rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    return make_transform(exp_so3(rng.normal(size=3)), rng.normal(scale=scale, size=3))


@pytest.mark.parametrize('anchored', [False, True], ids=['odom-at-start', 'initial-pose'])
def test_pose_covariance_in_base_is_the_first_order_propagation(anchored: bool) -> None:
    """Against a finite-difference Jacobian of ``T_odom_base = A T_world_lidar T_bl^-1``
    (``A = T_bl`` when odom is where the base started, another anchor after an initial pose),
    with errors as the covariance convention states: position, then rotation about the fixed
    frame's axes (``R' = exp(dtheta) R``)."""
    rng = np.random.default_rng(0)
    T_bl = _random_transform(rng, 0.5)
    T_wl = _random_transform(rng, 3.0)
    A = _random_transform(rng, 2.0) if anchored else T_bl

    def odom_base(delta: np.ndarray) -> np.ndarray:
        T = T_wl.copy()
        T[:3, 3] += delta[:3]
        T[:3, :3] = exp_so3(delta[3:]) @ T[:3, :3]
        return A @ T @ np.linalg.inv(T_bl)

    T_ob = odom_base(np.zeros(6))
    J = np.zeros((6, 6))
    eps = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        plus, minus = odom_base(d), odom_base(-d)
        J[:3, k] = (plus[:3, 3] - minus[:3, 3]) / (2 * eps)
        J[3:, k] = (
            log_so3(plus[:3, :3] @ T_ob[:3, :3].T) - log_so3(minus[:3, :3] @ T_ob[:3, :3].T)
        ) / (2 * eps)
    L = rng.normal(size=(6, 6))
    cov = L @ L.T
    expected = J @ cov @ J.T
    got = pose_covariance_in_base(cov, T_bl, T_ob, A if anchored else None)
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-6 * np.abs(expected).max())


@pytest.fixture
def make_node(rclpy_context: Any) -> Iterator[Callable[..., Any]]:
    """Construct KentRegNode in a private context; destroyed afterwards unless a test did.

    Each node gets a name of its own (other test runs on this machine may share the ROS
    domain and run a ``kentreg_node``), and its timers are cancelled: nothing spins it, and
    what the timers would send the tests send themselves, when their assertions need it."""
    nodes: list[Any] = []

    def make(**kwargs: Any) -> Any:
        kwargs.setdefault('node_name', f'kentreg_test_{uuid.uuid4().hex[:8]}')
        node = node_module.KentRegNode(context=rclpy_context, **kwargs)
        nodes.append(node)
        for timer in node.timers:
            timer.cancel()
        return node

    yield make
    for node in nodes:
        if node.handle is not None:
            node.destroy_node()


def test_startup_error_is_a_kentreg_error_naming_the_parameter(make_node: Any) -> None:
    match = r"Expected `odometry.model` to be one of \['previous_scan', 'local_map'\]"
    with pytest.raises(KentRegError, match=match):
        make_node(parameter_overrides=[Parameter('model', value='fast')])
    with pytest.raises(node_module.StartupError, match='queue_size') as caught:
        make_node(parameter_overrides=[Parameter('queue_size', value=0)])
    assert caught.value.names == ('queue_size',)


def test_a_refused_change_is_a_parameter_error_naming_it_with_the_reason() -> None:
    """parameters.changes raises (the node hands str(exc) to ``ros2 param set``) instead of
    returning the reason in place of the settings."""
    settings = apply_parameters({})
    config, node = settings.config, settings.node
    with pytest.raises(ParameterError, match='takes effect only at startup') as caught:
        parameters_module.changes([Parameter('qos_depth', value=3)], config, node)
    assert caught.value.names == ('qos_depth',)
    with pytest.raises(ParameterError, match=r'`path_length` in \[1, 1000000\]') as caught:
        given = [Parameter('path_length', value=0), Parameter('use_sim_time', value=True)]
        parameters_module.changes(given, config, node)
    assert caught.value.names == ('path_length',)
    changed = parameters_module.changes([Parameter('max_range', value=30)], config, node)
    assert changed.config.preprocess.max_range == 30.0 and changed.node == node


@pytest.mark.parametrize(
    'how',
    [
        {'parameter_overrides': [Parameter('em.bogus', value=3), Parameter('other', value=1)]},
        {'cli_args': ['--ros-args', '-p', 'em.bogus:=3', '-p', 'other:=1']},
    ],
    ids=['override', 'command-line'],
)
def test_parameters_not_of_the_node_are_warned_about_once_not_fatal(
    make_node: Any, how: dict, capfd: pytest.CaptureFixture[str]
) -> None:
    """A shared bringup file under /** holds other nodes' keys; research fields are not node
    parameters: the node starts, ignores them and says so once."""
    node = make_node(**how)
    assert not node.has_parameter('em.bogus') or node.get_parameter('em.bogus') is not None
    err = capfd.readouterr().err
    assert err.count("Ignoring parameter(s) ['em.bogus', 'other']") == 1


def test_given_parameters_apply_with_their_declared_type_and_range(make_node: Any) -> None:
    """The known parameters rclpy declared as given are declared again with their descriptors:
    the given value stays, and the range and type now come with it."""
    node = make_node(
        parameter_overrides=[
            Parameter('max_range', value=33.0),
            Parameter('path_length', value=7),
            Parameter('use_sim_time', value=False),
            Parameter('start_type_description_service', value=False),
            Parameter('qos_overrides./points.subscription.depth', value=3),
        ]
    )
    assert node.get_parameter('max_range').value == 33.0
    assert node.get_parameter('path_length').value == 7
    (rng,) = node.describe_parameter('path_length').integer_range
    assert (rng.from_value, rng.to_value) == (1, 1_000_000)
    assert node.describe_parameter('qos_depth').read_only
    # Out of range, inconsistent and unknown names are refused at run time too.
    (result,) = node.set_parameters([Parameter('path_length', value=0)])
    assert not result.successful and 'path_length' in result.reason
    (result,) = node.set_parameters([Parameter('min_range', value=40.0)])
    assert not result.successful and 'preprocess.min_range < preprocess.max_range' in result.reason
    with pytest.raises(ParameterNotDeclaredException):
        node.set_parameters([Parameter('em.bogus', value=1)])


def test_an_integer_for_a_double_parameter_is_taken_as_a_number(make_node: Any) -> None:
    """Users write ``max_range: 100`` (and ``ros2 param set ... max_range 100``); rclpy would
    refuse the integer for a double, the node converts it by the configuration's rules."""
    node = make_node(parameter_overrides=[Parameter('max_range', value=100)])
    assert node._config.preprocess.max_range == 100.0
    (result,) = node.set_parameters([Parameter('voxel_size', value=1)])
    assert result.successful and node._config.preprocess.voxel_size == 1.0
    (result,) = node.set_parameters([Parameter('voxel_size', value='big')])
    assert not result.successful and 'to be a number' in result.reason


def test_path_length_changes_reach_the_path_through_the_worker_only(
    make_node: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The worker appends to the path (the map's timer publishes it): a path_length change is
    handed over and applied by the worker, not by the thread that set the parameter.

    Each forced publication follows the worker's ``published`` count: the scan's pose is in
    the path then (at ``processed`` it may not be yet, and the path had nothing new to send)."""
    node = make_node(parameter_overrides=[Parameter('path_length', value=5)])
    paths: list[Any] = []
    monkeypatch.setattr(node._outputs.path, 'publish', paths.append)
    for k in range(3):
        feed(node, k)
        assert wait_until(lambda k=k: handled(node) == k + 1)
        assert node._outputs.publish_path(node._worker.settings, force=True)
    path = node._outputs._poses
    # From this thread, as the executor thread runs `ros2 param set`.
    (result,) = node.set_parameters([Parameter('path_length', value=2)])
    assert result.successful
    assert node._outputs._poses is path and path.maxlen == 5, 'the parameter thread touched it'
    feed(node, 3)
    assert wait_until(lambda: handled(node) == 4)
    assert node._outputs.publish_path(node._worker.settings, force=True)
    assert not node._outputs.publish_path(node._worker.settings, force=True), 'nothing new to send'
    assert [len(p.poses) for p in paths] == [1, 2, 3, 2]
    assert [stamp_ns(p.header.stamp) for p in paths[-1].poses] == [3 * 10**9, 4 * 10**9]
    assert total(node, 'errors') == 0


def test_the_path_goes_out_on_the_timer_not_with_every_scan(
    make_node: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A Path carries every pose, so its cost grows with the run: the worker only appends, and
    the map's timer sends it at most every PATH_PERIOD_S, when it grew. The period is read on
    a clock of the test's (the outputs' ``time``), so how long this machine takes for a scan
    does not decide whether it has passed."""
    clock = SimpleNamespace(now=1000.0)
    monkeypatch.setattr(outputs_module, 'time', SimpleNamespace(monotonic=lambda: clock.now))
    node = make_node()
    paths: list[Any] = []
    monkeypatch.setattr(node._outputs.path, 'publish', paths.append)
    for k in range(2):
        feed(node, k)
        assert wait_until(lambda k=k: handled(node) == k + 1)
    assert paths == [], 'the worker published the path'
    assert node._outputs.publish_path(node._worker.settings)  # the first is due at once
    assert [len(p.poses) for p in paths] == [2]
    feed(node, 2)
    assert wait_until(lambda: handled(node) == 3)
    clock.now += 0.5 * outputs_module.PATH_PERIOD_S  # halves: exact in binary
    assert not node._outputs.publish_path(node._worker.settings), (
        'sent before PATH_PERIOD_S passed'
    )
    clock.now += 0.5 * outputs_module.PATH_PERIOD_S
    assert node._outputs.publish_path(node._worker.settings)
    clock.now += 10 * outputs_module.PATH_PERIOD_S
    assert not node._outputs.publish_path(node._worker.settings), 'sent again without a new pose'
    assert [len(p.poses) for p in paths] == [2, 3]
    assert stamp_ns(paths[-1].header.stamp) == 3 * 10**9


def test_diagnostics_report_the_model_in_use_and_the_pending_one(
    make_node: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An accepted model change applies from the next scan: until then diagnostics must say the
    worker still registers against the old model, and which one is pending."""
    node = make_node()
    sent: list[Any] = []
    monkeypatch.setattr(node._pub_diag, 'publish', sent.append)

    def modes() -> tuple[str, str]:
        node._publish_diagnostics()
        values = {kv.key: kv.value for kv in sent[-1].status[0].values}
        return values['model'], values['pending_model']

    assert modes() == ('previous_scan', '')
    (result,) = node.set_parameters([Parameter('model', value='local_map')])
    assert result.successful
    assert modes() == ('previous_scan', 'local_map')
    feed(node, 0)
    assert wait_until(lambda: handled(node) == 1)
    assert modes() == ('local_map', '')


def test_destroy_keeps_the_publishers_while_the_worker_still_holds_a_scan(
    make_node: Any, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    """A worker that outlives destroy_node's wait publishes its scan on live publishers (before,
    they were destroyed under it and the scan ended in an error)."""
    entered, release = threading.Event(), threading.Event()
    process = worker_module.ScanWorker.process

    def held(worker: Any, scan: Any, settings: Any) -> None:
        entered.set()
        release.wait(TIMEOUT_S)
        process(worker, scan, settings)

    monkeypatch.setattr(worker_module.ScanWorker, 'process', held)
    node = make_node()
    node.WORKER_STOP_TIMEOUT_S = 0.1
    feed(node, 0)
    assert entered.wait(TIMEOUT_S)
    try:
        node.destroy_node()
        assert node._worker.is_alive()
        assert node._outputs.odom in node.publishers and node._outputs.pose in node.publishers
        assert node._sub not in node.subscriptions  # no more input
    finally:
        release.set()
    node._worker.join(TIMEOUT_S)
    assert not node._worker.is_alive()
    assert (total(node, 'published'), total(node, 'errors')) == (1, 0)
    assert 'did not stop within 0.1 s' in capfd.readouterr().err


@pytest.mark.parametrize('flag', ['--help', '-h'])
def test_node_help_prints_its_usage_and_exits_0_without_starting_ros(
    flag: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``kentreg_node --help`` answers like any command line: its own options, where the ROS
    arguments go and where the parameters are documented; it never initialises rclpy (before,
    it ignored the flag and started the node)."""

    def no_init(*args: Any, **kwargs: Any) -> None:
        raise AssertionError('rclpy.init was called for --help')

    monkeypatch.setattr(node_module.rclpy, 'init', no_init)
    with pytest.raises(SystemExit) as exit_info:
        node_module.main(['kentreg_node', flag])
    assert exit_info.value.code == 0
    out, err = capsys.readouterr()
    assert out.startswith('usage: kentreg_node') and err == ''
    for text in ('--ros-args', '-p name:=value', '--params-file FILE', 'docs/', '--version'):
        assert text in out, text


def test_node_refuses_an_argument_of_its_own_it_does_not_know(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A ROS argument written without ``--ros-args`` (a common slip) was silently ignored, so the
    node ran without the user's parameter file: now it is an error naming ``--ros-args``."""
    monkeypatch.setattr(node_module.rclpy, 'init', lambda *a, **k: pytest.fail('rclpy.init'))
    code = node_module.main(['kentreg_node', '--params-file', 'config/kentreg.yaml'])
    out, err = capsys.readouterr()
    assert code == 2 and out == ''
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('kentreg_node: error: '), err
    assert '--params-file' in lines[0] and '--ros-args' in lines[0]


def _rosout_listener(context: Any) -> tuple[Any, Any, list[Any]]:
    """A node in ``context`` subscribed to /rosout (reliable, transient-local like rclpy's
    publisher), with its executor and the list of the messages it receives."""
    from rcl_interfaces.msg import Log
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    listener = rclpy.create_node(f'kentreg_rosout_{uuid.uuid4().hex[:8]}', context=context)
    received: list[Any] = []
    qos = QoSProfile(
        depth=1000,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
    listener.create_subscription(Log, '/rosout', received.append, qos)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(listener)
    return listener, executor, received


def test_a_scan_the_core_rejects_leaves_a_warn_on_rosout(
    make_node: Any, rclpy_context: Any
) -> None:
    """The core logs through Python logging; the node forwards it to its rclpy logger, so a
    rejected scan is a WARN on /rosout (rqt_console, launch logs), not only a line on stderr;
    so is deskewing asked for on scans without per-point times."""
    from rcl_interfaces.msg import Log

    listener, executor, received = _rosout_listener(rclpy_context)
    try:
        name = f'kentreg_test_{uuid.uuid4().hex[:8]}'  # other processes may run a kentreg_node
        node = make_node(node_name=name, parameter_overrides=[Parameter('deskew', value='on')])
        feed(node, 0)
        assert wait_until(lambda: handled(node) == 1)  # a queue of 1: one at a time
        node._on_points(
            array_to_pointcloud2(ROOM[:3], stamp_ns=2 * 10**9, frame_id='lidar', factory=FACTORY)
        )
        # The health is counted after `processed`: wait for the end of the scan.
        assert wait_until(lambda: handled(node) == 2)
        assert total(node, 'rejected') == 1

        def warned(text: str) -> list[Any]:
            return [
                m
                for m in received
                if m.name == node.get_logger().name and m.level == Log.WARN and text in m.msg
            ]

        deadline = time.monotonic() + TIMEOUT_S
        while not warned('Rejected the scan') and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        (msg,) = warned('Rejected the scan')
        assert msg.msg.startswith('Scan 1: Rejected the scan') and 'prediction' in msg.msg
        assert len(warned('odometry.deskew is on but the scans carry no per-point times')) == 1
        node.destroy_node()
        assert not [
            h for h in logging.getLogger('kentreg_ros').handlers if h is node._log_handler
        ], 'the handler outlived its node'
    finally:
        executor.shutdown()
        listener.destroy_node()


class _Failing:
    """Wraps Odometry.step: raises a RuntimeError on the given calls (0-based), else steps."""

    def __init__(self, step: Callable[..., Any], failing: set[int]) -> None:
        self.step, self.failing, self.calls = step, failing, 0

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        call, self.calls = self.calls, self.calls + 1
        if call in self.failing:
            raise RuntimeError(f'injected failure on call {call}')
        return self.step(*args, **kwargs)


def _x(msg: Any) -> float:
    return float(msg.pose.pose.position.x)


def test_an_unexpected_error_skips_the_scan_counts_it_and_keeps_the_trajectory(
    make_node: Any, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    """One failing step: the scan is skipped and counted, odom goes on from the scans before
    (it jumped back to the identity, which REP-105 forbids), the traceback is logged, and the
    diagnostics tell the error apart from fell-back or rejected scans (they said "0 scans fell
    back or were rejected")."""
    from diagnostic_msgs.msg import DiagnosticStatus

    from kentreg_ros.ros import diagnostics

    # Input older than STALE_INPUT_S turns the message into "no scans on ..."; how long this
    # machine takes for the five scans must not decide which message is checked.
    monkeypatch.setattr(diagnostics, 'STALE_INPUT_S', float('inf'))
    node = make_node()
    odoms: list[Any] = []
    diags: list[Any] = []
    monkeypatch.setattr(node._outputs.odom, 'publish', odoms.append)
    monkeypatch.setattr(node._pub_diag, 'publish', diags.append)
    monkeypatch.setattr(node._worker.odometry, 'step', _Failing(node._worker.odometry.step, {2}))
    for k in range(5):
        feed(node, k)
        assert wait_until(lambda k=k: handled(node) == k + 1)
    assert (total(node, 'errors'), total(node, 'resets'), total(node, 'processed')) == (1, 0, 4)
    # The sensor moves 5 cm along x per scan: scan 3 is registered against scan 1.
    assert [stamp_ns(m.header.stamp) for m in odoms] == [10**9, 2 * 10**9, 4 * 10**9, 5 * 10**9]
    np.testing.assert_allclose([_x(m) for m in odoms], [0.0, 0.05, 0.15, 0.20], atol=0.01)
    # The twist of scan 3 is its motion since scan 1 over the 2 s between them: 5 cm/s.
    velocities = [m.twist.twist.linear.x for m in odoms[1:]]
    np.testing.assert_allclose(velocities, [0.05, 0.05, 0.05], atol=0.005)
    node._publish_diagnostics()
    status = diags[-1].status[0]
    assert status.level == DiagnosticStatus.ERROR
    assert '1 scans skipped after an unexpected error' in status.message
    assert 'fell back or were rejected' not in status.message
    err = capfd.readouterr().err
    assert 'injected failure on call 2' in err and 'the scan is skipped' in err
    assert err.count('Traceback (most recent call last)') == 1 and 'restart' not in err


def test_a_bug_in_the_registration_is_counted_as_an_error_not_a_fall_back(
    make_node: Any, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    """The core falls back only on its own errors (a scene it cannot solve): a bug in the
    registration (here a TypeError on the third scan) reaches the worker, which counts it in
    errors with its traceback, not as a scan that fell back."""
    import kentreg_ros.core.odometry.verify as verify_stage

    real, raised = verify_stage.register, []

    def buggy_on_the_third_scan(*args: Any, **kwargs: Any) -> Any:
        if node._worker.odometry.n_steps == 2 and not raised:
            raised.append(True)
            raise TypeError('a bug')
        return real(*args, **kwargs)

    node = make_node()
    monkeypatch.setattr(verify_stage, 'register', buggy_on_the_third_scan)
    for k in range(4):
        feed(node, k)
        assert wait_until(lambda k=k: handled(node) == k + 1)
    assert (total(node, 'errors'), total(node, 'fell_back'), total(node, 'processed')) == (1, 0, 3)
    err = capfd.readouterr().err
    assert 'TypeError: a bug' in err and 'the scan is skipped' in err


def test_errors_in_a_row_restart_the_trajectory_after_three_and_say_why(
    make_node: Any, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    """Two errors, a good scan, three errors: only the third in a row restarts (the odometry's
    state is then taken to be broken), saying so; the traceback of the one kind of error is
    logged once, not per scan."""
    node = make_node()
    odoms: list[Any] = []
    monkeypatch.setattr(node._outputs.odom, 'publish', odoms.append)
    monkeypatch.setattr(
        node._worker.odometry, 'step', _Failing(node._worker.odometry.step, {2, 3, 5, 6, 7})
    )
    for k in range(9):
        feed(node, k)
        assert wait_until(lambda k=k: handled(node) == k + 1)
    # The last scan was published: the errors' logs and the restart before it are done.
    assert (total(node, 'errors'), total(node, 'resets')) == (5, 1)
    assert [stamp_ns(m.header.stamp) // 10**9 for m in odoms] == [1, 2, 5, 9]
    np.testing.assert_allclose([_x(m) for m in odoms[:3]], [0.0, 0.05, 0.20], atol=0.01)
    # After the restart the next scan starts a new trajectory at the identity.
    np.testing.assert_allclose(_x(odoms[3]), 0.0, atol=1e-12)
    err = capfd.readouterr().err
    assert err.count('Traceback (most recent call last)') == 1
    assert '3 unexpected errors in a row' in err and 'the trajectory restarts' in err


def test_a_publish_that_fails_because_ros_shut_down_is_no_error(
    make_node: Any, rclpy_context: Any, monkeypatch: pytest.MonkeyPatch,
    capfd: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    """Ctrl-C shuts the context down from rclpy's signal handler while the worker may still be
    publishing a scan: rclpy then raises "publisher's context is invalid". That is the node
    ending, not an unexpected error: not counted, no traceback, the worker stops (seen as a
    traceback in test_node's repeated Ctrl-C test once tracebacks were logged)."""
    node = make_node()
    publish = node._outputs.pose.publish

    def shut_down_then_publish(msg: Any) -> None:
        rclpy.shutdown(context=rclpy_context)
        publish(msg)  # raises: the context is gone

    monkeypatch.setattr(node._outputs.pose, 'publish', shut_down_then_publish)
    feed(node, 0)
    node._worker.join(TIMEOUT_S)
    assert not node._worker.is_alive()
    assert total(node, 'errors') == 0
    err = capfd.readouterr().err
    assert 'Traceback' not in err and 'Unexpected error' not in err
