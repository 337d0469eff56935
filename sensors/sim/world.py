"""World descriptions for the simulator (docs/design.md §9, file format in docs/design.md §12).

A world is a set of rooms — floor polygons extruded from the floor (z = 0) to a ceiling, with
openings cut into their walls for doors and windows — plus boxes (pillars, furniture, beams,
ducts; optionally yawed) and vertical cylinders. Boxes and cylinders may be ``movable`` (they are
what :func:`perturb_movables` changes) and ``retroreflective`` (the LMS marks returns from them
as it marks returns from beacons).

Validation at load names the key path and the bad value: a footprint that is clockwise or
self-intersecting, an opening outside its wall or above the ceiling, an object outside every
room or through a ceiling, a duplicate name.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, Self

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, model_validator

from sensors.errors import WorldError
from sensors.sim.polygon import find_self_intersection, points_in_polygon, signed_area
from sensors.yamlio import read_yaml_mapping, validate_mapping

__all__ = [
    "Box",
    "Cylinder",
    "ObjectChange",
    "Opening",
    "Room",
    "World",
    "load_world",
    "perturb_movables",
    "world_from_mapping",
    "world_to_yaml",
]

Point2 = Annotated[list[float], Field(min_length=2, max_length=2)]
Extent2 = Annotated[list[float], Field(min_length=2, max_length=2)]
Name = Annotated[str, Field(min_length=1, max_length=80, pattern=r"^[A-Za-z0-9_.\-]+$")]

#: Geometric tolerance of the checks (metres).
TOLERANCE_M = 1e-9
#: A room's footprint: at most this many vertices (its simplicity check is quadratic).
MAX_FOOTPRINT_VERTICES = 4096


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


class Opening(_Model):
    """A rectangular hole in wall ``wall`` of a room (wall i runs from vertex i to i + 1).

    ``from_m``/``to_m`` are distances along the wall from its first vertex; ``bottom_m``/``top_m``
    heights above the floor. A door starts at the floor, a window above it.
    """

    wall: int = Field(ge=0)
    from_m: float = Field(ge=0)
    to_m: float
    bottom_m: float = Field(0.0, ge=0)
    top_m: float

    @model_validator(mode="after")
    def _ordered(self) -> Self:
        if self.to_m <= self.from_m:
            raise ValueError(f"to_m ({self.to_m}) must be beyond from_m ({self.from_m})")
        if self.top_m <= self.bottom_m:
            raise ValueError(f"top_m ({self.top_m}) must be above bottom_m ({self.bottom_m})")
        return self

    @property
    def is_door(self) -> bool:
        return self.bottom_m <= TOLERANCE_M


class Room(_Model):
    """A floor polygon (counter-clockwise, metres) extruded up to ``ceiling_m``."""

    name: Name
    footprint: list[Point2] = Field(min_length=3, max_length=MAX_FOOTPRINT_VERTICES)
    ceiling_m: float = Field(gt=0, le=100)
    openings: list[Opening] = []

    @model_validator(mode="after")
    def _valid_geometry(self) -> Self:
        polygon = self.footprint_xy
        crossing = find_self_intersection(polygon)
        if crossing is not None:
            i, j = crossing
            if i == j:
                raise ValueError(
                    f"room {self.name!r}: footprint vertices {i} and {(i + 1) % len(polygon)} "
                    "coincide"
                )
            raise ValueError(
                f"room {self.name!r}: footprint is self-intersecting (walls {i} and {j} cross)"
            )
        area = signed_area(polygon)
        if area <= 0:
            raise ValueError(
                f"room {self.name!r}: footprint is clockwise (signed area {area:.3g} m²); "
                "list its vertices counter-clockwise"
            )
        lengths = self.wall_lengths_m
        for k, opening in enumerate(self.openings):
            where = f"room {self.name!r}: openings[{k}]"
            if opening.wall >= len(lengths):
                raise ValueError(
                    f"{where}: wall {opening.wall} does not exist "
                    f"(the footprint has walls 0-{len(lengths) - 1})"
                )
            length = lengths[opening.wall]
            if opening.to_m > length + TOLERANCE_M:
                raise ValueError(
                    f"{where}: spans {opening.from_m:g}-{opening.to_m:g} m along wall "
                    f"{opening.wall}, which is only {length:.3f} m long"
                )
            if opening.top_m > self.ceiling_m + TOLERANCE_M:
                raise ValueError(
                    f"{where}: top_m {opening.top_m:g} is above the ceiling ({self.ceiling_m:g} m)"
                )
        return self

    @property
    def footprint_xy(self) -> np.ndarray:
        """(N, 2) footprint vertices."""
        return np.asarray(self.footprint, dtype=float)

    @property
    def wall_lengths_m(self) -> np.ndarray:
        polygon = self.footprint_xy
        return np.asarray(np.linalg.norm(np.roll(polygon, -1, axis=0) - polygon, axis=1))

    def contains(self, points_xy: np.ndarray) -> np.ndarray:
        """Which (M, 2) points lie inside the footprint."""
        return points_in_polygon(points_xy, self.footprint_xy)


class _Solid(_Model):
    name: Name
    center: Point2
    z_m: Extent2
    movable: bool = False
    retroreflective: bool = False

    @model_validator(mode="after")
    def _z_ordered(self) -> Self:
        bottom, top = self.z_m
        if bottom < 0:
            raise ValueError(f"{self.name!r}: z_m starts below the floor ({bottom:g})")
        if top <= bottom:
            raise ValueError(f"{self.name!r}: z_m must run upwards, got [{bottom:g}, {top:g}]")
        return self


class Box(_Solid):
    """A box: footprint ``size`` (x, y extent before yaw) centred at ``center``, z from z_m."""

    size: Point2
    yaw_deg: float = 0.0

    @model_validator(mode="after")
    def _positive_size(self) -> Self:
        if min(self.size) <= 0:
            raise ValueError(f"{self.name!r}: size must be positive, got {self.size}")
        return self

    @property
    def yaw_rad(self) -> float:
        return math.radians(self.yaw_deg)

    def corners_xy(self) -> np.ndarray:
        """(4, 2) footprint corners, counter-clockwise."""
        hx, hy = self.size[0] / 2, self.size[1] / 2
        local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return local @ np.array([[c, s], [-s, c]]) + np.asarray(self.center)


class Cylinder(_Solid):
    """A vertical cylinder of radius ``radius_m`` centred at ``center``, z from z_m."""

    radius_m: float = Field(gt=0)


@dataclass(frozen=True)
class ObjectChange:
    """What :func:`perturb_movables` did to one object."""

    name: str
    action: Literal["moved", "removed"]
    shift_m: tuple[float, float] = (0.0, 0.0)
    yaw_deg: float = 0.0


class World(_Model):
    """Rooms, boxes and cylinders; the map frame has z up with the floor at z = 0."""

    name: Name
    rooms: list[Room] = Field(min_length=1)
    boxes: list[Box] = []
    cylinders: list[Cylinder] = []

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        seen: dict[str, str] = {}
        for k, each_room in enumerate(self.rooms):
            self._check_unique(seen, each_room.name, f"rooms[{k}]")
        for k, box in enumerate(self.boxes):
            self._check_unique(seen, box.name, f"boxes[{k}]")
        for k, cyl in enumerate(self.cylinders):
            self._check_unique(seen, cyl.name, f"cylinders[{k}]")
        for kind, solids in (("boxes", self.boxes), ("cylinders", self.cylinders)):
            for k, solid in enumerate(solids):
                room = self.room_at(solid.center)
                where = f"{kind}[{k}] {solid.name!r}"
                if room is None:
                    x, y = solid.center
                    raise ValueError(f"{where}: centre ({x:g}, {y:g}) lies outside every room")
                if solid.z_m[1] > room.ceiling_m + TOLERANCE_M:
                    raise ValueError(
                        f"{where}: rises to {solid.z_m[1]:g} m, above the ceiling of room "
                        f"{room.name!r} ({room.ceiling_m:g} m)"
                    )
        return self

    @staticmethod
    def _check_unique(seen: dict[str, str], name: str, where: str) -> None:
        if name in seen:
            raise ValueError(f"{where}: name {name!r} is already used by {seen[name]}")
        seen[name] = where

    def room_at(self, point_xy: list[float] | tuple[float, float] | np.ndarray) -> Room | None:
        """The first room whose footprint contains the point, or None."""
        point = np.asarray(point_xy, dtype=float).reshape(1, 2)
        for room in self.rooms:
            if room.contains(point)[0]:
                return room
        return None

    def inside(self, points_xy: np.ndarray) -> np.ndarray:
        """Which (M, 2) points lie inside some room."""
        points_xy = np.atleast_2d(np.asarray(points_xy, dtype=float))
        result = np.zeros(len(points_xy), dtype=bool)
        for room in self.rooms:
            result |= room.contains(points_xy)
        return result

    def bounds_xy(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners of the rooms' footprints."""
        vertices = np.concatenate([room.footprint_xy for room in self.rooms])
        return vertices.min(axis=0), vertices.max(axis=0)

    @property
    def max_ceiling_m(self) -> float:
        return max(room.ceiling_m for room in self.rooms)

    def movable_names(self) -> list[str]:
        return [s.name for s in (*self.boxes, *self.cylinders) if s.movable]


def world_from_mapping(data: dict[str, Any], source: str = "world") -> World:
    """Validate a world document (already parsed from YAML)."""
    return validate_mapping(World, data, WorldError, source)


def load_world(path: Path | str) -> World:
    """Load and validate a world YAML file; raises ``WorldError`` with one clear line."""
    path = Path(path)
    return world_from_mapping(read_yaml_mapping(path, WorldError), source=str(path))


def world_to_yaml(world: World) -> str:
    """The world as a YAML document that :func:`load_world` reads back to an equal world."""
    return yaml.safe_dump(world.model_dump(mode="json"), sort_keys=False)


def perturb_movables(
    world: World,
    rng: np.random.Generator,
    *,
    fraction: float,
    shift_m: float,
    yaw_deg: float,
    remove_fraction: float = 0.0,
    max_tries: int = 20,
) -> tuple[World, list[ObjectChange]]:
    """Move, turn or remove a random share of the movable objects.

    Each movable object is changed with probability ``fraction``; a changed object is removed
    with probability ``remove_fraction``, otherwise its centre moves uniformly within a disc of
    radius ``shift_m`` and (boxes only) it turns by a uniform angle in ±``yaw_deg``. A move that
    would leave every room is drawn again (up to ``max_tries`` times; then the object stays).
    Deterministic for a given generator state.
    """
    for label, value in (("fraction", fraction), ("remove_fraction", remove_fraction)):
        if not 0.0 <= value <= 1.0 or math.isnan(value):
            raise WorldError(f"perturbation {label} must be within [0, 1], got {value}")
    if not shift_m >= 0 or not yaw_deg >= 0:
        raise WorldError(f"perturbation shift_m and yaw_deg must be >= 0, got {shift_m}, {yaw_deg}")

    changes: list[ObjectChange] = []

    def perturb(solid: Box | Cylinder) -> Box | Cylinder | None:
        if not solid.movable or rng.random() >= fraction:
            return solid
        if rng.random() < remove_fraction:
            changes.append(ObjectChange(solid.name, "removed"))
            return None
        for _ in range(max_tries):
            radius = shift_m * math.sqrt(rng.random())
            angle = rng.uniform(0.0, 2.0 * math.pi)
            dx, dy = radius * math.cos(angle), radius * math.sin(angle)
            dyaw = float(rng.uniform(-yaw_deg, yaw_deg)) if isinstance(solid, Box) else 0.0
            center = [solid.center[0] + dx, solid.center[1] + dy]
            room = world.room_at(center)
            if room is not None and solid.z_m[1] <= room.ceiling_m + TOLERANCE_M:
                update: dict[str, Any] = {"center": center}
                if isinstance(solid, Box):
                    update["yaw_deg"] = solid.yaw_deg + dyaw
                changes.append(ObjectChange(solid.name, "moved", (dx, dy), dyaw))
                return solid.model_copy(update=update)
        return solid

    boxes = [b for b in (perturb(b) for b in world.boxes) if isinstance(b, Box)]
    cylinders = [c for c in (perturb(c) for c in world.cylinders) if isinstance(c, Cylinder)]
    changed = world_from_mapping(
        {
            **world.model_dump(),
            "boxes": [b.model_dump() for b in boxes],
            "cylinders": [c.model_dump() for c in cylinders],
        },
        source=f"{world.name} (perturbed)",
    )
    return changed, changes
