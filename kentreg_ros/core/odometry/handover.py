"""What the pipeline's two processes share: how a scan is handed over, and how often each
checks that the other is alive."""

from __future__ import annotations

import os
from typing import Any

import numpy as np
from numpy.typing import NDArray

#: Seconds between the worker's checks that its parent is still alive (it exits when not) and
#: between the main process's checks that the worker is (while it waits for a result).
PARENT_CHECK_S = 0.5


def write_scan_file(path: str, points: NDArray[Any], times: NDArray[Any] | None) -> None:
    """Hand a scan over in a file (on ``/dev/shm``, memory): one copy, where a 2-3 MB pickle
    through the pipe is read in 64 kB pieces, each waiting for the reading thread to get the
    GIL from the preparation running beside it (measured: 100+ ms a scan under load)."""
    with open(path, 'wb') as f:
        np.save(f, points, allow_pickle=False)
        if times is not None:
            np.save(f, times, allow_pickle=False)


def read_scan_file(path: str, has_times: bool) -> tuple[NDArray[Any], NDArray[Any] | None]:
    """The scan of :func:`write_scan_file`; the file is removed."""
    try:
        with open(path, 'rb') as f:
            points = np.load(f, allow_pickle=False)
            times = np.load(f, allow_pickle=False) if has_times else None
    finally:
        try:
            os.unlink(path)
        except FileNotFoundError:
            pass
    return points, times
