"""Shared pytest fixtures: where the repository and the real recorded data live."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

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
