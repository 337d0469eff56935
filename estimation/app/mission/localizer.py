"""Global localization of each new station while the mission goes on (paper §2.3).

When a station's local map is complete, its searches — against the station before it, the two
and three before it, and the older stations near it (``estimation.search.stations``) — run in a
worker process while the robots build the next local map; the ``Localize`` events they find
enter the loop's graph at the next dwell. The worker is spawned (not forked: the loop's
process holds GTSAM and numba thread pools) and sees only explicit values: the stations with
their sweeps, the estimate and the factors at submission.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from estimation.errors import EstimationError
from estimation.posegraph.events import Localize
from estimation.posegraph.graph import FactorSpec
from estimation.search.stations import (
    SearchRecord,
    Station,
    StationMaps,
    StationParams,
    loop_closures,
    station_links,
)

__all__ = ["ConcurrentLocalizer", "Localized", "localize_station", "watch_parent"]


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
) -> Localized:
    """The searches of the station ``key`` (the last of ``stations``) on one estimate."""
    started = time.perf_counter()
    events: list[Localize] = []
    records: list[SearchRecord] = []
    maps = StationMaps(params)  # each station map fused once for the three searches
    for back in ((1,), (2, 3)):
        found, done = station_links(
            stations, estimate, factors, params, back=back, only={key}, maps=maps
        )
        events += found
        records += done
    found, done = loop_closures(stations, estimate, factors, params, only={key}, maps=maps)
    label = next((s.label for s in stations if s.key == key), str(key))
    return Localized(label, events + found, records + done, time.perf_counter() - started)


@dataclass(frozen=True)
class _Job:
    station: str
    future: Future[Localized]
    submitted_mission_s: float


def watch_parent(parent_pid: int, poll_s: float = 0.5) -> None:
    """In the worker: exit when the loop's process is gone (killed with SIGKILL, a worker
    would otherwise wait for work forever: it holds both ends of the pool's pipes)."""

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(poll_s)
        os._exit(0)

    threading.Thread(target=watch, name="watch-parent", daemon=True).start()


class ConcurrentLocalizer:
    """At most one station's searches at a time, in a worker process (or inline)."""

    def __init__(self, params: StationParams, concurrent: bool = True) -> None:
        self.params = params
        self._executor: ProcessPoolExecutor | None = None
        if concurrent:
            self._executor = ProcessPoolExecutor(
                1, mp_context=multiprocessing.get_context("spawn"),
                initializer=watch_parent, initargs=(os.getpid(),),
            )  # fmt: skip
        self._job: _Job | None = None
        self.done: list[tuple[Localized, float, float]] = []  # result, submitted, collected

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
        args = (stations, estimate, factors, self.params, key)
        if self._executor is None:
            future: Future[Localized] = Future()
            future.set_result(localize_station(*args))
        else:
            future = self._executor.submit(localize_station, *args)
        self._job = _Job(label, future, mission_s)

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
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None
