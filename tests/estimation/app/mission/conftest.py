"""Estimated maps the planner's tests share: two rooms seen from inside (one partly unseen, a
robot's body in it) and two rooms seen whole."""

from __future__ import annotations

import numpy as np
import pytest

from estimation.app.config import Config
from estimation.app.mission.view import MapView
from mapping.grid import GridParams, OccupancyGrid

RES = 0.1
CONFIG = Config()
BODY_AT = (2.0, 2.0)  # another robot's scans put this robot's body in the map here
UNSEEN_AT = (4.0, 1.0)  # the floor under a robot that never moved away: nobody saw it


def two_rooms() -> OccupancyGrid:
    """Seen from inside: room A (x 0-6 m) and room B (x 6.1-8 m) under a 2.5 m ceiling, 4 m
    deep, joined by a door (y 1.5-2.5 m, 2.1 m high) in the wall at x = 6; the back 1.2 m of
    room B was never seen; behind a wall without a door at x = 8, a closet (x 8.1-10 m) seen
    free (through a window, say). A robot body stands at ``BODY_AT``, unseen floor under
    another robot at ``UNSEEN_AT``."""
    i, j, k = np.meshgrid(np.arange(-1, 101), np.arange(-1, 41), np.arange(25), indexing="ij")
    cells = np.column_stack([i.ravel(), j.ravel(), k.ravel()])
    x, y, z = ((cells + 0.5) * RES).T
    wall = (cells[:, 0] == -1) | (cells[:, 0] == 100) | (cells[:, 1] == -1) | (cells[:, 1] == 40)
    wall |= cells[:, 0] == 80
    door = (y > 1.5) & (y < 2.5) & (z < 2.1)
    wall |= (cells[:, 0] == 60) & ~door
    body = (np.hypot(x - BODY_AT[0], y - BODY_AT[1]) <= 0.3) & (z < 0.4)
    unseen = ((x > 6.8) & (x < 8.0) & ~wall) | (
        (np.hypot(x - UNSEEN_AT[0], y - UNSEEN_AT[1]) <= 0.35) & (z < 0.5)
    )
    params = GridParams(resolution_m=RES)
    values = np.where(wall | body, params.logodds_max, params.logodds_min)
    return OccupancyGrid.from_cells(params, cells[~unseen], values[~unseen])


@pytest.fixture(scope="module")
def grid() -> OccupancyGrid:
    return two_rooms()


@pytest.fixture(scope="module")
def view(grid: OccupancyGrid) -> MapView:
    return MapView(grid, CONFIG, np.array([BODY_AT, UNSEEN_AT]))


def seen_whole() -> OccupancyGrid:
    """Rooms A (x 0-4 m) and B (x 4.1-8 m), 4 m deep under a 2.5 m ceiling, joined by a 1 m
    door (y 1.5-2.5 m) and seen whole: no frontier is left."""
    i, j, k = np.meshgrid(np.arange(-1, 81), np.arange(-1, 41), np.arange(25), indexing="ij")
    cells = np.column_stack([i.ravel(), j.ravel(), k.ravel()])
    y = (cells[:, 1] + 0.5) * RES
    wall = (cells[:, 0] == -1) | (cells[:, 0] == 80) | (cells[:, 1] == -1) | (cells[:, 1] == 40)
    wall |= (cells[:, 0] == 40) & ~((y > 1.5) & (y < 2.5))
    params = GridParams(resolution_m=RES)
    return OccupancyGrid.from_cells(params, cells, np.where(wall, params.logodds_max,
                                                            params.logodds_min))  # fmt: skip


def glimpsed(door: bool = True) -> OccupancyGrid:
    """Rooms A (x 0-4 m) and B (x 4.1-8 m), 4 m deep under a 2.5 m ceiling, joined by a 1.2 m
    door (y 1.4-2.6 m, 2.1 m high; with ``door`` False, a window above 0.9 m instead). Room A
    is seen whole; of room B only the first 0.3 m behind the wall and a narrow fan of rays from
    (1, 0.5) through the opening: a sliver of free floor, drivable only far from the opening."""
    i, j, k = np.meshgrid(np.arange(-1, 81), np.arange(-1, 41), np.arange(25), indexing="ij")
    cells = np.column_stack([i.ravel(), j.ravel(), k.ravel()])
    x, y, z = ((cells + 0.5) * RES).T
    wall = (cells[:, 0] == -1) | (cells[:, 0] == 80) | (cells[:, 1] == -1) | (cells[:, 1] == 40)
    opening = (y > 1.4) & (y < 2.6) & ((z < 2.1) if door else (z > 0.9) & (z < 2.1))
    wall |= (cells[:, 0] == 40) & ~opening
    bearing = np.arctan2(y - 0.5, x - 1.0)
    fan = (bearing > np.arctan2(1.3, 3.0)) & (bearing < np.arctan2(1.75, 3.0))
    unseen = (cells[:, 0] > 43) & (cells[:, 0] < 80) & ~fan
    params = GridParams(resolution_m=RES)
    values = np.where(wall, params.logodds_max, params.logodds_min)
    return OccupancyGrid.from_cells(params, cells[~unseen], values[~unseen])
