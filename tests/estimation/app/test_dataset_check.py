"""coopmap dataset check: every problem of a dataset at once, each naming its file and line."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from estimation.app.cli.main import app
from estimation.app.dataset_check import check_dataset
from tests.estimation.app.missions import copy_of


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory, essex_simulated: Path) -> Path:
    out = copy_of(essex_simulated, tmp_path_factory, "check")
    return out


def copy(dataset: Path, tmp_path: Path) -> Path:
    target = tmp_path / "copy"
    shutil.copytree(dataset, target)
    return target


def lines(path: Path) -> list[dict[str, object]]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def write_lines(path: Path, events: list[dict[str, object]]) -> None:
    path.write_text("".join(json.dumps(e) + "\n" for e in events))


def test_a_simulated_dataset_has_no_problem(dataset: Path) -> None:
    check = check_dataset(dataset)
    assert check.problems == []
    assert check.robots == ["a", "b"]
    assert check.dwells == 7
    assert check.sweeps == 14  # every robot's sweep in every dwell


def test_every_problem_is_listed_not_only_the_first(dataset: Path, tmp_path: Path) -> None:
    ds = copy(dataset, tmp_path)
    events = lines(ds / "events.jsonl")
    dwell = next(k for k, e in enumerate(events) if e["event"] == "dwell" and e["t_s"] > 0)
    move = next(k for k, e in enumerate(events) if e["event"] == "move")
    events[dwell]["end_s"] = "soon"  # a mistyped field
    events[move].update(from_index=5, to_index=6)  # a move from a pose the robot is not at
    events.append({"event": "dwell", "t_s": 1.0, "end_s": 2.0, "poses": {"a": 0}})  # goes back
    write_lines(ds / "events.jsonl", events)
    with (ds / "events.jsonl").open("a") as f:
        f.write("{not json\n")
    (ds / "robots" / "b" / "odometry.tum").write_text("0 1 2\n")
    check = check_dataset(ds)
    found = [p.line() for p in check.problems]
    assert f"error: events.jsonl:{dwell + 1}: dwell: end_s must be a number >= t_s" in found
    assert any(f"events.jsonl:{move + 1}: move of b from pose 5, but b is at pose 0" in p
               for p in found)  # fmt: skip
    assert any(f"events.jsonl:{len(events)}: dwell: poses must give" in p for p in found)
    assert any(f"events.jsonl:{len(events) + 1}: not JSON" in p for p in found)
    assert any("robots/b/odometry.tum:1: TUM line needs 8 fields" in p for p in found)
    assert check.errors == len(found) == 5
    assert check.sweeps == 0  # the sweeps are cut only once the files are sound


def test_index_order_coverage_and_role_problems(dataset: Path, tmp_path: Path) -> None:
    ds = copy(dataset, tmp_path)
    events = lines(ds / "events.jsonl")
    dwells = [k for k, e in enumerate(events) if e["event"] == "dwell"]
    moves = [k for k, e in enumerate(events) if e["event"] == "move"]
    events[dwells[1]]["poses"] = {"a": 0, "b": 3}
    events[dwells[2]]["mapper"] = events[dwells[2]]["reference"]
    events[dwells[3]].pop("mapper")
    events[moves[-1]]["t_s"] = 1e6  # beyond the odometry (and everything after it goes back)
    write_lines(ds / "events.jsonl", events)
    found = [p.line() for p in check_dataset(ds, decode=False).problems]
    assert f"error: events.jsonl:{dwells[1] + 1}: dwell: poses do not follow the moves: b: 3 " \
        "(at 1)" in found  # fmt: skip
    assert any(f"events.jsonl:{dwells[2] + 1}: dwell: reference and mapper are both" in p
               for p in found)  # fmt: skip
    assert any(p.startswith(f"warning: events.jsonl:{dwells[3] + 1}: dwell: a reference "
                            "without a mapper") for p in found)  # fmt: skip
    assert any(f"events.jsonl:{moves[-1] + 1}: move of " in p and "outside its odometry" in p
               for p in found)  # fmt: skip
    assert any("goes back" in p for p in found)


def test_missing_files_and_a_broken_mission(dataset: Path, tmp_path: Path) -> None:
    ds = copy(dataset, tmp_path)
    (ds / "robots" / "a" / "lms.cap").unlink()
    (ds / "ground_truth" / "b.tum").write_text("garbage\n")
    (ds / "world.yaml").write_text("rooms: [\n")
    found = [p.line() for p in check_dataset(ds).problems]
    assert "error: robots/a/lms.cap: no such file" in found
    assert any(p.startswith("error: ground_truth/b.tum:1:") for p in found)
    assert any(p.startswith("error: world.yaml:") for p in found)
    (ds / "mission.yaml").write_text("robots: [{name: ../x, start: [0, 0, 0]}]\nconfig: 3\n")
    (ds / "events.jsonl").unlink()
    found = [p.line() for p in check_dataset(ds).problems]
    assert any("robots[0]: name must be one lowercase letter" in p for p in found)
    assert "error: mission.yaml: config: must be a mapping" in found
    assert "error: events.jsonl: missing (required)" in found
    assert [p.line() for p in check_dataset(tmp_path / "nothing").problems] == [
        f"error: {tmp_path / 'nothing'}: not a folder"
    ]


def test_a_plain_dump_and_damaged_captures_are_named(dataset: Path, tmp_path: Path) -> None:
    ds = copy(dataset, tmp_path)
    cap = ds / "robots" / "b" / "lms.cap"
    data = bytearray(cap.read_bytes())
    start = len(data) // 2
    data[start : start + 4000] = bytes(4000)  # a zeroed stretch in the middle of the capture
    cap.write_bytes(bytes(data))
    check = check_dataset(ds)
    assert check.errors == 0
    damaged = [p.line() for p in check.problems if p.where == "robots/b/lms.cap"]
    assert len(damaged) == 1
    assert damaged[0].startswith("warning: robots/b/lms.cap: ")
    assert "bytes skipped" in damaged[0]
    (ds / "robots" / "a" / "lms.cap").write_bytes(b"\x02\x80" * 100)
    found = [p.line() for p in check_dataset(ds).problems]
    assert any(p.startswith("error: robots/a/lms.cap: a plain binary dump") for p in found)


def test_the_command_prints_every_problem_and_exits_2(dataset: Path, tmp_path: Path) -> None:
    runner = CliRunner()
    ok = runner.invoke(app, ["dataset", "check", str(dataset)])
    assert ok.exit_code == 0, ok.output
    assert ok.stdout.strip().endswith("7 dwells, 14 sweeps: 0 errors, 0 warnings")
    ds = copy(dataset, tmp_path)
    (ds / "robots" / "a" / "odometry.tum").unlink()
    (ds / "robots" / "b" / "odometry.tum").unlink()
    bad = runner.invoke(app, ["dataset", "check", str(ds)])
    assert bad.exit_code == 2
    out = bad.stdout.splitlines()
    assert out[:2] == [
        "error: robots/a/odometry.tum: no such file or directory",
        "error: robots/b/odometry.tum: no such file or directory",
    ], out
    assert out[-1].endswith(": 2 errors, 0 warnings")
    data = json.loads(runner.invoke(app, ["dataset", "check", str(ds), "--json"]).stdout)
    assert data["errors"] == 2
    assert len(data["problems"]) == 2
