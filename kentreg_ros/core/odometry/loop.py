"""Scan-to-model LiDAR odometry: register each scan against the model, chain ``T_world_lidar``.

:meth:`Odometry.step` runs the stages in this order, each in one module::

    predict    T_world_pred = T_world_last @ motion  (the last *accepted* motion, or none)
                                                                              motion.py
    prepare    the scan once, deskewed with that motion (crop, voxels, normals, clusters),
               by the preparer the caller chose (here, or ahead in a worker)  preparation.py
    register   source = the scan, target = the model, init = the prediction
    verify     a doubtful step (failed, too fast, fitting clearly worse than the last accepted
               ones) is searched again without a start and the best-fitting plausible pose is
               chosen, the one nearest the prediction among those fitting about equally;
               nothing plausible that fits -> fall back to the prediction    verify.py
    deskew     again with the registered motion, registering again, while that matters
                                                                              deskew.py
    chain      T_world_curr = T_world_model @ T_model_curr, with its covariance
                                                                              motion.py
    model      the previous scan, or the local map of the accepted scans, moves on
                                                                              models.py

A step that fell back keeps the predicted pose and is flagged; it never feeds the motion, so
one bad step cannot be repeated by the next prediction (a runaway). A cloud that cannot be
used at all (:class:`~kentreg_ros.core.errors.InvalidPointCloudError`, e.g. too few points) is
flagged ``rejected``, gets the predicted pose, and the model is kept for the next scan. A scan
that does not continue the trajectory (its stamp not after the last one, another sensor frame)
is refused with :class:`~kentreg_ros.core.odometry.step.ScanOrderError` before anything changes.

:class:`Odometry` keeps no global state; the ROS node runs one instance in one worker thread.
An instance is not meant to be shared between threads.
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kentreg_ros.core import kernels
from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.errors import InvalidInputError
from kentreg_ros.core.geometry import check_transform, invert_transform
from kentreg_ros.core.odometry.deskew import Deskewed, Deskewer, PointTimes, Sweep, twist_of
from kentreg_ros.core.odometry.localmap import LocalMap
from kentreg_ros.core.odometry.models import (
    LocalMapModel,
    ModelStrategy,
    PosedScan,
    PreviousScanModel,
)
from kentreg_ros.core.odometry.motion import Chained, Motion, chain, predict
from kentreg_ros.core.odometry.preparation import (
    InThreadPreparer,
    Preparation,
    PrepareInputs,
    Preparer,
    RawScan,
)
from kentreg_ros.core.odometry.step import (
    HEALTHS,
    Health,
    OdometryStep,
    OutOfOrder,
    ScanOrderError,
)
from kentreg_ros.core.odometry.verify import Outcome, Verifier
from kentreg_ros.core.odometry_config import Model
from kentreg_ros.core.stopwatch import Stopwatch

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: Registration stages whose times a step reports.
STAGE_TIMINGS = ('rotation', 'translation', 'refine', 'search')


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
    preparer : Preparer, optional
        Where the prepare stage runs (default :class:`InThreadPreparer`: in the thread that
        steps). A preparer that works ahead, e.g. in a worker process
        (:class:`kentreg_ros.runtime.ProcessPreparer`), gives the same poses; the caller owns
        it (and closes it).

    Notes
    -----
    Every scan is preprocessed once: the :class:`PreparedScan` of the new scan is the source
    of this registration and the target of the next one. With automatic voxel sizing the search
    for each scan starts at the previous scan's voxel size.

    The constant-velocity prediction repeats the last accepted motion, stretched by the ratio
    of the time gaps when scans arrive irregularly (e.g. a dropped scan in the ROS node; see
    :func:`~kentreg_ros.core.odometry.motion.predict`).

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

    # The trajectory so far (set by reset).
    _model: ModelStrategy
    _poses: deque[FloatArray]
    _stamps: deque[int]
    _frame_id: str | None
    _motion: Motion | None  # the last accepted motion
    _fits: deque[float]  # the fits of the last accepted steps
    _voxel_size_hint: float
    _counts: dict[Health, int]
    _n_searched: int
    _warned: set[str]
    _next_inputs: PrepareInputs  # what the next scan is prepared with (set by _expect)

    def __init__(
        self,
        config: KentRegConfig | None = None,
        *,
        initial_pose: ArrayLike | None = None,
        max_history: int | None = None,
        preparer: Preparer | None = None,
    ) -> None:
        if max_history is not None and (isinstance(max_history, bool) or max_history < 2):
            raise InvalidInputError(f'Expected `max_history` >= 2 or None, got {max_history!r}.')
        self._max_history = max_history
        self._initial_pose = (
            np.eye(4) if initial_pose is None else check_transform(initial_pose, 'initial_pose')
        )
        self._preparer: Preparer = preparer if preparer is not None else InThreadPreparer()
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
            Acquisition time, integer nanoseconds (e.g. the message header stamp), after the
            last scan's.
        frame_id : str, optional
            Sensor frame of the scan: the same as the last scan's (None: not checked).
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
        ScanOrderError
            The stamp is not after the last scan's, or the frame is another (``kind`` says
            which); nothing changed.
        InvalidInputError
            ``stamp_ns`` is not an integer (also a ``TypeError``).
        """
        watch = Stopwatch()
        stamp = self._check_order(stamp_ns, frame_id)
        index, model, model_index = self.n_steps, self._model, self._model.index
        # predict: the last pose moved by the last accepted motion, and in the model's frame.
        T_world_pred = self._predict(stamp)
        T_model_pred = invert_transform(model.T_world) @ T_world_pred
        # prepare: the scan once, deskewed with that motion, by the preparer the caller chose.
        prep = self._preparer.prepare(RawScan(points, point_times, stamp), self._next_inputs)
        watch.add('preprocess', prep.ms)
        watch.merge(prep.timings, 'prepare.')
        # register from the prediction, verify (the one place a pose is chosen), deskew again.
        done = self._register(prep, model, T_model_pred, stamp, watch)
        outcome, scan = done.outcome, done.scan
        own = outcome.result.covariance if outcome.health.accepted and outcome.result else None
        outcome = outcome.with_anchor(model.anchor)  # the model pose's error is the step's too
        # chain: the pose in the world with its covariance; what the next scans learn from it.
        pose = chain(model.T_world, model.cov, outcome, T_world_pred, T_model_pred)
        T_prev_curr = self._learn(index, stamp, frame_id, prep, outcome, pose)
        self._expect()  # known now: a preparer ahead can go on
        # model: the previous scan, or the local map of the accepted scans, moves on.
        posed = PosedScan(
            scan, outcome.health, pose, stamp, index, prep.timed_sweep, done.first, own
        )
        model.update(posed, watch)
        watch.merge(outcome.stage_timings(STAGE_TIMINGS))
        watch.add('total', watch.elapsed_ms())
        return OdometryStep(
            index=index,
            stamp_ns=stamp,
            frame_id=frame_id,
            T_world_lidar=pose.T_world.copy(),
            T_prev_curr=T_prev_curr,
            T_model_pred=T_model_pred,
            model_index=model_index,
            result=outcome.result,
            health=outcome.health,
            message=outcome.message,
            timings=watch.as_dict(),
            n_points=int(np.shape(points)[0]) if np.ndim(points) >= 1 else 0,
            n_prepared=len(scan) if scan is not None else 0,
            n_untimed=prep.sweep.n_untimed if prep.sweep is not None else 0,
            covariance=pose.covariance,
            fit=outcome.fit if outcome.health.accepted else float('nan'),
            searched=outcome.searched,
            points=scan.points if scan is not None else None,
        )

    def _register(
        self,
        prep: Preparation,
        model: ModelStrategy,
        T_model_pred: FloatArray,
        stamp: int,
        watch: Stopwatch,
    ) -> Deskewed:
        """The step's pose in the model frame (an :class:`Outcome`) and its scan, deskewed again
        when that mattered (the model's first scan with it)."""
        if prep.scan is None:
            return Deskewed(None, Outcome.rejected(prep.rejected))
        if model.scan is None:
            return Deskewed(prep.scan, Outcome.first())
        gap = stamp - model.stamp_ns
        with watch('register'):
            fits = list(self._fits)
            outcome = self._verifier.choose(prep.scan, model.scan, T_model_pred, gap, fits)
            sweep = prep.timed_sweep
            if sweep is None or not outcome.health.accepted:
                return Deskewed(prep.scan, outcome)
            assert prep.twist is not None  # a sweep with times was deskewed with it
            return self._deskewer.iterate(sweep, prep.scan, outcome, prep.twist, model, gap)

    def _learn(
        self,
        index: int,
        stamp: int,
        frame_id: str | None,
        prep: Preparation,
        outcome: Outcome,
        pose: Chained,
    ) -> FloatArray:
        """Keep the step: its pose and stamp; an accepted motion for the next prediction (with
        its twist, which the next sweeps are deskewed with) and its fit for the next steps'
        doubt; the prepared scan's voxel size, where the next search starts. Returns the motion
        since the last pose, ``T_prev_curr``."""
        self._log(index, prep.sweep, outcome)
        if outcome.health.accepted:
            gap = stamp - self._model.stamp_ns
            self._motion = Motion(pose.T_model, gap, twist_of(pose.T_model, gap * 1e-9))
            if np.isfinite(outcome.fit):
                self._fits.append(outcome.fit)
        if prep.scan is not None:
            self._voxel_size_hint = prep.scan.voxel_size
        last = self._poses[-1] if self._poses else None
        self._poses.append(pose.T_world.copy())
        self._stamps.append(stamp)
        self._frame_id = frame_id if frame_id is not None else self._frame_id
        self._counts[outcome.health] += 1
        self._n_searched += int(outcome.searched)
        return invert_transform(last) @ pose.T_world if last is not None else np.eye(4)

    def _check_order(self, stamp_ns: int, frame_id: str | None) -> int:
        """The stamp as an integer, after checking that the scan continues the trajectory."""
        if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, int | np.integer):
            raise InvalidInputError(
                f'Expected `stamp_ns` to be an integer number of nanoseconds, got {stamp_ns!r}.'
            )
        stamp = int(stamp_ns)
        last = self._stamps[-1] if self._stamps else None
        if last is not None and stamp == last:
            raise ScanOrderError(
                f"The scan repeats the last scan's stamp ({stamp} ns).", OutOfOrder.REPEATED_STAMP
            )
        if last is not None and stamp < last:
            raise ScanOrderError(
                f'Time went backwards by {(last - stamp) * 1e-9:.3f} s: the scan is stamped '
                f'{stamp} ns, the last one {last} ns.',
                OutOfOrder.EARLIER_STAMP,
            )
        if frame_id is not None and self._frame_id is not None and frame_id != self._frame_id:
            raise ScanOrderError(
                f'The sensor frame changed from {self._frame_id!r} to {frame_id!r}.',
                OutOfOrder.OTHER_FRAME,
            )
        return stamp

    def _predict(self, stamp: int) -> FloatArray:
        if not self._poses:
            return self._initial_pose.copy()
        motion = self._motion if self._config.odometry.constant_velocity else None
        return predict(self._poses[-1], self._stamps[-1], stamp, motion)

    def _log(self, index: int, sweep: Sweep | None, outcome: Outcome) -> None:
        """Say what became of the scan: a fall-back or a rejection as a warning, the other
        healths but ok and first as information; a sweep's warning once per trajectory."""
        if sweep is not None and sweep.warning and sweep.warning_kind not in self._warned:
            self._warned.add(sweep.warning_kind)
            logger.warning(sweep.warning)
        health = outcome.health
        if health in (Health.FELL_BACK, Health.REJECTED):
            logger.warning('Scan %d: %s', index, outcome.message)
        elif health not in (Health.OK, Health.FIRST):
            logger.info('Scan %d: %s', index, outcome.message)

    def _expect(self) -> None:
        """Work out what the next scan is prepared with besides itself, once it is known (after
        a step, a reset, a new configuration): the configuration, the twist of the last accepted
        motion (zero before one) and the last prepared scan's voxel size; keep it for that
        scan's step and tell the preparer (one working ahead can go on)."""
        twist = self._motion.twist if self._motion is not None else np.zeros(6)
        self._next_inputs = PrepareInputs(self._config, twist, self._voxel_size_hint)
        self._preparer.expect(self._next_inputs)

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
        self._model = self._new_model(PreviousScanModel(self._initial_pose))
        self._voxel_size_hint = 0.0
        self._poses = deque(maxlen=self._max_history)
        self._stamps = deque(maxlen=self._max_history)
        self._frame_id = None
        self._counts = dict.fromkeys(HEALTHS, 0)
        self._motion = None
        self._fits = deque(maxlen=self._config.odometry.fit_window)
        self._n_searched = 0
        self._warned = set()
        self._expect()

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
        previous = self._config.preprocess
        self._set_config(config)
        self._fits = deque(self._fits, maxlen=config.odometry.fit_window)
        if config.preprocess != previous:
            self._voxel_size_hint = 0.0  # the previous size was searched for other settings
        self._model = self._new_model(self._model)
        self._expect()

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
        return self._model.map if isinstance(self._model, LocalMapModel) else None

    @property
    def has_model(self) -> bool:
        """True once a scan has been accepted as the model."""
        return self._model.scan is not None
