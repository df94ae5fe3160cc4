"""The odometry: the loop (:mod:`.loop`) over its stages, one module each: predict and chain
(:mod:`.motion`), prepare (:mod:`.preparation`), register and verify (:mod:`.verify`), deskew
(:mod:`.deskew`), the model (:mod:`.models`, the local map :mod:`.localmap`); its report
(:mod:`.step`) and the covariances of a chained pose and of a step's twist (:mod:`.covariance`)."""

from kentreg_ros.core.odometry.covariance import twist_covariance
from kentreg_ros.core.odometry.deskew import (
    ImplausibleTimesError,
    PointTimes,
    Sweep,
    read_sweep,
    sweep_times,
)
from kentreg_ros.core.odometry.localmap import LocalMap, VoxelMap
from kentreg_ros.core.odometry.loop import Odometry
from kentreg_ros.core.odometry.preparation import (
    InThreadPreparer,
    Preparation,
    PrepareInputs,
    Preparer,
    RawScan,
    prepare_swept,
)
from kentreg_ros.core.odometry.step import (
    ACCEPTED,
    HEALTHS,
    Health,
    OdometryStep,
    OutOfOrder,
    ScanOrderError,
)

__all__ = [
    'ACCEPTED',
    'HEALTHS',
    'Health',
    'ImplausibleTimesError',
    'InThreadPreparer',
    'LocalMap',
    'Odometry',
    'OdometryStep',
    'OutOfOrder',
    'PointTimes',
    'PrepareInputs',
    'Preparation',
    'Preparer',
    'RawScan',
    'ScanOrderError',
    'Sweep',
    'VoxelMap',
    'prepare_swept',
    'read_sweep',
    'sweep_times',
    'twist_covariance',
]
