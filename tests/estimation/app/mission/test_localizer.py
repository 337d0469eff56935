"""Station localization during the mission: inline or in a spawned worker, the same answer."""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import numpy as np
import pytest

from estimation.app.config import Config
from estimation.app.mission.localizer import ConcurrentLocalizer, Localized, localize_station
from estimation.app.rig import T_robot_scanner, station_params
from estimation.errors import EstimationError
from estimation.posegraph.events import Localize
from estimation.posegraph.graph import FactorSpec
from estimation.posegraph.keys import pose_key
from estimation.search.stations import Station, StationParams, View
from sensors.geometry import se2
from sensors.geometry.frames import pose2_matrix
from tests.mapping.conftest import room_scan

CONFIG = Config()
PARAMS: StationParams = station_params(CONFIG)
#: A 6 m × 4 m room whose 3.2 m ceiling lies above the ceiling band: the band holds its walls.
ROOM = (6.0, 4.0, 3.2)
K0, K1 = pose_key("a", 0), pose_key("a", 1)
TRUTH = {K0: np.array([2.0, 1.5, 0.0]), K1: np.array([3.5, 2.2, 0.4])}


def view_at(robot: str, index: int, pose: np.ndarray) -> View:
    """The sweep of a robot at ``pose`` (map frame) in the room, in its scanner frame."""
    T_map_scanner = pose2_matrix(*pose) @ T_robot_scanner(CONFIG)
    points_map = room_scan(T_map_scanner[:3, 3], ROOM, azimuth_steps=360, elevation_steps=90)
    T_scanner_map = np.linalg.inv(T_map_scanner)
    return View(robot, index, points_map @ T_scanner_map[:3, :3].T + T_scanner_map[:3, 3])


Case = tuple[list[Station], dict[int, np.ndarray], list[FactorSpec]]


@pytest.fixture(scope="module")
def two_stations() -> Case:
    """Two stations of robot a; the estimate of the second is 7 cm and 0.9° off."""
    stations = [
        Station("a", 0, 0.0, (view_at("a", 0, TRUTH[K0]),)),
        Station("a", 1, 40.0, (view_at("a", 1, TRUTH[K1]),)),
    ]
    estimate = {K0: TRUTH[K0].copy(), K1: TRUTH[K1] + [0.06, -0.04, 0.015]}
    odometry = se2.between(estimate[K0], estimate[K1])
    factors = [
        FactorSpec("prior", (K0,), estimate[K0], np.diag([1e-4, 1e-4, 1e-5]), 0),
        FactorSpec("odometry", (K0, K1), odometry, np.diag([0.01, 0.01, 0.001]), 1),
    ]
    return stations, estimate, factors


def blind_stations() -> Case:
    """Stations whose sweeps saw nothing: no station map, so no search."""
    stations = [Station("b", k, 10.0 * k, (View("b", k, np.zeros((0, 3))),)) for k in range(3)]
    estimate = {pose_key("b", k): np.array([1.0 * k, 0.0, 0.0]) for k in range(3)}
    factors = [FactorSpec("prior", (pose_key("b", 0),), estimate[pose_key("b", 0)],
                          np.diag([1e-4, 1e-4, 1e-5]), 0)]  # fmt: skip
    factors += [FactorSpec("odometry", (pose_key("b", k - 1), pose_key("b", k)),
                           np.array([1.0, 0.0, 0.0]), np.diag([0.01, 0.01, 0.001]), k)
                for k in (1, 2)]  # fmt: skip
    return stations, estimate, factors


def assert_same(got: Localized, expected: Localized) -> None:
    assert got.station == expected.station
    assert len(got.events) == len(expected.events)
    for a, b in zip(got.events, expected.events, strict=True):
        assert isinstance(a, Localize)
        assert (a.robot, a.index, a.reference, a.peak_radius, a.pose) == (
            b.robot, b.index, b.reference, b.peak_radius, b.pose)  # fmt: skip
        for name in ("x_m", "y_m", "yaw_rad", "prob"):
            np.testing.assert_array_equal(getattr(a.pdf, name), getattr(b.pdf, name))
    records = [
        [{k: v for k, v in dataclasses.asdict(r).items() if k != "seconds"} for r in result.records]
        for result in (got, expected)
    ]
    np.testing.assert_equal(records[0], records[1])
    assert got.seconds >= 0.0


def test_localize_station_links_a_station_to_the_one_before(two_stations: Case) -> None:
    stations, estimate, factors = two_stations
    result = localize_station(stations, estimate, factors, PARAMS, K1)
    assert result.station == "a1"
    (record,) = result.records
    assert (record.kind, record.against, record.band, record.used) == (
        "link",
        "a0",
        "ceiling",
        True,
    )
    assert record.overlap > 0.5
    (event,) = result.events
    assert (event.robot, event.index, event.reference) == ("a", 1, ("a", 0))
    assert event.pose is not None
    true = se2.between(TRUTH[K0], TRUTH[K1])
    assert math.dist(event.pose[:2], true[:2]) < 0.1
    assert abs(math.remainder(event.pose[2] - true[2], 2 * math.pi)) < math.radians(1.0)
    # The first station has no station before it and no older neighbours: no search.
    first = localize_station(stations, estimate, factors, PARAMS, K0)
    assert (first.station, first.events, first.records) == ("a0", [], [])


def test_inline_localizer_returns_what_localize_station_returns(two_stations: Case) -> None:
    stations, estimate, factors = two_stations
    localizer = ConcurrentLocalizer(PARAMS, concurrent=False)
    try:
        assert not localizer.busy
        assert localizer.collect(5.0) is None  # nothing submitted
        assert localizer.collect(5.0, wait=True) is None
        localizer.submit(stations, estimate, factors, K1, mission_s=41.0)
        assert localizer.busy
        got = localizer.collect(47.5)
        assert got is not None
        assert not localizer.busy
        assert localizer.collect(48.0) is None  # collected once
        assert_same(got, localize_station(stations, estimate, factors, PARAMS, K1))
        assert len(got.events) == 1
        assert localizer.done == [(got, 41.0, 47.5)]
    finally:
        localizer.close()


def test_stations_whose_searches_find_nothing_give_empty_results() -> None:
    stations, estimate, factors = blind_stations()
    localizer = ConcurrentLocalizer(PARAMS, concurrent=False)
    for k in range(3):
        localizer.submit(stations, estimate, factors, pose_key("b", k), mission_s=10.0 * k)
        got = localizer.collect(10.0 * k + 1.0)
        assert got is not None
        assert (got.station, got.events, got.records) == (f"b{k}", [], [])
    assert [(r.station, s, c) for r, s, c in localizer.done] == [
        ("b0", 0.0, 1.0), ("b1", 10.0, 11.0), ("b2", 20.0, 21.0)]  # fmt: skip
    localizer.close()


def test_a_spawned_worker_gives_the_inline_result(two_stations: Case) -> None:
    stations, estimate, factors = two_stations
    inline = localize_station(stations, estimate, factors, PARAMS, K1)
    localizer = ConcurrentLocalizer(PARAMS, concurrent=True)
    try:
        localizer.submit(stations, estimate, factors, K1, mission_s=41.0)
        # The worker needs its imports first: the job is not done at once.
        assert localizer.collect(41.0) is None
        assert localizer.busy
        deadline = time.monotonic() + 120.0
        got = None
        while got is None and time.monotonic() < deadline:
            time.sleep(0.1)
            got = localizer.collect(42.0)
        assert got is not None, "the worker did not answer within 120 s"
        assert_same(got, inline)
        # A second job in the warm worker, with waiting.
        blind, blind_estimate, blind_factors = blind_stations()
        localizer.submit(blind, blind_estimate, blind_factors, pose_key("b", 2), mission_s=50.0)
        second = localizer.collect(51.0, wait=True)
        assert second is not None
        assert (second.station, second.events, second.records) == ("b2", [], [])
        assert [(s, c) for _, s, c in localizer.done] == [(41.0, 42.0), (50.0, 51.0)]
        # The worker searches on one thread beside the loop; inline, the searches use the CPUs.
        assert localizer.params.station_search.workers == 1
        assert ConcurrentLocalizer(PARAMS, concurrent=False).params == PARAMS
        assert PARAMS.station_search.workers == 0
    finally:
        localizer.close()
    assert localizer._executor is None
    localizer.close()  # closing twice is harmless


def test_a_second_submission_before_collecting_and_an_unknown_station_are_errors() -> None:
    stations, estimate, factors = blind_stations()
    localizer = ConcurrentLocalizer(PARAMS, concurrent=False)
    with pytest.raises(EstimationError, match="not among the stations"):
        localizer.submit(stations, estimate, factors, pose_key("z", 9), mission_s=0.0)
    localizer.submit(stations, estimate, factors, pose_key("b", 0), mission_s=0.0)
    with pytest.raises(EstimationError, match="b0's searches are still to be collected"):
        localizer.submit(stations, estimate, factors, pose_key("b", 1), mission_s=1.0)
    assert localizer.collect(2.0) is not None
    assert localizer.collect(3.0) is None
    localizer.close()


def test_the_worker_exits_when_the_loop_process_is_killed() -> None:
    """A base killed with SIGKILL leaves no localization worker behind."""
    import os
    import signal
    import subprocess
    import sys

    script = (
        "import time\n"
        "from estimation.app.config import Config\n"
        "from estimation.app.mission.localizer import ConcurrentLocalizer\n"
        "from estimation.app.rig import station_params\n"
        "loc = ConcurrentLocalizer(station_params(Config()), True)\n"
        "future = loc._executor.submit(int, 1)\n"
        "future.result()\n"
        "print(*loc._executor._processes, flush=True)\n"
        "time.sleep(60)\n"
    )
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert parent.stdout is not None
        worker = int(parent.stdout.readline())
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait(10)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            try:
                os.kill(worker, 0)
            except ProcessLookupError:
                break
            time.sleep(0.1)
        else:
            os.kill(worker, signal.SIGKILL)
            pytest.fail("the worker outlived its parent by 10 s")
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()


def _numbered(stations: list[Station]) -> list[Station]:
    """The stations with each view numbered as a mission's sweep (its dwell)."""
    return [
        Station(s.robot, s.index, s.time_s,
                tuple(dataclasses.replace(v, dwell=10 * n + k) for k, v in enumerate(s.views)))
        for n, s in enumerate(stations)
    ]  # fmt: skip


def _sent(localizer: ConcurrentLocalizer, monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """The requests an inline localizer runs, recorded."""
    from estimation.app.mission import localizer as module

    requests: list[Any] = []
    run = module._localize_request

    def recorded(request: Any) -> Localized:
        requests.append(request)
        return run(request)

    monkeypatch.setattr(module, "_localize_request", recorded)
    return requests


def test_the_worker_is_sent_each_sweep_once_and_keeps_the_station_maps(
    two_stations: Case, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A second search that uses the same stations sends no sweep again and fuses no map again
    (the estimate did not move); the answer is the one of a fresh search."""
    from estimation.app.mission import localizer as module

    stations, estimate, factors = two_stations
    stations = _numbered(stations)
    localizer = ConcurrentLocalizer(PARAMS, concurrent=False)
    sent = _sent(localizer, monkeypatch)
    try:
        localizer.submit(stations, estimate, factors, K1, mission_s=41.0)
        got = localizer.collect(42.0)
        assert got is not None
        assert sorted(sent[0].views) == [(0, "a"), (10, "a")]
        assert sent[0].keep == frozenset({(0, "a"), (10, "a")})
        assert module._HELD is not None
        maps = module._HELD.maps
        builds = {k: w.own_builds for k, w in maps.work.items()}
        assert builds == {K0: 1, K1: 1}
        localizer.submit(stations, estimate, factors, K1, mission_s=50.0)
        second = localizer.collect(51.0)
        assert second is not None
        assert sent[1].views == {}  # the worker holds both sweeps
        assert {k: w.own_builds for k, w in maps.work.items()} == builds  # kept, not fused
        assert_same(second, localize_station(stations, estimate, factors, PARAMS, K1))
    finally:
        localizer.close()
    assert module._HELD is None  # an inline localizer's sweeps go when it closes


def test_the_worker_forgets_sweeps_its_searches_no_longer_use(
    two_stations: Case, monkeypatch: pytest.MonkeyPatch
) -> None:
    from estimation.app.mission import localizer as module

    stations, estimate, factors = two_stations
    stations = _numbered(stations)
    localizer = ConcurrentLocalizer(PARAMS, concurrent=False)
    sent = _sent(localizer, monkeypatch)
    try:
        localizer.submit(stations, estimate, factors, K1, mission_s=1.0)
        assert localizer.collect(2.0) is not None
        # a0's searches use a0 alone (nothing before it): the worker lets a1's sweep go
        localizer.submit(stations, estimate, factors, K0, mission_s=3.0)
        assert localizer.collect(4.0) is not None
        assert sent[1].keep == frozenset({(0, "a")})
        assert sent[1].views == {}
        assert module._HELD is not None
        assert set(module._HELD.views) == {(0, "a")}
        assert set(module._HELD.maps._own) <= {K0}
        # a1 again: its sweep, no longer held, is sent again; a0's is not
        localizer.submit(stations, estimate, factors, K1, mission_s=5.0)
        got = localizer.collect(6.0)
        assert got is not None
        assert sorted(sent[2].views) == [(10, "a")]
        assert_same(got, localize_station(stations, estimate, factors, PARAMS, K1))
    finally:
        localizer.close()


def test_a_worker_that_lacks_a_sweep_says_so() -> None:
    from estimation.app.mission.localizer import _localize_request, _Request

    _, estimate, factors = blind_stations()
    request = _Request("elsewhere", [("b", 0, 0.0, ((7, "b"),))], {}, frozenset({(7, "b")}),
                       estimate, factors, PARAMS, pose_key("b", 0))  # fmt: skip
    with pytest.raises(EstimationError, match=r"lacks the sweeps \[\(7, 'b'\)\]"):
        _localize_request(request)
