"""kentreg_ros.ros.messages: poses, stamps and covariances to and from rclpy messages.

The expected values are written out independently of the code under test: a quarter turn about
z is the quaternion (0, 0, sin 45 deg, cos 45 deg); a stamp splits into whole seconds and the
nanoseconds left over; a covariance is laid out row by row.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip(
    'geometry_msgs', reason="ROS 2 messages are not installed (pip install -e '.[ros]')"
)

from geometry_msgs.msg import Pose, Transform  # noqa: E402

from kentreg_ros.core import (  # noqa: E402
    InvalidInputError,  # noqa: E402
    exp_so3,
    make_transform,
)
from kentreg_ros.ros import messages  # noqa: E402

QUARTER_TURN_Z = np.array(
    [[0.0, -1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0], [0.0, 0.0, 0.0, 1.0]]
)


def test_pose_to_msg_writes_position_and_xyzw_quaternion() -> None:
    pose = messages.pose_to_msg(QUARTER_TURN_Z)
    assert isinstance(pose, Pose)
    assert (pose.position.x, pose.position.y, pose.position.z) == (1.0, 2.0, 3.0)
    q = pose.orientation
    s = math.sqrt(0.5)
    np.testing.assert_allclose([q.x, q.y, q.z, q.w], [0.0, 0.0, s, s], atol=1e-15)


def test_transform_to_msg_matches_pose_to_msg() -> None:
    tf = messages.transform_to_msg(QUARTER_TURN_Z)
    assert isinstance(tf, Transform)
    assert (tf.translation.x, tf.translation.y, tf.translation.z) == (1.0, 2.0, 3.0)
    s = math.sqrt(0.5)
    r = tf.rotation
    np.testing.assert_allclose([r.x, r.y, r.z, r.w], [0.0, 0.0, s, s], atol=1e-15)


def test_pose_and_transform_round_trip() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        T = make_transform(exp_so3(rng.normal(size=3)), rng.normal(scale=10.0, size=3))
        np.testing.assert_allclose(messages.pose_from_msg(messages.pose_to_msg(T)), T, atol=1e-12)
        np.testing.assert_allclose(
            messages.transform_from_msg(messages.transform_to_msg(T)), T, atol=1e-12
        )


def test_pose_from_msg_reads_a_hand_written_message() -> None:
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = 1.0, 2.0, 3.0
    pose.orientation.z = pose.orientation.w = math.sqrt(0.5)
    np.testing.assert_allclose(messages.pose_from_msg(pose), QUARTER_TURN_Z, atol=1e-15)


def test_pose_to_msg_rejects_a_matrix_that_is_not_a_rigid_transform() -> None:
    with pytest.raises(InvalidInputError, match='rotation'):
        messages.pose_to_msg(np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(InvalidInputError, match='4x4'):
        messages.transform_to_msg(np.full((4, 4), np.nan))


@pytest.mark.parametrize(
    ('stamp_ns', 'sec', 'nanosec'),
    [
        (0, 0, 0),
        (1_700_000_000_123_456_789, 1_700_000_000, 123_456_789),
        (999_999_999, 0, 999_999_999),
    ],
)
def test_stamps_convert_exactly(stamp_ns: int, sec: int, nanosec: int) -> None:
    msg = messages.stamp_to_msg(stamp_ns)
    assert (msg.sec, msg.nanosec) == (sec, nanosec)
    assert messages.stamp_from_msg(msg) == stamp_ns  # exact: no float seconds on the way


def test_negative_stamp_is_refused() -> None:
    with pytest.raises(ValueError, match='stamp_ns'):
        messages.stamp_to_msg(-1)


def test_covariance_is_row_major_36_floats_and_round_trips() -> None:
    C = np.arange(36.0).reshape(6, 6)
    flat = messages.covariance_to_msg(C)
    assert flat[:7] == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0]  # row 0, then row 1 begins
    assert all(type(v) is float for v in flat) and len(flat) == 36
    np.testing.assert_array_equal(messages.covariance_from_msg(flat), C)
    with pytest.raises(InvalidInputError, match=r'shape \(6, 6\)'):
        messages.covariance_to_msg(np.eye(3))
    with pytest.raises(InvalidInputError, match='36 covariance values'):
        messages.covariance_from_msg([0.0] * 35)
