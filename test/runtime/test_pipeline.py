"""The odometry with its prepare stage in a worker process (kentreg_ros.runtime.ProcessPreparer)
gives the sequential loop's poses bit for bit, surfaces the worker's errors and leaves no process
behind."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from kentreg_ros.core import KentRegConfig, Odometry, PointTimes
from kentreg_ros.runtime import MAX_OPEN_JOBS, PipelineError, ProcessPreparer

#: Worker processes: the integration tier.
pytestmark = pytest.mark.integration

NS = 1_000_000_000


@pytest.fixture(scope='module')
def balm_50(repo_root: Path) -> list[tuple[np.ndarray, int]]:
    pytest.importorskip('rosbags', reason='rosbags is not installed (pip install -e .[io])')
    from kentreg_ros.io import open_scan_source

    return [(s.points, int(s.stamp_ns)) for s in open_scan_source(repo_root / 'bags' / 'balm_50')]


def _sweep_times(points: np.ndarray) -> PointTimes:
    """Per-point times of a 10 Hz spinning sensor, from each point's azimuth (Ouster-like
    uint32 nanoseconds from the sweep start), so the scans are deskewed."""
    turn = (np.arctan2(points[:, 1], points[:, 0]) + np.pi) / (2.0 * np.pi)
    return PointTimes((turn * 0.1 * NS).astype(np.uint32), 't')


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A zombie (exited, not yet reaped by its parent) is not running.
    try:
        with open(f'/proc/{pid}/stat') as f:
            return f.read().split()[2] != 'Z'
    except FileNotFoundError:
        return False


def _wait_gone(pid: int, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not _alive(pid):
            return True
        time.sleep(0.05)
    return False


@pytest.mark.parametrize('model', ['previous_scan', 'local_map'])
def test_pipelined_poses_equal_the_sequential_loop_on_balm_50(
    balm_50: list[tuple[np.ndarray, int]], model: str
) -> None:
    config = KentRegConfig().with_updates({'odometry.model': model})
    sequential = Odometry(config)
    expected = [sequential.step(p, t).T_world_lidar for p, t in balm_50]
    with ProcessPreparer() as preparer:
        odometry = Odometry(config, preparer=preparer)
        got = []
        preparer.prefetch(*balm_50[0])
        for i, (points, stamp) in enumerate(balm_50):
            if i + 1 < len(balm_50):
                preparer.prefetch(*balm_50[i + 1])  # the next scan is prepared meanwhile
            got.append(odometry.step(points, stamp).T_world_lidar)
        stats = preparer.stats
    assert all(np.array_equal(a, b) for a, b in zip(expected, got, strict=True))
    # The worker prepared every scan (none was prepared again here): the overlap is real.
    assert stats.prepared_remote == len(balm_50), stats
    assert stats.prepared_here == 0


def test_pipelined_poses_equal_the_sequential_loop_with_per_point_times(
    balm_50: list[tuple[np.ndarray, int]],
) -> None:
    scans = [(p, t, _sweep_times(p)) for p, t in balm_50[:15]]
    config = KentRegConfig().with_updates({'odometry.model': 'local_map'})
    sequential = Odometry(config)
    expected = [sequential.step(p, t, point_times=pt) for p, t, pt in scans]
    assert any(s.n_prepared and s.timings for s in expected)
    with ProcessPreparer() as preparer:
        odometry = Odometry(config, preparer=preparer)
        got = []
        for i, (points, stamp, times) in enumerate(scans):
            if i == 0:
                preparer.prefetch(points, stamp, point_times=times)
            if i + 1 < len(scans):
                preparer.prefetch(scans[i + 1][0], scans[i + 1][1], point_times=scans[i + 1][2])
            got.append(odometry.step(points, stamp, point_times=times))
        assert preparer.stats.prepared_remote == len(scans)
    for a, b in zip(expected, got, strict=True):
        assert np.array_equal(a.T_world_lidar, b.T_world_lidar)
        assert a.health == b.health


def test_dropped_scans_reset_and_reconfigure_keep_the_sequential_poses(
    balm_50: list[tuple[np.ndarray, int]],
) -> None:
    """Scans prefetched and never stepped (a queue dropping them), a reset and a change of
    settings between steps: the worker's results made with other inputs are prepared again
    here, so the poses stay the sequential loop's over the stepped scans."""
    scans = balm_50[:16]
    dropped = {3, 4, 9}
    other = KentRegConfig().with_updates({'odometry.model': 'local_map'})

    def run(odometry: Odometry, preparer: ProcessPreparer | None = None) -> list[np.ndarray]:
        poses = []
        for i, (points, stamp) in enumerate(scans):
            if preparer is not None:
                if i == 0:
                    preparer.prefetch(points, stamp)
                if i + 1 < len(scans):
                    preparer.prefetch(*scans[i + 1])
            if i in dropped:
                continue
            if i == 6:
                odometry.reset()
            if i == 11:
                odometry.reconfigure(other)
            poses.append(odometry.step(points, stamp).T_world_lidar)
        return poses

    expected = run(Odometry(KentRegConfig()))
    with ProcessPreparer() as preparer:
        # Whether the worker had prepared a scan before its inputs changed (then it is
        # prepared again here) depends on timing; the poses must not.
        got = run(Odometry(KentRegConfig(), preparer=preparer), preparer)
    assert all(np.array_equal(a, b) for a, b in zip(expected, got, strict=True))


def test_a_caller_more_than_max_open_jobs_behind_gets_every_scan(
    balm_50: list[tuple[np.ndarray, int]],
) -> None:
    """A node with a long queue (``queue_size`` above :data:`MAX_OPEN_JOBS`) prefetches more
    scans than the pipeline keeps open: the oldest jobs are discarded and handed over again
    when stepped, with newer ids than the scans prefetched after them. The replies of those
    later scans arrive first and must be kept (they were dropped, and the next step waited
    forever)."""
    scans = balm_50[: MAX_OPEN_JOBS + 4]
    sequential = Odometry(KentRegConfig())
    expected = [sequential.step(p, t).T_world_lidar for p, t in scans]
    got: list[np.ndarray] = []
    with ProcessPreparer() as preparer:
        odometry = Odometry(KentRegConfig(), preparer=preparer)
        for points, stamp in scans:
            preparer.prefetch(points, stamp)  # all of them before the first step

        def step_all() -> None:
            got.extend(odometry.step(p, t).T_world_lidar for p, t in scans)

        runner = threading.Thread(target=step_all, daemon=True)
        runner.start()
        runner.join(timeout=120.0)
        assert not runner.is_alive(), f'a step waits forever (after {len(got)} scans)'
    assert all(np.array_equal(a, b) for a, b in zip(expected, got, strict=True))


def test_an_error_in_the_worker_is_raised_from_its_step_and_the_loop_goes_on(
    balm_50: list[tuple[np.ndarray, int]], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A scan the worker fails on (here: its hand-over file is garbage) raises PipelineError
    from its step, with the worker's traceback; the worker and the loop go on."""
    import kentreg_ros.runtime.preparer as preparer_module

    (p0, t0), (p1, t1), (p2, t2) = balm_50[:3]
    real = preparer_module.write_scan_file

    def garbage_for_p1(path: str, points: np.ndarray, times: np.ndarray | None) -> None:
        if points is p1:
            Path(path).write_bytes(b'not a numpy file')
        else:
            real(path, points, times)

    monkeypatch.setattr(preparer_module, 'write_scan_file', garbage_for_p1)
    with ProcessPreparer() as preparer:
        odometry = Odometry(preparer=preparer)
        odometry.step(p0, t0)
        with pytest.raises(PipelineError, match='could not be read'):
            odometry.step(p1, t1)
        step = odometry.step(p2, t2)
        assert step.ok, step.message
        assert preparer.n_worker_restarts == 0
        assert odometry.n_steps == 2  # the failed scan did not step


def test_a_scan_that_cannot_be_handed_over_is_prepared_here(
    balm_50: list[tuple[np.ndarray, int]],
) -> None:
    """Per-point times of a dtype the hand-over file refuses (objects): the scan is prepared
    in the main process, so it fails exactly as in the sequential loop."""
    (p0, t0), (p1, t1) = balm_50[:2]
    bad_times = np.array(['x'] * len(p1), dtype=object)
    with pytest.raises(ValueError):
        Odometry().step(p1, t1, point_times=bad_times)
    with ProcessPreparer() as preparer:
        odometry = Odometry(preparer=preparer)
        odometry.step(p0, t0)
        with pytest.raises(ValueError):
            odometry.step(p1, t1, point_times=bad_times)


def test_a_killed_worker_is_replaced_and_no_scan_is_lost(
    balm_50: list[tuple[np.ndarray, int]],
) -> None:
    sequential = Odometry()
    expected = [sequential.step(p, t).T_world_lidar for p, t in balm_50[:4]]
    with ProcessPreparer() as preparer:
        odometry = Odometry(preparer=preparer)
        got = [odometry.step(*balm_50[0]).T_world_lidar]
        first = preparer.worker_pid
        assert first is not None
        preparer.prefetch(*balm_50[1])
        os.kill(first, signal.SIGKILL)
        got += [odometry.step(p, t).T_world_lidar for p, t in balm_50[1:4]]
        assert preparer.n_worker_restarts == 1
        assert preparer.worker_pid not in (None, first)
    assert _wait_gone(first)
    assert all(np.array_equal(a, b) for a, b in zip(expected, got, strict=True))


def test_close_stops_the_worker() -> None:
    preparer = ProcessPreparer()
    odometry = Odometry(preparer=preparer)
    pid = preparer.worker_pid
    assert pid is not None and _alive(pid)
    preparer.close()
    preparer.close()  # idempotent
    assert _wait_gone(pid)
    with pytest.raises(PipelineError, match='closed'):
        odometry.step(np.zeros((100, 3)), 1)
    assert odometry.n_steps == 0


def test_the_worker_exits_when_its_parent_is_killed(tmp_path: Path) -> None:
    """No orphan: a parent killed without any chance to clean up (SIGKILL) leaves a worker
    that notices within a second and exits."""
    script = textwrap.dedent(
        """
        import os, signal, sys
        from kentreg_ros.runtime import ProcessPreparer
        preparer = ProcessPreparer()
        print(preparer.worker_pid, flush=True)
        os.kill(os.getpid(), signal.SIGKILL)
        """
    )
    env = {**os.environ, 'PYTHONPATH': str(Path(__file__).resolve().parents[2])}
    out = subprocess.run(
        [sys.executable, '-c', script], capture_output=True, text=True, env=env, timeout=60
    )
    assert out.returncode == -signal.SIGKILL, out.stderr
    pid = int(out.stdout.split()[0])
    assert _wait_gone(pid), f'worker {pid} outlived its parent'
