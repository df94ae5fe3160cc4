"""kentreg_ros.ros.frames: the moving frame, the sensor mount from tf2, the fallback static
transform and the (inverse) odometry TF.

tf2_ros is not on PyPI, so the broadcasters and the buffer are stand-ins with tf2_ros's methods
(``sendTransform``, ``lookup_transform``) that record what the node sends and answer what a
tf2 buffer would; the node under test is real rclpy.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy', reason="rclpy is not installed (pip install -e '.[ros]')")

from geometry_msgs.msg import TransformStamped  # noqa: E402

from kentreg_ros.core import exp_so3, invert_transform, make_transform  # noqa: E402
from kentreg_ros.io.params import NodeSettings  # noqa: E402
from kentreg_ros.ros import frames as frames_module  # noqa: E402
from kentreg_ros.ros.frames import Frames, moving_frame  # noqa: E402
from kentreg_ros.ros.messages import (  # noqa: E402
    transform_from_msg,
    transform_from_xyzrpy,
    transform_to_msg,
)

#: rclpy nodes (DDS participants) in this process: the integration tier.
pytestmark = pytest.mark.integration


class _TransformError(Exception):
    """Stands in for tf2_ros.TransformException."""


class Broadcaster:
    """Records what is sent (tf2_ros.TransformBroadcaster's and StaticTransformBroadcaster's
    method)."""

    def __init__(self) -> None:
        self.sent: list[Any] = []

    def sendTransform(self, msg: Any) -> None:  # noqa: N802 - tf2_ros's name
        self.sent.append(msg)


class Buffer:
    """A tf2 buffer holding the latest transform per (target, source); static transforms sent
    by the broadcaster given land in it too, as they would through /tf_static."""

    def __init__(self, static: Broadcaster) -> None:
        self.transforms: dict[tuple[str, str], np.ndarray] = {}
        self.static = static

    def lookup_transform(self, target: str, source: str, when: Any) -> Any:
        for msg in self.static.sent:
            self.transforms.setdefault(
                (msg.header.frame_id, msg.child_frame_id), transform_from_msg(msg.transform)
            )
        if (target, source) not in self.transforms:
            raise _TransformError(f'"{source}" passed to lookupTransform does not exist')
        out = TransformStamped()
        out.transform = transform_to_msg(self.transforms[target, source])
        return out


@pytest.fixture
def make_frames(
    rclpy_context: Any, monkeypatch: pytest.MonkeyPatch
) -> Iterator[Callable[..., tuple[Frames, Broadcaster, Broadcaster, Buffer | None]]]:
    node = rclpy.create_node('kentreg_frames_test', context=rclpy_context)
    monkeypatch.setattr(
        frames_module, 'tf2_ros', SimpleNamespace(TransformException=_TransformError)
    )

    def make(with_buffer: bool = True) -> tuple[Frames, Broadcaster, Broadcaster, Buffer | None]:
        dynamic, static = Broadcaster(), Broadcaster()
        buffer = Buffer(static) if with_buffer else None
        return Frames(node, NodeSettings(), (dynamic, static, buffer)), dynamic, static, buffer

    yield make
    node.destroy_node()


def _mount(x: float) -> np.ndarray:
    return make_transform(exp_so3(np.array([0.0, 0.0, 0.3])), np.array([x, 0.0, 1.2]))


def test_without_a_base_frame_the_cloud_frame_moves(make_frames: Any) -> None:
    frames, _, static, _ = make_frames()
    settings = NodeSettings()
    assert settings.base_frame == '' and moving_frame('lidar', settings) == 'lidar'
    np.testing.assert_array_equal(frames.mount('lidar', settings, 0.0), np.eye(4))
    assert static.sent == []  # nothing to connect: the tree is odom -> lidar
    same = settings.with_updates({'base_frame': 'lidar'})
    np.testing.assert_array_equal(frames.mount('lidar', same, 0.0), np.eye(4))


def test_the_mount_is_looked_up_again_so_a_late_or_changed_one_is_used(
    make_frames: Any,
) -> None:
    frames, _, static, buffer = make_frames()
    settings = NodeSettings().with_updates({'base_frame': 'base_link', 'tf_wait': 5.0})
    # Not in tf2 yet: the scan waits (within tf_wait).
    assert frames.mount('lidar', settings, 0.0) is None
    # It appears: used.
    buffer.transforms['base_link', 'lidar'] = _mount(0.5)
    np.testing.assert_allclose(frames.mount('lidar', settings, 1.0), _mount(0.5), atol=1e-12)
    # It changes (recalibrated): the new one from the next scan on, not the first forever.
    buffer.transforms['base_link', 'lidar'] = _mount(0.7)
    np.testing.assert_allclose(frames.mount('lidar', settings, 2.0), _mount(0.7), atol=1e-12)
    # A lookup that fails later keeps the last mount.
    del buffer.transforms['base_link', 'lidar']
    np.testing.assert_allclose(frames.mount('lidar', settings, 3.0), _mount(0.7), atol=1e-12)
    assert static.sent == []  # someone publishes it: no fallback


def test_without_a_transform_the_fallback_is_used_and_broadcast_once_as_static(
    make_frames: Any,
) -> None:
    frames, _, static, buffer = make_frames()
    xyzrpy = [0.2, -0.1, 0.9, 0.0, 0.1, 1.5]
    settings = NodeSettings().with_updates(
        {'base_frame': 'base_link', 'tf_wait': 1.0, 'base_to_lidar': xyzrpy}
    )
    assert frames.mount('lidar', settings, 10.0) is None
    assert frames.mount('lidar', settings, 10.5) is None
    T = frames.mount('lidar', settings, 11.0)
    np.testing.assert_allclose(T, transform_from_xyzrpy(xyzrpy), atol=1e-12)
    (msg,) = static.sent
    assert (msg.header.frame_id, msg.child_frame_id) == ('base_link', 'lidar')
    np.testing.assert_allclose(transform_from_msg(msg.transform), T, atol=1e-9)
    # Our own static transform comes back through tf2: the same mount, nothing sent again.
    for now in (12.0, 13.0):
        np.testing.assert_allclose(frames.mount('lidar', settings, now), T, atol=1e-9)
    assert len(static.sent) == 1
    # Another node publishes a different one later (a calibration): it is used.
    buffer.transforms['base_link', 'lidar'] = _mount(0.4)
    np.testing.assert_allclose(frames.mount('lidar', settings, 14.0), _mount(0.4), atol=1e-12)


def test_without_tf2_the_fallback_is_used_at_once_and_nothing_is_sent(make_frames: Any) -> None:
    frames, _, static, _ = make_frames(with_buffer=False)
    settings = NodeSettings().with_updates({'base_frame': 'base_link', 'tf_wait': 30.0})
    np.testing.assert_array_equal(frames.mount('lidar', settings, 0.0), np.eye(4))
    assert frames.lookup('odom', 'map') is None


def test_tf_is_odom_to_moving_or_its_inverse(make_frames: Any) -> None:
    frames, dynamic, _, _ = make_frames()
    T = _mount(3.0)
    settings = NodeSettings()
    sent = frames.broadcast(5 * 10**9, T, 'lidar', settings)
    assert sent is dynamic.sent[-1]
    assert (sent.header.frame_id, sent.child_frame_id) == ('odom', 'lidar')
    assert sent.header.stamp.sec == 5
    np.testing.assert_allclose(transform_from_msg(sent.transform), T, atol=1e-9)
    inverted = settings.with_updates({'invert_tf': True, 'base_frame': 'base_link'})
    sent = frames.broadcast(6 * 10**9, T, 'base_link', inverted)
    assert (sent.header.frame_id, sent.child_frame_id) == ('base_link', 'odom')
    np.testing.assert_allclose(transform_from_msg(sent.transform), invert_transform(T), atol=1e-9)
    assert frames.broadcast(7, T, 'lidar', settings.with_updates({'publish_tf': False})) is None
    assert len(dynamic.sent) == 2


def test_a_lookup_error_that_is_not_tf2s_propagates(make_frames: Any) -> None:
    frames, _, _, buffer = make_frames()

    def broken(*args: Any) -> Any:
        raise TypeError('a bug')

    buffer.lookup_transform = broken
    settings = NodeSettings().with_updates({'base_frame': 'base_link'})
    with pytest.raises(TypeError, match='a bug'):
        frames.mount('lidar', settings, 0.0)
