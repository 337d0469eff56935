"""Drivable space and frontiers on an estimated grid (a scan of a long room seen only nearby)."""

from __future__ import annotations

import numpy as np
import pytest

from mapping.errors import MapError
from mapping.grid import GridParams, OccupancyGrid
from mapping.traversability import drivable_space, floor_map, frontiers, line_of_sight
from tests.mapping.conftest import room_scan

ROOM = (10.0, 3.0, 2.5)
SENSOR = np.array([1.5, 1.5, 0.4])


def scanned(
    max_range_m: float,
    room: tuple[float, float, float] = ROOM,
    sensor: np.ndarray = SENSOR,
) -> OccupancyGrid:
    """The room seen from ``sensor``, returns beyond ``max_range_m`` lost (their space unknown)."""
    grid = OccupancyGrid(GridParams(resolution_m=0.1, origin_m=(-0.5, -0.5, -0.05)))
    points = room_scan(sensor, room, azimuth_steps=360, elevation_steps=90)
    near = np.linalg.norm(points - sensor, axis=1) <= max_range_m
    for _ in range(2):
        grid.integrate_scan(points[near], sensor)
    return grid


@pytest.fixture(scope="module")
def grid() -> OccupancyGrid:
    return scanned(4.0)


def test_walls_are_obstacles_and_the_seen_floor_is_free(grid: OccupancyGrid) -> None:
    floor = floor_map(grid, body_z_m=(0.1, 0.5))
    space = drivable_space(floor, robot_radius_m=0.3, margin_m=0.1)
    xs = floor.lower_xy[0] + (np.arange(floor.shape[1]) + 0.5) * 0.1
    ys = floor.lower_xy[1] + (np.arange(floor.shape[0]) + 0.5) * 0.1
    gx, gy = np.meshgrid(xs, ys)
    assert floor.obstacle[np.abs(gy - 3.05) < 0.06].any()  # the far wall (y = 3)
    assert floor.free[(np.abs(gx - 2.0) < 0.3) & (np.abs(gy - 1.5) < 0.3)].all()
    assert not floor.free[gx > 6.0].any()  # beyond the 4 m of returns nothing is known free
    # The centre stays 0.4 m from the walls and 0.3 m from anything unknown.
    drivable_y = gy[space.free]
    assert drivable_y.min() >= 0.4 - 0.1
    assert drivable_y.max() <= 3.0 - 0.4 + 0.1
    assert space.is_free(SENSOR[:2])
    assert not space.is_free((0.2, 1.5))  # 0.2 m from the wall at x = 0


def test_the_frontier_lies_where_the_returns_ended(grid: OccupancyGrid) -> None:
    floor = floor_map(grid, body_z_m=(0.1, 0.5))
    space = drivable_space(floor, robot_radius_m=0.3)
    found = frontiers(floor, space, robot_radius_m=0.3, from_xy=SENSOR[:2])
    assert len(found) >= 1
    biggest = found[0]
    assert 3.0 < biggest.centroid_xy[0] < 5.5  # towards the unseen end of the room, x > 1.5
    assert 0.8 < biggest.centroid_xy[1] < 2.2
    assert all(space.free[r, c] for r, c in biggest.cells)


def test_a_room_seen_whole_has_no_frontier() -> None:
    """A 5 m room seen from its middle: the gaps between far rays are not frontiers."""
    centre = np.array([2.5, 1.5, 0.4])
    grid = scanned(20.0, (5.0, 3.0, 2.5), centre)
    floor = floor_map(grid, body_z_m=(0.1, 0.5), lower_xy=(-0.5, -0.5), upper_xy=(5.5, 3.5))
    assert floor.free.sum() * 0.01 > 0.85 * 4.8 * 2.8  # nearly all the floor inside the walls
    space = drivable_space(floor, robot_radius_m=0.3)
    assert frontiers(floor, space, robot_radius_m=0.3, from_xy=centre[:2]) == []


def test_bad_input_is_a_clear_error(grid: OccupancyGrid) -> None:
    floor = floor_map(grid, body_z_m=(0.1, 0.5))
    with pytest.raises(MapError, match="positive robot radius"):
        drivable_space(floor, robot_radius_m=0.0)
    space = drivable_space(floor, robot_radius_m=0.3)
    with pytest.raises(MapError, match=r"stands outside the drivable space"):
        frontiers(floor, space, robot_radius_m=0.3, from_xy=(9.0, 1.5))
    empty = OccupancyGrid(GridParams(resolution_m=0.1))
    with pytest.raises(MapError, match="holds no observed cell"):
        floor_map(empty, body_z_m=(0.1, 0.5))


def test_unseen_gaps_between_far_rays_count_as_free_floor() -> None:
    grid = scanned(20.0)
    box = {"lower_xy": (-0.5, -0.5), "upper_xy": (10.5, 3.5)}
    strict = floor_map(grid, body_z_m=(0.1, 0.5), max_gap_m2=0.0, **box)
    filled = floor_map(grid, body_z_m=(0.1, 0.5), **box)
    assert filled.free.sum() > strict.free.sum()
    assert not (filled.free & filled.obstacle).any()
    assert (filled.free | ~strict.free).all()  # only unknown cells became free
    assert (filled.obstacle == strict.obstacle).all()


def test_line_of_sight_is_blocked_by_walls_and_by_what_nobody_saw(grid: OccupancyGrid) -> None:
    beacon_z = 1.6
    assert line_of_sight(grid, np.array([1.5, 1.5, 0.4]), np.array([3.0, 1.0, beacon_z]))
    # Through the wall at y = 3 to a point outside the room: the wall is occupied.
    outside = np.array([1.5, 4.0, 1.0])
    assert not line_of_sight(grid, SENSOR, outside, unknown_blocks=False)
    # Towards the end of the room nobody saw: unknown blocks unless told otherwise.
    far = np.array([8.5, 1.5, 0.4])
    assert not line_of_sight(grid, SENSOR, far)
    assert line_of_sight(grid, SENSOR, far, unknown_blocks=False)
    assert line_of_sight(grid, SENSOR, SENSOR + 0.1)  # shorter than the end clearance
    with pytest.raises(MapError, match="finite end points"):
        line_of_sight(grid, SENSOR, np.array([np.nan, 0.0, 0.0]))
