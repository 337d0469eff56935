"""Where a robot may drive on the map as estimated, and where the map ends: frontiers.

The mission loop plans on the estimated 3D grid, never on the true world (docs/design.md §13).
A floor column is an **obstacle** when a cell at the robot's body height is occupied, **free**
when enough of those cells were seen empty, and **unknown** otherwise. The robot's centre may
stand where the disc of its radius (plus a margin) holds no obstacle and its radius holds no
unknown column either: it never drives into what nobody has seen. **Frontier** cells are free
cells that reach to within one cell beyond the robot's radius of unknown floor that borders
seen free floor (not of the unknown far side of a wall); connected
frontier cells form a frontier, and a frontier reachable from the robot is a place to look next.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from mapping.band import Band, extract_band
from mapping.errors import MapError
from mapping.grid import OccupancyGrid
from mapping.kernels.traversal import ray_cells
from sensors.sim.planner import FreeSpace

__all__ = [
    "FloorMap",
    "Frontier",
    "drivable_space",
    "floor_map",
    "frontiers",
    "large_unknown",
    "line_of_sight",
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


def floor_map(
    grid: OccupancyGrid,
    *,
    body_z_m: tuple[float, float],
    free_min_observed: float = 0.5,
    max_gap_m2: float = 0.05,
    lower_xy: np.ndarray | tuple[float, float] | None = None,
    upper_xy: np.ndarray | tuple[float, float] | None = None,
) -> FloorMap:
    """The floor columns of ``grid`` between the heights ``body_z_m`` (above the floor cells
    themselves, up to the robot's top); a column is free when at least ``free_min_observed`` of
    its layers were seen and none is occupied. Unseen patches of at most ``max_gap_m2`` inside
    free floor (not at an obstacle or the border) are gaps between rays and count as free.
    MapError when the band holds nothing seen."""
    band: Band = extract_band(
        grid, body_z_m[0], body_z_m[1], free_min_observed=free_min_observed,
        lower_xy=lower_xy, upper_xy=upper_xy,
    )  # fmt: skip
    obstacle = band.known & (band.occupancy > 0.0)
    free = band.known & ~obstacle
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
) -> bool:
    """Whether the segment start → end (map frame, metres) crosses no occupied cell of the
    estimated map, nor (with ``unknown_blocks``) a cell nobody has seen; the first
    ``start_clearance_m`` and the last ``end_clearance_m`` (the observer's own body, the target
    itself, e.g. a beacon's cylinder) are not tested, nor cells within ``ignore_radius_m`` (in
    the plane) of the points ``ignore_xy`` (N, 2) — where robots stood, whose bodies other
    robots' scans put in the map. The cells are those the fusion's own traversal visits."""
    start = np.asarray(start_m, dtype=float)
    end = np.asarray(end_m, dtype=float)
    if not (np.isfinite(start).all() and np.isfinite(end).all()):
        raise MapError(f"line of sight needs finite end points, got {start} and {end}")
    for name, value in (("start_clearance_m", start_clearance_m),
                        ("end_clearance_m", end_clearance_m)):  # fmt: skip
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
    cells = ray_cells((first - origin) / res, (stop - origin) / res, True)
    if ignore_xy is not None and len(ignore_xy) and ignore_radius_m > 0:
        centres = grid.cell_centers(cells)[:, :2]
        points = np.asarray(ignore_xy, dtype=float).reshape(-1, 2)
        near = np.hypot(centres[:, None, 0] - points[None, :, 0],
                        centres[:, None, 1] - points[None, :, 1]) <= ignore_radius_m  # fmt: skip
        cells = cells[~near.any(axis=1)]
    values = grid.logodds_at(cells)
    if unknown_blocks and np.isnan(values).any():
        return False
    return not bool(np.any(values > grid.params.logodds_threshold))


def _distance_to(mask: np.ndarray, resolution_m: float) -> np.ndarray:
    """Distance (m) from each cell to the nearest cell of ``mask``; cells beyond the grid's
    border count as part of the mask."""
    padded = np.pad(mask, 1, constant_values=True)
    distance = ndimage.distance_transform_edt(~padded) * resolution_m
    return np.asarray(distance[1:-1, 1:-1])
