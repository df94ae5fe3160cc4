"""Scan-to-previous-scan LiDAR odometry: register, chain ``T_world_lidar``, keep the new model.

The loop of the design card, one scan at a time::

    predict    T_world_pred = T_world_last @ velocity    (the last *accepted* motion, or none)
    prepare    the new scan once (crop, voxels, normals, clusters)
    register   source = new scan, target = model (previous scan), init = prediction
    doubt      the step failed, breaks the speed limits, or fits clearly worse than the last
               accepted steps  ->  also search without a start (zero motion and the
               start-free rotation search) and keep the best-fitting plausible pose; poses
               that fit about equally well go to the one nearest the prediction
    check      nothing plausible that fits -> fall back to the prediction
    chain      T_world_curr = T_world_model @ T_model_curr
    keep       the new scan, with its cached preprocessing, as the next model

With ``odometry.model = 'local_map'`` the model is instead a bounded voxel map of the accepted
scans (:class:`~kentreg_ros.core.localmap.VoxelMap`, in the world frame, with the normals each
scan brought), expressed in the frame of the last accepted pose: every step above runs
unchanged (the prediction, the zero-motion start and the start-free search are all relative to
that pose). Only an accepted step (or the first scan) enters the map; a step that fell back or
was rejected leaves map and model as they were, so the next scan is registered from the last
accepted pose across the gap.

A step that fell back keeps the predicted pose and is flagged; it never feeds the velocity,
so one bad step cannot be repeated by the next prediction (a runaway). A cloud that cannot be
used at all (:class:`~kentreg_ros.core.errors.InvalidPointCloudError`, e.g. too few points) is
flagged ``'rejected'``, gets the predicted pose, and the model is kept for the next scan.

:class:`Odometry` keeps no global state; the ROS node runs one instance in one worker thread.
An instance is not meant to be shared between threads.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core import kernels
from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.covariance import prediction_covariance, propagate_covariance
from kentreg_ros.core.deskew import (
    ImplausibleTimesError,
    PointTimes,
    deskew,
    sweep_times,
    twist_of,
)
from kentreg_ros.core.errors import InvalidInputError, InvalidPointCloudError, KentRegError
from kentreg_ros.core.localmap import LocalMap, nearest_spacing
from kentreg_ros.core.preprocess import as_points
from kentreg_ros.core.registration import (
    STATUS_DEGENERATE,
    STATUS_FAILED,
    PreparedScan,
    RegistrationResult,
    elapsed_ms,
    prepare_scan,
    register,
)
from kentreg_ros.core.rotations import (
    check_transform,
    exp_so3,
    invert_transform,
    log_so3,
    make_transform,
    rotation_angle,
)
from kentreg_ros.core.step import (
    ACCEPTED,
    HEALTH_AMBIGUOUS,
    HEALTH_DEGENERATE,
    HEALTH_FELL_BACK,
    HEALTH_FIRST,
    HEALTH_OK,
    HEALTH_RECOVERED,
    HEALTH_REJECTED,
    HEALTHS,
    OdometryStep,
)
from kentreg_ros.core.verify import FitGates, rms_displacement

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

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
#: Fewest points with a finite time a deskewed scan keeps (points without one are dropped):
#: below this the scan cannot be prepared anyway (the neighbourhood of the normals needs more).
MIN_TIMED_POINTS = 20
#: Largest factor by which the last motion is stretched when the scan gap grows (dropped scans).
MAX_VELOCITY_SCALE = 5.0


def _scale_motion(T: FloatArray, factor: float) -> FloatArray:
    """Rotation vector and translation of ``T`` scaled by ``factor`` (first-order screw)."""
    if factor == 1.0:
        return T.copy()
    return make_transform(exp_so3(factor * log_so3(T[:3, :3])), factor * T[:3, 3])


def _resolvable(change: FloatArray, span_s: float, choice: _Choice) -> bool:
    """Whether deskewing a sweep of ``span_s`` seconds with a twist differing by ``change``
    would move its registered pose by more than the registration resolves: the pose lands
    about half the sweep's motion difference away (``change x span / 2``), compared with the
    covariance of the registration (Mahalanobis distance above 1)."""
    if choice.result is None:
        return False
    bias = 0.5 * span_s * np.concatenate([change[3:], change[:3]])  # (x, y, z, roll, ...)
    cov = np.asarray(choice.result.covariance, dtype=np.float64)
    try:
        return bool(bias @ np.linalg.solve(cov, bias) > 1.0)
    except np.linalg.LinAlgError:
        return False


def _judged(result: RegistrationResult, before: _Choice) -> tuple[str, str]:
    """Health and message of a re-registration (after deskewing) from the pose ``before``
    chose: its own status decides ok or degenerate; a pose found by the search, or chosen among
    ambiguous ones, keeps saying so."""
    if result.status == STATUS_DEGENERATE:
        return HEALTH_DEGENERATE, f'{result.message} (re-registered after deskewing)'
    if before.health in (HEALTH_RECOVERED, HEALTH_AMBIGUOUS):
        return before.health, before.message
    return HEALTH_OK, f'{result.message} (re-registered after deskewing)'


def _as_stamp(stamp_ns: int) -> int:
    if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, int | np.integer):
        raise InvalidInputError(
            f'Expected `stamp_ns` to be an integer number of nanoseconds, got {stamp_ns!r}.'
        )
    return int(stamp_ns)


class Odometry:
    """Scan-to-model odometry (previous scan or local map) with the Kent registration.

    Parameters
    ----------
    config : KentRegConfig, optional
        Registration and odometry settings (default ``KentRegConfig()``, robust mode). The
        ``odometry`` section selects the constant-velocity prediction and the largest
        plausible step.
    initial_pose : array_like, shape (4, 4), optional
        ``T_world_lidar`` of the first scan (default identity).
    max_history : int, optional
        Keep only the last ``max_history`` poses and stamps (at least 2, which the prediction
        needs) in :attr:`poses` / :attr:`stamps_ns`, so that a long-running node does not grow
        without bound. None (default) keeps every pose, as offline replay wants.

    Notes
    -----
    Every scan is preprocessed exactly once: the :class:`PreparedScan` of the new scan is the
    source of this registration and the target of the next one. With automatic voxel sizing
    the search for each scan starts at the previous scan's voxel size.

    The constant-velocity prediction repeats the motion between the last two poses, stretched
    by the ratio of the time gaps when scans arrive irregularly (e.g. a dropped scan in the ROS
    node; the factor is limited to :data:`MAX_VELOCITY_SCALE`).

    Examples
    --------
    >>> odom = Odometry(KentRegConfig())                      # doctest: +SKIP
    >>> for points, stamp_ns in scans:                        # doctest: +SKIP
    ...     step = odom.step(points, stamp_ns, frame_id='lidar')
    ...     if not step.ok:
    ...         log.warning(step.message)
    >>> odom.poses.shape                                      # doctest: +SKIP
    (N, 4, 4)
    """

    def __init__(
        self,
        config: KentRegConfig | None = None,
        *,
        initial_pose: ArrayLike | None = None,
        max_history: int | None = None,
    ) -> None:
        cfg = config if config is not None else KentRegConfig()
        if not isinstance(cfg, KentRegConfig):
            raise InvalidInputError(
                f'Expected `config` to be a KentRegConfig, got {type(cfg).__name__}.'
            )
        if max_history is not None and (isinstance(max_history, bool) or max_history < 2):
            raise InvalidInputError(f'Expected `max_history` >= 2 or None, got {max_history!r}.')
        self._max_history = max_history
        self._config = cfg
        self._config_preprocess = cfg.preprocess
        self._initial_pose = (
            np.eye(4) if initial_pose is None else check_transform(initial_pose, 'initial_pose')
        )
        # Compile (or load) the per-point kernels now, not in the first scan's time budget.
        kernels.warm_up()
        self.reset()

    # ----------------------------------------------------------------------------------------
    # State

    def reset(self, initial_pose: ArrayLike | None = None) -> None:
        """Forget every scan and pose; the next scan starts a new trajectory.

        Parameters
        ----------
        initial_pose : array_like, shape (4, 4), optional
            ``T_world_lidar`` of the next first scan (default: the one given at construction).
        """
        if initial_pose is not None:
            self._initial_pose = check_transform(initial_pose, 'initial_pose')
        self._model: PreparedScan | None = None
        self._model_index = -1
        self._T_world_model = self._initial_pose.copy()
        self._cov_model = np.zeros((6, 6))
        self._voxel_size_hint = 0.0
        self._poses: deque[FloatArray] = deque(maxlen=self._max_history)
        self._stamps: deque[int] = deque(maxlen=self._max_history)
        self._n_steps = 0
        self._frame_id: str | None = None
        self._counts = dict.fromkeys(HEALTHS, 0)
        # The last accepted motion T_prev_curr and its time gap (ns); None until one exists.
        self._velocity: tuple[FloatArray, int] | None = None
        self._model_stamp = 0
        self._fits: deque[float] = deque(maxlen=self._config.odometry.fit_window)
        self._n_searched = 0
        self._warned: set[str] = set()
        # Raw points and times of a model prepared before any motion was known (see _deskewed).
        self._model_sweep: tuple[FloatArray, FloatArray] | None = None
        # odometry.model == 'local_map': the map of the accepted scans, in the world frame.
        self._map: LocalMap | None = None

    @property
    def config(self) -> KentRegConfig:
        """The settings in use."""
        return self._config

    def reconfigure(self, config: KentRegConfig) -> None:
        """Use ``config`` from the next scan on, keeping the trajectory and the model.

        The model keeps the preprocessing it was prepared with; the next scan is prepared with
        the new settings and registered against it, so the trajectory continues without a gap.
        """
        if not isinstance(config, KentRegConfig):
            raise InvalidInputError(
                f'Expected `config` to be a KentRegConfig, got {type(config).__name__}.'
            )
        self._config = config
        self._fits = deque(self._fits, maxlen=config.odometry.fit_window)
        if config.preprocess != self._config_preprocess:
            self._voxel_size_hint = 0.0  # the previous size was searched for other settings
        self._config_preprocess = config.preprocess

    @property
    def poses(self) -> FloatArray:
        """``T_world_lidar`` of every scan so far (the last ``max_history``), shape (N, 4, 4)."""
        if not self._poses:
            return np.zeros((0, 4, 4))
        return np.array(self._poses)

    @property
    def stamps_ns(self) -> NDArray[np.int64]:
        """Stamps of every scan so far (the last ``max_history``), integer ns, shape (N,)."""
        return np.array(self._stamps, dtype=np.int64)

    @property
    def counts(self) -> dict[str, int]:
        """Number of steps per health value (see :data:`HEALTHS`)."""
        return dict(self._counts)

    @property
    def n_steps(self) -> int:
        """Scans given to :meth:`step` since the start or the last :meth:`reset`."""
        return self._n_steps

    @property
    def n_failed(self) -> int:
        """Scans whose pose is a prediction: fell back or rejected."""
        return self._counts[HEALTH_FELL_BACK] + self._counts[HEALTH_REJECTED]

    @property
    def n_searched(self) -> int:
        """Steps for which the start-free search ran."""
        return self._n_searched

    @property
    def n_degenerate(self) -> int:
        """Scans registered in a degenerate scene (estimate used, flagged)."""
        return self._counts[HEALTH_DEGENERATE]

    @property
    def local_map(self) -> LocalMap | None:
        """The local map (world frame) when ``odometry.model`` is 'local_map', else None.

        Owned by this instance: read it from the thread that calls :meth:`step`.
        """
        return self._map

    @property
    def has_model(self) -> bool:
        """True once a scan has been accepted as the model."""
        return self._model is not None

    # ----------------------------------------------------------------------------------------
    # The loop

    def _predict(self, stamp_ns: int) -> FloatArray:
        """``T_world_pred`` of a scan taken at ``stamp_ns``: the last pose moved by the last
        accepted motion, stretched to the time gap (constant velocity), or the last pose."""
        if not self._poses:
            return self._initial_pose.copy()
        T_last = self._poses[-1]
        if not self._config.odometry.constant_velocity or self._velocity is None:
            return T_last.copy()
        motion, gap_motion = self._velocity
        gap_now = stamp_ns - self._stamps[-1]
        factor = 1.0
        if gap_motion > 0 and gap_now > 0:
            factor = min(gap_now / gap_motion, MAX_VELOCITY_SCALE)
        return T_last @ _scale_motion(motion, factor)

    def _implausible(self, T_model_curr: FloatArray, gap_ns: int) -> str:
        """Why a step breaks the speed limits over ``gap_ns``, or '' if it does not."""
        if gap_ns <= 0:
            return ''
        odo = self._config.odometry
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

    def _doubt(self, result: RegistrationResult, why_implausible: str) -> str:
        """Why the registration from the prediction is doubtful, or '' if it is not."""
        if result.status == STATUS_FAILED:
            return f'it failed ({result.message})'
        if why_implausible:
            return why_implausible
        if not np.isfinite(result.fit):
            return ''  # paper mode: no fit to judge by
        if not self._fits:
            return 'no accepted step yet to compare its fit with'
        median = float(np.median(self._fits))
        ratio = self._config.odometry.doubt_ratio
        if result.fit < ratio * median:
            return f'its fit {result.fit:.2f} is below {ratio} x the recent median {median:.2f}'
        return ''

    def step(
        self,
        points: ArrayLike,
        stamp_ns: int,
        *,
        frame_id: str | None = None,
        point_times: ArrayLike | PointTimes | None = None,
    ) -> OdometryStep:
        """Register a new scan against the model (previous scan or local map); return its pose.

        Parameters
        ----------
        points : array_like, shape (N, 3)
            Finite points of the new scan in its sensor frame (drop NaN/inf first).
        stamp_ns : int
            Acquisition time, integer nanoseconds (e.g. the message header stamp).
        frame_id : str, optional
            Sensor frame of the scan; recorded in the step.
        point_times : array_like, shape (N,), optional
            The driver's per-point acquisition times (any unit, relative or absolute; a
            :class:`~kentreg_ros.core.deskew.PointTimes` also names the field, which tells
            the unit: see :func:`kentreg_ros.core.deskew.sweep_times`). With
            ``odometry.deskew`` 'auto' or 'on' every point is moved to the stamp's time with
            the motion of the sweep (constant velocity, re-estimated from the registration;
            see :meth:`_deskewed`). Points whose time is not finite are dropped and counted
            (``n_untimed``); times that are no plausible sweep leave the scan undeskewed,
            with one warning.

        Returns
        -------
        OdometryStep
            The pose and the health of the step. Never raises for a cloud that is merely
            unusable or a registration that fails: those are the ``'rejected'`` and
            ``'fell_back'`` healths.

        Raises
        ------
        InvalidInputError
            ``stamp_ns`` is not an integer (also a ``TypeError``).
        """
        t_start = time.perf_counter()
        stamp = _as_stamp(stamp_ns)
        index = self._n_steps
        if self._stamps and stamp <= self._stamps[-1]:
            logger.warning(
                'Scan %d: stamp %d ns is not after the previous one (%d ns).',
                index,
                stamp,
                self._stamps[-1],
            )
        if frame_id is not None:
            if self._frame_id is not None and frame_id != self._frame_id:
                logger.warning(
                    'Scan %d: frame_id changed from %r to %r.', index, self._frame_id, frame_id
                )
            self._frame_id = frame_id
        T_world_pred = self._predict(stamp)
        pending = _Pending(
            index=index,
            stamp_ns=stamp,
            frame_id=frame_id,
            T_model_pred=invert_transform(self._T_world_model) @ T_world_pred,
            n_points=int(np.shape(points)[0]) if np.ndim(points) >= 1 else 0,
            t_start=t_start,
        )

        t0 = time.perf_counter()
        try:
            points, times = self._sweep_times(points, point_times, stamp, pending)
            swept = points
            if times is not None:
                swept = deskew(as_points(points), times, self._predicted_twist(stamp))
            scan = prepare_scan(swept, config=self._config, voxel_size_hint=self._voxel_size_hint)
        except InvalidPointCloudError as exc:
            pending.timings['preprocess'] = elapsed_ms(t0)
            message = f'Rejected the scan: {exc} The pose is the prediction.'
            logger.warning('Scan %d: %s', index, message)
            return self._record(pending, T_world_pred, None, HEALTH_REJECTED, message, None)
        pending.timings['preprocess'] = elapsed_ms(t0)
        pending.n_prepared = len(scan)
        self._voxel_size_hint = scan.voxel_size
        if self._model is None:
            message = 'First scan: it becomes the model.'
            first = self._record(pending, T_world_pred, None, HEALTH_FIRST, message, scan)
            if times is not None:
                self._model_sweep = (as_points(points), times)
            return first

        t0 = time.perf_counter()
        choice = self._register(scan, pending, stamp - self._model_stamp)
        if times is not None and choice.health != HEALTH_FELL_BACK:
            scan, choice = self._deskewed(points, times, scan, choice, stamp)
        pending.timings['register'] = elapsed_ms(t0)
        if choice.result is not None:
            for stage in ('rotation', 'translation', 'refine', 'search'):
                if stage in choice.result.timings:
                    pending.timings[stage] = choice.result.timings[stage]
        if choice.health == HEALTH_FELL_BACK:
            logger.warning('Scan %d: %s', index, choice.message)
            return self._record(
                pending, T_world_pred, choice.result, HEALTH_FELL_BACK, choice.message, scan
            )
        if choice.health != HEALTH_OK:
            logger.info('Scan %d: %s', index, choice.message)
        pending.fit = choice.fit
        T_world_curr = self._T_world_model @ choice.T
        return self._record(
            pending, T_world_curr, choice.result, choice.health, choice.message, scan
        )

    def _sweep_times(
        self,
        points: ArrayLike,
        point_times: ArrayLike | PointTimes | None,
        stamp: int,
        pending: _Pending,
    ) -> tuple[ArrayLike, FloatArray | None]:
        """The points to prepare and their seconds from the stamp, when the scan is to be
        deskewed (else the points as given and None). Points without a finite time are dropped
        (counted in ``pending.n_untimed``); times that are no plausible sweep are not used."""
        odo = self._config.odometry
        if odo.deskew == 'off' or point_times is None:
            if odo.deskew == 'on' and point_times is None:
                self._warn_once(
                    'no_times', 'odometry.deskew is on but the scans carry no per-point times.'
                )
            return points, None
        field = point_times.field if isinstance(point_times, PointTimes) else ''
        values = np.asarray(point_times)
        if values.ndim != 1 or len(values) != int(np.shape(points)[0]):
            raise InvalidPointCloudError(
                f'Expected one time per point ({np.shape(points)[0]}), got shape {values.shape}.'
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
            self._warn_once(
                'implausible_times',
                f'Not deskewing: {exc}. Set odometry.point_time_unit and '
                'odometry.point_time_reference if the driver uses another convention.',
            )
            return points, None
        times = found.seconds
        timed = np.isfinite(times)
        if not timed.all():
            pending.n_untimed = int(np.count_nonzero(~timed))
            points, times = as_points(points)[timed], times[timed]
            if len(times) < MIN_TIMED_POINTS:
                raise InvalidPointCloudError(
                    f'only {len(times)} of {pending.n_points} points have a finite time '
                    f'(need {MIN_TIMED_POINTS}).'
                )
        return points, (times if np.ptp(times) > 0.0 else None)

    def _warn_once(self, key: str, message: str) -> None:
        """Log ``message`` the first time ``key`` happens in this trajectory."""
        if key not in self._warned:
            self._warned.add(key)
            logger.warning(message)

    def _predicted_twist(self, stamp: int) -> FloatArray:
        """The sensor's velocity during the sweep: the last accepted motion (zero before one)."""
        if self._velocity is None:
            return np.zeros(6)
        motion, gap = self._velocity
        return twist_of(motion, gap * 1e-9)

    def _deskewed(
        self, points: ArrayLike, times: FloatArray, scan: PreparedScan, choice: _Choice, stamp: int
    ) -> tuple[PreparedScan, _Choice]:
        """Deskew again with the motion just registered while it moves the sweep's points by
        more than half a voxel from where the last deskewing put them, or the registered pose by
        more than the registration resolves (:func:`_resolvable`), registering once more from
        the pose found each time (the registration and the deskewing converge together:
        constant velocity within the sweep, iterated with the registration; at most
        :data:`MAX_DESKEW_ITERATIONS` times)."""
        assert self._model is not None
        gap_s = (stamp - self._model_stamp) * 1e-9
        used = self._predicted_twist(stamp)
        reach = float(np.max(np.linalg.norm(scan.points, axis=1))) if len(scan) else 0.0
        spacing = max(scan.voxel_size, 1e-9)
        for _ in range(MAX_DESKEW_ITERATIONS):
            twist = twist_of(choice.T, gap_s)
            change = twist - used
            shift = (np.linalg.norm(change[:3]) * reach + np.linalg.norm(change[3:])) * np.ptp(
                times
            )
            if shift <= DESKEW_ITERATE_SPACINGS * spacing and not _resolvable(
                change, np.ptp(times), choice
            ):
                break
            try:
                if self._model_sweep is not None:
                    # The model was prepared before any motion was known (the first scan): its
                    # sweep moved like this one (constant velocity), so deskew it now, once.
                    model_points, model_times = self._model_sweep
                    first = prepare_scan(
                        deskew(model_points, model_times, twist),
                        config=self._config,
                        voxel_size_hint=self._model.voxel_size,
                    )
                    if self._map is not None:  # the map holds only the first scan yet
                        self._map.clear()
                        first = self._map_model(first, self._T_world_model)
                    self._model = first
                    self._model_sweep = None
                again = prepare_scan(
                    deskew(as_points(points), times, twist),
                    config=self._config,
                    voxel_size_hint=scan.voxel_size,
                )
                result = register(
                    again, self._model, init=choice.T, config=self._config, global_search=False
                )
            except (KentRegError, np.linalg.LinAlgError):
                break
            if (
                result.status == STATUS_FAILED
                or not result.fit >= choice.fit * self._config.search.ambiguity_ratio
                or self._implausible(result.T_target_source, stamp - self._model_stamp)
            ):
                break  # keep the last round: this one is no better, or breaks the limits
            scan, used = again, twist
            choice = _Choice(result, result.T_target_source, result.fit, *_judged(result, choice))
        return scan, choice

    def _register(self, scan: PreparedScan, pending: _Pending, gap: int) -> _Choice:
        """Choose the pose of ``scan`` in the model frame (see the module docstring)."""
        assert self._model is not None
        cfg = self._config
        T_pred = pending.T_model_pred
        try:
            first = register(scan, self._model, init=T_pred, config=cfg, global_search=False)
        except (KentRegError, np.linalg.LinAlgError) as exc:
            return _Choice.fell_back(f'the registration raised {type(exc).__name__}: {exc}')
        why = self._implausible(first.T_target_source, gap)
        doubt = self._doubt(first, why)
        if not doubt:
            health = HEALTH_DEGENERATE if first.status == STATUS_DEGENERATE else HEALTH_OK
            return _Choice(first, first.T_target_source, first.fit, health, first.message)
        candidates: list[_Candidate] = []
        if first.status != STATUS_FAILED and not why:
            candidates.append(_Candidate(first, first.T_target_source, first.fit, False))
        if cfg.mode == 'robust' and cfg.search.mode != 'never':
            self._n_searched += 1
            pending.searched = True
            try:
                found = register(scan, self._model, init=np.eye(4), config=cfg, global_search=True)
            except (KentRegError, np.linalg.LinAlgError) as exc:
                logger.warning(
                    'Scan %d: the search raised %s: %s', pending.index, type(exc).__name__, exc
                )
            else:
                if found.status != STATUS_FAILED:
                    for T, fit in [(found.T_target_source, found.fit), *found.alternatives]:
                        if not self._implausible(T, gap):
                            candidates.append(_Candidate(found, T, fit, True))
        if not candidates:
            return _Choice.fell_back(
                f'the registration from it was doubtful ({doubt}) and no plausible pose was found',
                first,
            )
        fits = np.array([c.fit if np.isfinite(c.fit) else 0.0 for c in candidates])
        best_fit = float(fits.max())
        if np.isfinite(first.fit) and best_fit < cfg.odometry.min_fit:
            return _Choice.fell_back(
                f'the best pose found fits {best_fit:.2f} < odometry.min_fit='
                f'{cfg.odometry.min_fit} ({doubt})',
                first,
            )
        ratio = cfg.search.ambiguity_ratio
        near = [c for c, f in zip(candidates, fits, strict=True) if f >= ratio * best_fit]
        # Poses that fit about equally: the one nearest the motion prior wins.
        chosen = min(near, key=lambda c: rms_displacement(scan.points, c.T, T_pred))
        spacing = max(scan.voxel_size, self._model.voxel_size)
        gate = 2.0 * FitGates.for_spacing(spacing).distance if spacing > 0.0 else 0.0
        distinct = [c for c in near if rms_displacement(scan.points, c.T, chosen.T) > gate]
        if chosen.from_search and not candidates[0].from_search:
            if rms_displacement(scan.points, candidates[0].T, chosen.T) <= gate:
                chosen = candidates[0]  # the search confirmed the registration
        if distinct:
            health = HEALTH_AMBIGUOUS
            message = (
                f'{len(distinct) + 1} distinct poses fit about equally (fit {chosen.fit:.2f}); '
                f'used the one nearest the prediction. Searched because {doubt}.'
            )
        elif chosen.from_search:
            health = HEALTH_RECOVERED
            message = (
                f'Recovered: the registration from the prediction was doubtful ({doubt}); the '
                f'search found a pose fitting {chosen.fit:.2f} (it fitted {first.fit:.2f}).'
            )
        else:
            result = chosen.result
            health = HEALTH_DEGENERATE if result.status == STATUS_DEGENERATE else HEALTH_OK
            message = f'{result.message} Confirmed by a search ({doubt}).'
        return _Choice(chosen.result, chosen.T, chosen.fit, health, message)

    def _map_model(self, scan: PreparedScan, T_world_scan: FloatArray) -> PreparedScan:
        """Insert ``scan`` (posed at ``T_world_scan``) into the local map, drop what lies beyond
        the map radius, and return the map in the scan's frame as the next model."""
        odo = self._config.odometry
        if (
            self._map is None
            or self._map.voxels.max_points_per_voxel != odo.map_points_per_voxel
            or (odo.map_voxel_size > 0.0 and self._map.voxel_size != odo.map_voxel_size)
        ):
            voxel = odo.map_voxel_size or scan.voxel_size or nearest_spacing(scan.points)
            self._map = LocalMap(voxel, max_points_per_voxel=odo.map_points_per_voxel)
        radius = odo.map_radius or float(np.sqrt(np.max(np.sum(scan.points**2, axis=1))))
        self._map.insert_scan(scan, T_world_scan, radius=radius)
        try:
            return self._map.target(T_world_scan, config=self._config)
        except InvalidPointCloudError as exc:
            # Too few map points survive the radius: register against the scan itself.
            logger.warning('The local map cannot be a target (%s); using the scan itself.', exc)
            return scan

    def _record(
        self,
        pending: _Pending,
        T_world_curr: FloatArray,
        result: RegistrationResult | None,
        health: str,
        message: str,
        new_model: PreparedScan | None,
    ) -> OdometryStep:
        """Append the pose, move the model on (unless ``new_model`` is None), build the step."""
        prepared = new_model.points if new_model is not None else None
        T_prev_curr = (
            invert_transform(self._poses[-1]) @ T_world_curr if self._poses else np.eye(4)
        )
        if self._model is None and new_model is not None:
            covariance = self._cov_model.copy()  # the first pose is the origin of the frame
        else:
            if health in ACCEPTED and result is not None:
                cov_step = np.asarray(result.covariance, dtype=np.float64)
            else:
                cov_step = prediction_covariance(pending.T_model_pred)
            T_model_curr = invert_transform(self._T_world_model) @ T_world_curr
            covariance = propagate_covariance(
                self._cov_model, self._T_world_model, T_model_curr, cov_step
            )
        model_index = self._model_index
        if health in ACCEPTED and self._model is not None:
            # Only accepted motions feed the prediction and the fits a step is judged by.
            T_model_curr = invert_transform(self._T_world_model) @ T_world_curr
            self._velocity = (T_model_curr, pending.stamp_ns - self._model_stamp)
            if np.isfinite(pending.fit):
                self._fits.append(pending.fit)
        if self._config.odometry.model != 'local_map':
            self._map = None
        elif new_model is not None:
            if self._model is None or self._map is None or health in ACCEPTED:
                new_model = self._map_model(new_model, T_world_curr)
            else:
                # A fall-back stays out of the map: the model stays the map in the frame of the
                # last accepted pose, and the next scan is registered from there.
                new_model = None
        if new_model is not None:
            self._model_sweep = None
            # A fall-back still moves the model on: the scan is valid and its predicted pose is
            # the best estimate; the next registration then bridges one scan gap, not two.
            self._model = new_model
            self._model_index = pending.index
            self._T_world_model = T_world_curr.copy()
            self._cov_model = covariance
            self._model_stamp = pending.stamp_ns
        self._poses.append(T_world_curr.copy())
        self._stamps.append(pending.stamp_ns)
        self._n_steps += 1
        self._counts[health] += 1
        pending.timings['total'] = elapsed_ms(pending.t_start)
        return OdometryStep(
            index=pending.index,
            stamp_ns=pending.stamp_ns,
            frame_id=pending.frame_id,
            T_world_lidar=T_world_curr.copy(),
            T_prev_curr=T_prev_curr,
            T_model_pred=pending.T_model_pred,
            model_index=model_index,
            result=result,
            health=health,
            message=message,
            timings=pending.timings,
            n_points=pending.n_points,
            n_prepared=pending.n_prepared,
            n_untimed=pending.n_untimed,
            covariance=covariance,
            fit=pending.fit,
            searched=pending.searched,
            points=prepared,
        )


@dataclass
class _Pending:
    """What is known of a step before its outcome."""

    index: int
    stamp_ns: int
    frame_id: str | None
    T_model_pred: FloatArray
    n_points: int
    t_start: float
    n_prepared: int = 0
    timings: dict[str, float] = field(default_factory=dict)
    fit: float = float('nan')
    searched: bool = False
    n_untimed: int = 0


@dataclass(frozen=True, eq=False)
class _Candidate:
    """A pose the step may take."""

    result: RegistrationResult
    T: FloatArray
    fit: float
    from_search: bool


@dataclass(frozen=True, eq=False)
class _Choice:
    """The pose a step takes, or a fall-back to the prediction (``health``)."""

    result: RegistrationResult | None
    T: FloatArray
    fit: float
    health: str
    message: str

    @classmethod
    def fell_back(cls, reason: str, result: RegistrationResult | None = None) -> _Choice:
        """Fall back to the prediction; ``result`` (the rejected estimate) is kept for
        inspection."""
        message = f'Fell back to the prediction: {reason}.'
        return cls(result, np.eye(4), float('nan'), HEALTH_FELL_BACK, message)
