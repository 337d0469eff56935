"""Floor coverage and rooms entered, on two rooms joined by a door with only the first one seen."""

from __future__ import annotations

import numpy as np
import pytest

from estimation.app.evaluation.coverage import floor_coverage
from mapping.grid import GridParams, OccupancyGrid
from sensors.sim.planner import free_space
from sensors.sim.world import World, world_from_mapping
from tests.mapping.conftest import room_scan

DOOR = {"from_m": 1.0, "to_m": 2.0, "bottom_m": 0.0, "top_m": 2.0}


@pytest.fixture(scope="module")
def world() -> World:
    return world_from_mapping({
        "name": "two_rooms",
        "rooms": [
            {"name": "west", "footprint": [[0, 0], [4, 0], [4, 3], [0, 3]], "ceiling_m": 2.5,
             "openings": [{"wall": 1, **DOOR}]},
            {"name": "east", "footprint": [[4, 0], [8, 0], [8, 3], [4, 3]], "ceiling_m": 2.5,
             "openings": [{"wall": 3, **DOOR}]},
        ],
    })  # fmt: skip


def west_seen() -> OccupancyGrid:
    grid = OccupancyGrid(GridParams(resolution_m=0.1, origin_m=(-0.5, -0.5, -0.05)))
    sensor = np.array([2.0, 1.5, 0.4])
    points = room_scan(sensor, (4.0, 3.0, 2.5), azimuth_steps=360, elevation_steps=90)
    for _ in range(2):
        grid.integrate_scan(points, sensor)
    return grid


def test_only_the_seen_room_counts_and_only_the_visited_room_is_entered(world: World) -> None:
    space = free_space(world, robot_radius_m=0.3, robot_height_m=0.35)
    truth = {"a": np.array([[2.0, 1.5], [2.5, 1.5]])}
    found = floor_coverage(world, space, west_seen(), [np.array([2.0, 1.5])], truth, 0.35)
    assert found["rooms"] == ["east", "west"]  # joined by the door: both reachable
    assert found["rooms_entered"] == ["west"]
    # The west room's floor is known, the east room's not: about half of the reachable floor.
    assert 0.40 < found["coverage"] < 0.55
    assert found["known_cells"] == round(found["coverage"] * found["reachable_cells"])


def test_an_empty_map_covers_nothing_and_a_start_outside_reaches_nothing(world: World) -> None:
    space = free_space(world, robot_radius_m=0.3, robot_height_m=0.35)
    empty = OccupancyGrid(GridParams(resolution_m=0.1))
    found = floor_coverage(world, space, empty, [np.array([2.0, 1.5])], {}, 0.35)
    assert found["coverage"] == 0.0
    assert found["reachable_cells"] > 0
    assert found["rooms_entered"] == []
    outside = floor_coverage(world, space, west_seen(), [np.array([20.0, 1.5])], {}, 0.35)
    assert (outside["reachable_cells"], outside["coverage"], outside["rooms"]) == (0, 0.0, [])
