"""The odometry: the loop over stages (:mod:`.loop`, :mod:`.stages`), its report (:mod:`.step`),
the local map, deskewing and the chained covariance."""

from kentreg_ros.core.odometry.deskew import ImplausibleTimesError, PointTimes, sweep_times
from kentreg_ros.core.odometry.localmap import LocalMap, VoxelMap
from kentreg_ros.core.odometry.loop import Odometry
from kentreg_ros.core.odometry.pipeline import PipelinedOdometry, PipelineError
from kentreg_ros.core.odometry.step import ACCEPTED, HEALTHS, Health, OdometryStep

__all__ = [
    'ACCEPTED',
    'HEALTHS',
    'Health',
    'ImplausibleTimesError',
    'LocalMap',
    'Odometry',
    'OdometryStep',
    'PipelineError',
    'PipelinedOdometry',
    'PointTimes',
    'VoxelMap',
    'sweep_times',
]
