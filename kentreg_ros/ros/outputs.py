"""What the node publishes for each step: odometry, pose, path, TF, the registered cloud, and
the map of the run.

Every output carries the stamp of the scan it was computed from, under one prefix
(:mod:`kentreg_ros.io.names`: ``kentreg/odometry``, ``kentreg/pose``, ``kentreg/path``,
``kentreg/cloud_registered``, ``kentreg/map``), so none collides with a robot's ``/odom``.

Frames. The odometry core estimates ``T_world_lidar`` (its world: the first scan's sensor
pose). The node publishes the moving frame in ``odom_frame``::

    T_odom_moving = T_odom_world @ T_world_lidar @ inv(T_moving_lidar)

``T_odom_world`` is the *anchor*: ``T_moving_lidar`` at the start of a trajectory (odom is
where the moving frame started, REP-105), moved by an ``initialpose`` message
(:meth:`Outputs.request_pose`) so that the pose at that moment becomes the one given. The map and
the trajectory of the run are kept in the core's world frame and moved by the anchor when they
are published or saved: an initial pose moves the whole run rigidly, map and path alike.

The map (:class:`~kentreg_ros.io.runmap.RunMap`, the replay's too) holds the registered points
of every accepted scan; :meth:`Outputs.publish_map` sends the part within ``map_radius`` of the
sensor every ``map_period`` seconds, reliable and transient-local (depth 1), so a viewer that
subscribes later still receives the latest; ``~/save_map`` writes all of it
(:meth:`Outputs.run_snapshot`). The path goes out on the same timer, every
:data:`PATH_PERIOD_S` (:meth:`Outputs.publish_path`), not with every scan: it carries every
pose, so its cost grows with the run.

Threads: :meth:`Outputs.publish` runs on the worker; :meth:`Outputs.publish_map`,
:meth:`Outputs.publish_path`, :meth:`Outputs.run_snapshot` and :meth:`Outputs.request_pose` on
the executor. What they share (the anchor, the latest pose, the pending initial pose, the path's
poses) is under one lock; the map and the trajectory log have their own.
"""

from __future__ import annotations

import collections
import contextlib
import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time as TimeMsg
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry as OdometryMsg
from nav_msgs.msg import Path
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from rclpy.qos_overriding_options import InvalidQosOverridesError, QoSOverridingOptions
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from kentreg_ros.core import OdometryStep, invert_transform, log_so3, twist_covariance
from kentreg_ros.io import names
from kentreg_ros.io.params import NodeSettings, QosReliability, RegisteredCloud
from kentreg_ros.io.pointcloud2 import array_to_pointcloud2, rclpy_factory
from kentreg_ros.io.runmap import RunMap, TrajectoryLog
from kentreg_ros.ros.frames import Frames
from kentreg_ros.ros.messages import (
    covariance_to_msg,
    pose_covariance_in_base,
    pose_to_msg,
    stamp_to_msg,
)
from kentreg_ros.ros.parameters import StartupError

FloatArray = np.ndarray
#: Variance reported for unknown twist components (no motion measured yet).
UNKNOWN_VARIANCE = 1e6
#: Seconds between the map timer's looks at whether ``map_period`` has passed (a cheap check;
#: the map itself goes out every ``map_period``).
MAP_TICK_S = 0.1
#: Seconds between publications of the path (on the map's timer, off the worker). A Path
#: message carries every pose of the last ``path_length``, and rclpy builds it at ~10 us a
#: pose (measured: 9.9 ms of CPU per publication at 1000 poses, 0.7 ms at 50): sent with every
#: scan it took a tenth of a 10 Hz sensor's period from the worker once the path was full.
#: A display needs it no faster.
PATH_PERIOD_S = 1.0


def qos_overridable() -> QoSOverridingOptions:
    """``qos_overrides.<topic>.<publisher|subscription>.{history,depth,reliability}`` apply
    (rclpy reads them when the endpoint is created; they are read-only afterwards)."""
    return QoSOverridingOptions.with_default_policies()


@contextlib.contextmanager
def qos_override_errors() -> Iterator[None]:
    """Creating endpoints: a ``qos_overrides`` value rclpy cannot apply is a
    :class:`~kentreg_ros.ros.parameters.StartupError` naming it (rclpy raises RuntimeError on
    an unknown policy name and asserts on a wrong type)."""
    try:
        yield
    except (InvalidQosOverridesError, RuntimeError, ValueError, TypeError) as exc:
        raise StartupError(f'Invalid qos_overrides: {exc}') from exc
    except AssertionError as exc:
        raise StartupError(
            'Invalid qos_overrides: a value of the wrong type (depth takes an integer; '
            'history, reliability and durability a policy name such as reliable)'
        ) from exc


def input_qos(settings: NodeSettings) -> QoSProfile:
    """The input subscription's QoS: keep-last ``qos_depth``, ``qos_reliability``, volatile
    (the sensor-data profile's durability); ``qos_overrides`` may change it further."""
    reliable = settings.qos_reliability == QosReliability.RELIABLE
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=settings.qos_depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=qos_profile_sensor_data.durability,
    )


def transform_points(points: np.ndarray, T: FloatArray) -> np.ndarray:
    """``points`` (N, 3) moved by ``T`` (4, 4)."""
    return points @ T[:3, :3].T + T[:3, 3]


class Outputs:
    """The node's publishers and what they need between steps (anchor, path, map, poses).

    Parameters
    ----------
    node : rclpy.node.Node
    frames : Frames
        Sends the TF.
    settings : NodeSettings
        The settings at start-up (path length, map voxel and bound).
    """

    def __init__(self, node: Node, frames: Frames, settings: NodeSettings) -> None:
        self._frames = frames
        self._clock = node.get_clock()
        new = node.create_publisher
        self.odom = new(OdometryMsg, names.ODOMETRY, 10, qos_overriding_options=qos_overridable())
        self.pose = new(PoseStamped, names.POSE, 10, qos_overriding_options=qos_overridable())
        self.path = new(Path, names.PATH, 1, qos_overriding_options=qos_overridable())
        self.cloud = new(
            PointCloud2, names.CLOUD_REGISTERED, 5, qos_overriding_options=qos_overridable()
        )
        # Latched: a viewer that starts later gets the latest map.
        map_qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        self.map = new(PointCloud2, names.MAP, map_qos, qos_overriding_options=qos_overridable())
        self._cloud_factory = rclpy_factory(PointCloud2, PointField, Header, TimeMsg)
        self._poses: collections.deque[Any] = collections.deque(maxlen=settings.path_length)
        self.run_map = RunMap(settings.map_voxel_size, max_points=settings.map_max_points)
        self.trajectory = TrajectoryLog()  # T_world_moving of every step
        self._lock = threading.Lock()
        self._anchor: FloatArray | None = None  # T_odom_world
        self._pending_pose: FloatArray | None = None  # T_odom_moving asked for
        self._last_T_wl: FloatArray | None = None
        self._last_stamp_ns = 0
        self._map_changed = False
        self._map_published: float | None = None  # time.monotonic() of the last map
        self._path_header: Header | None = None  # of the newest pose; None: nothing new
        self._path_published: float | None = None  # time.monotonic() of the last path

    @property
    def anchor(self) -> FloatArray | None:
        """``T_odom_world`` of the current trajectory (None before its first scan)."""
        with self._lock:
            return None if self._anchor is None else self._anchor.copy()

    def reset(self) -> None:
        """Forget the path, the map, the trajectory and the anchor (a new trajectory); a
        pending initial pose stays: it places the new trajectory."""
        self.run_map.clear()
        self.trajectory.clear()
        with self._lock:
            self._poses.clear()
            self._path_header = None
            self._anchor = None
            self._last_T_wl = None
            self._map_changed = True

    def request_pose(self, T_odom_moving: FloatArray) -> None:
        """Make ``T_odom_moving`` the pose of the latest scan (an ``initialpose``): applied
        before the next scan's outputs, which follow from it by the motion since."""
        with self._lock:
            self._pending_pose = np.array(T_odom_moving, dtype=float)

    def publish(
        self,
        step: OdometryStep,
        T_ml: FloatArray,
        prev_stamp: int | None,
        settings: NodeSettings,
        child: str,
    ) -> None:
        """Odometry (pose, twist, covariances), pose, path, TF and the registered cloud of
        ``step``, in ``odom_frame`` -> ``child`` (the moving frame, ``T_ml`` the sensor's pose
        in it); the step's points go into the map when its pose was registered."""
        T_wl = step.T_world_lidar
        anchor = self._update_anchor(T_wl, T_ml, settings)
        T_odom_moving = anchor @ T_wl @ invert_transform(T_ml)
        pose = pose_to_msg(T_odom_moving)
        self.trajectory.append(step.stamp_ns, T_wl @ invert_transform(T_ml))

        odom = OdometryMsg()
        odom.header.stamp = stamp_to_msg(step.stamp_ns)
        odom.header.frame_id = settings.odom_frame
        odom.child_frame_id = child
        odom.pose.pose = pose
        cov = pose_covariance_in_base(step.covariance, T_ml, T_odom_moving, anchor)
        odom.pose.covariance = covariance_to_msg(cov)
        odom.twist.covariance = covariance_to_msg(self._twist(odom, step, T_ml, prev_stamp))
        self.odom.publish(odom)

        pose_msg = PoseStamped()
        pose_msg.header = odom.header
        pose_msg.pose = pose
        self.pose.publish(pose_msg)

        with self._lock:
            if self._poses.maxlen != settings.path_length:
                self._poses = collections.deque(self._poses, maxlen=settings.path_length)
            self._poses.append(pose_msg)
            self._path_header = odom.header

        self._frames.broadcast(step.stamp_ns, T_odom_moving, child, settings)
        self._publish_cloud(step, anchor, settings)
        if step.ok and step.points is not None:
            self.run_map.add(step.points, T_wl)
        with self._lock:
            self._last_T_wl, self._last_stamp_ns = T_wl, step.stamp_ns
            self._map_changed = True

    def _update_anchor(
        self, T_wl: FloatArray, T_ml: FloatArray, settings: NodeSettings
    ) -> FloatArray:
        """The anchor for this step: the mount at a trajectory's start, or the one that puts
        the latest pose where a pending initial pose says (then the path is redrawn)."""
        with self._lock:
            pending, self._pending_pose = self._pending_pose, None
            if self._anchor is None:
                self._anchor = T_ml.copy()
            if pending is not None:
                # The pose asked for is the latest scan's (this one's on a new trajectory).
                last = self._last_T_wl if self._last_T_wl is not None else T_wl
                self._anchor = pending @ T_ml @ invert_transform(last)
                self._map_changed = True
            anchor = self._anchor.copy()
        if pending is not None:
            self._redraw_path(anchor, settings)
        return anchor

    def _redraw_path(self, anchor: FloatArray, settings: NodeSettings) -> None:
        """The path's poses again, moved by the new anchor (from the trajectory log)."""
        with self._lock:
            n = len(self._poses)
        stamps, T_wm = self.trajectory.snapshot(last=n)
        poses = []
        for stamp, T in zip(stamps, T_wm, strict=True):
            msg = PoseStamped()
            msg.header.stamp = stamp_to_msg(int(stamp))
            msg.header.frame_id = settings.odom_frame
            msg.pose = pose_to_msg(anchor @ T)
            poses.append(msg)
        with self._lock:
            self._poses.clear()
            self._poses.extend(poses)

    def _publish_cloud(
        self, step: OdometryStep, anchor: FloatArray, settings: NodeSettings
    ) -> None:
        if settings.registered_cloud == RegisteredCloud.OFF or step.points is None:
            return
        if settings.registered_cloud == RegisteredCloud.ODOM:
            points = transform_points(step.points, anchor @ step.T_world_lidar)
            frame = settings.odom_frame
        else:
            points, frame = step.points, step.frame_id or 'lidar'
        msg = array_to_pointcloud2(
            points, frame_id=frame, stamp_ns=step.stamp_ns, factory=self._cloud_factory
        )
        self.cloud.publish(msg)

    @staticmethod
    def _twist(
        odom: Any, step: OdometryStep, T_ml: FloatArray, prev_stamp: int | None
    ) -> FloatArray:
        """Fill the twist of ``odom`` (moving frame, from the motion since the previous step);
        return its covariance (:data:`UNKNOWN_VARIANCE` where nothing was measured)."""
        twist_cov = np.eye(6) * UNKNOWN_VARIANCE
        if prev_stamp is None or step.index == 0 or step.stamp_ns <= prev_stamp:
            return twist_cov
        dt = (step.stamp_ns - prev_stamp) * 1e-9
        # The current pose of the moving frame in its previous pose.
        T_motion = T_ml @ step.T_prev_curr @ invert_transform(T_ml)
        R = T_motion[:3, :3]
        v = R.T @ T_motion[:3, 3] / dt  # in the current moving frame (child_frame_id)
        w = log_so3(R) / dt
        linear, angular = odom.twist.twist.linear, odom.twist.twist.angular
        linear.x, linear.y, linear.z = (float(x) for x in v)
        angular.x, angular.y, angular.z = (float(x) for x in w)
        if step.result is not None and step.ok:
            # The registration's target is the previous pose's frame (the last accepted one's
            # for the local map), so its covariance is the motion's; a rotation of the sensor
            # also moves a base mounted away from it.
            twist_cov = twist_covariance(step.result.covariance, step.T_prev_curr, dt, T_ml)
        return twist_cov

    def publish_map(self, settings: NodeSettings, *, force: bool = False) -> bool:
        """Send the map around the sensor when ``map_period`` has passed and it changed (or
        ``force``); return whether it was sent. Runs on the executor (a timer)."""
        now = time.monotonic()
        if settings.map_period <= 0.0 and not force:
            return False
        due = self._map_published is None or now - self._map_published >= settings.map_period
        with self._lock:
            if not (force or (due and self._map_changed)) or self._anchor is None:
                return False
            anchor, stamp_ns = self._anchor.copy(), self._last_stamp_ns
            center = None if self._last_T_wl is None else self._last_T_wl[:3, 3].copy()
            self._map_changed = False
        if center is None:
            return False
        points = self.run_map.around(center, settings.map_radius)
        if not len(points):
            return False
        msg = array_to_pointcloud2(
            transform_points(points.astype(np.float64), anchor),
            frame_id=settings.odom_frame,
            stamp_ns=stamp_ns,
            factory=self._cloud_factory,
        )
        self.map.publish(msg)
        self._map_published = now
        return True

    def publish_path(self, settings: NodeSettings, *, force: bool = False) -> bool:
        """Send the path (the last ``path_length`` poses) when it changed and
        :data:`PATH_PERIOD_S` has passed (``force``: whenever it changed); return whether it
        was sent. Runs on the executor (the map's timer)."""
        now = time.monotonic()
        due = self._path_published is None or now - self._path_published >= PATH_PERIOD_S
        if not settings.publish_path or not (due or force):
            return False
        with self._lock:
            header, self._path_header = self._path_header, None
            if header is None:
                return False
            poses = list(self._poses)
        path = Path()
        path.header = header
        path.poses = poses
        self.path.publish(path)
        self._path_published = now
        return True

    def run_snapshot(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """The whole map (M, 3) and trajectory (stamps (N,), ``T_odom_moving`` (N, 4, 4)) of
        the run in ``odom_frame``, and the map's voxel edge: what ``~/save_map`` writes."""
        anchor = self.anchor
        if anchor is None:
            anchor = np.eye(4)
        stamps, T_wm = self.trajectory.snapshot()
        points = transform_points(self.run_map.points.astype(np.float64), anchor)
        return points, stamps, anchor @ T_wm, self.run_map.voxel_size
