"""Calibration from a simulated recording whose true rig is known, and its bad inputs.

The recording (tests/estimation/app/calibration_data.py) is made with the true rig; every
calibration starts from a wrong one (d +30 mm, φ0 +3°, motor phase +60°, beacon height −30 cm,
offset −7 cm). Tolerances asserted (achieved over five simulation seeds in brackets): d ±0.5 mm
[0.1 mm]; the elevation the sweeps get ±0.05° [0.025°]; φ0 ±0.3° [0.2°]; motor phase ±12° [8°];
beacon height ±1.5 cm [1.1 cm]; beacon offset ±1 cm [3 mm].
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from estimation.app.calibration import (
    FRAGMENT_HEADER,
    MirrorResult,
    calibrate_beacon,
    calibrate_mirror,
    check_fragment_target,
    write_fragment,
)
from estimation.app.config import ConfigError, load_config
from sensors.errors import OutputError, SensorError
from tests.estimation.app.calibration_data import (
    HALF_TURN_MOTOR_TURNS,
    START,
    TRUE,
    simulate_calibration_dataset,
)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulate_calibration_dataset(tmp_path_factory.mktemp("calibration"))


@pytest.fixture(scope="module")
def mirror_a(dataset: Path) -> MirrorResult:
    return calibrate_mirror(dataset, "a", START)


def wrapped_deg(value: float) -> float:
    return math.remainder(value, 360.0)


def elevation_error_deg(estimate: dict[str, float]) -> float:
    """What the calibrated keys add to every sweep's elevation, against the truth."""
    true = TRUE["mirror"]
    phase = wrapped_deg(estimate["edge_on_motor_phase_deg"] - true["edge_on_motor_phase_deg"])
    return (
        estimate["elevation_offset_deg"]
        - true["elevation_offset_deg"]
        - phase / HALF_TURN_MOTOR_TURNS
    )


def test_mirror_calibration_recovers_the_true_rig(mirror_a: MirrorResult) -> None:
    e, true = mirror_a.estimate, TRUE["mirror"]
    assert e["axis_offset_m"] == pytest.approx(true["axis_offset_m"], abs=5e-4)
    assert elevation_error_deg(e) == pytest.approx(0.0, abs=0.05)
    assert e["elevation_offset_deg"] == pytest.approx(true["elevation_offset_deg"], abs=0.3)
    assert wrapped_deg(
        e["edge_on_motor_phase_deg"] - true["edge_on_motor_phase_deg"]
    ) == pytest.approx(0.0, abs=12.0)
    assert mirror_a.start == START["mirror"]
    fit = mirror_a.fit
    assert fit.rms_before_m > 0.02
    assert fit.rms_after_m < 0.005  # the LMS range noise is 5 mm
    assert fit.sweeps == mirror_a.dwells == 7
    assert fit.points > 10_000
    assert fit.floor_points > 5_000
    assert mirror_a.warnings == ()
    assert mirror_a.missing == ()


def test_the_other_robots_mirror_too(dataset: Path) -> None:
    found = calibrate_mirror(dataset, "b", START)
    assert found.robot == "b"
    assert found.estimate["axis_offset_m"] == pytest.approx(
        TRUE["mirror"]["axis_offset_m"], abs=5e-4
    )
    assert elevation_error_deg(found.estimate) == pytest.approx(0.0, abs=0.05)


def test_the_fragment_loads_and_improves_the_residual(
    mirror_a: MirrorResult, dataset: Path, tmp_path: Path
) -> None:
    path = tmp_path / "rig.yaml"
    text = write_fragment(path, mirror_a)
    assert path.read_text(encoding="utf-8") == text
    assert text.startswith(FRAGMENT_HEADER)
    assert "point-to-plane RMS" in text.splitlines()[2]
    keys = yaml.safe_load(text)
    assert keys == {"mirror": mirror_a.estimate}
    config = load_config(path)
    assert config.mirror.axis_offset_m == mirror_a.estimate["axis_offset_m"]
    again = calibrate_mirror(dataset, "a", keys)
    assert again.fit.rms_before_m == pytest.approx(mirror_a.fit.rms_after_m, abs=2e-4)
    assert again.fit.rms_before_m < 0.2 * mirror_a.fit.rms_before_m
    assert again.estimate["axis_offset_m"] == pytest.approx(
        mirror_a.estimate["axis_offset_m"], abs=2e-4
    )


def test_beacon_calibration_recovers_height_and_offset(dataset: Path) -> None:
    found = calibrate_beacon(dataset, {"beacon": START["beacon"]})
    assert found.estimate["height_m"] == pytest.approx(TRUE["beacon"]["height_m"], abs=0.015)
    assert found.estimate["offset_m"] == pytest.approx(TRUE["beacon"]["offset_m"], abs=0.01)
    # 30 cm too low: the detector, gating by the configured height, finds nothing at first.
    assert found.at_configured_height == 0
    assert found.observations == found.offset.used == 6
    assert found.offset.skipped_degenerate == 0
    assert found.heights == 12
    assert found.offset.separation_rms_before_m > 0.01
    assert found.offset.separation_rms_after_m < 0.004
    assert found.warnings == ()


def test_a_mirror_fragment_and_then_a_beacon_fragment_share_one_file(
    mirror_a,
    dataset: Path,
    tmp_path: Path,
) -> None:
    path = tmp_path / "rig.yaml"
    write_fragment(path, mirror_a)
    beacon = calibrate_beacon(dataset, {"beacon": START["beacon"]})
    text = write_fragment(path, beacon)
    assert yaml.safe_load(text) == {"mirror": mirror_a.estimate, "beacon": beacon.estimate}
    summaries = [line for line in text.splitlines() if line.startswith(("# mirror", "# beacon"))]
    assert len(summaries) == 2
    text = write_fragment(path, mirror_a)  # recalibrated: its summary is replaced, not repeated
    assert sum(line.startswith("# mirror") for line in text.splitlines()) == 1
    assert load_config(path).beacon.offset_m == beacon.estimate["offset_m"]


def test_fragment_targets_that_are_refused(tmp_path: Path) -> None:
    notes = tmp_path / "notes.yaml"
    notes.write_text("mirror:\n  axis_offset_m: 0.1\n", encoding="utf-8")
    with pytest.raises(OutputError, match="exists and is not a coopmap calibration fragment"):
        check_fragment_target(notes)
    with pytest.raises(OutputError, match="is a folder; --out names the fragment file"):
        check_fragment_target(tmp_path)
    link = tmp_path / "link.yaml"
    link.symlink_to(notes)
    with pytest.raises(OutputError, match="is a symbolic link"):
        check_fragment_target(link)
    check_fragment_target(tmp_path / "new.yaml")  # a new file is fine
    assert notes.read_text(encoding="utf-8") == "mirror:\n  axis_offset_m: 0.1\n"


Event = dict[str, Any]


def edited(dataset: Path, folder: Path, change: Callable[[Event], Event | None]) -> Path:
    """A copy of the dataset with every event passed through ``change`` (None drops it)."""
    copy = folder / "edited"
    shutil.copytree(dataset, copy)
    events = [json.loads(line) for line in (copy / "events.jsonl").read_text().splitlines()]
    kept = [e for e in (change(e) for e in events) if e is not None]
    (copy / "events.jsonl").write_text("".join(json.dumps(e) + "\n" for e in kept))
    return copy


def test_missing_dataset_is_named(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"not a coopmap dataset \(mission.yaml is missing\)"):
        calibrate_mirror(tmp_path / "nowhere")
    with pytest.raises(ConfigError, match=r"not a coopmap dataset"):
        calibrate_beacon(tmp_path / "nowhere")


def test_unknown_robot_is_named(dataset: Path) -> None:
    with pytest.raises(ConfigError, match=r"robot 'z' is not in the mission \(robots: a, b\)"):
        calibrate_mirror(dataset, "z")


def test_a_dataset_without_sweeps_is_refused(dataset: Path, tmp_path: Path) -> None:
    def short(e: Event) -> Event:
        return {**e, "end_s": e["t_s"] + 2.0} if e["event"] == "dwell" else e

    with pytest.raises(
        SensorError, match=r"no dwell of robot a yields a sweep \(dwell \d+: only \d+ scans\)"
    ):
        calibrate_mirror(edited(dataset, tmp_path, short))


def test_a_dataset_without_dwells_is_refused(dataset: Path, tmp_path: Path) -> None:
    copy = edited(dataset, tmp_path, lambda e: None if e["event"] == "dwell" else e)
    with pytest.raises(SensorError, match=r"the event log has no dwell: no static sweeps"):
        calibrate_mirror(copy)


def test_no_mutual_observations(dataset: Path, tmp_path: Path) -> None:
    def unpaired(e: Event) -> Event:
        return {k: v for k, v in e.items() if k not in ("reference", "mapper")}

    with pytest.raises(SensorError, match=r"no dwell names a reference and a mapper"):
        calibrate_beacon(edited(dataset, tmp_path, unpaired))
    # Beacons searched far from where they are: nothing is found.
    with pytest.raises(SensorError, match=r"in none of 7 dwells did both robots detect"):
        calibrate_beacon(dataset, {"beacon": {"height_m": 3.5}}, height_search_m=0.1)


def test_degenerate_observations_are_refused(dataset: Path) -> None:
    with pytest.raises(SensorError, match=r"all 6 mutual observations are degenerate"):
        calibrate_beacon(dataset, min_asymmetry_m=10.0)


def test_bad_values_are_refused(dataset: Path) -> None:
    with pytest.raises(ConfigError, match=r"mirror\.axis_offset_m"):
        calibrate_mirror(dataset, overrides={"mirror": {"axis_offset_m": float("nan")}})
    with pytest.raises(ConfigError, match=r"height search must be a positive distance, got nan"):
        calibrate_beacon(dataset, height_search_m=float("nan"))


def test_a_fragment_the_configuration_would_refuse_is_not_written(
    mirror_a: MirrorResult, tmp_path: Path
) -> None:
    broken = dataclasses.replace(mirror_a, estimate={**mirror_a.estimate, "axis_offset_m": -0.01})
    with pytest.raises(SensorError, match=r"values the configuration refuses: .*axis_offset_m"):
        write_fragment(tmp_path / "rig.yaml", broken)
    assert not (tmp_path / "rig.yaml").exists()
