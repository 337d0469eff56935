"""How much of the building a mission explored: floor coverage and the rooms entered.

**Floor coverage** is the share of the building's reachable floor (where the robot's centre
fits, in the part of the true world joined to the robots' starts) that the estimated map knows:
the floor surface itself was seen, or the column at the robot's body height is known free or
occupied (``mapping.traversability.floor_map``).
A **room is entered** when a robot's true position lay inside it at some instant (the ground
truth's samples); rooms are counted when some of their floor is reachable.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mapping.errors import MapError
from mapping.grid import OccupancyGrid
from mapping.traversability import floor_map
from sensors.sim.planner import FreeSpace
from sensors.sim.world import World

__all__ = ["floor_coverage"]

#: Floor cells above this height are part of the body band (the floor's own cells lie below).
FLOOR_CLEAR_M = 0.1


def floor_coverage(
    world: World,
    space: FreeSpace,
    grid: OccupancyGrid,
    starts_xy: list[np.ndarray],
    truth_xy: dict[str, np.ndarray],
    body_height_m: float,
) -> dict[str, Any]:
    """``coverage`` (share of the reachable floor the map knows), the reachable and known cell
    counts, and the rooms with reachable floor and those entered (by name, sorted)."""
    reachable = np.zeros_like(space.free)
    for xy in starts_xy:
        if space.is_free(xy):
            reachable |= space.component_of(xy)
    rows, cols = np.nonzero(reachable)
    centres = space.lower_xy + (np.column_stack([cols, rows]) + 0.5) * space.resolution_m
    known = np.zeros(len(centres), dtype=bool)
    if len(centres):
        # The planner's floor map (``ground_z_m``: a column whose floor was seen is known).
        try:
            floor = floor_map(
                grid, body_z_m=(FLOOR_CLEAR_M, body_height_m),
                ground_z_m=(-FLOOR_CLEAR_M, FLOOR_CLEAR_M),
                lower_xy=centres.min(axis=0), upper_xy=centres.max(axis=0),
            )  # fmt: skip
        except MapError:  # nothing seen there
            floor = None
        if floor is not None:
            ij = np.floor((centres - floor.lower_xy) / floor.resolution_m).astype(int)
            h, w = floor.shape
            inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
            known[inside] = ~floor.unknown[ij[inside, 1], ij[inside, 0]]
    rooms_reachable = _rooms_holding(world, centres)
    entered = set().union(*(_rooms_holding(world, xy) for xy in truth_xy.values()))
    return {
        "coverage": float(known.mean()) if len(known) else 0.0,
        "reachable_cells": len(known),
        "known_cells": int(known.sum()),
        "rooms": rooms_reachable,
        "rooms_entered": sorted(entered & set(rooms_reachable)),
    }


def _rooms_holding(world: World, points_xy: np.ndarray) -> list[str]:
    """The rooms (sorted names) that hold at least one of the (N, 2) points."""
    points = np.asarray(points_xy, dtype=float).reshape(-1, 2)
    if not len(points):
        return []
    return sorted(room.name for room in world.rooms if bool(np.any(room.contains(points))))
