"""``coopmap export DATASET`` and ``coopmap import``: what they print, and one-line errors."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from estimation.app.sim.simulate import run_simulation
from tests.estimation.app.cli.clirun import assert_one_line_error, run
from tests.estimation.app.missions import ONE_STEP_MISSION

MISSION = ONE_STEP_MISSION


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, str]:
    root = tmp_path_factory.mktemp("cli_ros")
    (root / "small.yaml").write_text(MISSION)
    run_simulation(root / "small.yaml", root / "sim")
    code, stdout, stderr = run("export", root / "sim", "--mcap", root / "sim.mcap")
    assert code == 0, stderr
    return root / "sim", root / "sim.mcap", stdout


def test_export_of_a_dataset_prints_its_topics(exported: tuple[Path, Path, str]) -> None:
    _, bag, stdout = exported
    assert stdout.splitlines() == [
        "coopmap export: 10 topics, 6,604 messages: /tf_static, /coopmap/mission, "
        "/coopmap/events, /a/lms_raw, /a/scan, /a/odom, /tf, /b/lms_raw, /b/scan, /b/odom",
        f"  wrote {bag} (3.6 MB)",
    ]


def test_export_of_a_dataset_takes_no_dataset_option(
    exported: tuple[Path, Path, str], tmp_path: Path
) -> None:
    dataset, _, _ = exported
    assert_one_line_error(
        *run("export", dataset, "--mcap", tmp_path / "x.mcap", "--dataset", dataset),
        r"--dataset: .*sim is a dataset; --dataset is for a result",
    )


def test_import_of_coopmaps_bag_prints_what_it_wrote(
    exported: tuple[Path, Path, str], tmp_path: Path
) -> None:
    _, bag, _ = exported
    out = tmp_path / "back"
    code, stdout, stderr = run("import", bag, "--out", out)
    assert code == 0, stderr
    lines = stdout.splitlines()
    assert lines[:6] == [
        f"coopmap import: {bag} → {out} (coopmap's records, lossless)",
        "  robot a: /a/lms_raw 916 capture records (196 kB), /a/odom 733 odometry samples",
        "  robot b: /b/lms_raw 916 capture records (196 kB), /b/odom 733 odometry samples",
        "  2 dwells (the bag's events): 0.0–31.3 s, 41.9–73.2 s",
        "  6 events",
        "  skipped messages: none",
    ]
    assert lines[6] == f"  wrote {out} (514 kB)"


def test_import_of_laserscans_finds_the_dwells(
    exported: tuple[Path, Path, str], tmp_path: Path
) -> None:
    dataset, bag, _ = exported
    config = tmp_path / "rig.yaml"
    config.write_text(
        yaml.safe_dump(yaml.safe_load((dataset / "mission.yaml").read_text())["config"])
    )
    out = tmp_path / "foreign"
    code, stdout, stderr = run(
        "import", bag, "--out", out, "--topics", "/a/scan,/b/scan", "--topics", "/a/odom,/b/odom",
        "--config", config, "--reference", "a", "--mapper", "b",
        "--start", "a=2,3.5,20", "--start", "b=3.5,5.75,220",
    )  # fmt: skip
    assert code == 0, stderr
    assert stdout.splitlines() == [
        f"coopmap import: {bag} → {out} (LaserScans re-encoded)",
        "  robot a: /a/scan 916 scans (194 kB), /a/odom 733 odometry samples",
        "  robot b: /b/scan 916 scans (194 kB), /b/odom 733 odometry samples",
        "  2 dwells found (still below 0.01 m/s and 0.5°/s for 20 s or more): 0.0–31.3 s, "
        "42.0–73.2 s",
        "  5 events",
        "  skipped messages: none; beams without a range: 96,529 +inf (no return)",
        f"  wrote {out} ({(sum(p.stat().st_size for p in out.rglob('*') if p.is_file())) / 1e3:.0f} kB)",
    ]
    mission = yaml.safe_load((out / "mission.yaml").read_text())
    assert mission["robots"] == [{"name": "a", "start": [2.0, 3.5, 20.0]},
                                 {"name": "b", "start": [3.5, 5.75, 220.0]}]  # fmt: skip
    assert mission["imported"]["dwells"] == {
        "still_speed_m_s": 0.01, "still_turn_rate_deg_s": 0.5, "min_dwell_s": 20.0}  # fmt: skip


@pytest.mark.parametrize(
    ("args", "pattern"),
    [
        (["{tmp}/none.mcap", "--out", "{tmp}/o"], r"none\.mcap: no such file or folder"),
        (["{bag}", "--out", "{tmp}/o", "--topics", "/a/scan", "--start", "a=1,2"],
         r"--start a=1,2: expected NAME=X_M,Y_M,YAW_DEG"),
        (["{bag}", "--out", "{tmp}/o", "--topics", "/a/scan", "--robot", "a"],
         r"--robot 'a': expected NAME=VALUE"),
        (["{bag}", "--out", "{tmp}/o", "--still-speed", "0"],
         r"dwell detection: still_speed_m_s must be > 0, got 0"),
        (["{bag}", "--out", "{tmp}/mine"], r"mine: holds files coopmap did not write"),
        (["{bag}", "--out", "{bag}"], r"holds the bag .*sim\.mcap; choose another --out"),
        (["{tmp}/junk.mcap", "--out", "{tmp}/o"], r"junk\.mcap: not a readable ROS bag"),
        (["{bag}", "--out", "{tmp}/o", "--topics", "/a/odom,/b/odom"],
         r"no sensor_msgs/LaserScan topic to import \(topics: /a/odom, /b/odom\)"),
    ],
)  # fmt: skip
def test_import_errors_are_one_line(
    exported: tuple[Path, Path, str], tmp_path: Path, args: list[str], pattern: str
) -> None:
    _, bag, _ = exported
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine\n")
    (tmp_path / "junk.mcap").write_bytes(b"\x89MCAP0\r\n" + bytes(100))
    filled = [a.format(tmp=tmp_path, bag=bag) for a in args]
    assert_one_line_error(*run("import", *filled), pattern)
    assert not (tmp_path / "o").exists()
