"""Global localization inside a mission: station maps, ceiling bands, searches (docs/design.md §5,
§7).

The searches take explicit values: the mission's reference :class:`Station` values (each with
the :class:`View` values its map is fused from), the current estimate, the graph's factors and
one :class:`StationParams`. Every reference station gets a local map — the sweeps of its dwells
taken at poses tied to it by a mutual observation (its own, and the mapper's around it), fused
in the station's frame — and its ceiling band. The searches run in stages (``SEARCH_STAGES``),
the graph optimized again after each:

* **links** — each station against the station one place before it, then two and three places
  before it. Mutual observations tie a station to the mapper poses around it, but the step from
  one station to the next passes through a turn in place measured only by odometry (a robot
  that has just turned cannot see the other's beacon behind it), so the station maps are
  matched in a small window around the predicted relative pose. In a corridor such a match
  fixes the heading and the cross-track position but hardly the along-track one, so its
  factor's covariance is fitted to the probability near the peak (``_LINK_RADIUS``).
* **loop closures** — each station against the map of the stations at least ``_MIN_AGE``
  older near it, in the frame of the nearest of them, over ±3σ of the predicted relative pose
  (σ from the graph's joint marginals); a dominant peak that passes the χ² gate against the
  prediction becomes a factor. A peak that stands out only once the prediction weighs the
  poses is taken when its runner-up registers to the same pose (one mode drawn out along a
  corridor, not two places the station could be).

Each accepted search is a ``Localize`` event: a between-factor from the anchor station. After
the ``changes`` step, each robot's last sweep is localized against the final map (ceiling band,
and a floor band for comparison): those results are reported.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from estimation.chi2 import chi2_quantile
from estimation.errors import EstimationError
from estimation.posegraph.events import Localize
from estimation.posegraph.graph import FactorSpec
from estimation.posegraph.marginals import relative_covariances
from estimation.search.correlate import correlate_all
from estimation.search.exhaustive import (
    SearchParams,
    SearchResult,
    overlap_fraction,
    result_from_scores,
)
from estimation.search.lattice import pose_lattice
from estimation.search.older_stations import (
    OLDER_MOST,
    apart_from_drift,
    placed_against,
    pose_sigmas,
    seen_alike,
)
from estimation.search.records import SearchPicture, SearchRecord, pose_of
from estimation.search.registration import Cloud, Registration, register
from estimation.search.station_maps import (
    Dwell,
    Station,
    StationMaps,
    StationParams,
    View,
    mutual_ties,
    side_by_side,
)
from mapping.band import Band
from sensors.geometry import se2

__all__ = [
    "SEARCH_STAGES",
    "Dwell",
    "Station",
    "StationMaps",
    "StationParams",
    "View",
    "loop_closures",
    "scan_links",
    "searched_with",
    "station_links",
]

#: Older stations farther than this from a station are not searched against it.
_NEIGHBOURHOOD_M = 12.0
#: A loop closure matches against stations at least this many stations older (a revisit):
#: recent neighbours are already tied by mutual observations, and corridors repeat along their
#: axis, so matching them adds false peaks rather than information.
_MIN_AGE = 4
#: A loop-closure search covers ±``_LOOP_SIGMAS`` standard deviations of the predicted
#: relative pose (from the graph's joint marginals), within these bounds (window side, m; yaw
#: reach, rad); its dominant peak becomes a factor when it passes the χ² gate against the
#: prediction (99.9 %, three degrees of freedom).
_LOOP_SIGMAS = 3.0
_LOOP_WINDOW_M = (4.0, 16.0)
_LOOP_YAW_RAD = (math.radians(5.0), math.radians(30.0))
_LOOP_GATE = chi2_quantile(0.999, 3)
#: A link searches this square window (side, m) around the predicted relative pose, accepts a
#: best pose this close to the prediction, and fits its covariance to this neighbourhood.
_LINK_WINDOW_M = 1.0
_LINK_CONSISTENT_M = 0.35
_LINK_CONSISTENT_RAD = math.radians(12.0)
_LINK_RADIUS = (0.5, math.radians(5.0))
_LINK_YAW_RAD = math.radians(20.0)
#: A link or loop closure becomes a factor only if at least this share of the station map's
#: known cells overlaps known cells of the map it was matched against: a match over a sliver
#: (two stations that share a corner of ceiling) has a broad PDF and an unreliable peak. Links
#: to the previous station overlap by 28–68 % in the simulated missions; the links two places
#: back that overlapped by 4–5 % were 5–14 cm and 0.7–1.3° off.
_MIN_OVERLAP = 0.1
#: Below this overlap a link's search must also be dominant: of 2,632 links used in 8 generated
#: buildings 9 were wrong, 2 of them among the 18 neither dominant nor overlapping by 20 %.
_THIN_OVERLAP = 0.2
#: A loop closure's best pose and its runner-up that register this close together (m, rad) lie
#: in one basin.
_ONE_BASIN_M = 0.01
_ONE_BASIN_RAD = math.radians(0.1)


def _search_near(local: Band, global_: Band, params: SearchParams, predicted: np.ndarray,
                 side_m: float, yaw_reach_rad: float) -> tuple[SearchResult, bool]:  # fmt: skip
    """Every pose of the square window of ``side_m`` centred on the predicted position (moved
    inside the map if it lies outside) within ``yaw_reach_rad`` of the predicted yaw, on the
    search's lattices: the PDF of that window (a corridor's 180° twin lies outside it), and
    whether the best pose lies on the window's border."""
    x0, x1, y0, y1 = global_.extent()
    cx, cy = float(np.clip(predicted[0], x0, x1)), float(np.clip(predicted[1], y0, y1))
    half = side_m / 2
    x_m, y_m, _ = pose_lattice(local, global_, (cx - half, cx + half, cy - half, cy + half))
    step = params.angular_resolution_rad
    reach = math.ceil(yaw_reach_rad / step)
    yaw_rad = (round(predicted[2] / step) + np.arange(-reach, reach + 1)) * step
    started = time.perf_counter()
    scores = correlate_all(local, global_, x_m, y_m, yaw_rad, params.metric)
    result = result_from_scores(scores, x_m, y_m, yaw_rad, params, started, (local, global_))
    _, by, bx = result.best_index
    return result, bx in (0, len(x_m) - 1) or by in (0, len(y_m) - 1)


@dataclass(frozen=True)
class _Refined:
    """A search's answer as a factor would take it: the pose, the covariance to use (None: fit
    it to the PDF), and the registration (None when none ran) with whether it was accepted."""

    pose: np.ndarray
    covariance: np.ndarray | None
    registration: Registration | None
    sound: bool

    def record_fields(self, result: SearchResult) -> dict[str, Any]:
        if self.registration is None:
            return {"pose": pose_of(result)}
        x, y, yaw = (float(v) for v in self.pose)
        return {"pose": (x, y, yaw), "searched": pose_of(result),
                "inliers": self.registration.inliers}  # fmt: skip

    def event(self, station: Station, anchor: Station, peak: tuple[float, float] | None,
              result: SearchResult) -> Localize:  # fmt: skip
        x, y, yaw = (float(v) for v in self.pose)
        covariance = (
            None if self.covariance is None else tuple(tuple(float(v) for v in row)
                                                       for row in self.covariance)
        )  # fmt: skip
        anchored = (anchor.robot, anchor.index)
        return Localize(
            station.robot, station.index, result.pdf, anchored, peak, (x, y, yaw), covariance
        )


def _refined(
    result: SearchResult,
    source: Cloud | None,
    target: Cloud | None,
    params: StationParams,
    seed: np.ndarray | None = None,
) -> _Refined:
    """The search's pose (or ``seed``) refined on the stations' points
    (``params.registration``): the registration's pose and covariance when it converged with
    enough corresponding points, else unsound. Without registration, the search's pose as it
    is; without clouds, unsound."""
    settings = params.registration
    searched = np.asarray(result.pose, dtype=float)
    if settings is None:
        return _Refined(searched, None, None, True)
    if source is None or target is None:
        return _Refined(searched, None, None, False)
    seed = searched if seed is None else np.asarray(seed, dtype=float)
    target = target.within(seed[:2], source.reach_m() + settings.max_distance_m)
    found = register(source, target, seed, settings)
    if found is None:
        return _Refined(seed, None, None, False)
    return _Refined(found.pose, found.covariance, found, found.accepted(settings))


def _near(pose: np.ndarray, other: np.ndarray, within_m: float = _LINK_CONSISTENT_M,
          within_rad: float = _LINK_CONSISTENT_RAD) -> bool:  # fmt: skip
    """Two poses agree to ``within_m`` and ``within_rad`` (by default: a link's pose agrees with
    the prediction across the turn between the stations)."""
    return (
        math.dist(pose[:2], other[:2]) < within_m
        and abs(math.remainder(float(pose[2] - other[2]), 2 * math.pi)) < within_rad
    )


def _searchable(
    station: Station,
    previous: Station,
    estimate: dict[int, np.ndarray],
    maps: StationMaps,
    ties: dict[int, set[int]],
) -> tuple[Band, Band, np.ndarray] | None:
    """The two stations' bands and the predicted relative pose when a link can be searched:
    both have a band, and the link's window around the prediction can reach the older one."""
    local = maps.band(station, estimate, ties)
    global_ = maps.band(previous, estimate, ties)
    if local is None or global_ is None:
        return None
    predicted = se2.between(estimate[previous.key], estimate[station.key])
    x0, x1, y0, y1 = global_.extent()
    outside = math.hypot(max(x0 - predicted[0], 0.0, predicted[0] - x1),
                         max(y0 - predicted[1], 0.0, predicted[1] - y1))  # fmt: skip
    if outside > _LINK_WINDOW_M / 2 + _LINK_CONSISTENT_M:
        return None  # no pose of the (moved) window could agree with the prediction
    return local, global_, predicted


_Answer = tuple[Localize | None, SearchRecord] | None


def _link(
    station: Station,
    previous: Station,
    searchable: tuple[Band, Band, np.ndarray],
    estimate: dict[int, np.ndarray],
    maps: StationMaps,
    ties: dict[int, set[int]],
    params: StationParams,
) -> _Answer:
    """``station``'s map searched against ``previous``'s around the predicted relative pose and
    registered on their points (``searchable``: :func:`_searchable`'s answer): the
    ``Localize`` event when the answer is sound and consistent with the prediction (else None),
    and the record; None when the search cannot run."""
    search = params.station_search
    local, global_, predicted = searchable
    started = time.perf_counter()
    try:
        result, _ = _search_near(local, global_, search, predicted, _LINK_WINDOW_M, _LINK_YAW_RAD)
    except EstimationError:
        return None
    overlap = overlap_fraction(local, global_, result.pose)
    consistent = _near(result.pose, predicted) and overlap >= _MIN_OVERLAP
    refined = None
    if consistent or params.registration is not None:
        # A search whose peak strays from the prediction (a band that matches poorly, the
        # peak on the window's edge) leaves the registration to start from the prediction.
        source = maps.cloud(station, estimate, ties)
        refined = _refined(result, source, maps.cloud(previous, estimate, ties), params,
                           None if consistent else predicted)  # fmt: skip
        overlap = overlap_fraction(local, global_, refined.pose)
    used = refined is not None and refined.sound and _near(refined.pose, predicted)
    dominant = result.is_dominant(search.dominance_ratio)
    used = used and overlap >= _MIN_OVERLAP and (dominant or overlap >= _THIN_OVERLAP)
    event = refined.event(station, previous, _LINK_RADIUS, result) if used and refined else None
    record = SearchRecord(
        station=station.label, against=previous.label, band="ceiling", kind="link",
        peak_ratio=float(result.peak_ratio),
        dominant=dominant, used=used,
        seconds=time.perf_counter() - started, time_s=station.time_s, overlap=overlap,
        **(refined or _Refined(result.pose, None, None, False)).record_fields(result),
    )  # fmt: skip
    return event, record


def station_links(
    stations: list[Station],
    estimate: dict[int, np.ndarray],
    factors: list[FactorSpec],
    params: StationParams,
    back: tuple[int, ...] = (1,),
    only: set[int] | None = None,
    maps: StationMaps | None = None,
) -> tuple[list[Localize], list[SearchRecord]]:
    """Search each station's map against the maps of the stations ``back`` places before it,
    around the predicted relative pose; a best pose consistent with the prediction becomes a
    ``Localize`` event. With ``only`` (station keys), just those stations are searched (the
    mission loop localizes each new station as it completes). ``maps``: the station maps kept
    from earlier stages (a new :class:`StationMaps` if None)."""
    stations = [s for s in stations if s.key in estimate]
    maps = StationMaps(params) if maps is None else maps
    ties = mutual_ties(factors)
    pairs = [
        (stations[n - k], stations[n])
        for n in range(len(stations))
        for k in back
        if n >= k and (only is None or stations[n].key in only)
    ]
    return _links(pairs, estimate, maps, ties, params)


def _links(
    pairs: Iterable[tuple[Station, Station]],
    estimate: dict[int, np.ndarray],
    maps: StationMaps,
    ties: dict[int, set[int]],
    params: StationParams,
) -> tuple[list[Localize], list[SearchRecord]]:
    """:func:`_link` of each (earlier station, station) pair: the events and the records. The
    maps are made first; then the pairs are searched and registered side by side (they only
    read the maps), their answers taken in the pairs' order."""
    pairs = list(pairs)
    workers = params.station_search.thread_count()
    maps.prepare([one for p, s in pairs for one in (s, p)], estimate, ties, workers)
    ready = [
        (p, s, searchable)
        for p, s in pairs
        if (searchable := _searchable(s, p, estimate, maps, ties)) is not None
    ]
    maps.prepare([one for p, s, _ in ready for one in (s, p)], estimate, ties, workers,
                 clouds=True)  # fmt: skip

    def link(item: tuple[Station, Station, tuple[Band, Band, np.ndarray]]) -> _Answer:
        previous, station, searchable = item
        return _link(station, previous, searchable, estimate, maps, ties, params)

    answers = side_by_side(link, ready, workers)
    found = []
    for (_, station, _), answer in zip(ready, answers, strict=True):
        if answer is not None:
            maps.searched(station, answer[1].seconds)
            found.append(answer)
    return [e for e, _ in found if e is not None], [r for _, r in found]


def scan_links(
    stations: list[Station],
    estimate: dict[int, np.ndarray],
    factors: list[FactorSpec],
    params: StationParams,
    only: set[int] | None = None,
    maps: StationMaps | None = None,
) -> tuple[list[Localize], list[SearchRecord]]:
    """Link each scan of a station's dwells that no mutual observation ties (beacon missed,
    observation gated out) to the station as :func:`station_links` links stations, and to its
    own robot's last station before it, so that it rests on more than the mapper's odometry
    (design §7): a scan taken out of the station's view often still overlaps the mapper's own
    last station. Scans at a pose that is itself a station are left to the station links;
    ``only``, ``maps`` as there."""
    stations = [s for s in stations if s.key in estimate]
    maps = StationMaps(params) if maps is None else maps
    ties = mutual_ties(factors)
    keys = {s.key for s in stations}
    pairs = []
    for station in stations:
        if only is not None and station.key not in only:
            continue
        for view in station.views:
            if view.key in ties or view.key in keys or view.key not in estimate:
                continue
            scan = Station(view.robot, view.index, station.time_s, (view,))
            pairs.append((station, scan))
            own = [s for s in stations if s.robot == view.robot and s.index < view.index]
            if own:
                pairs.append((max(own, key=lambda s: s.index), scan))
    return _links(dict.fromkeys(pairs), estimate, maps, ties, params)


@dataclass(frozen=True)
class _Searched:
    """A loop closure's search: its result, whether its peak is dominant alone and given the
    prediction (``dominant``) or given the prediction only (``given``), the overlap at the
    peak, and the seconds taken."""

    result: SearchResult
    dominant: bool
    given: bool
    overlap: float
    seconds: float


@dataclass(frozen=True)
class _Closure:
    """A loop closure to search: the station, its anchor and the older stations near it, their
    bands, the predicted relative pose and its covariance, the window's side and yaw reach."""

    station: Station
    anchor: Station
    older: list[Station]
    local: Band
    global_: Band
    predicted: np.ndarray
    uncertainty: np.ndarray
    side_m: float
    reach_rad: float


def loop_closures(
    stations: list[Station],
    estimate: dict[int, np.ndarray],
    factors: list[FactorSpec],
    params: StationParams,
    only: set[int] | None = None,
    maps: StationMaps | None = None,
) -> tuple[list[Localize], list[SearchRecord]]:
    """Search each station against the older stations near it, in windows around the predicted
    pose that grow until the peak is dominant; a dominant peak consistent with the prediction
    becomes a ``Localize`` event. With ``only``, just those stations are searched; ``maps`` as
    in :func:`station_links`. The stations' own maps are made side by side, then the older
    stations' maps (each anchor's appended to in mission order, the anchors side by side), then
    the searches run side by side, then the registrations."""
    search = params.station_search
    workers = search.thread_count()
    stations = [s for s in stations if s.key in estimate]
    maps = StationMaps(params) if maps is None else maps
    ties = mutual_ties(factors)
    relative = relative_covariances(factors, estimate)
    positions = np.array([estimate[s.key][:2] for s in stations], dtype=np.float64).reshape(-1, 2)
    near_by: list[tuple[Station, Station, list[Station], np.ndarray]] = []
    for n, station in enumerate(stations):
        if only is not None and station.key not in only:
            continue
        near, distance = _older_near(positions, n)
        if not len(near):
            continue
        anchor = stations[_anchor(near, distance, stations, ties)]
        older = [stations[k] for k in near]
        # The new station's and the older ones' poses against the anchor: one joint marginal.
        uncertainty, *placed = relative.around(anchor.key, [station.key, *(s.key for s in older)])
        older = placed_against(older, placed, uncertainty)
        tied = relative.around(station.key, [s.key for s in older])
        older = apart_from_drift(older, anchor, tied)
        near_by.append((station, anchor, older, uncertainty))
    # The bands searched and those ranked by what they saw, made side by side.
    maps.prepare([s for station, _, older, _ in near_by
                  for s in (station, *(older if len(older) > OLDER_MOST else ()))],
                 estimate, ties, workers)  # fmt: skip
    chosen = [
        (station, anchor, seen_alike(station, anchor, older, estimate, ties, maps), uncertainty)
        for station, anchor, older, uncertainty in near_by
        if maps.band(station, estimate, ties) is not None
    ]
    # The older stations' maps: each anchor's appended to in mission order, anchors side by side.
    older_bands = maps.older_bands([c[:3] for c in chosen], estimate, ties, workers)
    closures = []
    for (station, anchor, older, uncertainty), global_ in zip(chosen, older_bands, strict=True):
        sigma_m, sigma_rad = pose_sigmas(uncertainty)
        local = maps.band(station, estimate, ties)
        if local is None or global_ is None:
            continue
        closures.append(_Closure(
            station, anchor, older, local, global_,
            se2.between(estimate[anchor.key], estimate[station.key]), uncertainty,
            float(np.clip(2 * _LOOP_SIGMAS * sigma_m, *_LOOP_WINDOW_M)),
            float(np.clip(_LOOP_SIGMAS * sigma_rad, *_LOOP_YAW_RAD)),
        ))  # fmt: skip
    answers = side_by_side(lambda c: _closure_search(c, search), closures, workers)
    found = [(c, f) for c, f in zip(closures, answers, strict=True) if f is not None]
    wanted = [(c, f) for c, f in found if f.given and f.overlap >= _MIN_OVERLAP]
    maps.prepare([s for c, _ in wanted for s in (c.station, *c.older)], estimate, ties, workers,
                 clouds=True)  # fmt: skip

    def refine(item: tuple[_Closure, _Searched]) -> tuple[_Refined, Localize | None, float]:
        closure, searched = item
        result = searched.result
        started = time.perf_counter()
        cloud = maps.cloud(closure.station, estimate, ties)
        anchor = maps.cloud(closure.anchor, estimate, ties)
        # The anchor's own map does not depend on the estimate: a sound registration there is
        # the closure (generated building 4: on 51–54 older stations 12–21 cm and 1.4–1.7° off
        # with their shared drift, on the anchor alone within 0.4 cm / 0.05°). A dominant peak
        # tries it first from the search's pose; the older stations' cloud (ten times the
        # points) only when that fails, or to check a peak dominant given the prediction.
        alone_first = searched.dominant and len(closure.older) > 1
        refined = _refined(result, cloud, anchor, params) if alone_first else None
        if refined is None or not refined.sound:
            older = maps.older_cloud(closure.anchor, closure.older, estimate, ties)
            refined = _refined(result, cloud, older, params)
            if not searched.dominant and not _one_basin(result, refined, cloud, older, params):
                refused = _Refined(refined.pose, None, refined.registration, False)
                return refused, None, time.perf_counter() - started
            again = not (alone_first and np.array_equal(refined.pose, result.pose))  # tried
            if len(closure.older) > 1 and again:
                alone = _refined(result, cloud, anchor, params, seed=refined.pose)
                refined = alone if alone.sound else refined
        measured = result.covariance if refined.covariance is None else refined.covariance
        offset = se2.log(se2.between(closure.predicted, refined.pose))
        covariance = closure.uncertainty + measured
        chi2_value = float(offset @ np.linalg.solve(covariance, offset))
        use = refined.sound and chi2_value < _LOOP_GATE
        # Its PDF (a copy of up to 1.6 M poses) is made here, on the searches' threads.
        event = refined.event(closure.station, closure.anchor, None, result) if use else None
        return refined, event, time.perf_counter() - started

    refinements = dict(zip((id(c) for c, _ in wanted), side_by_side(refine, wanted, workers),
                           strict=True))  # fmt: skip
    events: list[Localize] = []
    records: list[SearchRecord] = []
    for closure, searched in found:
        result, seconds = searched.result, searched.seconds
        refined = _Refined(np.asarray(result.pose, dtype=float), None, None, False)
        event = None
        if id(closure) in refinements:
            refined, event, more = refinements[id(closure)]
            seconds += more
        if event is not None:
            events.append(event)
        maps.searched(closure.station, seconds)
        records.append(
            SearchRecord(
                station=closure.station.label, against=closure.anchor.label, band="ceiling",
                kind="loop", peak_ratio=float(result.peak_ratio), dominant=searched.dominant,
                used=event is not None, seconds=seconds, time_s=closure.station.time_s,
                overlap=searched.overlap,
                picture=SearchPicture.of(result, closure.local, closure.global_),
                **refined.record_fields(result),
            )
        )  # fmt: skip
    return events, records


def _closure_search(closure: _Closure, search: SearchParams) -> _Searched | None:
    """A loop closure's search (:class:`_Searched`); None when the search cannot run."""
    started = time.perf_counter()
    try:
        result, on_edge = _search_near(closure.local, closure.global_, search, closure.predicted,
                                       closure.side_m, closure.reach_rad)  # fmt: skip
    except EstimationError:
        return None
    # Dominant alone and beside the prediction: in a repeating room chance picks a repeat.
    given = not on_edge and result.dominant_given(closure.predicted, closure.uncertainty, search)
    dominant = given and result.is_dominant(search.dominance_ratio)
    overlap = overlap_fraction(closure.local, closure.global_, result.pose)
    return _Searched(result, dominant, given, overlap, time.perf_counter() - started)


def _one_basin(result: SearchResult, refined: _Refined, source: Cloud | None,
               target: Cloud | None, params: StationParams) -> bool:  # fmt: skip
    """Whether the search's runner-up (its best pose outside the peak) registers soundly where
    its best pose did (``refined``): a peak that stands out only given the prediction is then
    one mode drawn out along a ridge (the ceiling of a corridor: generated building 0's
    runner-up lay 0.5 m down the corridor and both registered 0.3 cm from the truth), not one
    of two places the station could be. Without registration, never."""
    if not refined.sound or refined.registration is None:
        return False
    search = params.station_search
    modes = result.modes(2, search.peak_radius_m, search.peak_radius_rad)
    if len(modes) < 2:
        return True  # no other pose holds any probability
    other = _refined(result, source, target, params, seed=modes[1])
    return other.sound and _near(other.pose, refined.pose, _ONE_BASIN_M, _ONE_BASIN_RAD)


def _anchor(
    near: np.ndarray, distance: np.ndarray, stations: list[Station], ties: dict[int, set[int]]
) -> int:
    """The loop closure's anchor among the older stations ``near``: the nearest whose own pose a
    mutual observation ties, else the nearest. The closure is measured in the anchor's frame,
    so an anchor whose heading rests on odometry alone (a pivot's untied turn, 1.5° off in a
    generated building) passes its error on to the factor, which then holds it there."""
    tied = near[[stations[k].key in ties for k in near]]
    pool = tied if len(tied) else near
    return int(pool[np.argmin(distance[pool])])


def _older_near(positions: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The indices of the stations old enough for station ``n``'s loop closure and within
    ``_NEIGHBOURHOOD_M`` of it (``positions``: every station's, in mission order), and the
    distances of all the old enough ones."""
    candidates = positions[: max(0, n - _MIN_AGE + 1)]
    distance = np.sqrt(((candidates - positions[n]) ** 2).sum(axis=1))
    return np.flatnonzero(distance < _NEIGHBOURHOOD_M), distance


def searched_with(stations: list[Station], estimate: dict[int, np.ndarray], key: int,
                  back: tuple[int, ...] = (1, 2, 3)) -> set[int]:  # fmt: skip
    """The keys of the stations whose maps the searches of station ``key`` use
    (:func:`station_links` ``back`` places before it, :func:`loop_closures`): itself, the
    stations before it, and the older ones near it."""
    stations = [s for s in stations if s.key in estimate]
    n = next((k for k, s in enumerate(stations) if s.key == key), None)
    if n is None:
        return set()
    positions = np.array([estimate[s.key][:2] for s in stations], dtype=np.float64).reshape(-1, 2)
    near, _ = _older_near(positions, n)
    used = {n, *(n - k for k in back if n >= k), *near.tolist()}
    return {stations[k].key for k in used}


#: The searches inside a mission, in order; the graph is optimized again after each stage that
#: added factors: the links fix the stations' headings, which the loop closures' predictions
#: (and windows) then rely on.
SEARCH_STAGES = (
    ("links to the previous station", station_links),
    ("links to earlier stations", functools.partial(station_links, back=(2, 3))),
    ("links of unobserved scans", scan_links),
    ("loop closures", loop_closures),
)
