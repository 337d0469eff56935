"""Station localization during the mission: inline or in a spawned worker, the same answer."""

from __future__ import annotations

import dataclasses
import math
import time

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
