"""Plane polygon helpers: orientation, simplicity, containment, triangulation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from sensors.sim.polygon import (
    find_self_intersection,
    points_in_polygon,
    signed_area,
    triangulate,
)

SQUARE = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]])
L_SHAPE = np.array([[0, 0], [4, 0], [4, 1], [1, 1], [1, 3], [0, 3]], dtype=float)


def test_signed_area_sign_gives_orientation() -> None:
    assert signed_area(SQUARE) == pytest.approx(4.0)
    assert signed_area(SQUARE[::-1]) == pytest.approx(-4.0)
    assert signed_area(L_SHAPE) == pytest.approx(6.0)


@pytest.mark.parametrize(
    ("polygon", "expected"),
    [
        (SQUARE, None),
        (L_SHAPE, None),
        (np.array([[0, 0], [2, 2], [2, 0], [0, 2]], float), (0, 2)),  # bow tie
        (np.array([[0, 0], [2, 0], [2, 0], [0, 2]], float), (1, 1)),  # repeated vertex
        (np.array([[0, 0], [3, 0], [1, 0], [1, 2]], float), (0, 1)),  # edge folds back
        (np.array([[0, 0], [4, 0], [4, 2], [2, 0.0], [0, 2]], float), (0, 2)),  # vertex on edge
    ],
)
def test_self_intersection(polygon: np.ndarray, expected: tuple[int, int] | None) -> None:
    assert find_self_intersection(polygon) == expected


def test_points_in_polygon_l_shape() -> None:
    points = np.array([[0.5, 0.5], [3.5, 0.5], [0.5, 2.5], [2.0, 2.0], [5.0, 0.5], [-0.1, 1.0]])
    assert points_in_polygon(points, L_SHAPE).tolist() == [True, True, True, False, False, False]


@st.composite
def star_polygons(draw: st.DrawFn) -> np.ndarray:
    """Star-shaped polygons around the origin: simple and counter-clockwise by construction."""
    n = draw(st.integers(min_value=3, max_value=24))
    radii = draw(st.lists(st.floats(0.2, 5.0), min_size=n, max_size=n))
    jitter = draw(st.lists(st.floats(0.05, 0.95), min_size=n, max_size=n))
    angles = [2 * math.pi * (k + j) / n for k, j in enumerate(jitter)]
    gaps = np.diff([*angles, angles[0] + 2 * math.pi])
    assume(gaps.max() < math.pi - 1e-3)  # otherwise the origin is outside: not a star
    return np.array(
        [[r * math.cos(a), r * math.sin(a)] for r, a in zip(radii, angles, strict=True)]
    )


@settings(max_examples=200, deadline=None)
@given(star_polygons())
def test_triangulation_covers_the_polygon_exactly(polygon: np.ndarray) -> None:
    triangles = triangulate(polygon)
    assert triangles.shape == (len(polygon) - 2, 3)
    areas = [signed_area(polygon[t]) for t in triangles]
    assert min(areas) > 0  # every triangle counter-clockwise
    assert sum(areas) == pytest.approx(signed_area(polygon), rel=1e-9)
    centroids = polygon[triangles].mean(axis=1)
    assert points_in_polygon(centroids, polygon).all()


def test_triangulation_of_a_polygon_with_collinear_vertices() -> None:
    polygon = np.array([[0, 0], [1, 0], [2, 0], [2, 2], [0, 2]], dtype=float)
    triangles = triangulate(polygon)
    assert sum(signed_area(polygon[t]) for t in triangles) == pytest.approx(4.0)


def test_triangulation_rejects_too_few_vertices() -> None:
    with pytest.raises(ValueError, match="at least 3 vertices"):
        triangulate(SQUARE[:2])


def reference_self_intersection(polygon: np.ndarray) -> tuple[int, int] | None:
    """Every pair of edges tested one at a time, straight from the definition."""
    n = len(polygon)
    edges = [(polygon[i], polygon[(i + 1) % n]) for i in range(n)]
    for i in range(n):
        if np.allclose(*edges[i], rtol=0.0, atol=1e-12):
            return (i, i)

    def cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
        return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))

    def on(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
        return bool(np.all((np.minimum(a, b) - 1e-9 <= p) & (p <= np.maximum(a, b) + 1e-9)))

    for i in range(n):
        for j in range(i + 1, n):
            (p1, p2), (q1, q2) = edges[i], edges[j]
            if j == i + 1 or (i == 0 and j == n - 1):
                shared, u_end, v_end = (p2, p1, q2) if j == i + 1 else (p1, p2, q1)
                u, v = u_end - shared, v_end - shared
                if abs(u[0] * v[1] - u[1] * v[0]) <= 1e-12 and float(u @ v) > 0:
                    return (i, j)
                continue
            d = [cross(q1, q2, p1), cross(q1, q2, p2), cross(p1, p2, q1), cross(p1, p2, q2)]
            if d[0] * d[1] < 0 and d[2] * d[3] < 0:
                return (i, j)
            ends = [(p1, q1, q2), (p2, q1, q2), (q1, p1, p2), (q2, p1, p2)]
            if any(abs(dk) <= 1e-12 and on(*e) for dk, e in zip(d, ends, strict=True)):
                return (i, j)
    return None


def test_self_intersection_agrees_with_the_definition_on_random_polygons() -> None:
    rng = np.random.default_rng(0)
    for trial in range(600):
        n = int(rng.integers(3, 12))
        if trial % 2:
            polygon = rng.integers(0, 5, size=(n, 2)).astype(float)  # many touching cases
        else:
            polygon = rng.uniform(-1.0, 1.0, size=(n, 2))
        assert find_self_intersection(polygon) == reference_self_intersection(polygon), polygon


def test_self_intersection_of_thousands_of_vertices_is_quick() -> None:
    import time

    angle = np.linspace(0.0, 2.0 * np.pi, 2000, endpoint=False)
    circle = 10.0 * np.column_stack([np.cos(angle), np.sin(angle)])
    started = time.perf_counter()
    assert find_self_intersection(circle) is None
    assert time.perf_counter() - started < 4.0  # the pairwise loop took 18 s
    circle[1000] = [0.0, 0.0]  # a spike to the centre crosses nothing, ...
    circle[500] = [0.0, -12.0]  # ... a vertex pulled across the circle does
    assert find_self_intersection(circle) is not None
