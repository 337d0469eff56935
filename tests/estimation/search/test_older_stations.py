"""Which older stations a loop closure matches against: those the graph places well against its
anchor (``placed_against``), not tied to the new station much more tightly than the anchor
(``apart_from_drift``), and of those at most ``OLDER_MOST``, the ones that saw the new
station's view (``seen_alike``)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from estimation.posegraph.graph import FactorSpec
from estimation.posegraph.keys import pose_key
from estimation.posegraph.marginals import RelativeCovariances, relative_covariances
from estimation.search import stations as stations_module
from estimation.search.older_stations import (
    OLDER_MOST,
    apart_from_drift,
    placed_against,
    pose_sigmas,
    seen_alike,
)
from estimation.search.registration import RegistrationParams
from estimation.search.station_maps import Station
from estimation.search.stations import loop_closures
from mapping.band import Band
from sensors.geometry import se2
from tests.estimation.search.test_station_maps import TOLERANT, revisiting_mission

TIGHT = np.diag([1e-4, 1e-4, math.radians(0.05) ** 2])


def chain_of_stations(
    chain: list[np.ndarray],
) -> tuple[list[FactorSpec], dict[int, np.ndarray], list[Station]]:
    """Stations a0… 1 m apart in a row, a prior on a0 and odometry with the ``chain``'s
    covariances between them: (factors, estimate, stations)."""
    keys = [pose_key("a", n) for n in range(len(chain) + 1)]
    estimate = {k: np.array([1.0 * n, 0.0, 0.0]) for n, k in enumerate(keys)}
    step = np.array([1.0, 0.0, 0.0])
    factors = [FactorSpec("prior", (keys[0],), estimate[keys[0]], TIGHT * 1e-2, 0)]
    factors += [FactorSpec("odometry", (keys[n], keys[n + 1]), step, c, n + 1)
                for n, c in enumerate(chain)]  # fmt: skip
    return factors, estimate, [Station("a", n, 40.0 * n, ()) for n in range(len(keys))]


def test_a_loop_closure_matches_only_older_stations_the_graph_places_well_against_its_anchor() -> (
    None
):
    """Stations a0–a3 tied tightly, then an untied stretch (3° of heading), then a4–a6 tied
    tightly again: a new station after them, anchored on a1, matches a0–a3 only. a4–a6 lie in
    the anchor's frame as far off as the new station itself (generated building 106)."""
    tight, loose = TIGHT, np.diag([0.01, 0.01, math.radians(3.0) ** 2])
    factors, estimate, stations = chain_of_stations([tight, tight, tight, loose, tight, tight,
                                                     loose])  # fmt: skip
    keys, step = [s.key for s in stations], np.array([1.0, 0.0, 0.0])
    relative = relative_covariances(factors, estimate)
    anchor, older, new = stations[1], stations[:7], stations[7]

    def kept(relative: RelativeCovariances, of: list[Station] = older) -> list[Station]:
        uncertainty, *placed = relative.around(anchor.key, [new.key, *(s.key for s in of)])
        return placed_against(of, placed, uncertainty)

    assert pose_sigmas(relative(anchor.key, new.key))[1] > math.radians(4.0)
    assert kept(relative) == stations[:4]
    # A new station tied tightly to a6 still rests on the untied stretch, as a4–a6 do.
    tied = [*factors[:-1], FactorSpec("odometry", (keys[6], keys[7]), step, tight, 7)]
    assert kept(relative_covariances(tied, estimate)) == stations[:4]
    # No untied stretch: every older station lies within the floors (0.1 m, 0.5°); the anchor
    # (its own covariance zero) is always matched.
    all_tight = [*factors[:1], *(dataclasses.replace(f, covariance=tight) for f in factors[1:])]
    relative = relative_covariances(all_tight, estimate)
    zero = np.zeros((3, 3))
    assert placed_against(older, relative.around(anchor.key, [s.key for s in older]), zero) == older
    assert placed_against([anchor], [zero], zero) == [anchor]


def test_a_closure_leaves_out_the_older_stations_that_share_the_new_stations_drift() -> None:
    """a0–a1 tied tightly, a loose stretch to a2, then a2–a7 tied tightly: the new station a7,
    anchored on a1, shares its drift with a2–a6 (known to it 10× better than a1 is), so only
    a0 and the anchor are left to match."""
    loose = np.diag([0.01, 0.01, math.radians(1.0) ** 2])
    factors, estimate, stations = chain_of_stations([TIGHT, loose, *[TIGHT] * 5])
    anchor, older, new = stations[1], stations[:7], stations[7]
    covariances = relative_covariances(factors, estimate).around(new.key, [s.key for s in older])
    assert apart_from_drift(older, anchor, covariances) == [stations[0], anchor]
    # Both are needed to leave a station out: one known better in position only is kept.
    anchor_covariance = covariances[1]
    sharper = np.diag([1e-8, 1e-8, anchor_covariance[2, 2]])
    assert apart_from_drift([stations[0], anchor], anchor, [sharper, anchor_covariance]) == [
        stations[0],
        anchor,
    ]
    both = np.diag([1e-8, 1e-8, 0.2 * anchor_covariance[2, 2]])
    assert apart_from_drift([stations[0], anchor], anchor, [both, anchor_covariance]) == [anchor]
    # The anchor is always kept; it must be among the older stations.
    assert apart_from_drift([anchor], anchor, [anchor_covariance]) == [anchor]
    with pytest.raises(ValueError, match="anchor must be one of the older stations"):
        apart_from_drift([stations[0]], anchor, [covariances[0]])


RES = 0.5


def rectangle(width_m: float, height_m: float = 4.0) -> Band | None:
    """A band known over [0, width) × [0, height) in its station's frame (None when empty)."""
    cols, rows = round(width_m / RES), round(height_m / RES)
    if cols == 0:
        return None
    return Band(np.zeros((rows, cols)), np.ones((rows, cols), dtype=bool), np.zeros(2), RES)


class Bands:
    """Stands in for ``StationMaps``: each station's band, and which were asked for."""

    def __init__(self, bands: dict[int, Band | None]) -> None:
        self.bands = bands
        self.asked: list[int] = []

    def band(self, station: Station, estimate: object, ties: object) -> Band | None:
        self.asked.append(station.key)
        return self.bands[station.key]


def test_a_closure_keeps_the_anchor_and_the_older_stations_that_saw_its_view() -> None:
    """The new station at (10, 5) facing +y sees [6, 10] × [5, 9]. Older stations at (6, 5)
    facing +x hold [6, 6 + w) × [5, 9): 16 w of its 64 cells. One as wide but turned round
    holds [2, 6) and none of them; the anchor holds none and is kept all the same."""
    new = Station("a", 20, 800.0, ())
    widths = [1.0, 3.0, 0.0, 4.0, 2.0, 0.5, 3.5, 1.5]
    older = [Station("b", n, 40.0 * n, ()) for n in range(len(widths) + 2)]
    anchor, turned = older[-2], older[-1]
    estimate = {new.key: np.array([10.0, 5.0, math.pi / 2]), anchor.key: np.array([30.0, 0, 0]),
                turned.key: np.array([6.0, 5.0, math.pi])}  # fmt: skip
    bands: dict[int, Band | None] = {new.key: rectangle(4.0), anchor.key: rectangle(4.0),
                                     turned.key: rectangle(4.0)}  # fmt: skip
    for station, width in zip(older, widths, strict=False):
        estimate[station.key] = np.array([6.0, 5.0, 0.0])
        bands[station.key] = rectangle(width)
    maps = Bands(bands)
    chosen = seen_alike(new, anchor, older, estimate, {}, maps, most=4)
    # widths 4, 3.5 and 3 (stations 3, 6 and 1) and the anchor, in mission order
    assert chosen == [older[1], older[3], older[6], anchor]
    # The one turned round holds none of the view, one with no band ranks below it.
    few = [turned, older[0], older[1], older[2], anchor]
    assert seen_alike(new, anchor, few, estimate, {}, maps, most=3) == [
        older[0],
        older[1],
        anchor,
    ]
    # No more than the most: nothing to choose, no band made.
    maps.asked.clear()
    assert seen_alike(new, anchor, few, estimate, {}, maps, most=5) == few
    assert maps.asked == []
    # The new station saw no ceiling: nothing to rank by, all are kept.
    maps.bands[new.key] = None
    assert seen_alike(new, anchor, older, estimate, {}, maps, most=4) == older
    assert OLDER_MOST == 16


def test_loop_closures_match_against_the_chosen_older_stations(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The revisiting mission with odometry as tight as the mutual observations, so that the
    graph places every older station well, and closures from the third station on: with at
    most two older stations (the anchor and the one that saw most of the view) the closures
    still land on the truth."""
    stations, factors, truth = revisiting_mission()
    tight = np.diag([1e-4, 1e-4, 1e-5])
    factors = [dataclasses.replace(f, covariance=tight) if f.kind == "odometry" else f
               for f in factors]  # fmt: skip
    calls = []

    def two(
        station: Station, anchor: Station, older: list[Station], *rest: object
    ) -> list[Station]:
        chosen = seen_alike(station, anchor, older, *rest, most=2)
        calls.append((station.label, anchor, older, chosen))
        return chosen

    monkeypatch.setattr(stations_module, "seen_alike", two)
    monkeypatch.setattr(stations_module, "_MIN_AGE", 2)
    params = dataclasses.replace(TOLERANT, registration=RegistrationParams())
    events, records = loop_closures(stations, dict(truth), factors, params)
    assert [(r.station, r.against, r.used) for r in records][2:] == [
        ("a4", "b1", True),
        ("b5", "b1", True),
    ]
    limited = [(older, chosen, anchor) for _, anchor, older, chosen in calls if len(older) > 2]
    assert [label for label, *_ in calls] == ["a2", "b3", "a4", "b5"]
    assert len(limited) == 2
    for older, chosen, anchor in limited:
        assert len(chosen) == 2
        assert anchor in chosen
        assert set(chosen) <= set(older)
    assert len(events) >= 3
    for event in events:
        expected = se2.between(truth[pose_key(*event.reference)],
                               truth[pose_key(event.robot, event.index)])  # fmt: skip
        assert math.dist(event.pose[:2], expected[:2]) < 0.03
