"""Point clouds in and out: PointCloud2 <-> numpy, scan files, pose files, bags, parameter files.

Never imports rclpy. :mod:`kentreg_ros.io.pointcloud2`, :mod:`~kentreg_ros.io.scanfiles`,
:mod:`~kentreg_ros.io.poses`, :mod:`~kentreg_ros.io.params` and :mod:`~kentreg_ros.io.paramfile`
need only numpy/scipy/PyYAML; the bag names (``open_scan_source``, ``BagWriter``, ...) load
rosbags on first use, so a ROS node without rosbags can still import this package.
"""

from typing import TYPE_CHECKING, Any

from kentreg_ros.io.errors import BagError, PoseFileError, ScanFileError
from kentreg_ros.io.paramfile import (
    dump_config,
    effective_config,
    load_config,
    parameters_from_yaml,
)
from kentreg_ros.io.params import NODE_NAME
from kentreg_ros.io.pointcloud2 import (
    CloudArrays,
    MessageFactory,
    array_to_pointcloud2,
    pointcloud2_to_array,
    rclpy_factory,
    rosbags_factory,
)
from kentreg_ros.io.poses import (
    Trajectory,
    pose_file_beside,
    read_poses,
    write_kitti,
    write_tum,
)
from kentreg_ros.io.scanfiles import list_scans, read_scan, write_pcd
from kentreg_ros.io.yamlfile import parse_overrides

if TYPE_CHECKING:
    from kentreg_ros.io.bags import BagScanSource, bag_topics, is_bag
    from kentreg_ros.io.bagwriter import BagWriter, write_odometry_mcap
    from kentreg_ros.io.recordings import Recording, open_recording, read_ground_truth
    from kentreg_ros.io.sources import FilesScanSource, Scan, ScanSource, open_scan_source

#: The names loaded on first use, and the module each comes from.
_LAZY = {
    'BagScanSource': 'kentreg_ros.io.bags',
    'bag_topics': 'kentreg_ros.io.bags',
    'is_bag': 'kentreg_ros.io.bags',
    'FilesScanSource': 'kentreg_ros.io.sources',
    'Scan': 'kentreg_ros.io.sources',
    'ScanSource': 'kentreg_ros.io.sources',
    'open_scan_source': 'kentreg_ros.io.sources',
    'Recording': 'kentreg_ros.io.recordings',
    'open_recording': 'kentreg_ros.io.recordings',
    'read_ground_truth': 'kentreg_ros.io.recordings',
    'BagWriter': 'kentreg_ros.io.bagwriter',
    'write_odometry_mcap': 'kentreg_ros.io.bagwriter',
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')


__all__ = [
    'NODE_NAME',
    'BagError',
    'BagScanSource',
    'BagWriter',
    'CloudArrays',
    'FilesScanSource',
    'MessageFactory',
    'PoseFileError',
    'Recording',
    'Scan',
    'ScanFileError',
    'ScanSource',
    'Trajectory',
    'array_to_pointcloud2',
    'bag_topics',
    'dump_config',
    'effective_config',
    'is_bag',
    'list_scans',
    'load_config',
    'open_recording',
    'open_scan_source',
    'parameters_from_yaml',
    'parse_overrides',
    'pointcloud2_to_array',
    'pose_file_beside',
    'rclpy_factory',
    'read_ground_truth',
    'read_poses',
    'read_scan',
    'rosbags_factory',
    'write_kitti',
    'write_odometry_mcap',
    'write_pcd',
    'write_tum',
]
