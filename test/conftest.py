"""Shared pytest fixtures: where the repository and the real recorded data live; ROS set-up."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import ros_env  # test/ is on sys.path (rootdir conftest, default 'prepend' import mode)

# One BLAS thread for the tests and the processes they start (set before numpy is imported:
# no plugin imports it earlier): the tests' matrices are tiny, and where the cores are busy
# OpenBLAS's threads spend far longer waiting for each other than computing.
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

REPO_ROOT = Path(__file__).resolve().parents[1]
#: Real scans (BALM, small_gicp pair) kept beside the repository, not inside it.
SHARED_DATA = Path(os.environ.get('KENTREG_SHARED_DATA', REPO_ROOT.parent / 'shared' / 'data'))


@pytest.fixture(scope='session')
def repo_root() -> Path:
    """The repository root (holds ``bags/``)."""
    return REPO_ROOT


@pytest.fixture(scope='session')
def shared_data() -> Path:
    """``../shared/data``; tests using it skip when the repository is cloned without it."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f'real data folder {SHARED_DATA} is absent (set KENTREG_SHARED_DATA)')
    return SHARED_DATA


def pytest_configure(config: pytest.Config) -> None:
    """Keep DDS on loopback in a test-only domain before any test can call ``rclpy.init``.

    Subprocesses started by tests inherit these variables (see ``test/ros_env.py``).
    """
    ros_env.apply_ros_env()


@pytest.fixture(scope='session')
def ros_env_vars() -> dict[str, str]:
    """The DDS variables of this session (already in ``os.environ``)."""
    return ros_env.ros_env()


@pytest.fixture
def rclpy_context() -> Iterator[Any]:
    """A fresh, initialised ``rclpy`` context (not the default one), shut down afterwards.

    Create nodes with ``Node(..., context=rclpy_context)`` and executors with
    ``SingleThreadedExecutor(context=rclpy_context)``. Skips when rclpy is not installed.
    """
    rclpy = pytest.importorskip('rclpy', reason='rclpy is not installed (pip install -e .[ros])')
    from rclpy.context import Context

    context = Context()
    rclpy.init(context=context)
    try:
        yield context
    finally:
        rclpy.try_shutdown(context=context)
