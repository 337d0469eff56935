"""SE(2) helpers: the single-pose fast paths agree with the vectorised ones and with gtsam."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from sensors.geometry import se2


def test_between_one_pose_and_many_agree_with_gtsam() -> None:
    rng = np.random.default_rng(3)
    a = np.column_stack([rng.uniform(-5, 5, (50, 2)), rng.uniform(-math.pi, math.pi, 50)])
    b = np.column_stack([rng.uniform(-5, 5, (50, 2)), rng.uniform(-math.pi, math.pi, 50)])
    many = se2.between(a, b)
    for k in range(len(a)):
        one = se2.between(a[k], b[k])
        expected = gtsam.Pose2(*a[k]).between(gtsam.Pose2(*b[k]))
        np.testing.assert_allclose(one, [expected.x(), expected.y(), expected.theta()], atol=1e-12)
        np.testing.assert_allclose(se2.wrap_angle(one - many[k]), 0.0, atol=1e-12)
    np.testing.assert_allclose(se2.wrap_angle(many - se2.compose(se2.inverse(a), b)), 0, atol=1e-12)


def test_between_keeps_a_small_turn_exactly() -> None:
    turn = 1e-10
    assert se2.between(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.0 + turn]))[2] == (
        pytest.approx(turn, rel=1e-6)
    )
    assert abs(se2.between(np.zeros(3), np.array([0.0, 0.0, 3 * math.pi]))[2]) == pytest.approx(
        math.pi
    )


def test_transform_points_agrees_with_gtsam_and_undoes_itself() -> None:
    rng = np.random.default_rng(5)
    points = rng.uniform(-10, 10, (40, 2))
    for _ in range(20):
        pose = np.array([*rng.uniform(-5, 5, 2), rng.uniform(-math.pi, math.pi)])
        moved = se2.transform_points(pose, points)
        expected = [gtsam.Pose2(*pose).transformFrom(gtsam.Point2(*p)) for p in points]
        np.testing.assert_allclose(moved, expected, atol=1e-12)
        np.testing.assert_allclose(
            se2.transform_points(se2.inverse(pose), moved), points, atol=1e-12
        )
    assert se2.transform_points(np.zeros(3), np.zeros((0, 2))).shape == (0, 2)
