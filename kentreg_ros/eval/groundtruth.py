"""Reference poses for an evaluation: projected onto SO(3) and associated with the scans."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core import project_to_so3
from kentreg_ros.io.poses import Trajectory

logger = logging.getLogger(__name__)

#: Largest stamp difference (s) for a scan and a ground-truth pose to be associated.
GT_TOLERANCE_S = 0.01
#: Largest change of a rotation entry by :func:`orthonormalize` that goes unreported.
_PROJECTION_REPORTED = 1e-9


@dataclass
class GroundTruth:
    """Reference poses and where they came from; the rotations are projected on creation.

    Attributes
    ----------
    trajectory : Trajectory
        The reference poses ``T_world_sensor``, every rotation block an exact rotation (see
        :func:`orthonormalize`).
    origin : str
        The pose file or bag topic they were read from (for reports).
    """

    trajectory: Trajectory
    origin: str

    def __post_init__(self) -> None:
        self.trajectory = orthonormalize(self.trajectory, self.origin)


def orthonormalize(trajectory: Trajectory, origin: str) -> Trajectory:
    """The trajectory with every rotation block replaced by the nearest rotation.

    Pose files print rotations with few decimals (BALM: 6), so ``R^T R`` misses the identity by
    up to about 1e-6. The pair error ``arccos((tr(R^T R_est) - 1) / 2)`` of a 0.04 deg error
    compares ``1 - cos`` values of about 2.4e-7, so unprojected rotations would dominate it.
    The projection is :func:`~kentreg_ros.core.rotations.project_to_so3` (SVD, Frobenius
    nearest); a change larger than 1e-9 is logged at INFO with ``origin``.
    """
    T = np.array(trajectory.T_world_sensor, dtype=np.float64)
    if len(T) == 0:
        return Trajectory(trajectory.stamps_ns, T)
    R = project_to_so3(T[:, :3, :3])
    deviation = float(np.abs(R - T[:, :3, :3]).max())
    if deviation > _PROJECTION_REPORTED:
        logger.info(
            'Projected the rotations of %s onto SO(3) (max change %.1e).', origin, deviation
        )
    T[:, :3, :3] = R
    return Trajectory(trajectory.stamps_ns, T)


def associate(
    stamps_ns: NDArray[np.int64],
    input_indices: Sequence[int],
    ground_truth: Trajectory,
    *,
    tolerance_s: float = GT_TOLERANCE_S,
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Pair scans with ground-truth poses: by nearest stamp, or by scan index without stamps.

    Parameters
    ----------
    stamps_ns : ndarray of int64, shape (N,)
        Stamps of the processed scans.
    input_indices : sequence of int, length N
        Their indices in the input (used when the reference has no stamps, e.g. KITTI).
    ground_truth : Trajectory
        The reference poses.
    tolerance_s : float
        Largest stamp difference of an associated pair, in seconds.

    Returns
    -------
    scan_rows : ndarray of int, shape (M,)
        Rows of the run's steps that have a reference pose.
    gt_rows : ndarray of int, shape (M,)
        The matching rows of ``ground_truth.T_world_sensor``.
    """
    n_gt = len(ground_truth.T_world_sensor)
    if ground_truth.stamps_ns is None:
        idx = np.asarray(input_indices, dtype=np.intp)
        keep = idx < n_gt
        return np.flatnonzero(keep), idx[keep]
    gt_stamps = np.asarray(ground_truth.stamps_ns, dtype=np.int64)
    order = np.argsort(gt_stamps, kind='stable')
    sorted_stamps = gt_stamps[order]
    pos = np.clip(np.searchsorted(sorted_stamps, stamps_ns), 1, max(len(sorted_stamps) - 1, 1))
    left = sorted_stamps[pos - 1]
    right = sorted_stamps[np.minimum(pos, len(sorted_stamps) - 1)]
    use_left = np.abs(stamps_ns - left) <= np.abs(right - stamps_ns)
    nearest = np.where(use_left, pos - 1, np.minimum(pos, len(sorted_stamps) - 1))
    diff = np.abs(sorted_stamps[nearest] - stamps_ns)
    keep = diff <= int(tolerance_s * 1e9)
    return np.flatnonzero(keep), order[nearest[keep]]
