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

This module is the one home of deskewing in the odometry, in the order a step meets it:

================== ==========================================================================
:func:`read_sweep` the points and their seconds from the stamp (a :class:`Sweep`)
:func:`prepare_sweep` the sweep deskewed with a twist, then prepared (the prepare stage's work)
:class:`Deskewer`  after the registration: deskew again with the registered motion and
                   register again, while that matters; the model's first scan, prepared before
                   any motion was known, is deskewed again here too (and handed to the model
                   stage, which takes it with the step's scan: the model never changes mid-step)
================== ==========================================================================
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.errors import InvalidPointCloudError, KentRegError
from kentreg_ros.core.geometry import log_so3, row_norms
from kentreg_ros.core.odometry.verify import Outcome, Verifier
from kentreg_ros.core.odometry_config import Deskew, TimeReference, TimeUnit
from kentreg_ros.core.registration import register
from kentreg_ros.core.scan import PreparedScan, prepare_scan
from kentreg_ros.core.scan.voxels import as_points

if TYPE_CHECKING:  # models imports this module
    from kentreg_ros.core.odometry.models import FirstAgain, ModelStrategy

FloatArray = NDArray[np.float64]


#: Seconds per unit.
UNIT_SECONDS = {TimeUnit.S: 1.0, TimeUnit.MS: 1e-3, TimeUnit.US: 1e-6, TimeUnit.NS: 1e-9}

#: The longest sweep a per-point time field may describe (s): spinning LiDARs turn at 5-20 Hz,
#: a 0.5 Hz scanner's sweep is 2 s. Read in the right unit, every point of a sweep lies within
#: this of the scan's stamp; times spanning more are not a sweep (a wrong unit, or garbage).
MAX_SWEEP_S = 2.0
#: Fewest points with a finite time a deskewed scan keeps (points without one are dropped):
#: below this the scan cannot be prepared anyway (the neighbourhood of the normals needs more).
MIN_TIMED_POINTS = 20
#: Deskew once more with the registered motion when it moves the sweep's points by more than
#: this many voxel edges from where the predicted motion put them: below half a voxel the
#: difference is under the sampling resolution of the scan (a smaller change is still acted
#: on when it would bias the registered pose by more than its resolution, see _resolvable).
DESKEW_ITERATE_SPACINGS = 0.5
#: Most deskew-and-register rounds per scan. A registration of a sweep deskewed with a twist
#: off by d lands off by about d x (sweep / 2) and so re-estimates the twist off by about
#: d x sweep / (2 gap), at most d / 2 (a sweep fills the gap between scans at most): three
#: rounds divide a sudden change of velocity at least by eight, by 1000 when the sweep lasts a
#: fifth of the gap.
MAX_DESKEW_ITERATIONS = 3


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


class ImplausibleTimesError(KentRegError, ValueError):
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


# ------------------------------------------------------------------------------------------------
# The sweep, and the scan prepared from it


@dataclass(frozen=True, eq=False)
class Sweep:
    """A scan's points and, when it is to be deskewed, their times.

    Attributes
    ----------
    points : ndarray, shape (N, 3)
        Finite points (those without a finite time dropped when ``times`` is given).
    times : ndarray, shape (N,) or None
        Seconds from the stamp; None: not deskewed.
    n_untimed : int
        Points dropped because their time was not finite.
    warning : str
        Why the times were not used ('' when they were, or there were none), to be logged once
        per ``warning_kind`` in a trajectory.
    """

    points: FloatArray
    times: FloatArray | None = None
    n_untimed: int = 0
    warning: str = ''
    warning_kind: str = ''


def read_sweep(
    points: ArrayLike,
    point_times: ArrayLike | PointTimes | None,
    stamp: int,
    config: KentRegConfig,
) -> Sweep:
    """The points and their seconds from the stamp, when the scan is to be deskewed.

    Raises
    ------
    InvalidPointCloudError
        Malformed points, times not one per point, or too few points with a finite time.
    """
    pts = as_points(points)
    odo = config.odometry
    if odo.deskew == Deskew.OFF or point_times is None:
        warning = ''
        if odo.deskew == Deskew.ON and point_times is None:
            warning = 'odometry.deskew is on but the scans carry no per-point times.'
        return Sweep(pts, warning=warning, warning_kind='no_times')
    field = point_times.field if isinstance(point_times, PointTimes) else ''
    values = np.asarray(point_times)
    if values.ndim != 1 or len(values) != len(pts):
        raise InvalidPointCloudError(
            f'Expected one time per point ({len(pts)}), got shape {values.shape}.'
        )
    try:
        found = sweep_times(
            values,
            stamp,
            field=field,
            unit=odo.point_time_unit,
            reference=odo.point_time_reference,
        )
    except ImplausibleTimesError as exc:
        return Sweep(
            pts,
            warning=f'Not deskewing: {exc}. Set odometry.point_time_unit and '
            'odometry.point_time_reference if the driver uses another convention.',
            warning_kind='implausible_times',
        )
    times = found.seconds
    timed = np.isfinite(times)
    n_untimed = int(np.count_nonzero(~timed))
    if n_untimed:
        rows = np.flatnonzero(timed)  # take(): boolean indexing's rows, ~4x faster on (N, 3)
        pts, times = pts.take(rows, axis=0), times.take(rows)
        if len(times) < MIN_TIMED_POINTS:
            raise InvalidPointCloudError(
                f'only {len(times)} of {len(timed)} points have a finite time '
                f'(need {MIN_TIMED_POINTS}).'
            )
    return Sweep(pts, times if np.ptp(times) > 0.0 else None, n_untimed)


def prepare_sweep(
    sweep: Sweep, twist: FloatArray, config: KentRegConfig, voxel_size_hint: float
) -> PreparedScan:
    """The scan prepared from its sweep: deskewed with ``twist`` (when it has times), then
    cropped, downsampled, given normals and clusters (:func:`~kentreg_ros.core.scan.prepare_scan`).

    Raises
    ------
    InvalidPointCloudError
        Too few points survive the preprocessing.
    """
    points = sweep.points if sweep.times is None else deskew(sweep.points, sweep.times, twist)
    return prepare_scan(points, config=config, voxel_size_hint=voxel_size_hint)


# ------------------------------------------------------------------------------------------------
# Deskewing again with the registered motion


def _resolvable(change: FloatArray, span_s: float, outcome: Outcome) -> bool:
    """Whether deskewing a sweep of ``span_s`` seconds with a twist differing by ``change``
    would move its registered pose by more than the registration resolves: the pose lands
    about half the sweep's motion difference away (``change x span / 2``), compared with the
    resolution of the registration (Mahalanobis distance above 1): whether the fit's minimum
    moves, not whether the move is within the pose's error."""
    if outcome.result is None:
        return False
    bias = 0.5 * span_s * np.concatenate([change[3:], change[:3]])  # (x, y, z, roll, ...)
    result = outcome.result
    cov = np.asarray(
        result.covariance if result.resolution is None else result.resolution, dtype=np.float64
    )
    try:
        return bool(bias @ np.linalg.solve(cov, bias) > 1.0)
    except np.linalg.LinAlgError:
        return False


@dataclass(frozen=True, eq=False)
class Deskewed:
    """What :meth:`Deskewer.iterate` found: the step's scan (None: rejected) and outcome after
    the last round taken, and the model's first scan deskewed again, when it was (for the model
    stage to take with the step's scan)."""

    scan: PreparedScan | None
    outcome: Outcome
    first: FirstAgain | None = None


class Deskewer:
    """Deskews a sweep again with the motion just registered and registers it once more,
    while that moves the sweep's points by more than half a voxel from where the last deskewing
    put them or the registered pose by more than the registration resolves (the deskewing and
    the registration converge together: constant velocity within the sweep; at most
    :data:`MAX_DESKEW_ITERATIONS` rounds, each judged by :meth:`Verifier.judge_round`).

    The model's first scan was prepared before any motion was known, so not deskewed: while
    the model is that scan alone (:attr:`ModelStrategy.first_sweep`), the first round that
    deskews again deskews it too, with the same twist (its sweep moved like this one: constant
    velocity), and registers against the model made of it
    (:meth:`ModelStrategy.with_first`). The model itself is left as it is: the step hands that
    first scan to the model stage, which takes it before the step's own scan.
    """

    def __init__(self, config: KentRegConfig, verifier: Verifier) -> None:
        self.config = config
        self.verifier = verifier

    def iterate(
        self,
        sweep: Sweep,
        scan: PreparedScan,
        outcome: Outcome,
        used: FloatArray,
        model: ModelStrategy,
        gap_ns: int,
    ) -> Deskewed:
        """The scan deskewed with the registered motion and its outcome (``used``: the twist
        ``scan`` was deskewed with)."""
        assert sweep.times is not None and model.scan is not None
        span = float(np.ptp(sweep.times))
        reach = float(np.max(row_norms(scan.points))) if len(scan) else 0.0
        spacing = max(scan.voxel_size, 1e-9)
        target, first = model.scan, None
        for _ in range(MAX_DESKEW_ITERATIONS):
            twist = twist_of(outcome.T, gap_ns * 1e-9)
            change = twist - used
            shift = (np.linalg.norm(change[:3]) * reach + np.linalg.norm(change[3:])) * span
            if shift <= DESKEW_ITERATE_SPACINGS * spacing and not _resolvable(
                change, span, outcome
            ):
                break
            try:
                if first is None and model.first_sweep is not None:
                    again_first = prepare_sweep(
                        model.first_sweep, twist, self.config, model.scan.voxel_size
                    )
                    first = model.with_first(again_first)
                    target = first.target
                again = prepare_sweep(sweep, twist, self.config, scan.voxel_size)
                result = register(
                    again, target, init=outcome.T, config=self.config, global_search=False
                )
            except (KentRegError, np.linalg.LinAlgError):
                break
            judged = self.verifier.judge_round(result, outcome, gap_ns)
            if judged is None:
                break  # keep the last round: this one is no better, or breaks the limits
            scan, used, outcome = again, twist, judged
        return Deskewed(scan, outcome, first)
