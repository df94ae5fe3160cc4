"""The names of what kentreg publishes: one place for the node, the replay's MCAP and RViz.

The node's outputs are relative names under one prefix (``kentreg/...``), so they follow the
node's namespace and never collide with a robot's own ``/odom`` (wheel odometry) or ``/path``;
in the root namespace they resolve to ``/kentreg/...``, the names the replay writes into its
MCAP and ``rviz/kentreg.rviz`` shows. Diagnostics go to ``/diagnostics``, where
diagnostic_aggregator and rqt_robot_monitor look.
"""

from __future__ import annotations

#: Prefix of every output topic.
PREFIX = 'kentreg'
#: The input (subscribed; remap it to the sensor's topic).
POINTS = 'points'
#: nav_msgs/Odometry: the pose of the moving frame in the odometry frame, twist, covariances.
ODOMETRY = f'{PREFIX}/odometry'
#: geometry_msgs/PoseStamped: the same pose.
POSE = f'{PREFIX}/pose'
#: nav_msgs/Path: the recent poses.
PATH = f'{PREFIX}/path'
#: sensor_msgs/PointCloud2 per scan: its registered (deskewed, prepared) points.
CLOUD_REGISTERED = f'{PREFIX}/cloud_registered'
#: sensor_msgs/PointCloud2: the map around the sensor (transient-local).
MAP = f'{PREFIX}/map'
#: diagnostic_msgs/DiagnosticArray.
DIAGNOSTICS = '/diagnostics'
#: geometry_msgs/PoseWithCovarianceStamped (subscribed): what RViz's "2D Pose Estimate" sends.
INITIAL_POSE = 'initialpose'
#: Localization in a saved map (``map_file``), private to the node: its pose in ``map_frame``
#: (geometry_msgs/PoseWithCovarianceStamped), its state (std_msgs/String, transient-local) and
#: the search from no start (std_srvs/Trigger).
LOCALIZATION_POSE = '~/pose'
LOCALIZATION_STATE = '~/state'
RELOCALIZE = '~/relocalize'
#: tf2_msgs/TFMessage topics.
TF = '/tf'
TF_STATIC = '/tf_static'


def absolute(name: str) -> str:
    """``name`` as it resolves in the root namespace (``kentreg/odometry`` ->
    ``/kentreg/odometry``)."""
    return name if name.startswith('/') else f'/{name}'
