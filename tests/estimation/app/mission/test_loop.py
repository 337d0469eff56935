"""The mission loop end to end: estimation and planning during a simulated mission, the dataset
it records, and batch reproducing its result."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from estimation.app.dataset import mapping_sweeps, stations
from estimation.app.mission.fleet import SimulatedFleet
from estimation.app.mission.loop import MissionLoop
from estimation.app.mission.work import PARTS
from estimation.app.pipeline import prepare, run_batch, unobserved_stations
from estimation.app.sim.simulate import (
    SimulationResult,
    mission_config,
    robot_free_space,
    run_simulation,
)
from estimation.errors import EstimationError
from estimation.posegraph.events import Move, Observe, Start
from sensors.sim.mission import MissionError, load_mission
from sensors.sim.world import load_world
from sensors.trajio import read_tum
from tests.paths import REPO

ESSEX = REPO / "configs" / "worlds" / "essex_lab.yaml"


def write_mission(folder: Path, **auto: object) -> Path:
    path = folder / "mission.yaml"
    document = {
        "world": str(ESSEX),
        "seed": 0,
        "robots": [
            {"name": "a", "start": [2.0, 3.5, 20]},
            {"name": "b", "start": [3.5, 5.75, 220]},
        ],
        "plan": "auto",
        "auto": {"stations": 2, "scans_per_station": 2, "planner": "map", **auto},
        "changes": {"movable_fraction": 0.5, "shift_m": 0.5, "yaw_deg": 30},
    }
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def flown(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, SimulationResult]:
    folder = tmp_path_factory.mktemp("loop")
    result = run_simulation(write_mission(folder), folder / "dataset")
    return folder / "dataset", result


def test_the_loop_records_a_dataset_that_batch_reproduces(
    flown: tuple[Path, SimulationResult],
) -> None:
    dataset = flown[0]
    for name in ("mission.yaml", "events.jsonl", "world.yaml", "world_changed.yaml"):
        assert (dataset / name).is_file(), name
    for robot in "ab":
        assert (dataset / "robots" / robot / "lms.cap").stat().st_size > 100_000
        assert (dataset / "ground_truth" / f"{robot}.tum").is_file()
    out = run_batch(dataset, dataset.parent / "batch", figures=False)
    for robot in "ab":
        _, live = read_tum(dataset / "result" / "poses" / f"{robot}.tum")
        _, offline = read_tum(dataset.parent / "batch" / "poses" / f"{robot}.tum")
        assert live.shape == offline.shape
        assert len(live) >= 3
        assert np.abs(live[:, :2] - offline[:, :2]).max() < 1e-3
        assert np.abs(np.angle(np.exp(1j * (live[:, 2] - offline[:, 2])))).max() < 1e-3
    assert out.report["observations"] >= 4
    assert out.report["stations_without_mutual"] == []
    # Without their mutual factors every station is listed, with its search factors.
    prepared = prepare(dataset, None, None)
    factors = [f for f in out.factors if f.kind != "mutual"]
    listed = unobserved_stations(prepared, factors)
    every = stations(prepared.dataset, mapping_sweeps(prepared.dataset, prepared.sweeps))
    # the two stations of the plan (a's first, b's last), and any pose a reference stood at
    # for a pivot's dwell
    assert every[0].label == "a0"
    assert every[-1].robot == "b"
    assert len(every) >= 2
    assert [s["station"] for s in listed] == [s.label for s in every]
    searched = [s["search_factors"] for s in listed]
    assert searched == [sum(1 for f in factors if f.kind == "global" and s.key in f.keys)
                        for s in every]  # fmt: skip


def test_the_loop_reports_its_own_figures(flown: tuple[Path, SimulationResult]) -> None:
    dataset, result = flown
    report = json.loads((dataset / "result" / "report.json").read_text(encoding="utf-8"))
    loop = report["mission_loop"]
    assert loop["stop_reason"] == "station budget (2) spent"
    assert loop["dwells"] >= 6  # start, 2 × 2 scans, a station turn, the relocalization
    assert 0 < loop["work_per_dwell_s"]["median"] <= loop["work_per_dwell_s"]["p99"] < 5.0
    waits = loop["localization_waits_s"]
    assert 0 <= waits["max"] <= waits["total"]
    assert 0 < loop["warm_up_s"] < 120
    # The simulator makes the recordings as the loop receives them: not the loop's work.
    assert 0 < loop["receive_s"]["median"] <= loop["receive_s"]["max"]
    parts = loop["work_parts_s"]
    slowest = parts["slowest_dwells"][0]
    assert slowest["work"] == pytest.approx(loop["work_per_dwell_s"]["max"], abs=1e-4)
    assert sum(slowest[p] for p in PARTS) == pytest.approx(slowest["work"], abs=1e-3)
    assert all(0 < parts[p]["median"] <= parts[p]["max"] for p in PARTS)
    assert waits["count"] <= len(loop["concurrent_localization"])
    located = [item["station"] for item in loop["concurrent_localization"]]
    assert located == [station["reference"] for station in loop["stations"]]
    assert located[0] == "a0"
    assert located[1].startswith("b")
    assert loop["concurrent_localization"][-1]["next_map_mission_s"] is None
    # The estimate steering the mission against the final one (the caller's figure).
    assert result.loop is not None
    assert result.loop["online_vs_final_m"] < 0.05
    assert len(loop["changed"]) > 0
    assert loop["refused_goals"] == []
    assert loop["closing_stations"] == []  # the budget ended it, not an empty map
    assert len(loop["stations"]) == 2
    mission = yaml.safe_load((dataset / "mission.yaml").read_text(encoding="utf-8"))
    # the plan as flown, explicit: each station, and each pivot that tied a turn
    assert len(mission["plan"]) == 2 + loop["pivots"]
    assert result.steps == 2 + loop["pivots"]


def test_the_loops_event_stream_is_the_one_batch_reads(tmp_path: Path) -> None:
    """The loop decodes and builds events as the bytes arrive; batch reads the dataset: the
    same events, number for number."""
    path = write_mission(tmp_path, stations=1, scans_per_station=1)
    mission = load_mission(path)
    config = mission_config(mission, None, str(path))
    world = load_world(ESSEX)
    starts = {r.name: np.array([r.start[0], r.start[1], math.radians(r.start[2])])
              for r in mission.robots}  # fmt: skip
    work = tmp_path / "work"
    work.mkdir()
    fleet = SimulatedFleet(world, robot_free_space(world, config), config, starts, seed=3)
    loop = MissionLoop(fleet, mission, config, work, concurrent=False)
    loop.run()
    loop.record()
    offline = prepare(work, None, None).events
    assert len(offline) == len(loop.maker.events) >= 4
    kinds = {type(e) for e in offline}
    assert {Start, Move, Observe} <= kinds
    for a, b in zip(offline, loop.maker.events, strict=True):
        assert type(a) is type(b)
        if isinstance(a, Move) and isinstance(b, Move):
            assert a.delta == pytest.approx(b.delta, abs=1e-12)
            assert a.motion == pytest.approx(b.motion, abs=1e-12)
        if isinstance(a, Observe) and isinstance(b, Observe):
            assert (a.a_m, a.b_m) == pytest.approx((b.a_m, b.b_m), abs=1e-12)


def test_a_start_where_the_robot_does_not_fit_is_refused(tmp_path: Path) -> None:
    path = write_mission(tmp_path)
    document = yaml.safe_load(path.read_text(encoding="utf-8"))
    document["robots"][0]["start"] = [-5.0, -5.0, 0.0]
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    with pytest.raises(MissionError, match="robot 'a' starts at"):
        run_simulation(path, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def failing_after(monkeypatch: pytest.MonkeyPatch, dwells: int, error: Exception) -> None:
    """Every dwell after the first ``dwells`` ends in ``error`` once it is recorded."""
    original = MissionLoop.dwell
    calls = []

    def dwell(self: MissionLoop, **kwargs: object) -> int:
        done = original(self, **kwargs)  # type: ignore[arg-type]
        calls.append(done)
        if len(calls) > dwells:
            raise error
        return done

    monkeypatch.setattr(MissionLoop, "dwell", dwell)


def test_a_mission_that_fails_under_way_keeps_its_recording(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A known failure mid-mission (here an indeterminate system after three dwells) ends the
    command with one error, and the dataset recorded so far takes the output's place, marked
    partial: batch reads it."""
    failing_after(monkeypatch, 3, EstimationError("Indeterminate linear system at b2"))
    out = tmp_path / "dataset"
    with pytest.raises(MissionError, match=r"the mission failed: Indeterminate linear system at "
                       r"b2; its recording up to the failure is in .*partial\.json"):  # fmt: skip
        run_simulation(write_mission(tmp_path), out)
    note = json.loads((out / "partial.json").read_text(encoding="utf-8"))
    assert note["failure"] == "Indeterminate linear system at b2"
    assert note["dwells"] == 4
    assert note["mission_s"] > 0
    for name in ("mission.yaml", "events.jsonl", "world.yaml"):
        assert (out / name).is_file(), name
    assert not (out / "result").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    events = [json.loads(line) for line in (out / "events.jsonl").read_text().splitlines()]
    assert sum(e["event"] == "dwell" for e in events) == 4
    result = run_batch(out, tmp_path / "batch", figures=False)
    assert result.report["observations"] >= 2
    assert result.report["partial_mission"] == "Indeterminate linear system at b2"
    # Run again over it: a partial dataset is coopmap's and is replaced like any other.
    monkeypatch.undo()
    failing_after(monkeypatch, 1, EstimationError("again"))
    with pytest.raises(MissionError, match="the mission failed: again"):
        run_simulation(write_mission(tmp_path), out)
    assert json.loads((out / "partial.json").read_text(encoding="utf-8"))["dwells"] == 2


def test_a_mission_that_fails_with_a_bug_keeps_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An error that is no known failure (a bug) leaves no dataset behind: nothing half made
    takes the output's place."""
    failing_after(monkeypatch, 2, RuntimeError("a bug"))
    with pytest.raises(RuntimeError, match="a bug"):
        run_simulation(write_mission(tmp_path), tmp_path / "dataset")
    assert not (tmp_path / "dataset").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


@pytest.mark.parametrize(("failing", "reason"), [
    ({1}, "station budget (5) spent"),
    ({1, 2, 3, 4}, "no mapper pose around robot"),
])  # fmt: skip
def test_a_frontier_no_pair_reaches_is_given_up_for_another(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, failing: set[int], reason: str
) -> None:
    """When neither pair finds a scan pose toward a frontier (every goal refused on a leg the
    estimated map shows free), the loop gives that frontier up and explores on; after three
    such frontiers in a row, a fourth ends the mission."""
    original = MissionLoop._station
    tried: list[tuple[int, str]] = []

    def station(self: MissionLoop, k: int, explorer: object, reference: str, mapper: str,
                frontier: object) -> object:  # fmt: skip
        tried.append((k, reference))
        if k in failing:
            return None
        return original(self, k, explorer, reference, mapper, frontier)  # type: ignore[arg-type]

    monkeypatch.setattr(MissionLoop, "_station", station)
    path = write_mission(tmp_path, stations=5, scans_per_station=1)
    document = yaml.safe_load(path.read_text(encoding="utf-8"))
    del document["changes"]
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    result = run_simulation(path, tmp_path / "dataset")
    assert result.loop is not None
    assert result.loop["stop_reason"].startswith(reason)
    given_up = result.loop["given_up_frontiers"] + result.loop["retried_frontiers"]
    assert len(given_up) >= 1
    assert {k for k, _ in tried} >= failing | {0}
    assert sum(1 for k, _ in tried if k == 1) == 2  # the pair, then the pair swapped


def test_a_floating_tail_sends_the_pair_back_before_the_mission_ends(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Nothing is left to explore after two stations, and the tail is taken to float from the
    second: the pair flies closing stations toward where the first stood (a room target) until
    the budget ends the mission; they are reported."""
    from estimation.app.mission import closing
    from estimation.app.mission.explore import Explorer

    found = Explorer.frontier
    asked: list[int] = []

    def frontier(self: Explorer, view: object, from_xy: object) -> object:
        asked.append(1)
        return found(self, view, from_xy) if len(asked) <= 2 else None  # type: ignore[arg-type]

    monkeypatch.setattr(Explorer, "frontier", frontier)
    monkeypatch.setattr(
        closing,
        "floating_tail",
        lambda order, untied, records: order[1] if len(order) > 1 else None,
    )
    path = write_mission(tmp_path, stations=4, scans_per_station=1)
    result = run_simulation(path, tmp_path / "dataset")
    assert result.loop is not None
    assert result.loop["stop_reason"] == "station budget (4) spent"
    trace = result.loop["stations"]
    flown = [t for t in trace if t["scans"]]
    assert len(flown) == 4
    assert result.loop["closing_stations"] == [flown[1]["reference"]] * 2
    report = json.loads((tmp_path / "dataset" / "result" / "report.json").read_text())
    assert report["mission_loop"]["closing_stations"] == result.loop["closing_stations"]
    # The closing stations aimed at where the first station stood: a room target there.
    for station in trace[2:]:
        assert station["room"]
        assert math.dist(station["frontier"], flown[0]["pose"][:2]) < 0.1
