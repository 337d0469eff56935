"""``coopmap evaluate-missions``: the start poses of a generated building's mission, one building
flown end to end, failed buildings kept as rows, and one-line refusals of bad arguments and of a
user's folder."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from estimation.app.cli.evaluate_missions import format_ate
from estimation.app.config import Config
from estimation.app.evaluation import missions
from estimation.app.evaluation.missions import generated_mission
from estimation.app.sim.planning import BeaconGeometry, mutual_dwells
from estimation.app.sim.simulate import resolve_mission_world, robot_free_space
from sensors.sim.generate import generate_building
from sensors.sim.mission import MissionError, mission_from_mapping
from sensors.sim.scene import RaycastScene, build_mesh
from sensors.sim.world import load_world
from tests.estimation.app.cli.clirun import assert_one_line_error, run


def _pose(spec: list[float]) -> np.ndarray:
    return np.array([spec[0], spec[1], math.radians(spec[2])])


@pytest.mark.parametrize(
    ("seed", "rooms", "robots"), [(1, 3, 2), (2, 3, 3), (5, 3, 2), (4, None, 3), (9, None, 2)]
)
def test_generated_mission_places_robots_that_fit_and_see_each_other(
    tmp_path: Path, seed: int, rooms: int | None, robots: int
) -> None:
    world_path = tmp_path / "world.yaml"
    world_path.write_text(generate_building(seed, rooms).text, encoding="utf-8")
    mission = generated_mission(world_path, seed, robots)
    assert mission == generated_mission(world_path, seed, robots)  # deterministic
    spec = mission_from_mapping(mission)
    (tmp_path / "mission.yaml").write_text("", encoding="utf-8")
    assert resolve_mission_world(spec, tmp_path / "mission.yaml") == world_path
    assert spec.robot_names() == ["a", "b", "c"][:robots]
    assert (spec.seed, spec.plan, spec.auto.stations, spec.auto.scans_per_station) == (
        seed, "auto", 250, 2,
    )  # fmt: skip
    assert spec.auto.planner == "map"  # the mission loop, on the estimated map
    assert spec.changes is not None
    assert spec.changes.movable_fraction == 0.5

    config = Config()
    world = load_world(world_path)
    space = robot_free_space(world, config)
    poses = [_pose(r.start) for r in spec.robots]
    assert all(space.is_free(p[:2]) for p in poses)
    joined = space.component_of(poses[0][:2])
    assert all(joined[space.cell(p[:2])] for p in poses[1:])
    # The planner's test of mutual visibility, and simulate's test of the first dwell.
    scene = RaycastScene(build_mesh(world))
    geometry = BeaconGeometry(config, scene)
    band = (0.5, config.beacon.max_range_m)
    a, b, *rest = poses
    assert 1.5 <= np.hypot(*(a[:2] - b[:2])) <= 3.5
    assert geometry.mutual(a, b, band)
    dwell = {"event": "dwell", "reference": "a", "mapper": "b", "poses": {"a": 0, "b": 0}}
    assert mutual_dwells([dwell], {"a": [(0.0, a)], "b": [(0.0, b)]}, config, scene) == 1
    for c in rest:
        assert min(np.hypot(*(c[:2] - p[:2])) for p in (a, b)) >= 0.9
        assert geometry.mutual(a, c, band) or geometry.mutual(b, c, band)


def test_generated_mission_refuses_a_world_with_no_floor(tmp_path: Path) -> None:
    world_path = tmp_path / "tiny.yaml"
    world_path.write_text(
        "name: closet\nrooms:\n  - name: closet\n    footprint: [[0, 0], [0.6, 0], [0.6, 0.6], "
        "[0, 0.6]]\n    ceiling_m: 2.5\nboxes: []\ncylinders: []\n",
        encoding="utf-8",
    )
    with pytest.raises(MissionError, match=r"closet: no floor where a robot fits"):
        generated_mission(world_path, 0, 2)


def _cells(stdout: str, seed: int) -> list[str]:
    """The printed table row of a building, cell by cell."""
    for line in stdout.splitlines():
        cells = [c.strip() for c in line.split("│")]
        if len(cells) > 1 and cells[0] == str(seed):
            return cells
    raise AssertionError(f"no row for seed {seed} in:\n{stdout}")


def test_evaluate_missions_flies_a_building_and_writes_what_it_prints(tmp_path: Path) -> None:
    out = tmp_path / "eval"
    code, stdout, stderr = run(
        "evaluate-missions", "--worlds", "1", "--seed", "3", "--rooms", "3", "--stations", "3",
        "--out", out,
    )  # fmt: skip
    assert code == 0, stderr
    document = json.loads((out / "evaluation.json").read_text(encoding="utf-8"))
    (row,) = document["rows"]
    assert row["error"] is None
    assert (row["seed"], row["rooms"], row["folder"]) == (3, 3, "seed-0003")
    folder = out / "seed-0003"
    assert (folder / "world.yaml").is_file()
    assert (folder / "dataset" / "result" / "metrics.json").is_file()
    report = json.loads((folder / "dataset" / "result" / "report.json").read_text(encoding="utf-8"))
    assert report["dataset"] == str(folder / "dataset")  # the path it has, not a temporary one
    assert (
        mission_from_mapping(generated_mission(folder / "world.yaml", 3, 2)).world == "world.yaml"
    )
    assert sorted(row["robots"]) == ["a", "b"]
    for robot in row["robots"].values():
        assert robot["poses"] >= 2
        assert 0.0 <= robot["ate_m"] < 0.5
        assert 0.0 <= robot["ate_deg"] < 10.0
    assert 0.0 < row["coverage"] <= 1.0
    assert 1 <= row["rooms_entered"] <= row["rooms_reachable"] <= 3
    assert row["relocalization"]["searches"] >= 2  # the mission moves furniture at the end
    assert 0 <= row["relocalization"]["success"] <= row["relocalization"]["searches"]
    assert 0.5 < row["map_precision"] <= 1.0
    assert 0.5 < row["map_recall"] <= 1.0
    assert 0.0 < row["wall_time_s"] < 600.0
    loop = row["loop"]  # the mission loop planned it, on the estimated map
    assert loop["stop_reason"]
    assert 1 <= loop["stations"] <= 3  # the budget
    assert 0.0 < loop["work_per_dwell_p99_s"] < 5.0
    assert loop["localizations_late"] == 0
    summary = document["summary"]
    assert (summary["buildings"], summary["failed"]) == (1, 0)
    assert summary["ate_m"]["worst"] == max(r["ate_m"] for r in row["robots"].values())
    reloc = row["relocalization"]
    assert _cells(stdout, 3)[1:] == [
        "3",
        f"{row['coverage']:.1%}",
        f"{row['rooms_entered']} / {row['rooms_reachable']}",
        format_ate(row["robots"]["a"]),
        format_ate(row["robots"]["b"]),
        f"{reloc['success']} / {reloc['searches']}",
        f"{row['map_precision']:.3f}",
        f"{row['map_recall']:.3f}",
        f"{row['wall_time_s']:.1f}",
    ]
    assert f"wrote {out / 'evaluation.json'}" in stdout


def test_a_failed_building_keeps_its_row_and_the_run_goes_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def fly(folder: Path, mission: dict[str, Any], *_: Any) -> dict[str, Any]:
        if mission["seed"] == 3:
            raise MissionError("plan[2]: robot 'b' cannot reach (1, 2):\n no collision-free path")
        robot = {"poses": 5, "ate_m": 0.02, "ate_deg": 0.3}
        return {"robots": {"a": robot, "b": robot}, "coverage": 0.5, "rooms_entered": 2,
                "rooms_reachable": 3, "relocalization": None, "map_precision": 0.99,
                "map_recall": 0.9}  # fmt: skip

    monkeypatch.setattr(missions, "_fly", fly)
    out = tmp_path / "eval"
    code, stdout, stderr = run(
        "evaluate-missions", "--worlds", "2", "--seed", "2", "--rooms", "3", "--out", out
    )
    assert code == 0, stderr
    document = json.loads((out / "evaluation.json").read_text(encoding="utf-8"))
    ok, failed = document["rows"]
    assert ok["error"] is None
    assert failed["error"] == "plan[2]: robot 'b' cannot reach (1, 2): no collision-free path"
    assert failed["rooms"] == 3
    assert failed["robots"] == {}
    summary = document["summary"]
    assert (summary["buildings"], summary["failed"]) == (2, 1)
    assert summary["within_5cm_05deg"] == summary["within_10cm_1deg"] == 0.5
    assert summary["ate_m"] == {"median": 0.02, "worst": 0.02}
    assert _cells(stdout, 2)[6] == "-"  # no changes, no relocalization
    assert _cells(stdout, 3)[2] == "failed"
    assert f"seed 3 failed: {failed['error']}" in stdout
    # Its own earlier output is replaced as a whole.
    code, _, stderr = run("evaluate-missions", "--worlds", "1", "--seed", "2", "--rooms", "3",
                          "--out", out)  # fmt: skip
    assert code == 0, stderr
    assert sorted(p.name for p in out.iterdir()) == [".coopmap", "evaluation.json", "seed-0002"]


def test_an_out_folder_holding_a_users_files_is_refused(tmp_path: Path) -> None:
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me\n", encoding="utf-8")
    assert_one_line_error(
        *run("evaluate-missions", "--worlds", "1", "--seed", "0", "--out", out),
        r"mine: holds files coopmap did not write \(notes\.txt\); refusing to replace it",
    )
    assert [p.name for p in tmp_path.iterdir()] == ["mine"]
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


@pytest.mark.parametrize(
    ("args", "pattern"),
    [
        (["--worlds", "0", "--seed", "1"], r"--worlds must be >= 1, got 0"),
        (["--worlds", "1", "--seed", "1", "--robots", "4"], r"--robots must be 2 or 3, got 4"),
        (["--worlds", "1", "--seed", "-1"], r"--seed must be >= 0, got -1"),
        (["--worlds", "1", "--seed", "1", "--rooms", "2"], r"--rooms must be within 3-40, got 2"),
        (["--worlds", "1", "--seed", "1", "--stations", "0"], r"--stations must be within 1-500"),
    ],
)
def test_bad_arguments_are_one_line(tmp_path: Path, args: list[str], pattern: str) -> None:
    out = tmp_path / "eval"
    assert_one_line_error(*run("evaluate-missions", *args, "--out", out), pattern)
    assert not out.exists()
