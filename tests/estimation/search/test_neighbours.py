"""The voxel-grid neighbour search: a k-d tree's answer, on any cloud, within bounded memory."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from estimation.errors import EstimationError
from estimation.search.neighbours import NearestSince, PointGrid


def _distances(points: np.ndarray, queries: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Distances of the answered neighbours, -1 where none (index == len(points))."""
    padded = np.vstack([points, np.full((1, 3), np.inf)])
    d = np.linalg.norm(padded[index] - queries[:, None, :], axis=2)
    return np.where(np.isfinite(d), d, -1.0)


def _tree(points: np.ndarray, queries: np.ndarray, k: int, reach: float) -> np.ndarray:
    _, index = cKDTree(points).query(queries, k=k, distance_upper_bound=reach)
    return np.asarray(index).reshape(len(queries), k)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 300),
    k=st.integers(1, 12),
    reach=st.floats(0.01, 2.0),
    cell=st.floats(0.03, 0.6),
)
def test_the_answer_is_the_k_d_trees(seed: int, n: int, k: int, reach: float, cell: float) -> None:
    rng = np.random.default_rng(seed)
    points = rng.uniform(-2.0, 2.0, (n, 3)) * rng.uniform(0.01, 3.0, 3)
    queries = rng.uniform(-3.0, 3.0, (40, 3))  # some beyond the cloud's box
    grid = PointGrid(points, cell_m=cell)
    index = grid.query(queries, k, reach)
    assert index.shape == (40, k)
    assert index.dtype == np.int64
    expected = _tree(points, queries, k, reach)
    np.testing.assert_allclose(_distances(points, queries, index),
                               _distances(points, queries, expected), atol=1e-12)  # fmt: skip
    assert ((index == n) == (expected == n)).all()
    near = grid.any_within(queries, reach)  # whether the tree finds one, not which
    assert near.dtype == bool
    assert (near == (expected[:, 0] < n)).all()


def test_any_within_on_a_surface_empty_and_at_the_reach() -> None:
    """A wall queried 30 cm in front along its length at the registration's overlap reach
    (45 cm: within it up to 33.5 cm beyond either end), a point exactly at the reach (within,
    as the k-d tree counts), and nothing to find."""
    u = np.arange(0.0, 80.0) * 0.05
    a, b = np.meshgrid(u, u[:50])
    wall = np.c_[a.ravel(), np.zeros(a.size), b.ravel()]
    xs = np.linspace(-1.0, 5.0, 61)
    queries = np.c_[xs, np.full(61, 0.3), np.full(61, 1.0)]
    near = PointGrid(wall).any_within(queries, 0.45)
    reach_x = np.sqrt(0.45**2 - 0.3**2)
    assert (near == ((xs > -reach_x) & (xs < u[-1] + reach_x))).all()
    one = PointGrid(np.array([[0.0, 0.0, 0.0]]))
    assert one.any_within(np.array([[0.0, 0.5, 0.0], [0.0, 0.5000001, 0.0]]), 0.5).tolist() == [
        True,
        False,
    ]
    assert PointGrid(np.zeros((0, 3))).any_within(queries, 1.0).tolist() == [False] * 61
    assert PointGrid(wall).any_within(np.zeros((0, 3)), 1.0).shape == (0,)
    assert not PointGrid(wall).any_within(queries, -1.0).any()


def test_a_surface_cloud_matches_the_tree_at_the_registrations_reaches() -> None:
    """A box of walls at the registration's 5 cm voxels, queried 3.6 cm off (a registration
    near convergence) with k = 1, 8 and 20 at 10 and 30 cm."""
    rng = np.random.default_rng(3)
    u = np.arange(0.0, 4.0, 0.05)
    a, b = np.meshgrid(u, u[:50])
    walls = [np.c_[a.ravel(), np.zeros(a.size), b.ravel()],
             np.c_[np.zeros(a.size), a.ravel(), b.ravel()],
             np.c_[a.ravel(), np.full(a.size, 4.0), b.ravel()]]  # fmt: skip
    points = np.vstack(walls) + rng.normal(0.0, 0.004, (3 * a.size, 3))
    queries = points + np.array([0.03, -0.02, 0.0])
    grid = PointGrid(points)
    for k, reach in ((1, 0.1), (1, 0.3), (8, 0.3), (20, 0.3)):
        index = grid.query(queries, k, reach)
        expected = _tree(points, queries, k, reach)
        np.testing.assert_allclose(_distances(points, queries, index),
                                   _distances(points, queries, expected), atol=1e-12)  # fmt: skip
        assert (index[:, 0] < len(points)).all()


def test_nothing_within_reach_is_len_points() -> None:
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    grid = PointGrid(points)
    index = grid.query(np.array([[0.5, 0.0, 0.0], [10.0, 10.0, 10.0], [0.05, 0.0, 0.0]]), 2, 0.4)
    assert index.tolist() == [[2, 2], [2, 2], [0, 2]]
    assert grid.query(np.array([[0.5, 0.0, 0.0]]), 2, 0.5).tolist() in ([[0, 1]], [[1, 0]])


def test_queries_above_below_and_beside_a_flat_grid() -> None:
    """A floor of points (one layer of cells): queries far above, below and beside it find
    nothing; one just above or below the layer, or just beyond its edge, finds its point."""
    u = np.arange(0.0, 1.0, 0.1)
    a, b = np.meshgrid(u, u)
    points = np.c_[a.ravel(), b.ravel(), np.zeros(a.size)]
    grid = PointGrid(points)
    queries = np.array([[0.5, 0.5, 50.0], [0.5, 0.5, -50.0], [40.0, 0.5, 0.0],
                        [0.5, 0.5, 0.25], [0.5, 0.5, -0.25], [-0.25, 0.3, 0.0], [0.9, 1.1, 0.05]])  # fmt: skip
    index = grid.query(queries, 1, 0.3)
    expected = _tree(points, queries, 1, 0.3)
    assert index[:3, 0].tolist() == [len(points)] * 3
    np.testing.assert_allclose(_distances(points, queries, index),
                               _distances(points, queries, expected), atol=1e-12)  # fmt: skip
    assert (index[3:, 0] < len(points)).all()


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 400), cell=st.floats(0.03, 0.6))
def test_the_cells_hold_the_points_in_a_stable_sort_by_cell(seed: int, n: int,
                                                           cell: float) -> None:  # fmt: skip
    """The grid's counting sort: the points sorted by cell (x-major) with a stable argsort,
    runs of repeated points and points on the box's far faces included."""
    rng = np.random.default_rng(seed)
    points = np.round(rng.uniform(-1.0, 1.0, (n, 3)) * rng.uniform(0.01, 2.0, 3), 2)
    grid = PointGrid(points, cell_m=cell)
    assert np.array_equal(grid.lower, points.min(axis=0))
    ijk = np.minimum(np.floor((points - grid.lower) / grid.cell_m).astype(np.int64),
                     grid.dims - 1)  # fmt: skip
    keys = (ijk[:, 0] * grid.dims[1] + ijk[:, 1]) * grid.dims[2] + ijk[:, 2]
    order = np.argsort(keys, kind="stable")
    assert np.array_equal(grid.order, order)
    assert np.array_equal(grid.sorted, points[order])
    counts = np.bincount(keys, minlength=int(np.prod(grid.dims)))
    assert np.array_equal(grid.starts, np.r_[0, np.cumsum(counts)])


def test_an_empty_cloud_and_no_queries() -> None:
    empty = PointGrid(np.zeros((0, 3)))
    assert len(empty) == 0
    assert empty.query(np.zeros((3, 3)), 2, 1.0).tolist() == [[0, 0]] * 3
    assert PointGrid(np.ones((4, 3))).query(np.zeros((0, 3)), 3, 1.0).shape == (0, 3)


def test_a_cloud_over_a_huge_box_gets_larger_cells_not_a_huge_grid() -> None:
    """Three points, two of them 10 km apart: 1e15 cells of 10 cm; the grid keeps to its 4,096
    cells and the answer stays exact. A large cloud gets at most 4 cells per point."""
    points = np.array([[0.0, 0.0, 0.0], [10_000.0, 10_000.0, 10_000.0], [0.05, 0.0, 0.0]])
    grid = PointGrid(points)
    assert len(grid.starts) <= 4096 + 1
    assert grid.cell_m > 10_000.0 / 16
    assert grid.query(np.array([[0.01, 0.0, 0.0]]), 3, 1.0).tolist() == [[0, 2, 3]]
    spread = np.random.default_rng(0).uniform(0.0, 100.0, (20_000, 3))
    assert len(PointGrid(spread).starts) <= 4 * 20_000 + 1


@pytest.mark.parametrize(
    ("points", "cell", "message"),
    [
        (np.array([[0.0, np.nan, 0.0]]), 0.1, "points must be finite"),
        (np.array([[0.0, np.inf, 0.0]]), 0.1, "points must be finite"),
        (np.zeros((2, 3)), 0.0, "cell size must be positive"),
        (np.zeros((2, 3)), float("nan"), "cell size must be positive"),
        # A view of 2**31 points (no memory behind it): refused before anything is allocated.
        (np.broadcast_to(np.zeros(3), (1 << 31, 3)), 0.1, "2,147,483,648 points, at most"),
    ],
)
def test_bad_clouds_are_one_line_errors(points: np.ndarray, cell: float, message: str) -> None:
    with pytest.raises(EstimationError, match=message):
        PointGrid(points, cell_m=cell)


def test_k_below_one_is_an_error() -> None:
    with pytest.raises(EstimationError, match="k must be at least 1"):
        PointGrid(np.zeros((2, 3))).query(np.zeros((1, 3)), 0, 1.0)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 400),
    reach=st.floats(0.02, 0.6),
    margin=st.floats(0.001, 0.3),
    step=st.floats(0.0, 0.2),
)
def test_the_nearest_since_is_the_grids_nearest_at_every_step(
    seed: int, n: int, reach: float, margin: float, step: float
) -> None:
    """Queries drifting in small and large steps, a different subset asked each time: every
    answer is the grid's own (index for index, ties included)."""
    rng = np.random.default_rng(seed)
    # On a 5 cm lattice, so that equidistant points (ties) are common.
    points = np.round(rng.uniform(-1.0, 1.0, (n, 3)) / 0.05) * 0.05
    grid = PointGrid(points)
    queries = rng.uniform(-1.2, 1.2, (60, 3))
    memo = NearestSince(grid, len(queries), reach, margin)
    asked = 0
    for move in range(12):
        rows = np.flatnonzero(rng.random(len(queries)) < 0.8)
        asked += len(rows)
        np.testing.assert_array_equal(memo.query(rows, queries[rows]),
                                      grid.query(queries[rows], 1, reach)[:, 0])  # fmt: skip
        queries = queries + rng.normal(0.0, step if move % 4 else 0.5, queries.shape)
        if move % 3 == 0:
            queries[::7] = np.round(queries[::7] / 0.025) * 0.025  # midway between lattice points
    assert memo.looked_up <= asked


def test_the_nearest_since_looks_up_only_the_queries_that_moved_enough() -> None:
    u = np.arange(0.0, 40.0) * 0.05
    a, b = np.meshgrid(u, u)
    wall = np.c_[a.ravel(), np.zeros(a.size), b.ravel()]  # 5 cm apart
    grid = PointGrid(wall)
    queries = np.c_[u[5:35] + 0.011, np.full(30, 0.1), np.full(30, 1.013)]
    rows = np.arange(30)
    memo = NearestSince(grid, 30, 0.3, 0.05)
    first = memo.query(rows, queries)
    assert memo.looked_up == 30
    # A millimetre: the nearest stays nearest for every query; none is looked up again.
    np.testing.assert_array_equal(memo.query(rows, queries + np.array([0.001, 0, 0])), first)
    assert memo.looked_up == 30
    # Two centimetres along the wall: past the point midway to the next, looked up again.
    moved = queries + np.array([0.02, 0.0, 0.0])
    np.testing.assert_array_equal(memo.query(rows, moved), grid.query(moved, 1, 0.3)[:, 0])
    assert memo.looked_up == 60
    # Nothing within the reach and the margin: none, and not looked up again while the queries
    # move less than the margin.
    away = queries + np.array([0.0, 0.3, 0.0])
    np.testing.assert_array_equal(memo.query(rows, away), np.full(30, len(wall)))
    assert memo.looked_up == 90
    np.testing.assert_array_equal(memo.query(rows, away - np.array([0.0, 0.04, 0.0])),
                                  np.full(30, len(wall)))  # fmt: skip
    assert memo.looked_up == 90
    # Exactly midway between two points: a tie, looked up each time.
    tie = np.array([[0.025, 0.1, 1.013]])
    memo.query(np.array([0]), tie)
    memo.query(np.array([0]), tie)
    assert memo.looked_up == 92
    with pytest.raises(EstimationError, match="margin"):
        NearestSince(grid, 3, 0.3, 0.0)
    with pytest.raises(EstimationError, match="reach"):
        NearestSince(grid, 3, -0.1, 0.05)
