"""Tying the mission's tail before it ends (docs/mission-loop.md, "A floating tail is tied").

A reference's turn that no pivot chain tied rests on odometry until a search ties its station:
its link to the station before, or a loop closure. When neither was used, that station and
every station after it, chained to it by mutual observations and links, are rotated with the
turn's error (generated building 13: a half-turn 3.7° off, the last five stations rotated with
it; building 10: the last turn 1.5° off). In the middle of a mission a later loop closure ties
them; at its end nothing does. So once nothing is left to explore, the pair flies up to
``CLOSING_STATIONS`` more stations back toward where the station before the floating one
stood, a place the estimate ties, until a search of a station after it is used against a
station before it.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any, Protocol

import numpy as np

from estimation.app.mission.view import MapView
from estimation.posegraph.keys import key_label
from mapping.traversability import Room

__all__ = ["CLOSING_STATIONS", "closing_target", "floating_tail", "target_near"]

#: Stations flown at most, once nothing is left to explore, to tie a floating tail.
CLOSING_STATIONS = 8
#: The target of a closing station: the drivable floor within this distance of the place.
_TARGET_M = 1.0
#: The searches that tie a station to an older one.
_TYING = ("link", "loop")


class ClosingLoop(Protocol):
    """What closing needs of the loop (:class:`~estimation.app.mission.loop.MissionLoop`)."""

    estimate: dict[int, np.ndarray]
    trace: list[dict[str, Any]]
    localizations: list[dict[str, Any]]
    untied: dict[str, str]
    closing: list[str]


def closing_target(loop: ClosingLoop, view: MapView) -> Room | None:
    """The target of the next closing station, once nothing is left to explore: the drivable
    floor around where the station before the floating tail stood; None when no tail floats,
    ``CLOSING_STATIONS`` were flown, or the place is not drivable. The first station of the
    tail is noted in ``loop.closing``. The searches of the last station must be collected."""
    if len(loop.closing) >= CLOSING_STATIONS:
        return None
    order = [str(t["reference"]) for t in loop.trace if t["scans"]]
    records = [r for item in loop.localizations for r in item["records"]]
    first = floating_tail(order, loop.untied, records)
    if first is None or order.index(first) == 0:
        return None
    before = order[order.index(first) - 1]
    key = next((k for k in loop.estimate if key_label(k) == before), None)
    if key is None:
        return None
    target = target_near(view, loop.estimate[key][:2])
    if target is not None:
        loop.closing.append(first)
    return target


def floating_tail(order: Sequence[str], untied: Iterable[str],
                  records: Iterable[dict[str, Any]]) -> str | None:  # fmt: skip
    """The first station of the floating tail (``order``: the stations' labels as flown), or
    None when none floats. A station floats when its turn was untied (``untied``) and none of
    its searches was used (``records``: the concurrent localizations' search records, with
    ``station``, ``against``, ``kind`` and ``used``); the stations after it float with it
    until one of them has a search used against a station before it."""
    place = {label: n for n, label in enumerate(order)}
    tied_to: dict[str, list[int]] = {}
    for r in records:
        if r.get("used") and r.get("kind") in _TYING and r.get("against") in place:
            tied_to.setdefault(str(r["station"]), []).append(place[r["against"]])
    loose = set(untied)
    floating: int | None = None
    for n, label in enumerate(order):
        against = tied_to.get(label, [])
        if floating is not None and any(k < floating for k in against):
            floating = None
        if floating is None and label in loose and not against:
            floating = n
    return None if floating is None else order[floating]


def target_near(view: MapView, xy: np.ndarray) -> Room | None:
    """A target for the pair at ``xy``: the drivable floor within ``_TARGET_M`` of it, as a
    room nobody stood in is a target; None when none is drivable."""
    space = view.space
    rows, cols = np.nonzero(space.free)
    centres = space.lower_xy + (np.column_stack([cols, rows]) + 0.5) * space.resolution_m
    near = np.hypot(*(centres - np.asarray(xy, dtype=float)[:2]).T) <= _TARGET_M
    if not near.any():
        return None
    cells = np.column_stack([rows[near], cols[near]])
    res = space.resolution_m
    return Room(cells, np.asarray(xy, dtype=float)[:2].copy(), len(cells), 0.0,
                float(len(cells) * res * res))  # fmt: skip
