"""The node's frames: which frame moves, where the sensor sits on it, and what goes on /tf.

- **The moving frame** is ``base_frame``, or the cloud's own frame when ``base_frame`` is empty
  (the default): played into the node, a bag without any ``/tf`` gives the tree
  ``odom -> <cloud frame>``, and RViz can draw the input cloud at once.
- **The sensor's mount** ``T_base_sensor``: the identity when the moving frame is the cloud's
  frame; otherwise tf2's ``base_frame <- sensor`` transform, looked up again on every scan (a
  transform that appears late, or changes, is used from the next scan on; a lookup that fails
  after one succeeded keeps the last one). While tf2 has none, scans wait up to ``tf_wait``
  seconds (dropped and counted); then ``base_to_lidar`` is used and, since nobody publishes
  one, broadcast as a static transform (``/tf_static``), so the tree is whole.
- **/tf**: ``odom_frame -> moving frame``, or its inverse with ``invert_tf`` (for a robot whose
  ``odom -> base`` belongs to another node: a frame has one parent in tf). With a ``map_file``,
  also ``map_frame -> odom_frame`` (:meth:`Frames.broadcast_map`, REP-105), once the map has
  placed the run.

tf2_ros is not on PyPI (nor tf2_msgs, its message package): without it (a pip-only
installation) nothing is broadcast, the mount is ``base_to_lidar``, and one log line says so.
The broadcasters and the buffer are used through tf2_ros's API (``sendTransform``,
``lookup_transform``), so tests hand in stand-ins with the same methods.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import rclpy.time
from geometry_msgs.msg import TransformStamped
from rclpy.node import Node

from kentreg_ros.core import invert_transform
from kentreg_ros.io.params import NodeSettings
from kentreg_ros.ros.messages import (
    stamp_to_msg,
    transform_from_msg,
    transform_from_xyzrpy,
    transform_to_msg,
)

try:  # tf2_ros is not on PyPI: a pip-only install runs without TF.
    import tf2_ros
except ImportError:  # pragma: no cover - depends on the installation
    tf2_ros = None

FloatArray = np.ndarray
#: Two mounts closer than this (m, and rad through the rotation matrix entries) are the same:
#: far below any calibration, far above the float noise of a transform sent through tf2.
SAME_MOUNT_TOLERANCE = 1e-6


def moving_frame(cloud_frame: str, settings: NodeSettings) -> str:
    """The child frame of the odometry and the TF: ``base_frame``, or the cloud's frame when
    it is empty (``'lidar'`` for a cloud without a frame, kentreg_convert's name)."""
    return settings.base_frame or cloud_frame or 'lidar'


@dataclass
class _MountState:
    """What the lookup of one sensor frame found so far."""

    T: FloatArray | None = None
    waiting_since: float | None = None
    fallback: bool = False
    static_sent: set[tuple[str, str, tuple[float, ...]]] = field(default_factory=set)


class Frames:
    """The mount lookup and the TF broadcasts of one node (see the module docstring).

    Parameters
    ----------
    node : rclpy.node.Node
    settings : NodeSettings
        The settings at start-up (for the log line without tf2).
    tf : object, optional
        ``(broadcaster, static_broadcaster, buffer)`` to use instead of tf2_ros's (tests);
        default: tf2_ros's when it is installed, else none.
    """

    def __init__(self, node: Node, settings: NodeSettings, tf: Any = None) -> None:
        self._log = node.get_logger()
        self.broadcaster: Any = None
        self.static_broadcaster: Any = None
        self.buffer: Any = None
        self._listener: Any = None
        if tf is not None:
            self.broadcaster, self.static_broadcaster, self.buffer = tf
        elif tf2_ros is not None:
            self.broadcaster = tf2_ros.TransformBroadcaster(node)
            self.static_broadcaster = tf2_ros.StaticTransformBroadcaster(node)
            self.buffer = tf2_ros.Buffer()
            self._listener = tf2_ros.TransformListener(self.buffer, node)
        else:
            self._log.info(
                'tf2_ros is not installed (pip-only rclpy): no /tf or /tf_static broadcast '
                f'(odom_frame {settings.odom_frame!r} -> the moving frame), and the sensor '
                'pose in base_frame comes from base_to_lidar. Install ROS 2 Jazzy '
                '(ros-jazzy-tf2-ros) for TF.'
            )
        self._state = _MountState()

    def reset(self) -> None:
        """Forget the mount found (a new trajectory; the static transforms sent stay sent)."""
        sent = self._state.static_sent
        self._state = _MountState(static_sent=sent)

    def lookup(self, target: str, source: str) -> FloatArray | None:
        """``T_target_source`` from tf2 (latest), or None when tf2 is missing or has none."""
        if self.buffer is None:
            return None
        try:
            tf = self.buffer.lookup_transform(target, source, rclpy.time.Time()).transform
        except _transform_errors():
            return None
        return transform_from_msg(tf)

    def mount(self, cloud_frame: str, settings: NodeSettings, now: float) -> FloatArray | None:
        """``T_base_sensor`` for a scan of ``cloud_frame`` at monotonic time ``now``, or None
        while waiting for tf2 (see the module docstring)."""
        child = moving_frame(cloud_frame, settings)
        state = self._state
        if child == cloud_frame or not cloud_frame:
            return np.eye(4)
        found = self.lookup(child, cloud_frame)
        if found is not None and not (state.fallback and _same(found, state.T)):
            if state.T is None or not _same(found, state.T):
                verb = 'changed' if state.T is not None else 'found'
                self._log.info(
                    f'Sensor mount {child} <- {cloud_frame} {verb} in tf2: '
                    f'translation {np.round(found[:3, 3], 4).tolist()} m.'
                )
            state.T, state.fallback = found, False
            return found
        if state.T is not None:
            return state.T  # a lookup that fails after one succeeded keeps the last mount
        if self.buffer is not None:
            if state.waiting_since is None:
                state.waiting_since = now
            if now - state.waiting_since < settings.tf_wait:
                return None
        state.T, state.fallback = transform_from_xyzrpy(settings.base_to_lidar), True
        why = (
            f'tf2 has no {child} <- {cloud_frame} after {settings.tf_wait:g} s'
            if self.buffer is not None
            else 'without tf2'
        )
        self._log.warning(
            f'{why}: the sensor mount is base_to_lidar={list(settings.base_to_lidar)}'
            + (', broadcast as a static transform.' if self._can_send_static(settings) else '.')
        )
        self._send_static(child, cloud_frame, state.T, settings)
        return state.T

    def _can_send_static(self, settings: NodeSettings) -> bool:
        return settings.publish_tf and self.static_broadcaster is not None

    def _send_static(self, parent: str, child: str, T: FloatArray, settings: NodeSettings) -> None:
        key = (parent, child, tuple(settings.base_to_lidar))
        if not self._can_send_static(settings) or key in self._state.static_sent:
            return
        msg = TransformStamped()
        msg.header.frame_id, msg.child_frame_id = parent, child
        msg.transform = transform_to_msg(T)
        self.static_broadcaster.sendTransform(msg)
        self._state.static_sent.add(key)

    def broadcast(
        self, stamp_ns: int, T_odom_moving: FloatArray, child: str, settings: NodeSettings
    ) -> TransformStamped | None:
        """Send ``odom_frame -> child`` (or the inverse with ``invert_tf``) on /tf; return
        the message sent (None when TF is off or tf2 is missing)."""
        if not settings.publish_tf or self.broadcaster is None:
            return None
        msg = TransformStamped()
        msg.header.stamp = stamp_to_msg(stamp_ns)
        if settings.invert_tf:
            msg.header.frame_id, msg.child_frame_id = child, settings.odom_frame
            msg.transform = transform_to_msg(invert_transform(T_odom_moving))
        else:
            msg.header.frame_id, msg.child_frame_id = settings.odom_frame, child
            msg.transform = transform_to_msg(T_odom_moving)
        self.broadcaster.sendTransform(msg)
        return msg

    def broadcast_map(
        self, stamp_ns: int, T_map_odom: FloatArray, settings: NodeSettings
    ) -> TransformStamped | None:
        """Send ``map_frame -> odom_frame`` on /tf (REP-105: the localization's correction of
        the odometry's drift); return the message sent (None when TF is off or tf2 is
        missing)."""
        if not settings.publish_tf or self.broadcaster is None:
            return None
        msg = TransformStamped()
        msg.header.stamp = stamp_to_msg(stamp_ns)
        msg.header.frame_id, msg.child_frame_id = settings.map_frame, settings.odom_frame
        msg.transform = transform_to_msg(T_map_odom)
        self.broadcaster.sendTransform(msg)
        return msg


def _same(a: FloatArray, b: FloatArray | None) -> bool:
    return b is not None and bool(np.allclose(a, b, rtol=0.0, atol=SAME_MOUNT_TOLERANCE))


def _transform_errors() -> type[BaseException] | tuple[type[BaseException], ...]:
    """tf2's lookup failures (``LookupException``, ``ExtrapolationException``, ...), or none:
    anything else a lookup raises is a bug and propagates."""
    return tf2_ros.TransformException if tf2_ros is not None else ()
