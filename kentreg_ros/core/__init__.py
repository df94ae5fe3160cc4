"""Registration core of kentreg_ros: numpy/scipy only, never imports rclpy or rosbags."""

from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.errors import (
    ConfigError,
    DegenerateSceneError,
    InvalidPointCloudError,
    KentRegError,
)
from kentreg_ros.core.preprocess import as_points, drop_nonfinite, voxel_downsample
from kentreg_ros.core.registration import (
    PreparedScan,
    RegistrationResult,
    prepare_scan,
    register,
)

__all__ = [
    'ConfigError',
    'DegenerateSceneError',
    'InvalidPointCloudError',
    'KentRegConfig',
    'KentRegError',
    'PreparedScan',
    'RegistrationResult',
    'as_points',
    'drop_nonfinite',
    'prepare_scan',
    'register',
    'voxel_downsample',
]
