"""``plan: auto``: leapfrog stations and scan poses chosen by expected new map information.

The paper chose its next-best views by hand. Here a greedy planner does it on a 2D model of the
world: what a scan sees is the floor area inside the scanner's 100° wedge, up to a range, with
walls (except their openings) and tall objects occluding. A mapper scan pose must let both robots
see each other's beacon — distance within the configured band, each beacon at a bearing between
the forward blind wedge and 45° from the other scanner's axis, and a clear 3D line between the
beacons — and be reachable without collision. Among those, poses are taken greedily by the
floor area they add to what is already covered (the frontier of the current map), less a cost
for the path. After each station the last mapper becomes the next reference (leapfrog) and turns
to the heading whose front holds the most uncovered, reachable space. Planning stops when the
coverage target or the station budget is reached.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit

from estimation.app.config import Config
from sensors.errors import SensorError
from sensors.sim.mission import MissionSpec, StepSpec
from sensors.sim.planner import FreeSpace
from sensors.sim.scene import RaycastScene, build_mesh
from sensors.sim.world import World

__all__ = [
    "BeaconGeometry",
    "CoverageModel",
    "Route",
    "as_spec",
    "grid_graph",
    "mapper_candidates",
    "mutual_dwells",
    "plan_leapfrog",
]

_WEDGE_RAD = math.radians(50.0)
_VIEW_RANGE_M = 7.0


@dataclass
class CoverageModel:
    """Floor cells of the reachable free space, which of them are covered, and what occludes."""

    space: FreeSpace
    target: np.ndarray  # (H, W) cells worth covering (reachable floor)
    covered: np.ndarray  # (H, W)
    opaque: np.ndarray  # (H, W)

    def visible(self, x: float, y: float, yaw: float) -> np.ndarray:
        """Cells seen from (x, y) within ±50° of ``yaw`` up to the view range: each ray up to
        its first opaque cell or the map's edge."""
        seen = np.zeros_like(self.opaque)
        self._walk(x, y, yaw, seen)
        return seen & self.target

    def gain(self, pose: np.ndarray) -> int:
        """How many cells worth covering and not covered yet a scan from ``pose`` would see."""
        x, y, yaw = (float(v) for v in pose[:3])
        return self._walk(x, y, yaw, np.zeros_like(self.opaque))

    def _walk(self, x: float, y: float, yaw: float, seen: np.ndarray) -> int:
        """Mark in ``seen`` the cells the rays reach; returns how many of them are worth
        covering and not covered yet."""
        angles = yaw + np.linspace(-_WEDGE_RAD, _WEDGE_RAD, 101)
        steps = np.arange(0.3, _VIEW_RANGE_M, self.space.resolution_m / 2)
        px, py = x + np.outer(np.cos(angles), steps), y + np.outer(np.sin(angles), steps)
        return int(_walk_rays(px, py, float(self.space.lower_xy[0]),
                              float(self.space.lower_xy[1]), self.space.resolution_m,
                              self.opaque, self.target, self.covered, seen))  # fmt: skip

    def add(self, pose: np.ndarray) -> None:
        self.covered |= self.visible(*pose)

    @property
    def fraction(self) -> float:
        return float(self.covered.sum() / max(1, self.target.sum()))


def _opaque_grid(world: World, space: FreeSpace) -> np.ndarray:
    """Walls (minus their openings) and objects taller than 1 m, on the free-space lattice."""
    h, w = space.free.shape
    res = space.resolution_m
    opaque = np.zeros((h, w), dtype=bool)

    def mark(points: np.ndarray) -> None:
        cols = np.floor((points[:, 0] - space.lower_xy[0]) / res).astype(int)
        rows = np.floor((points[:, 1] - space.lower_xy[1]) / res).astype(int)
        ok = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        opaque[rows[ok], cols[ok]] = True

    for room in world.rooms:
        polygon = room.footprint_xy
        for i in range(len(polygon)):
            a, b = polygon[i], polygon[(i + 1) % len(polygon)]
            length = float(np.linalg.norm(b - a))
            s = np.arange(0.0, length, res / 3)
            gap = np.zeros(len(s), dtype=bool)
            for o in room.openings:
                if o.wall == i and o.bottom_m < 1.0:
                    gap |= (s > o.from_m) & (s < o.to_m)
            mark(a + np.outer(s[~gap] / length, b - a))
    centers = space.lower_xy + (np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1) + 0.5) * res
    flat = centers.reshape(-1, 2)
    from sensors.sim.polygon import points_in_polygon

    for box in world.boxes:
        if box.z_m[1] - box.z_m[0] > 0.0 and box.z_m[1] > 1.0 and box.z_m[0] < 1.0:
            opaque |= points_in_polygon(flat, box.corners_xy()).reshape(h, w)
    for cyl in world.cylinders:
        if cyl.z_m[1] > 1.0 and cyl.z_m[0] < 1.0:
            d = np.hypot(flat[:, 0] - cyl.center[0], flat[:, 1] - cyl.center[1])
            opaque |= (d <= cyl.radius_m).reshape(h, w)
    return opaque


class BeaconGeometry:
    """Where a robot's scanner and beacon are, and whether two beacons see each other: on the
    true world (``scene``, for the simulator) or through ``line_clear(start, end)`` (3D points;
    the mission loop asks its estimated map)."""

    def __init__(
        self,
        config: Config,
        scene: RaycastScene | None = None,
        line_clear: Callable[[np.ndarray, np.ndarray], bool] | None = None,
    ) -> None:
        self.scanner_x = config.robot.scanner_x_m
        self.ahead = config.robot.scanner_x_m + config.beacon.offset_m
        self.beacon_z = config.beacon.height_m
        self.scanner_z = config.robot.scanner_height_m
        self.min_bearing = config.beacon.blind_wedge_rad / 2 + math.radians(5)
        self.max_bearing = math.radians(45)
        if line_clear is None:
            if scene is None:
                raise ValueError("BeaconGeometry needs a scene or a line_clear test")
            line_clear = functools.partial(_scene_clear, scene)
        self.line_clear = line_clear

    def scanner(self, pose: np.ndarray) -> np.ndarray:
        return pose[:2] + self.scanner_x * np.array([math.cos(pose[2]), math.sin(pose[2])])

    def beacon(self, pose: np.ndarray) -> np.ndarray:
        return pose[:2] + self.ahead * np.array([math.cos(pose[2]), math.sin(pose[2])])

    def bearing_ok(self, observer: np.ndarray, observed: np.ndarray) -> bool:
        delta = self.beacon(observed) - self.scanner(observer)
        bearing = abs(math.remainder(math.atan2(delta[1], delta[0]) - observer[2], 2 * math.pi))
        return self.min_bearing <= bearing <= self.max_bearing

    def sees_beacon(self, observer: np.ndarray, observed: np.ndarray) -> bool:
        """A clear 3D line from the observer's scanner to the other robot's beacon (centre)."""
        start = np.array([*self.scanner(observer), self.scanner_z])
        end = np.array([*self.beacon(observed), self.beacon_z])
        return self.line_clear(start, end)

    def beacons_see_each_other(self, a: np.ndarray, b: np.ndarray) -> bool:
        return self.sees_beacon(a, b) and self.sees_beacon(b, a)

    def mutual(self, reference: np.ndarray, mapper: np.ndarray, band: tuple[float, float]) -> bool:
        distance = float(np.linalg.norm(self.beacon(reference) - self.beacon(mapper)))
        return (
            band[0] <= distance <= band[1]
            and self.bearing_ok(reference, mapper)
            and self.bearing_ok(mapper, reference)
            and self.beacons_see_each_other(reference, mapper)
        )


def _scene_clear(scene: RaycastScene, start: np.ndarray, end: np.ndarray) -> bool:
    """Nothing in the true world between ``start`` and the last 15 cm before ``end``."""
    distance = float(np.linalg.norm(end - start))
    hits = scene.cast(start[None], (end - start)[None], normals=False)
    return bool(hits.range_m[0] > distance - 0.15)


def mutual_dwells(
    events: list[dict[str, Any]],
    stops: dict[str, list[tuple[float, np.ndarray]]],
    config: Config,
    scene: RaycastScene,
) -> int:
    """How many dwells of a timeline let their reference and mapper see each other's beacon:
    within the beacon's range, inside the scanner's field of view and outside its blind wedge,
    with a clear 3D line between scanner and beacon both ways."""
    geometry = BeaconGeometry(config, scene)
    geometry.min_bearing = config.beacon.blind_wedge_rad / 2
    geometry.max_bearing = math.radians(config.scanner.field_of_view_deg / 2)
    count = 0
    for event in events:
        reference, mapper = event.get("reference"), event.get("mapper")
        if event["event"] != "dwell" or reference is None or mapper is None:
            continue
        a = stops[reference][event["poses"][reference]][1]
        c = stops[mapper][event["poses"][mapper]][1]
        count += geometry.mutual(a, c, (0.0, config.beacon.max_range_m))
    return count


def mapper_candidates(
    ref: np.ndarray, geometry: BeaconGeometry, band: tuple[float, float]
) -> list[np.ndarray]:
    """Mapper poses in the reference's front sectors, facing it at ±25°."""
    # In Python floats, operation for operation as on 2-vectors: numpy's small arrays cost
    # more than the arithmetic, and a planner asks for a hundred candidates per heading.
    x, y, yaw0 = float(ref[0]), float(ref[1]), float(ref[2])
    c0, s0 = math.cos(yaw0), math.sin(yaw0)
    ox, oy = x + geometry.scanner_x * c0, y + geometry.scanner_x * s0
    rx, ry = x + geometry.ahead * c0, y + geometry.ahead * s0  # the reference's beacon
    ahead, scanner_x, tilt = geometry.ahead, geometry.scanner_x, math.radians(25)
    out = []
    for distance in np.linspace(band[0], band[1], 5).tolist():
        for side in (-1, 1):
            for bearing_deg in (16, 20, 25, 33, 41):
                direction = yaw0 + side * math.radians(bearing_deg)
                bx = ox + distance * math.cos(direction)
                by = oy + distance * math.sin(direction)
                for turn in (-1, 1):
                    # Solve for a robot pose whose beacon sits at (bx, by) and that sees the
                    # reference's beacon at ±25°: iterate the geometry.
                    yaw = math.atan2(ry - by, rx - bx) - turn * tilt
                    for _ in range(3):
                        c, s = math.cos(yaw), math.sin(yaw)
                        px, py = bx - ahead * c, by - ahead * s
                        to_x = rx - (px + scanner_x * c)
                        to_y = ry - (py + scanner_x * s)
                        yaw = math.atan2(to_y, to_x) - turn * tilt
                    out.append(np.array([bx - ahead * math.cos(yaw), by - ahead * math.sin(yaw),
                                         yaw]))  # fmt: skip
    return out


def as_spec(pose: np.ndarray) -> list[float]:
    return [round(float(pose[0]), 3), round(float(pose[1]), 3),
            round(math.degrees(math.remainder(float(pose[2]), 2 * math.pi)), 2)]  # fmt: skip


def plan_leapfrog(
    mission: MissionSpec,
    world: World,
    space: FreeSpace,
    config: Config,
    rng: np.random.Generator,
) -> list[StepSpec]:
    """Leapfrog steps for ``plan: auto`` (deterministic for a given generator)."""
    auto = mission.auto
    band = (float(auto.mapper_distance_m[0]), float(auto.mapper_distance_m[1]))
    scene = RaycastScene(build_mesh(world, cylinder_segments=16))
    geometry = BeaconGeometry(config, scene)
    names = mission.robot_names()
    poses = {
        r.name: np.array([r.start[0], r.start[1], math.radians(r.start[2])]) for r in mission.robots
    }
    for name, pose in poses.items():
        if not space.is_free(pose[:2]):
            raise SensorError(
                f"robot {name!r} starts at ({pose[0]:g}, {pose[1]:g}), where it does not fit "
                f"(nearest obstacle {space.clearance_m[space.cell(pose[:2])]:.2f} m away)"
            )
    reachable = space.component_of(poses[names[0]][:2])
    for name in names[1:]:
        if not reachable[space.cell(poses[name][:2])]:
            raise SensorError(
                f"robots {names[0]!r} and {name!r} start in parts of the world not joined by a path"
            )
    coverage = CoverageModel(
        space, reachable.copy(), np.zeros_like(reachable), _opaque_grid(world, space)
    )
    for pose in poses.values():
        coverage.add(pose)
    route = Route(space, reachable, [np.array(w, dtype=float) for w in auto.route])
    steps: list[StepSpec] = []
    reference, mapper = names[0], names[1]
    for k in range(auto.stations):
        ref = poses[reference]
        route.advance(ref)
        if route.done:
            break
        at: list[float] | None = None
        headings = [float(ref[2])]
        if k > 0:
            heading = (
                route.heading(ref)
                if route.active
                else _best_heading(ref, poses[mapper], space, coverage, geometry, band)
            )
            # When no mapper pose around the reference works at that heading (a wall or another
            # robot ahead), the headings nearest to it are tried in turn.
            turns = sorted(np.radians(np.arange(15.0, 360.0, 15.0)),
                           key=lambda t: abs(math.remainder(float(t), 2 * math.pi)))  # fmt: skip
            headings = [heading] + [math.remainder(heading + float(t), 2 * math.pi) for t in turns]
        scans: list[list[float]] = []
        for heading in headings:
            turned = np.array([ref[0], ref[1], heading])
            scans, current = _mapper_scans(turned, mapper, poses, auto.scans_per_station, space,
                                           reachable, geometry, band, coverage, route, config,
                                           rng)  # fmt: skip
            if scans:
                if abs(math.remainder(heading - ref[2], 2 * math.pi)) > 1e-6:
                    poses[reference] = turned
                    at = as_spec(turned)
                ref = turned
                break
        if not scans:
            if k == 0:
                raise SensorError(
                    f"no mapper pose around robot {reference!r} at ({ref[0]:.2f}, {ref[1]:.2f}) "
                    "sees its beacon: move the start poses into open space"
                )
            break
        steps.append(StepSpec(reference=reference, at=at, mapper=mapper, scans=scans))
        poses[mapper] = current
        if not route.active and coverage.fraction >= auto.coverage:
            break
        # Leapfrog: the mapper stays as the next reference; the next robot maps around it.
        reference, mapper = mapper, names[(names.index(mapper) + 1) % len(names)]
        if mapper == reference:
            mapper = names[(names.index(reference) + 1) % len(names)]
    return steps


def _mapper_scans(
    ref: np.ndarray, mapper: str, poses: dict[str, np.ndarray], count: int, space: FreeSpace,
    reachable: np.ndarray, geometry: BeaconGeometry, band: tuple[float, float],
    coverage: CoverageModel, route: Route, config: Config, rng: np.random.Generator,
) -> tuple[list[list[float]], np.ndarray]:  # fmt: skip
    """Up to ``count`` scan poses for ``mapper`` around the reference at ``ref`` (each the best
    of its candidates by coverage gain less path length, or by nearness to the route), and
    where the mapper ends; the poses taken are added to the coverage model (none when no pose
    is found)."""
    scans: list[list[float]] = []
    current = poses[mapper]
    spacing = 2 * config.robot.footprint_radius_m + 0.3
    others = [p for n, p in poses.items() if n != mapper]
    for _ in range(count):
        best, best_score = None, -math.inf
        for candidate in mapper_candidates(ref, geometry, band):
            if not space.is_free(candidate[:2]) or not reachable[space.cell(candidate[:2])]:
                continue
            if any(np.hypot(*(candidate[:2] - p[:2])) < spacing for p in others):
                continue
            if not geometry.mutual(ref, candidate, band):
                continue
            legs = space.path(current[:2], candidate[:2])
            if legs is None:
                continue
            length = sum(float(np.linalg.norm(b - a)) for a, b in itertools.pairwise(legs))
            score = coverage.gain(candidate) - 20.0 * length + rng.uniform(0, 1e-3)
            if route.active:
                score = 0.05 * score - 100.0 * route.distance(candidate)
            if score > best_score:
                best, best_score = candidate, score
        if best is None:
            break
        coverage.add(best)
        scans.append(as_spec(best))
        current = best
    return scans, current


def grid_graph(cells_mask: np.ndarray, resolution_m: float) -> tuple[Any, np.ndarray]:
    """The 8-connected graph of the cells of ``cells_mask`` (edge weights in metres) as a
    sparse matrix, and the node number of every cell (−1 outside the mask)."""
    from scipy.sparse import coo_matrix

    h, w = cells_mask.shape
    index = np.full((h, w), -1, dtype=np.int64)
    cells = np.argwhere(cells_mask)
    index[cells[:, 0], cells[:, 1]] = np.arange(len(cells))
    rows, cols, weights = [], [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        a = cells
        b = cells + np.array([dr, dc])
        ok = (b[:, 0] >= 0) & (b[:, 0] < h) & (b[:, 1] >= 0) & (b[:, 1] < w)
        a, b = a[ok], b[ok]
        both = index[b[:, 0], b[:, 1]] >= 0
        rows.append(index[a[both, 0], a[both, 1]])
        cols.append(index[b[both, 0], b[both, 1]])
        weights.append(np.full(both.sum(), math.hypot(dr, dc) * resolution_m))
    graph = coo_matrix(
        (np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))),
        shape=(len(cells), len(cells)),
    ).tocsr()
    return graph, index


class Route:
    """Waypoints followed in order; distances are shortest paths through free space."""

    def __init__(
        self, space: FreeSpace, reachable: np.ndarray, waypoints: list[np.ndarray]
    ) -> None:
        from scipy.sparse.csgraph import dijkstra

        self.space = space
        self.waypoints = waypoints
        self.next = 0
        self.fields: list[np.ndarray] = []
        if not waypoints:
            return
        graph, index = grid_graph(reachable, space.resolution_m)
        h, w = reachable.shape
        cells = np.argwhere(reachable)
        for k, point in enumerate(waypoints):
            if not space.is_free(point) or not reachable[space.cell(point)]:
                raise SensorError(
                    f"route waypoint {k} ({point[0]:g}, {point[1]:g}) is not reachable free space"
                )
            source = index[space.cell(point)]
            field = np.full((h, w), np.inf)
            field[cells[:, 0], cells[:, 1]] = dijkstra(graph, directed=False, indices=source)
            self.fields.append(field)

    @property
    def active(self) -> bool:
        return bool(self.waypoints) and not self.done

    @property
    def done(self) -> bool:
        return bool(self.waypoints) and self.next >= len(self.waypoints)

    def distance(self, pose: np.ndarray) -> float:
        return float(self.fields[self.next][self.space.cell(pose[:2])])

    def advance(self, pose: np.ndarray, reached_m: float = 2.5) -> None:
        while self.active and self.distance(pose) < reached_m:
            self.next += 1

    def heading(self, pose: np.ndarray) -> float:
        """Towards the next waypoint along the shortest path. (Turning towards the other robot
        instead, to observe it at the station, leaves no forward mapper poses in corridors.)"""
        legs = self.space.path(pose[:2], self.waypoints[self.next])
        target = legs[1] if legs is not None and len(legs) > 1 else self.waypoints[self.next]
        return math.atan2(target[1] - pose[1], target[0] - pose[0])


def _best_heading(ref: np.ndarray, mapper: np.ndarray, space: FreeSpace, coverage: CoverageModel,
                  geometry: BeaconGeometry, band: tuple[float, float]) -> float:  # fmt: skip
    """The heading at which the reference's front sectors hold the most uncovered space;
    headings that keep the other robot's beacon in view (a mutual observation at the station)
    come first."""
    best, best_gain = ref[2], -1
    for heading in np.radians(np.arange(0, 360, 15)):
        pose = np.array([ref[0], ref[1], heading])
        gain = 0 if geometry.mutual(pose, mapper, (0.5, 8.0)) else -1_000_000
        for candidate in mapper_candidates(pose, geometry, band)[::3]:
            if space.is_free(candidate[:2]):
                gain = max(gain, coverage.gain(candidate))
        if gain > best_gain:
            best, best_gain = float(heading), gain
    return best


@njit(cache=True)
def _walk_rays(
    px: np.ndarray, py: np.ndarray, lower_x: float, lower_y: float, res: float,
    opaque: np.ndarray, target: np.ndarray, covered: np.ndarray, seen: np.ndarray,
) -> int:  # fmt: skip
    """Mark in ``seen`` the cells that the rays (rows of sample points ``px``, ``py``) reach
    before their first opaque cell or the map's edge; returns how many of the cells newly
    marked are worth covering (``target``) and not ``covered``."""
    h, w = opaque.shape
    count = 0
    for i in range(px.shape[0]):
        for j in range(px.shape[1]):
            col = math.floor((px[i, j] - lower_x) / res)
            row = math.floor((py[i, j] - lower_y) / res)
            if not (0 <= row < h and 0 <= col < w) or opaque[row, col]:
                break
            if not seen[row, col]:
                seen[row, col] = True
                if target[row, col] and not covered[row, col]:
                    count += 1
    return count
