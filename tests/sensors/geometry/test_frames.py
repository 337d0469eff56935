"""Planar poses as homogeneous transforms (T_a_b maps points from b into a)."""

from __future__ import annotations

import math

import numpy as np

from sensors.geometry.frames import pose2_matrix, transform_points, transform_vectors


def test_pose2_maps_points_into_the_parent_frame() -> None:
    T_map_robot = pose2_matrix(2.0, 1.0, math.pi / 2, z_m=0.5)
    np.testing.assert_allclose(
        transform_points(T_map_robot, np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 1.0]])),
        [[2.0, 2.0, 0.5], [1.0, 1.0, 1.5]],
        atol=1e-12,
    )
    np.testing.assert_allclose(
        transform_vectors(T_map_robot, np.array([[1.0, 0.0, 0.0]])), [[0.0, 1.0, 0.0]], atol=1e-12
    )


def test_composition_follows_the_frame_convention() -> None:
    T_map_robot = pose2_matrix(1.0, 2.0, 0.3)
    T_robot_scanner = pose2_matrix(0.1, 0.0, 0.0, z_m=0.45)
    T_map_scanner = T_map_robot @ T_robot_scanner
    origin = transform_points(T_map_scanner, np.zeros((1, 3)))[0]
    np.testing.assert_allclose(origin, [1.0 + 0.1 * math.cos(0.3), 2.0 + 0.1 * math.sin(0.3), 0.45])
    np.testing.assert_allclose(T_map_scanner @ np.linalg.inv(T_map_scanner), np.eye(4), atol=1e-12)


def test_the_scanner_mount_lifts_and_shifts_the_robot_frame() -> None:
    from sensors.geometry.frames import scanner_mount, scanner_pose_matrix

    T_robot_scanner = scanner_mount(0.1, 0.45)
    np.testing.assert_allclose(T_robot_scanner[:3, 3], [0.1, 0.0, 0.45])
    np.testing.assert_allclose(T_robot_scanner[:3, :3], np.eye(3))
    T_map_scanner = scanner_pose_matrix(2.0, 3.0, np.pi / 2, 0.1, 0.45)
    np.testing.assert_allclose(T_map_scanner[:3, 3], [2.0, 3.1, 0.45], atol=1e-12)
    np.testing.assert_allclose(T_map_scanner, pose2_matrix(2.0, 3.0, np.pi / 2) @ T_robot_scanner)
