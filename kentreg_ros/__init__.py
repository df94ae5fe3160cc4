"""kentreg_ros: LiDAR odometry with Kent (FB5) mixture registration."""

__version__ = '0.1.0'
