"""Poses, stamps and covariances to and from ROS 2 messages (rclpy message classes).

The node and the player used to fill these fields by hand; each conversion now has one home.

=============================== ==================================================
``pose_to_msg`` / ``pose_from_msg``             4x4 ``T_parent_child`` <-> geometry_msgs/Pose
``transform_to_msg`` / ``transform_from_msg``   4x4 ``T_parent_child`` <-> geometry_msgs/Transform
``stamp_to_msg`` / ``stamp_from_msg``           integer nanoseconds <-> builtin_interfaces/Time
``covariance_to_msg`` / ``covariance_from_msg`` 6x6 <-> the 36 floats of a ``*WithCovariance``
``pose_covariance_in_base``                     a pose covariance carried to the published frame
``pose_covariance_in_map``                      a localization's covariance as one in the map
=============================== ==================================================

Quaternions are ``(x, y, z, w)`` as in geometry_msgs/Quaternion (and scipy's ``as_quat``). A
covariance in nav_msgs is row-major over ``(x, y, z, rotation about X, rotation about Y,
rotation about Z)``, the order of :attr:`kentreg_ros.core.RegistrationResult.covariance`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Pose, Transform
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from kentreg_ros.core import InvalidInputError, check_transform, hat
from kentreg_ros.io.pointcloud2 import ns_to_sec_nanosec

__all__ = [
    'covariance_from_msg',
    'covariance_to_msg',
    'pose_from_msg',
    'pose_to_msg',
    'stamp_from_msg',
    'stamp_to_msg',
    'transform_from_msg',
    'transform_to_msg',
]

FloatArray = NDArray[np.float64]
_NS_PER_S = 1_000_000_000


def _matrix(translation: Sequence[float], quaternion_xyzw: Sequence[float]) -> FloatArray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(quaternion_xyzw).as_matrix()
    T[:3, 3] = translation
    return T


def _parts(T: ArrayLike, name: str) -> tuple[list[float], list[float]]:
    M = check_transform(T, name)
    q = Rotation.from_matrix(M[:3, :3]).as_quat()  # x, y, z, w
    return [float(v) for v in M[:3, 3]], [float(v) for v in q]


def pose_to_msg(T_parent_child: ArrayLike) -> Pose:
    """geometry_msgs/Pose of a rigid transform.

    Parameters
    ----------
    T_parent_child : array_like, shape (4, 4)
        The child frame's pose in the parent frame.

    Raises
    ------
    InvalidInputError
        ``T_parent_child`` is not a finite rigid 4x4 transform.
    """
    (x, y, z), (qx, qy, qz, qw) = _parts(T_parent_child, 'T_parent_child')
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = x, y, z
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = qx, qy, qz, qw
    return pose


def pose_from_msg(pose: Pose) -> FloatArray:
    """The 4x4 transform of a geometry_msgs/Pose (its quaternion normalised)."""
    p, q = pose.position, pose.orientation
    return _matrix([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])


def transform_to_msg(T_parent_child: ArrayLike) -> Transform:
    """geometry_msgs/Transform of a rigid transform (see :func:`pose_to_msg`)."""
    (x, y, z), (qx, qy, qz, qw) = _parts(T_parent_child, 'T_parent_child')
    tf = Transform()
    tf.translation.x, tf.translation.y, tf.translation.z = x, y, z
    tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = qx, qy, qz, qw
    return tf


def transform_from_msg(transform: Transform) -> FloatArray:
    """The 4x4 transform of a geometry_msgs/Transform (its quaternion normalised)."""
    t, q = transform.translation, transform.rotation
    return _matrix([t.x, t.y, t.z], [q.x, q.y, q.z, q.w])


def stamp_to_msg(stamp_ns: int) -> Time:
    """builtin_interfaces/Time of a stamp in integer nanoseconds (exact, no float rounding).

    Raises
    ------
    ValueError
        A negative stamp (Time holds non-negative times only).
    """
    sec, nanosec = ns_to_sec_nanosec(stamp_ns)
    return Time(sec=sec, nanosec=nanosec)


def stamp_from_msg(stamp: Time) -> int:
    """Integer nanoseconds of a builtin_interfaces/Time."""
    return int(stamp.sec) * _NS_PER_S + int(stamp.nanosec)


def covariance_to_msg(covariance: ArrayLike) -> list[float]:
    """The 36 row-major floats of a ``PoseWithCovariance``/``TwistWithCovariance`` covariance.

    Parameters
    ----------
    covariance : array_like, shape (6, 6)
        In the order (x, y, z, rotation about X, Y, Z).

    Raises
    ------
    InvalidInputError
        Not a 6x6 array.
    """
    C = np.asarray(covariance, dtype=float)
    if C.shape != (6, 6):
        raise InvalidInputError(f'Expected `covariance` to have shape (6, 6), got {C.shape}.')
    return [float(v) for v in C.ravel()]


def covariance_from_msg(values: Sequence[float]) -> FloatArray:
    """The 6x6 covariance of a message's 36 row-major floats (see :func:`covariance_to_msg`).

    Raises
    ------
    InvalidInputError
        Not 36 values.
    """
    flat = np.asarray(values, dtype=float)
    if flat.shape != (36,):
        raise InvalidInputError(f'Expected 36 covariance values, got shape {flat.shape}.')
    return flat.reshape(6, 6).copy()


def transform_from_xyzrpy(values: Sequence[float]) -> FloatArray:
    """4x4 transform of ``[x, y, z, roll, pitch, yaw]`` (m, rad; fixed-axis x-y-z Euler angles,
    the convention of ROS's RPY)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler('xyz', values[3:6]).as_matrix()
    T[:3, 3] = values[:3]
    return T


def pose_covariance_in_base(
    cov_world_lidar: FloatArray,
    T_base_lidar: FloatArray,
    T_odom_base: FloatArray,
    T_odom_world: FloatArray | None = None,
) -> FloatArray:
    """Covariance of ``T_odom_base = T_odom_world T_world_lidar T_bl^-1`` from that of
    ``T_world_lidar`` (``T_odom_world`` defaults to ``T_bl``: odom is the base at the start).

    Both in the nav_msgs order (x, y, z, rot_x, rot_y, rot_z): position error and rotation
    error about the fixed frame's axes. With ``A = T_odom_world``,
    ``p_ob = R_A (R_wl t_lb + t_wl) + t_A`` (``t_lb`` the base origin in the lidar frame) and
    ``dtheta_ob = R_A dtheta_wl``, the Jacobian is ``[[R_A, [R_ob t_bl]x R_A], [0, R_A]]``.
    """
    A = T_base_lidar if T_odom_world is None else T_odom_world
    R_A = A[:3, :3]
    J = np.zeros((6, 6))
    J[:3, :3] = R_A
    J[3:, 3:] = R_A
    J[:3, 3:] = hat(T_odom_base[:3, :3] @ T_base_lidar[:3, 3]) @ R_A
    return J @ cov_world_lidar @ J.T


def pose_covariance_in_map(cov: FloatArray, T_map_scan: FloatArray) -> FloatArray:
    """The covariance of a localization's ``T_map_scan`` as a pose covariance in the map.

    The localization's (a registration's against the map,
    :attr:`~kentreg_ros.core.RegistrationResult.covariance`) is of the left perturbation
    ``T_true = exp(delta) T`` in the map frame, ``delta = (t_true - dR t, log dR)``; a
    nav_msgs pose covariance is of the position error ``t_true - t`` and ``log dR``. To first
    order ``t_true - t = delta_t - [t]x delta_R``, so ``J = [[I, -[t]x], [0, I]]``: the
    rotation's uncertainty moves a pose far from the map's origin.
    """
    J = np.eye(6)
    J[:3, 3:] = -hat(T_map_scan[:3, 3])
    out = J @ cov @ J.T
    return np.asarray(0.5 * (out + out.T), dtype=np.float64)
