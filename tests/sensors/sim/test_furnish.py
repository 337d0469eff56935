"""Furnishing: the floor check, clear doorways, fixtures in the band, pillars, distractors."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from sensors.sim.floorcheck import floor_reachable
from sensors.sim.floorplan import Door, PlanRoom, Rect, outline
from sensors.sim.furnish import FurnishParams, furnish_room
from sensors.sim.world import Box

ROOM = PlanRoom("lab_01", "lab", (Rect(0, 0, 6, 4),), Rect(0, 0, 6, 4).corners(), 3.0)
# Doors in the south wall near the west end and in the north wall near the east end.
DOORS = [(np.array([1.0, 0.0]), np.array([2.2, 0.0])), (np.array([5.0, 4.0]), np.array([3.8, 4.0]))]


def shelf(x0: float, x1: float) -> dict[str, Any]:
    """A shelf across the room at y 1.8-2.2 from x0 to x1."""
    return {"name": "shelf", "center": [(x0 + x1) / 2, 2.0], "size": [x1 - x0, 0.4],
            "z_m": [0.0, 1.8]}  # fmt: skip


@pytest.mark.parametrize(
    ("boxes", "reachable"),
    [
        ([], True),
        ([shelf(0.0, 6.0)], False),  # wall to wall between the doors
        ([shelf(0.0, 4.8)], True),  # 1.2 m left at the east wall: wide enough
        ([shelf(0.0, 5.4)], False),  # 0.6 m: too narrow for a 0.45 m radius
        ([{**shelf(0.0, 6.0), "z_m": [0.5, 1.8]}], True),  # above the robot: no obstacle
        ([{"name": "crate", "center": [1.6, 0.5], "size": [0.8, 0.6], "z_m": [0.0, 1.0]}], False),
    ],
)  # fmt: skip
def test_floor_check_needs_a_path_between_the_doors(
    boxes: list[dict[str, Any]], reachable: bool
) -> None:
    assert floor_reachable(ROOM, boxes, [], DOORS, radius_m=0.45) is reachable


def test_floor_check_sees_cylinders() -> None:
    barrel = {"name": "barrel", "center": [4.4, 3.5], "radius_m": 0.4, "z_m": [0.0, 0.9]}
    assert floor_reachable(ROOM, [], [barrel], DOORS, radius_m=0.45) is False
    assert floor_reachable(ROOM, [], [{**barrel, "center": [3.0, 2.0]}], DOORS, radius_m=0.45)


def hall(ceiling_m: float) -> PlanRoom:
    part = Rect(0.0, 0.0, 16.0, 11.0)
    return PlanRoom("hall_01", "hall", (part,), part.corners(), ceiling_m)


HALL_DOORS = [
    Door((0, 1), (6.0, 0.0), (8.0, 0.0), 2.6),
    Door((0, 2), (16.0, 4.0), (16.0, 5.2), 2.1),
]


def footprint(doc: dict[str, Any]) -> np.ndarray:
    """Corners of a box, or the bounding square of a cylinder."""
    if "radius_m" in doc:
        centre, r = np.asarray(doc["center"], dtype=float), float(doc["radius_m"])
        return np.array([centre - r, centre + r])
    return Box.model_validate(doc).corners_xy()


@pytest.mark.parametrize("ceiling_m", [2.4, 3.2, 4.5])
def test_fixtures_reach_the_band_and_the_floor_stays_clear(ceiling_m: float) -> None:
    params = FurnishParams(band_m=(2.3, 2.9))
    for seed in range(8):
        stuff = furnish_room(hall(ceiling_m), HALL_DOORS, params, np.random.default_rng(seed))
        fixtures = [d for d in stuff.boxes + stuff.cylinders if d["z_m"][0] > 2.0]
        assert all(d["z_m"][1] <= ceiling_m + 1e-9 for d in stuff.boxes + stuff.cylinders)
        if stuff.ceiling != ["bare"]:
            assert fixtures
            # All reach into the band but a truss's top chord, which carries the roof.
            hanging = [d for d in fixtures if "truss_top" not in str(d["name"])]
            assert all(d["z_m"][0] < 2.9 and d["z_m"][1] > 2.3 for d in hanging), stuff.ceiling
            if ceiling_m > 3.6:
                assert "beams" not in stuff.ceiling
                assert "bulkhead" not in stuff.ceiling
        # Nothing stands in front of a door (1.5 m deep, 0.5 m either side).
        keep_out = [Rect(5.5, 0.0, 8.5, 1.5), Rect(14.5, 3.5, 16.0, 5.7)]
        for doc in stuff.boxes + stuff.cylinders:
            if doc["z_m"][0] >= 0.35:
                continue
            lo, hi = footprint(doc).min(axis=0), footprint(doc).max(axis=0)
            for k in keep_out:
                assert hi[0] <= k.x0 or lo[0] >= k.x1 or hi[1] <= k.y0 or lo[1] >= k.y1, doc
        spans = [(np.asarray(d.start_xy), np.asarray(d.end_xy)) for d in HALL_DOORS]
        assert floor_reachable(hall(ceiling_m), stuff.boxes, stuff.cylinders, spans, radius_m=0.4)


def test_halls_get_pillars_furniture_is_movable_and_distractors_reflect_at_beacon_height() -> None:
    params = FurnishParams(beacon_height_m=1.6, beacon_length_m=0.6)
    pillars = distractors = 0
    for seed in range(12):
        stuff = furnish_room(hall(4.2), HALL_DOORS, params, np.random.default_rng(seed))
        pillars += stuff.pillars
        distractors += stuff.distractors
        for doc in stuff.boxes + stuff.cylinders:
            name = str(doc["name"])
            assert name.startswith("hall_01_")
            if any(w in name for w in ("rack", "crate", "table", "barrel")):
                assert doc.get("movable") is True
            if doc.get("retroreflective"):
                assert doc["z_m"][0] < 1.9
                assert doc["z_m"][1] > 1.3
                assert "movable" not in doc
            if "pillar" in name:
                assert doc["z_m"] == [0.0, 4.2]
    assert pillars >= 12
    assert distractors >= 2
    names = [d["name"] for s in range(3) for d in
             furnish_room(hall(4.2), HALL_DOORS, params, np.random.default_rng(s)).boxes]  # fmt: skip
    assert len(set(names)) < len(names)  # the same names in other draws, unique within one


def test_an_l_shaped_room_keeps_its_things_inside() -> None:
    parts = (Rect(0, 0, 5, 4), Rect(0, 4, 10, 9))
    room = PlanRoom("l_shaped_01", "l_shaped", parts, outline(parts), 3.0)
    from sensors.sim.polygon import points_in_polygon

    for seed in range(10):
        stuff = furnish_room(room, [], FurnishParams(), np.random.default_rng(seed))
        for doc in stuff.boxes + stuff.cylinders:
            corners = footprint(doc)
            shrunk = corners + 0.02 * np.sign(corners.mean(axis=0) - corners)
            assert points_in_polygon(shrunk, room.footprint).all(), (seed, doc["name"])
