"""kentreg_ros.ros.logbridge: the package's Python log records on an rclpy logger, throttled.

With a recording stand-in for the rclpy logger (what was forwarded, at which severity) and, for
the severities and call sites rclpy insists on, with rclpy's own logger. The node's use of it
(a rejected scan leaves a WARN on /rosout) is tested in ``test_ros_node.py``.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip('rclpy', reason="rclpy is not installed (pip install -e '.[ros]')")

from kentreg_ros.ros.logbridge import PACKAGE_LOGGER, RclpyLogHandler  # noqa: E402

THROTTLE_S = 5.0
CORE = logging.getLogger('kentreg_ros.core.odometry')


class Recorder:
    """Stands in for an rclpy logger: keeps (severity name, message) of every call."""

    def __init__(self, level: int = 20) -> None:
        self.calls: list[tuple[str, str]] = []
        self.level = level

    def get_effective_level(self) -> int:
        return self.level

    def debug(self, message: str) -> None:
        self.calls.append(('DEBUG', message))

    def info(self, message: str) -> None:
        self.calls.append(('INFO', message))

    def warning(self, message: str) -> None:
        self.calls.append(('WARN', message))

    def error(self, message: str) -> None:
        self.calls.append(('ERROR', message))

    def fatal(self, message: str) -> None:
        self.calls.append(('FATAL', message))


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def bridge() -> Iterator[tuple[RclpyLogHandler, Recorder, Clock]]:
    recorder, clock = Recorder(level=10), Clock()
    handler = RclpyLogHandler(recorder, throttle_s=THROTTLE_S, clock=clock).attach()
    try:
        yield handler, recorder, clock
    finally:
        handler.detach()


def test_records_go_out_at_the_matching_severity_with_their_traceback(
    bridge: tuple[RclpyLogHandler, Recorder, Clock],
) -> None:
    _, recorder, _ = bridge
    CORE.debug('a debug record')
    CORE.info('an info record')
    CORE.warning('Scan %d: %s', 3, 'Rejected the scan: too few points.')
    CORE.error('an error record')
    CORE.critical('a critical record')
    try:
        raise ValueError('boom')
    except ValueError:
        CORE.warning('with a traceback', exc_info=True)
    severities = [s for s, _ in recorder.calls]
    assert severities == ['DEBUG', 'INFO', 'WARN', 'ERROR', 'FATAL', 'WARN']
    assert recorder.calls[2][1] == 'Scan 3: Rejected the scan: too few points.'
    assert 'Traceback' in recorder.calls[-1][1] and 'ValueError: boom' in recorder.calls[-1][1]


def test_a_kind_of_message_is_held_back_within_the_throttle_period_and_counted(
    bridge: tuple[RclpyLogHandler, Recorder, Clock],
) -> None:
    """Numbers vary, the kind does not: held back and counted. Two kinds of the same template
    ('Scan %d: %s') are throttled apart, so a rejection does not hide a fall-back."""
    _, recorder, clock = bridge
    for index in range(4):
        CORE.warning('Scan %d: %s', index, f'Rejected the scan: got {index} points.')
        clock.now += 1.0
    CORE.warning('Scan %d: %s', 9, 'The registration failed: the pose is the prediction.')
    assert [m for _, m in recorder.calls] == [
        'Scan 0: Rejected the scan: got 0 points.',
        'Scan 9: The registration failed: the pose is the prediction.',
    ]
    clock.now += THROTTLE_S
    CORE.warning('Scan %d: %s', 20, 'Rejected the scan: got 20 points.')
    assert recorder.calls[-1][1] == (
        'Scan 20: Rejected the scan: got 20 points. (3 more like this in the last 9 s not shown.)'
    )


def test_the_package_logger_takes_the_rclpy_level_while_attached_and_gets_its_own_back() -> None:
    package = logging.getLogger(PACKAGE_LOGGER)
    before = package.level
    try:
        package.setLevel(logging.NOTSET)  # nobody chose one
        handler = RclpyLogHandler(Recorder(level=10), throttle_s=1.0).attach()
        try:
            assert package.level == logging.DEBUG and handler in package.handlers
        finally:
            handler.detach()
        assert package.level == logging.NOTSET and handler not in package.handlers
        package.setLevel(logging.ERROR)  # a level someone chose stands
        handler = RclpyLogHandler(Recorder(level=10), throttle_s=1.0).attach()
        assert package.level == logging.ERROR
        handler.detach()
        assert package.level == logging.ERROR
    finally:
        package.setLevel(before)


def test_a_record_of_a_thread_a_handler_owns_goes_to_that_handler_only() -> None:
    mine, other = Recorder(), Recorder()
    a = RclpyLogHandler(mine, throttle_s=0.0).attach()
    b = RclpyLogHandler(other, throttle_s=0.0).attach()
    try:
        done = threading.Event()

        def work() -> None:
            a.own_thread(threading.get_ident())
            CORE.warning('from the worker')
            done.set()

        worker = threading.Thread(target=work)
        worker.start()
        worker.join(10.0)  # ended: no thread of this test outlives it
        assert done.is_set()
        CORE.warning('from the main thread')
    finally:
        a.detach()
        b.detach()
    assert [m for _, m in mine.calls] == ['from the worker', 'from the main thread']
    assert [m for _, m in other.calls] == ['from the main thread']


def test_rclpys_own_logger_takes_every_severity_from_the_handler_repeatedly(
    capfd: pytest.CaptureFixture[str],
) -> None:
    """rclpy refuses a call site whose severity changes between calls; the handler calls it
    from one site per severity, so records of mixed levels go out every time."""
    import rclpy.logging

    logger = rclpy.logging.get_logger('kentreg_logbridge_test')
    logger.set_level(rclpy.logging.LoggingSeverity.DEBUG)
    handler = RclpyLogHandler(logger, throttle_s=0.0).attach()
    try:
        for round_ in range(2):
            for level in (logging.DEBUG, logging.INFO, logging.WARNING, logging.ERROR):
                CORE.log(level, 'round %d at %s', round_, logging.getLevelName(level))
    finally:
        handler.detach()
    err = capfd.readouterr().err
    assert 'Logging error' not in err and 'cannot be changed' not in err, err
    for round_ in range(2):
        for name in ('DEBUG', 'INFO', 'WARNING', 'ERROR'):
            assert f'round {round_} at {name}' in err, err


@pytest.mark.integration
def test_importing_the_node_attaches_no_handler(repo_root: Path) -> None:
    env = {**os.environ, 'PYTHONPATH': os.pathsep.join([str(repo_root), *sys.path])}
    script = (
        'import logging, kentreg_ros.ros.node, kentreg_ros.ros.logbridge\n'
        "print(len(logging.getLogger('kentreg_ros').handlers), logging.getLogger().handlers)\n"
    )
    proc = subprocess.run(
        [sys.executable, '-c', script], capture_output=True, text=True, env=env, timeout=120,
        check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ['0', '[]']


def test_throttle_must_be_a_non_negative_number() -> None:
    with pytest.raises(ValueError, match='Expected `throttle_s` >= 0, got -1'):
        RclpyLogHandler(Recorder(), throttle_s=-1)
