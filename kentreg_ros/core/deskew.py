"""Motion compensation (deskewing) of a spinning LiDAR's sweep.

A spinning LiDAR takes its points over one sweep while it moves; each point is in the sensor
frame of its own acquisition time. With the sensor's motion during the sweep modelled as a
constant twist ``xi = (omega, v)`` (rad/s and m/s, in the sensor frame: a constant velocity in
the sensor's own frame, as a vehicle or a walker moving forward while turning has), the sensor
pose at time ``tau`` after the scan's reference time (its stamp) is the SE(3) exponential
``exp(tau xi) = (R, t)`` with ``R = exp(tau hat(omega))`` and ``t = V(tau omega) tau v``, and a
point ``p`` measured at ``tau`` is, in the reference frame::

    p' = R p + t

``V(w) = I + (1 - cos|w|) / |w|^2 hat(w) + (|w| - sin|w|) / |w|^3 hat(w)^2`` bends the path
into the arc a turning sensor follows; a straight path (``t = tau v``) would misplace the
points at the end of a 0.1 s sweep by ``tau^2 |omega| |v| / 2``: 2.6 mm at 1 m/s and 30 deg/s,
4 cm for a car at 15 m/s.

Per-point times come in several units and references (Velodyne ``time``: seconds from the
sweep start; Ouster ``t`` and Livox ``offset_time``: nanoseconds from it; Hesai and Robosense
``timestamp``: absolute seconds). :func:`relative_point_times` turns them into seconds from the
scan's stamp.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core.errors import InvalidPointCloudError
from kentreg_ros.core.rotations import log_so3

FloatArray = NDArray[np.float64]

#: Values above this are absolute times (seconds since 1970 are ~1.7e9, nanoseconds ~1.7e18);
#: relative times within a sweep of at most a few seconds stay far below it in any unit up to
#: microseconds, and Ouster/Livox relative nanoseconds stay below 1e9 for sweeps under 1 s.
ABSOLUTE_TIME_MIN = 1.0e8
#: The longest sweep the unit rule assumes (s): spinning LiDARs turn at 5-20 Hz, and a 0.5 Hz
#: scanner's sweep is 2 s. A relative time field spanning at most this is in seconds, at most
#: 1e3 times it in milliseconds, 1e6 times it in microseconds, more in nanoseconds.
MAX_SWEEP_S = 2.0


def relative_point_times(values: ArrayLike, stamp_ns: int) -> FloatArray:
    """Per-point times in seconds relative to the scan stamp, from a driver's time field.

    Absolute times (any value above :data:`ABSOLUTE_TIME_MIN`) are read as nanoseconds when
    above 1e15 and as seconds otherwise, and the stamp is subtracted. Relative times keep their
    zero (the driver's: usually the sweep start, which most drivers also stamp) and their unit
    is the one that makes their span a plausible sweep (:data:`MAX_SWEEP_S`).

    Raises
    ------
    InvalidPointCloudError
        Non-finite times.
    """
    t = np.asarray(values, dtype=np.float64).ravel()
    if len(t) == 0:
        return t
    if not np.isfinite(t).all():
        raise InvalidPointCloudError('The per-point time field has NaN or inf values.')
    top = float(np.max(np.abs(t)))
    if top > ABSOLUTE_TIME_MIN:
        if top > 1e15:  # absolute nanoseconds: subtract in integers-as-floats carefully
            return (t - float(stamp_ns)) * 1e-9
        return t - stamp_ns * 1e-9
    span = float(t.max() - t.min())
    # Relative values stay below ABSOLUTE_TIME_MIN, so as nanoseconds they always fit a sweep.
    for scale in (1.0, 1e-3, 1e-6):
        if span * scale <= MAX_SWEEP_S:
            return t * scale
    return t * 1e-9


def _arc_coefficients(theta: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``sin(t) / t``, ``(1 - cos t) / t^2`` and ``(t - sin t) / t^3`` (series near 0)."""
    small = theta < 1e-4
    safe = np.where(small, 1.0, theta)
    t2 = theta**2
    a = np.where(small, 1.0 - t2 / 6.0, np.sin(theta) / safe)
    b = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(theta)) / safe**2)
    c = np.where(small, 1.0 / 6.0 - t2 / 120.0, (theta - np.sin(theta)) / safe**3)
    return a, b, c


def twist_of(T_prev_curr: FloatArray, dt: float) -> FloatArray:
    """Constant twist ``(omega, v)`` (per second, frame of the earlier scan) that moves the
    sensor by ``T_prev_curr`` in ``dt`` seconds: the SE(3) logarithm over ``dt``, so that
    :func:`deskew` at ``tau = dt`` reproduces ``T_prev_curr`` exactly."""
    if not dt > 0.0:
        return np.zeros(6)
    w = log_so3(T_prev_curr[:3, :3])
    theta = np.array([np.linalg.norm(w)])
    a, b, _ = (float(x[0]) for x in _arc_coefficients(theta))
    t = np.asarray(T_prev_curr[:3, 3], dtype=np.float64)
    # V(w)^-1 t = t - hat(w) t / 2 + (1 - a / (2 b)) / theta^2 hat(w)^2 t
    th2 = float(theta[0]) ** 2
    d = (1.0 - a / (2.0 * b)) / th2 if th2 > 1e-8 else 1.0 / 12.0 + th2 / 720.0
    wxt = np.cross(w, t)
    u = t - 0.5 * wxt + d * np.cross(w, wxt)
    return np.concatenate([w, u]) / dt


def deskew(points: FloatArray, times_s: FloatArray, twist: FloatArray) -> FloatArray:
    """Points moved from their acquisition times to the reference time (see module docstring).

    Parameters
    ----------
    points : ndarray, shape (N, 3)
    times_s : ndarray, shape (N,)
        Seconds from the reference time (negative before it).
    twist : ndarray, shape (6,)
        ``(omega, v)``: the sensor's angular (rad/s) and linear (m/s) velocity in its frame.

    Returns
    -------
    ndarray, shape (N, 3)
    """
    omega, v = np.asarray(twist[:3], dtype=np.float64), np.asarray(twist[3:], dtype=np.float64)
    if not (np.any(omega) or np.any(v)):
        return np.array(points, dtype=np.float64)
    w = times_s[:, None] * omega[None, :]  # rotation vector of each point
    a, b, c = _arc_coefficients(np.linalg.norm(w, axis=1))
    cross = np.cross(w, points)
    rotated = points + a[:, None] * cross + b[:, None] * np.cross(w, cross)  # Rodrigues
    u = times_s[:, None] * v[None, :]
    wxu = np.cross(w, u)
    out: FloatArray = rotated + u + b[:, None] * wxu + c[:, None] * np.cross(w, wxu)
    return out
