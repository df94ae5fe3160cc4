"""kentreg_play: real rclpy publishing of the sample bag, received by a subscriber in this process.

DDS stays on loopback in a test-only domain (``conftest.py`` / ``ros_env.py``); every test uses
its own topic name, so parallel test runs on one machine cannot see each other's messages.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from ros_env import ros_env, unique_topic

from kentreg_ros.ros import play
from kentreg_ros.ros.play import Timing, main

pytest.importorskip('rclpy', reason='rclpy is not installed (pip install -e .[ros])')

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402

from kentreg_ros.io import open_scan_source, pointcloud2_to_array  # noqa: E402

#: kentreg_play over real rclpy and DDS: the integration tier.
pytestmark = pytest.mark.integration

TIMEOUT_S = 60.0


@pytest.fixture(scope='module')
def sample_bag(repo_root: Path) -> Path:
    bag = repo_root / 'bags' / 'balm_50'
    if not bag.is_dir():
        pytest.skip(f'{bag} is absent')
    return bag


@pytest.fixture(scope='module')
def bag_scans(sample_bag: Path) -> list[Any]:
    """The first 13 scans of the sample bag as kentreg_play reads them (float32)."""
    scans = []
    for scan in open_scan_source(sample_bag, dtype=np.float32):
        scans.append(scan)
        if len(scans) == 13:
            break
    return scans


class Receiver:
    """A subscriber node in this process that keeps every message it gets."""

    def __init__(self, context: Any, topic: str, msg_type: type = PointCloud2) -> None:
        self.node = Node('kentreg_test_receiver', context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.messages: list[Any] = []
        self.node.create_subscription(
            msg_type,
            topic,
            self.messages.append,
            QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE),
        )

    def spin_until(self, done: Any, timeout_s: float = TIMEOUT_S) -> None:
        deadline = time.monotonic() + timeout_s
        while not done() and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        self.executor.remove_node(self.node)
        self.executor.shutdown()
        self.node.destroy_node()


@pytest.fixture
def make_receiver(rclpy_context: Any) -> Iterator[Any]:
    receivers: list[Receiver] = []

    def make(topic: str, msg_type: type = PointCloud2) -> Receiver:
        receivers.append(Receiver(rclpy_context, topic, msg_type))
        return receivers[-1]

    yield make
    for r in receivers:
        r.close()


def _start_play(repo_root: Path, *args: str) -> subprocess.Popen[str]:
    env = {
        **os.environ,
        **ros_env(),
        'PYTHONPATH': os.pathsep.join([str(repo_root), *sys.path]),
    }
    return subprocess.Popen(
        [sys.executable, '-m', 'kentreg_ros.ros.play', *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


def _play_and_receive(
    receiver: Receiver, proc: subprocess.Popen[str], expected: int
) -> tuple[int, str, str]:
    receiver.spin_until(lambda: proc.poll() is not None and len(receiver.messages) >= expected)
    # Everything was acknowledged before the player exited; one more short spin for stragglers.
    receiver.spin_until(lambda: False, timeout_s=0.3)
    try:
        stdout, stderr = proc.communicate(timeout=TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc.returncode, stdout, stderr


def _ns(t: Any) -> int:
    """``builtin_interfaces/Time`` in integer nanoseconds."""
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def test_play_publishes_bag_scans_in_order_with_their_stamps_and_points(
    repo_root: Path, sample_bag: Path, bag_scans: list[Any], make_receiver: Any
) -> None:
    topic = unique_topic('points')
    receiver = make_receiver(topic)
    proc = _start_play(
        repo_root, str(sample_bag), '--max-scans', '5', '--rate', '0', '--topic', topic,
        '--wait-subscribers', '30',
    )  # fmt: skip
    code, stdout, stderr = _play_and_receive(receiver, proc, 5)
    assert code == 0, stderr
    got = receiver.messages
    assert len(got) == 5
    assert [m.header.frame_id for m in got] == ['lidar'] * 5
    assert [m.width * m.height for m in got] == [len(s.points) for s in bag_scans[:5]]
    stamps = [_ns(m.header.stamp) for m in got]
    assert stamps == [s.stamp_ns for s in bag_scans[:5]]
    assert all(b > a for a, b in zip(stamps, stamps[1:], strict=False))
    assert [f.name for f in got[0].fields] == ['x', 'y', 'z', 'intensity']
    decoded = pointcloud2_to_array(got[3])
    np.testing.assert_array_equal(decoded.points, bag_scans[3].points.astype(np.float64))
    np.testing.assert_array_equal(decoded.extras['intensity'], bag_scans[3].extras['intensity'])
    assert f'published 5 scan(s) on {topic}' in stdout


def test_play_start_hz_and_restamp_now_stamp_with_the_current_time(
    repo_root: Path, sample_bag: Path, bag_scans: list[Any], make_receiver: Any
) -> None:
    """What arrives over DDS; when it is published is checked on a virtual clock below."""
    topic = unique_topic('points')
    receiver = make_receiver(topic)
    before_ns = time.time_ns()
    proc = _start_play(
        repo_root, str(sample_bag), '--start', '10', '--max-scans', '3', '--hz', '20',
        '--restamp', 'now', '--fields', 'none', '--frame-id', 'velodyne', '--topic', topic,
        '--wait-subscribers', '30',
    )  # fmt: skip
    code, stdout, stderr = _play_and_receive(receiver, proc, 3)
    assert code == 0, stderr
    got = receiver.messages
    assert [m.width for m in got] == [len(s.points) for s in bag_scans[10:13]]
    assert [m.header.frame_id for m in got] == ['velodyne'] * 3
    assert [f.name for f in got[0].fields] == ['x', 'y', 'z']
    # Stamped with the current time when published, not with the recorded stamps.
    stamps = [_ns(m.header.stamp) for m in got]
    assert stamps[0] >= before_ns and all(b > a for a, b in zip(stamps, stamps[1:], strict=False))
    assert not set(stamps) & {s.stamp_ns for s in bag_scans}
    assert 'published 3 scan(s)' in stdout and 'pass(es)' in stdout


class _VirtualClock:
    """Stands in for the player's ``time``: monotonic() reads it, sleep() advances it."""

    def __init__(self) -> None:
        self.now = 1000.0

    def monotonic(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += max(seconds, 0.0)


class _Publisher:
    """Records the virtual time of each publish; publishing may itself take time (``costs``)."""

    topic_name = '/points'

    def __init__(self, clock: _VirtualClock, costs: list[float]) -> None:
        self.clock, self.costs, self.times = clock, costs, []

    def publish(self, msg: Any) -> None:
        self.times.append(self.clock.now)
        if self.costs:
            self.clock.now += self.costs.pop(0)

    def get_subscription_count(self) -> int:
        return 1


class _Node:
    def __init__(self, clock: _VirtualClock, costs: list[float]) -> None:
        self.context = SimpleNamespace(ok=lambda: True)
        self.publishers: list[_Publisher] = []
        self.clock, self.costs = clock, costs

    def create_publisher(self, msg_type: Any, topic: str, qos: Any) -> _Publisher:
        self.publishers.append(_Publisher(self.clock, self.costs))
        return self.publishers[-1]


def _publish_times(
    monkeypatch: pytest.MonkeyPatch, stamps_s: list[float], args: list[str], costs: list[float]
) -> list[float]:
    """Run Player.run over scans stamped ``stamps_s`` on a virtual clock; publish times from
    the first one (s)."""
    clock = _VirtualClock()
    monkeypatch.setattr(play, 'time', clock)
    node = _Node(clock, list(costs))
    source = [
        SimpleNamespace(
            stamp_ns=int(round(t * 1e9)), points=np.zeros((3, 3), np.float32), extras={},
            frame_id='lidar',
        )
        for t in stamps_s
    ]  # fmt: skip
    options = play.build_parser().parse_args(['scans', *args])
    play.Player(node, source, options, play._ros()).run()
    times = node.publishers[0].times
    return [t - times[0] for t in times]


@pytest.mark.parametrize(
    ('args', 'costs', 'expected'),
    [
        ([], [], [0.0, 0.5, 2.0, 2.25]),  # the recorded gaps
        (['--rate', '2'], [], [0.0, 0.25, 1.0, 1.125]),  # twice as fast
        (['--rate', '0'], [], [0.0, 0.0, 0.0, 0.0]),  # no waiting
        (['--hz', '1.6'], [], [0.0, 0.625, 1.25, 1.875]),  # fixed rate, stamps ignored
        # Publishing takes 0.1 s each time, less than every gap: the schedule holds.
        ([], [0.1, 0.1, 0.1, 0.1], [0.0, 0.5, 2.0, 2.25]),
        # Publishing the first scan took 1 s, past the second's due time (0.5 s): the second
        # goes out at once and the next gap is measured from it, never compressed to catch up.
        ([], [1.0], [0.0, 1.0, 2.5, 2.75]),
    ],
)
def test_player_publishes_each_scan_on_schedule(
    monkeypatch: pytest.MonkeyPatch, args: list[str], costs: list[float], expected: list[float]
) -> None:
    times = _publish_times(monkeypatch, [10.0, 10.5, 12.0, 12.25], args, costs)
    assert times == pytest.approx(expected, abs=1e-9)


def test_play_loop_with_clock_keeps_stamps_increasing_across_passes(
    repo_root: Path, sample_bag: Path, bag_scans: list[Any], make_receiver: Any
) -> None:
    topic = unique_topic('points')
    clock_topic = unique_topic('clock')
    receiver = make_receiver(topic)
    clocks = make_receiver(clock_topic, Clock)
    proc = _start_play(
        repo_root, str(sample_bag), '--max-scans', '2', '--loop', '--rate', '20', '--clock',
        '--topic', topic, '--wait-subscribers', '30', '--ros-args', '-r',
        f'/clock:={clock_topic}',
    )  # fmt: skip
    try:
        receiver.spin_until(lambda: len(receiver.messages) >= 5)
        clocks.spin_until(lambda: len(clocks.messages) >= 3)
    finally:
        proc.send_signal(signal.SIGINT)
    code, _, stderr = _play_and_receive(receiver, proc, 0)
    assert code == 130, stderr
    assert 'Traceback' not in stderr
    assert re.search(r'interrupted after \d+ scan\(s\)', stderr)
    stamps = [_ns(m.header.stamp) for m in receiver.messages]
    assert len(stamps) >= 5
    # Assert on what arrived, not on the first five: the player starts once its publisher has
    # matched the subscription, but the subscription may match the publisher later; what was
    # sent meanwhile is only resent while still in the publisher's history (depth 10: 0.25 s
    # at 40 Hz), so a slow discovery loses the first messages, reliable QoS or not.
    # Pass k is the two scans shifted by k * (span + one period) = 2k periods, so every stamp
    # is first + j * period with j = 2k (first scan) or 2k + 1 (second), strictly increasing.
    first, second = (s.stamp_ns for s in bag_scans[:2])
    period = second - first
    assert all((s - first) % period == 0 for s in stamps), (stamps, first, period)
    steps = [(s - first) // period for s in stamps]
    assert steps[0] >= 0 and all(b > a for a, b in zip(steps, steps[1:], strict=False)), steps
    assert {j % 2 for j in steps} == {0, 1}, steps  # both scans are played, not one per pass
    clock_ns = [_ns(c.clock) for c in clocks.messages]
    assert len(clock_ns) >= 3
    assert clock_ns == sorted(clock_ns) and clock_ns[0] >= first


def test_play_keeps_its_exit_status_when_ctrl_c_is_pressed_again_while_it_exits(
    repo_root: Path, sample_bag: Path, make_receiver: Any
) -> None:
    """A Ctrl-C repeated while the player cleans up or the interpreter finalises must not kill
    it by the signal (exit -2) or raise in its cleanup: the status of the first one stands."""
    topic = unique_topic('points')
    receiver = make_receiver(topic)
    proc = _start_play(
        repo_root, str(sample_bag), '--max-scans', '2', '--loop', '--rate', '20',
        '--topic', topic, '--wait-subscribers', '30',
    )  # fmt: skip
    try:
        receiver.spin_until(lambda: len(receiver.messages) >= 3)
    finally:
        proc.send_signal(signal.SIGINT)
    deadline = time.monotonic() + TIMEOUT_S
    while proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(signal.SIGINT)
    code, _, stderr = _play_and_receive(receiver, proc, 0)
    assert code == 130, stderr
    assert 'Traceback' not in stderr
    assert re.search(r'interrupted after \d+ scan\(s\)', stderr), stderr


def test_play_bad_input_exits_2_with_one_line(
    sample_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cases = [
        ([str(tmp_path / 'missing_bag')], 'no such file or folder'),
        ([str(sample_bag), '--bag-topic', '/nope'], "no topic '/nope'"),
        ([str(sample_bag), '--start', '50'], '--start 50 is past the last scan'),
        ([str(sample_bag), '--rate', '2', '--hz', '5'], '--rate and --hz exclude each other'),
        ([str(sample_bag), '--clock', '--restamp', 'now'], 'use it with --restamp bag'),
        ([str(sample_bag), '--rate', '-1'], 'expected a finite number >= 0'),
    ]
    for argv, message in cases:
        assert main(argv) == 2, argv
        out, err = capsys.readouterr()
        lines = err.strip().splitlines()
        assert out == ''
        assert len(lines) == 1 and lines[0].startswith('kentreg_play: error: '), err
        assert message in lines[0]


def test_play_ctrl_c_before_publishing_exits_130_with_one_line(
    sample_bag: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from kentreg_ros.ros import play

    def interrupted(options: Any) -> Any:
        raise KeyboardInterrupt

    monkeypatch.setattr(play, '_open_source', interrupted)
    assert main([str(sample_bag)]) == 130
    out, err = capsys.readouterr()
    assert out == '' and err == 'kentreg_play: interrupted before publishing\n'


def test_installed_console_script_reports_bad_input(tmp_path: Path) -> None:
    import shutil

    script = shutil.which('kentreg_play')
    if script is None:
        pytest.skip('kentreg_play is not installed (pip install -e .[ros])')
    proc = subprocess.run(
        [script, str(tmp_path / 'nothing')],
        capture_output=True, text=True, timeout=TIMEOUT_S, check=False,
    )  # fmt: skip
    assert proc.returncode == 2
    assert proc.stderr.strip() == (
        f'kentreg_play: error: {tmp_path / "nothing"}: no such file or folder'
    )


def test_timing_gaps_follow_rate_hz_or_nothing() -> None:
    second = 1_000_000_000
    assert Timing.from_options(None, None).gap_s(0, second // 2) == pytest.approx(0.5)
    assert Timing.from_options(4.0, None).gap_s(0, second) == pytest.approx(0.25)
    assert Timing.from_options(0.0, None).gap_s(0, second) == 0.0
    assert Timing.from_options(None, 20.0).gap_s(0, 5 * second) == pytest.approx(0.05)
    # Stamps that go backwards never make the player wait.
    assert Timing.from_options(1.0, None).gap_s(second, 0) == 0.0


def test_play_skips_a_malformed_cloud_counts_it_and_publishes_the_rest(
    repo_root: Path, sample_bag: Path, bag_scans: list[Any], make_receiver: Any, tmp_path: Path
) -> None:
    """The policy of the node and the replay: a PointCloud2 of the bag that cannot be decoded
    is skipped, said (input index, stamp, reason) and counted in the summary, and the rest of
    the bag is published; exit 0. It ended playback there with exit 2."""
    pytest.importorskip('rosbags', reason='the bag is written with rosbags')
    from recordings import bag_with_malformed_clouds

    bag = tmp_path / 'one_bad'
    stamps = bag_with_malformed_clouds(sample_bag, bag, 5, {1})
    topic = unique_topic('points')
    receiver = make_receiver(topic)
    proc = _start_play(
        repo_root, str(bag), '--rate', '0', '--topic', topic, '--wait-subscribers', '30'
    )
    code, stdout, stderr = _play_and_receive(receiver, proc, 4)
    assert code == 0, stderr
    assert [_ns(m.header.stamp) for m in receiver.messages] == [stamps[i] for i in (0, 2, 3, 4)]
    assert f'published 4 scan(s) on {topic}' in stdout and '1 skipped' in stdout
    (warning,) = [line for line in stderr.splitlines() if 'WARNING' in line]
    assert f'scan 1 (stamp {stamps[1] * 1e-9:.3f} s)' in warning
    assert 'expected row_step * height' in warning
