"""Drivable space and frontiers on an estimated grid (a scan of a long room seen only nearby)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapping.errors import MapError
from mapping.grid import GridParams, OccupancyGrid
from mapping.kernels.traversal import ray_cells
from mapping.traversability import (
    FloorMap,
    Frontier,
    drivable_space,
    floor_map,
    frontiers,
    line_of_sight,
    unvisited_rooms,
)
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


RES = 0.1


def walled_floor(unknown_boxes: list[tuple[float, float, float, float]],
                 doorway: tuple[float, float] | None = None) -> FloorMap:  # fmt: skip
    """An 8 m × 6 m floor known free inside a one-cell wall at the map's border, with unknown
    boxes (x0, y0, x1, y1) in it; ``doorway`` (x0, x1): the bottom wall is missing there and
    the floor behind it, up to half a metre in, was never seen."""
    rows, cols = 60, 80
    obstacle = np.zeros((rows, cols), dtype=bool)
    obstacle[[0, -1], :] = True
    obstacle[:, [0, -1]] = True
    unknown = np.zeros_like(obstacle)
    xs = (np.arange(cols) + 0.5) * RES
    ys = (np.arange(rows) + 0.5) * RES
    gx, gy = np.meshgrid(xs, ys)
    for x0, y0, x1, y1 in unknown_boxes:
        unknown |= (gx > x0) & (gx < x1) & (gy > y0) & (gy < y1)
    if doorway is not None:
        door = (gx > doorway[0]) & (gx < doorway[1]) & (gy < 0.5)
        obstacle &= ~door
        unknown |= door
    return FloorMap(obstacle & ~unknown, ~obstacle & ~unknown, np.zeros(2), RES)


def centroids(found: list[Frontier]) -> list[tuple[float, float]]:
    return [(round(float(f.centroid_xy[0]), 1), round(float(f.centroid_xy[1]), 1)) for f in found]


def test_frontiers_of_a_small_enclosed_unknown_patch_are_dropped() -> None:
    # A desk's shadow (0.4 m × 0.4 m) and an unseen 2.5 m × 2.5 m area, both inside the room.
    floor = walled_floor([(1.8, 2.8, 2.2, 3.2), (4.5, 1.75, 7.0, 4.25)])
    assert floor.unknown.sum() * RES**2 == pytest.approx(0.16 + 6.25, abs=0.3)
    space = drivable_space(floor, robot_radius_m=0.3)
    every = frontiers(floor, space, robot_radius_m=0.3)
    assert len(every) == 2
    assert every[0].centroid_xy == pytest.approx((5.75, 3.0), abs=0.1)  # the larger first
    assert every[1].centroid_xy == pytest.approx((2.0, 3.0), abs=0.1)
    kept = frontiers(floor, space, robot_radius_m=0.3, min_unknown_m2=4.0)
    assert centroids(kept) == centroids(every[:1])
    np.testing.assert_array_equal(kept[0].cells, every[0].cells)
    # The threshold is on the patch's area: 6.25 m² passes 6 m² and fails 7 m².
    assert len(frontiers(floor, space, robot_radius_m=0.3, min_unknown_m2=6.0)) == 1
    assert frontiers(floor, space, robot_radius_m=0.3, min_unknown_m2=7.0) == []
    # The small patch still keeps the robot away: it only stops being a place to explore.
    assert not space.is_free((2.0, 3.0))


def test_unknown_space_beyond_the_map_border_is_never_small() -> None:
    # A doorway in the bottom wall: 0.5 m² of unseen floor behind it, reaching the border.
    floor = walled_floor([(1.8, 2.8, 2.2, 3.2)], doorway=(3.0, 4.0))
    space = drivable_space(floor, robot_radius_m=0.3)
    kept = frontiers(floor, space, robot_radius_m=0.3, min_unknown_m2=4.0, from_xy=(4.0, 3.0))
    assert len(kept) == 1
    assert kept[0].centroid_xy[0] == pytest.approx(3.5, abs=0.15)
    assert kept[0].centroid_xy[1] < 1.2
    # The same 0.5 m² enclosed inside the room is a shadow and is dropped.
    enclosed = walled_floor([(1.8, 2.8, 2.2, 3.2), (5.0, 2.5, 6.0, 3.0)])
    space = drivable_space(enclosed, robot_radius_m=0.3)
    assert frontiers(enclosed, space, robot_radius_m=0.3, min_unknown_m2=4.0) == []
    assert len(frontiers(enclosed, space, robot_radius_m=0.3)) == 2


def room_above_unknown(gap_m: float) -> FloorMap:
    """An 8 m × 6 m map: a room seen free above a wall at y = 1.0-1.1 m, with a gap of
    ``gap_m`` at x = 3.0 m that the scans saw nothing through; below the wall, 8 m² nobody saw."""
    rows, cols = 60, 80
    obstacle = np.zeros((rows, cols), dtype=bool)
    obstacle[-1, :] = True
    obstacle[11:, [0, -1]] = True
    obstacle[10, :] = True
    gap = slice(30, 30 + round(gap_m / RES))
    obstacle[10, gap] = False
    free = np.zeros_like(obstacle)
    free[11:-1, 1:-1] = True
    return FloorMap(obstacle, free, np.zeros(2), RES)


@pytest.mark.parametrize("min_unknown_m2", [0.0, 4.0])
def test_a_gap_in_a_wall_narrower_than_the_robot_opens_onto_nothing(min_unknown_m2: float) -> None:
    for gap_m, expected in ((0.3, 0), (0.5, 0), (1.0, 1)):
        floor = room_above_unknown(gap_m)
        space = drivable_space(floor, robot_radius_m=0.3)
        found = frontiers(floor, space, robot_radius_m=0.3, min_unknown_m2=min_unknown_m2,
                          from_xy=(4.0, 3.0))  # fmt: skip
        assert len(found) == expected, gap_m
        if expected:
            # The doorway: its frontier lies in front of the gap, in the room.
            assert found[0].centroid_xy[0] == pytest.approx(3.5, abs=0.2)
            assert 1.1 < found[0].centroid_xy[1] < 2.0


def slab_grid(occupied_xy: list[tuple[float, float]]) -> OccupancyGrid:
    """A 5 m × 2 m layer of cells seen free at z 0.4-0.5 m, with occupied cells at
    ``occupied_xy``; everything else unknown."""
    params = GridParams(resolution_m=RES)
    i, j = np.meshgrid(np.arange(50), np.arange(20), indexing="ij")
    cells = np.column_stack([i.ravel(), j.ravel(), np.full(i.size, 4)])
    values = np.full(len(cells), params.logodds_min)
    for x, y in occupied_xy:
        values[(cells == (math.floor(x / RES), math.floor(y / RES), 4)).all(axis=1)] = 2.0
    return OccupancyGrid.from_cells(params, cells, values)


A = np.array([0.55, 1.05, 0.45])
B = np.array([4.75, 1.05, 0.45])


def test_line_of_sight_ignores_what_was_seen_around_robots_only() -> None:
    grid = slab_grid([(2.05, 1.05), (4.05, 1.05)])
    assert line_of_sight(grid, A, B, end_clearance_m=0.0, unknown_blocks=True) is False
    assert line_of_sight(slab_grid([]), A, B, end_clearance_m=0.0) is True
    # Near an ignored point an occupied cell no longer blocks; the one elsewhere still does.
    one = np.array([[2.0, 1.1]])
    assert not line_of_sight(grid, A, B, ignore_xy=one, ignore_radius_m=0.3)
    both = np.array([[2.0, 1.1], [4.1, 0.9]])
    assert line_of_sight(grid, A, B, ignore_xy=both, ignore_radius_m=0.3)
    # The radius is in the plane, from the cell centres: 0.25 m away with a 0.2 m radius counts.
    off = np.array([[2.05, 1.3], [4.05, 0.8]])
    assert not line_of_sight(grid, A, B, ignore_xy=off, ignore_radius_m=0.2)
    assert line_of_sight(grid, A, B, ignore_xy=off, ignore_radius_m=0.26)
    # No radius or no points: nothing is ignored.
    assert not line_of_sight(grid, A, B, ignore_xy=both, ignore_radius_m=0.0)
    assert not line_of_sight(grid, A, B, ignore_xy=np.zeros((0, 2)), ignore_radius_m=0.3)
    # Ignored cells are not tested for being unknown either, but the others are.
    beyond = np.array([6.0, 1.05, 0.45])  # the last metre was never seen
    assert not line_of_sight(grid, A, beyond, ignore_xy=both, ignore_radius_m=0.3)
    assert line_of_sight(grid, A, beyond, ignore_xy=np.vstack([both, [[5.5, 1.05]]]),
                         ignore_radius_m=0.6)  # fmt: skip


def test_line_of_sight_skips_the_start_clearance() -> None:
    grid = slab_grid([(0.75, 1.05), (4.05, 1.05)])  # 0.2 m ahead of the start, and 0.7 m short
    end = np.array([3.35, 1.05, 0.45])  # short of the second: only the first is in the way
    assert not line_of_sight(grid, A, end)
    assert line_of_sight(grid, A, end, start_clearance_m=0.3)
    assert not line_of_sight(grid, A, end, start_clearance_m=0.1)
    # Start clearance does not reach the far cell, end clearance does.
    assert not line_of_sight(grid, A, B, start_clearance_m=0.3)
    assert line_of_sight(grid, A, B, start_clearance_m=0.3, end_clearance_m=0.8)
    # Both clearances together longer than the segment: nothing is left to test.
    assert line_of_sight(grid, A, A + np.array([0.5, 0.0, 0.0]), start_clearance_m=0.3,
                         end_clearance_m=0.25)  # fmt: skip


def test_line_of_sight_refuses_non_finite_end_points() -> None:
    grid = slab_grid([])
    for start, end in [(A, np.array([np.inf, 1.0, 0.45])), (np.array([np.nan, 1, 0.45]), B)]:
        with pytest.raises(MapError, match="finite end points"):
            line_of_sight(grid, start, end, ignore_xy=np.array([[2.0, 1.0]]),
                          ignore_radius_m=0.3)  # fmt: skip


@pytest.mark.parametrize("clearance", ["start_clearance_m", "end_clearance_m"])
def test_line_of_sight_refuses_a_non_finite_clearance(clearance: str) -> None:
    """A NaN clearance (e.g. from a NaN beacon offset) must be a MapError, not a crash."""
    grid = slab_grid([])
    with pytest.raises(MapError, match=clearance):
        line_of_sight(grid, A, B, **{clearance: math.nan})


def test_line_of_sight_refuses_non_finite_ignored_points() -> None:
    """Robots' stop poses from an estimate that diverged must not pass silently."""
    grid = slab_grid([(2.05, 1.05)])
    with pytest.raises(MapError, match="ignore"):
        line_of_sight(grid, A, B, ignore_xy=np.array([[np.nan, 1.0]]), ignore_radius_m=0.3)
    with pytest.raises(MapError, match="ignore"):
        line_of_sight(grid, A, B, ignore_xy=np.array([[2.0, 1.0]]), ignore_radius_m=math.nan)


def floor_plan(
    walls: list[tuple[float, float, float, float]], size_m: tuple[float, float]
) -> FloorMap:
    """A floor known everywhere, with obstacle boxes (x0, y0, x1, y1) and a wall at its border."""
    rows, cols = round(size_m[1] / RES), round(size_m[0] / RES)
    gx, gy = np.meshgrid((np.arange(cols) + 0.5) * RES, (np.arange(rows) + 0.5) * RES)
    obstacle = np.zeros((rows, cols), dtype=bool)
    obstacle[[0, -1], :] = True
    obstacle[:, [0, -1]] = True
    for x0, y0, x1, y1 in walls:
        obstacle |= (gx > x0) & (gx < x1) & (gy > y0) & (gy < y1)
    return FloorMap(obstacle, ~obstacle, np.zeros(2), RES)


#: Two 4 m × 4 m rooms side by side, the wall between them at x = 4 with a 1 m door.
TWO_ROOMS = floor_plan([(4.0, 0.0, 4.1, 1.5), (4.0, 2.5, 4.1, 4.1)], (8.1, 4.1))
ROOM_LEVELS = {"max_level_m": 0.9, "persistence_m": 0.2, "min_area_m2": 2.0}


def test_a_room_behind_a_door_is_unvisited_until_a_robot_stands_in_it() -> None:
    space = drivable_space(TWO_ROOMS, robot_radius_m=0.3, margin_m=0.05)
    found = unvisited_rooms(space, np.array([[1.5, 2.0]]), **ROOM_LEVELS)
    assert len(found) == 1
    room = found[0]
    assert 5.6 < room.centroid_xy[0] < 6.5
    assert 1.6 < room.centroid_xy[1] < 2.4
    # Parted by the door (its centre lies 0.5 m from the jambs), and the core inside room B.
    assert 0.5 < room.level_m < 0.75
    core_x = space.lower_xy[0] + (room.cells[:, 1] + 0.5) * RES
    assert core_x.min() > 4.1
    assert room.size == len(room.cells)
    assert 6.0 < room.area_m2 < 3.4 * 3.4  # room B's drivable floor, at most
    # A robot in room B, or at its edge by a wall, has been in it.
    for stood_b in ([6.0, 2.0], [7.6, 3.6], [4.55, 0.5]):
        assert unvisited_rooms(space, np.array([[1.5, 2.0], stood_b]), **ROOM_LEVELS) == []
    # In the doorway, not yet; nobody anywhere: both rooms are one place nobody stood in.
    assert len(unvisited_rooms(space, np.array([[1.5, 2.0], [4.05, 2.0]]), **ROOM_LEVELS)) == 1
    nobody = unvisited_rooms(space, np.zeros((0, 2)), **ROOM_LEVELS)
    assert len(nobody) == 1
    assert 3.5 < nobody[0].centroid_xy[0] < 4.6


def test_a_corridor_wide_in_places_is_no_string_of_rooms() -> None:
    # A 10 m corridor, 2 m wide, 2.6 m wide over one metre in its middle: its pieces part only
    # just below the corridor's own clearance. A room at its end, through a door, is a room.
    walls = [(0.0, 0.0, 4.5, 1.0), (5.5, 0.0, 10.0, 1.0), (0.0, 3.0, 4.5, 4.0),
             (5.5, 3.0, 10.0, 4.0), (4.5, 0.0, 5.5, 0.7), (4.5, 3.3, 5.5, 4.0)]  # fmt: skip
    corridor = drivable_space(floor_plan(walls, (10.1, 4.0)), robot_radius_m=0.3, margin_m=0.05)
    assert unvisited_rooms(corridor, np.array([[1.0, 2.0]]), **ROOM_LEVELS) == []
    door = [(10.0, 0.0, 10.1, 1.5), (10.0, 2.5, 10.1, 4.0)]
    space = drivable_space(floor_plan(walls + door, (14.0, 4.0)), robot_radius_m=0.3, margin_m=0.05)
    found = unvisited_rooms(space, np.array([[1.0, 2.0]]), **ROOM_LEVELS)
    assert [round(float(r.centroid_xy[0])) for r in found] == [12]


def test_unvisited_rooms_refuse_bad_input_and_need_drivable_floor() -> None:
    space = drivable_space(TWO_ROOMS, robot_radius_m=0.3, margin_m=0.05)
    with pytest.raises(MapError, match="finite"):
        unvisited_rooms(space, np.array([[math.nan, 2.0]]), **ROOM_LEVELS)
    assert (
        unvisited_rooms(space, np.array([[1.5, 2.0]]), **(ROOM_LEVELS | {"max_level_m": math.inf}))
        == []
    )
    walls = FloorMap(
        np.ones((20, 20), dtype=bool), np.zeros((20, 20), dtype=bool), np.zeros(2), RES
    )
    closed = drivable_space(walls, robot_radius_m=0.3)
    assert unvisited_rooms(closed, np.array([[1.0, 1.0]]), **ROOM_LEVELS) == []
    # Places off the map count for nothing.
    assert len(unvisited_rooms(space, np.array([[1.5, 2.0], [-50.0, 2.0]]), **ROOM_LEVELS)) == 1


def reference_sight(
    grid: OccupancyGrid, start: np.ndarray, end: np.ndarray, unknown_blocks: bool,
    ignore_xy: np.ndarray, radius_m: float,
) -> bool:  # fmt: skip
    """Line of sight cell by cell: the traversal's cells, their log-odds, the ignored ones."""
    origin, res = grid.origin_m, grid.resolution_m
    cells = ray_cells((start - origin) / res, (end - origin) / res, True)
    if len(ignore_xy) and radius_m > 0:
        centres = grid.cell_centers(cells)[:, :2]
        gap = centres[:, None, :] - ignore_xy[None, :, :]
        cells = cells[~(np.hypot(gap[..., 0], gap[..., 1]) <= radius_m).any(axis=1)]
    values = grid.logodds_at(cells)
    if unknown_blocks and np.isnan(values).any():
        return False
    return not bool(np.any(values > grid.params.logodds_threshold))


def test_line_of_sight_tests_the_cells_of_the_fusions_traversal(grid: OccupancyGrid) -> None:
    """400 segments through the scanned room, in and out of what was seen, with and without
    unknown cells blocking and with robots' places ignored: as tested cell by cell."""
    rng = np.random.default_rng(4)
    outcomes = set()
    for n in range(400):
        a = rng.uniform((-0.3, -0.3, 0.0), (7.0, 3.3, 2.6))
        b = rng.uniform((-0.3, -0.3, 0.0), (7.0, 3.3, 2.6))
        unknown = bool(n % 2)
        ignore = rng.uniform((0.0, 0.0), (6.0, 3.0), size=(n % 4, 2))
        radius = 0.4 if n % 3 else 0.0
        expected = reference_sight(grid, a, b, unknown, ignore, radius)
        seen = line_of_sight(grid, a, b, end_clearance_m=0.0, unknown_blocks=unknown,
                             ignore_xy=ignore, ignore_radius_m=radius)  # fmt: skip
        assert seen is expected
        outcomes.add(seen)
    assert outcomes == {True, False}


def test_a_segment_beyond_the_addressable_map_is_an_error(grid: OccupancyGrid) -> None:
    with pytest.raises(MapError, match="addressable"):
        line_of_sight(grid, SENSOR, np.array([1e12, 0.0, 0.0]))
    with pytest.raises(MapError, match="finite"):
        grid.segment_blocked(np.zeros(3), np.array([np.inf, 0, 0]), unknown_blocks=True,
                             ignore_xy=np.zeros((0, 2)), ignore_radius_m=0.0)  # fmt: skip


def test_a_column_whose_floor_was_seen_is_free_unless_the_band_holds_an_obstacle() -> None:
    # Columns x 0-2 m: the floor layer seen (hit) and one of the body band's three layers seen
    # free, as a steep ray crossing them leaves them; at x 1.0-1.2 m a layer is occupied; at
    # x 2-3 m neither floor nor band was seen.
    params = GridParams(resolution_m=0.1, origin_m=(0.0, 0.0, 0.0))
    i, j = np.meshgrid(np.arange(30), np.arange(10), indexing="ij")
    i, j = i.ravel(), j.ravel()
    seen = i < 20
    floor_cells = np.column_stack([i[seen], j[seen], np.zeros(seen.sum(), dtype=np.int64)])
    band_layer = np.column_stack([i[seen], j[seen], np.full(seen.sum(), 2, dtype=np.int64)])
    cells = np.vstack([floor_cells, band_layer])
    values = np.concatenate([np.full(len(floor_cells), params.logodds_max),
                             np.full(len(band_layer), params.logodds_min)])  # fmt: skip
    post = (cells[:, 2] == 2) & (cells[:, 0] >= 10) & (cells[:, 0] < 12)
    values[post] = params.logodds_max
    grid = OccupancyGrid.from_cells(params, cells, values)
    box = {"lower_xy": (0.05, 0.05), "upper_xy": (2.95, 0.95)}
    body = floor_map(grid, body_z_m=(0.1, 0.4), **box)
    with_ground = floor_map(grid, body_z_m=(0.1, 0.4), ground_z_m=(-0.1, 0.1), **box)
    x = with_ground.lower_xy[0] + (np.arange(with_ground.shape[1]) + 0.5) * 0.1
    steep, post_x, unseen = (x < 1.0) | ((x > 1.2) & (x < 2.0)), (x > 1.0) & (x < 1.2), x > 2.0
    assert body.unknown[:, steep].all()  # one layer of three seen: unknown without the floor
    assert with_ground.free[:, steep].all()
    assert with_ground.obstacle[:, post_x].all()
    assert body.obstacle[:, post_x].all()
    assert with_ground.unknown[:, unseen].all()  # neither the floor nor the band seen
    np.testing.assert_array_equal(with_ground.obstacle, body.obstacle)
    # The default bounding box (no rectangle given) covers the same columns.
    default = floor_map(grid, body_z_m=(0.1, 0.4), ground_z_m=(-0.1, 0.1))
    assert default.shape == (10, 20)
    assert default.free.sum() == with_ground.free[:, x < 2.0].sum()


def holed_slab(unknown_x: list[float], occupied_x: tuple[float, ...] = ()) -> OccupancyGrid:
    """:func:`slab_grid` with the cells at x in ``unknown_x`` (row y = 1.05 m) never seen."""
    grid = slab_grid([(x, 1.05) for x in occupied_x])
    cells, values = grid.cells()
    keep = np.ones(len(cells), dtype=bool)
    for x in unknown_x:
        keep &= ~((cells[:, 0] == math.floor(x / RES)) & (cells[:, 1] == 10))
    return OccupancyGrid.from_cells(grid.params, cells[keep], values[keep])


@pytest.mark.parametrize(
    ("unknown_x", "gap_m", "clear"),
    [
        ([2.05], 0.0, False),  # any unseen cell blocks
        ([2.05], 0.1, True),  # a gap of one cell between rays
        ([2.05, 2.15], 0.1, False),
        ([2.05, 2.15], 0.2, True),
        ([2.05, 2.15, 2.25], 0.2, False),  # three in a row: more than a gap
        ([2.05, 2.15, 3.05, 3.15], 0.2, True),  # runs count apart
        ([0.65], 0.2, True),  # next to the start
        ([4.65, 4.75], 0.2, True),  # at the end
    ],
)
def test_a_line_of_sight_passes_runs_of_unknown_cells_up_to_the_gap(
    unknown_x: list[float], gap_m: float, clear: bool
) -> None:
    grid = holed_slab(unknown_x)
    assert line_of_sight(grid, A, B, end_clearance_m=0.0, unknown_gap_m=gap_m) is clear
    assert line_of_sight(grid, A, B, end_clearance_m=0.0, unknown_blocks=False)


def test_a_gap_of_unknown_cells_never_lets_an_occupied_cell_through() -> None:
    grid = holed_slab([2.05], occupied_x=(2.15,))
    assert not line_of_sight(grid, A, B, end_clearance_m=0.0, unknown_gap_m=0.5)
    assert not line_of_sight(grid, A, B, end_clearance_m=0.0, unknown_blocks=False)
    with pytest.raises(MapError, match="unknown_gap_m"):
        line_of_sight(grid, A, B, unknown_gap_m=-0.1)
    with pytest.raises(MapError, match="unknown_gap_m"):
        line_of_sight(grid, A, B, unknown_gap_m=math.nan)
    with pytest.raises(MapError, match="unknown_gap_cells"):
        grid.segment_blocked(A / RES, B / RES, unknown_blocks=True, ignore_xy=np.zeros((0, 2)),
                             ignore_radius_m=0.0, unknown_gap_cells=-1)  # fmt: skip
