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
from kentreg_ros.core.fields import (
    Section,
    coerce_value,
    flatten_keys,
    iter_fields,
    nest_keys,
    plain_value,
    validate_value,
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
    ImplausibleTimesError,
    LocalMap,
    Odometry,
    OdometryStep,
    PipelinedOdometry,
    PipelineError,
    PointTimes,
    VoxelMap,
    sweep_times,
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
    'ConfigError',
    'DegenerateSceneError',
    'Health',
    'ImplausibleTimesError',
    'InvalidInputError',
    'InvalidPointCloudError',
    'KentRegConfig',
    'KentRegError',
    'LocalMap',
    'Mode',
    'Model',
    'Odometry',
    'OdometryStep',
    'PipelineError',
    'PipelinedOdometry',
    'PointTimes',
    'PreparedScan',
    'RegistrationResult',
    'Section',
    'Status',
    'VoxelMap',
    'as_points',
    'check_transform',
    'choose_voxel_size',
    'coerce_value',
    'count_voxels',
    'drop_nonfinite',
    'exp_so3',
    'flatten_keys',
    'hat',
    'invert_transform',
    'iter_fields',
    'kernels',
    'log_so3',
    'make_transform',
    'nest_keys',
    'plain_value',
    'prepare_scan',
    'project_to_so3',
    'register',
    'rotation_angle',
    'sweep_times',
    'validate_value',
    'voxel_downsample',
]
