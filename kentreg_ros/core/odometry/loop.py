"""Scan-to-model LiDAR odometry: register each scan against the model, chain ``T_world_lidar``.

:meth:`Odometry.step` runs the stages of :mod:`kentreg_ros.core.odometry.stages` in order::

    predict    T_world_pred = T_world_last @ motion  (the last *accepted* motion, or none)
    prepare    the scan once, deskewed with that motion (crop, voxels, normals, clusters)
    register   source = the scan, target = the model, init = the prediction
    verify     a doubtful step (failed, too fast, fitting clearly worse than the last accepted
               ones) is searched again without a start and the best-fitting plausible pose is
               chosen, the one nearest the prediction among those fitting about equally;
               nothing plausible that fits -> fall back to the prediction
    deskew     again with the registered motion, registering again, while that matters
    chain      T_world_curr = T_world_model @ T_model_curr
    model      the previous scan, or the local map of the accepted scans, moves on

A step that fell back keeps the predicted pose and is flagged; it never feeds the motion, so
one bad step cannot be repeated by the next prediction (a runaway). A cloud that cannot be
used at all (:class:`~kentreg_ros.core.errors.InvalidPointCloudError`, e.g. too few points) is
flagged ``rejected``, gets the predicted pose, and the model is kept for the next scan.

:class:`Odometry` keeps no global state; the ROS node runs one instance in one worker thread.
An instance is not meant to be shared between threads.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core import kernels
from kentreg_ros.core.config import KentRegConfig, Model
from kentreg_ros.core.errors import InvalidInputError
from kentreg_ros.core.geometry import check_transform, invert_transform
from kentreg_ros.core.odometry.covariance import prediction_covariance, propagate_covariance
from kentreg_ros.core.odometry.deskew import PointTimes
from kentreg_ros.core.odometry.localmap import LocalMap
from kentreg_ros.core.odometry.models import LocalMapModel, ModelStrategy, PreviousScanModel
from kentreg_ros.core.odometry.preparation import Preparation, prepare_input
from kentreg_ros.core.odometry.stages import Deskewer, Motion, Outcome, Sweep, Verifier, predict
from kentreg_ros.core.odometry.step import HEALTHS, Health, OdometryStep
from kentreg_ros.core.scan.prepared import PreparedScan, elapsed_ms

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: Registration stages whose times a step reports.
STAGE_TIMINGS = ('rotation', 'translation', 'refine', 'search')


def _as_stamp(stamp_ns: int) -> int:
    if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, int | np.integer):
        raise InvalidInputError(
            f'Expected `stamp_ns` to be an integer number of nanoseconds, got {stamp_ns!r}.'
        )
    return int(stamp_ns)


@dataclass
class _Pending:
    """What is known of a step before its outcome."""

    index: int
    stamp_ns: int
    frame_id: str | None
    T_model_pred: FloatArray
    n_points: int
    t_start: float
    timings: dict[str, float] = field(default_factory=dict)


class Odometry:
    """Scan-to-model odometry (previous scan or local map) with the Kent registration.

    Parameters
    ----------
    config : KentRegConfig, optional
        Registration and odometry settings (default ``KentRegConfig()``, robust mode). The
        ``odometry`` section selects the model, the deskewing and the plausible speeds.
    initial_pose : array_like, shape (4, 4), optional
        ``T_world_lidar`` of the first scan (default identity).
    max_history : int, optional
        Keep only the last ``max_history`` poses and stamps (at least 2, which the prediction
        needs) in :attr:`poses` / :attr:`stamps_ns`, so that a long-running node does not grow
        without bound. None (default) keeps every pose, as offline replay wants.

    Notes
    -----
    Every scan is preprocessed once: the :class:`PreparedScan` of the new scan is the source
    of this registration and the target of the next one. With automatic voxel sizing the search
    for each scan starts at the previous scan's voxel size.

    The constant-velocity prediction repeats the last accepted motion, stretched by the ratio
    of the time gaps when scans arrive irregularly (e.g. a dropped scan in the ROS node; see
    :func:`~kentreg_ros.core.odometry.stages.predict`).

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
        if max_history is not None and (isinstance(max_history, bool) or max_history < 2):
            raise InvalidInputError(f'Expected `max_history` >= 2 or None, got {max_history!r}.')
        self._max_history = max_history
        self._initial_pose = (
            np.eye(4) if initial_pose is None else check_transform(initial_pose, 'initial_pose')
        )
        self._set_config(config if config is not None else KentRegConfig())
        # Compile (or load) the per-point kernels now, not in the first scan's time budget.
        kernels.warm_up()
        self.reset()

    def _set_config(self, config: KentRegConfig) -> None:
        if not isinstance(config, KentRegConfig):
            raise InvalidInputError(
                f'Expected `config` to be a KentRegConfig, got {type(config).__name__}.'
            )
        self._config = config
        self._verifier = Verifier(config)
        self._deskewer = Deskewer(config, self._verifier)

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
        self._model: ModelStrategy = self._new_model(PreviousScanModel(self._initial_pose))
        self._voxel_size_hint = 0.0
        self._poses: deque[FloatArray] = deque(maxlen=self._max_history)
        self._stamps: deque[int] = deque(maxlen=self._max_history)
        self._frame_id: str | None = None
        self._counts = dict.fromkeys(HEALTHS, 0)
        self._motion: Motion | None = None  # the last accepted motion
        self._fits: deque[float] = deque(maxlen=self._config.odometry.fit_window)
        self._n_searched = 0
        self._warned: set[str] = set()
        #: The last step's model upkeep, when it was deferred (see update_model).
        self._deferred: Callable[[], None] | None = None

    def _new_model(self, current: ModelStrategy) -> ModelStrategy:
        """The model strategy the configuration asks for, continuing from ``current``."""
        if self._config.odometry.model == Model.LOCAL_MAP:
            if isinstance(current, LocalMapModel):
                current.config = self._config
                return current
            return LocalMapModel.like(current, self._config)
        if type(current) is PreviousScanModel:
            return current
        return PreviousScanModel.like(current, self._config)

    @property
    def config(self) -> KentRegConfig:
        """The settings in use."""
        return self._config

    def reconfigure(self, config: KentRegConfig) -> None:
        """Use ``config`` from the next scan on, keeping the trajectory and the model.

        The model keeps the preprocessing it was prepared with; the next scan is prepared with
        the new settings and registered against it, so the trajectory continues without a gap.
        """
        self.update_model()  # the last step's upkeep runs with the settings it was taken with
        previous = self._config.preprocess
        self._set_config(config)
        self._fits = deque(self._fits, maxlen=config.odometry.fit_window)
        if config.preprocess != previous:
            self._voxel_size_hint = 0.0  # the previous size was searched for other settings
        self._model = self._new_model(self._model)

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
        return {str(h): n for h, n in self._counts.items()}

    @property
    def n_steps(self) -> int:
        """Scans given to :meth:`step` since the start or the last :meth:`reset`."""
        return sum(self._counts.values())

    @property
    def n_failed(self) -> int:
        """Scans whose pose is a prediction: fell back or rejected."""
        return self._counts[Health.FELL_BACK] + self._counts[Health.REJECTED]

    @property
    def n_searched(self) -> int:
        """Steps for which the start-free search ran."""
        return self._n_searched

    @property
    def n_degenerate(self) -> int:
        """Scans registered in a degenerate scene (estimate used, flagged)."""
        return self._counts[Health.DEGENERATE]

    @property
    def local_map(self) -> LocalMap | None:
        """The local map (world frame) when ``odometry.model`` is 'local_map', else None.

        Owned by this instance: read it from the thread that calls :meth:`step`.
        """
        self.update_model()
        return self._model.map if isinstance(self._model, LocalMapModel) else None

    @property
    def has_model(self) -> bool:
        """True once a scan has been accepted as the model."""
        self.update_model()
        return self._model.scan is not None

    # ----------------------------------------------------------------------------------------
    # The loop

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
        point_times : array_like, shape (N,), or PointTimes, optional
            The driver's per-point acquisition times (any unit, relative or absolute; a
            :class:`~kentreg_ros.core.odometry.deskew.PointTimes` also names the field, which
            tells the unit: see :func:`~kentreg_ros.core.odometry.deskew.sweep_times`). With
            ``odometry.deskew`` 'auto' or 'on' every point is moved to the stamp's time with
            the motion of the sweep (constant velocity, iterated with the registration). Points
            whose time is not finite are dropped and counted (``n_untimed``); times that are
            no plausible sweep leave the scan undeskewed, with one warning.

        Returns
        -------
        OdometryStep
            The pose and the health of the step. Never raises for a cloud that is merely
            unusable or a registration that fails: those are the ``rejected`` and
            ``fell_back`` healths.

        Raises
        ------
        InvalidInputError
            ``stamp_ns`` is not an integer (also a ``TypeError``).
        """
        stamp = _as_stamp(stamp_ns)
        pending = self._begin(points, stamp, frame_id)
        self.update_model()
        return self._step(pending, self._prepare_here(points, point_times, stamp))

    def _prepare_here(
        self, points: ArrayLike, point_times: ArrayLike | PointTimes | None, stamp: int
    ) -> Preparation:
        """The prepare stage in this thread, with the inputs the loop gives it now."""
        return prepare_input(
            points, point_times, stamp, self._config, self.twist_for_next, self._voxel_size_hint
        )

    @property
    def twist_for_next(self) -> FloatArray:
        """The twist the next scan is deskewed with: the last accepted motion's, or zero."""
        return self._motion.twist() if self._motion is not None else np.zeros(6)

    @property
    def voxel_size_hint(self) -> float:
        """Where the next scan's voxel-size search starts: the last prepared scan's size
        (0: search from the scan's own extent). Part of the prepare stage's inputs."""
        return self._voxel_size_hint

    def update_model(self) -> None:
        """Move the model on with the last step's scan, when :meth:`_step` deferred it.

        A pipeline defers the model's upkeep (the local map's insertion and target) past the
        publication of the step's pose and runs it while the next scan is prepared; the next
        step needs it, so :meth:`step` calls this first. Without a deferred update it does
        nothing.
        """
        deferred, self._deferred = self._deferred, None
        if deferred is not None:
            deferred()

    def _step(self, pending: _Pending, prep: Preparation, *, defer: bool = False) -> OdometryStep:
        """The stages after preparation: register, verify, deskew again, chain, model."""
        stamp = pending.stamp_ns
        # 1. predict: the last pose moved by the last accepted motion.
        T_world_pred = self._predict(stamp)
        pending.T_model_pred = invert_transform(self._model.T_world) @ T_world_pred
        # 2. the scan prepared once, deskewed with the predicted motion (prepare_input).
        pending.timings['preprocess'] = prep.ms
        sweep, scan = prep.sweep, prep.scan
        if sweep is not None and sweep.warning:
            self._warn_once(sweep.warning_kind, sweep.warning)
        if scan is None:
            rejected = f'Rejected the scan: {prep.rejected} The pose is the prediction.'
            outcome = Outcome(None, np.eye(4), float('nan'), Health.REJECTED, rejected)
            return self._finish(pending, T_world_pred, outcome, None, None, defer)
        self._voxel_size_hint = scan.voxel_size
        pending.timings |= {f'prepare.{k}': v for k, v in scan.timings.items() if k != 'total'}
        if self._model.scan is None:
            first = Outcome(
                None, np.eye(4), float('nan'), Health.FIRST, 'First scan: it becomes the model.'
            )
            return self._finish(pending, T_world_pred, first, scan, sweep, defer)
        assert sweep is not None  # a prepared scan has its sweep
        # 3. register from the prediction, and 4. verify: the only place a pose is chosen.
        t0 = time.perf_counter()
        gap = stamp - self._model.stamp_ns
        outcome = self._verifier.choose(
            scan, self._model.scan, pending.T_model_pred, gap, list(self._fits)
        )
        # 5. deskew again with the registered motion while that moves the points.
        if sweep.times is not None and outcome.accepted:
            twist = prep.twist if prep.twist is not None else self.twist_for_next
            scan, outcome = self._deskewer.iterate(sweep, scan, outcome, twist, self._model, gap)
        pending.timings['register'] = elapsed_ms(t0)
        # 6. chain the pose; the model moves on.
        T_world = T_world_pred if not outcome.accepted else self._model.T_world @ outcome.T
        return self._finish(pending, T_world, outcome, scan, sweep, defer)

    def _begin(self, points: ArrayLike, stamp: int, frame_id: str | None) -> _Pending:
        """Check the stamp's order and the frame; what is known of the step before it runs."""
        index = self.n_steps
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
        n_points = int(np.shape(points)[0]) if np.ndim(points) >= 1 else 0
        return _Pending(index, stamp, frame_id, np.eye(4), n_points, time.perf_counter())

    def _predict(self, stamp: int) -> FloatArray:
        if not self._poses:
            return self._initial_pose.copy()
        motion = self._motion if self._config.odometry.constant_velocity else None
        return predict(self._poses[-1], self._stamps[-1], stamp, motion)

    def _warn_once(self, kind: str, message: str) -> None:
        """Log ``message`` the first time a warning of its ``kind`` comes in this trajectory."""
        if kind not in self._warned:
            self._warned.add(kind)
            logger.warning(message)

    def _finish(
        self,
        pending: _Pending,
        T_world_curr: FloatArray,
        outcome: Outcome,
        scan: PreparedScan | None,
        sweep: Sweep | None,
        defer: bool = False,
    ) -> OdometryStep:
        """Append the pose, feed the motion and the fits, move the model (or, ``defer``, leave
        that to :meth:`update_model`), build the step."""
        model = self._model
        health = outcome.health
        if health == Health.FELL_BACK:
            logger.warning('Scan %d: %s', pending.index, outcome.message)
        elif health not in (Health.OK, Health.FIRST):
            log = logger.warning if health == Health.REJECTED else logger.info
            log('Scan %d: %s', pending.index, outcome.message)
        T_model_curr = invert_transform(model.T_world) @ T_world_curr
        if model.scan is None and scan is not None:
            covariance = model.cov.copy()  # the first pose is the origin of the frame
        else:
            if outcome.accepted and outcome.result is not None:
                cov_step = np.asarray(outcome.result.covariance, dtype=np.float64)
            else:
                cov_step = prediction_covariance(pending.T_model_pred)
            covariance = propagate_covariance(model.cov, model.T_world, T_model_curr, cov_step)
        if outcome.accepted and model.scan is not None:
            # Only accepted motions feed the prediction and the fits a step is judged by.
            self._motion = Motion(T_model_curr, pending.stamp_ns - model.stamp_ns)
            if np.isfinite(outcome.fit):
                self._fits.append(outcome.fit)
        model_index = model.index
        T_prev_curr = (
            invert_transform(self._poses[-1]) @ T_world_curr if self._poses else np.eye(4)
        )
        timed = sweep if sweep is not None and sweep.times is not None else None
        stamp, index = pending.stamp_ns, pending.index

        def move_model() -> None:
            model.update(scan, health, T_world_curr, covariance, stamp, index, timed)

        if defer:
            self._deferred = move_model
        else:
            move_model()
            pending.timings |= {f'model.{k}': v for k, v in model.timings.items()}
        self._poses.append(T_world_curr.copy())
        self._stamps.append(pending.stamp_ns)
        self._counts[health] += 1
        self._n_searched += int(outcome.searched)
        if outcome.result is not None:
            for stage in STAGE_TIMINGS:
                if stage in outcome.result.timings:
                    pending.timings[stage] = outcome.result.timings[stage]
        pending.timings['total'] = elapsed_ms(pending.t_start)
        return OdometryStep(
            index=pending.index,
            stamp_ns=pending.stamp_ns,
            frame_id=pending.frame_id,
            T_world_lidar=T_world_curr.copy(),
            T_prev_curr=T_prev_curr,
            T_model_pred=pending.T_model_pred,
            model_index=model_index,
            result=outcome.result,
            health=health,
            message=outcome.message,
            timings=pending.timings,
            n_points=pending.n_points,
            n_prepared=len(scan) if scan is not None and health != Health.REJECTED else 0,
            n_untimed=sweep.n_untimed if sweep is not None else 0,
            covariance=covariance,
            fit=outcome.fit if outcome.accepted else float('nan'),
            searched=outcome.searched,
            points=scan.points if scan is not None else None,
        )
