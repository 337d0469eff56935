"""``coopmap calibrate mirror|beacon``: fragments written or printed, and one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from estimation.app.config import load_config
from tests.estimation.app.calibration_data import (
    START,
    TRUE,
    simulate_calibration_dataset,
    write_start_config,
)
from tests.estimation.app.cli.clirun import assert_one_line_error, run


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("calibrate")
    return simulate_calibration_dataset(folder), write_start_config(folder / "start.yaml")


def test_mirror_then_beacon_into_one_fragment(recording: tuple[Path, Path], tmp_path: Path) -> None:
    dataset, start = recording
    rig = tmp_path / "rig.yaml"
    code, stdout, stderr = run("calibrate", "mirror", dataset, "--config", start, "--out", rig)
    assert code == 0, stderr
    assert stdout.startswith("coopmap calibrate mirror: robot a, 7 sweeps of 7 dwells")
    assert f"wrote {rig}" in stdout
    mirror = load_config(rig).mirror
    assert mirror.axis_offset_m == pytest.approx(TRUE["mirror"]["axis_offset_m"], abs=5e-4)
    # The beacon starts wrong too, with the mirror as calibrated (a user's file of both).
    both = tmp_path / "both.yaml"
    both.write_text(yaml.safe_dump({**yaml.safe_load(rig.read_text()), "beacon": START["beacon"]}))
    code, stdout, stderr = run("calibrate", "beacon", dataset, "--config", both, "--out", rig)
    assert code == 0, stderr
    assert "(0 found at the configured height)" in stdout
    config = load_config(rig)
    assert config.mirror == mirror
    assert config.beacon.height_m == pytest.approx(TRUE["beacon"]["height_m"], abs=0.015)
    assert config.beacon.offset_m == pytest.approx(TRUE["beacon"]["offset_m"], abs=0.01)
    assert set(yaml.safe_load(rig.read_text())) == {"mirror", "beacon"}


def test_without_out_the_fragment_is_printed(recording: tuple[Path, Path]) -> None:
    dataset, start = recording
    code, stdout, stderr = run("calibrate", "mirror", dataset, "--robot", "b", "--config", start)
    assert code == 0, stderr
    assert stdout.startswith("# coopmap calibration fragment")
    assert "# mirror of robot b from" in stdout
    keys = yaml.safe_load(stdout)
    assert set(keys) == {"mirror"}
    assert set(keys["mirror"]) == {
        "axis_offset_m",
        "elevation_offset_deg",
        "edge_on_motor_phase_deg",
    }
    assert "coopmap calibrate mirror: robot b" in stderr  # the summary stays off stdout


def test_json_reports_estimates_and_residuals(recording: tuple[Path, Path], tmp_path: Path) -> None:
    dataset, _ = recording
    start = tmp_path / "beacon.yaml"
    start.write_text(yaml.safe_dump({"beacon": START["beacon"]}))
    code, stdout, stderr = run("calibrate", "beacon", dataset, "--config", start, "--json")
    assert code == 0, stderr
    report = json.loads(stdout)
    assert report["calibration"] == "beacon"
    assert report["start"] == START["beacon"]
    assert report["estimate"]["offset_m"] == pytest.approx(TRUE["beacon"]["offset_m"], abs=0.01)
    assert report["separation_rms_after_mm"] < report["separation_rms_before_mm"]
    assert report["used"] + report["skipped_degenerate"] == report["observations"] == 6
    assert report["fragment"].startswith("# coopmap calibration fragment")
    assert report["out"] is None


def test_a_users_file_and_a_folder_are_refused_before_any_work(
    recording: tuple[Path, Path], tmp_path: Path
) -> None:
    dataset, _ = recording
    notes = tmp_path / "notes.yaml"
    notes.write_text("my notes\n")
    code, stdout, stderr = run("calibrate", "mirror", dataset, "--out", notes)
    assert_one_line_error(
        code, stdout, stderr, r"notes\.yaml: exists and is not a coopmap calibration fragment"
    )
    assert notes.read_text() == "my notes\n"
    code, stdout, stderr = run("calibrate", "beacon", dataset, "--out", tmp_path)
    assert_one_line_error(code, stdout, stderr, r"is a folder; --out names the fragment file")


def test_errors_are_one_line(recording: tuple[Path, Path], tmp_path: Path) -> None:
    dataset, _ = recording
    code, stdout, stderr = run("calibrate", "mirror", tmp_path / "nowhere")
    assert_one_line_error(
        code, stdout, stderr, r"not a coopmap dataset \(mission\.yaml is missing\)"
    )
    code, stdout, stderr = run("calibrate", "mirror", dataset, "--robot", "q")
    assert_one_line_error(code, stdout, stderr, r"robot 'q' is not in the mission")
    bad = tmp_path / "bad.yaml"
    bad.write_text("mirror:\n  axis_offset_m: .nan\n")
    code, stdout, stderr = run("calibrate", "mirror", dataset, "--config", bad)
    assert_one_line_error(code, stdout, stderr, r"mirror\.axis_offset_m")
    code, stdout, stderr = run("calibrate", "beacon", dataset, "--height-search-m", "-1")
    assert_one_line_error(code, stdout, stderr, r"height search must be a positive distance")
