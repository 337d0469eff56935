"""Generated buildings: valid, connected, drivable, varied, deterministic; the file guard."""

from __future__ import annotations

import os
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from sensors.errors import OutputError, WorldError
from sensors.sim.floorplan import KINDS, door_links
from sensors.sim.furnish import FurnishParams
from sensors.sim.generate import (
    HEADER,
    GeneratedBuilding,
    generate_building,
    is_generated_world,
    room_kind,
    write_generated_world,
)
from sensors.sim.planner import free_space
from sensors.sim.world import World, load_world
from tests.paths import REPO

SEEDS = range(50)
PARAMS = FurnishParams()


@pytest.fixture(scope="module")
def buildings() -> dict[int, GeneratedBuilding]:
    return {seed: generate_building(seed) for seed in SEEDS}


def reachable_rooms(world: World, links: dict[str, set[str]]) -> set[str]:
    start = world.rooms[0].name
    seen, todo = {start}, [start]
    while todo:
        for other in links[todo.pop()] - seen:
            seen.add(other)
            todo.append(other)
    return seen


def test_every_seed_writes_a_world_the_loader_accepts(
    buildings: dict[int, GeneratedBuilding], tmp_path: Path
) -> None:
    for seed, building in buildings.items():
        path = tmp_path / f"{seed}.yaml"
        path.write_text(building.text, encoding="utf-8")
        world = load_world(path)
        assert world == building.world
        assert [r.name for r in world.rooms] == [r.name for r in building.rooms]


def test_room_counts_stay_within_3_to_15_and_follow_rooms(
    buildings: dict[int, GeneratedBuilding],
) -> None:
    counts = Counter(len(b.world.rooms) for b in buildings.values())
    assert min(counts) == 3
    assert max(counts) == 15
    assert len(counts) >= 10  # drawn from the seed, not fixed
    for rooms in (3, 8, 15):
        assert len(generate_building(5, rooms).world.rooms) == rooms


def test_every_kind_occurs_and_names_carry_the_kind(
    buildings: dict[int, GeneratedBuilding],
) -> None:
    kinds = Counter(room.kind for b in buildings.values() for room in b.rooms)
    assert set(kinds) == set(KINDS)
    for building in buildings.values():
        for room in building.rooms:
            assert room_kind(room.name) == room.kind
            assert f"#   {room.name}: {room.kind}, " in building.text
    l_rooms = [r for b in buildings.values() for r in b.world.rooms if r.name.startswith("l_")]
    assert l_rooms
    assert all(len(r.footprint) == 6 for r in l_rooms)
    with pytest.raises(WorldError, match="'lab' is not a generated room"):
        room_kind("lab")


def test_doors_join_every_room_to_every_other(buildings: dict[int, GeneratedBuilding]) -> None:
    for seed, building in buildings.items():
        world = building.world
        links = door_links(world)
        assert reachable_rooms(world, links) == {r.name for r in world.rooms}, seed
        for room in world.rooms:
            for door in (o for o in room.openings if o.is_door):
                assert door.to_m - door.from_m >= 1.0 - 1e-9, (seed, room.name)
                assert door.top_m >= 2.0


def test_ceilings_span_2_4_to_4_5_m_and_vary_within_a_building(
    buildings: dict[int, GeneratedBuilding],
) -> None:
    every = [r.ceiling_m for b in buildings.values() for r in b.world.rooms]
    assert 2.4 <= min(every) <= 2.5
    assert 4.4 <= max(every) <= 4.5
    for seed, building in buildings.items():
        assert len({r.ceiling_m for r in building.world.rooms}) >= 2, seed
    halls = [r for b in buildings.values() for r in b.rooms if r.kind == "hall"]
    assert halls
    assert min(r.ceiling_m for r in halls) >= 3.6
    offices = [r for b in buildings.values() for r in b.rooms if r.kind == "office"]
    assert max(r.ceiling_m for r in offices) <= 3.0


def test_every_room_has_reachable_floor_for_the_robot(
    buildings: dict[int, GeneratedBuilding],
) -> None:
    for seed, building in buildings.items():
        world = building.world
        space = free_space(world, robot_radius_m=PARAMS.robot_radius_m, robot_height_m=0.35)
        cells = np.argwhere(space.free)
        centres = space.lower_xy + (cells[:, ::-1] + 0.5) * space.resolution_m
        first = centres[np.flatnonzero(world.rooms[0].contains(centres))[0]]
        component = space.component_of(first)[cells[:, 0], cells[:, 1]]
        # One component reaches into every room: the doors are passable and not blocked.
        for room in world.rooms:
            inside = room.contains(centres)
            assert (inside & component).sum() >= 20, (seed, room.name)


def test_ceiling_structure_reaches_the_band_and_differs_between_rooms(
    buildings: dict[int, GeneratedBuilding],
) -> None:
    low, high = PARAMS.band_m
    bare = structured = 0
    for building in buildings.values():
        world = building.world
        layouts = []
        for room, info in zip(world.rooms, building.rooms, strict=True):
            fixtures = [
                s for s in (*world.boxes, *world.cylinders)
                if s.z_m[0] > 2.0 and world.room_at(s.center) == room
            ]  # fmt: skip
            in_band = [s for s in fixtures if s.z_m[0] < high and s.z_m[1] > low]
            if info.ceiling_structure == ("bare",):
                bare += 1
                assert len(fixtures) <= 1
            else:
                structured += 1
                assert in_band, (building.seed, room.name, info.ceiling_structure)
            if info.ceiling_structure != ("bare",):
                # The band's cross-section of the room: its outline and what hangs in it.
                origin = room.footprint_xy.min(axis=0)
                shape = tuple(map(tuple, (room.footprint_xy - origin).round(1)))
                layouts.append((shape, tuple(sorted(
                    (round(s.center[0] - origin[0], 1), round(s.center[1] - origin[1], 1))
                    for s in in_band))))  # fmt: skip
        assert len(set(layouts)) == len(layouts), building.seed
    assert 0.05 < bare / (bare + structured) < 0.3
    features = Counter(f for b in buildings.values() for r in b.rooms for f in r.ceiling_structure)
    assert {"lights", "ducts", "beams", "bulkhead", "trusses", "bare"} <= set(features)


def test_furniture_is_movable_pillars_stand_in_large_rooms_and_distractors_at_beacon_height(
    buildings: dict[int, GeneratedBuilding],
) -> None:
    beacon_low = PARAMS.beacon_height_m - PARAMS.beacon_length_m / 2
    beacon_high = PARAMS.beacon_height_m + PARAMS.beacon_length_m / 2
    with_distractors = 0
    for building in buildings.values():
        world = building.world
        solids = (*world.boxes, *world.cylinders)
        floor = [s for s in solids if s.z_m[0] == 0.0 and "pillar" not in s.name]
        assert floor
        assert all(s.movable for s in floor if "post" not in s.name)
        reflective = [s for s in solids if s.retroreflective]
        assert all(s.z_m[0] < beacon_high and s.z_m[1] > beacon_low for s in reflective)
        assert not any(s.movable for s in reflective)
        with_distractors += bool(reflective)
        for room in building.rooms:
            if room.pillars:
                assert room.area_m2 >= 50.0
                assert room.kind in ("hall", "lab", "l_shaped")
    assert 10 <= with_distractors < len(buildings)
    assert sum(r.pillars > 0 for b in buildings.values() for r in b.rooms) >= 10


def test_the_same_seed_gives_the_same_bytes_and_seeds_differ() -> None:
    first = generate_building(11, 9)
    assert generate_building(11, 9).text == first.text
    assert generate_building(12, 9).text != first.text
    assert generate_building(11, 10).text != first.text
    # Another interpreter with another hash seed writes the same bytes.
    code = "from sensors.sim.generate import generate_building as g; print(g(11, 9).text, end='')"
    env = {**os.environ, "PYTHONHASHSEED": "12345"}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, env=env, check=True
    )
    assert out.stdout == first.text


def test_the_band_and_robot_come_from_the_parameters() -> None:
    low = generate_building(3, 6, FurnishParams(band_m=(2.2, 2.6))).world
    fixtures = [b for b in low.boxes if b.z_m[0] > 2.0 and "lamp" in b.name]
    assert fixtures
    assert all(b.z_m[0] < 2.6 and b.z_m[1] > 2.2 for b in fixtures)
    wide = generate_building(3, 6, FurnishParams(robot_radius_m=0.45)).world
    doors = [o for r in wide.rooms for o in r.openings if o.is_door]
    assert min(o.to_m - o.from_m for o in doors) >= 2 * (0.45 + 0.1) + 0.2 - 1e-9


@pytest.mark.parametrize(
    ("seed", "rooms", "message"),
    [(0, 2, r"--rooms must be within 3-40, got 2"), (0, 41, r"--rooms must be within 3-40"),
     (-1, None, r"--seed must be >= 0, got -1")],
)  # fmt: skip
def test_bad_arguments_are_refused(seed: int, rooms: int | None, message: str) -> None:
    with pytest.raises(WorldError, match=message):
        generate_building(seed, rooms)


def test_write_replaces_only_its_own_files(tmp_path: Path) -> None:
    out = tmp_path / "nested" / "b.yaml"
    building = write_generated_world(out, 4, 5)
    assert out.read_text(encoding="utf-8") == building.text
    assert building.text.startswith(HEADER)
    assert is_generated_world(out)
    again = write_generated_world(out, 6, 7)  # an earlier generated world is replaced
    assert load_world(out).name == again.world.name == "generated_6_7"

    user = tmp_path / "mine.yaml"
    user.write_text("# my hand-made lab\nname: lab\n", encoding="utf-8")
    with pytest.raises(OutputError, match=r"mine\.yaml: exists and is a file this command did"):
        write_generated_world(user, 4, 5)
    assert user.read_text(encoding="utf-8") == "# my hand-made lab\nname: lab\n"
    link = tmp_path / "link.yaml"
    link.symlink_to(out)
    with pytest.raises(OutputError, match="symbolic link"):
        write_generated_world(link, 4, 5)
    (tmp_path / "folder.yaml").mkdir()
    with pytest.raises(OutputError, match="exists and is a folder"):
        write_generated_world(tmp_path / "folder.yaml", 4, 5)
    with pytest.raises(OutputError, match=r"--out must name a \.yaml file"):
        write_generated_world(tmp_path / "b.json", 4, 5)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder.yaml", "link.yaml", "mine.yaml",
                                                          "nested"]  # fmt: skip
    assert sorted(p.name for p in (tmp_path / "nested").iterdir()) == ["b.yaml"]  # no leftovers


@pytest.mark.parametrize("rooms", [3, 15])
def test_explicit_room_counts_give_loadable_buildings(rooms: int, tmp_path: Path) -> None:
    """Seed 210 with 15 rooms shared a wall 1e-6 m shorter than a door and its jambs, and the
    door's start was drawn from an empty range."""
    for seed in (210, *range(200, 206)):
        building = generate_building(seed, rooms)
        assert len(building.rooms) == rooms
        path = tmp_path / f"{seed}_{rooms}.yaml"
        path.write_text(building.text, encoding="utf-8")
        assert load_world(path) == building.world
