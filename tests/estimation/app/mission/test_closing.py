"""Tying the mission's tail: which station floats, and where the pair goes to tie it."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from estimation.app.mission.closing import (
    CLOSING_STATIONS,
    closing_target,
    floating_tail,
    target_near,
)
from estimation.app.mission.view import MapView
from estimation.posegraph.keys import pose_key
from tests.estimation.app.mission.conftest import BODY_AT, RES

# Generated building 13's last stations, as flown: a160's half-turn was untied, its link to
# b149 and its loop closure were refused, and every later search was against a160 or after it.
ORDER = ["a157", "b149", "a160", "b152", "b153", "a164", "b156"]


def used(station: str, against: str, kind: str = "link", ok: bool = True) -> dict[str, Any]:
    return {"station": station, "against": against, "kind": kind, "used": ok}


BUILDING_13 = [
    used("b149", "a157"), used("b149", "b135", "loop"),
    used("a160", "b149", ok=False), used("a160", "a125", "loop", ok=False),
    used("b152", "a160"), used("b152", "a47", "loop", ok=False),
    used("b153", "b152"), used("b153", "a160"),
    used("a164", "b153"), used("a164", "b152"), used("a164", "a160", ok=False),
    used("b156", "a164"), used("b156", "b153"), used("b156", "a55", "loop", ok=False),
]  # fmt: skip


def test_a_tail_after_an_untied_turn_whose_searches_all_failed_floats() -> None:
    assert floating_tail(ORDER, {"b149", "a160"}, BUILDING_13) == "a160"


def test_a_search_used_against_a_station_before_the_tail_ties_it() -> None:
    for tie in (used("b156", "b149", "loop"), used("b153", "a157", "loop"), used("b152", "b149")):
        assert floating_tail(ORDER, {"a160"}, [*BUILDING_13, tie]) is None
    # Against the floating station itself, or a station after it: still floating.
    for inside in (used("b156", "a160", "loop"), used("b156", "b152", "loop")):
        assert floating_tail(ORDER, {"a160"}, [*BUILDING_13, inside]) == "a160"
    # A search of a station against one the mission does not know ties nothing.
    assert floating_tail(ORDER, {"a160"}, [*BUILDING_13, used("b156", "z1", "loop")]) == "a160"


def test_an_untied_turn_whose_own_link_was_used_does_not_float() -> None:
    assert floating_tail(ORDER, {"a160"}, [*BUILDING_13, used("a160", "b149")]) is None
    # Tied turns do not float, whatever their searches.
    assert floating_tail(ORDER, set(), BUILDING_13) is None
    assert floating_tail([], {"a160"}, BUILDING_13) is None


def test_the_first_of_two_floating_stations_starts_the_tail_until_it_is_tied() -> None:
    # b153 turned untied too and none of its searches was used: the tail starts at a160.
    records = [r for r in BUILDING_13 if r["station"] != "b153"]
    assert floating_tail(ORDER, {"a160", "b153"}, records) == "a160"
    # A loop closure of b152 to b149 ties the tail begun at a160, and a164's link to b152
    # the one begun at b153.
    tied = [*records, used("b152", "b149", "loop")]
    assert floating_tail(ORDER, {"a160", "b153"}, tied) is None
    # Without that link b153 floats anew.
    untied_b153 = [r for r in tied if (r["station"], r["against"]) != ("a164", "b152")]
    assert floating_tail(ORDER, {"a160", "b153"}, untied_b153) == "b153"


def test_the_target_is_the_drivable_floor_around_the_place(view: MapView) -> None:
    place = np.array([3.0, 2.0])
    target = target_near(view, place)
    assert target is not None
    np.testing.assert_array_equal(target.centroid_xy, place)
    centres = view.space.lower_xy + (target.cells[:, ::-1] + 0.5) * RES
    assert np.hypot(*(centres - place).T).max() <= 1.0
    assert view.space.free[target.cells[:, 0], target.cells[:, 1]].all()
    assert target.size == len(target.cells) > 0.9 * math.pi / RES**2
    assert target.area_m2 == pytest.approx(target.size * RES**2)
    # Beyond the map, or where nothing within a metre is drivable: no target.
    assert target_near(view, np.array([40.0, 40.0])) is None


@dataclass
class Loop:
    """The parts of the mission loop that closing reads."""

    estimate: dict[int, np.ndarray] = field(default_factory=dict)
    trace: list[dict[str, Any]] = field(default_factory=list)
    localizations: list[dict[str, Any]] = field(default_factory=list)
    untied: dict[str, str] = field(default_factory=dict)
    closing: list[str] = field(default_factory=list)


def test_closing_goes_back_where_the_station_before_the_tail_stood(view: MapView) -> None:
    loop = Loop(
        estimate={pose_key("b", 149): np.array([BODY_AT[0], BODY_AT[1], 0.3])},
        trace=[{"reference": label, "scans": 2} for label in ORDER],
        localizations=[{"records": BUILDING_13[:7]}, {"records": BUILDING_13[7:]}],
        untied={"a160": "no chain of pivots"},
    )  # fmt: skip
    target = closing_target(loop, view)
    assert target is not None
    np.testing.assert_array_equal(target.centroid_xy, BODY_AT)
    assert loop.closing == ["a160"]
    # Bounded: after CLOSING_STATIONS stations the mission ends, tied or not.
    loop.closing = ["a160"] * CLOSING_STATIONS
    assert closing_target(loop, view) is None
    # A tied tail, a station the estimate does not place, a failed station: no target.
    loop.closing = []
    loop.localizations.append({"records": [used("b156", "b149", "loop")]})
    assert closing_target(loop, view) is None
    loop.localizations.pop()
    loop.estimate = {}
    assert closing_target(loop, view) is None
    assert loop.closing == []
    loop.estimate = {pose_key("b", 149): np.array([BODY_AT[0], BODY_AT[1], 0.3])}
    loop.trace[1]["scans"] = 0  # b149 took no scan: the station before a160 is a157
    assert closing_target(loop, view) is None  # a157 is not placed
