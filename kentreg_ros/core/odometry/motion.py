"""The motion stages of the odometry: predict a scan's pose, and chain the chosen one.

``predict`` moves the last pose by the last accepted motion (constant velocity); ``chain``
puts the step's pose, found in the model's frame, into the world frame with its covariance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core.geometry import exp_so3, invert_transform, log_so3, make_transform
from kentreg_ros.core.odometry.covariance import prediction_covariance, propagate_covariance
from kentreg_ros.core.odometry.step import Health
from kentreg_ros.core.odometry.verify import Outcome

FloatArray = NDArray[np.float64]

#: Largest factor by which the last motion is stretched when the scan gap grows (dropped scans).
MAX_VELOCITY_SCALE = 5.0


@dataclass(frozen=True)
class Motion:
    """The last accepted motion ``T_prev_curr``, the time it took (ns), and its constant twist
    ``(omega, v)`` per second (:func:`~.deskew.twist_of`, worked out once when the motion is
    learned: the next sweeps are deskewed with it)."""

    T_prev_curr: FloatArray
    gap_ns: int
    twist: FloatArray


def predict(
    T_world_last: FloatArray, stamp_last: int, stamp: int, motion: Motion | None
) -> FloatArray:
    """``T_world_pred`` of a scan taken at ``stamp``: the last pose moved by the last accepted
    motion stretched to the time gap (constant velocity, the factor at most
    :data:`MAX_VELOCITY_SCALE`), or the last pose without a motion."""
    if motion is None:
        return T_world_last.copy()
    gap_now = stamp - stamp_last
    factor = 1.0
    if motion.gap_ns > 0 and gap_now > 0:
        factor = min(gap_now / motion.gap_ns, MAX_VELOCITY_SCALE)
    T = motion.T_prev_curr
    if factor != 1.0:  # the rotation vector and the translation scaled alike (first-order screw)
        T = make_transform(exp_so3(factor * log_so3(T[:3, :3])), factor * T[:3, 3])
    return T_world_last @ T


@dataclass(frozen=True, eq=False)
class Chained:
    """A step's pose in the world, and the same pose in the model's frame.

    Attributes
    ----------
    T_world : ndarray, shape (4, 4)
        ``T_world_lidar`` of the step.
    T_model : ndarray, shape (4, 4)
        ``T_model_lidar``, read back from ``T_world`` (the motion the next prediction repeats
        is the one between the poses the odometry reports, rounding included).
    covariance : ndarray, shape (6, 6)
        Covariance of ``T_world`` (see :func:`propagate_covariance`).
    """

    T_world: FloatArray
    T_model: FloatArray
    covariance: FloatArray


def chain(
    T_world_model: FloatArray,
    cov_world_model: FloatArray,
    outcome: Outcome,
    T_world_pred: FloatArray,
    T_model_pred: FloatArray,
) -> Chained:
    """``T_world_curr = T_world_model @ T_model_curr`` for a registered step, the prediction
    otherwise; the covariances chained (a predicted step adds
    :func:`prediction_covariance`; the first scan is the origin, with the model's)."""
    T_world = T_world_model @ outcome.T if outcome.health.accepted else T_world_pred
    T_model = invert_transform(T_world_model) @ T_world
    if outcome.health is Health.FIRST:
        return Chained(T_world, T_model, cov_world_model.copy())
    if outcome.health.accepted and outcome.result is not None:
        cov_step = np.asarray(outcome.result.covariance, dtype=np.float64)
    else:
        cov_step = prediction_covariance(T_model_pred)
    cov = propagate_covariance(cov_world_model, T_world_model, T_model, cov_step)
    return Chained(T_world, T_model, cov)
