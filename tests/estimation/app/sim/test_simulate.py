"""Missions: the file format, the leapfrog timeline, odometry, auto planning, the dataset."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from estimation.app.cli.main import app
from estimation.app.config import Config, ConfigError
from estimation.app.sim.planning import BeaconGeometry
from estimation.app.sim.simulate import robot_free_space, run_simulation
from sensors.atomic import replace_directory
from sensors.errors import SensorError
from sensors.lms200.capture import CaptureReader, decode_stream
from sensors.sim.mission import (
    MissionError,
    OdometryNoise,
    build_timeline,
    load_mission,
    mission_from_mapping,
    odometry,
)
from sensors.sim.scene import RaycastScene, build_mesh
from sensors.sim.world import World, load_world, world_from_mapping
from tests.paths import REPO

ROOM = {"name": "r", "footprint": [[0, 0], [10, 0], [10, 8], [0, 8]], "ceiling_m": 3.0}


def room() -> World:
    return world_from_mapping({"name": "room", "rooms": [ROOM]})


def mission(**changes: Any) -> dict[str, Any]:
    doc: dict[str, Any] = {
        "world": "room.yaml",
        "robots": [{"name": "a", "start": [2, 2, 0]}, {"name": "b", "start": [2, 5, 0]}],
        "plan": [{"reference": "a", "mapper": "b", "scans": [[5, 3, 180], [5, 5, 200]]},
                 {"reference": "b", "at": [5, 5, 90], "mapper": "a", "scans": [[7, 6, 160]]}],
    }  # fmt: skip
    doc.update(changes)
    return doc


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"robots": [{"name": "a", "start": [2, 2, 0]}]}, r"robots: List should have at least 2 items"),
        ({"robots": [{"name": "a", "start": [2, 2, 0]}, {"name": "a", "start": [3, 2, 0]}]}, r"robot names must be unique"),
        ({"robots": [{"name": "ab", "start": [2, 2, 0]}, {"name": "b", "start": [3, 2, 0]}]}, r"robots\[0\]\.name: String should match pattern"),
        ({"plan": [{"reference": "a", "mapper": "z", "scans": [[1, 1, 0]]}]}, r"plan\[0\]: mapper 'z' is not one of the robots"),
        ({"plan": [{"reference": "a", "mapper": "a", "scans": [[1, 1, 0]]}]}, r"plan\[0\]: robot 'a' cannot map around itself"),
        ({"plan": [{"reference": "a", "mapper": "b", "scans": []}]}, r"scans: List should have at least 1 item"),
        ({"plan": "manual"}, r"plan"),
        ({"changes": {"movable_fraction": 2}}, r"changes\.movable_fraction: Input should be less than or equal to 1"),
        ({"colour": "red"}, r"colour: unknown key"),
    ],
)  # fmt: skip
def test_mission_rejections(changes: dict[str, Any], message: str) -> None:
    with pytest.raises(MissionError, match=message):
        mission_from_mapping(mission(**changes), "m.yaml")


def test_builtin_missions_load() -> None:
    folder = REPO / "configs" / "missions"
    names = sorted(p.stem for p in folder.glob("*.yaml"))
    assert {"essex_lab", "office_loop", "cluttered_hall_changes", "three_robots"} <= set(names)
    for name in names:
        spec = load_mission(folder / f"{name}.yaml")
        assert len(spec.robots) >= 2


def test_timeline_of_an_explicit_plan() -> None:
    spec = mission_from_mapping(mission())
    space = robot_free_space(room(), Config())
    timeline = build_timeline(spec, list(spec.plan), space, speed_m_s=0.5,  # type: ignore[arg-type]
                              turn_rate_rad_s=math.radians(90), dwell_s=30.0, changes_at_end=True)  # fmt: skip
    dwells = [e for e in timeline.events if e["event"] == "dwell"]
    assert [d["phase"] for d in dwells] == [
        "start",
        "mapping",
        "mapping",
        "station",
        "mapping",
        "relocalize",
    ]
    assert all(d["end_s"] - d["t_s"] == pytest.approx(30.0) for d in dwells)
    # One robot moves at a time; during a dwell nobody moves.
    for d in dwells:
        times = np.linspace(d["t_s"], d["end_s"], 7)
        for robot in ("a", "b"):
            poses = timeline.poses_at(robot, times)
            assert np.ptp(poses, axis=0) == pytest.approx(0.0, abs=1e-5)  # event times: µs
    # b: (2, 5) facing 0° → (5, 3) facing 180°: turn to the leg's heading, drive √13 m, turn.
    move = next(e for e in timeline.events if e["event"] == "move")
    heading = math.atan2(-2, 3)
    turns = abs(heading) + abs(math.remainder(math.pi - heading, 2 * math.pi))
    expected = turns / math.radians(90) + math.sqrt(13) / 0.5
    assert move["t_s"] - move["start_s"] == pytest.approx(expected, rel=1e-6)
    assert timeline.stops["b"][1][1] == pytest.approx([5, 3, math.pi])
    assert {k: len(v) for k, v in timeline.stops.items()} == {"a": 2, "b": 4}
    assert timeline.change_s == pytest.approx(dwells[-1]["t_s"])


def test_unreachable_and_blocked_stations_are_named() -> None:
    spec = mission_from_mapping(
        mission(plan=[{"reference": "a", "mapper": "b", "scans": [[0.1, 3, 0]]}])
    )
    space = robot_free_space(room(), Config())
    with pytest.raises(
        MissionError, match=r"plan\[0\]\.scans\[0\]: robot 'b' cannot stand at \(0\.1, 3\)"
    ):
        build_timeline(spec, list(spec.plan), space, speed_m_s=0.5, turn_rate_rad_s=1.0, dwell_s=1.0,  # type: ignore[arg-type]
                       changes_at_end=False)  # fmt: skip
    walled = world_from_mapping({
        "name": "two", "rooms": [ROOM, {"name": "s", "footprint": [[12, 0], [16, 0], [16, 8], [12, 8]], "ceiling_m": 3.0}],
    })  # fmt: skip
    spec = mission_from_mapping(
        mission(plan=[{"reference": "a", "mapper": "b", "scans": [[14, 4, 0]]}])
    )
    with pytest.raises(
        MissionError,
        match=r"robot 'b' cannot reach \(14, 4\) from \(2\.00, 5\.00\): no collision-free path",
    ):
        build_timeline(spec, list(spec.plan), robot_free_space(walled, Config()), speed_m_s=0.5,  # type: ignore[arg-type]
                       turn_rate_rad_s=1.0, dwell_s=1.0, changes_at_end=False)  # fmt: skip
    spec = mission_from_mapping(
        mission(robots=[{"name": "a", "start": [0.05, 2, 0]}, {"name": "b", "start": [2, 5, 0]}])
    )
    with pytest.raises(
        MissionError, match=r"robot 'a' starts at \(0\.05, 2\), where it does not fit"
    ):
        build_timeline(spec, list(spec.plan), space, speed_m_s=0.5, turn_rate_rad_s=1.0, dwell_s=1.0,  # type: ignore[arg-type]
                       changes_at_end=False)  # fmt: skip


def test_odometry_errors_accrue_per_leg() -> None:
    spec = mission_from_mapping(mission())
    timeline = build_timeline(spec, list(spec.plan), robot_free_space(room(), Config()), speed_m_s=0.5,  # type: ignore[arg-type]
                              turn_rate_rad_s=1.0, dwell_s=5.0, changes_at_end=False)  # fmt: skip
    times = np.arange(0.0, timeline.end_s, 0.1)
    exact = odometry(timeline, "b", times, OdometryNoise(0, 0, 0, 0), np.random.default_rng(0))
    np.testing.assert_allclose(exact[:, :2], timeline.poses_at("b", times)[:, :2], atol=1e-9)
    finals = []
    for seed in range(200):
        noisy = odometry(
            timeline, "b", times, OdometryNoise(0.01, 0.05, 0.01, 0.02), np.random.default_rng(seed)
        )
        finals.append(noisy[-1, :2] - timeline.poses_at("b", times[-1:])[0, :2])
    spread = np.std(np.array(finals), axis=0)
    assert 0.05 < spread.mean() < 0.6  # three legs of 2–3 m with 1 cm + 5 cm/m and heading error


def test_auto_plan_keeps_beacons_in_view(tmp_path: Path) -> None:
    result = run_simulation(REPO / "configs" / "missions" / "essex_lab.yaml", tmp_path / "ds")
    assert result.steps >= 2
    spec = load_mission(tmp_path / "ds" / "mission.yaml")
    config = Config()
    world = load_world(tmp_path / "ds" / "world.yaml")
    geometry = BeaconGeometry(config, RaycastScene(build_mesh(world)))
    starts = {
        r.name: np.array([r.start[0], r.start[1], math.radians(r.start[2])]) for r in spec.robots
    }
    assert isinstance(spec.plan, list)
    for step in spec.plan:
        ref = (
            starts[step.reference]
            if step.at is None
            else np.array([*step.at[:2], math.radians(step.at[2])])
        )
        for scan in step.scans:
            pose = np.array([scan[0], scan[1], math.radians(scan[2])])
            assert geometry.mutual(ref, pose, (1.5, 4.5)), (step.reference, scan)
            starts[step.mapper] = pose
        starts[step.reference] = ref


def test_dataset_is_complete_and_consistent(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    result = run_simulation(REPO / "configs" / "missions" / "essex_lab.yaml", out)
    for name in ("a", "b"):
        assert (out / "robots" / name / "lms.cap").is_file()
        odo = np.loadtxt(out / "robots" / name / "odometry.tum")
        truth = np.loadtxt(out / "ground_truth" / f"{name}.tum")
        assert odo.shape == truth.shape
        assert odo[-1, 0] == pytest.approx(result.duration_s, abs=0.1)
        np.testing.assert_allclose(np.linalg.norm(truth[:, 4:], axis=1), 1.0, atol=1e-9)
        records, summary = decode_stream(CaptureReader(out / "robots" / name / "lms.cap"))
        assert sum(1 for r in records if r["kind"] == "scan") == result.telegrams[name]
        assert summary.checksum_failures == 0
        # 12.5 scans/s over the mission.
        assert result.telegrams[name] == pytest.approx(12.5 * result.duration_s, rel=0.01)
    events = [json.loads(line) for line in (out / "events.jsonl").read_text().splitlines()]
    assert events == sorted(events, key=lambda e: e["t_s"])
    assert {e["event"] for e in events} >= {"start", "roles", "move", "dwell", "changes"}
    assert (out / "world_changed.yaml").is_file()
    assert load_world(out / "world_changed.yaml") != load_world(out / "world.yaml")


def test_failed_simulation_keeps_the_old_dataset(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    with replace_directory(out, "dataset") as work:
        (work / "keep.txt").write_text("earlier result")

    def failing_run() -> None:
        with replace_directory(out, "dataset") as work:
            (work / "partial").write_text("x")
            raise RuntimeError("simulation failed")

    with pytest.raises(RuntimeError, match="simulation failed"):
        failing_run()
    assert (out / "keep.txt").read_text() == "earlier result"
    assert [p.name for p in tmp_path.iterdir()] == ["ds"]
    with replace_directory(out, "dataset") as work:
        (work / "new.txt").write_text("new")
    assert sorted(p.name for p in out.iterdir()) == [".coopmap", "new.txt"]


def test_simulate_refuses_a_users_folder_before_simulating(tmp_path: Path) -> None:
    thesis = tmp_path / "my_thesis"
    thesis.mkdir()
    (thesis / "chapter1.tex").write_text("precious")
    result = CliRunner().invoke(app, ["simulate", "essex_lab", "--out", str(thesis)])
    assert result.exit_code == 2
    assert "holds files coopmap did not write (chapter1.tex)" in result.stderr
    assert [p.name for p in thesis.iterdir()] == ["chapter1.tex"]
    assert [p.name for p in tmp_path.iterdir()] == ["my_thesis"]


def test_simulate_cli_errors(tmp_path: Path) -> None:
    result = CliRunner().invoke(app, ["simulate", "nowhere_mission", "--out", str(tmp_path / "d")])
    assert result.exit_code == 2
    assert "neither a mission file nor a built-in mission" in result.stderr
    bad = tmp_path / "bad.yaml"
    bad.write_text("world: essex_lab\nrobots: []\nplan: auto\n")
    result = CliRunner().invoke(app, ["simulate", str(bad), "--out", str(tmp_path / "d")])
    assert result.exit_code == 2
    assert "robots: List should have at least 2 items" in result.stderr
    assert not (tmp_path / "d").exists()


def test_auto_plan_reports_a_cramped_start() -> None:
    from estimation.app.sim.planning import plan_leapfrog

    spec = mission_from_mapping(
        mission(
            plan="auto",
            robots=[{"name": "a", "start": [0.2, 2, 0]}, {"name": "b", "start": [2, 5, 0]}],
        )
    )
    with pytest.raises(
        SensorError, match=r"robot 'a' starts at \(0\.2, 2\), where it does not fit"
    ):
        plan_leapfrog(
            spec, room(), robot_free_space(room(), Config()), Config(), np.random.default_rng(0)
        )


def test_a_plan_in_which_no_beacon_can_be_seen_is_refused(tmp_path: Path) -> None:
    """Robots that turn their backs on each other in every dwell: no mutual observation."""
    mission = tmp_path / "backs.yaml"
    mission.write_text(
        "world: essex_lab\nseed: 0\nrobots:\n"
        "  - {name: a, start: [2.0, 3.5, 200]}\n  - {name: b, start: [3.5, 5.75, 40]}\n"
        "plan:\n  - {reference: a, mapper: b, scans: [[3.6, 5.7, 45]]}\n"
    )
    with pytest.raises(ConfigError, match=r"backs\.yaml: in no dwell of the plan can the "
                       r"reference and the mapper see each other's beacon"):  # fmt: skip
        run_simulation(mission, tmp_path / "out")
    assert not (tmp_path / "out").exists()
    # Facing each other, the same plan is flown.
    mission.write_text(mission.read_text().replace("200]", "20]").replace("40]", "220]"))
    result = run_simulation(mission, tmp_path / "out")
    assert result.steps == 1


def test_a_route_heading_without_a_mapper_pose_turns_to_the_nearest_heading_that_has_one(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The route points the reference where no mapper pose sees its beacon (a wall or a robot
    ahead): the plan goes on from the nearest heading that has one instead of ending after its
    first step."""
    from estimation.app.sim import planning

    blocked = math.pi
    monkeypatch.setattr(planning.Route, "heading", lambda self, pose: blocked)
    candidates = planning.mapper_candidates
    monkeypatch.setattr(
        planning, "mapper_candidates",
        lambda ref, *args: [] if abs(math.remainder(ref[2] - blocked, 2 * math.pi)) < 1e-6
        else candidates(ref, *args),
    )  # fmt: skip
    spec = mission_from_mapping(
        mission(
            plan="auto",
            robots=[{"name": "a", "start": [2, 4, 0]}, {"name": "b", "start": [5, 4, 180]}],
            auto={"stations": 4, "scans_per_station": 1, "route": [[8.5, 6.5], [8.5, 1.5]]},
        )
    )
    config = Config()
    steps = planning.plan_leapfrog(
        spec, room(), robot_free_space(room(), config), config, np.random.default_rng(0)
    )
    assert len(steps) >= 3
    geometry = BeaconGeometry(config, RaycastScene(build_mesh(room())))
    for step in steps[1:]:
        assert step.at is not None
        heading = math.radians(step.at[2])
        assert 14.9 < abs(math.degrees(math.remainder(heading - blocked, 2 * math.pi))) < 180.0
        pose = np.array([step.at[0], step.at[1], heading])
        assert geometry.mutual(pose, np.array([*step.scans[0][:2], math.radians(step.scans[0][2])]),
                               (1.5, 4.5))  # fmt: skip
