"""What the node publishes for each step: odometry, pose, path, TF and the map.

Every output carries the stamp of the scan it was computed from. The map holds the registered
points of every scan whose pose was registered (its prepared points: voxel centroids with
isolated returns and normal outliers removed, deskewed when deskewing ran), in ``odom_frame``,
one per ``map_voxel_size`` voxel, dropped beyond ``map_radius`` of the sensor (bounded memory);
it is published every ``map_period`` seconds, reliable and transient-local (depth 1), so a
viewer that subscribes later still receives the latest map. The worker thread owns it.
"""

from __future__ import annotations

import collections
import time
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time as TimeMsg
from geometry_msgs.msg import PoseStamped, TransformStamped
from nav_msgs.msg import Odometry as OdometryMsg
from nav_msgs.msg import Path
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from kentreg_ros.core import ACCEPTED, Health, OdometryStep, VoxelMap, invert_transform, log_so3
from kentreg_ros.io.params import NodeSettings
from kentreg_ros.io.pointcloud2 import array_to_pointcloud2, rclpy_factory
from kentreg_ros.ros.messages import (
    covariance_to_msg,
    pose_covariance_in_base,
    pose_to_msg,
    stamp_to_msg,
    transform_to_msg,
)

FloatArray = np.ndarray
#: Variance reported for unknown twist components (no motion measured yet).
UNKNOWN_VARIANCE = 1e6


class Outputs:
    """The node's publishers and what they need between steps (the path, the map).

    Parameters
    ----------
    node : rclpy.node.Node
    tf_broadcaster : tf2_ros.TransformBroadcaster or None
        None where tf2_ros is missing (a pip-only install): no /tf.
    path_length : int
        Poses the published path keeps.
    """

    def __init__(self, node: Node, tf_broadcaster: Any, path_length: int) -> None:
        self._tf_broadcaster = tf_broadcaster
        self.odom = node.create_publisher(OdometryMsg, 'odom', 10)
        self.pose = node.create_publisher(PoseStamped, 'pose', 10)
        self.path = node.create_publisher(Path, 'path', 1)
        # Latched: a viewer that starts later gets the latest map.
        map_qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        self.map = node.create_publisher(PointCloud2, '~/map', map_qos)
        self._cloud_factory = rclpy_factory(PointCloud2, PointField, Header, TimeMsg)
        self._poses: collections.deque[Any] = collections.deque(maxlen=path_length)
        self._map: VoxelMap | None = None
        self._map_published: float | None = None  # time.monotonic() of the last map

    def reset(self) -> None:
        """Forget the path and the map (a new trajectory)."""
        self._poses.clear()
        self._map = None

    def publish(
        self,
        step: OdometryStep,
        T_base_lidar: FloatArray,
        prev_stamp: int | None,
        settings: NodeSettings,
    ) -> None:
        """Odometry (pose, twist, covariances), pose, path and TF of ``step``, in
        ``odom_frame`` -> ``base_frame``; then the map when it is due."""
        if self._poses.maxlen != settings.path_length:
            self._poses = collections.deque(self._poses, maxlen=settings.path_length)
        T_bl = T_base_lidar
        T_odom_base = T_bl @ step.T_world_lidar @ invert_transform(T_bl)
        pose = pose_to_msg(T_odom_base)

        odom = OdometryMsg()
        odom.header.stamp = stamp_to_msg(step.stamp_ns)
        odom.header.frame_id = settings.odom_frame
        odom.child_frame_id = settings.base_frame
        odom.pose.pose = pose
        cov = pose_covariance_in_base(step.covariance, T_bl, T_odom_base)
        odom.pose.covariance = covariance_to_msg(cov)
        odom.twist.covariance = covariance_to_msg(self._twist(odom, step, T_bl, prev_stamp))
        self.odom.publish(odom)

        pose_msg = PoseStamped()
        pose_msg.header = odom.header
        pose_msg.pose = pose
        self.pose.publish(pose_msg)

        if settings.publish_path:
            self._poses.append(pose_msg)
            path = Path()
            path.header = odom.header
            path.poses = list(self._poses)
            self.path.publish(path)

        if settings.publish_tf and self._tf_broadcaster is not None:
            tf = TransformStamped()
            tf.header = odom.header
            tf.child_frame_id = settings.base_frame
            tf.transform = transform_to_msg(T_odom_base)
            self._tf_broadcaster.sendTransform(tf)
        self._update_map(step, T_bl, settings)

    @staticmethod
    def _twist(
        odom: Any, step: OdometryStep, T_bl: FloatArray, prev_stamp: int | None
    ) -> FloatArray:
        """Fill the twist of ``odom`` (base frame, from the motion since the previous step);
        return its covariance (:data:`UNKNOWN_VARIANCE` where nothing was measured)."""
        twist_cov = np.eye(6) * UNKNOWN_VARIANCE
        if prev_stamp is None or step.index == 0 or step.stamp_ns <= prev_stamp:
            return twist_cov
        dt = (step.stamp_ns - prev_stamp) * 1e-9
        # The current base pose in the previous base frame.
        T_motion = T_bl @ step.T_prev_curr @ invert_transform(T_bl)
        R = T_motion[:3, :3]
        v = R.T @ T_motion[:3, 3] / dt  # in the current base frame (child_frame_id)
        w = log_so3(R) / dt
        linear, angular = odom.twist.twist.linear, odom.twist.twist.angular
        linear.x, linear.y, linear.z = (float(x) for x in v)
        angular.x, angular.y, angular.z = (float(x) for x in w)
        if step.result is not None and step.ok:
            J = np.zeros((6, 6))
            J[:3, :3] = J[3:, 3:] = T_bl[:3, :3]
            twist_cov = J @ np.asarray(step.result.covariance) @ J.T / dt**2
        return twist_cov

    def _update_map(self, step: OdometryStep, T_bl: FloatArray, settings: NodeSettings) -> None:
        """Add the scan to the map when its pose was registered; publish the map when
        ``map_period`` has passed."""
        if settings.map_period <= 0.0:
            self._map = None
            return
        if self._map is None or self._map.voxel_size != settings.map_voxel_size:
            self._map = VoxelMap(settings.map_voxel_size)
        if step.points is not None and (step.health in ACCEPTED or step.health == Health.FIRST):
            # Sensor points -> odom frame: T_odom_lidar = T_base_lidar @ T_world_lidar.
            T = T_bl @ step.T_world_lidar
            self._map.insert(step.points @ T[:3, :3].T + T[:3, 3])
            self._map.crop(T[:3, 3], settings.map_radius)
        now = time.monotonic()
        due = self._map_published is None or now - self._map_published >= settings.map_period
        if due and len(self._map):
            msg = array_to_pointcloud2(
                self._map.points,
                frame_id=settings.odom_frame,
                stamp_ns=step.stamp_ns,
                factory=self._cloud_factory,
            )
            self.map.publish(msg)
            self._map_published = now
