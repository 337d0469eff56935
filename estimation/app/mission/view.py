"""The planner's view of the estimated map at one moment (docs/design.md §13).

A :class:`MapView` of the occupancy grid as estimated (never the true world) holds its floor
columns at the robot's body height, the drivable space (known free floor, clear of obstacles and
of what nobody has seen), the rooms nobody stood in, and a 2D coverage model: what a scan would
add is the unknown floor inside the scanner's wedge up to its range, occluded by obstacle
columns. Beacon line of sight is tested on the 3D grid (unknown cells block it: a beacon behind
what nobody has seen may be hidden).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from scipy import ndimage

from estimation.app.config import Config
from estimation.app.sim.planning import BeaconGeometry, CoverageModel, grid_graph
from mapping.errors import MapError
from mapping.grid import OccupancyGrid
from mapping.traversability import (
    FloorMap,
    Room,
    drivable_space,
    floor_map,
    large_unknown,
    line_of_sight,
    unvisited_rooms,
)
from sensors.sim.planner import FreeSpace

__all__ = ["MIN_UNKNOWN_M2", "MapView"]

#: Unknown floor that counts as unexplored: regions of at least this much (m²).
MIN_UNKNOWN_M2 = 4.0
#: Rooms (``mapping.traversability.unvisited_rooms``): parted by passages up to this much
#: clearance (m) above the drivable space's least, persisting this much above it, with at least
#: this much drivable floor (m²).
_ROOM_LEVEL_M, _ROOM_PERSISTENCE_M, _ROOM_M2 = 0.9, 0.2, 2.0
#: Where a robot found its way blocked, an obstacle of this radius (m): what blocked it lies
#: within the robot's radius of that point, so the planner keeps its radius and margin off it.
_BLOCKED_M = 0.1
#: The floor's own layers (m): a column whose floor was seen, with nothing in the body band, is
#: free (``mapping.traversability.floor_map``). Generated building 17 ended with the last 2.4 m
#: of its corridor "unknown" (its floor seen, the body band only by rays reaching it steeply),
#: and the room whose door lay there never entered.
_GROUND_M = (-0.1, 0.1)
#: A beacon's line of sight passes unknown cells in runs up to this long (m): gaps between rays.
#: Generated building 10: from inside a room seen through its door, every line from the
#: mapper's scanner to the reference's beacon crossed one unseen cell just past the robot, and
#: no scan pose inside the room was ever offered.
_SIGHT_GAP_M = 0.2
#: Unknown floor added around the known map, m.
_BORDER_M = 1.0
#: Path-distance fields a view keeps (about 1 MB each on a 40 m × 30 m floor).
_KEPT_DISTANCES = 16


class MapView:
    """The estimated map as the planner sees it at one moment.

    ``stood_xy`` (N, 2) are the places robots stood (their estimated stop poses): the floor
    under a robot is free, the scanners cannot see it, and the other robots' scans put the
    robot's own body there; within the footprint (plus a cell) nothing counts as an obstacle,
    and within the footprint plus the margin nothing counts as unknown. ``robots_xy`` (M, 2) are
    where the robots stand now: beacon lines of sight ignore what the scans saw around them
    (their bodies and beacons). Only there: ignoring what lay around every place a robot ever
    stood blanked out furniture and door jambs all over a long mission's map, and the planner
    sent robots to poses from which a wall hid the beacons (building 3 of evaluate-missions:
    108 of 109 such misses were clear only because of it). ``blocked_xy`` (K, 2) are where
    refused goals found the robot's way blocked: each is an obstacle of ``_BLOCKED_M`` radius,
    so that no path is planned through it again (generated building 4 at 150 stations: 210 of
    282 refused goals on the same leg through a wall the map showed open)."""

    def __init__(self, grid: OccupancyGrid, config: Config, stood_xy: np.ndarray | None = None,
                 margin_m: float = 0.05, robots_xy: np.ndarray | None = None,
                 blocked_xy: np.ndarray | None = None) -> None:  # fmt: skip
        robot = config.robot
        self.grid = grid
        self.radius_m = robot.footprint_radius_m
        # A border of unknown floor around what is known: the room beyond a door nobody has
        # looked through is unknown space, not the end of the map.
        low, high = grid.bounds_cells()
        res = grid.resolution_m
        floor = floor_map(
            grid, body_z_m=(0.1, robot.body_height_m), ground_z_m=_GROUND_M,
            lower_xy=grid.origin_m[:2] + low[:2] * res - _BORDER_M,
            upper_xy=grid.origin_m[:2] + (high[:2] + 1) * res + _BORDER_M,
        )  # fmt: skip
        self.stood = np.zeros((0, 2)) if stood_xy is None else np.asarray(stood_xy).reshape(-1, 2)
        drivable = floor
        if len(self.stood):
            floor, drivable = _clear_where_stood(floor, self.stood, self.radius_m, margin_m)
        if blocked_xy is not None and len(blocked_xy):
            blocked = np.asarray(blocked_xy, dtype=float).reshape(-1, 2)
            seen = _block(floor, blocked)
            drivable = seen if drivable is floor else _block(drivable, blocked)
            floor = seen
        self.floor: FloorMap = floor
        # A robot's beacon sits ahead of its centre: ignore scans within reach of both.
        self._ignore_m = config.robot.scanner_x_m + config.beacon.offset_m + 0.25
        self.robots = np.zeros((0, 2)) if robots_xy is None else np.asarray(robots_xy)
        self.robots = self.robots.reshape(-1, 2)
        self.space: FreeSpace = drivable_space(
            drivable, robot_radius_m=self.radius_m, margin_m=margin_m
        )
        # What a scan adds: unknown floor of the regions a frontier leads to (the shadows of
        # furniture, never resolved, would keep the pair busy where it already is).
        self.unexplored = large_unknown(self.floor, MIN_UNKNOWN_M2)
        self.coverage = CoverageModel(
            self.space, ~self.floor.obstacle, ~self.unexplored, self.floor.obstacle
        )
        self.geometry = BeaconGeometry(config, line_clear=self._clear)
        self._graph: tuple[object, np.ndarray] | None = None
        self._distances: dict[tuple[int, ...], np.ndarray] = {}
        self._rooms: list[Room] | None = None

    def rooms(self) -> list[Room]:
        """The rooms of the drivable space that no robot stood in (computed once)."""
        if self._rooms is None:
            self._rooms = unvisited_rooms(
                self.space, self.stood, max_level_m=_ROOM_LEVEL_M,
                persistence_m=_ROOM_PERSISTENCE_M, min_area_m2=_ROOM_M2,
            )  # fmt: skip
        return self._rooms

    def _clear(self, start: np.ndarray, end: np.ndarray) -> bool:
        try:
            seen = line_of_sight(
                self.grid, start, end, start_clearance_m=0.3, end_clearance_m=0.3,
                unknown_blocks=True, ignore_xy=self.robots, ignore_radius_m=self._ignore_m,
                unknown_gap_m=_SIGHT_GAP_M,
            )  # fmt: skip
        except MapError:
            return False
        return seen and not self._walled(start, end)

    def _walled(self, start: np.ndarray, end: np.ndarray) -> bool:
        """Whether the segment, where it passes within ``_ignore_m`` of a robot standing now,
        crosses an occupied cell over an obstacle of the floor map (a wall, furniture; not a
        robot's body, cleared where robots stood). There the 3D cells are not tested (the
        robot's body and its beacon at every heading it turned to, which stand on free floor),
        and a wall beside the robot would not be either: a robot 0.42 m from a corridor wall
        saw through it into the hall beyond, and its partner was sent there (generated
        building 4: four scan poses unobserved, then lost)."""
        if not len(self.robots):
            return False
        floor, grid = self.floor, self.grid
        a, b = np.asarray(start, dtype=float), np.asarray(end, dtype=float)
        steps = max(2, math.ceil(2.0 * float(np.linalg.norm(b - a)) / grid.resolution_m) + 1)
        points = _over_obstacles(a, b, steps, self.robots, self._ignore_m, floor.obstacle,
                                 float(floor.lower_xy[0]), float(floor.lower_xy[1]),
                                 float(floor.resolution_m))  # fmt: skip
        if not len(points):
            return False
        cells = np.floor((points - np.asarray(grid.origin_m)) / grid.resolution_m)
        values = grid.logodds_at(cells.astype(np.int64))
        return bool(np.any(values > grid.params.logodds_threshold))

    def free_near(self, xy: np.ndarray, reach_m: float = 0.6) -> np.ndarray | None:
        """``xy`` if the robot may stand there, else the nearest drivable cell centre within
        ``reach_m`` (an estimate a few centimetres off can put a robot beside the space)."""
        if self.space.is_free(xy):
            return np.asarray(xy, dtype=float)[:2]
        row, col = self.space.cell(xy)
        res = self.space.resolution_m
        k = math.ceil(reach_m / res)
        h, w = self.space.free.shape
        r0, r1, c0, c1 = max(0, row - k), min(h, row + k + 1), max(0, col - k), min(w, col + k + 1)
        cells = np.argwhere(self.space.free[r0:r1, c0:c1]) + np.array([r0, c0])
        if not len(cells):
            return None
        centres = self.space.lower_xy + (cells[:, ::-1] + 0.5) * res
        d = np.hypot(*(centres - np.asarray(xy)[:2]).T)
        best = int(np.argmin(d))
        return centres[best] if d[best] <= reach_m else None

    def distances_from(self, sources_xy: list[np.ndarray]) -> np.ndarray:
        """Shortest-path distance (m) through the drivable space from the nearest of
        ``sources_xy`` to every cell (inf where unreachable); read-only. The last few are kept:
        a turn's pivots and each heading's candidates ask from the same place again."""
        from scipy.sparse.csgraph import dijkstra

        if self._graph is None:
            self._graph = grid_graph(self.space.free, self.space.resolution_m)
        graph, index = self._graph
        nodes = tuple(sorted({int(index[self.space.cell(p)]) for p in sources_xy
                              if self.space.is_free(p)}))  # fmt: skip
        if nodes in self._distances:
            return self._distances[nodes]
        out = np.full(self.space.free.shape, np.inf)
        if nodes:
            distance = dijkstra(graph, directed=False, indices=list(nodes), min_only=True)
            cells = np.argwhere(index >= 0)
            out[cells[:, 0], cells[:, 1]] = distance
        out.flags.writeable = False
        if len(self._distances) >= _KEPT_DISTANCES:
            del self._distances[next(iter(self._distances))]
        self._distances[nodes] = out
        return out

    def at(self, field_: np.ndarray, xy: np.ndarray) -> float:
        row, col = self.space.cell(xy)
        h, w = field_.shape
        return float(field_[row, col]) if 0 <= row < h and 0 <= col < w else math.inf


def _distance_to_points(floor: FloorMap, points: np.ndarray, reach_m: float) -> np.ndarray:
    """Per cell of ``floor``, the distance (m) from its centre to the nearest of ``points``
    (N, 2; non-finite ones skipped) when within ``reach_m``, else infinity."""
    res = floor.resolution_m
    h, w = floor.shape
    out = np.full((h, w), np.inf)
    k = math.ceil(reach_m / res) + 1
    for x, y in points[np.isfinite(points).all(axis=1)]:
        row = math.floor((y - floor.lower_xy[1]) / res)
        col = math.floor((x - floor.lower_xy[0]) / res)
        r0, r1, c0, c1 = max(0, row - k), min(h, row + k + 1), max(0, col - k), min(w, col + k + 1)
        if r0 >= r1 or c0 >= c1:
            continue
        ys = floor.lower_xy[1] + (np.arange(r0, r1) + 0.5) * res
        xs = floor.lower_xy[0] + (np.arange(c0, c1) + 0.5) * res
        window = out[r0:r1, c0:c1]
        np.minimum(window, np.hypot(xs[None, :] - x, ys[:, None] - y), out=window)
    return out


def _clear_where_stood(floor: FloorMap, stood: np.ndarray, radius_m: float,
                       margin_m: float) -> tuple[FloorMap, FloorMap]:  # fmt: skip
    """The floor map as seen and as driven (see :class:`MapView`). Driven: no obstacle within
    the footprint (plus a cell) of each place a robot stood, and nothing unknown within the
    footprint plus the margin. Seen: the same, but a structure reaching beyond that disk (an
    obstacle 8-connected to obstacles outside every disk: a wall, not a robot's body) keeps its
    cells outside the footprint. Generated building 1: b112 stood 4 cm from a wall; its
    surface was cleared, the unseen inside of the wall behind it looked like floor to explore,
    and b turned to face the wall, its sweep too near it to hold a ceiling."""
    res = floor.resolution_m
    d = _distance_to_points(floor, stood, radius_m + margin_m + res)
    body = d <= radius_m + res
    around = d <= radius_m + margin_m + res
    obstacle = floor.obstacle & ~body
    free = floor.free | body | (around & ~obstacle)
    driven = FloorMap(obstacle, free, floor.lower_xy, res)
    ring = floor.obstacle & body & (d > radius_m)  # cleared outside the footprint
    if not ring.any():
        return driven, driven
    labels, _ = ndimage.label(floor.obstacle, structure=np.ones((3, 3), dtype=bool))
    beyond = np.unique(labels[obstacle])
    structure = np.isin(labels, beyond[beyond > 0]) & ring
    if not structure.any():
        return driven, driven
    return FloorMap(obstacle | structure, free & ~structure, floor.lower_xy, res), driven


def _block(floor: FloorMap, points: np.ndarray) -> FloorMap:
    """The floor map with an obstacle within ``_BLOCKED_M`` of each of ``points`` (finite
    ones; those off the map change nothing)."""
    res = floor.resolution_m
    obstacle = floor.obstacle | (_distance_to_points(floor, points, _BLOCKED_M + res)
                                 <= _BLOCKED_M + res / 2)  # fmt: skip
    return FloorMap(obstacle, floor.free & ~obstacle, floor.lower_xy, res)


@njit(cache=True)
def _over_obstacles(
    a: np.ndarray, b: np.ndarray, steps: int, robots: np.ndarray, reach_m: float,
    obstacle: np.ndarray, lower_x: float, lower_y: float, resolution_m: float,
) -> np.ndarray:  # fmt: skip
    """Of ``steps`` points evenly along a → b (ends included, as ``np.linspace`` places them),
    those within ``reach_m`` (in the plane) of a robot that lie over an obstacle cell of the
    floor map (``obstacle``, rows y, columns x, from ``lower_x``, ``lower_y``)."""
    out = np.empty((steps, 3))
    n = 0
    h, w = obstacle.shape
    step = 1.0 / (steps - 1)
    for i in range(steps):
        t = 1.0 if i == steps - 1 else i * step
        x = a[0] + t * (b[0] - a[0])
        y = a[1] + t * (b[1] - a[1])
        near = False
        for r in range(len(robots)):
            if math.hypot(x - robots[r, 0], y - robots[r, 1]) <= reach_m:
                near = True
                break
        if not near:
            continue
        col = math.floor((x - lower_x) / resolution_m)
        row = math.floor((y - lower_y) / resolution_m)
        if 0 <= row < h and 0 <= col < w and obstacle[row, col]:
            out[n, 0] = x
            out[n, 1] = y
            out[n, 2] = a[2] + t * (b[2] - a[2])
            n += 1
    return out[:n]
