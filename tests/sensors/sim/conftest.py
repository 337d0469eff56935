"""Small worlds with analytic answers."""

from __future__ import annotations

from typing import Any

import pytest

from sensors.sim.world import World, world_from_mapping


def box_room_document(**room: Any) -> dict[str, Any]:
    """A 4 m × 3 m room with a 2.5 m ceiling and no openings."""
    return {
        "name": "box_room",
        "rooms": [
            {
                "name": "r",
                "footprint": [[0, 0], [4, 0], [4, 3], [0, 3]],
                "ceiling_m": 2.5,
                **room,
            }
        ],
    }


@pytest.fixture
def box_room() -> World:
    return world_from_mapping(box_room_document())
