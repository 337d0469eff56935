"""Generated floor plans: rectangles that share walls, joined by doors (docs/worlds.md).

A building is a rectangle cut into rooms by guillotine cuts (a treemap of the rooms' target
areas), optionally with a corridor strip through it that the rooms on either side open onto; two
neighbouring rooms whose union is an L become one L-shaped room. Every coordinate lies on a 5 cm
grid and two rooms that share a wall use the same numbers for it, so the shared walls coincide
exactly. Doors are cut into shared walls — in the wall of each room, as the world format needs —
along a random spanning tree of the rooms' neighbourhood (every room reachable from every other),
plus a few more doors that make loops; windows go into outer walls.

The frame: x east, y north, metres, the building's south-west corner at the origin. Footprints
are counter-clockwise; wall i runs from vertex i to vertex i + 1.
"""

from __future__ import annotations

import itertools
import math
from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from sensors.sim.world import Room, World

__all__ = [
    "KINDS",
    "Door",
    "FloorPlan",
    "PlanRoom",
    "Rect",
    "WallOpening",
    "door_links",
    "draw_floor_plan",
    "outline",
    "shared_walls",
]

#: Room kinds, in the order they are listed.
KINDS = ("hall", "lab", "office", "l_shaped", "corridor")
#: Grid that every coordinate lies on (metres).
GRID_M = 0.05
#: Shortest side of a room other than a corridor (metres).
MIN_SIDE_M = 2.8
#: Longest side over shortest side of a room other than a corridor.
MAX_ASPECT = 3.5
#: Wall left on either side of a door, so that robots pass clear of the corners.
JAMB_M = 0.6
#: Target floor areas (m²) and ceiling heights (m) per kind.
AREA_M2 = {"office": (9.0, 20.0), "lab": (24.0, 45.0), "hall": (60.0, 140.0)}
CEILING_M = {
    "office": (2.4, 3.0),
    "corridor": (2.4, 3.0),
    "lab": (2.8, 3.6),
    "l_shaped": (2.6, 3.4),
    "hall": (3.6, 4.5),
}
_TOL = 1e-6


def _q(value: float) -> float:
    """``value`` on the 5 cm grid, as a plain float (never -0.0)."""
    return round(round(value / GRID_M) * GRID_M, 2) + 0.0


@dataclass(frozen=True)
class Rect:
    """An axis-aligned rectangle [x0, x1] × [y0, y1] (metres)."""

    x0: float
    y0: float
    x1: float
    y1: float

    @property
    def width(self) -> float:
        return self.x1 - self.x0

    @property
    def height(self) -> float:
        return self.y1 - self.y0

    @property
    def area(self) -> float:
        return self.width * self.height

    def corners(self) -> np.ndarray:
        """(4, 2) corners, counter-clockwise from the south-west one."""
        return np.array(
            [[self.x0, self.y0], [self.x1, self.y0], [self.x1, self.y1], [self.x0, self.y1]]
        )

    def transposed(self) -> Rect:
        return Rect(self.y0, self.x0, self.y1, self.x1)


@dataclass(frozen=True)
class WallOpening:
    """An opening in wall ``wall`` of one room, as the world format writes it."""

    wall: int
    from_m: float
    to_m: float
    bottom_m: float
    top_m: float

    def as_mapping(self) -> dict[str, float | int]:
        return {
            "wall": self.wall,
            "from_m": self.from_m,
            "to_m": self.to_m,
            "bottom_m": self.bottom_m,
            "top_m": self.top_m,
        }


@dataclass(frozen=True)
class PlanRoom:
    """A room of the plan: its kind, the rectangles it is made of, its footprint and ceiling."""

    name: str
    kind: str
    parts: tuple[Rect, ...]
    footprint: np.ndarray  # (N, 2) counter-clockwise
    ceiling_m: float

    @property
    def area_m2(self) -> float:
        return sum(part.area for part in self.parts)


@dataclass(frozen=True)
class Door:
    """A door between rooms ``rooms`` (indices), from ``start_xy`` to ``end_xy`` (map frame)."""

    rooms: tuple[int, int]
    start_xy: tuple[float, float]
    end_xy: tuple[float, float]
    top_m: float

    @property
    def width_m(self) -> float:
        return math.dist(self.start_xy, self.end_xy)


@dataclass(frozen=True)
class FloorPlan:
    rooms: tuple[PlanRoom, ...]
    doors: tuple[Door, ...]
    openings: tuple[tuple[WallOpening, ...], ...]  # per room: its doors and windows


def outline(rects: list[Rect] | tuple[Rect, ...]) -> np.ndarray:
    """The counter-clockwise outline of a union of grid-aligned rectangles (simply connected).

    Each rectangle's edges are cut at every coordinate of the others; a piece that two
    rectangles share appears once in each direction and cancels, the rest chain into the outline.
    """
    xs = sorted({v for r in rects for v in (r.x0, r.x1)})
    ys = sorted({v for r in rects for v in (r.y0, r.y1)})
    pieces: set[tuple[tuple[float, float], tuple[float, float]]] = set()
    for r in rects:
        bottom = [x for x in xs if r.x0 <= x <= r.x1]
        side = [y for y in ys if r.y0 <= y <= r.y1]
        runs = [
            [(x, r.y0) for x in bottom],
            [(r.x1, y) for y in side],
            [(x, r.y1) for x in bottom[::-1]],
            [(r.x0, y) for y in side[::-1]],
        ]
        for run in runs:
            for a, b in itertools.pairwise(run):
                if (b, a) in pieces:
                    pieces.remove((b, a))
                else:
                    pieces.add((a, b))
    following = dict(pieces)
    start = min(following)
    loop = [start]
    while (nxt := following[loop[-1]]) != start:
        loop.append(nxt)
        if len(loop) > len(following):
            break
    if len(following) != len(pieces) or len(loop) != len(pieces):
        raise ValueError("the rectangles' union is not one simple polygon")
    points = np.array(loop, dtype=float)
    before, after = np.roll(points, 1, axis=0), np.roll(points, -1, axis=0)
    turn = (points[:, 0] - before[:, 0]) * (after[:, 1] - points[:, 1]) - (
        points[:, 1] - before[:, 1]
    ) * (after[:, 0] - points[:, 0])
    corners = points[np.abs(turn) > _TOL]
    # The start is the lowest-left vertex, a convex corner: roll it to the front again.
    return np.roll(corners, -int(np.lexsort((corners[:, 1], corners[:, 0]))[0]), axis=0)


def shared_walls(a: np.ndarray, b: np.ndarray) -> list[tuple[int, int, float, float]]:
    """Where footprints ``a`` and ``b`` share a wall: (wall of a, wall of b, from_m, to_m along
    a's wall). Shared walls are collinear and run in opposite directions."""
    found = []
    for i in range(len(a)):
        a0, a1 = a[i], a[(i + 1) % len(a)]
        length = float(np.linalg.norm(a1 - a0))
        along = (a1 - a0) / length
        for j in range(len(b)):
            b0, b1 = b[j], b[(j + 1) % len(b)]
            offsets = [along[0] * (p[1] - a0[1]) - along[1] * (p[0] - a0[0]) for p in (b0, b1)]
            if max(abs(o) for o in offsets) > _TOL or float(along @ (b1 - b0)) >= 0:
                continue
            s0, s1 = sorted(float(along @ (p - a0)) for p in (b0, b1))
            lo, hi = max(0.0, s0), min(length, s1)
            if hi - lo > _TOL:
                found.append((i, j, lo, hi))
    return found


def _cuts(rect: Rect, share: float) -> list[tuple[Rect, Rect]]:
    """The two ways of cutting ``rect`` into a ``share`` and the rest, on the grid."""
    x, y = _q(rect.x0 + share * rect.width), _q(rect.y0 + share * rect.height)
    return [
        (Rect(rect.x0, rect.y0, x, rect.y1), Rect(x, rect.y0, rect.x1, rect.y1)),
        (Rect(rect.x0, rect.y0, rect.x1, y), Rect(rect.x0, y, rect.x1, rect.y1)),
    ]


def _aspect(rect: Rect, rooms: int) -> float:
    """How far ``rect`` is from holding ``rooms`` squarish rooms (1 is ideal, inf impossible)."""
    short, long = sorted((rect.width, rect.height))
    if short < MIN_SIDE_M - _TOL:
        return math.inf
    return max(long / short / rooms, rooms * short / long, 1.0)


def _treemap(
    rect: Rect, areas: list[float], rng: np.random.Generator, budget: list[int]
) -> list[Rect] | None:
    """Guillotine cuts of ``rect`` into pieces of about ``areas`` (in order), or None when no
    cut keeps every piece wide enough. Tries the squarest cuts first, backtracking while
    ``budget`` (a one-element counter) lasts."""
    if len(areas) == 1:
        side = min(rect.width, rect.height)
        ok = side >= MIN_SIDE_M - _TOL and max(rect.width, rect.height) / side <= MAX_ASPECT
        return [rect] if ok else None
    shares = np.cumsum(areas)[:-1] / sum(areas)
    options = []
    for k, share in enumerate(shares, 1):
        for first, second in _cuts(rect, float(share)):
            score = max(_aspect(first, k), _aspect(second, len(areas) - k))
            if math.isfinite(score):
                options.append((score * float(rng.uniform(1.0, 1.3)), k, first, second))
    for _, k, first, second in sorted(options, key=lambda o: o[0]):
        budget[0] -= 1
        if budget[0] < 0:
            return None
        low = _treemap(first, areas[:k], rng, budget)
        high = _treemap(second, areas[k:], rng, budget) if low is not None else None
        if low is not None and high is not None:
            return low + high
    return None


def _layout(
    count: int, rng: np.random.Generator
) -> tuple[list[tuple[str, tuple[Rect, ...]]], int] | None:
    """Kinds and rectangles of ``count`` rooms (None: this draw failed, draw again)."""
    corridor = count >= 5 and rng.random() < 0.8
    merges = int(rng.integers(0, 1 + (count - 1) // 4)) if rng.random() < 0.6 else 0
    leaves = count - int(corridor) + merges
    halls = int(rng.integers(1, 2 + count // 6)) if rng.random() < 0.7 else 0
    halls = min(halls, max(0, leaves - 2))
    kinds = ["hall"] * halls + [
        "lab" if rng.random() < 0.35 else "office" for _ in range(leaves - halls)
    ]
    kinds = [kinds[k] for k in rng.permutation(len(kinds))]
    areas = [float(rng.uniform(*AREA_M2[kind])) for kind in kinds]
    total = sum(areas)
    if corridor:
        sides = rng.random(len(kinds)) < 0.5
        if rng.random() < 0.8:  # rooms on both sides, most often
            sides[: len(sides) // 2] = True
            sides[len(sides) // 2 :] = False
            sides = sides[rng.permutation(len(sides))]
        depth = float(rng.uniform(5.0, 9.0))
        groups = [[k for k in range(len(kinds)) if sides[k] == side] for side in (True, False)]
        length = _q(total / (depth * sum(1 for g in groups if g)))
        width = _q(float(rng.uniform(2.0, 2.8)))
        rects: dict[int, Rect] = {}
        y = 0.0
        corridor_rect = None
        for g, group in enumerate(groups):
            if g == 1:
                corridor_rect = Rect(0.0, y, length, _q(y + width))
                y = corridor_rect.y1
            if not group:
                continue
            block = Rect(0.0, y, length, _q(y + sum(areas[k] for k in group) / length))
            pieces = _treemap(block, [areas[k] for k in group], rng, [60])
            if pieces is None:
                return None
            rects.update(zip(group, pieces, strict=True))
            y = block.y1
        assert corridor_rect is not None
        ordered = [rects[k] for k in range(len(kinds))]
    else:
        aspect = float(rng.uniform(1.0, 1.8))
        width = _q(math.sqrt(total * aspect))
        pieces = _treemap(Rect(0.0, 0.0, width, _q(total / width)), areas, rng, [60])
        if pieces is None:
            return None
        ordered, corridor_rect = pieces, None
    if rng.random() < 0.5:  # run the building north-south as often as east-west
        ordered = [r.transposed() for r in ordered]
        corridor_rect = corridor_rect.transposed() if corridor_rect is not None else None
    rooms: list[tuple[str, tuple[Rect, ...]]] = [
        (k, (r,)) for k, r in zip(kinds, ordered, strict=True)
    ]
    for _ in range(merges):
        if not _merge_one(rooms, rng):
            return None
    if corridor_rect is not None:
        rooms.append(("corridor", (corridor_rect,)))
    return rooms, merges


def _merge_one(rooms: list[tuple[str, tuple[Rect, ...]]], rng: np.random.Generator) -> bool:
    """Join two neighbouring offices or labs whose union is an L into one L-shaped room."""
    pairs = []
    for i, (kind_i, parts_i) in enumerate(rooms):
        for j in range(i + 1, len(rooms)):
            kind_j, parts_j = rooms[j]
            if kind_i not in ("office", "lab") or kind_j not in ("office", "lab"):
                continue
            a, b = parts_i[0], parts_j[0]
            touching = shared_walls(a.corners(), b.corners())
            if touching and a.area + b.area <= 70.0 and len(outline([a, b])) == 6:
                pairs.append((i, j))
    if not pairs:
        return False
    i, j = pairs[int(rng.integers(len(pairs)))]
    rooms[i] = ("l_shaped", (rooms[i][1][0], rooms[j][1][0]))
    del rooms[j]
    return True


def _unit(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.asarray((b - a) / np.linalg.norm(b - a))


def _doors(rooms: list[PlanRoom], rng: np.random.Generator, min_door_m: float) -> list[Door] | None:
    """A door on a random spanning tree of the neighbourhood, plus some loops (None: the
    rooms are not joined by walls long enough for a door)."""
    need = min_door_m + 2 * JAMB_M
    links = []
    for i in range(len(rooms)):
        for j in range(i + 1, len(rooms)):
            walls = shared_walls(rooms[i].footprint, rooms[j].footprint)
            usable = [w for w in walls if w[3] - w[2] >= need - _TOL]
            if usable:
                links.append((i, j, max(usable, key=lambda w: w[3] - w[2])))
    order = rng.permutation(len(links))
    # Rooms open onto a corridor first, as buildings do; then random links join the rest.
    corridor = [
        k for k in order if "corridor" in (rooms[links[k][0]].kind, rooms[links[k][1]].kind)
    ]
    ranked = corridor + [k for k in order if k not in corridor]
    parent = list(range(len(rooms)))

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    chosen = []
    for k in ranked:
        i, j, _ = links[k]
        if root(i) != root(j):
            parent[root(i)] = root(j)
            chosen.append(k)
        elif rng.random() < 0.25:
            chosen.append(k)
    if len({root(i) for i in range(len(rooms))}) > 1:
        return None
    doors = []
    for k in sorted(chosen):
        i, j, (wall, _, lo, hi) = links[k]
        big = "hall" in (rooms[i].kind, rooms[j].kind)
        widest = min(hi - lo - 2 * JAMB_M, 2.4 if big else 1.3)
        width = _q(float(rng.uniform(min_door_m, max(min_door_m, widest))))
        width = max(width, _q(min_door_m + GRID_M / 2))
        # A wall usable within _TOL may be a hair shorter than the door and its jambs (seed
        # 210 with 15 rooms: 1e-6 m); the door then starts at the first jamb.
        start = _q(float(rng.uniform(lo + JAMB_M, max(lo + JAMB_M, hi - JAMB_M - width))))
        room = rooms[i].footprint
        a0, a1 = room[wall], room[(wall + 1) % len(room)]
        along = _unit(a0, a1)
        p, q = a0 + start * along, a0 + (start + width) * along
        lowest = min(rooms[i].ceiling_m, rooms[j].ceiling_m) - 0.1
        top = _q(min(lowest, float(rng.uniform(2.3, 2.9) if big else rng.uniform(2.05, 2.25))))
        doors.append(Door((i, j), (_q(p[0]), _q(p[1])), (_q(q[0]), _q(q[1])), top))
    return doors


def _door_opening(room: PlanRoom, door: Door) -> WallOpening:
    """The door as an opening in the wall of ``room`` that it lies in."""
    p, q = np.asarray(door.start_xy), np.asarray(door.end_xy)
    poly = room.footprint
    for wall in range(len(poly)):
        a0, a1 = poly[wall], poly[(wall + 1) % len(poly)]
        along = _unit(a0, a1)
        off = [abs(along[0] * (x[1] - a0[1]) - along[1] * (x[0] - a0[0])) for x in (p, q)]
        s = sorted(float(along @ (x - a0)) for x in (p, q))
        if max(off) < _TOL and s[0] >= -_TOL and s[1] <= float(np.linalg.norm(a1 - a0)) + _TOL:
            return WallOpening(wall, _q(s[0]), _q(s[1]), 0.0, door.top_m)
    raise AssertionError(f"door {door} is not in a wall of room {room.name}")


def _windows(rooms: list[PlanRoom], index: int, rng: np.random.Generator) -> list[WallOpening]:
    """Windows in the parts of a room's walls that no other room shares (the outer walls)."""
    room = rooms[index]
    covered: dict[int, list[tuple[float, float]]] = defaultdict(list)
    for k, other in enumerate(rooms):
        if k != index:
            for wall, _, lo, hi in shared_walls(room.footprint, other.footprint):
                covered[wall].append((lo, hi))
    chance = 0.25 if room.kind == "corridor" else 0.6
    lengths = np.linalg.norm(np.roll(room.footprint, -1, axis=0) - room.footprint, axis=1)
    found = []
    for wall, length in enumerate(lengths):
        free, cursor = [], 0.0
        for lo, hi in sorted(covered[wall]):
            if lo > cursor:
                free.append((cursor, lo))
            cursor = max(cursor, hi)
        if cursor < length:
            free.append((cursor, float(length)))
        for lo, hi in free:
            if hi - lo < 2.0 or rng.random() >= chance:
                continue
            width = _q(float(rng.uniform(1.0, 2.0)))
            gap = _q(float(rng.uniform(0.6, 1.6)))
            n = int(min(4, (hi - lo - 0.6 + gap) // (width + gap)))
            if n < 1:
                continue
            spare = max(0.0, hi - lo - 0.6 - n * width - (n - 1) * gap)
            start = lo + 0.3 + float(rng.uniform(0.0, spare))
            bottom = _q(float(rng.uniform(0.8, 1.0)))
            top = _q(min(room.ceiling_m - 0.15, float(rng.uniform(2.1, 2.6))))
            for m in range(n):
                s = _q(start + m * (width + gap))
                found.append(WallOpening(wall, s, _q(s + width), bottom, top))
    return found


def draw_floor_plan(
    count: int, rng: np.random.Generator, *, min_door_m: float, attempts: int = 200
) -> FloorPlan:
    """A connected floor plan of ``count`` rooms, drawn from ``rng`` (deterministic)."""
    for _ in range(attempts):
        drawn = _layout(count, rng)
        if drawn is None:
            continue
        layout, _ = drawn
        order = sorted(range(len(layout)), key=lambda k: KINDS.index(layout[k][0]))
        rooms = []
        for n, k in enumerate(order, 1):
            kind, parts = layout[k]
            low, high = CEILING_M[kind]
            rooms.append(
                PlanRoom(
                    f"{kind}_{n:02d}",
                    kind,
                    parts,
                    outline(parts),
                    _q(float(rng.uniform(low, high))),
                )
            )
        if len({r.ceiling_m for r in rooms}) == 1:  # a building's rooms differ in height
            last = rooms[-1]
            bumped = _q(last.ceiling_m + (0.2 if last.ceiling_m < 2.8 else -0.2))
            rooms[-1] = PlanRoom(last.name, last.kind, last.parts, last.footprint, bumped)
        doors = _doors(rooms, rng, min_door_m)
        if doors is None:
            continue
        openings = []
        for k, room in enumerate(rooms):
            own = [_door_opening(room, d) for d in doors if k in d.rooms]
            openings.append(
                tuple(sorted(own + _windows(rooms, k, rng), key=lambda o: (o.wall, o.from_m)))
            )
        return FloorPlan(tuple(rooms), tuple(doors), tuple(openings))
    raise RuntimeError(f"no floor plan of {count} rooms after {attempts} attempts")


def door_links(world: World, *, robot_height_m: float = 0.35) -> dict[str, set[str]]:
    """Which rooms a robot can drive between: room name → the rooms one door away.

    A door joins two rooms when both have a floor-level opening, taller than the robot, over
    the same stretch of a wall they share.
    """
    links: dict[str, set[str]] = {room.name: set() for room in world.rooms}
    for i, a in enumerate(world.rooms):
        for b in world.rooms[i + 1 :]:
            for wall_a, wall_b, lo, hi in shared_walls(a.footprint_xy, b.footprint_xy):
                for oa in a.openings:
                    if oa.wall != wall_a or not oa.is_door or oa.top_m < robot_height_m:
                        continue
                    # b's wall runs the other way: a's distance s is b's distance length_b' − s.
                    start_b = _along_b(a, b, wall_a, wall_b)
                    for ob in b.openings:
                        if ob.wall != wall_b or not ob.is_door or ob.top_m < robot_height_m:
                            continue
                        from_a, to_a = start_b - ob.to_m, start_b - ob.from_m
                        overlap = min(oa.to_m, to_a, hi) - max(oa.from_m, from_a, lo)
                        if overlap > 0.8:
                            links[a.name].add(b.name)
                            links[b.name].add(a.name)
    return links


def _along_b(a: Room, b: Room, wall_a: int, wall_b: int) -> float:
    """Distance along a's wall ``wall_a`` (from its first vertex) of b's wall's first vertex."""
    pa, pb = a.footprint_xy, b.footprint_xy
    a0, a1 = pa[wall_a], pa[(wall_a + 1) % len(pa)]
    return float(_unit(a0, a1) @ (pb[wall_b] - a0))
