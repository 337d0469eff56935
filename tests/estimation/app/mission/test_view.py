"""The planner's view of the estimated map: drivable space around where robots stood, snapping
to it, path distances, lines of sight around the robots, and where goals found the way blocked."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from estimation.app.mission.view import MapView, _over_obstacles
from mapping.grid import GridParams, OccupancyGrid
from tests.estimation.app.mission.conftest import (
    BODY_AT,
    CONFIG,
    RES,
    UNSEEN_AT,
    seen_whole,
)


def test_where_robots_stood_becomes_drivable(grid: OccupancyGrid, view: MapView) -> None:
    bare = MapView(grid, CONFIG)
    for xy in (BODY_AT, UNSEEN_AT):
        assert not bare.space.is_free(xy)
        assert view.space.is_free(xy)
    # The body was an obstacle and the floor beneath the other robot unknown; now both are free.
    assert bare.floor.obstacle[bare.space.cell(BODY_AT)]
    assert bare.floor.unknown[bare.space.cell(UNSEEN_AT)]
    assert view.floor.free[view.space.cell(BODY_AT)]
    assert view.floor.free[view.space.cell(UNSEEN_AT)]
    # Only there: the walls, the door and the unseen back of room B are as they were.
    changed = (view.floor.free != bare.floor.free) | (view.floor.obstacle != bare.floor.obstacle)
    rows, cols = np.nonzero(changed)
    centres = view.floor.lower_xy + (np.column_stack([cols, rows]) + 0.5) * RES
    near = np.minimum(np.hypot(*(centres - BODY_AT).T), np.hypot(*(centres - UNSEEN_AT).T))
    assert near.max() <= CONFIG.robot.footprint_radius_m + 0.05 + RES + 1e-9
    assert not view.space.is_free((6.05, 3.5))  # the wall beside the door
    assert view.space.is_free((6.05, 2.0))  # the door
    assert not view.space.is_free((7.5, 2.0))  # nobody saw it
    # The known map has a metre of unknown floor around it, so it does not end at its walls.
    assert view.floor.lower_xy[0] == pytest.approx(-1.1, abs=1e-9)
    assert view.floor.unknown[:, 0].all()


def test_a_wall_beside_where_a_robot_stood_stays_in_the_floor_seen(grid: OccupancyGrid) -> None:
    """Generated building 1: a robot stood 4 cm from a wall, here the closet's far wall (x
    10.0-10.1 m, the map's end). Its footprint and a cell are drivable, as for the body at ``BODY_AT``, but the
    wall's cells stay obstacles in the floor the planner looks at: the unseen inside of the wall
    behind them is no floor to explore."""
    near_wall = (10.0 - CONFIG.robot.footprint_radius_m - 0.04, 2.0)
    stood = MapView(grid, CONFIG, np.array([BODY_AT, UNSEEN_AT, near_wall]))
    bare = MapView(grid, CONFIG, np.array([BODY_AT, UNSEEN_AT]))
    wall = stood.space.cell((10.05, 2.0))
    assert bare.floor.obstacle[wall]
    assert stood.floor.obstacle[wall]
    assert stood.space.is_free(near_wall)
    # The body stands alone: cleared in both.
    assert stood.floor.free[stood.space.cell(BODY_AT)]
    # No body stood there: the obstacles are those of the map.
    np.testing.assert_array_equal(stood.floor.obstacle, bare.floor.obstacle)


def test_free_near_snaps_to_the_nearest_drivable_cell_within_reach(view: MapView) -> None:
    space = view.space
    inside = np.array([3.0, 3.0])
    np.testing.assert_array_equal(view.free_near(inside), inside)
    rows, cols = np.nonzero(space.free)
    centres = space.lower_xy + (np.column_stack([cols, rows]) + 0.5) * RES
    for xy in [(0.2, 2.0), (3.0, 3.75), (6.05, 1.0), (5.8, 0.1)]:
        assert not space.is_free(xy)
        got = view.free_near(np.array(xy))
        assert got is not None
        assert space.is_free(got)
        nearest = np.hypot(*(centres - xy).T).min()
        assert math.dist(got, xy) == pytest.approx(nearest, abs=1e-9)
        assert math.dist(got, xy) <= 0.6
    # Beyond reach: outside the rooms, or deep in the unseen part of room B.
    for xy in [(-0.5, 2.0), (7.5, 2.0)]:
        assert view.free_near(np.array(xy)) is None
    assert view.free_near(np.array([7.5, 2.0]), reach_m=1.2) is not None
    assert view.free_near(np.array([50.0, 50.0])) is None  # off the map


def test_distances_from_are_path_lengths(view: MapView) -> None:
    start = np.array([1.0, 1.0])
    reach = view.distances_from([start])
    assert view.at(reach, start) == 0.0
    # In open floor the 8-connected path is within 8 % of the straight line, never shorter.
    for xy in [(4.5, 3.2), (1.0, 3.4), (5.4, 0.6), (3.0, 1.0)]:
        straight = math.dist(start, xy)
        assert straight - RES <= view.at(reach, xy) <= 1.082 * straight + 2 * RES
    # Into room B through the door: longer than the straight line through the wall.
    corner = (6.5, 3.5)
    via_door = math.dist(start, (6.05, 2.3)) + math.dist((6.05, 2.3), corner)
    assert view.at(reach, corner) == pytest.approx(via_door, rel=0.1)
    assert view.at(reach, corner) > math.dist(start, corner) + 0.3
    # Walled off, unseen, off the map: unreachable.
    for xy in [(9.0, 2.0), (7.5, 2.0), (6.05, 3.5), (20.0, 2.0)]:
        assert view.at(reach, xy) == math.inf
    # From the nearer of two sources; from nowhere drivable, nothing is reachable.
    both = view.distances_from([start, np.array([5.5, 2.0])])
    assert view.at(both, (5.0, 2.0)) == pytest.approx(0.5, abs=RES)
    assert (both <= reach).all()
    closet = view.distances_from([np.array([9.05, 2.05])])  # cell centres: exact distances
    assert view.at(closet, (9.05, 3.05)) == pytest.approx(1.0, abs=1e-9)
    assert view.at(closet, (9.55, 2.55)) == pytest.approx(0.5 * math.sqrt(2), abs=1e-9)
    assert view.at(closet, start) == math.inf
    assert np.isinf(view.distances_from([np.array([6.05, 3.5])])).all()  # inside the wall
    assert np.isinf(view.distances_from([])).all()


def test_lines_of_sight_ignore_the_robots_where_they_stand_now_not_where_they_stood() -> None:
    # A room seen free, with one column occupied from the floor to 2 m at (3.0, 2.0): the mast
    # and beacon a robot left in the map where it once stood, or a coat stand.
    i, j, k = np.meshgrid(np.arange(60), np.arange(40), np.arange(25), indexing="ij")
    cells = np.column_stack([i.ravel(), j.ravel(), k.ravel()])
    x, y, z = ((cells + 0.5) * RES).T
    column = (np.hypot(x - 3.0, y - 2.0) < 0.12) & (z < 2.0)
    params = GridParams(resolution_m=RES)
    grid = OccupancyGrid.from_cells(
        params, cells, np.where(column, params.logodds_max, params.logodds_min)
    )
    observer = np.array([1.0, 2.0, 0.0])
    target = np.array([5.2, 2.0, math.pi])
    # The robots stand at ``observer`` and ``target`` now; a robot once stood at (3.0, 2.0).
    now = np.array([observer[:2], target[:2]])
    view = MapView(grid, CONFIG, np.array([*now, [3.0, 2.0]]), robots_xy=now)
    assert not view.geometry.sees_beacon(observer, target)
    assert not view.geometry.sees_beacon(target, observer)
    # Were the column around a robot standing there now, it would be that robot: ignored.
    there = MapView(grid, CONFIG, np.array([*now, [3.0, 2.0]]),
                    robots_xy=np.array([*now, [3.0, 2.0]]))  # fmt: skip
    assert there.geometry.sees_beacon(observer, target)
    assert there.geometry.sees_beacon(target, observer)


def test_a_wall_beside_a_robot_standing_now_still_hides_a_beacon_beyond_it() -> None:
    """Around a robot standing now the 3D cells are not tested (its body, its beacon at every
    heading it turned to); a wall 0.42 m from it still is, through the floor map."""
    i, j, k = np.meshgrid(np.arange(60), np.arange(40), np.arange(25), indexing="ij")
    cells = np.column_stack([i.ravel(), j.ravel(), k.ravel()])
    wall = cells[:, 0] == 30  # x 3.0-3.1 m, floor to ceiling
    params = GridParams(resolution_m=RES)
    grid = OccupancyGrid.from_cells(
        params, cells, np.where(wall, params.logodds_max, params.logodds_min)
    )
    observer = np.array([2.58, 2.0, 0.0])  # its centre 0.42 m from the wall
    target = np.array([4.6, 2.0, math.pi])
    beside = MapView(grid, CONFIG, np.array([observer[:2]]), robots_xy=np.array([observer[:2]]))
    assert not beside.geometry.sees_beacon(observer, target)
    assert not beside.geometry.sees_beacon(target, observer)
    # Along the wall, on the robot's side of it, the beacon is in view.
    along = np.array([2.5, 0.5, math.pi / 2])
    assert beside.geometry.sees_beacon(observer, along)
    assert beside.geometry.sees_beacon(along, observer)


def test_a_low_box_beside_a_robot_standing_now_does_not_hide_a_beacon_above_it() -> None:
    """The floor map marks a 0.3 m high crate beside the robot as an obstacle, but the line of
    sight from the scanner (0.45 m) up to the beacon passes over it."""
    i, j, k = np.meshgrid(np.arange(60), np.arange(40), np.arange(25), indexing="ij")
    cells = np.column_stack([i.ravel(), j.ravel(), k.ravel()])
    crate = (cells[:, 0] == 30) & (cells[:, 2] < 3)  # x 3.0-3.1 m, up to 0.3 m
    params = GridParams(resolution_m=RES)
    grid = OccupancyGrid.from_cells(
        params, cells, np.where(crate, params.logodds_max, params.logodds_min)
    )
    observer = np.array([2.58, 2.0, 0.0])
    target = np.array([4.6, 2.0, math.pi])
    beside = MapView(grid, CONFIG, np.array([observer[:2]]), robots_xy=np.array([observer[:2]]))
    assert beside.floor.obstacle.any()
    assert beside.geometry.sees_beacon(observer, target)


def test_where_a_robot_found_its_way_blocked_no_path_is_planned_again() -> None:
    grid = seen_whole()
    robots = [np.array([1.0, 1.0])]
    open_view = MapView(grid, CONFIG, np.array(robots))
    start, goal = np.array([1.0, 1.0]), np.array([3.0, 3.0])
    assert open_view.space.segment_free(start, goal)
    blocked = MapView(grid, CONFIG, np.array(robots), blocked_xy=np.array([[2.0, 2.0]]))
    assert not blocked.space.is_free((2.0, 2.0))
    assert not blocked.space.segment_free(start, goal)
    path = blocked.space.path(start, goal)
    assert path is not None  # around it
    samples = np.concatenate([np.linspace(a, b, 20) for a, b in itertools.pairwise(path)])
    assert np.hypot(*(samples - (2.0, 2.0)).T).min() >= CONFIG.robot.footprint_radius_m + 0.05
    # Points off the map or not finite change nothing.
    same = MapView(grid, CONFIG, np.array(robots),
                   blocked_xy=np.array([[-40.0, 2.0], [math.nan, 1.0]]))  # fmt: skip
    np.testing.assert_array_equal(same.space.free, open_view.space.free)


def over_obstacles_reference(
    a: np.ndarray, b: np.ndarray, steps: int, robots: np.ndarray, reach_m: float,
    obstacle: np.ndarray, lower_xy: np.ndarray, res: float,
) -> np.ndarray:  # fmt: skip
    """The points along a segment near a robot and over an obstacle, with numpy."""
    points = a + np.linspace(0.0, 1.0, steps)[:, None] * (b - a)
    gap = points[:, None, :2] - robots[None, :, :]
    points = points[(np.hypot(gap[..., 0], gap[..., 1]) <= reach_m).any(axis=1)]
    cols = np.floor((points[:, 0] - lower_xy[0]) / res).astype(np.int64)
    rows = np.floor((points[:, 1] - lower_xy[1]) / res).astype(np.int64)
    h, w = obstacle.shape
    inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    under = np.zeros(len(points), dtype=bool)
    under[inside] = obstacle[rows[inside], cols[inside]]
    return np.asarray(points[under])


def test_points_over_obstacles_near_robots_are_those_numpy_finds() -> None:
    rng = np.random.default_rng(7)
    obstacle = rng.random((40, 60)) < 0.3
    lower = np.array([-1.0, -0.5])
    found = 0
    for n in range(300):
        a = rng.uniform((-2, -1, 0), (7, 4.5, 2))
        b = rng.uniform((-2, -1, 0), (7, 4.5, 2))
        robots = rng.uniform((-1, -0.5), (5, 3.5), size=(n % 4, 2))
        steps = int(rng.integers(2, 90))
        got = _over_obstacles(a, b, steps, robots, 0.6, obstacle, lower[0], lower[1], 0.1)
        want = over_obstacles_reference(a, b, steps, robots, 0.6, obstacle, lower, 0.1)
        np.testing.assert_array_equal(got, want)
        found += len(got)
    assert found > 100


def test_path_distances_from_the_same_cells_are_computed_once(view: MapView) -> None:
    here = np.array(BODY_AT)
    first = view.distances_from([here])
    assert view.distances_from([here + 0.01]) is first  # the same cell
    other = view.distances_from([here, np.array(UNSEEN_AT)])
    assert other is not first
    assert np.all(other <= first)  # from the nearer of two sources
    with pytest.raises(ValueError, match="read-only"):
        first[0, 0] = 0.0
    nowhere = view.distances_from([np.array([1e3, 1e3])])
    assert np.isinf(nowhere).all()


def test_the_view_counts_floor_seen_steeply_as_free_and_passes_sight_gaps() -> None:
    # Room A of ``seen_whole``; in x 1-2 m the floor seen but not the body band (rays reaching
    # the floor steeply cross its layers in other columns), and one unseen cell at the height
    # of a beacon's line.
    grid = seen_whole()
    cells, values = grid.cells()
    x = (cells[:, 0] + 0.5) * RES
    z = (cells[:, 2] + 0.5) * RES
    steep = (x > 1.0) & (x < 2.0) & (z > 0.1) & (z < 0.3)  # the body band's two layers
    hole = (cells == (30, 20, 8)).all(axis=1)  # x 3.0-3.1, y 2.0-2.1, z 0.8-0.9
    keep = ~(steep | hole)
    view = MapView(OccupancyGrid.from_cells(grid.params, cells[keep], values[keep]), CONFIG)
    for xy in ((1.3, 1.0), (1.7, 3.0)):
        assert view.floor.free[view.space.cell(xy)]
    start, end = np.array([2.0, 2.05, 0.5]), np.array([3.9, 2.05, 1.2])  # crosses the hole
    assert view._clear(start, end)
    wider = keep & ~((cells[:, 0] >= 29) & (cells[:, 0] <= 31) & (cells[:, 1] == 20)
                     & (cells[:, 2] >= 7) & (cells[:, 2] <= 9))  # fmt: skip
    closed = MapView(OccupancyGrid.from_cells(grid.params, cells[wider], values[wider]), CONFIG)
    assert not closed._clear(start, end)
