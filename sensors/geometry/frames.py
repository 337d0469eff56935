"""Rigid transforms as 4×4 homogeneous matrices (docs/design.md §2: ``p_a = T_a_b @ p_b``)."""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "pose2_matrix",
    "scanner_mount",
    "scanner_pose_matrix",
    "transform_points",
    "transform_vectors",
]


def pose2_matrix(x_m: float, y_m: float, yaw_rad: float, z_m: float = 0.0) -> np.ndarray:
    """T_parent_child of a planar pose (x, y, yaw) lifted to 3D at height ``z_m``."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array(
        [[c, -s, 0.0, x_m], [s, c, 0.0, y_m], [0.0, 0.0, 1.0, z_m], [0.0, 0.0, 0.0, 1.0]]
    )


def scanner_mount(scanner_x_m: float, scanner_height_m: float) -> np.ndarray:
    """T_robot_scanner: the scanner ``scanner_x_m`` ahead of the robot's centre on its x axis,
    ``scanner_height_m`` above the floor, axes parallel to the robot's (docs/design.md §2)."""
    return pose2_matrix(scanner_x_m, 0.0, 0.0, scanner_height_m)


def scanner_pose_matrix(
    x_m: float, y_m: float, yaw_rad: float, scanner_x_m: float, scanner_height_m: float
) -> np.ndarray:
    """T_map_scanner = T_map_robot @ T_robot_scanner of a robot at (x, y, yaw) on the floor."""
    return pose2_matrix(x_m, y_m, yaw_rad) @ scanner_mount(scanner_x_m, scanner_height_m)


def transform_points(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Map (N, 3) points from frame b into frame a."""
    return np.asarray(points_b @ T_a_b[:3, :3].T + T_a_b[:3, 3])


def transform_vectors(T_a_b: np.ndarray, vectors_b: np.ndarray) -> np.ndarray:
    """Rotate (N, 3) direction vectors from frame b into frame a."""
    return np.asarray(vectors_b @ T_a_b[:3, :3].T)
