"""World files: the built-ins, round trips, every rejection, and seeded perturbation."""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sensors.errors import WorldError
from sensors.sim.world import (
    Box,
    World,
    load_world,
    perturb_movables,
    world_from_mapping,
    world_to_yaml,
)
from tests.paths import REPO
from tests.sensors.sim.conftest import box_room_document

WORLDS = REPO / "configs" / "worlds"
BUILTIN = ["essex_lab", "office_loop", "cluttered_hall"]


@pytest.mark.parametrize("name", BUILTIN)
def test_builtin_worlds_load(name: str) -> None:
    world = load_world(WORLDS / f"{name}.yaml")
    assert world.name == name
    assert world.movable_names(), "every built-in world has movable objects"


def test_essex_lab_matches_the_paper() -> None:
    world = load_world(WORLDS / "essex_lab.yaml")
    lower, upper = world.bounds_xy()
    assert upper[0] - lower[0] == pytest.approx(12.0)  # "about 12 m wide"
    assert world.rooms[0].ceiling_m == pytest.approx(3.0)
    pillars = [b for b in world.boxes if b.name.startswith("pillar")]
    assert len(pillars) == 2
    assert all(not p.movable for p in pillars)
    windows = [o for o in world.rooms[0].openings if not o.is_door]
    doors = [o for o in world.rooms[0].openings if o.is_door]
    assert len(windows) >= 3
    assert {o.wall for o in windows} == {2}
    assert len(doors) >= 1
    movable = world.movable_names()
    assert any(n.startswith("desk") for n in movable)
    assert any(n.startswith("chair") for n in movable)


def test_office_loop_is_a_corridor_loop() -> None:
    world = load_world(WORLDS / "office_loop.yaml")
    lower, upper = world.bounds_xy()
    assert upper - lower == pytest.approx([30.0, 20.0])
    # A walk around the loop stays inside corridor rooms; the office block is not a room.
    loop = np.array([[1.0, 1.0], [29.0, 1.0], [29.0, 19.0], [1.0, 19.0]])
    assert world.inside(loop).all()
    assert not world.inside(np.array([[15.0, 10.0]]))[0]
    assert sum(r.name.startswith("office") for r in world.rooms) >= 4


def _band_raster(world: World, footprint: np.ndarray, res: float = 0.05) -> np.ndarray:
    """Cells of an axis-aligned room footprint under a fixed object in the band 2.3-2.9 m."""
    from sensors.sim.polygon import points_in_polygon

    lower, upper = footprint.min(axis=0), footprint.max(axis=0)
    xs = np.arange(lower[0] + res / 2, upper[0], res)
    ys = np.arange(lower[1] + res / 2, upper[1], res)
    gx, gy = np.meshgrid(xs, ys)
    centres = np.column_stack([gx.ravel(), gy.ravel()])
    hit = np.zeros(len(centres), dtype=bool)
    for box in world.boxes:
        if not box.movable and box.z_m[0] < 2.9 and box.z_m[1] > 2.3:
            hit |= points_in_polygon(centres, box.corners_xy())
    return hit.reshape(gx.shape)


def test_office_loop_offices_differ_in_the_ceiling_band() -> None:
    # The offices share one footprint, so only their fixtures can tell them apart to a
    # ceiling-band search: less than half of what two offices (or an office and its own half
    # turn) hold in the band may coincide.
    world = load_world(WORLDS / "office_loop.yaml")
    offices = [r for r in world.rooms if r.name.startswith("office")]
    rasters = {r.name: _band_raster(world, r.footprint_xy) for r in offices}
    assert len({r.shape for r in rasters.values()}) == 1
    for name, raster in rasters.items():
        assert raster.sum() > 200, f"{name} has next to nothing in the band"
        others = [(f"{o} turned {t}", np.rot90(rasters[o], t)) for o in rasters for t in (0, 2)]
        for label, other in others:
            if label == f"{name} turned 0":
                continue
            iou = (raster & other).sum() / (raster | other).sum()
            assert iou < 0.5, f"{name} looks like {label} in the band (IoU {iou:.2f})"


def test_cluttered_hall_has_dense_movable_clutter_below_the_band() -> None:
    world = load_world(WORLDS / "cluttered_hall.yaml")
    movable = [s for s in (*world.boxes, *world.cylinders) if s.movable]
    assert len(movable) >= 50
    assert max(s.z_m[1] for s in movable) <= 2.2  # clutter stays below the ceiling band
    assert max(s.z_m[1] for s in movable) >= 1.8  # and reaches ~2 m
    in_band = [b for b in world.boxes if not b.movable and b.z_m[1] > 2.3 and b.z_m[0] < 2.9]
    assert len(in_band) >= 5  # beams and ducts


@pytest.mark.parametrize("name", BUILTIN)
def test_world_yaml_round_trip(tmp_path: Path, name: str) -> None:
    world = load_world(WORLDS / f"{name}.yaml")
    path = tmp_path / "w.yaml"
    path.write_text(world_to_yaml(world), encoding="utf-8")
    assert load_world(path) == world


def edited(**changes: Any) -> dict[str, Any]:
    doc = copy.deepcopy(box_room_document())
    doc.update(changes)
    return doc


@pytest.mark.parametrize(
    ("document", "message"),
    [
        (
            edited(rooms=[{"name": "r", "footprint": [[0, 0], [4, 3], [4, 0], [0, 3]], "ceiling_m": 2.5}]),
            r"rooms\[0\]: room 'r': footprint is self-intersecting \(walls 0 and 2 cross\)",
        ),
        (
            edited(rooms=[{"name": "r", "footprint": [[0, 0], [0, 3], [4, 3], [4, 0]], "ceiling_m": 2.5}]),
            r"rooms\[0\]: room 'r': footprint is clockwise \(signed area -12 m²\)",
        ),
        (
            edited(rooms=[{"name": "r", "footprint": [[0, 0], [4, 0], [4, 0], [0, 3]], "ceiling_m": 2.5}]),
            r"room 'r': footprint vertices 1 and 2 coincide",
        ),
        (
            edited(rooms=[{"name": "r", "footprint": [[0, 0], [4, 0], [2, 0]], "ceiling_m": 2.5}]),
            r"room 'r': footprint is self-intersecting",
        ),
        (
            box_room_document(openings=[{"wall": 0, "from_m": 3.5, "to_m": 4.5, "top_m": 2.0}]),
            r"openings\[0\]: spans 3\.5-4\.5 m along wall 0, which is only 4\.000 m long",
        ),
        (
            box_room_document(openings=[{"wall": 4, "from_m": 1, "to_m": 2, "top_m": 2.0}]),
            r"openings\[0\]: wall 4 does not exist \(the footprint has walls 0-3\)",
        ),
        (
            box_room_document(openings=[{"wall": 1, "from_m": 1, "to_m": 2, "top_m": 2.6}]),
            r"openings\[0\]: top_m 2\.6 is above the ceiling \(2\.5 m\)",
        ),
        (
            box_room_document(openings=[{"wall": 1, "from_m": 2, "to_m": 1, "top_m": 2.0}]),
            r"rooms\[0\]\.openings\[0\]: to_m \(1\.0\) must be beyond from_m \(2\.0\)",
        ),
        (
            box_room_document(openings=[{"wall": 1, "from_m": -1, "to_m": 1, "top_m": 2.0}]),
            r"rooms\[0\]\.openings\[0\]\.from_m: Input should be greater than or equal to 0",
        ),
        (
            edited(boxes=[{"name": "crate", "center": [5.0, 1.0], "size": [0.5, 0.5], "z_m": [0, 1]}]),
            r"boxes\[0\] 'crate': centre \(5, 1\) lies outside every room",
        ),
        (
            edited(cylinders=[{"name": "bin", "center": [-1, 1], "radius_m": 0.2, "z_m": [0, 1]}]),
            r"cylinders\[0\] 'bin': centre \(-1, 1\) lies outside every room",
        ),
        (
            edited(boxes=[{"name": "tall", "center": [1, 1], "size": [0.5, 0.5], "z_m": [0, 3]}]),
            r"boxes\[0\] 'tall': rises to 3 m, above the ceiling of room 'r' \(2\.5 m\)",
        ),
        (
            edited(boxes=[{"name": "b", "center": [1, 1], "size": [0.5, 0.0], "z_m": [0, 1]}]),
            r"boxes\[0\]: 'b': size must be positive",
        ),
        (
            edited(boxes=[{"name": "b", "center": [1, 1], "size": [0.5, 0.5], "z_m": [1, 0.5]}]),
            r"boxes\[0\]: 'b': z_m must run upwards, got \[1, 0\.5\]",
        ),
        (
            edited(boxes=[{"name": "b", "center": [1, 1], "size": [0.5, 0.5], "z_m": [-0.5, 1]}]),
            r"'b': z_m starts below the floor",
        ),
        (
            edited(boxes=[{"name": "r", "center": [1, 1], "size": [0.5, 0.5], "z_m": [0, 1]}]),
            r"boxes\[0\]: name 'r' is already used by rooms\[0\]",
        ),
        (
            edited(boxes=[{"name": "b", "center": [1, 1], "size": [0.5, 0.5], "z_m": [0, 1], "colour": "red"}]),
            r"boxes\[0\]\.colour: unknown key \(got 'red'\)",
        ),
        (
            edited(boxes=[{"name": "b", "center": [1, 1, 0], "size": [0.5, 0.5], "z_m": [0, 1]}]),
            r"boxes\[0\]\.center: List should have at most 2 items",
        ),
        (
            edited(boxes=[{"name": "b", "center": [1, ".nan"], "size": [0.5, 0.5], "z_m": [0, 1]}]),
            r"boxes\[0\]\.center\[1\]: Input should be a valid number",
        ),
        (edited(rooms=[]), r"rooms: List should have at least 1 item"),
        (
            edited(rooms=[{"name": "r", "ceiling_m": 2.5, "footprint": [
                [10 * math.cos(a), 10 * math.sin(a)] for a in np.linspace(0, 6.28, 5000)]}]),
            r"rooms\[0\]\.footprint: List should have at most 4096 items",
        ),
        ({"rooms": box_room_document()["rooms"]}, r"name: required key is missing"),
    ],
)  # fmt: skip
def test_world_rejections_name_the_problem(document: dict[str, Any], message: str) -> None:
    with pytest.raises(WorldError, match=message) as info:
        world_from_mapping(document, source="w.yaml")
    assert str(info.value).startswith("w.yaml: ")
    assert "\n" not in str(info.value)


def test_nan_in_yaml_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "w.yaml"
    text = world_to_yaml(world_from_mapping(box_room_document())).replace("2.5", ".nan")
    path.write_text(text, encoding="utf-8")
    with pytest.raises(WorldError, match=r"rooms\[0\]\.ceiling_m: Input should be a finite number"):
        load_world(path)


def test_malformed_and_missing_world_files(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("rooms: [\n", encoding="utf-8")
    with pytest.raises(WorldError, match=r"bad\.yaml: malformed YAML at line"):
        load_world(bad)
    with pytest.raises(WorldError, match=r"absent\.yaml: no such file"):
        load_world(tmp_path / "absent.yaml")


def test_box_corners_follow_yaw() -> None:
    box = Box(name="b", center=[1.0, 2.0], size=[2.0, 1.0], z_m=[0.0, 1.0], yaw_deg=90.0)
    corners = box.corners_xy()
    np.testing.assert_allclose(corners[0], [1.5, 1.0], atol=1e-12)  # (−1, −0.5) turned by 90°
    np.testing.assert_allclose(corners.mean(axis=0), [1.0, 2.0], atol=1e-12)


def movable_world() -> World:
    doc = box_room_document()
    doc["boxes"] = [
        {
            "name": f"crate_{k}",
            "center": [0.5 + 0.4 * k, 1.5],
            "size": [0.3, 0.3],
            "z_m": [0, 1],
            "movable": True,
        }
        for k in range(8)
    ] + [{"name": "pillar", "center": [2.0, 2.5], "size": [0.3, 0.3], "z_m": [0, 2.5]}]
    doc["cylinders"] = [
        {"name": "bin", "center": [3.5, 0.5], "radius_m": 0.2, "z_m": [0, 0.5], "movable": True}
    ]
    return world_from_mapping(doc)


def test_perturbation_is_seeded_and_touches_only_movables() -> None:
    world = movable_world()
    a, changes_a = perturb_movables(
        world, np.random.default_rng(3), fraction=1.0, shift_m=0.5, yaw_deg=30.0
    )
    b, changes_b = perturb_movables(
        world, np.random.default_rng(3), fraction=1.0, shift_m=0.5, yaw_deg=30.0
    )
    assert a == b
    assert changes_a == changes_b
    assert {c.name for c in changes_a} == set(world.movable_names())
    pillar = next(x for x in a.boxes if x.name == "pillar")
    assert pillar == next(x for x in world.boxes if x.name == "pillar")
    for change in changes_a:
        assert np.hypot(*change.shift_m) <= 0.5 + 1e-12
        assert abs(change.yaw_deg) <= 30.0
    assert a.inside(np.array([s.center for s in (*a.boxes, *a.cylinders)])).all()
    moved = next(x for x in a.boxes if x.name == "crate_0")
    change = next(c for c in changes_a if c.name == "crate_0")
    np.testing.assert_allclose(moved.center, np.add([0.5, 1.5], change.shift_m), atol=1e-12)


def test_perturbation_fraction_and_removal() -> None:
    world = movable_world()
    same, changes = perturb_movables(
        world, np.random.default_rng(0), fraction=0.0, shift_m=1.0, yaw_deg=10
    )
    assert same == world
    assert changes == []
    empty, changes = perturb_movables(
        world, np.random.default_rng(0), fraction=1.0, shift_m=1.0, yaw_deg=10, remove_fraction=1.0
    )
    assert empty.movable_names() == []
    assert len(changes) == 9
    assert all(c.action == "removed" for c in changes)
    assert [b.name for b in empty.boxes] == ["pillar"]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"fraction": 1.5, "shift_m": 0.1, "yaw_deg": 0}, r"fraction must be within \[0, 1\]"),
        ({"fraction": 0.5, "shift_m": 0.1, "yaw_deg": 0, "remove_fraction": -0.1}, r"remove_fraction"),
        ({"fraction": 0.5, "shift_m": -1.0, "yaw_deg": 0}, r"shift_m and yaw_deg must be >= 0"),
        ({"fraction": float("nan"), "shift_m": 0.1, "yaw_deg": 0}, r"fraction must be within"),
    ],
)  # fmt: skip
def test_perturbation_rejects_bad_parameters(kwargs: dict[str, float], message: str) -> None:
    with pytest.raises(WorldError, match=message):
        perturb_movables(movable_world(), np.random.default_rng(0), **kwargs)  # type: ignore[arg-type]
