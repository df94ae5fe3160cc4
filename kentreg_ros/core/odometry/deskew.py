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

Per-point times come in several units and references (Velodyne ``time``: float32 seconds from
the sweep start; Ouster ``t`` and Livox ``offset_time``: uint32 nanoseconds from it; Hesai and
Robosense ``timestamp``: float64 absolute seconds; livox_ros_driver2's ``timestamp``: float64
absolute nanoseconds, told from seconds by its magnitude). :func:`sweep_times` turns them into
seconds from the scan's stamp: from what the message says first (the field's name and
datatype, see :data:`DRIVER_TIME_FIELDS`), then from the values, and a stated unit and reference
(``odometry.point_time_unit`` / ``odometry.point_time_reference``) overrides both. Times that do
not describe a plausible sweep around the stamp are not used: a wrong deskew throws points far
off, which is worse than none.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core.config import TimeReference, TimeUnit
from kentreg_ros.core.geometry import log_so3, row_norms

FloatArray = NDArray[np.float64]


#: Seconds per unit.
UNIT_SECONDS = {TimeUnit.S: 1.0, TimeUnit.MS: 1e-3, TimeUnit.US: 1e-6, TimeUnit.NS: 1e-9}

#: The longest sweep a per-point time field may describe (s): spinning LiDARs turn at 5-20 Hz,
#: a 0.5 Hz scanner's sweep is 2 s. Read in the right unit, every point of a sweep lies within
#: this of the scan's stamp; times spanning more are not a sweep (a wrong unit, or garbage).
MAX_SWEEP_S = 2.0


@dataclass(frozen=True)
class DriverTimeField:
    """What a driver's per-point time field means (``unit`` None: read it off the values)."""

    unit: TimeUnit | None
    reference: TimeReference
    driver: str


#: Per-point time fields of common drivers, by name and numpy datatype code.
DRIVER_TIME_FIELDS: dict[tuple[str, str], DriverTimeField] = {
    ('t', 'u4'): DriverTimeField(TimeUnit.NS, TimeReference.RELATIVE, 'Ouster'),
    ('offset_time', 'u4'): DriverTimeField(TimeUnit.NS, TimeReference.RELATIVE, 'Livox'),
    ('time', 'f4'): DriverTimeField(TimeUnit.S, TimeReference.RELATIVE, 'Velodyne'),
    ('time', 'f8'): DriverTimeField(TimeUnit.S, TimeReference.RELATIVE, 'Velodyne-style'),
    # float64 absolute: seconds (Hesai, Robosense) or nanoseconds (livox_ros_driver2, its
    # PointCloud2); the unit that puts them within a sweep of the stamp tells them apart: the
    # readings are 1e9 apart (1.7e9 s against 1.7e18 ns; on a sensor's clock counting from
    # its boot, 1e3 s against 1e12 ns), and a sweep is at most MAX_SWEEP_S.
    ('timestamp', 'f8'): DriverTimeField(
        None, TimeReference.ABSOLUTE, 'Hesai/Robosense s or livox_ros_driver2 ns'
    ),
    ('timestamp', 'u8'): DriverTimeField(TimeUnit.NS, TimeReference.ABSOLUTE, 'absolute ns'),
}


@dataclass(frozen=True, eq=False)
class PointTimes:
    """A per-point time field as a message carried it: its values (in their own datatype,
    which is part of what they say) and the field's name ('' when unknown). Behaves as the
    array of its values (``np.asarray``)."""

    values: NDArray[Any]
    field: str = ''

    def __len__(self) -> int:
        return len(self.values)

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> NDArray[Any]:
        return np.asarray(self.values, dtype=dtype)


@dataclass(frozen=True)
class SweepTimes:
    """Per-point times in seconds from the scan's stamp, and how they were read.

    Attributes
    ----------
    seconds : ndarray, shape (N,)
        NaN where the field's value is not finite.
    unit, reference : str
        The unit and reference used.
    source : str
        How they were decided, for messages (``"field 't' (uint32, Ouster)"``, ``'stated'``,
        ``'values'``).
    """

    seconds: FloatArray
    unit: TimeUnit
    reference: TimeReference
    source: str

    @property
    def span(self) -> float:
        """Seconds between the first and the last finite time (0 without any)."""
        finite = self.seconds[np.isfinite(self.seconds)]
        return float(np.ptp(finite)) if len(finite) else 0.0


class ImplausibleTimesError(ValueError):
    """A time field that does not describe a sweep around the stamp in the unit and reference
    given or found; its message says what was tried."""


def _plausible(seconds: FloatArray) -> bool:
    return bool(len(seconds) == 0 or np.max(np.abs(seconds)) <= MAX_SWEEP_S)


def _convert(
    values: FloatArray, stamp_ns: int, unit: TimeUnit, reference: TimeReference
) -> FloatArray:
    scale = UNIT_SECONDS[unit]
    if reference is TimeReference.RELATIVE:
        return values * scale
    if unit is TimeUnit.NS:  # integral nanoseconds: subtract before scaling (float64 holds
        return (values - float(stamp_ns)) * 1e-9  # 1.7e18 to ~256 ns, the stamp exactly)
    return values * scale - stamp_ns * 1e-9


def sweep_times(
    values: ArrayLike,
    stamp_ns: int,
    *,
    field: str = '',
    unit: TimeUnit | str = TimeUnit.AUTO,
    reference: TimeReference | str = TimeReference.AUTO,
) -> SweepTimes:
    """Per-point times in seconds from the scan stamp, from a driver's time field.

    The unit and reference are, in this order of precedence: the ones stated (``unit``,
    ``reference``), the driver's for a known field name and datatype
    (:data:`DRIVER_TIME_FIELDS`), and those that make the values a plausible sweep around the
    stamp: read as absolute times in the first unit (s, ms, us, ns) that puts every point within
    :data:`MAX_SWEEP_S` of the stamp, otherwise as relative times in the coarsest unit whose
    span is a plausible sweep. A relative field is preferred when both readings are plausible
    (stamps near zero, as in simulation), since drivers publish relative fields far more often.

    Parameters
    ----------
    values : array_like, shape (N,)
        The field as the message carried it (its datatype is part of what it says).
    stamp_ns : int
        The scan's stamp, integer nanoseconds.
    field : str
        The field's name in the message ('' when unknown).

    Returns
    -------
    SweepTimes
        ``seconds`` is NaN where a value is not finite.

    Raises
    ------
    ImplausibleTimesError
        The times are no sweep around the stamp in any reading allowed (wrong stated unit,
        garbage, a span longer than :data:`MAX_SWEEP_S`): deskewing must be skipped.
    """
    raw = np.asarray(values)
    t = raw.astype(np.float64).ravel()
    unit = TimeUnit(unit)
    reference = TimeReference(reference)
    finite = np.isfinite(t)
    tf = t[finite]
    known = DRIVER_TIME_FIELDS.get((field, raw.dtype.str[1:])) if field else None
    source = 'stated'
    if known is not None and (unit is TimeUnit.AUTO or reference is TimeReference.AUTO):
        source = f'field {field!r} ({raw.dtype.name}, {known.driver})'
        if unit is TimeUnit.AUTO and known.unit is not None:
            unit = known.unit
        if reference is TimeReference.AUTO:
            reference = known.reference
    elif unit is TimeUnit.AUTO or reference is TimeReference.AUTO:
        source = 'values'
    units = list(UNIT_SECONDS) if unit is TimeUnit.AUTO else [unit]
    refs = (
        [TimeReference.RELATIVE, TimeReference.ABSOLUTE]
        if reference is TimeReference.AUTO
        else [reference]
    )
    if not len(tf):
        raise ImplausibleTimesError('the per-point time field has no finite value')
    span = float(np.ptp(tf))
    readings: list[tuple[TimeUnit, TimeReference]] = []
    for ref in refs:
        for u in units:
            if ref is TimeReference.RELATIVE and span * UNIT_SECONDS[u] > MAX_SWEEP_S:
                continue
            if _plausible(_convert(tf, stamp_ns, u, ref)):
                readings.append((u, ref))
                break  # the coarsest plausible unit for this reference
    if not readings:
        tried = ', '.join(f'{r.value} {u.value}' for r in refs for u in units)
        raise ImplausibleTimesError(
            f'the per-point times ({source}: {len(tf)} finite values from {tf.min():.6g} to '
            f'{tf.max():.6g}) are no sweep of at most {MAX_SWEEP_S} s around the stamp '
            f'{stamp_ns} ns as any of: {tried}'
        )
    u, ref = readings[0]
    if known is not None and known.unit is None and unit is TimeUnit.AUTO:
        source = f'{source[:-1]}: {u.value} by the values)'
    out = np.full(len(t), np.nan)
    if u is TimeUnit.NS and ref is TimeReference.ABSOLUTE and raw.dtype.kind in 'iu':
        # Integer absolute ns (1.7e18) lose up to 128 ns as float64: subtract them exactly.
        out[:] = (raw.ravel().astype(np.int64) - np.int64(stamp_ns)) * 1e-9
    else:
        out[finite] = _convert(tf, stamp_ns, u, ref)
    return SweepTimes(out, u, ref, source)


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
    a, b, c = _arc_coefficients(row_norms(w))
    cross = np.cross(w, points)
    rotated = points + a[:, None] * cross + b[:, None] * np.cross(w, cross)  # Rodrigues
    u = times_s[:, None] * v[None, :]
    wxu = np.cross(w, u)
    out: FloatArray = rotated + u + b[:, None] * wxu + c[:, None] * np.cross(w, wxu)
    return out
