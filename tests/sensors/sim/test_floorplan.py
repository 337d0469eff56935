"""Floor plans: outlines of rectangle unions, shared walls, doors in both walls, the door graph."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from sensors.sim.floorplan import (
    JAMB_M,
    Rect,
    door_links,
    draw_floor_plan,
    outline,
    shared_walls,
)
from sensors.sim.polygon import signed_area
from sensors.sim.world import world_from_mapping


def test_outline_of_an_l_and_of_two_halves_of_a_rectangle() -> None:
    ell = outline([Rect(0, 0, 4, 3), Rect(0, 3, 10, 8)])
    assert ell.tolist() == [[0, 0], [4, 0], [4, 3], [10, 3], [10, 8], [0, 8]]
    assert signed_area(ell) == pytest.approx(12 + 50)
    whole = outline([Rect(0, 0, 4, 3), Rect(4, 0, 9, 3)])
    assert whole.tolist() == [[0, 0], [9, 0], [9, 3], [0, 3]]
    with pytest.raises(ValueError, match="not one simple polygon"):
        outline([Rect(0, 0, 1, 1), Rect(1, 1, 2, 2)])  # touching at a corner only


def test_shared_walls_run_opposite_ways_over_the_common_stretch() -> None:
    a = Rect(0, 0, 4, 3).corners()
    b = Rect(4, 1, 8, 6).corners()
    # a's east wall (1) runs north from (4, 0); b's west wall (3) runs south; they share y 1-3.
    assert shared_walls(a, b) == [(1, 3, pytest.approx(1.0), pytest.approx(3.0))]
    assert shared_walls(a, Rect(5, 0, 8, 3).corners()) == []


def two_rooms(door_a: dict[str, Any] | None, door_b: dict[str, Any] | None) -> dict[str, Any]:
    """Rooms west (0-4) and east (4-8) of x = 4; wall 1 of west and wall 3 of east are shared."""
    west: dict[str, Any] = {
        "name": "west",
        "footprint": [[0, 0], [4, 0], [4, 5], [0, 5]],
        "ceiling_m": 3.0,
        "openings": [door_a] if door_a else [],
    }
    east: dict[str, Any] = {
        "name": "east",
        "footprint": [[4, 0], [8, 0], [8, 5], [4, 5]],
        "ceiling_m": 4.0,
        "openings": [door_b] if door_b else [],
    }
    return {"name": "pair", "rooms": [west, east]}  # fmt: skip


@pytest.mark.parametrize(
    ("door_a", "door_b", "linked"),
    [
        # West's wall 1 runs north: 1-2.2 m from (4, 0) is y 1-2.2; east's wall 3 runs south
        # from (4, 5), so the same stretch is 2.8-4.0 m along it.
        ({"wall": 1, "from_m": 1.0, "to_m": 2.2, "top_m": 2.1},
         {"wall": 3, "from_m": 2.8, "to_m": 4.0, "top_m": 2.1}, True),
        ({"wall": 1, "from_m": 1.0, "to_m": 2.2, "top_m": 2.1}, None, False),
        ({"wall": 1, "from_m": 1.0, "to_m": 2.2, "top_m": 2.1},
         {"wall": 3, "from_m": 1.0, "to_m": 2.2, "top_m": 2.1}, False),  # another stretch
        ({"wall": 1, "from_m": 1.0, "to_m": 2.2, "bottom_m": 0.9, "top_m": 2.1},
         {"wall": 3, "from_m": 2.8, "to_m": 4.0, "bottom_m": 0.9, "top_m": 2.1}, False),  # window
        ({"wall": 1, "from_m": 1.0, "to_m": 2.2, "top_m": 2.1},
         {"wall": 2, "from_m": 1.0, "to_m": 2.2, "top_m": 2.1}, False),  # not the shared wall
    ],
)  # fmt: skip
def test_door_links_need_a_door_over_the_same_stretch_in_both_walls(
    door_a: dict[str, Any] | None, door_b: dict[str, Any] | None, linked: bool
) -> None:
    links = door_links(world_from_mapping(two_rooms(door_a, door_b)))
    assert links == ({"west": {"east"}, "east": {"west"}} if linked else
                     {"west": set(), "east": set()})  # fmt: skip


@pytest.mark.parametrize("count", [3, 7, 15])
def test_doors_sit_in_shared_walls_clear_of_their_ends(count: int) -> None:
    for seed in range(6):
        plan = draw_floor_plan(count, np.random.default_rng(seed), min_door_m=1.0)
        assert len(plan.rooms) == count
        assert len(plan.doors) >= count - 1  # a spanning tree at least
        for door in plan.doors:
            i, j = door.rooms
            assert door.width_m >= 1.0 - 1e-9
            walls = shared_walls(plan.rooms[i].footprint, plan.rooms[j].footprint)
            footprint = plan.rooms[i].footprint
            inside = False
            for wall, _, lo, hi in walls:
                a = footprint[wall]
                along = (footprint[(wall + 1) % len(footprint)] - a) / np.linalg.norm(
                    footprint[(wall + 1) % len(footprint)] - a
                )
                s = sorted(float(along @ (np.asarray(p) - a)) for p in (door.start_xy, door.end_xy))
                rel = np.asarray(door.start_xy) - a
                offset = abs(along[0] * rel[1] - along[1] * rel[0])
                if offset < 1e-6 and s[0] >= lo + JAMB_M - 0.03 and s[1] <= hi - JAMB_M + 0.03:
                    inside = True
            assert inside, (seed, door)
            # The door is an opening in the wall of each of its two rooms.
            for k in (i, j):
                assert any(o.bottom_m == 0.0 and o.top_m == door.top_m for o in plan.openings[k])
        for room in plan.rooms:
            assert min(min(p.width, p.height) for p in room.parts) >= 2.0
            assert signed_area(room.footprint) == pytest.approx(room.area_m2)
