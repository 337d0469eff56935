"""Generated buildings: worlds for evaluation that nobody tuned for (docs/worlds.md).

``generate_building(seed, rooms)`` draws a connected floor plan of 3–15 rooms (offices, labs,
halls, corridors, L-shaped rooms; ``sensors.sim.floorplan``), varies the ceiling height from room
to room (2.4–4.5 m), and furnishes each room (``sensors.sim.furnish``): ceiling structure in the
sub-ceiling band, pillars in large rooms, movable furniture that leaves the doors and a path
between them clear, and retro-reflective distractors at beacon height in some rooms. The world
passes :func:`sensors.sim.world.world_from_mapping`; the YAML text is the same, byte for byte,
for the same seed, rooms and parameters. Randomness comes from ``np.random.default_rng`` seeded
with the seed (one stream for the plan, one for the furnishing), never from global state.

Room names start with their kind (``office_03``, ``l_shaped_07``); the file's header comment
lists the rooms with their kinds, areas, ceilings and ceiling structure, and marks the file as
generated, so that :func:`write_generated_world` replaces only files it wrote itself.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sensors.atomic import write_text_atomic
from sensors.errors import OutputError, WorldError
from sensors.sim.floorplan import KINDS, draw_floor_plan
from sensors.sim.furnish import FurnishParams, furnish_room
from sensors.sim.world import World, world_from_mapping

__all__ = [
    "DRAWN_MAX_ROOMS",
    "HEADER",
    "MAX_ROOMS",
    "MIN_ROOMS",
    "GeneratedBuilding",
    "GeneratedRoom",
    "check_writable",
    "generate_building",
    "is_generated_world",
    "room_kind",
    "write_generated_world",
]

#: ``--rooms`` accepts up to ``MAX_ROOMS`` (large buildings for benchmarks); a seed without
#: ``--rooms`` draws its count from ``MIN_ROOMS``–``DRAWN_MAX_ROOMS``, as it always has.
MIN_ROOMS, MAX_ROOMS, DRAWN_MAX_ROOMS = 3, 40, 15
#: Reading the text back checks it; libyaml's loader when there is one (it is 10× faster).
_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
#: The first line of every generated world file: what marks it as ours to replace.
HEADER = "# coopmap generated world"


@dataclass(frozen=True)
class GeneratedRoom:
    """One room of a generated building, as an evaluation counts it."""

    name: str
    kind: str  # one of sensors.sim.floorplan.KINDS
    area_m2: float
    ceiling_m: float
    ceiling_structure: tuple[str, ...]  # "lights", "ducts", "beams", "bulkhead", "trusses", "bare"
    doors: int
    windows: int
    pillars: int
    distractors: int


@dataclass(frozen=True)
class GeneratedBuilding:
    seed: int
    world: World
    rooms: tuple[GeneratedRoom, ...]
    text: str  # the world YAML, header comment included

    def kinds(self) -> dict[str, int]:
        """How many rooms of each kind."""
        return dict(Counter(room.kind for room in self.rooms))


def room_kind(name: str) -> str:
    """The kind of a generated room from its name (``l_shaped_07`` → ``l_shaped``)."""
    kind, _, number = name.rpartition("_")
    if kind not in KINDS or not number.isdigit():
        raise WorldError(f"room {name!r} is not a generated room (kinds: {', '.join(KINDS)})")
    return kind


def _check_arguments(seed: int, rooms: int | None) -> None:
    if seed < 0:
        raise WorldError(f"--seed must be >= 0, got {seed}")
    if rooms is not None and not MIN_ROOMS <= rooms <= MAX_ROOMS:
        raise WorldError(f"--rooms must be within {MIN_ROOMS}-{MAX_ROOMS}, got {rooms}")


def generate_building(
    seed: int, rooms: int | None = None, params: FurnishParams | None = None
) -> GeneratedBuilding:
    """A furnished building of ``rooms`` rooms (drawn from the seed when None), validated."""
    _check_arguments(seed, rooms)
    params = params or FurnishParams()
    plan_rng = np.random.default_rng([seed, 0])
    count = int(plan_rng.integers(MIN_ROOMS, DRAWN_MAX_ROOMS + 1)) if rooms is None else rooms
    # The narrowest door a robot passes with the planner's margin on both sides, and a cell.
    min_door_m = max(1.0, round(2 * (params.robot_radius_m + 0.1) + 0.2, 2))
    plan = draw_floor_plan(count, plan_rng, min_door_m=min_door_m)
    furnish_rng = np.random.default_rng([seed, 1])
    boxes: list[dict[str, Any]] = []
    cylinders: list[dict[str, Any]] = []
    summary = []
    for k, room in enumerate(plan.rooms):
        doors = [d for d in plan.doors if k in d.rooms]
        stuff = furnish_room(room, doors, params, furnish_rng)
        boxes += stuff.boxes
        cylinders += stuff.cylinders
        windows = sum(1 for o in plan.openings[k] if o.bottom_m > 0)
        summary.append(
            GeneratedRoom(
                room.name,
                room.kind,
                round(room.area_m2, 2),
                room.ceiling_m,
                tuple(stuff.ceiling),
                len(doors),
                windows,
                stuff.pillars,
                stuff.distractors,
            )
        )
    name = f"generated_{seed}_{count}"
    document = {
        "name": name,
        "rooms": [
            {
                "name": room.name,
                "footprint": room.footprint.round(2).tolist(),
                "ceiling_m": room.ceiling_m,
                "openings": [o.as_mapping() for o in plan.openings[k]],
            }
            for k, room in enumerate(plan.rooms)
        ],
        "boxes": boxes,
        "cylinders": cylinders,
    }
    text = _header(seed, rooms, summary) + _to_yaml(document)
    world = world_from_mapping(yaml.load(text, Loader=_LOADER), source=name)
    return GeneratedBuilding(seed, world, tuple(summary), text)


def _header(seed: int, rooms: int | None, summary: list[GeneratedRoom]) -> str:
    command = f"coopmap world generate --seed {seed}" + (f" --rooms {rooms}" if rooms else "")
    ceilings = [r.ceiling_m for r in summary]
    kinds = Counter(r.kind for r in summary)
    lines = [
        f"{HEADER} ({command}); edits are lost when the command runs again.",
        f"# {len(summary)} rooms ({', '.join(f'{n} {k}' for k, n in sorted(kinds.items()))}), "
        f"ceilings {min(ceilings):g}-{max(ceilings):g} m. Room names start with their kind.",
        "# room: kind, floor area, ceiling, ceiling structure, doors, windows, pillars, "
        "reflective distractors",
    ]
    for r in summary:
        lines.append(
            f"#   {r.name}: {r.kind}, {r.area_m2:.1f} m2, {r.ceiling_m:g} m, "
            f"{'+'.join(r.ceiling_structure) or 'none'}, {r.doors} doors, {r.windows} windows, "
            f"{r.pillars} pillars, {r.distractors} distractors"
        )
    return "\n".join(lines) + "\n"


def _flow(value: Any) -> str:
    """A value in YAML flow style: mappings of names, numbers, flags and lists of numbers."""
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {_flow(v)}" for k, v in value.items()) + "}"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_flow(v) for v in value) + "]"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)  # metres rounded to 1 mm: plain decimals such as 2.45, never 1e-05
    return str(value)  # a name: letters, digits and underscores, starting with a letter


def _to_yaml(document: dict[str, Any]) -> str:
    """The world in the layout of the built-in worlds: one line per opening and per object."""
    out = [f"name: {document['name']}", "rooms:"]
    for room in document["rooms"]:
        out += [
            f"  - name: {room['name']}",
            f"    footprint: {_flow(room['footprint'])}",
            f"    ceiling_m: {room['ceiling_m']}",
        ]
        if room["openings"]:
            out.append("    openings:")
            out += [f"      - {_flow(o)}" for o in room["openings"]]
    for key in ("boxes", "cylinders"):
        out.append(f"{key}:" + ("" if document[key] else " []"))
        out += [f"  - {_flow(doc)}" for doc in document[key]]
    return "\n".join(out) + "\n"


def is_generated_world(path: Path | str) -> bool:
    """Whether ``path`` is a regular file that this generator wrote (its first line)."""
    path = Path(path)
    if path.is_symlink() or not path.is_file():
        return False
    try:
        with path.open("rb") as f:
            first = f.read(len(HEADER.encode()))
    except OSError:
        return False
    return first == HEADER.encode()


def check_writable(path: Path | str) -> None:
    """Refuse an output that is not a ``.yaml`` file, or that exists and is not ours."""
    path = Path(path)
    if path.suffix not in (".yaml", ".yml"):
        raise OutputError(f"{path}: --out must name a .yaml file")
    if path.is_symlink():
        raise OutputError(f"{path}: is a symbolic link; refusing to replace it")
    if path.exists() and not is_generated_world(path):
        what = "a folder" if path.is_dir() else "a file this command did not write"
        raise OutputError(f"{path}: exists and is {what}; refusing to replace it")


def write_generated_world(
    path: Path | str, seed: int, rooms: int | None = None, params: FurnishParams | None = None
) -> GeneratedBuilding:
    """Generate a building and write it to ``path`` atomically.

    ``path`` may exist only as a world this generator wrote earlier; anything else (a user's
    world, a folder, a link) is refused before any work, with one line naming it.
    """
    _check_arguments(seed, rooms)
    check_writable(path)
    building = generate_building(seed, rooms, params)
    check_writable(path)  # nothing else moved in while we worked
    write_text_atomic(path, building.text)
    return building
