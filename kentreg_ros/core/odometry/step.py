"""What :meth:`kentreg_ros.core.odometry.loop.Odometry.step` reports: the step and its health,
or, for a scan that does not continue the trajectory, :class:`ScanOrderError`."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core.errors import KentRegError
from kentreg_ros.core.registration.result import RegistrationResult

FloatArray = NDArray[np.float64]


class Health(StrEnum):
    """What became of a scan, in order of severity."""

    #: It became the first model.
    FIRST = 'first'
    #: The registration from the prediction was used.
    OK = 'ok'
    #: That one was doubtful; the search found a better-fitting pose, which was used.
    RECOVERED = 'recovered'
    #: The estimate was used, but some direction is poorly constrained.
    DEGENERATE = 'degenerate'
    #: Distinct poses fit about equally; the one nearest the prediction was used.
    AMBIGUOUS = 'ambiguous'
    #: Nothing plausible fitted: the pose is the prediction.
    FELL_BACK = 'fell_back'
    #: The cloud is unusable: the pose is the prediction and the model is kept.
    REJECTED = 'rejected'

    @property
    def accepted(self) -> bool:
        """The pose comes from a registration (it feeds the velocity and the fit window)."""
        return self in ACCEPTED


class OutOfOrder(StrEnum):
    """How a scan fails to continue the trajectory."""

    #: Its stamp is the last scan's.
    REPEATED_STAMP = 'repeated_stamp'
    #: Its stamp is before the last scan's (a bag played again, a sensor restarted).
    EARLIER_STAMP = 'earlier_stamp'
    #: Its sensor frame is not the last scan's.
    OTHER_FRAME = 'other_frame'


class ScanOrderError(KentRegError, ValueError):
    """A scan that does not continue the trajectory; the odometry did not take it.

    Attributes
    ----------
    kind : OutOfOrder
        What is wrong: a repeated or earlier stamp, or another sensor frame. A caller that
        follows a live sensor drops a repeated stamp, and restarts the trajectory
        (:meth:`Odometry.reset`) for the others.
    """

    def __init__(self, message: str, kind: OutOfOrder) -> None:
        super().__init__(message)
        self.kind = kind


#: Every health value of an :class:`OdometryStep`, in order of severity.
HEALTHS = tuple(Health)
#: Healths whose pose comes from a registration (they feed the velocity and the fit window).
ACCEPTED = (Health.OK, Health.RECOVERED, Health.DEGENERATE, Health.AMBIGUOUS)


@dataclass(frozen=True, eq=False)
class OdometryStep:
    """What :meth:`Odometry.step` did with one scan.

    Attributes
    ----------
    index : int
        0-based number of the scan since the start (or the last :meth:`Odometry.reset`).
    stamp_ns : int
        Acquisition time of the scan, integer nanoseconds.
    frame_id : str or None
        Sensor frame of the scan, as given.
    T_world_lidar : ndarray, shape (4, 4)
        Pose of the scan in the odometry (world) frame.
    T_prev_curr : ndarray, shape (4, 4)
        Motion since the previous scan's pose: maps points of this scan into the previous
        scan's frame (identity for the first scan).
    T_model_pred : ndarray, shape (4, 4)
        The prediction in the model's frame, the ``init`` given to the registration.
    model_index : int
        Index of the scan used as the model (target); ``-1`` when there was none.
    result : RegistrationResult or None
        The registration result; None for the first scan, a rejected scan, or a registration
        that raised.
    health : Health
        What became of the scan (see :class:`Health`).
    fit : float
        Balanced fit of the pose used (NaN without a registration or in paper mode).
    searched : bool
        The start-free search ran for this step.
    points : ndarray, shape (M, 3) or None
        The scan's prepared points (downsampled, isolated returns and normal outliers
        removed, deskewed when deskewing ran) in its sensor frame: the points that were
        registered. None for a rejected scan. Shared with the odometry's model: do not modify.
    message : str
        Human-readable explanation of the health.
    timings : dict of str to float
        Milliseconds: ``'preprocess'`` (the prepare stage, wherever it ran), the preparation's
        stages as ``'prepare.<stage>'`` (``downsample``, ``neighbours``, ``normals``,
        ``outliers``, ``clustering``: :attr:`PreparedScan.timings`), ``'register'`` (the
        registrations, the search and the deskewing rounds) when it ran, the model's upkeep as
        ``'model.<part>'`` (the previous scan's ``target_tree``; the local map's
        ``map_insert``, ``map_frame`` and ``map_tree``), the registration stages
        (``'rotation'``, ``'translation'``, ``'refine'``, ``'search'``) of the result used,
        and ``'total'`` for the whole step.
    n_points : int
        Points given.
    n_prepared : int
        Points kept after preprocessing (0 if rejected).
    n_untimed : int
        Points dropped before deskewing because their time was not finite.
    covariance : ndarray, shape (6, 6)
        First-order covariance of ``T_world_lidar`` in the order (x, y, z, rot_x, rot_y, rot_z)
        of nav_msgs/Odometry: position error in world axes, rotation error about world axes
        (see :func:`propagate_covariance`). The registration covariances are chained; a
        predicted step adds an isotropic uncertainty as large as the predicted motion (at least
        :data:`PREDICTION_MIN_STD`). It grows without bound, as odometry drift does.
    """

    index: int
    stamp_ns: int
    frame_id: str | None
    T_world_lidar: FloatArray
    T_prev_curr: FloatArray
    T_model_pred: FloatArray
    model_index: int
    result: RegistrationResult | None
    health: Health
    message: str
    timings: dict[str, float] = field(default_factory=dict)
    n_points: int = 0
    n_prepared: int = 0
    n_untimed: int = 0
    covariance: FloatArray = field(default_factory=lambda: np.zeros((6, 6)))
    fit: float = float('nan')
    searched: bool = False
    points: FloatArray | None = None

    @property
    def ok(self) -> bool:
        """True when the pose comes from a registration (or is the first pose)."""
        return self.health == Health.FIRST or self.health in ACCEPTED

    @property
    def stamp(self) -> float:
        """Acquisition time in seconds (float; use ``stamp_ns`` for exact values)."""
        return self.stamp_ns * 1e-9
