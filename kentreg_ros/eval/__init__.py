"""What judges a run: pair errors and failures, RPE/ATE (:mod:`~kentreg_ros.eval.metrics`), the
KITTI segment metric (:mod:`~kentreg_ros.eval.kitti`) and plots (:mod:`~kentreg_ros.eval.plotting`,
matplotlib imported only when a plot is drawn). Never imports rclpy.
"""
