"""Global localization of each new station while the mission goes on (paper §2.3).

When a station's local map is complete, its searches — against the station before it, the two
and three before it, the links of its scans that no mutual observation ties, and the older
stations near it (``estimation.search.stations``) — run in a worker process while the robots
build the next local map; the ``Localize`` events they find enter the loop's graph at the next
dwell. Between stations the worker keeps the sweeps and station maps of the neighbourhood it
searches and is sent only the sweeps it lacks. The worker is spawned (not forked: the loop's
process holds GTSAM and numba thread pools) and sees only explicit values: the stations with
the sweeps it lacks, the estimate and the factors at submission.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import time
import uuid
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from estimation.app.workers import watch_parent
from estimation.errors import EstimationError
from estimation.posegraph.events import Localize
from estimation.posegraph.graph import FactorSpec
from estimation.search.stations import (
    SearchRecord,
    Station,
    StationMaps,
    StationParams,
    View,
    loop_closures,
    scan_links,
    searched_with,
    station_links,
)

__all__ = ["ConcurrentLocalizer", "Localized", "localize_station"]


@dataclass(frozen=True)
class Localized:
    """One station's searches: what became events, every record, and the work's wall time."""

    station: str
    events: list[Localize]
    records: list[SearchRecord]
    seconds: float


def localize_station(
    stations: list[Station],
    estimate: dict[int, np.ndarray],
    factors: list[FactorSpec],
    params: StationParams,
    key: int,
    maps: StationMaps | None = None,
) -> Localized:
    """The searches of the station ``key`` (the last of ``stations``) on one estimate.
    ``maps``: the station maps kept from earlier stations' searches (new ones if None)."""
    started = time.perf_counter()
    events: list[Localize] = []
    records: list[SearchRecord] = []
    maps = StationMaps(params) if maps is None else maps  # each map fused once for the searches
    for back in ((1,), (2, 3)):
        found, done = station_links(
            stations, estimate, factors, params, back=back, only={key}, maps=maps
        )
        events += found
        records += done
    found, done = scan_links(stations, estimate, factors, params, only={key}, maps=maps)
    events += found
    records += done
    found, done = loop_closures(stations, estimate, factors, params, only={key}, maps=maps)
    label = next((s.label for s in stations if s.key == key), str(key))
    return Localized(label, events + found, records + done, time.perf_counter() - started)


#: A sweep as the worker holds it: (dwell, robot).
_Token = tuple[int, str]


@dataclass(frozen=True)
class _Request:
    """One station's searches as sent to the worker: the stations with the tokens of the
    views their searches use (none for the stations they do not use), the views the worker
    does not hold yet, and every token it is to keep (the rest it forgets)."""

    session: str
    stations: list[tuple[str, int, float, tuple[_Token, ...]]]
    views: dict[_Token, View]
    keep: frozenset[_Token]
    estimate: dict[int, np.ndarray]
    factors: list[FactorSpec]
    params: StationParams
    key: int


@dataclass
class _Held:
    """What the worker keeps from one station's searches to the next: the sweeps near the
    stations it searches, and their station maps (fused again only when a view moved
    relative to its station, ``StationParams.reuse_tolerance_m``)."""

    session: str
    views: dict[_Token, View]
    maps: StationMaps


_HELD: _Held | None = None


def _localize_request(request: _Request) -> Localized:
    """In the worker (or inline): the request's searches, on the views and maps it holds."""
    global _HELD
    held = _HELD
    if held is None or held.session != request.session:
        held = _HELD = _Held(request.session, {}, StationMaps(request.params))
    held.views = {t: v for t, v in held.views.items() if t in request.keep}
    held.views.update(request.views)
    missing = [t for _, _, _, tokens in request.stations for t in tokens if t not in held.views]
    if missing:
        raise EstimationError(f"the localization worker lacks the sweeps {missing[:3]}")
    stations = [Station(robot, index, time_s, tuple(held.views[t] for t in tokens))
                for robot, index, time_s, tokens in request.stations]  # fmt: skip
    held.maps.retain({s.key for s in stations if s.views})
    return localize_station(stations, request.estimate, request.factors, request.params,
                            request.key, held.maps)  # fmt: skip


@dataclass(frozen=True)
class _Job:
    station: str
    future: Future[Localized]
    submitted_mission_s: float


class ConcurrentLocalizer:
    """At most one station's searches at a time, in a worker process (or inline)."""

    def __init__(self, params: StationParams, concurrent: bool = True) -> None:
        self._executor: ProcessPoolExecutor | None = None
        if concurrent:
            # One worker process beside the loop searches on one thread: the loop keeps a core.
            search = dataclasses.replace(params.station_search, workers=1)
            params = dataclasses.replace(params, station_search=search)
            self._executor = ProcessPoolExecutor(
                1, mp_context=multiprocessing.get_context("spawn"),
                initializer=watch_parent, initargs=(os.getpid(),),
            )  # fmt: skip
        self.params = params
        self._job: _Job | None = None
        self.done: list[tuple[Localized, float, float]] = []  # result, submitted, collected
        self._session = uuid.uuid4().hex  # the worker's held sweeps and maps are this one's
        self._held: frozenset[_Token] = frozenset()  # what the worker holds after the last job

    @property
    def busy(self) -> bool:
        return self._job is not None

    @property
    def ready(self) -> bool:
        """A job was submitted and has finished (collecting it will not wait)."""
        return self._job is not None and self._job.future.done()

    def submit(self, stations: list[Station], estimate: dict[int, np.ndarray],
               factors: list[FactorSpec], key: int, mission_s: float) -> None:  # fmt: skip
        """Start the searches of station ``key``; the previous job must have been collected."""
        if self._job is not None:
            raise EstimationError(
                f"station {self._job.station}'s searches are still to be collected"
            )
        label = next((s.label for s in stations if s.key == key), None)
        if label is None:
            raise EstimationError(f"station {key} is not among the stations to search")
        request = self._request(stations, estimate, factors, key)
        if self._executor is None:
            future: Future[Localized] = Future()
            future.set_result(_localize_request(request))
        else:
            future = self._executor.submit(_localize_request, request)
        self._job = _Job(label, future, mission_s)

    def _request(self, stations: list[Station], estimate: dict[int, np.ndarray],
                 factors: list[FactorSpec], key: int) -> _Request:  # fmt: skip
        """Only the sweeps the searches use, and of those only the ones the worker does not
        hold: a long mission would otherwise send every sweep of the mission at every station
        and have each of their maps fused again."""
        used = searched_with(stations, estimate, key)
        skeleton, views, serial = [], {}, 0
        for station in stations:
            tokens = []
            for view in station.views if station.key in used else ():
                if view.dwell < 0:  # not a mission's sweep: sent every time, never held
                    serial -= 1
                    token: _Token = (serial, view.robot)
                else:
                    token = (view.dwell, view.robot)
                tokens.append(token)
                if token not in self._held:
                    views[token] = view
            skeleton.append((station.robot, station.index, station.time_s, tuple(tokens)))
        keep = frozenset(t for _, _, _, tokens in skeleton for t in tokens)
        self._held = frozenset(t for t in keep if t[0] >= 0)
        return _Request(self._session, skeleton, views, keep, estimate, factors, self.params,
                        key)  # fmt: skip

    def collect(self, mission_s: float, wait: bool = False) -> Localized | None:
        """The finished job's result (waiting for it with ``wait``), or None if none is done."""
        job = self._job
        if job is None:
            return None
        if not wait and not job.future.done():
            return None
        result = job.future.result()
        self._job = None
        self.done.append((result, job.submitted_mission_s, mission_s))
        return result

    def close(self) -> None:
        global _HELD
        if _HELD is not None and _HELD.session == self._session:
            _HELD = None  # inline: what it held goes with it
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None
