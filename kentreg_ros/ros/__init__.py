"""Everything that talks ROS 2 through rclpy: the node, its parameters, message conversions, play.

- :mod:`kentreg_ros.ros.node`: ``kentreg_node``, live odometry from PointCloud2 messages (the
  ROS wiring); :mod:`kentreg_ros.ros.worker`: its queue and the thread that steps the odometry
  and publishes.
- :mod:`kentreg_ros.ros.parameters`: the node's parameters (:mod:`kentreg_ros.io.params`) through
  rclpy; :mod:`kentreg_ros.ros.frames`: its moving frame, the sensor mount and TF;
  :mod:`kentreg_ros.ros.outputs`: what it publishes (and the map of the run);
  :mod:`kentreg_ros.ros.services`: ``~/save_map`` and ``initialpose``;
  :mod:`kentreg_ros.ros.diagnostics`: its counters and status; :mod:`kentreg_ros.ros.logbridge`:
  the core's logs to /rosout; :mod:`kentreg_ros.ros.usage`: ``kentreg_node --help``.
- :mod:`kentreg_ros.ros.messages`: poses, stamps and covariances to and from ROS messages.
- :mod:`kentreg_ros.ros.play`: ``kentreg_play``, publishes the scans of a bag or a folder
  (:mod:`kentreg_ros.ros.playopts`: its command line, timing and summary).

No other package of kentreg_ros imports rclpy or a ROS message package (the PointCloud2 codec in
:mod:`kentreg_ros.io.pointcloud2` works on rclpy and rosbags messages without importing either).
This ``__init__`` imports nothing.
"""
