"""Furnishing a generated floor plan: ceiling structure, pillars, furniture, distractors.

For each room: the ceiling structure (``sensors.sim.ceiling``), pillars on a grid in large
halls and labs, movable furniture (desks with chairs, shelves, benches, trolleys, racks, crates,
barrels) that keeps clear of the doors and at least ``GAP_M`` from other furniture, and, in
about a third of the rooms, retro-reflective distractors at beacon height: signs on walls, tape
round pillars, reflective posts. A raster check of the floor (``sensors.sim.floorcheck``) then
takes away the last pieces placed until a robot can drive between the room's doors.
"""

from __future__ import annotations

import math

import numpy as np

from sensors.sim.ceiling import add_ceiling_structure
from sensors.sim.floorcheck import floor_reachable
from sensors.sim.floorplan import Door, PlanRoom, Rect
from sensors.sim.polygon import points_in_polygon
from sensors.sim.roomdraw import GAP_M, Furnishing, FurnishParams, RoomDraw, box_doc, cylinder_doc

__all__ = ["FurnishParams", "Furnishing", "furnish_room"]


def _pillars(r: RoomDraw) -> list[tuple[float, float, float]]:
    """Columns on a grid in large parts of halls and labs: (x, y, half width) each."""
    placed = []
    chance = {"hall": 0.85, "lab": 0.4, "l_shaped": 0.3}.get(r.room.kind, 0.0)
    round_ = r.rng.random() < 0.4
    half = r.u(0.15, 0.25)
    for part in r.room.parts:
        if min(part.width, part.height) < 6.0 or part.area < 50.0 or r.rng.random() >= chance:
            continue
        spacing = r.u(4.5, 7.0)
        nx = max(1, int((part.width - 4.0) // spacing) + 1)
        ny = max(1, int((part.height - 4.0) // spacing) + 1)
        for i in range(nx):
            for j in range(ny):
                x = 0.5 * (part.x0 + part.x1) + (i - (nx - 1) / 2) * spacing
                y = 0.5 * (part.y0 + part.y1) + (j - (ny - 1) / 2) * spacing
                bounds = Rect(x - half, y - half, x + half, y + half)
                if not r.fits(bounds, gap=0.6):
                    continue
                r.take(bounds)
                name, top = r.name("pillar"), r.room.ceiling_m
                if round_:
                    r.add(cylinder_doc(name, x, y, half, 0.0, top))
                else:
                    r.add(box_doc(name, x, y, 2 * half, 2 * half, 0.0, top))
                placed.append((x, y, half))
    r.out.pillars = len(placed)
    return placed


#: Furniture per kind: (what, count range, against a wall?, (length, depth) ranges, height range).
_FURNITURE: dict[
    str,
    list[tuple[str, tuple[int, int], bool, tuple[float, float, float, float], tuple[float, float]]],
] = {
    "office": [
        ("desk", (1, 3), True, (1.4, 1.8, 0.7, 0.8), (0.72, 0.76)),
        ("shelf", (0, 2), True, (0.8, 1.6, 0.35, 0.45), (1.6, 2.0)),
        ("table", (0, 1), False, (1.0, 1.4, 0.8, 1.2), (0.72, 0.74)),
    ],
    "lab": [
        ("bench", (2, 4), True, (1.8, 3.0, 0.75, 0.9), (0.88, 0.92)),
        ("shelf", (1, 3), True, (0.8, 1.8, 0.35, 0.5), (1.8, 2.1)),
        ("trolley", (0, 2), False, (0.8, 1.0, 0.45, 0.6), (0.9, 1.0)),
        ("table", (0, 1), False, (1.6, 2.0, 0.8, 1.0), (0.72, 0.9)),
    ],
    "hall": [
        ("rack", (2, 6), False, (2.0, 4.0, 0.8, 1.1), (1.8, 2.2)),
        ("rack", (0, 2), True, (2.0, 4.0, 0.6, 0.9), (1.8, 2.2)),
        ("crate", (2, 8), False, (0.8, 1.2, 0.6, 1.0), (0.4, 1.2)),
        ("table", (0, 2), False, (1.6, 2.4, 0.8, 1.0), (0.72, 0.9)),
    ],
    "corridor": [("cabinet", (0, 2), True, (0.8, 1.6, 0.3, 0.4), (0.9, 1.9))],
}
_FURNITURE["l_shaped"] = _FURNITURE["office"] + _FURNITURE["lab"][:2]


def _place(
    r: RoomDraw, part: Rect, against_wall: bool, length: float, depth: float, tries: int = 30
) -> tuple[float, float, bool, float] | None:
    """A centre, orientation (True: long along x) and yaw for a piece of furniture."""
    sides = r.wall_sides(part)
    for _ in range(tries):
        if against_wall:
            if not sides:
                return None
            side = sides[int(r.rng.integers(len(sides)))]
            along_x = side in "sn"
            wall_len = part.width if along_x else part.height
            if wall_len < length + 0.2:
                continue
            t = r.u(length / 2 + 0.05, wall_len - length / 2 - 0.05)
            off = depth / 2 + 0.03
            x, y = {
                "s": (part.x0 + t, part.y0 + off),
                "n": (part.x0 + t, part.y1 - off),
                "w": (part.x0 + off, part.y0 + t),
                "e": (part.x1 - off, part.y0 + t),
            }[side]
            yaw = 0.0
        else:
            along_x = r.rng.random() < 0.5
            hx, hy = (length / 2, depth / 2) if along_x else (depth / 2, length / 2)
            if part.width < 2 * (hx + GAP_M) or part.height < 2 * (hy + GAP_M):
                continue
            x = r.u(part.x0 + hx + GAP_M, part.x1 - hx - GAP_M)
            y = r.u(part.y0 + hy + GAP_M, part.y1 - hy - GAP_M)
            yaw = r.u(-12.0, 12.0)
        hx, hy = (length / 2, depth / 2) if along_x else (depth / 2, length / 2)
        grow = 0.5 * math.sin(math.radians(abs(yaw))) * (length + depth)
        bounds = Rect(x - hx - grow, y - hy - grow, x + hx + grow, y + hy + grow)
        if r.fits(bounds):
            return x, y, along_x, yaw
    return None


def _furniture(r: RoomDraw) -> None:
    group = 0
    for what, (lo, hi), wall, (l0, l1, d0, d1), (h0, h1) in _FURNITURE[r.room.kind]:
        for _ in range(int(r.rng.integers(lo, hi + 1))):
            part = r.room.parts[int(r.rng.integers(len(r.room.parts)))]
            length, depth = r.u(l0, l1), r.u(d0, d1)
            # A desk brings its chair: the pair keeps its distance from the rest as one piece.
            reach = depth + (0.7 if what == "desk" else 0.0)
            spot = _place(r, part, wall, length, reach)
            if spot is None:
                continue
            x, y, along_x, yaw = spot
            group += 1
            hx, hy = (length / 2, reach / 2) if along_x else (reach / 2, length / 2)
            r.take(Rect(x - hx, y - hy, x + hx, y + hy))
            size = (length, depth) if along_x else (depth, length)
            if what == "desk":
                # The desk against the wall, the chair on the room side of it.
                inward = np.sign(
                    np.array([0.5 * (part.x0 + part.x1) - x, 0.5 * (part.y0 + part.y1) - y])
                )
                shift = np.array([0.0, inward[1]]) if along_x else np.array([inward[0], 0.0])
                desk = np.array([x, y]) - shift * 0.35
                chair = np.array([x, y]) + shift * (reach / 2 - 0.3)
                top = r.u(h0, h1)
                r.add(
                    box_doc(r.name("desk"), desk[0], desk[1], *size, 0.0, top, movable=True), group
                )
                yaw = r.u(-30, 30)
                chair_doc = box_doc(
                    r.name("chair"),
                    chair[0],
                    chair[1],
                    0.5,
                    0.5,
                    0.0,
                    0.9,
                    yaw_deg=yaw,
                    movable=True,
                )
                r.add(chair_doc, group)
            else:
                top = r.u(h0, h1)
                r.add(
                    box_doc(r.name(what), x, y, *size, 0.0, top, yaw_deg=yaw, movable=True), group
                )
    if r.room.kind in ("hall", "lab") and r.rng.random() < 0.6:  # barrels, bins
        for _ in range(int(r.rng.integers(1, 4))):
            part = r.room.parts[int(r.rng.integers(len(r.room.parts)))]
            radius = r.u(0.2, 0.3)
            spot = _place(r, part, False, 2 * radius, 2 * radius)
            if spot is None:
                continue
            group += 1
            x, y, _, _ = spot
            r.take(Rect(x - radius, y - radius, x + radius, y + radius))
            top = r.u(0.6, 0.95)
            r.add(cylinder_doc(r.name("barrel"), x, y, radius, 0.0, top, movable=True), group)


def _distractors(r: RoomDraw, pillars: list[tuple[float, float, float]]) -> None:
    """Retro-reflective objects at beacon height, which a beacon detector must not take for a
    robot: a sign on a wall, tape round a pillar, a reflective post."""
    if r.rng.random() >= 0.35:
        return
    h, half = r.params.beacon_height_m, r.params.beacon_length_m / 2
    for _ in range(int(r.rng.integers(1, 3))):
        choice = r.rng.random()
        part = r.room.parts[int(r.rng.integers(len(r.room.parts)))]
        zc = h + r.u(-0.5, 0.5) * half
        if choice < 0.3 and pillars:
            x, y, w = pillars[int(r.rng.integers(len(pillars)))]
            tape = r.name("reflector")
            if any(c["center"] == [round(x, 3), round(y, 3)] for c in r.out.cylinders):
                r.add(cylinder_doc(tape, x, y, w + 0.01, zc - 0.1, zc + 0.1, retroreflective=True))
            else:
                wrap = 2 * w + 0.02
                r.add(box_doc(tape, x, y, wrap, wrap, zc - 0.1, zc + 0.1, retroreflective=True))
        elif choice < 0.7 and r.wall_sides(part):
            sides = r.wall_sides(part)
            side = sides[int(r.rng.integers(len(sides)))]
            wide = r.u(0.15, 0.4)
            t = r.u(0.3, (part.width if side in "sn" else part.height) - 0.3)
            x, y, size = {
                "s": (part.x0 + t, part.y0 + 0.02, (wide, 0.03)),
                "n": (part.x0 + t, part.y1 - 0.02, (wide, 0.03)),
                "w": (part.x0 + 0.02, part.y0 + t, (0.03, wide)),
                "e": (part.x1 - 0.02, part.y0 + t, (0.03, wide)),
            }[side]
            sign = box_doc(r.name("sign"), x, y, *size, zc - 0.12, zc + 0.12, retroreflective=True)
            r.add(sign)
        else:
            radius = r.u(0.04, 0.12)
            spot = _place(r, part, False, 2 * radius, 2 * radius)
            if spot is None:
                continue
            x, y, _, _ = spot
            r.take(Rect(x - radius, y - radius, x + radius, y + radius))
            top = h + half + 0.1
            r.add(cylinder_doc(r.name("post"), x, y, radius, 0.0, top, retroreflective=True))
        r.out.distractors += 1


def furnish_room(
    room: PlanRoom, doors: list[Door], params: FurnishParams, rng: np.random.Generator
) -> Furnishing:
    """Ceiling structure, pillars, furniture and distractors for one room of a plan."""
    spans = [(np.asarray(d.start_xy), np.asarray(d.end_xy)) for d in doors]
    # Orient each door along the room's wall (counter-clockwise), so its left is the inside.
    spans = [_along_wall(room, a, b) for a, b in spans]
    r = RoomDraw(room, spans, params, rng)
    add_ceiling_structure(r)
    pillars = _pillars(r)
    _furniture(r)
    _distractors(r, pillars)
    radius = params.robot_radius_m + 0.15
    while not floor_reachable(room, r.out.boxes, r.out.cylinders, spans, radius_m=radius):
        last = max(r.groups.values(), default=0)
        if last == 0:
            break  # nothing movable is left to take away (the tests check every room's floor)
        r.remove_group(last)
    return r.out


def _along_wall(room: PlanRoom, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(a, b)`` or ``(b, a)``: the order in which the room's counter-clockwise wall runs."""
    along = (b - a) / np.linalg.norm(b - a)
    probe = 0.5 * (a + b) + 0.05 * np.array([-along[1], along[0]])
    return (a, b) if points_in_polygon(probe[None, :], room.footprint)[0] else (b, a)
