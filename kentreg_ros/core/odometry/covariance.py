"""First-order covariance of a chained pose: the odometry's uncertainty along its path."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core.geometry import hat, rotation_angle

FloatArray = NDArray[np.float64]

#: Smallest standard deviations (m, rad) of a predicted step (fall-back or rejected scan): a
#: constant-velocity guess is not known better than a few centimetres and a degree even when
#: the sensor barely moves (a stop, a jerk within one scan period).
PREDICTION_MIN_STD = (0.05, float(np.radians(1.0)))


def prediction_covariance(T_model_pred: FloatArray) -> FloatArray:
    """Isotropic covariance of a step known only by prediction, as large as the motion."""
    std_t = max(float(np.linalg.norm(T_model_pred[:3, 3])), PREDICTION_MIN_STD[0])
    std_r = max(rotation_angle(T_model_pred[:3, :3]), PREDICTION_MIN_STD[1])
    return np.diag([std_t**2] * 3 + [std_r**2] * 3)


def propagate_covariance(
    cov_world_model: ArrayLike,
    T_world_model: ArrayLike,
    T_model_curr: ArrayLike,
    cov_step: ArrayLike,
) -> FloatArray:
    """Covariance of ``T_world_curr = T_world_model @ T_model_curr``, to first order.

    Parameters
    ----------
    cov_world_model : array_like, shape (6, 6)
        Covariance of ``T_world_model`` in the order (x, y, z, rot_x, rot_y, rot_z), for the
        errors ``R_true = exp(w) R`` and ``p_true = p + v`` (world axes, at the pose's own
        position: the usual reading of a nav_msgs/Odometry pose covariance).
    T_world_model, T_model_curr : array_like, shape (4, 4)
    cov_step : array_like, shape (6, 6)
        Covariance of ``T_model_curr`` for the left perturbation ``T_true = exp(delta) T`` in
        the model frame, (x, y, z, rot_x, rot_y, rot_z): what
        :attr:`~kentreg_ros.core.registration.register.RegistrationResult.covariance` gives.

    Returns
    -------
    ndarray, shape (6, 6)
        Covariance of ``T_world_curr`` in the convention of ``cov_world_model``.

    Notes
    -----
    With ``R = R_world_model`` and ``d = R t_model_curr`` (the step in world axes),
    ``v_curr = v_model - [d]x w_model + R v_step - [d]x R w_step`` and
    ``w_curr = w_model + R w_step``.
    """
    cov_m = np.asarray(cov_world_model, dtype=np.float64)
    T_wm = np.asarray(T_world_model, dtype=np.float64)
    T_mc = np.asarray(T_model_curr, dtype=np.float64)
    R = T_wm[:3, :3]
    d_hat = hat(R @ T_mc[:3, 3])
    J_model = np.eye(6)
    J_model[:3, 3:] = -d_hat
    J_step = np.zeros((6, 6))
    J_step[:3, :3] = R
    J_step[:3, 3:] = -d_hat @ R
    J_step[3:, 3:] = R
    cov = J_model @ cov_m @ J_model.T + J_step @ np.asarray(cov_step, np.float64) @ J_step.T
    return np.asarray(0.5 * (cov + cov.T), dtype=np.float64)
