"""One room of a generated building being furnished: the state its furnishers share.

``sensors.sim.ceiling`` puts up the ceiling structure and ``sensors.sim.furnish`` the pillars,
furniture and distractors; both work on a :class:`RoomDraw`: the room, the random generator, the
objects placed so far (as world-format mappings), the floor they take and the floor kept clear
in front of the doors. The frame is the map frame (metres, z up from the floor).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sensors.sim.floorplan import PlanRoom, Rect
from sensors.sim.polygon import points_in_polygon

__all__ = [
    "DOOR_DEPTH_M",
    "GAP_M",
    "FurnishParams",
    "Furnishing",
    "RoomDraw",
    "box_doc",
    "cylinder_doc",
    "overlap",
]

#: Free floor kept between two pieces of furniture, and in front of a door (metres).
GAP_M = 1.0
DOOR_DEPTH_M = 1.6


@dataclass(frozen=True)
class FurnishParams:
    """What the furnishing needs of the robots and the mapper (metres)."""

    band_m: tuple[float, float] = (2.3, 2.9)
    robot_radius_m: float = 0.3
    beacon_height_m: float = 1.6
    beacon_length_m: float = 0.6


@dataclass
class Furnishing:
    """The objects of one room (world-format mappings) and what was put there."""

    boxes: list[dict[str, Any]] = field(default_factory=list)
    cylinders: list[dict[str, Any]] = field(default_factory=list)
    ceiling: list[str] = field(default_factory=list)
    pillars: int = 0
    distractors: int = 0


def _r(value: float) -> float:
    return round(float(value), 3) + 0.0


def box_doc(
    name: str,
    x: float,
    y: float,
    sx: float,
    sy: float,
    z0: float,
    z1: float,
    *,
    yaw_deg: float = 0.0,
    movable: bool = False,
    retroreflective: bool = False,
) -> dict[str, Any]:
    """A world-format box: centre (x, y), size (sx, sy) before yaw, z from z0 to z1."""
    doc: dict[str, Any] = {
        "name": name,
        "center": [_r(x), _r(y)],
        "size": [_r(sx), _r(sy)],
        "z_m": [_r(z0), _r(z1)],
    }
    if _r(yaw_deg):
        doc["yaw_deg"] = _r(yaw_deg)
    return _flag(doc, movable, retroreflective)


def cylinder_doc(
    name: str,
    x: float,
    y: float,
    radius: float,
    z0: float,
    z1: float,
    *,
    movable: bool = False,
    retroreflective: bool = False,
) -> dict[str, Any]:
    """A world-format vertical cylinder: centre (x, y), ``radius``, z from z0 to z1."""
    doc: dict[str, Any] = {
        "name": name,
        "center": [_r(x), _r(y)],
        "radius_m": _r(radius),
        "z_m": [_r(z0), _r(z1)],
    }
    return _flag(doc, movable, retroreflective)


def _flag(doc: dict[str, Any], movable: bool, retroreflective: bool) -> dict[str, Any]:
    """Only the flags that are set, as the built-in worlds write them."""
    if movable:
        doc["movable"] = True
    if retroreflective:
        doc["retroreflective"] = True
    return doc


class RoomDraw:
    """One room being furnished: names, the rng, the objects and the floor taken so far."""

    def __init__(
        self,
        room: PlanRoom,
        doors: list[tuple[np.ndarray, np.ndarray]],
        params: FurnishParams,
        rng: np.random.Generator,
    ) -> None:
        self.room, self.params, self.rng = room, params, rng
        self.out = Furnishing()
        self.counts: dict[str, int] = {}
        self.doors = doors  # (start, end) of each door in the room's walls
        # Floor kept free: in front of each door, on both sides of it.
        self.keep_out: list[Rect] = []
        for a, b in doors:
            along = (b - a) / np.linalg.norm(b - a)
            inward = np.array([-along[1], along[0]])
            corners = [a - 0.5 * along, b + 0.5 * along]
            corners += [c + DOOR_DEPTH_M * inward for c in corners]
            pts = np.array(corners)
            lo, hi = pts.min(axis=0), pts.max(axis=0)
            self.keep_out.append(Rect(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])))
        self.taken: list[Rect] = []  # bounds of the floor that objects stand on
        self.groups: dict[str, int] = {}  # object name → its movable group (0: fixed)
        self._sides: dict[Rect, list[str]] = {}

    def name(self, what: str) -> str:
        self.counts[what] = self.counts.get(what, 0) + 1
        return f"{self.room.name}_{what}{self.counts[what]}"

    def u(self, low: float, high: float) -> float:
        """A uniform draw from [low, high)."""
        return float(self.rng.uniform(low, high))

    def hang(self, thickness: float) -> tuple[float, float]:
        """z of a fixture of ``thickness`` under the ceiling, inside the band."""
        low, high = self.params.band_m
        ceiling = self.room.ceiling_m
        if ceiling <= high + 0.05:
            top = ceiling - self.u(0.0, max(0.0, min(0.1, ceiling - low - thickness)))
        else:  # a high ceiling: the fixture hangs down into the band
            top = self.u(min(high, low + thickness + 0.05), high)
        return max(top - thickness, 2.15), top

    def wall_sides(self, part: Rect) -> list[str]:
        """Sides of ``part`` ("s", "n", "w", "e") that are walls of the room, not the inside
        edge of an L."""
        if part in self._sides:
            return self._sides[part]
        mid = {
            "s": (0.5 * (part.x0 + part.x1), part.y0 - 0.05),
            "n": (0.5 * (part.x0 + part.x1), part.y1 + 0.05),
            "w": (part.x0 - 0.05, 0.5 * (part.y0 + part.y1)),
            "e": (part.x1 + 0.05, 0.5 * (part.y0 + part.y1)),
        }
        outside = ~points_in_polygon(np.array(list(mid.values())), self.room.footprint)
        self._sides[part] = [side for side, out in zip(mid, outside, strict=True) if out]
        return self._sides[part]

    def fits(self, bounds: Rect, gap: float = GAP_M) -> bool:
        """Whether ``bounds``, grown by ``gap``, keeps clear of the doors and what stands."""
        grown = Rect(bounds.x0 - gap, bounds.y0 - gap, bounds.x1 + gap, bounds.y1 + gap)
        return not any(overlap(grown, taken) for taken in self.keep_out + self.taken)

    def take(self, bounds: Rect) -> None:
        """Mark the floor of ``bounds`` as taken."""
        self.taken.append(bounds)

    def add(self, doc: dict[str, Any], group: int = 0) -> None:
        """Add a box or cylinder mapping; ``group`` > 0 numbers the movable piece it belongs to
        (a desk and its chair are one), which the floor check may take away again."""
        (self.out.cylinders if "radius_m" in doc else self.out.boxes).append(doc)
        self.groups[doc["name"]] = group

    def remove_group(self, group: int) -> None:
        names = {name for name, g in self.groups.items() if g == group}
        self.out.boxes = [d for d in self.out.boxes if d["name"] not in names]
        self.out.cylinders = [d for d in self.out.cylinders if d["name"] not in names]
        for name in names:
            del self.groups[name]


def overlap(a: Rect, b: Rect) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1
