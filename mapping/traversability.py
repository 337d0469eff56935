"""Where a robot may drive on the map as estimated, and where the map ends: frontiers.

The mission loop plans on the estimated 3D grid, never on the true world (docs/design.md §13).
A floor column is an **obstacle** when a cell at the robot's body height is occupied, **free**
when enough of those cells were seen empty, and **unknown** otherwise. The robot's centre may
stand where the disc of its radius (plus a margin) holds no obstacle and its radius holds no
unknown column either: it never drives into what nobody has seen. **Frontier** cells are free
cells that reach to within one cell beyond the robot's radius of unknown floor that borders
seen free floor (not of the unknown far side of a wall); connected
frontier cells form a frontier, and a frontier reachable from the robot is a place to look next.

**Rooms** are parts of the drivable space that narrow passages (doorways) set apart: at some
clearance level the cells at least that far from every obstacle and unknown column fall into
separate cores, and a core that stays wide well above that level is a room rather than a wide
spot of a corridor (its clearance persists; a corridor's pieces vanish just above the level that
parts them). A room nobody stood in is a place to go once no frontier is left: a room seen
whole through its doors has no frontier, yet it was never entered.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from mapping.band import Band, extract_band
from mapping.errors import MapError
from mapping.grid import OccupancyGrid
from sensors.sim.planner import FreeSpace

__all__ = [
    "FloorMap",
    "Frontier",
    "Room",
    "drivable_space",
    "floor_map",
    "frontiers",
    "large_unknown",
    "line_of_sight",
    "unvisited_rooms",
]


@dataclass(frozen=True)
class FloorMap:
    """Floor columns of the estimated map: (H, W) masks, row = y, column = x."""

    obstacle: np.ndarray
    free: np.ndarray
    lower_xy: np.ndarray
    resolution_m: float

    @property
    def unknown(self) -> np.ndarray:
        return np.asarray(~(self.obstacle | self.free))

    @property
    def shape(self) -> tuple[int, int]:
        rows, cols = self.obstacle.shape
        return rows, cols


@dataclass(frozen=True)
class Frontier:
    """Connected free cells at the edge of the known map."""

    cells: np.ndarray  # (N, 2) (row, col)
    centroid_xy: np.ndarray  # (2,) map frame
    size: int


@dataclass(frozen=True)
class Room:
    """A room's core: ``cells`` (N, 2) (row, col) farther than ``level_m`` from every obstacle
    and unknown column, their mean ``centroid_xy`` (map frame), ``size`` cells, and the drivable
    floor within reach of the core, ``area_m2``."""

    cells: np.ndarray
    centroid_xy: np.ndarray
    size: int
    level_m: float
    area_m2: float


def floor_map(
    grid: OccupancyGrid,
    *,
    body_z_m: tuple[float, float],
    free_min_observed: float = 0.5,
    max_gap_m2: float = 0.05,
    lower_xy: np.ndarray | tuple[float, float] | None = None,
    upper_xy: np.ndarray | tuple[float, float] | None = None,
    ground_z_m: tuple[float, float] | None = None,
) -> FloorMap:
    """The floor columns of ``grid`` between the heights ``body_z_m`` (above the floor cells
    themselves, up to the robot's top); a column is free when at least ``free_min_observed`` of
    its layers were seen and none is occupied. Unseen patches of at most ``max_gap_m2`` inside
    free floor (not at an obstacle or the border) are gaps between rays and count as free.
    With ``ground_z_m`` (the floor's own layers), a column whose floor was seen is free too
    unless a layer of the band is occupied: a ray that reaches the floor steeply (over a desk,
    down the far end of a corridor) crosses each layer of the band in another column, so such
    columns hold fewer seen layers than ``free_min_observed`` though nothing stands there.
    MapError when the band holds nothing seen."""
    band: Band = extract_band(
        grid, body_z_m[0], body_z_m[1], free_min_observed=free_min_observed,
        lower_xy=lower_xy, upper_xy=upper_xy,
    )  # fmt: skip
    obstacle = band.known & (band.occupancy > 0.0)
    free = band.known & ~obstacle
    if ground_z_m is not None:
        rows, cols = obstacle.shape
        half = band.resolution_m / 2
        ground = extract_band(
            grid, ground_z_m[0], ground_z_m[1], lower_xy=band.lower_xy + half,
            upper_xy=band.lower_xy + np.array([cols, rows]) * band.resolution_m - half,
        )  # fmt: skip
        free |= ground.known & ~obstacle
    # Far from the scanner, rays thin out: single unseen columns between seen-free ones are
    # gaps in the sampling, not unexplored space (they would make frontiers everywhere).
    res = band.resolution_m
    gaps, count = ndimage.label(~(obstacle | free))
    if count:
        sizes = np.bincount(gaps.ravel(), minlength=count + 1)
        touching = np.zeros(count + 1, dtype=bool)
        border = np.concatenate([gaps[0], gaps[-1], gaps[:, 0], gaps[:, -1]])
        touching[border] = True
        touching[gaps[ndimage.binary_dilation(obstacle, structure=np.ones((3, 3)))]] = True
        small = (sizes * res * res <= max_gap_m2) & ~touching
        small[0] = False
        free |= small[gaps]
    return FloorMap(obstacle, free, band.lower_xy, res)


def drivable_space(floor: FloorMap, *, robot_radius_m: float, margin_m: float = 0.1) -> FreeSpace:
    """Where the robot's centre may be: ``robot_radius_m + margin_m`` clear of obstacles and
    ``robot_radius_m`` clear of unknown columns (a map border counts as unknown)."""
    if not robot_radius_m > 0 or margin_m < 0:
        raise MapError(f"need a positive robot radius and a margin >= 0, got {robot_radius_m}, "
                       f"{margin_m}")  # fmt: skip
    res = floor.resolution_m
    to_obstacle = _distance_to(floor.obstacle, res)
    to_unknown = _distance_to(floor.unknown, res)
    free = floor.free & (to_obstacle > robot_radius_m + margin_m) & (to_unknown > robot_radius_m)
    return FreeSpace(free, np.minimum(to_obstacle, to_unknown), floor.lower_xy, res)


def frontiers(
    floor: FloorMap,
    space: FreeSpace,
    *,
    robot_radius_m: float,
    from_xy: np.ndarray | tuple[float, float] | None = None,
    min_cells: int = 3,
    min_unknown_m2: float = 0.0,
) -> list[Frontier]:
    """Frontiers of the drivable space, largest first; with ``from_xy`` only those the robot
    standing there can reach. Frontiers of fewer than ``min_cells`` cells are dropped, and
    with ``min_unknown_m2`` those that border only unknown patches smaller than that (the
    shadow behind a desk, not the room beyond a door; unknown space that reaches the map's
    border is never small).

    Only unknown floor farther than ``robot_radius_m`` from every obstacle counts: where a
    robot could stand. A gap in a wall that the scans missed (narrower than the robot) then
    opens onto nothing, and the corner behind it is no longer joined to the unknown space
    beyond the wall; a doorway wider than the robot still opens onto the room behind it."""
    res = floor.resolution_m
    unknown = _passable_unknown(floor, robot_radius_m, min_unknown_m2)
    # Where seen free floor meets unknown floor; unknown space that meets only obstacles (the
    # far side of a wall) is no frontier.
    cross = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], dtype=bool)
    unknown = unknown & ndimage.binary_dilation(floor.free, structure=cross)
    near_unknown = _distance_to(unknown, res) <= robot_radius_m + 1.5 * res
    edge = space.free & near_unknown
    if from_xy is not None:
        if not space.is_free(from_xy):
            raise MapError(f"the robot at {tuple(map(float, from_xy))} stands outside the "
                           "drivable space of the estimated map")  # fmt: skip
        edge &= space.component_of(from_xy)
    labels, count = ndimage.label(edge, structure=np.ones((3, 3)))
    found = []
    for label in range(1, count + 1):
        cells = np.argwhere(labels == label)
        if len(cells) < min_cells:
            continue
        centroid = floor.lower_xy + (cells[:, ::-1].mean(axis=0) + 0.5) * res
        found.append(Frontier(cells, centroid, len(cells)))
    return sorted(found, key=lambda f: -f.size)


def _passable_unknown(floor: FloorMap, radius_m: float, min_unknown_m2: float) -> np.ndarray:
    """The unknown cells farther than ``radius_m`` from every obstacle cell, in connected regions
    (8-connected) whose unknown floor — the region and the unknown cells within ``radius_m`` of
    it — covers at least ``min_unknown_m2``, or reaches the map's border."""
    res = floor.resolution_m
    unknown = floor.unknown
    # Distances run between cell centres: an obstacle cell's edge lies half a cell nearer.
    clearance = ndimage.distance_transform_edt(~floor.obstacle) * res - res / 2
    passable = unknown & (clearance > radius_m)
    if min_unknown_m2 <= 0 or not passable.any():
        return np.asarray(passable)
    labels, count = ndimage.label(passable, structure=np.ones((3, 3)))
    distance, (rows, cols) = ndimage.distance_transform_edt(~passable, return_indices=True)
    grown = np.where(unknown & (distance * res <= radius_m + res), labels[rows, cols], 0)
    large = np.bincount(grown.ravel(), minlength=count + 1) * res * res >= min_unknown_m2
    large[np.concatenate([grown[0], grown[-1], grown[:, 0], grown[:, -1]])] = True
    large[0] = False
    return np.asarray(large[labels])


def unvisited_rooms(
    space: FreeSpace,
    stood_xy: np.ndarray,
    *,
    max_level_m: float,
    persistence_m: float,
    min_area_m2: float,
    reach_m: float = 0.2,
) -> list[Room]:
    """The rooms of the drivable space (see the module's docstring) in which no point of
    ``stood_xy`` (N, 2) lies, largest first.

    The clearance levels run from one cell above the drivable space's smallest clearance ``c0``
    up to ``c0 + max_level_m`` in half cells. At each level a connected core (8-connected)
    counts when its own clearance reaches ``persistence_m`` above the level and the drivable
    floor within ``level - c0`` of it (where the robot's disc fits, on the core's side of
    every wall) covers ``min_area_m2``. A point stood in it when it lies within ``level - c0 +
    reach_m`` of the core; a core that is the only one of a room's size inside a core of the
    level below was stood in if that one was. A room is reported at the lowest level at which
    it is unvisited; a core inside a room already reported is the same room."""
    free, clearance, res = space.free, space.clearance_m, space.resolution_m
    stood = np.asarray(stood_xy, dtype=float).reshape(-1, 2)
    if not (free.any() and math.isfinite(max_level_m) and math.isfinite(persistence_m)):
        return []
    if not np.isfinite(stood).all():
        raise MapError("unvisited rooms: the places stood in must be finite")
    cells = np.floor((stood - space.lower_xy) / res).astype(np.int64)[:, ::-1]  # (row, col)
    h, w = free.shape
    cells = cells[(cells[:, 0] >= 0) & (cells[:, 0] < h) & (cells[:, 1] >= 0) & (cells[:, 1] < w)]
    base = float(clearance[free].min())
    found: list[Room] = []
    reported = np.zeros_like(free)
    parents, parents_visited = np.zeros(free.shape, dtype=np.int64), np.zeros(1, dtype=bool)
    for level in np.arange(base + res, base + max_level_m + 1e-9, res / 2):
        core = free & (clearance >= level)
        labels, count = ndimage.label(core, structure=np.ones((3, 3)))
        if not count:
            break
        index = np.arange(1, count + 1)
        peak = np.asarray(ndimage.maximum(clearance, labels, index))
        grow = level - base
        distance, (rows, cols) = ndimage.distance_transform_edt(~core, return_indices=True)
        distance = distance * res
        owner = labels[rows, cols]
        area = np.bincount(owner[free & (distance <= grow)], minlength=count + 1) * res * res
        visited = np.zeros(count + 1, dtype=bool)
        if len(cells):
            near = distance[cells[:, 0], cells[:, 1]] <= grow + reach_m
            visited[owner[cells[near, 0], cells[near, 1]]] = True
        # A core that is its parent's only core of a room's size is that core, shrunk: it was
        # visited if its parent was (a robot by the wall stands farther from a smaller core).
        first = np.zeros(count + 1, dtype=np.int64)
        first[labels[core]] = parents[core]
        sized = np.flatnonzero(area >= min_area_m2)
        children = np.bincount(first[sized], minlength=len(parents_visited))
        only = (children[first] == 1) & parents_visited[first]
        visited |= only
        for label in index:
            if visited[label] or peak[label - 1] < level + persistence_m:
                continue
            if area[label] < min_area_m2:
                continue
            mask = labels == label
            if reported[mask].any():
                continue
            reported |= mask
            room = np.argwhere(mask)
            centroid = space.lower_xy + (room[:, ::-1].mean(axis=0) + 0.5) * res
            found.append(Room(room, centroid, len(room), float(level), float(area[label])))
        parents, parents_visited = labels, visited
    return sorted(found, key=lambda r: -r.area_m2)


def large_unknown(floor: FloorMap, min_unknown_m2: float) -> np.ndarray:
    """The unknown floor cells in connected unknown regions of at least ``min_unknown_m2``
    (8-connected), or reaching the map's border."""
    res = floor.resolution_m
    labels, count = ndimage.label(floor.unknown, structure=np.ones((3, 3)))
    sizes = np.bincount(labels.ravel(), minlength=count + 1) * res * res
    large = sizes >= min_unknown_m2
    border = np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])
    large[border] = True
    large[0] = False
    return np.asarray(large[labels])


def line_of_sight(
    grid: OccupancyGrid,
    start_m: np.ndarray,
    end_m: np.ndarray,
    *,
    end_clearance_m: float = 0.15,
    start_clearance_m: float = 0.0,
    unknown_blocks: bool = True,
    ignore_xy: np.ndarray | None = None,
    ignore_radius_m: float = 0.0,
    unknown_gap_m: float = 0.0,
) -> bool:
    """Whether the segment start → end (map frame, metres) crosses no occupied cell of the
    estimated map, nor (with ``unknown_blocks``) a cell nobody has seen, except in runs of
    unknown cells no longer than ``unknown_gap_m`` (cells, rounded down: gaps between rays that
    a wall does not leave, for the space behind a wall is unseen too); the first
    ``start_clearance_m`` and the last ``end_clearance_m`` (the observer's own body, the target
    itself, e.g. a beacon's cylinder) are not tested, nor cells within ``ignore_radius_m`` (in
    the plane) of the points ``ignore_xy`` (N, 2) — where robots stood, whose bodies other
    robots' scans put in the map. The cells are those the fusion's own traversal visits."""
    start = np.asarray(start_m, dtype=float)
    end = np.asarray(end_m, dtype=float)
    if not (np.isfinite(start).all() and np.isfinite(end).all()):
        raise MapError(f"line of sight needs finite end points, got {start} and {end}")
    for name, value in (("start_clearance_m", start_clearance_m),
                        ("end_clearance_m", end_clearance_m),
                        ("unknown_gap_m", unknown_gap_m)):  # fmt: skip
        if not (math.isfinite(value) and value >= 0):
            raise MapError(f"line of sight: {name} must be finite and >= 0, got {value}")
    if (
        ignore_xy is not None
        and len(ignore_xy)
        and not (
            np.isfinite(np.asarray(ignore_xy, dtype=float)).all()
            and math.isfinite(ignore_radius_m)
            and ignore_radius_m >= 0
        )
    ):
        raise MapError("line of sight: the ignored points and their radius must be finite")
    length = float(np.linalg.norm(end - start))
    if length <= end_clearance_m + start_clearance_m:
        return True
    first = start + (end - start) * (start_clearance_m / length)
    stop = start + (end - start) * (1.0 - end_clearance_m / length)
    origin, res = grid.origin_m, grid.resolution_m
    ignore = np.zeros((0, 2)) if ignore_xy is None else np.asarray(ignore_xy, dtype=float)
    return not grid.segment_blocked(
        (first - origin) / res, (stop - origin) / res, unknown_blocks=unknown_blocks,
        ignore_xy=ignore, ignore_radius_m=ignore_radius_m if len(ignore) else 0.0,
        unknown_gap_cells=math.floor(unknown_gap_m / res + 1e-9),
    )  # fmt: skip


def _distance_to(mask: np.ndarray, resolution_m: float) -> np.ndarray:
    """Distance (m) from each cell to the nearest cell of ``mask``; cells beyond the grid's
    border count as part of the mask."""
    padded = np.pad(mask, 1, constant_values=True)
    distance = ndimage.distance_transform_edt(~padded) * resolution_m
    return np.asarray(distance[1:-1, 1:-1])
