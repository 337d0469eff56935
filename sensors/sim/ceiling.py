"""Ceiling structure of a generated room: luminaires, ducts, beams, bulkheads, trusses.

Every fixture reaches into the sub-ceiling band (``FurnishParams.band_m``): under a low ceiling
it hangs from the ceiling, under a high one (a high-bay hall) it hangs down into the band on
pendants, and beams too shallow to reach the band under a high roof become deep trusses. Each
room draws its own mix and layout (about one room in seven is nearly bare), so the band's
cross-section differs from room to room — that is what global localization matches.
"""

from __future__ import annotations

from sensors.sim.floorplan import Rect
from sensors.sim.roomdraw import RoomDraw, box_doc

__all__ = ["add_ceiling_structure"]

_STYLES: dict[str, list[tuple[str, ...]]] = {
    "office": [("lights",), ("lights", "bulkhead"), ("lights", "beams"), ("lights", "ducts")],
    "lab": [
        ("lights", "ducts"),
        ("lights", "beams"),
        ("beams", "ducts"),
        ("lights", "bulkhead", "ducts"),
    ],
    "l_shaped": [("lights", "beams"), ("lights", "bulkhead"), ("lights", "ducts")],
    "hall": [
        ("trusses", "lights"),
        ("trusses", "ducts", "lights"),
        ("ducts", "lights"),
        ("beams", "lights"),
    ],
    "corridor": [("lights",), ("lights", "ducts"), ("beams", "lights")],
}


def _lights(r: RoomDraw, part: Rect) -> None:
    big = r.room.kind == "hall"
    spacing = r.u(4.0, 6.0) if big else r.u(2.0, 3.5)
    long_x = r.rng.random() < 0.5
    size = (0.5, 0.5) if big else ((1.2, 0.3) if long_x else (0.3, 1.2))
    nx = max(1, round((part.width - 0.8) / spacing))
    ny = max(1, round((part.height - 0.8) / spacing))
    jitter = 0.25 * spacing
    keep = r.rng.random((nx, ny)) >= 0.2  # one missing here and there breaks the pattern
    keep.flat[int(r.rng.integers(keep.size))] = True
    for i in range(nx):
        for j in range(ny):
            if not keep[i, j]:
                continue
            x = part.x0 + (i + 0.5) * part.width / nx + r.u(-jitter, jitter)
            y = part.y0 + (j + 0.5) * part.height / ny + r.u(-jitter, jitter)
            x = min(max(x, part.x0 + 0.7), part.x1 - 0.7)
            y = min(max(y, part.y0 + 0.7), part.y1 - 0.7)
            z0, z1 = r.hang(0.25 if big else 0.12)
            r.add(box_doc(r.name("lamp"), x, y, *size, z0, z1))


def _beams(r: RoomDraw, part: Rect) -> bool:
    low, high = r.params.band_m
    ceiling = r.room.ceiling_m
    if ceiling - 0.8 > high - 0.1:
        return False  # a beam this deep cannot reach the band: that is a truss's job
    across_x = part.width < part.height  # beams span the short side
    span, run = (part.width, part.height) if across_x else (part.height, part.width)
    spacing = r.u(2.5, 5.0)
    width = r.u(0.25, 0.4)
    bottom = max(low + 0.05, min(ceiling - 0.3, r.u(ceiling - 0.8, high - 0.1)), 2.2)
    k = 1
    s = r.u(0.8, spacing)
    while s < run - 0.8:
        if across_x:
            r.add(
                box_doc(
                    r.name("beam"),
                    0.5 * (part.x0 + part.x1),
                    part.y0 + s,
                    span - 0.04,
                    width,
                    bottom,
                    ceiling,
                )
            )
        else:
            r.add(
                box_doc(
                    r.name("beam"),
                    part.x0 + s,
                    0.5 * (part.y0 + part.y1),
                    width,
                    span - 0.04,
                    bottom,
                    ceiling,
                )
            )
        s += spacing * r.u(0.8, 1.2)
        k += 1
    return k > 1


def _ducts(r: RoomDraw, part: Rect) -> None:
    along_x = part.width >= part.height
    run, span = (part.width, part.height) if along_x else (part.height, part.width)
    for _ in range(1 if span < 5 or r.rng.random() < 0.6 else 2):
        width, depth = min(r.u(0.4, 0.9), span - 1.3), r.u(0.3, 0.5)
        length = r.u(0.5, 0.95) * run
        start = r.u(0.05 * run, max(0.06 * run, run - length - 0.05 * run))
        offset = r.u(0.6 + width / 2, span - 0.6 - width / 2)
        z0, z1 = r.hang(depth)
        mid = start + length / 2
        if along_x:
            x, y, size = part.x0 + mid, part.y0 + offset, (length, width)
        else:
            x, y, size = part.x0 + offset, part.y0 + mid, (width, length)
        r.add(box_doc(r.name("duct"), x, y, *size, z0, z1))
        if r.room.ceiling_m - z1 > 0.2 and r.rng.random() < 0.6:  # a riser up to the ceiling
            rx, ry = (
                (x + r.u(-0.4, 0.4) * length, y) if along_x else (x, y + r.u(-0.4, 0.4) * length)
            )
            r.add(box_doc(r.name("riser"), rx, ry, 0.4, 0.4, z1, r.room.ceiling_m))


def _bulkhead(r: RoomDraw, part: Rect) -> bool:
    _, high = r.params.band_m
    ceiling = r.room.ceiling_m
    # Its underside: 0.3-0.6 m below the ceiling, above the doors and inside the band.
    lowest, highest = max(2.35, ceiling - 0.6), min(ceiling - 0.3, high - 0.05)
    sides = r.wall_sides(part)
    if highest < lowest or not sides:
        return False
    side = sides[int(r.rng.integers(len(sides)))]
    depth, drop = r.u(0.4, 0.9), ceiling - r.u(lowest, highest)
    wall_len = part.width if side in "sn" else part.height
    length = r.u(0.4, 0.95) * (wall_len - 0.04)
    along = r.u(length / 2 + 0.02, wall_len - length / 2 - 0.02)
    if side in "sn":
        y = part.y0 + depth / 2 + 0.01 if side == "s" else part.y1 - depth / 2 - 0.01
        box = box_doc(
            r.name("bulkhead"), part.x0 + along, y, length, depth, ceiling - drop, ceiling
        )
    else:
        x = part.x0 + depth / 2 + 0.01 if side == "w" else part.x1 - depth / 2 - 0.01
        box = box_doc(
            r.name("bulkhead"), x, part.y0 + along, depth, length, ceiling - drop, ceiling
        )
    r.add(box)
    return True


def _trusses(r: RoomDraw, part: Rect) -> bool:
    low, high = r.params.band_m
    ceiling = r.room.ceiling_m
    if ceiling < 3.5:
        return False
    across_x = part.width < part.height
    span, run = (part.width, part.height) if across_x else (part.height, part.width)
    bottom = r.u(low + 0.2, max(low + 0.2, high - 0.3))
    spacing = r.u(3.5, 6.0)
    s = r.u(1.5, spacing)
    while s < run - 1.0:
        posts = max(2, int(span // r.u(1.5, 2.5)))
        for chord, (z0, z1) in (
            ("chord", (bottom, bottom + 0.2)),
            ("top", (ceiling - 0.25, ceiling)),
        ):
            size = (span - 0.04, 0.2) if across_x else (0.2, span - 0.04)
            x, y = (
                (0.5 * (part.x0 + part.x1), part.y0 + s)
                if across_x
                else (part.x0 + s, 0.5 * (part.y0 + part.y1))
            )
            r.add(box_doc(r.name(f"truss_{chord}"), x, y, *size, z0, z1))
        for p in range(1, posts):
            t = p * span / posts
            x, y = (part.x0 + t, part.y0 + s) if across_x else (part.x0 + s, part.y0 + t)
            r.add(box_doc(r.name("truss_post"), x, y, 0.12, 0.12, bottom + 0.2, ceiling - 0.25))
        s += spacing
    return True


def add_ceiling_structure(r: RoomDraw) -> None:
    if r.rng.random() < 0.15:  # nearly bare: at most one luminaire
        r.out.ceiling.append("bare")
        if r.rng.random() < 0.5:
            part = r.room.parts[0]
            z0, z1 = r.hang(0.12)
            x, y = r.u(part.x0 + 1, part.x1 - 1), r.u(part.y0 + 1, part.y1 - 1)
            r.add(box_doc(r.name("lamp"), x, y, 0.6, 0.6, z0, z1))
        return
    styles = _STYLES[r.room.kind]
    for feature in styles[int(r.rng.integers(len(styles)))]:
        done: set[str] = set()
        for part in r.room.parts:
            if feature == "lights":
                _lights(r, part)
                done.add("lights")
            elif feature == "ducts":
                _ducts(r, part)
                done.add("ducts")
            elif feature in ("beams", "trusses"):
                # A beam deep enough to reach the band under a high ceiling is a truss.
                if _beams(r, part):
                    done.add("beams")
                elif _trusses(r, part):
                    done.add("trusses")
            elif feature == "bulkhead" and _bulkhead(r, part):
                done.add("bulkhead")
        r.out.ceiling += sorted(done - set(r.out.ceiling))
