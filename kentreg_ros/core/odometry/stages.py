"""The stages of the odometry loop, each with one job and explicit inputs and outputs.

============ ===============================================================================
predict      :func:`predict`: the last pose moved by the last accepted motion (``Motion``)
deskew       :func:`read_sweep` (the times of the points) and, inside :func:`prepare`, the
             points moved to the stamp with the predicted twist; :class:`Deskewer` iterates it
             with the registration
prepare      :func:`prepare`: the scan once (crop, voxels, normals, clusters); a pure function
             of its inputs, so it can run on another core
register     :func:`~kentreg_ros.core.registration.register`, from the prediction
verify       :class:`Verifier`: doubt, the start-free search and the choice between the
             candidate poses (the only place a pose is chosen)
model        :mod:`~kentreg_ros.core.odometry.models` (the previous scan | a local map): the
             only thing that moves the model the next scan is registered against
============ ===============================================================================
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core.config import Deskew, KentRegConfig, Mode, SearchMode
from kentreg_ros.core.errors import InvalidPointCloudError, KentRegError
from kentreg_ros.core.geometry import (
    exp_so3,
    log_so3,
    make_transform,
    rotation_angle,
    row_norms,
)
from kentreg_ros.core.odometry.deskew import (
    ImplausibleTimesError,
    PointTimes,
    deskew,
    sweep_times,
    twist_of,
)
from kentreg_ros.core.odometry.step import Health
from kentreg_ros.core.registration import RegistrationResult, Status, register
from kentreg_ros.core.registration.verify import Candidate, FitGates, choose_pose
from kentreg_ros.core.scan import PreparedScan, prepare_scan
from kentreg_ros.core.scan.voxels import as_points

if TYPE_CHECKING:  # models imports this module
    from kentreg_ros.core.odometry.models import ModelStrategy

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: Largest factor by which the last motion is stretched when the scan gap grows (dropped scans).
MAX_VELOCITY_SCALE = 5.0
#: Fewest points with a finite time a deskewed scan keeps (points without one are dropped):
#: below this the scan cannot be prepared anyway (the neighbourhood of the normals needs more).
MIN_TIMED_POINTS = 20
#: Deskew once more with the registered motion when it moves the sweep's points by more than
#: this many voxel edges from where the predicted motion put them: below half a voxel the
#: difference is under the sampling resolution of the scan (a smaller change is still acted
#: on when it would bias the registered pose by more than its covariance, see _resolvable).
DESKEW_ITERATE_SPACINGS = 0.5
#: Most deskew-and-register rounds per scan. A registration of a sweep deskewed with a twist
#: off by d lands off by about d x (sweep / 2) and so re-estimates the twist off by about
#: d x sweep / (2 gap), at most d / 2 (a sweep fills the gap between scans at most): three
#: rounds divide a sudden change of velocity at least by eight, by 1000 when the sweep lasts a
#: fifth of the gap.
MAX_DESKEW_ITERATIONS = 3


# ------------------------------------------------------------------------------------------------
# predict


@dataclass(frozen=True)
class Motion:
    """The last accepted motion ``T_prev_curr`` and the time it took (ns)."""

    T_prev_curr: FloatArray
    gap_ns: int

    def twist(self) -> FloatArray:
        """The constant twist ``(omega, v)`` of this motion (per second)."""
        return twist_of(self.T_prev_curr, self.gap_ns * 1e-9)


def _scale_motion(T: FloatArray, factor: float) -> FloatArray:
    """Rotation vector and translation of ``T`` scaled by ``factor`` (first-order screw)."""
    if factor == 1.0:
        return T.copy()
    return make_transform(exp_so3(factor * log_so3(T[:3, :3])), factor * T[:3, 3])


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
    return T_world_last @ _scale_motion(motion.T_prev_curr, factor)


# ------------------------------------------------------------------------------------------------
# deskew and prepare


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


def prepare(
    sweep: Sweep, twist: FloatArray, config: KentRegConfig, voxel_size_hint: float
) -> PreparedScan:
    """The scan prepared once: deskewed with ``twist`` (when it has times), then cropped,
    downsampled, given normals and clusters (:func:`~kentreg_ros.core.scan.prepare_scan`).

    Raises
    ------
    InvalidPointCloudError
        Too few points survive the preprocessing.
    """
    points = sweep.points if sweep.times is None else deskew(sweep.points, sweep.times, twist)
    return prepare_scan(points, config=config, voxel_size_hint=voxel_size_hint)


# ------------------------------------------------------------------------------------------------
# verify


@dataclass(frozen=True, eq=False)
class Outcome:
    """The pose a step takes in the model frame, or a fall-back to the prediction."""

    result: RegistrationResult | None
    T: FloatArray
    fit: float
    health: Health
    message: str
    searched: bool = False

    @classmethod
    def fell_back(
        cls, reason: str, result: RegistrationResult | None = None, searched: bool = False
    ) -> Outcome:
        """Fall back to the prediction; ``result`` (the rejected estimate) is kept for
        inspection."""
        message = f'Fell back to the prediction: {reason}.'
        return cls(result, np.eye(4), float('nan'), Health.FELL_BACK, message, searched)

    @property
    def accepted(self) -> bool:
        return self.health.accepted


def _own_health(result: RegistrationResult) -> Health:
    return Health.DEGENERATE if result.status == Status.DEGENERATE else Health.OK


class Verifier:
    """Judges a registration and chooses the step's pose: the only place that chooses.

    A registration from the prediction is *doubtful* when it failed, breaks the speed limits
    (``odometry.max_*_speed``) or fits clearly worse than the recent accepted steps
    (``odometry.doubt_ratio`` of the median of ``fits``; of 1, the best fit there is, before
    the first accepted step). Then the start-free search runs too
    and :func:`~kentreg_ros.core.registration.verify.choose_pose` chooses among the plausible
    poses, preferring the one nearest the prediction among those that fit about equally.
    """

    def __init__(self, config: KentRegConfig) -> None:
        self.config = config

    def implausible(self, T_model_curr: FloatArray, gap_ns: int) -> str:
        """Why a step breaks the speed limits over ``gap_ns``, or '' if it does not."""
        if gap_ns <= 0:
            return ''
        odo = self.config.odometry
        gap = gap_ns * 1e-9
        angle = np.degrees(rotation_angle(T_model_curr[:3, :3]))
        dist = float(np.linalg.norm(T_model_curr[:3, 3]))
        if angle > odo.max_angular_speed_deg * gap:
            return (
                f'the step turns {angle:.1f} deg in {gap:.3f} s, faster than '
                f'odometry.max_angular_speed_deg={odo.max_angular_speed_deg}'
            )
        if dist > odo.max_linear_speed * gap:
            return (
                f'the step moves {dist:.2f} m in {gap:.3f} s, faster than '
                f'odometry.max_linear_speed={odo.max_linear_speed}'
            )
        return ''

    def doubt(self, result: RegistrationResult, why_implausible: str, fits: list[float]) -> str:
        """Why the registration from the prediction is doubtful, or '' if it is not."""
        if result.status == Status.FAILED:
            return f'it failed ({result.message})'
        if why_implausible:
            return why_implausible
        if not np.isfinite(result.fit):
            return ''  # paper mode: no fit to judge by
        # With no accepted step yet, the best fit any pose can have (1, every point on a
        # matching surface) stands in for the recent median. A wrong minimum loses whole
        # families of surfaces: from the identity, right results fitted 0.70-0.92 and wrong ones
        # at most 0.50 (test_first_fit_separates_right_from_wrong_minima), so only a first fit
        # below doubt_ratio pays for the start-free search.
        median = float(np.median(fits)) if fits else 1.0
        ratio = self.config.odometry.doubt_ratio
        if result.fit < ratio * median:
            of = f'the recent median {median:.2f}' if fits else 'a perfect fit (no step yet)'
            return f'its fit {result.fit:.2f} is below {ratio} x {of}'
        return ''

    def choose(
        self,
        scan: PreparedScan,
        model: PreparedScan,
        T_pred: FloatArray,
        gap_ns: int,
        fits: list[float],
    ) -> Outcome:
        """Register ``scan`` against ``model`` from ``T_pred``; search when that is doubtful;
        return the step's pose in the model frame."""
        cfg = self.config
        try:
            first = register(scan, model, init=T_pred, config=cfg, global_search=False)
        except (KentRegError, np.linalg.LinAlgError) as exc:
            return Outcome.fell_back(f'the registration raised {type(exc).__name__}: {exc}')
        why = self.implausible(first.T_target_source, gap_ns)
        doubt = self.doubt(first, why, fits)
        if not doubt:
            return Outcome(
                first, first.T_target_source, first.fit, _own_health(first), first.message
            )
        candidates: list[Candidate[RegistrationResult]] = []
        if first.status != Status.FAILED and not why:
            candidates.append(Candidate(first.T_target_source, first.fit, first))
        searched = cfg.mode == Mode.ROBUST and cfg.search.mode != SearchMode.NEVER
        if searched:
            candidates += self._search(scan, model, gap_ns)
        if not candidates:
            reason = (
                f'the registration from it was doubtful ({doubt}) and no plausible pose was found'
            )
            return Outcome.fell_back(reason, first, searched)
        spacing = max(scan.voxel_size, model.voxel_size)
        gate = 2.0 * FitGates.for_spacing(spacing).distance if spacing > 0.0 else 0.0
        choice = choose_pose(
            candidates,
            scan.points,
            gate=gate,
            ratio=cfg.search.ambiguity_ratio,
            prior=T_pred,
            preferred=candidates[0] if not candidates[0].searched else None,
        )
        if np.isfinite(first.fit) and choice.best_fit < cfg.odometry.min_fit:
            return Outcome.fell_back(
                f'the best pose found fits {choice.best_fit:.2f} < odometry.min_fit='
                f'{cfg.odometry.min_fit} ({doubt})',
                first,
                searched,
            )
        chosen = choice.chosen
        if choice.rivals:
            health = Health.AMBIGUOUS
            message = (
                f'{len(choice.rivals) + 1} distinct poses fit about equally (fit '
                f'{chosen.fit:.2f}); used the one nearest the prediction. Searched because '
                f'{doubt}.'
            )
        elif chosen.searched:
            health = Health.RECOVERED
            message = (
                f'Recovered: the registration from the prediction was doubtful ({doubt}); the '
                f'search found a pose fitting {chosen.fit:.2f} (it fitted {first.fit:.2f}).'
            )
        else:
            health = _own_health(chosen.origin)
            message = f'{chosen.origin.message} Confirmed by a search ({doubt}).'
        return Outcome(chosen.origin, chosen.T, chosen.fit, health, message, searched)

    def _search(
        self, scan: PreparedScan, model: PreparedScan, gap_ns: int
    ) -> list[Candidate[RegistrationResult]]:
        """The plausible poses of the start-free search (its best and its alternatives)."""
        try:
            found = register(scan, model, init=np.eye(4), config=self.config, global_search=True)
        except (KentRegError, np.linalg.LinAlgError) as exc:
            logger.warning('The search raised %s: %s', type(exc).__name__, exc)
            return []
        if found.status == Status.FAILED:
            return []
        return [
            Candidate(T, fit, found, searched=True)
            for T, fit in [(found.T_target_source, found.fit), *found.alternatives]
            if not self.implausible(T, gap_ns)
        ]

    def judge_round(
        self, result: RegistrationResult, before: Outcome, gap_ns: int
    ) -> Outcome | None:
        """The outcome of a registration after deskewing again, from ``before``'s pose, or None
        when it is no better than ``before`` (it failed, fits clearly worse, or breaks the
        speed limits). Its own status decides ok or degenerate; a pose found by the search, or
        chosen among ambiguous ones, keeps saying so."""
        if (
            result.status == Status.FAILED
            or not result.fit >= before.fit * self.config.search.ambiguity_ratio
            or self.implausible(result.T_target_source, gap_ns)
        ):
            return None
        health, message = _own_health(result), f'{result.message} (re-registered after deskewing)'
        if health is Health.OK and before.health in (Health.RECOVERED, Health.AMBIGUOUS):
            health, message = before.health, before.message
        return Outcome(
            result, result.T_target_source, result.fit, health, message, before.searched
        )


# ------------------------------------------------------------------------------------------------
# deskew, iterated with the registration


def _resolvable(change: FloatArray, span_s: float, outcome: Outcome) -> bool:
    """Whether deskewing a sweep of ``span_s`` seconds with a twist differing by ``change``
    would move its registered pose by more than the registration resolves: the pose lands
    about half the sweep's motion difference away (``change x span / 2``), compared with the
    covariance of the registration (Mahalanobis distance above 1)."""
    if outcome.result is None:
        return False
    bias = 0.5 * span_s * np.concatenate([change[3:], change[:3]])  # (x, y, z, roll, ...)
    cov = np.asarray(outcome.result.covariance, dtype=np.float64)
    try:
        return bool(bias @ np.linalg.solve(cov, bias) > 1.0)
    except np.linalg.LinAlgError:
        return False


class Deskewer:
    """Deskews a sweep again with the motion just registered and registers it once more,
    while that moves the sweep's points by more than half a voxel from where the last deskewing
    put them or the registered pose by more than the registration resolves (the deskewing and
    the registration converge together: constant velocity within the sweep; at most
    :data:`MAX_DESKEW_ITERATIONS` rounds, each judged by :meth:`Verifier.judge_round`)."""

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
    ) -> tuple[PreparedScan, Outcome]:
        """The scan deskewed with the registered motion and its outcome (``used``: the twist
        ``scan`` was deskewed with)."""
        assert sweep.times is not None and model.scan is not None
        span = float(np.ptp(sweep.times))
        reach = float(np.max(row_norms(scan.points))) if len(scan) else 0.0
        spacing = max(scan.voxel_size, 1e-9)
        for _ in range(MAX_DESKEW_ITERATIONS):
            twist = twist_of(outcome.T, gap_ns * 1e-9)
            change = twist - used
            shift = (np.linalg.norm(change[:3]) * reach + np.linalg.norm(change[3:])) * span
            if shift <= DESKEW_ITERATE_SPACINGS * spacing and not _resolvable(
                change, span, outcome
            ):
                break
            try:
                target = model.deskew_first(twist, self.config)
                again = prepare(sweep, twist, self.config, scan.voxel_size)
                result = register(
                    again, target, init=outcome.T, config=self.config, global_search=False
                )
            except (KentRegError, np.linalg.LinAlgError):
                break
            judged = self.verifier.judge_round(result, outcome, gap_ns)
            if judged is None:
                break  # keep the last round: this one is no better, or breaks the limits
            scan, used, outcome = again, twist, judged
        return scan, outcome


# ------------------------------------------------------------------------------------------------
# model
