"""First-order covariances of the odometry: a chained pose (its uncertainty along the path) and a
step's twist."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core.geometry import hat, log_so3, rotation_angle

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


def moved_into_pose(cov_step: ArrayLike, T_model_curr: ArrayLike) -> FloatArray:
    """A step's covariance (left perturbation in the model frame) moved into the frame of the
    pose it found, to first order: the error of that pose against the model, seen from the pose.

    With ``C = T_model_curr`` and a step error ``D = (v, w)`` (``T_true = D C``), the pose's
    frame sees ``C^-1 D C``: ``(R^T (v - [t]x w), R^T w)``, ``(R, t)`` of ``C`` (the sign, which a
    covariance does not see, aside).

    Parameters
    ----------
    cov_step : array_like, shape (6, 6)
        In the convention of
        :attr:`~kentreg_ros.core.registration.result.RegistrationResult.covariance`.
    T_model_curr : array_like, shape (4, 4)

    Returns
    -------
    ndarray, shape (6, 6)
        The same error in the frame of ``T_model_curr``, in that convention.
    """
    C = np.asarray(T_model_curr, dtype=np.float64)
    Rt = C[:3, :3].T
    J = np.zeros((6, 6))
    J[:3, :3] = Rt
    J[:3, 3:] = -Rt @ hat(C[:3, 3])
    J[3:, 3:] = Rt
    cov = J @ np.asarray(cov_step, dtype=np.float64) @ J.T
    return np.asarray(0.5 * (cov + cov.T), dtype=np.float64)


def twist_covariance(
    cov_step: ArrayLike,
    T_prev_curr: ArrayLike,
    dt: float,
    T_frame_lidar: ArrayLike | None = None,
) -> FloatArray:
    """Covariance of the twist of one step, to first order.

    The twist of the motion ``M = A T_prev_curr A^-1`` of the frame ``A = T_frame_lidar`` (a
    robot's base carrying the sensor; the sensor itself by default) over ``dt`` seconds is
    ``v = R_M^T t_M / dt`` (in the frame's current pose, a nav_msgs/Odometry twist's
    ``child_frame_id``) and ``w = log(R_M) / dt``.

    Parameters
    ----------
    cov_step : array_like, shape (6, 6)
        Covariance of ``T_prev_curr`` for the left perturbation ``T_true = exp(delta) T`` in
        the previous frame, (x, y, z, rot_x, rot_y, rot_z):
        :attr:`~kentreg_ros.core.registration.result.RegistrationResult.covariance` of the
        step's registration, whose target is the previous pose's frame.
    T_prev_curr : array_like, shape (4, 4)
        The sensor's motion: its current pose in its previous one.
    dt : float
        The time the motion took (s), > 0.
    T_frame_lidar : array_like, shape (4, 4), optional
        The sensor's pose in the frame whose twist is wanted (default identity).

    Returns
    -------
    ndarray, shape (6, 6)
        Covariance of ``(v_x, v_y, v_z, w_x, w_y, w_z)`` in (m/s, rad/s).

    Notes
    -----
    The step's perturbation moves the frame's motion by ``Ad_A delta``:
    ``v_M = R_A v + [t_A]x R_A w`` and ``w_M = R_A w`` (a rotation of the sensor moves a frame
    mounted ``t_A`` away). Then ``R_M^T t_M`` moves by ``R_M^T v_M`` exactly, and
    ``log(R_M)`` by ``J_l^-1(log R_M) w_M``, the inverse left Jacobian of SO(3).
    """
    A = np.eye(4) if T_frame_lidar is None else np.asarray(T_frame_lidar, dtype=np.float64)
    T = np.asarray(T_prev_curr, dtype=np.float64)
    M = A @ T @ np.linalg.inv(A)
    R_A, R_M = A[:3, :3], M[:3, :3]
    J = np.zeros((6, 6))
    J[:3, :3] = R_M.T @ R_A
    J[:3, 3:] = R_M.T @ hat(A[:3, 3]) @ R_A
    J[3:, 3:] = _inverse_left_jacobian(log_so3(R_M)) @ R_A
    J /= dt
    cov = J @ np.asarray(cov_step, dtype=np.float64) @ J.T
    return np.asarray(0.5 * (cov + cov.T), dtype=np.float64)


def _inverse_left_jacobian(phi: FloatArray) -> FloatArray:
    """``J_l^-1(phi)`` of SO(3): ``log(exp(w) exp(phi)) = phi + J_l^-1(phi) w + O(|w|^2)``."""
    theta = float(np.linalg.norm(phi))
    K = hat(phi)
    if theta < 1e-6:
        return np.eye(3) - 0.5 * K + K @ K / 12.0
    c = 1.0 / theta**2 - (1.0 + np.cos(theta)) / (2.0 * theta * np.sin(theta))
    return np.eye(3) - 0.5 * K + c * (K @ K)
