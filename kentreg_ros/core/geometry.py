"""SO(3) and SE(3) helpers shared by every room of the core: exp/log maps, transforms."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core.errors import InvalidInputError

FloatArray = NDArray[np.float64]


def hat(w: ArrayLike) -> FloatArray:
    """Skew-symmetric matrix of a vector: ``hat(w) @ v == cross(w, v)``; shape (..., 3, 3)."""
    w = np.asarray(w, dtype=np.float64)
    out = np.zeros((*w.shape[:-1], 3, 3))
    out[..., 0, 1] = -w[..., 2]
    out[..., 0, 2] = w[..., 1]
    out[..., 1, 0] = w[..., 2]
    out[..., 1, 2] = -w[..., 0]
    out[..., 2, 0] = -w[..., 1]
    out[..., 2, 1] = w[..., 0]
    return out


def vee(m: FloatArray) -> FloatArray:
    """Inverse of :func:`hat` applied to the skew part of ``m``; shape (..., 3)."""
    return 0.5 * np.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]],
        axis=-1,
    )


def exp_so3(w: ArrayLike) -> FloatArray:
    """Rodrigues' formula: rotation matrix of the rotation vector ``w`` (radians)."""
    w = np.asarray(w, dtype=np.float64)
    theta = float(np.linalg.norm(w))
    k = hat(w)
    if theta < 1e-8:
        return np.eye(3) + k + 0.5 * k @ k
    return np.eye(3) + np.sin(theta) / theta * k + (1 - np.cos(theta)) / theta**2 * k @ k


def log_so3(R: FloatArray) -> FloatArray:
    """Rotation vector (radians) of a rotation matrix."""
    cos = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    theta = float(np.arccos(cos))
    if theta < 1e-8:
        return vee(R)
    if np.pi - theta < 1e-5:
        # Near pi: axis from the symmetric part.
        B = (R + np.eye(3)) / 2.0
        axis = np.sqrt(np.maximum(np.diag(B), 0.0))
        i = int(np.argmax(axis))
        axis = B[:, i] / max(axis[i], 1e-12)
        axis /= np.linalg.norm(axis)
        if np.dot(vee(R), axis) < 0:
            axis = -axis
        return axis * theta
    return vee(R) * (theta / np.sin(theta))


def rotation_angle(R: FloatArray) -> float:
    """Angle of a rotation matrix in radians (the geodesic distance to identity)."""
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def project_to_so3(M: ArrayLike) -> FloatArray:
    """Closest rotation (Frobenius) to a 3x3 matrix, or to each of a stack (..., 3, 3), by SVD."""
    A = np.asarray(M, dtype=np.float64)
    U, _, Vt = np.linalg.svd(A)
    d = np.where(np.linalg.det(U @ Vt) < 0.0, -1.0, 1.0)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    out: FloatArray = U @ Vt
    return out


#: Largest deviation of ``R^T R`` from the identity accepted in a transform given by a caller;
#: float32 poses composed of a few products are orthonormal to ~1e-6, so 1e-5 accepts them and
#: still refuses anything that is not a rotation (a scaled or sheared matrix is off by far more).
ORTHONORMAL_TOLERANCE = 1e-5
_EYE3 = np.eye(3)
_ORTHONORMAL_BOUND = ORTHONORMAL_TOLERANCE + 1e-5 * _EYE3  # np.allclose's default rtol
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])
_LAST_ROW_BOUND = 1e-8 + 1e-5 * _LAST_ROW  # np.allclose's default atol and rtol


def check_transform(T: ArrayLike, name: str) -> FloatArray:
    """Validate a rigid 4x4 transform given by a caller; returns it with an exact rotation.

    Raises
    ------
    InvalidInputError
        Not a finite 4x4 array, a rotation block that is not a rotation (to
        :data:`ORTHONORMAL_TOLERANCE`), or a last row other than ``[0, 0, 0, 1]``.
    """
    try:
        arr = np.array(T, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f'Expected `{name}` to be a numeric 4x4 array: {exc}') from exc
    if arr.shape != (4, 4) or not np.isfinite(arr).all():
        raise InvalidInputError(
            f'Expected `{name}` to be a finite 4x4 transform, got shape {arr.shape}.'
        )
    R = arr[:3, :3]
    # np.allclose's tests (|a - b| <= atol + rtol |b|, its default rtol) in one comparison each:
    # allclose takes ~7 us a call on a 3x3, and every step checks several transforms.
    if not (np.abs(R.T @ R - _EYE3) <= _ORTHONORMAL_BOUND).all() or np.linalg.det(R) < 0.0:
        raise InvalidInputError(f'Expected the rotation block of `{name}` to be a rotation.')
    if not (np.abs(arr[3] - _LAST_ROW) <= _LAST_ROW_BOUND).all():
        raise InvalidInputError(
            f'Expected the last row of `{name}` to be [0, 0, 0, 1], got {arr[3]}.'
        )
    arr[:3, :3] = project_to_so3(R)
    return arr


def invert_transform(T: FloatArray) -> FloatArray:
    """Inverse of a rigid 4x4 transform (``R^T``, ``-R^T t``)."""
    R = T[:3, :3]
    return make_transform(R.T, -R.T @ T[:3, 3])


def row_norms(a: FloatArray) -> FloatArray:
    """Euclidean norm of each row of an (N, 3) array: ``np.linalg.norm(a, axis=1)``, bit for
    bit (the same squares summed in the same order, ``(x x + y y) + z z``), ~4x faster (numpy
    reduces a length-3 row slowly)."""
    x, y, z = a[:, 0], a[:, 1], a[:, 2]
    out: FloatArray = np.sqrt((x * x + y * y) + z * z)
    return out


def cross_rows(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise cross product of (N, 3) arrays; a few times faster than ``np.cross``."""
    out = np.empty_like(a)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def make_transform(R: FloatArray, t: ArrayLike) -> FloatArray:
    """4x4 homogeneous transform from a rotation and a translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64)
    return T
