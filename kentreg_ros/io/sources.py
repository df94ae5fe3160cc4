"""Where scans come from: the scan value types, the scan source interface, scan folders, and
:func:`open_scan_source` (a bag or a folder)."""

from __future__ import annotations

import abc
import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import DTypeLike, NDArray

from kentreg_ros.core import InvalidPointCloudError, KentRegError
from kentreg_ros.io.errors import BagError, PoseFileError, ScanFileError, describe_error
from kentreg_ros.io.poses import Trajectory, read_poses
from kentreg_ros.io.scanfiles import SCAN_SUFFIXES, list_scans, read_scan

DEFAULT_RATE_HZ = 10.0


class Scan(NamedTuple):
    """One scan from a bag or a scan folder.

    Attributes
    ----------
    stamp_ns : int
        Header stamp (bags; the receive time when the header stamp is zero), or the pose
        file's time / ``start + i / rate`` (scan folders), in nanoseconds.
    frame_id : str
        Sensor frame.
    points : ndarray, shape (N, 3)
        Finite points in the sensor frame.
    extras : dict of str to ndarray, each shape (N,) or (N, k)
        Per-point fields aligned with ``points``.
    """

    stamp_ns: int
    frame_id: str
    points: NDArray[np.floating[Any]]
    extras: dict[str, NDArray[Any]]


logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SkippedScan:
    """An input message or scan file that holds no usable scan (see :meth:`ScanSource.entries`).

    Attributes
    ----------
    index : int
        Its position in the input: the message index on the topic, or the file's index.
    stamp_ns : int or None
        Its stamp when it could be read (a bag message's header stamp, or its log time when the
        header stamp is zero; a scan file's stamp), else None.
    reason : str
        Why it was skipped, one line (the decoder's message).
    """

    index: int
    stamp_ns: int | None
    reason: str


class ScanSource(abc.ABC):
    """Iterable of :class:`Scan` from a bag or scan files; ``len()`` is the number of scans.

    Iterating opens the underlying files and closes them when done; a source can be
    iterated more than once. ``n_dropped`` counts the non-finite points dropped so far.

    Iterating a source raises at the first message (or file) that cannot be decoded as a scan
    (:class:`~kentreg_ros.core.errors.InvalidPointCloudError`,
    :class:`~kentreg_ros.io.errors.ScanFileError`). :meth:`entries` instead yields a
    :class:`SkippedScan` in its place and goes on, as the ROS node and ``kentreg_replay`` do
    with a malformed scan: skip it, count it, say which.
    """

    path: Path
    n_dropped: int = 0

    @abc.abstractmethod
    def entries(self) -> Iterator[Scan | SkippedScan]:
        """One entry per input message or file, in order: its :class:`Scan`, or a
        :class:`SkippedScan` when it cannot be decoded as one. A fault of the container itself
        (a corrupt bag, an unreadable folder) still raises: nothing after it can be read."""

    def __iter__(self) -> Iterator[Scan]:
        for entry in self.entries():
            if isinstance(entry, SkippedScan):
                raise self._skip_error(entry)
            yield entry

    def _skip_error(self, entry: SkippedScan) -> KentRegError:
        return InvalidPointCloudError(f'{self.path}: scan {entry.index}: {entry.reason}')

    @abc.abstractmethod
    def __len__(self) -> int: ...

    @property
    @abc.abstractmethod
    def description(self) -> str:
        """One line telling what is read (for logs)."""


class FilesScanSource(ScanSource):
    """Scan files in a given order, timed by a pose file or a rate.

    Parameters
    ----------
    files : sequence of str or Path
        Scan files (.pcd, .ply, .bin, .csv), in scan order.
    poses : Trajectory or str or Path, optional
        One pose per scan; its times stamp the scans unless ``rate`` is given.
    rate : float, optional
        Scan rate in Hz: stamps are ``start_ns + i / rate``. Default: the pose times, or
        10 Hz when there are none.
    start_ns : int
        First stamp when stamps come from ``rate``.
    frame_id : str
        Sensor frame given to every scan.
    fields, dtype
        As in :func:`~kentreg_ros.io.scanfiles.read_scan`.

    Raises
    ------
    PoseFileError
        The pose count differs from the scan count.
    """

    def __init__(
        self,
        files: Sequence[str | Path],
        *,
        poses: Trajectory | str | Path | None = None,
        rate: float | None = None,
        start_ns: int = 0,
        frame_id: str = 'lidar',
        fields: Sequence[str] | None = None,
        dtype: DTypeLike = np.float64,
    ) -> None:
        self.files = [Path(f) for f in files]
        if not self.files:
            raise ValueError('Expected at least one scan file.')
        self.path = self.files[0].parent
        self.trajectory = read_poses(poses) if isinstance(poses, str | Path) else poses
        if self.trajectory is not None and len(self.trajectory.T_world_sensor) != len(self.files):
            raise PoseFileError(
                f'{len(self.trajectory.T_world_sensor)} poses for {len(self.files)} scans in '
                f'{self.path}; give one pose per scan.'
            )
        if rate is not None and not rate > 0.0:
            raise ValueError(f'Expected `rate` > 0 Hz, got {rate!r}.')
        if rate is None and self.trajectory is not None and self.trajectory.stamps_ns is not None:
            self.stamps_ns = self.trajectory.stamps_ns.astype(np.int64)
            self.timing = 'pose file times'
        else:
            hz = DEFAULT_RATE_HZ if rate is None else float(rate)
            if start_ns < 0:
                raise ValueError(f'Expected `start_ns` >= 0, got {start_ns}.')
            steps = np.rint(np.arange(len(self.files)) * (1e9 / hz)).astype(np.int64)
            self.stamps_ns = int(start_ns) + steps
            self.timing = f'{hz:g} Hz'
            if rate is None:
                logger.info('No scan times given; stamping scans at %g Hz.', hz)
        self.frame_id = frame_id
        self.fields = fields
        self.dtype = dtype

    def __len__(self) -> int:
        return len(self.files)

    @property
    def description(self) -> str:
        return f'{len(self.files)} scan files in {self.path} ({self.timing})'

    def entries(self) -> Iterator[Scan | SkippedScan]:
        for index, (path, stamp) in enumerate(zip(self.files, self.stamps_ns, strict=True)):
            try:
                cloud = read_scan(path, fields=self.fields, dtype=self.dtype)
            except InvalidPointCloudError as exc:  # ScanFileError among them
                yield SkippedScan(index, int(stamp), describe_error(exc))
                continue
            self.n_dropped += cloud.n_dropped
            yield Scan(int(stamp), self.frame_id, cloud.points, cloud.extras)

    def _skip_error(self, entry: SkippedScan) -> KentRegError:
        return ScanFileError(entry.reason)  # read_scan's message names the file


def open_scan_source(
    path: str | Path,
    *,
    topic: str | None = None,
    fields: Sequence[str] | None = None,
    dtype: DTypeLike = np.float64,
    poses: Trajectory | str | Path | None = None,
    rate: float | None = None,
    start_ns: int = 0,
    frame_id: str = 'lidar',
) -> ScanSource:
    """Open a bag, a scan folder or a single scan file as an iterable of :class:`Scan`.

    Parameters
    ----------
    path : str or Path
        A bag (``.bag``, ``.mcap``, ``.db3``, rosbag2 folder), a folder of scan files (natural
        order, see :func:`~kentreg_ros.io.scanfiles.list_scans`), or one scan file.
    topic : str, optional
        Bags only: the PointCloud2 topic, needed when there are several.
    fields : sequence of str, optional
        Extra fields to keep; None keeps all, ``()`` none.
    dtype : {numpy.float64, numpy.float32}
    poses, rate, start_ns, frame_id
        Scan files only; see :class:`FilesScanSource`.

    Returns
    -------
    ScanSource
        ``for stamp_ns, frame_id, points, extras in source: ...``

    Raises
    ------
    BagError, ScanFileError, PoseFileError
    """
    from kentreg_ros.io.bags import BAG_SUFFIXES, BagScanSource, is_bag  # it imports this module

    p = Path(path)
    if is_bag(p):
        if poses is not None or rate is not None:
            raise ValueError('`poses` and `rate` apply to scan files, not to bags.')
        return BagScanSource(p, topic, fields=fields, dtype=dtype)
    if topic is not None:
        raise ValueError(f'`topic` applies to bags; {p} is not a bag.')
    if p.is_dir():
        files = list_scans(p)
    elif p.is_file() and p.suffix.lower() in SCAN_SUFFIXES:
        files = [p]
    else:
        raise BagError(
            f'{p}: neither a bag ({", ".join(BAG_SUFFIXES)}, rosbag2 folder) nor a scan '
            f'folder or file ({", ".join(SCAN_SUFFIXES)}).'
        )
    return FilesScanSource(
        files,
        poses=poses,
        rate=rate,
        start_ns=start_ns,
        frame_id=frame_id,
        fields=fields,
        dtype=dtype,
    )
