"""``coopmap world generate``: writes a building, refuses bad arguments and users' files with one
line, and the building it writes can be flown by ``coopmap simulate``."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from sensors.sim.generate import HEADER, generate_building
from sensors.sim.planner import free_space
from sensors.sim.world import load_world
from tests.estimation.app.cli.clirun import assert_one_line_error, run


def test_generate_writes_the_building_of_the_seed(tmp_path: Path) -> None:
    out = tmp_path / "b.yaml"
    code, stdout, stderr = run(
        "world", "generate", "--seed", "3", "--rooms", "6", "--out", str(out)
    )
    assert code == 0, stderr
    assert out.read_text(encoding="utf-8") == generate_building(3, 6).text
    assert out.read_text(encoding="utf-8").startswith(f"{HEADER} (coopmap world generate --seed 3")
    world = load_world(out)
    assert len(world.rooms) == 6
    assert re.search(rf"wrote {re.escape(str(out))} \(\d+ kB\): generated_3_6, 6 rooms \(", stdout)
    # Running again replaces the command's own file; --rooms drawn from the seed when left out.
    code, stdout, _ = run("world", "generate", "--seed", "8", "--out", str(out))
    assert code == 0
    assert load_world(out).name == generate_building(8).world.name


def test_generate_takes_the_band_from_the_config(tmp_path: Path) -> None:
    config = tmp_path / "low.yaml"
    config.write_text("bands:\n  ceiling: {min_m: 2.0, max_m: 2.3}\n", encoding="utf-8")
    out = tmp_path / "b.yaml"
    code, _, stderr = run(
        "world",
        "generate",
        "--seed",
        "2",
        "--rooms",
        "5",
        "--out",
        str(out),
        "--config",
        str(config),
    )
    assert code == 0, stderr
    lamps = [b for b in load_world(out).boxes if "lamp" in b.name]
    assert lamps
    assert all(b.z_m[0] < 2.3 for b in lamps)
    assert out.read_text(encoding="utf-8") != generate_building(2, 5).text


@pytest.mark.parametrize(
    ("args", "pattern"),
    [
        (["--seed", "1", "--rooms", "2"], r"--rooms must be within 3-40, got 2"),
        (["--seed", "1", "--rooms", "41"], r"--rooms must be within 3-40, got 41"),
        (["--seed", "-4"], r"--seed must be >= 0, got -4"),
    ],
)
def test_generate_refuses_bad_arguments_in_one_line(
    tmp_path: Path, args: list[str], pattern: str
) -> None:
    out = tmp_path / "b.yaml"
    assert_one_line_error(*run("world", "generate", *args, "--out", str(out)), pattern)
    assert not out.exists()


def test_generate_never_overwrites_a_users_file(tmp_path: Path) -> None:
    mine = tmp_path / "lab.yaml"
    text = "# my lab, measured by hand\nname: lab\nrooms: []\n"
    mine.write_text(text, encoding="utf-8")
    assert_one_line_error(
        *run("world", "generate", "--seed", "1", "--out", str(mine)),
        r"lab\.yaml: exists and is a file this command did not write; refusing to replace it",
    )
    assert mine.read_text(encoding="utf-8") == text
    assert_one_line_error(
        *run("world", "generate", "--seed", "1", "--out", str(tmp_path / "b.png")),
        r"--out must name a \.yaml file",
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lab.yaml"]


def test_a_generated_building_can_be_flown(tmp_path: Path) -> None:
    world_file = tmp_path / "building.yaml"
    code, _, stderr = run(
        "world", "generate", "--seed", "4", "--rooms", "6", "--out", str(world_file)
    )
    assert code == 0, stderr
    world = load_world(world_file)
    # Two start poses 2.5 m apart, facing each other, in open floor of the roomiest room.
    space = free_space(world, robot_radius_m=0.3, robot_height_m=0.35)
    cells = np.argwhere(space.free & (space.clearance_m > 1.0))
    centres = space.lower_xy + (cells[:, ::-1] + 0.5) * space.resolution_m
    room = max(world.rooms, key=lambda r: int(r.contains(centres).sum()))
    points = centres[room.contains(centres)]
    a = points[len(points) // 2]
    b = points[np.argmin(np.abs(np.hypot(*(points - a).T) - 2.5))]
    yaw = float(np.degrees(np.arctan2(*(b - a)[::-1])))
    mission = {
        "world": world_file.name,
        "seed": 0,
        "robots": [
            {"name": "a", "start": [float(a[0]), float(a[1]), yaw]},
            {"name": "b", "start": [float(b[0]), float(b[1]), yaw + 180.0]},
        ],
        "plan": "auto",
        "auto": {"stations": 2, "scans_per_station": 1},
    }
    mission_file = tmp_path / "mission.yaml"
    mission_file.write_text(yaml.safe_dump(mission), encoding="utf-8")
    code, stdout, stderr = run("simulate", str(mission_file), "--out", str(tmp_path / "ds"))
    assert code == 0, stderr
    assert "in generated_4_6 (seed 0)" in stdout
    events = [json.loads(line) for line in (tmp_path / "ds" / "events.jsonl").open()]
    assert sum(e["event"] == "dwell" for e in events) >= 2
    assert load_world(tmp_path / "ds" / "world.yaml") == world
