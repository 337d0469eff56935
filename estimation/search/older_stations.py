"""The older stations a loop closure matches against (docs/design.md §7).

A loop closure matches a new station against the map of older stations near it, fused in the
frame of the nearest of them (the anchor). Three rules choose them, in this order:

* :func:`placed_against` keeps the older stations whose pose relative to the anchor the graph
  knows well: one known no better than the new station lies in the anchor's frame as far off
  as the new station, and the closure would measure the error as the truth;
* :func:`apart_from_drift` leaves out those tied to the *new* station much more tightly than
  the anchor is — the stations just before it on the way, which share its drift: matched
  against, they confirm the drift;
* :func:`seen_alike` keeps at most :data:`OLDER_MOST`, the anchor and those whose ceiling bands
  hold most of what the new station saw, so that a closure's work stays flat however often the
  mission came by.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from estimation.search.station_maps import Station, StationMaps
from sensors.geometry import se2

__all__ = ["OLDER_MOST", "apart_from_drift", "placed_against", "pose_sigmas", "seen_alike"]

#: A loop closure matches against at most this many older stations: the anchor and those whose
#: ceiling bands cover most of the new station's (``seen_alike``; design §7).
OLDER_MOST = 16


#: An older station goes into the map a loop closure matches against only when the graph knows
#: its pose relative to the anchor to within half the new station's uncertainty relative to the
#: anchor, or to within these (m, rad; standard deviations) when that is more.
_FUSE_M, _FUSE_RAD = 0.1, math.radians(0.5)


def pose_sigmas(covariance: np.ndarray) -> tuple[float, float]:
    """The largest position and the heading standard deviation of a pose covariance."""
    position = float(np.linalg.eigvalsh(covariance[:2, :2])[-1])
    return math.sqrt(max(0.0, position)), math.sqrt(max(0.0, float(covariance[2, 2])))


def placed_against(older: list[Station], covariances: Sequence[np.ndarray],
                   uncertainty: np.ndarray) -> list[Station]:  # fmt: skip
    """The older stations (in order) a loop closure matches against: those whose pose relative
    to its anchor (``covariances``, one per station; the anchor's own is zero) is known to
    within half the new station's (``uncertainty``), or to ``_FUSE_M`` / ``_FUSE_RAD``. One
    that shares the new station's drift lies in the anchor's frame as far off as it, and the
    closure would measure the drift as the truth (generated building 106: ten closures 3.5°
    off; design §7)."""
    sigma_m, sigma_rad = pose_sigmas(uncertainty)
    limit_m, limit_rad = max(_FUSE_M, 0.5 * sigma_m), max(_FUSE_RAD, 0.5 * sigma_rad)
    kept = []
    for station, covariance in zip(older, covariances, strict=True):
        m, r = pose_sigmas(covariance)
        if m <= limit_m and r <= limit_rad:
            kept.append(station)
    return kept


#: An older station is left out of a closure's map when the graph knows its pose relative to
#: the new station to within this fraction of the anchor's, in position and in heading.
_TIED = 0.5


def apart_from_drift(older: list[Station], anchor: Station,
                     covariances: Sequence[np.ndarray]) -> list[Station]:  # fmt: skip
    """The older stations (in order) that do not share the new station's drift: the anchor,
    and those whose pose relative to the new station (``covariances``, one per older station,
    the anchor's among them) the graph knows less than twice as well as the anchor's, in
    position or in heading. The stations just before the new one on the way are tied to it
    that tightly; the estimate puts them where the drift puts it, and a closure on their map
    confirms the drift (generated building 10: a closure 4.7 cm / 0.21° off; design §7)."""
    keys = [s.key for s in older]
    if anchor.key not in keys:
        raise ValueError("apart_from_drift: the anchor must be one of the older stations")
    anchor_m, anchor_rad = pose_sigmas(covariances[keys.index(anchor.key)])
    kept = []
    for station, covariance in zip(older, covariances, strict=True):
        m, r = pose_sigmas(covariance)
        if station.key == anchor.key or m >= _TIED * anchor_m or r >= _TIED * anchor_rad:
            kept.append(station)
    return kept


def seen_alike(
    station: Station,
    anchor: Station,
    older: list[Station],
    estimate: dict[int, np.ndarray],
    ties: dict[int, set[int]],
    maps: StationMaps,
    most: int = OLDER_MOST,
) -> list[Station]:
    """At most ``most`` of the ``older`` stations (in order) for ``station``'s loop closure: the
    anchor, and those whose ceiling bands, placed by the estimate, hold most of the known cells
    of the station's band. What a station sees lies down corridors and across rooms, not at the
    nearest stations (generated building 106; design §7), so the map keeps the stations that saw
    the same place, and its work stays flat however often the mission came by."""
    if len(older) <= most:
        return older
    local = maps.band(station, estimate, ties)
    if local is None:
        return older
    seen = se2.transform_points(estimate[station.key], local.known_centers())  # the map's frame

    def held(other: Station) -> int:
        band = maps.band(other, estimate, ties)
        if band is None:
            return -1
        return int(band.covers(se2.transform_points(se2.inverse(estimate[other.key]), seen)).sum())

    ranked = sorted(older, key=lambda s: (s.key != anchor.key, -held(s)))
    chosen = {s.key for s in ranked[:most]}
    return [s for s in older if s.key in chosen]
