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


def _cross_many(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise 2D cross products (a − o) × (b − o) of (M, 2) arrays (or (2,) broadcast)."""
    return np.asarray(
        (a[..., 0] - o[..., 0]) * (b[..., 1] - o[..., 1])
        - (a[..., 1] - o[..., 1]) * (b[..., 0] - o[..., 0])
    )


def _within_box(p: np.ndarray, a: np.ndarray, b: np.ndarray, eps: np.ndarray) -> np.ndarray:
    lo, hi = np.minimum(a, b) - eps[:, None], np.maximum(a, b) + eps[:, None]
    return np.asarray(np.all((lo <= p) & (p <= hi), axis=-1))


def _touching(p1: np.ndarray, p2: np.ndarray, q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Which of the segment pairs p1p2 (one, (2,)) and q1q2 ((M, 2)) cross or touch."""
    scale = np.maximum(
        1.0, np.maximum(np.abs(q1).max(axis=1), np.abs(q2).max(axis=1))
    )  # per pair, with the fixed segment's own extent
    scale = np.maximum(scale, float(np.abs(np.concatenate([p1, p2])).max()))
    eps = 1e-12 * scale * scale
    d1, d2 = _cross_many(q1, q2, p1), _cross_many(q1, q2, p2)
    d3, d4 = _cross_many(p1, p2, q1), _cross_many(p1, p2, q2)
    proper = (((d1 > eps) & (d2 < -eps)) | ((d1 < -eps) & (d2 > eps))) & (
        ((d3 > eps) & (d4 < -eps)) | ((d3 < -eps) & (d4 > eps))
    )
    lin = 1e-9 * scale
    p1s, p2s = np.broadcast_to(p1, q1.shape), np.broadcast_to(p2, q1.shape)
    return np.asarray(
        proper
        | ((np.abs(d1) <= eps) & _within_box(p1s, q1, q2, lin))
        | ((np.abs(d2) <= eps) & _within_box(p2s, q1, q2, lin))
        | ((np.abs(d3) <= eps) & _within_box(q1, p1s, p2s, lin))
        | ((np.abs(d4) <= eps) & _within_box(q2, p1s, p2s, lin))
    )


def _folds_back(shared: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
    """Adjacent edges share one vertex; they overlap only if they fold back onto each other."""
    u, v = a - shared, b - shared
    collinear = abs(u[0] * v[1] - u[1] * v[0]) <= 1e-12 * max(1.0, float(np.abs(u).max())) ** 2
    return bool(collinear and float(u @ v) > 0)


def find_self_intersection(polygon: np.ndarray) -> tuple[int, int] | None:
    """The first pair of edges (i, j) that cross or touch, or None for a simple polygon.

    Edge i runs from vertex i to vertex i + 1 (mod N). Adjacent edges may share their common
    vertex only; a repeated vertex or a zero-length edge makes the polygon non-simple. Each
    edge is tested against all later ones at once (2,000 vertices: well under a second).
    """
    polygon = np.asarray(polygon, dtype=float)
    n = len(polygon)
    after = np.roll(polygon, -1, axis=0)
    same = np.all(np.abs(after - polygon) <= 1e-12, axis=1)
    if same.any():
        k = int(np.argmax(same))
        return (k, k)
    for i in range(n):
        a1, a2 = polygon[i], after[i]
        if i + 1 < n and _folds_back(a2, a1, after[i + 1]):
            return (i, i + 1)
        last = n - 1 if i > 0 else n - 2  # edge n − 1 is adjacent to edge 0
        if i + 2 <= last:
            later = slice(i + 2, last + 1)
            hits = np.flatnonzero(_touching(a1, a2, polygon[later], after[later]))
            if len(hits):
                return (i, i + 2 + int(hits[0]))
        if i == 0 and n > 2 and _folds_back(a1, a2, polygon[n - 1]):
            return (0, n - 1)
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
