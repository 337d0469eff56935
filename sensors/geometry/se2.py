"""Planar rigid motions on numpy arrays: poses as (..., 3) rows ``x_m, y_m, yaw_rad``.

A pose ``T_a_b`` (docs/design.md §2) is the pose of frame b in frame a. Conventions match
``gtsam.Pose2``: tangent vectors are ``[v_x, v_y, ω]`` and perturbations act on the right,
``T · Exp(ξ)`` (ξ in the body frame), so covariances computed here can be handed to GTSAM noise
models unchanged. Everything is vectorised over leading axes; nothing here imports gtsam.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "adjoint",
    "between",
    "compose",
    "exp",
    "inverse",
    "log",
    "matrix",
    "propagate_compose",
    "transform_points",
    "wrap_angle",
]


def wrap_angle(angle_rad: np.ndarray | float) -> np.ndarray:
    """Angles wrapped into [−π, π)."""
    return np.asarray((np.asarray(angle_rad) + np.pi) % (2.0 * np.pi) - np.pi)


def _split(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pose = np.asarray(pose, dtype=float)
    return pose[..., 0], pose[..., 1], pose[..., 2]


def _one(pose: np.ndarray) -> tuple[float, float, float] | None:
    """(x, y, yaw) as floats when ``pose`` is a single pose: the fast path for one event."""
    if isinstance(pose, np.ndarray) and pose.shape == (3,):
        return float(pose[0]), float(pose[1]), float(pose[2])
    if isinstance(pose, list | tuple) and len(pose) == 3 and not isinstance(pose[0], list | tuple):
        return float(pose[0]), float(pose[1]), float(pose[2])
    return None


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def compose(T_a_b: np.ndarray, T_b_c: np.ndarray) -> np.ndarray:
    """T_a_c = T_a_b ∘ T_b_c."""
    p, q = _one(T_a_b), _one(T_b_c)
    if p is not None and q is not None:
        c, s = math.cos(p[2]), math.sin(p[2])
        return np.array(
            [p[0] + c * q[0] - s * q[1], p[1] + s * q[0] + c * q[1], _wrap(p[2] + q[2])]
        )
    x1, y1, t1 = _split(T_a_b)
    x2, y2, t2 = _split(T_b_c)
    c, s = np.cos(t1), np.sin(t1)
    return np.stack([x1 + c * x2 - s * y2, y1 + s * x2 + c * y2, wrap_angle(t1 + t2)], axis=-1)


def inverse(T_a_b: np.ndarray) -> np.ndarray:
    """T_b_a."""
    p = _one(T_a_b)
    if p is not None:
        c, s = math.cos(p[2]), math.sin(p[2])
        return np.array([-c * p[0] - s * p[1], s * p[0] - c * p[1], _wrap(-p[2])])
    x, y, t = _split(T_a_b)
    c, s = np.cos(t), np.sin(t)
    return np.stack([-c * x - s * y, s * x - c * y, wrap_angle(-t)], axis=-1)


def between(T_w_a: np.ndarray, T_w_b: np.ndarray) -> np.ndarray:
    """T_a_b = T_w_a⁻¹ ∘ T_w_b (gtsam's ``Pose2.between``): b's pose in a's frame."""
    p, q = _one(T_w_a), _one(T_w_b)
    if p is not None and q is not None:
        c, s = math.cos(p[2]), math.sin(p[2])
        dx, dy = q[0] - p[0], q[1] - p[1]
        # remainder is exact: odometry increments keep every bit of the turn they measure
        return np.array([c * dx + s * dy, -s * dx + c * dy, math.remainder(q[2] - p[2], math.tau)])
    x1, y1, t1 = _split(T_w_a)
    x2, y2, t2 = _split(T_w_b)
    c, s = np.cos(t1), np.sin(t1)
    dx, dy = x2 - x1, y2 - y1
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(t2 - t1)], axis=-1)


def transform_points(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Map (N, 2) points from frame b into frame a, for one pose ``T_a_b``."""
    x, y, t = (float(v) for v in np.asarray(T_a_b, dtype=float).reshape(3))
    c, s = math.cos(t), math.sin(t)
    points_b = np.asarray(points_b, dtype=float).reshape(-1, 2)
    return points_b @ np.array([[c, s], [-s, c]]) + np.array([x, y])


def matrix(pose: np.ndarray) -> np.ndarray:
    """(..., 3, 3) homogeneous matrices of poses."""
    x, y, t = _split(pose)
    c, s = np.cos(t), np.sin(t)
    out = np.zeros((*np.shape(x), 3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 0, 2] = c, -s, x
    out[..., 1, 0], out[..., 1, 1], out[..., 1, 2] = s, c, y
    out[..., 2, 2] = 1.0
    return out


def adjoint(pose: np.ndarray) -> np.ndarray:
    """(..., 3, 3) adjoint maps: ``T · Exp(ξ) = Exp(Ad_T ξ) · T`` (gtsam's ``AdjointMap``)."""
    p = _one(pose)
    if p is not None:
        c, s = math.cos(p[2]), math.sin(p[2])
        return np.array([[c, -s, p[1]], [s, c, -p[0]], [0.0, 0.0, 1.0]])
    x, y, t = _split(pose)
    c, s = np.cos(t), np.sin(t)
    out = np.zeros((*np.shape(x), 3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 0, 2] = c, -s, y
    out[..., 1, 0], out[..., 1, 1], out[..., 1, 2] = s, c, -x
    out[..., 2, 2] = 1.0
    return out


def _v_factors(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """sin θ / θ and (1 − cos θ) / θ, with their series near 0."""
    small = np.abs(theta) < 1e-6
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, theta / 2.0 - theta**3 / 24.0, (1.0 - np.cos(safe)) / safe)
    return a, b


def exp(xi: np.ndarray) -> np.ndarray:
    """Exp of tangent vectors ``[v_x, v_y, ω]`` (gtsam's ``Pose2.Expmap``)."""
    vx, vy, w = _split(xi)
    a, b = _v_factors(w)
    return np.stack([a * vx - b * vy, b * vx + a * vy, wrap_angle(w)], axis=-1)


def log(pose: np.ndarray) -> np.ndarray:
    """Log of poses: tangent vectors ``[v_x, v_y, ω]`` (gtsam's ``Pose2.Logmap``)."""
    p = _one(pose)
    if p is not None:
        w = _wrap(p[2])
        if abs(w) < 1e-6:
            f, g = 1.0 - w * w / 6.0, w / 2.0 - w**3 / 24.0
        else:
            f, g = math.sin(w) / w, (1.0 - math.cos(w)) / w
        d = f * f + g * g
        return np.array([(f * p[0] + g * p[1]) / d, (-g * p[0] + f * p[1]) / d, w])
    x, y, t = _split(pose)
    t = wrap_angle(t)
    a, b = _v_factors(t)
    det = a * a + b * b
    return np.stack([(a * x + b * y) / det, (-b * x + a * y) / det, t], axis=-1)


def propagate_compose(
    T_a_b: np.ndarray, cov_a_b: np.ndarray, T_b_c: np.ndarray, cov_b_c: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """T_a_c = T_a_b ∘ T_b_c with its first-order covariance (right perturbations, independent).

    ``T_a_b Exp(ξ1) T_b_c Exp(ξ2) = T_a_c Exp(Ad(T_b_c)⁻¹ ξ1 + ξ2)``.
    """
    T_a_c = compose(T_a_b, T_b_c)
    J = adjoint(inverse(T_b_c))
    cov = J @ np.asarray(cov_a_b) @ np.swapaxes(J, -1, -2) + np.asarray(cov_b_c)
    return T_a_c, cov
