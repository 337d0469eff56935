"""Synthetic 2D scenes for the global-localization search: tests, the benchmark, calibration.

A scene is drawn in continuous coordinates — thick wall segments and solid rectangles (beams,
pillars, ducts seen in a sub-ceiling band) inside a known rectangle — and rasterised into any
grid frame by supersampling each cell, so a map and a local view of it are two independent
discretisations, as two real maps of one building are. A local view keeps the cells within a
radius of the robot, adds occupancy noise and drops cells (unknown), like a local ceiling map.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimation.errors import EstimationError
from mapping.band import Band
from sensors.geometry import se2

__all__ = [
    "Scene",
    "corridor",
    "distinctive_room",
    "local_view",
    "office_floor",
    "random_building",
    "rasterise",
]

#: Grids with more cells than this are rasterised tile by tile, each against the geometry near it.
_TILED_CELLS = 250_000
#: Cells along a tile's side.
_TILE = 100


@dataclass(frozen=True)
class Scene:
    """Occupied geometry in the scene frame (metres) and the rectangle where cells are known."""

    walls: np.ndarray  # (N, 4): x0, y0, x1, y1 of wall centre lines
    wall_thickness_m: float
    boxes: np.ndarray  # (M, 5): centre x, centre y, size x, size y, yaw (rad)
    known_lo: np.ndarray  # (2,) known rectangle
    known_hi: np.ndarray

    def occupied(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: the points (N, 2) lie on a wall or in a box."""
        hit = np.zeros(len(points), dtype=bool)
        half = self.wall_thickness_m / 2.0
        for x0, y0, x1, y1 in self.walls:
            a = np.array([x0, y0])
            d = np.array([x1 - x0, y1 - y0])
            t = np.clip(((points - a) @ d) / max(float(d @ d), 1e-12), 0.0, 1.0)
            hit |= np.sum((points - a - t[:, None] * d) ** 2, axis=1) <= half * half
        for cx, cy, sx, sy, yaw in self.boxes:
            c, s = math.cos(yaw), math.sin(yaw)
            rel = points - (cx, cy)
            along = rel @ np.array([c, s])
            across = rel @ np.array([-s, c])
            hit |= (np.abs(along) <= sx / 2) & (np.abs(across) <= sy / 2)
        return hit

    def near(self, lo: np.ndarray, hi: np.ndarray) -> Scene:
        """The walls and boxes whose occupied area reaches into the rectangle [lo, hi]."""
        half = self.wall_thickness_m / 2.0
        w = self.walls
        keep_w = (
            (np.minimum(w[:, 0], w[:, 2]) - half <= hi[0])
            & (np.maximum(w[:, 0], w[:, 2]) + half >= lo[0])
            & (np.minimum(w[:, 1], w[:, 3]) - half <= hi[1])
            & (np.maximum(w[:, 1], w[:, 3]) + half >= lo[1])
        )
        b = self.boxes
        reach = 0.5 * np.hypot(b[:, 2], b[:, 3])  # a box lies within its half diagonal
        keep_b = np.all(
            (b[:, :2] - reach[:, None] <= hi) & (b[:, :2] + reach[:, None] >= lo), axis=1
        )
        return Scene(
            walls=w[keep_w].reshape(-1, 4),
            wall_thickness_m=self.wall_thickness_m,
            boxes=b[keep_b].reshape(-1, 5),
            known_lo=self.known_lo,
            known_hi=self.known_hi,
        )

    def inside(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(np.all((points >= self.known_lo) & (points <= self.known_hi), axis=1))

    @property
    def size_m(self) -> np.ndarray:
        return np.asarray(self.known_hi - self.known_lo)


def rasterise(
    scene: Scene,
    T_scene_grid: np.ndarray,
    lower_xy: np.ndarray | tuple[float, float],
    shape: tuple[int, int],
    resolution_m: float,
    *,
    supersample: int = 3,
) -> Band:
    """A band of ``shape`` (rows, cols) cells in a grid frame whose pose in the scene is
    ``T_scene_grid`` (x, y, yaw): each cell's occupancy is the share of its s×s sub-samples that
    fall on occupied geometry; a cell is known when its centre lies in the known rectangle.

    Large grids are rasterised tile by tile against the geometry that reaches each tile: the same
    tests on the same points, so the same band."""
    rows, cols = shape
    lower = np.asarray(lower_xy, dtype=float)
    if rows * cols > _TILED_CELLS:
        occupancy = np.zeros(shape)
        known = np.zeros(shape, dtype=bool)
        T = se2.matrix(np.asarray(T_scene_grid, dtype=float))
        for r0 in range(0, rows, _TILE):
            for c0 in range(0, cols, _TILE):
                size = (min(_TILE, rows - r0), min(_TILE, cols - c0))
                tile_lower = lower + resolution_m * np.array([c0, r0])
                corners = tile_lower + resolution_m * np.array(
                    [[0, 0], [size[1], 0], [0, size[0]], [size[1], size[0]]]
                )
                placed = corners @ T[:2, :2].T + T[:2, 2]
                part = scene.near(placed.min(axis=0), placed.max(axis=0))
                tile = rasterise(part, T_scene_grid, tile_lower, size, resolution_m,
                                 supersample=supersample)  # fmt: skip
                occupancy[r0 : r0 + size[0], c0 : c0 + size[1]] = tile.occupancy
                known[r0 : r0 + size[0], c0 : c0 + size[1]] = tile.known
        return Band(occupancy=occupancy, known=known, lower_xy=lower, resolution_m=resolution_m)
    sub = (np.arange(supersample) + 0.5) / supersample
    ys, xs = np.meshgrid(
        lower[1] + (np.arange(rows)[:, None] + sub[None, :]).ravel() * resolution_m,
        lower[0] + (np.arange(cols)[:, None] + sub[None, :]).ravel() * resolution_m,
        indexing="ij",
    )
    T = se2.matrix(np.asarray(T_scene_grid, dtype=float))
    points = np.column_stack([xs.ravel(), ys.ravel()]) @ T[:2, :2].T + T[:2, 2]
    hits = scene.occupied(points).reshape(rows, supersample, cols, supersample)
    occupancy = hits.mean(axis=(1, 3))
    cy, cx = np.meshgrid(
        lower[1] + (np.arange(rows) + 0.5) * resolution_m,
        lower[0] + (np.arange(cols) + 0.5) * resolution_m,
        indexing="ij",
    )
    centres = np.column_stack([cx.ravel(), cy.ravel()]) @ T[:2, :2].T + T[:2, 2]
    known = scene.inside(centres).reshape(rows, cols)
    return Band(
        occupancy=np.where(known, occupancy, 0.0),
        known=known,
        lower_xy=lower,
        resolution_m=resolution_m,
    )


def local_view(
    scene: Scene,
    T_scene_robot: np.ndarray,
    radius_m: float,
    resolution_m: float,
    rng: np.random.Generator,
    *,
    noise: float = 0.0,
    drop_fraction: float = 0.0,
    flip_fraction: float = 0.0,
) -> Band:
    """The band a robot at ``T_scene_robot`` would map around itself, in its own frame: the cells
    within ``radius_m`` (the grid's lattice has a corner at the robot), occupancy plus Gaussian
    ``noise`` (clipped to [0, 1]), ``flip_fraction`` of the known cells inverted (p → 1 − p) and
    ``drop_fraction`` of them unknown."""
    if not radius_m > resolution_m:
        raise EstimationError(f"local view radius {radius_m} m must exceed one cell")
    half = math.ceil(radius_m / resolution_m)
    band = rasterise(
        scene,
        T_scene_robot,
        (-half * resolution_m, -half * resolution_m),
        (2 * half, 2 * half),
        resolution_m,
    )
    cy, cx = np.meshgrid((np.arange(2 * half) - half + 0.5), (np.arange(2 * half) - half + 0.5))
    known = band.known & (np.hypot(cx, cy) * resolution_m <= radius_m)
    occupancy = band.occupancy
    if noise > 0:
        occupancy = np.clip(occupancy + rng.normal(0.0, noise, occupancy.shape), 0.0, 1.0)
    if flip_fraction > 0:
        flip = rng.random(occupancy.shape) < flip_fraction
        occupancy = np.where(flip, 1.0 - occupancy, occupancy)
    if drop_fraction > 0:
        known = known & (rng.random(known.shape) >= drop_fraction)
    return Band(
        occupancy=np.where(known, occupancy, 0.0),
        known=known,
        lower_xy=band.lower_xy,
        resolution_m=resolution_m,
    )


def _box_walls(x0: float, y0: float, x1: float, y1: float) -> list[list[float]]:
    return [[x0, y0, x1, y0], [x1, y0, x1, y1], [x1, y1, x0, y1], [x0, y1, x0, y0]]


def random_building(rng: np.random.Generator, size_m: float = 20.0) -> Scene:
    """A square floor of rooms: outer walls, a jittered grid of inner walls with door gaps,
    pillars, and beams and ducts of random sizes — irregular enough that one place looks like
    no other."""
    walls: list[list[float]] = _box_walls(0.0, 0.0, size_m, size_m)
    cuts = 3
    for axis in (0, 1):
        for k in range(1, cuts):
            at = size_m * k / cuts + rng.uniform(-1.5, 1.5)
            edges = np.sort(rng.uniform(0.5, size_m - 0.5, 4))
            # Walls with two door gaps.
            for a, b in ((0.0, edges[0]), (edges[1], edges[2]), (edges[3], size_m)):
                seg = [at, a, at, b] if axis == 0 else [a, at, b, at]
                walls.append(seg)
    boxes = []
    for _ in range(int(rng.integers(10, 16))):
        kind = rng.random()
        cx, cy = rng.uniform(0.5, size_m - 0.5, 2)
        if kind < 0.4:  # pillars
            boxes.append([cx, cy, 0.4, 0.4, 0.0])
        else:  # beams and ducts
            boxes.append(
                [cx, cy, rng.uniform(1.0, 5.0), rng.uniform(0.2, 0.6), rng.uniform(0, math.pi)]
            )
    return Scene(
        walls=np.array(walls),
        wall_thickness_m=0.2,
        boxes=np.array(boxes).reshape(-1, 5),
        known_lo=np.zeros(2),
        known_hi=np.full(2, size_m),
    )


def office_floor(rng: np.random.Generator, size_m: float = 100.0, block_m: float = 12.0) -> Scene:
    """A large square office floor: corridors 2–3 m wide every ``block_m`` (jittered) along both
    axes; the blocks between them split into rooms by partitions, with a door from every room
    onto a corridor; pillars, beams and ducts of random sizes in every block. No two places
    alike, as ``random_building``, but its rooms stay room-sized however large the floor."""
    walls: list[list[float]] = _box_walls(0.0, 0.0, size_m, size_m)
    n = max(2, round(size_m / block_m))
    corridors = []  # per axis: (centre, half width) of each corridor
    for _ in range(2):
        at = size_m * np.arange(1, n) / n + rng.uniform(-1.5, 1.5, n - 1)
        corridors.append(np.column_stack([at, rng.uniform(1.0, 1.5, n - 1)]))
    # Each axis's stretches between the crossing corridors (and the outer walls).
    stretches = []
    for axis in range(2):
        c = corridors[axis]
        stretches.append(np.column_stack([np.r_[0.0, c[:, 0] + c[:, 1]],
                                          np.r_[c[:, 0] - c[:, 1], size_m]]))  # fmt: skip
    door = 0.9
    for axis in range(2):
        for centre, half in corridors[axis]:
            for a, b in stretches[1 - axis]:
                for side in (-1.0, 1.0):  # a wall either side, a door in each
                    at = centre + side * half
                    d = rng.uniform(a + 0.3, max(a + 0.3, b - door - 0.3))
                    for lo, hi in ((a, d), (d + door, b)):
                        if hi - lo > 0.05:
                            walls.append([at, lo, at, hi] if axis == 0 else [lo, at, hi, at])
    boxes = []
    for x0, x1 in stretches[0]:
        for y0, y1 in stretches[1]:
            # One or two partitions across the block, each with a door.
            along = int(rng.integers(0, 2))
            lo, hi = (x0, x1) if along == 0 else (y0, y1)
            a, b = (y0, y1) if along == 0 else (x0, x1)
            for _ in range(int(rng.integers(1, 3))):
                at = rng.uniform(lo + 2.0, max(lo + 2.0, hi - 2.0))
                d = rng.uniform(a + 0.3, max(a + 0.3, b - door - 0.3))
                for p, q in ((a, d), (d + door, b)):
                    if q - p > 0.05:
                        walls.append([at, p, at, q] if along == 0 else [p, at, q, at])
            for _ in range(int(rng.integers(3, 8))):
                cx, cy = rng.uniform(x0 + 0.4, x1 - 0.4), rng.uniform(y0 + 0.4, y1 - 0.4)
                if rng.random() < 0.4:
                    boxes.append([cx, cy, 0.4, 0.4, 0.0])
                else:
                    boxes.append([cx, cy, rng.uniform(1.0, 4.0), rng.uniform(0.2, 0.6),
                                  rng.uniform(0, math.pi)])  # fmt: skip
    return Scene(
        walls=np.array(walls),
        wall_thickness_m=0.2,
        boxes=np.array(boxes).reshape(-1, 5),
        known_lo=np.zeros(2),
        known_hi=np.full(2, size_m),
    )


def corridor(length_m: float = 20.0, width_m: float = 2.4) -> Scene:
    """A straight corridor with nothing in it: every position along it looks the same, and so
    does the other direction."""
    return Scene(
        walls=np.array([[0.0, 0.0, length_m, 0.0], [0.0, width_m, length_m, width_m]]),
        wall_thickness_m=0.2,
        boxes=np.zeros((0, 5)),
        known_lo=np.array([0.0, -0.3]),
        known_hi=np.array([length_m, width_m + 0.3]),
    )


def distinctive_room(size_m: float = 8.0) -> Scene:
    """A room with an L-shaped partition, a pillar and a slanted beam: no symmetry."""
    walls = _box_walls(0.0, 0.0, size_m, 0.7 * size_m)
    walls += [
        [0.3 * size_m, 0.0, 0.3 * size_m, 0.35 * size_m],
        [0.3 * size_m, 0.35 * size_m, 0.5 * size_m, 0.35 * size_m],
    ]
    boxes = [
        [0.75 * size_m, 0.45 * size_m, 0.4, 0.4, 0.0],
        [0.6 * size_m, 0.15 * size_m, 2.0, 0.3, 0.5],
    ]
    return Scene(
        walls=np.array(walls),
        wall_thickness_m=0.2,
        boxes=np.array(boxes),
        known_lo=np.zeros(2),
        known_hi=np.array([size_m, 0.7 * size_m]),
    )
