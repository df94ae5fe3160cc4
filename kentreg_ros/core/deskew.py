"""Motion compensation (deskewing) of a spinning LiDAR's sweep.

A spinning LiDAR takes its points over one sweep while it moves; each point is in the sensor
frame of its own acquisition time. With the sensor's motion during the sweep modelled as a
constant twist ``xi = (omega, v)`` (rad/s and m/s, in the sensor frame), the sensor pose at
time ``tau`` after the scan's reference time (its stamp) is ``exp(tau xi)``, and a point ``p``
measured at ``tau`` is, in the reference frame::

    p' = exp(tau hat(omega)) p + tau v

(the first-order screw: rotation and translation each proportional to ``tau``, exact for a
constant velocity of the sensor origin in its own frame to within ``tau^2 |omega| |v| / 2``,
below a millimetre for 1 m/s and 30 deg/s over 0.1 s).

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


def twist_of(T_prev_curr: FloatArray, dt: float) -> FloatArray:
    """Constant twist ``(omega, v)`` (per second, frame of the earlier scan) that moves the
    sensor by ``T_prev_curr`` in ``dt`` seconds, first-order: ``log(R) / dt, t / dt``."""
    if not dt > 0.0:
        return np.zeros(6)
    return np.concatenate([log_so3(T_prev_curr[:3, :3]), T_prev_curr[:3, 3]]) / dt


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
    theta = np.linalg.norm(w, axis=1)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(theta) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(theta)) / safe**2)
    cross = np.cross(w, points)
    rotated = points + a[:, None] * cross + b[:, None] * np.cross(w, cross)  # Rodrigues
    out: FloatArray = rotated + times_s[:, None] * v[None, :]
    return out
