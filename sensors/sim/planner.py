"""Where a robot can drive in a world: configuration space, paths, and line of sight.

The configuration space is a 2D grid of the positions where a round robot of radius r fits:
inside a room, at least r (plus a margin) from every wall, and from every object low enough to
hit its body. Walls are open where a door (an opening from the floor up past the robot's
height) cuts them. Paths are A* on that grid (8-connected), shortened to straight legs that stay
in free space.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from sensors.errors import SensorError
from sensors.sim.polygon import points_in_polygon
from sensors.sim.world import World

__all__ = ["FreeSpace", "free_space"]


@dataclass(frozen=True)
class FreeSpace:
    """Cells (row = y, col = x) where the robot's centre may be; ``clearance_m`` to obstacles."""

    free: np.ndarray  # (H, W) bool
    clearance_m: np.ndarray  # (H, W) distance to the nearest obstacle cell
    lower_xy: np.ndarray  # map-frame corner of cell (0, 0)
    resolution_m: float

    def cell(self, xy: np.ndarray | tuple[float, float]) -> tuple[int, int]:
        x, y = float(xy[0]), float(xy[1])
        return (
            math.floor((y - self.lower_xy[1]) / self.resolution_m),
            math.floor((x - self.lower_xy[0]) / self.resolution_m),
        )

    def center(self, cell: tuple[int, int]) -> np.ndarray:
        row, col = cell
        return self.lower_xy + (np.array([col, row]) + 0.5) * self.resolution_m

    def is_free(self, xy: np.ndarray | tuple[float, float]) -> bool:
        row, col = self.cell(xy)
        h, w = self.free.shape
        return 0 <= row < h and 0 <= col < w and bool(self.free[row, col])

    def segment_free(self, a: np.ndarray, b: np.ndarray) -> bool:
        """Whether the straight leg a → b stays in free space (sampled at a quarter cell)."""
        return self.first_blocked(a, b) is None

    def first_blocked(self, a: np.ndarray, b: np.ndarray) -> np.ndarray | None:
        """The first point of the straight leg a → b (sampled at a quarter cell) that is not
        in free space, or None when the whole leg is."""
        a, b = np.asarray(a, float)[:2], np.asarray(b, float)[:2]
        steps = max(1, math.ceil(float(np.linalg.norm(b - a)) / (self.resolution_m / 4)))
        for s in np.linspace(0.0, 1.0, steps + 1):
            point = a + s * (b - a)
            if not self.is_free(point):
                return point
        return None

    def component_of(self, xy: np.ndarray | tuple[float, float]) -> np.ndarray:
        """The free cells connected to ``xy`` (8-connected)."""
        labels, _ = ndimage.label(self.free, structure=np.ones((3, 3)))
        row, col = self.cell(xy)
        if not self.is_free(xy):
            return np.zeros_like(self.free)
        return np.asarray(labels == labels[row, col])

    def path(self, start: np.ndarray, goal: np.ndarray) -> list[np.ndarray] | None:
        """Straight legs from ``start`` to ``goal`` through free space, or None if unreachable."""
        start, goal = np.asarray(start, float)[:2], np.asarray(goal, float)[:2]
        if not (self.is_free(start) and self.is_free(goal)):
            return None
        if self.segment_free(start, goal):
            return [start, goal]
        cells = _astar(self.free, self.cell(start), self.cell(goal))
        if cells is None:
            return None
        points = [start] + [self.center(c) for c in cells[1:-1]] + [goal]
        # Keep only the corners: jump as far ahead as a straight free leg reaches.
        legs = [points[0]]
        i = 0
        while i < len(points) - 1:
            j = len(points) - 1
            while j > i + 1 and not self.segment_free(points[i], points[j]):
                j -= 1
            legs.append(points[j])
            i = j
        return legs


def _astar(
    free: np.ndarray, start: tuple[int, int], goal: tuple[int, int]
) -> list[tuple[int, int]] | None:
    h, w = free.shape
    moves = [(-1, -1, math.sqrt(2)), (-1, 0, 1.0), (-1, 1, math.sqrt(2)), (0, -1, 1.0),
             (0, 1, 1.0), (1, -1, math.sqrt(2)), (1, 0, 1.0), (1, 1, math.sqrt(2))]  # fmt: skip
    best = {start: 0.0}
    parent: dict[tuple[int, int], tuple[int, int]] = {}
    queue = [(math.dist(start, goal), 0.0, start)]
    while queue:
        _, cost, node = heapq.heappop(queue)
        if node == goal:
            path = [node]
            while node in parent:
                node = parent[node]
                path.append(node)
            return path[::-1]
        if cost > best.get(node, math.inf):
            continue
        for dr, dc, step in moves:
            nxt = (node[0] + dr, node[1] + dc)
            if not (0 <= nxt[0] < h and 0 <= nxt[1] < w) or not free[nxt]:
                continue
            # No corner cutting between two blocked cells.
            if dr and dc and not (free[node[0] + dr, node[1]] and free[node[0], node[1] + dc]):
                continue
            new = cost + step
            if new < best.get(nxt, math.inf):
                best[nxt] = new
                parent[nxt] = node
                heapq.heappush(queue, (new + math.dist(nxt, goal), new, nxt))
    return None


def free_space(
    world: World,
    *,
    robot_radius_m: float,
    robot_height_m: float,
    margin_m: float = 0.1,
    resolution_m: float = 0.1,
) -> FreeSpace:
    """The configuration space of a round robot in ``world``."""
    if resolution_m <= 0 or robot_radius_m <= 0:
        raise SensorError("free space needs a positive resolution and robot radius")
    lower, upper = world.bounds_xy()
    lower = lower - 1.0
    shape = np.ceil((upper + 1.0 - lower) / resolution_m).astype(int)
    xs = lower[0] + (np.arange(shape[0]) + 0.5) * resolution_m
    ys = lower[1] + (np.arange(shape[1]) + 0.5) * resolution_m
    gx, gy = np.meshgrid(xs, ys)
    centers = np.column_stack([gx.ravel(), gy.ravel()])
    inside = world.inside(centers).reshape(gx.shape)
    blocked = ~inside

    def mark(points: np.ndarray) -> None:
        cols = np.floor((points[:, 0] - lower[0]) / resolution_m).astype(int)
        rows = np.floor((points[:, 1] - lower[1]) / resolution_m).astype(int)
        ok = (rows >= 0) & (rows < shape[1]) & (cols >= 0) & (cols < shape[0])
        blocked[rows[ok], cols[ok]] = True

    step = resolution_m / 3
    for room in world.rooms:
        polygon = room.footprint_xy
        for i in range(len(polygon)):
            a, b = polygon[i], polygon[(i + 1) % len(polygon)]
            length = float(np.linalg.norm(b - a))
            s = np.arange(0.0, length + step, step)
            s = s[s <= length]
            passable = np.zeros(len(s), dtype=bool)
            for o in room.openings:
                if o.wall == i and o.bottom_m <= 0.05 and o.top_m >= robot_height_m:
                    passable |= (s > o.from_m) & (s < o.to_m)
            mark(a + np.outer(s[~passable] / length, b - a))
    for box in world.boxes:
        if box.z_m[0] < robot_height_m:
            blocked |= points_in_polygon(centers, box.corners_xy()).reshape(gx.shape)
    for cyl in world.cylinders:
        if cyl.z_m[0] < robot_height_m:
            near = np.hypot(centers[:, 0] - cyl.center[0], centers[:, 1] - cyl.center[1])
            blocked |= (near <= cyl.radius_m).reshape(gx.shape)
    clearance = ndimage.distance_transform_edt(~blocked) * resolution_m
    free = (clearance > robot_radius_m + margin_m) & inside
    return FreeSpace(free, clearance, lower, resolution_m)
