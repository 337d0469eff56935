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
