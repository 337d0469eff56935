"""Plane polygons: orientation, simplicity, containment and triangulation.

Polygons are (N, 2) arrays of vertices in order, without the closing repeat of the first vertex.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "find_self_intersection",
    "points_in_polygon",
    "signed_area",
    "triangulate",
]


def signed_area(polygon: np.ndarray) -> float:
    """Shoelace area: positive when the vertices run counter-clockwise."""
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))


def _on_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray, eps: float) -> bool:
    return (
        min(a[0], b[0]) - eps <= p[0] <= max(a[0], b[0]) + eps
        and min(a[1], b[1]) - eps <= p[1] <= max(a[1], b[1]) + eps
    )


def _segments_touch(p1: np.ndarray, p2: np.ndarray, q1: np.ndarray, q2: np.ndarray) -> bool:
    scale = max(1.0, float(np.abs(np.concatenate([p1, p2, q1, q2])).max()))
    eps = 1e-12 * scale * scale
    d1, d2 = _cross(q1, q2, p1), _cross(q1, q2, p2)
    d3, d4 = _cross(p1, p2, q1), _cross(p1, p2, q2)
    if ((d1 > eps and d2 < -eps) or (d1 < -eps and d2 > eps)) and (
        (d3 > eps and d4 < -eps) or (d3 < -eps and d4 > eps)
    ):
        return True
    lin = 1e-9 * scale
    return (
        (abs(d1) <= eps and _on_segment(p1, q1, q2, lin))
        or (abs(d2) <= eps and _on_segment(p2, q1, q2, lin))
        or (abs(d3) <= eps and _on_segment(q1, p1, p2, lin))
        or (abs(d4) <= eps and _on_segment(q2, p1, p2, lin))
    )


def find_self_intersection(polygon: np.ndarray) -> tuple[int, int] | None:
    """The first pair of edges (i, j) that cross or touch, or None for a simple polygon.

    Edge i runs from vertex i to vertex i + 1 (mod N). Adjacent edges may share their common
    vertex only; a repeated vertex or a zero-length edge makes the polygon non-simple.
    """
    n = len(polygon)
    for i in range(n):
        if np.allclose(polygon[i], polygon[(i + 1) % n], rtol=0.0, atol=1e-12):
            return (i, i)
    for i in range(n):
        a1, a2 = polygon[i], polygon[(i + 1) % n]
        for j in range(i + 1, n):
            b1, b2 = polygon[j], polygon[(j + 1) % n]
            if j == i + 1 or (i == 0 and j == n - 1):
                # Adjacent edges share one vertex; they overlap only if they fold back.
                shared = a2 if j == i + 1 else a1
                other_a = a1 if j == i + 1 else a2
                other_b = b2 if j == i + 1 else b1
                u, v = other_a - shared, other_b - shared
                collinear = (
                    abs(u[0] * v[1] - u[1] * v[0]) <= 1e-12 * max(1.0, float(np.abs(u).max())) ** 2
                )
                if collinear and float(u @ v) > 0:
                    return (i, j)
                continue
            if _segments_touch(a1, a2, b1, b2):
                return (i, j)
    return None


def points_in_polygon(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Even-odd containment test of (M, 2) points; returns a boolean (M,) array.

    Points exactly on the boundary may fall either way.
    """
    points = np.atleast_2d(np.asarray(points, dtype=float))
    x, y = points[:, 0:1], points[:, 1:2]
    xa, ya = polygon[:, 0], polygon[:, 1]
    xb, yb = np.roll(xa, -1), np.roll(ya, -1)
    straddles = (ya > y) != (yb > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = xa + (y - ya) * (xb - xa) / (yb - ya)
    crossings = straddles & (x < x_cross)
    return np.asarray(np.count_nonzero(crossings, axis=1) % 2 == 1)


def triangulate(polygon: np.ndarray) -> np.ndarray:
    """Ear-clipping triangulation of a simple counter-clockwise polygon: (N − 2, 3) indices.

    Every triangle is counter-clockwise.
    """
    n = len(polygon)
    if n < 3:
        raise ValueError(f"a polygon needs at least 3 vertices, got {n}")
    remaining = list(range(n))
    triangles: list[tuple[int, int, int]] = []
    guard = 0
    while len(remaining) > 3:
        m = len(remaining)
        for k in range(m):
            i, j, m_ = remaining[(k - 1) % m], remaining[k], remaining[(k + 1) % m]
            a, b, c = polygon[i], polygon[j], polygon[m_]
            if _cross(a, b, c) <= 1e-15:
                continue  # reflex or degenerate corner: not an ear
            others = [v for v in remaining if v not in (i, j, m_)]
            if others and _any_inside_triangle(polygon[others], a, b, c):
                continue
            triangles.append((i, j, m_))
            del remaining[k]
            break
        else:
            guard += 1
            if guard > 1:
                raise ValueError("polygon could not be triangulated: is it simple and CCW?")
            # Drop a collinear vertex that blocks progress and try again.
            for k in range(m):
                i, j, m_ = remaining[(k - 1) % m], remaining[k], remaining[(k + 1) % m]
                if abs(_cross(polygon[i], polygon[j], polygon[m_])) <= 1e-15:
                    del remaining[k]
                    break
            continue
        guard = 0
    triangles.append((remaining[0], remaining[1], remaining[2]))
    return np.asarray(triangles, dtype=np.int32)


def _any_inside_triangle(points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> bool:
    """Whether any point lies inside or on the CCW triangle abc."""

    def side(p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
        return np.asarray(
            (p1[0] - p0[0]) * (points[:, 1] - p0[1]) - (p1[1] - p0[1]) * (points[:, 0] - p0[0])
        )

    inside = (side(a, b) >= 0) & (side(b, c) >= 0) & (side(c, a) >= 0)
    return bool(inside.any())
