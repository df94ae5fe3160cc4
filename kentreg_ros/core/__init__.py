"""Registration core of kentreg_ros: numpy/scipy only, never imports rclpy or rosbags.

Everything a command line, the node, the evaluation or a benchmark needs from the core is
importable from here; the modules behind these names may move.
"""

from kentreg_ros.core import kernels
from kentreg_ros.core.config import KentRegConfig, Mode, Model
from kentreg_ros.core.errors import (
    ConfigError,
    DegenerateSceneError,
    InvalidInputError,
    InvalidPointCloudError,
    KentRegError,
)
from kentreg_ros.core.geometry import (
    check_transform,
    exp_so3,
    hat,
    invert_transform,
    log_so3,
    make_transform,
    project_to_so3,
    rotation_angle,
)
from kentreg_ros.core.odometry import (
    ACCEPTED,
    HEALTHS,
    Health,
    LocalMap,
    Odometry,
    OdometryStep,
    PipelinedOdometry,
    PipelineError,
    PointTimes,
    VoxelMap,
)
from kentreg_ros.core.registration import RegistrationResult, Status, register
from kentreg_ros.core.scan import PreparedScan, prepare_scan
from kentreg_ros.core.scan.voxels import (
    as_points,
    choose_voxel_size,
    count_voxels,
    drop_nonfinite,
    voxel_downsample,
)

__all__ = [
    'ACCEPTED',
    'HEALTHS',
    'Health',
    'Mode',
    'Model',
    'PointTimes',
    'Status',
    'ConfigError',
    'DegenerateSceneError',
    'InvalidInputError',
    'InvalidPointCloudError',
    'KentRegConfig',
    'KentRegError',
    'LocalMap',
    'Odometry',
    'OdometryStep',
    'PipelineError',
    'PipelinedOdometry',
    'PreparedScan',
    'RegistrationResult',
    'VoxelMap',
    'as_points',
    'check_transform',
    'choose_voxel_size',
    'count_voxels',
    'drop_nonfinite',
    'exp_so3',
    'hat',
    'invert_transform',
    'kernels',
    'log_so3',
    'make_transform',
    'prepare_scan',
    'project_to_so3',
    'register',
    'rotation_angle',
    'voxel_downsample',
]
