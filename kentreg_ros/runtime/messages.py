"""What the two processes of the process pipeline say to each other, and how a scan is handed over.

Requests go from the main process to the worker, replies back, pickled through a pipe each; a
scan's points and times go in a file on ``/dev/shm`` (memory), named in its :class:`Job`.

============== ================================================================================
:class:`Job`   prepare the scan in ``path`` (written by :func:`write_scan_file`)
:class:`Go`    the loop's inputs for that scan, once known (a sweep with per-point times waits
               for them: it is deskewed with the motion of the scan before)
:class:`Discard` do not prepare that scan (the caller dropped it)
:class:`Configure` the settings from now on (``generation`` counts them)
:class:`Stop`  exit
:class:`Prepared` the :class:`~kentreg_ros.core.Preparation` of a job, with the generation of
               the settings it was made with
:class:`Failed` the worker raised on a job (a bug): its traceback
============== ================================================================================
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core import KentRegConfig, Preparation

FloatArray = NDArray[np.float64]

#: Seconds between the worker's checks that its parent is still alive (it exits when not) and
#: between the main process's checks that the worker is (while it waits for a result).
PARENT_CHECK_S = 0.5


@dataclass(frozen=True)
class Job:
    """A scan to prepare: its points (and times, ``has_times``) in the file ``path``, the name
    of its time field, its stamp, and the voxel-size hint when the main process knows it
    (None: continue from the worker's last prepared scan)."""

    id: int
    path: str
    has_times: bool
    field: str
    stamp_ns: int
    hint: float | None


@dataclass(frozen=True, eq=False)
class Go:
    """The loop's inputs for job ``id``: the twist to deskew with and the voxel-size hint."""

    id: int
    twist: FloatArray
    hint: float


@dataclass(frozen=True)
class Discard:
    """Job ``id`` will not be stepped: skip it, or forget it as the hint's source."""

    id: int


@dataclass(frozen=True, eq=False)
class Configure:
    """The settings from now on; every reply says the generation it was made with."""

    generation: int
    config: KentRegConfig


@dataclass(frozen=True)
class Stop:
    """Exit (a closed pipe means the same)."""


Request = Job | Go | Discard | Configure | Stop


@dataclass(frozen=True, eq=False)
class Prepared:
    """Job ``id`` prepared with the settings of ``generation``."""

    id: int
    generation: int
    preparation: Preparation


@dataclass(frozen=True)
class Failed:
    """The worker raised on job ``id``: its traceback."""

    id: int
    generation: int
    traceback: str


Reply = Prepared | Failed


def write_scan_file(path: str, points: NDArray[Any], times: NDArray[Any] | None) -> None:
    """Hand a scan over in a file (on ``/dev/shm``, memory): one copy, where a pickle of a few
    MB through the pipe is read in 64 kB pieces, each waiting for the reading thread to get the
    GIL from the preparation running beside it (slow under load: docs/notes-odometry.md)."""
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
        unlink(path)
    return points, times


def unlink(path: str) -> None:
    """Remove ``path`` if it is there."""
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass
