"""Message conventions: ROS time from mission time, covariances in the header's frame."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimation.app.ros.messages import RosMessages, covariance_6x6, stamp_ns


def test_stamps_are_mission_nanoseconds() -> None:
    assert stamp_ns(169.5) == 169_500_000_000
    assert stamp_ns(0.1) == 100_000_000
    assert stamp_ns(-0.2) == 0
    t = RosMessages().time(stamp_ns(12.3))
    assert (t.sec, t.nanosec) == (12, 300_000_000)


def test_covariance_is_rotated_into_the_map_frame() -> None:
    # 1 cm along the robot's x axis, 5 cm across it; the robot faces +y in the map.
    tangent = np.diag([0.01**2, 0.05**2, 0.02**2])
    tangent[0, 2] = tangent[2, 0] = 1e-5
    cov = covariance_6x6(tangent, math.pi / 2)
    assert cov.shape == (6, 6)
    assert cov[0, 0] == pytest.approx(0.05**2)  # map x is across the robot
    assert cov[1, 1] == pytest.approx(0.01**2)
    assert cov[5, 5] == pytest.approx(0.02**2)
    assert cov[1, 5] == pytest.approx(1e-5)  # the along-track/yaw coupling moves to map y
    assert abs(cov[0, 5]) < 1e-18
    np.testing.assert_array_equal(cov[2:5], 0.0)
    np.testing.assert_allclose(cov, cov.T)


def test_planar_poses_rotate_about_z() -> None:
    pose = RosMessages().pose((1.0, -2.0, math.radians(-120)), z_m=0.3)
    q = pose.orientation
    assert (q.x, q.y) == (0.0, 0.0)
    assert 2 * math.atan2(q.z, q.w) == pytest.approx(math.radians(-120))
    assert (pose.position.x, pose.position.y, pose.position.z) == (1.0, -2.0, 0.3)
