"""Localization evaluation: simulated worlds, and real data when ../shared/data is present."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from estimation.cli import app
from estimation.config import load_config
from estimation.errors import EstimationError
from estimation.evaluate_localization import (
    BETAS,
    Trial,
    by_room_kind,
    calibrate_beta,
    carmen_trials,
    format_report,
    geb079_trials,
    read_carmen_scans,
    simulated_trials,
    summarise,
)

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
GEB079 = DATA / "octomap_fr079" / "geb079.bt"
INTEL = DATA / "carmen_corrected" / "intel-corrected.log.gz"


def test_simulated_ceiling_localization_is_accurate() -> None:
    trials = simulated_trials("essex_lab", load_config(), np.random.default_rng(3), 3)
    assert len(trials) == 3
    for trial in trials:
        assert trial.band == "ceiling"
        assert trial.error_m < 0.05, trial
        assert trial.error_deg < 0.5, trial
        assert trial.peak_ratio > 2.0
        assert trial.room == "lab"  # the room holding the truth
        assert len(trial.log_likelihood) == len(BETAS)
        assert max(trial.log_likelihood) < 0.0


def test_station_map_trials_fuse_several_views_in_the_reference_frame() -> None:
    """A station map (the view at the truth and two mapper views 2–5 m away, in line of sight)
    localizes as accurately as one view: the extra views sit where the truth puts them."""
    config = load_config()
    trials = simulated_trials("essex_lab", config, np.random.default_rng(4), 2, views=3)
    single = simulated_trials("essex_lab", config, np.random.default_rng(4), 2)
    for trial in trials:
        assert trial.case == "essex_lab (station map, 3 views)"
        assert trial.error_m < 0.05, trial
        assert trial.error_deg < 0.5, trial
    assert [t.case for t in single] == ["essex_lab", "essex_lab"]


@pytest.mark.skipif(not GEB079.exists(), reason="../shared/data/octomap_fr079 is absent")
def test_geb079_ceiling_and_floor_bands_localize() -> None:
    trials = geb079_trials(GEB079, load_config(), np.random.default_rng(1), 1)
    assert sorted(t.band for t in trials) == ["ceiling", "floor"]
    for trial in trials:
        assert trial.error_m < 0.1, trial
        assert trial.error_deg < 1.0, trial
        assert trial.peak_ratio > 100


@pytest.mark.skipif(not INTEL.exists(), reason="../shared/data/carmen_corrected is absent")
def test_intel_scans_localize_in_the_map_of_the_other_scans() -> None:
    trials = carmen_trials(INTEL, load_config(), np.random.default_rng(2), 2, scans_per_local_map=5)
    for trial in trials:
        assert trial.case == "intel (5 scans)"
        assert trial.error_m < 0.1, trial
        assert trial.error_deg < 1.0, trial


def test_carmen_reader_parses_flaser_lines(tmp_path: Path) -> None:
    log = tmp_path / "tiny.log"
    ranges = " ".join(["2.0"] * 180)
    log.write_text(
        "# comment\nPARAM robot_frontlaser_offset 0.1 nohost 0\n"
        f"FLASER 180 {ranges} 1.0 2.0 0.5 1.0 2.0 0.5 12.0 host 12.0\n"
        "ODOM 1 2 0.5 0 0 0 12.0 host 12.0\n",
        encoding="utf-8",
    )
    scans = read_carmen_scans(log)
    assert scans.laser_offset_m == pytest.approx(0.1)
    np.testing.assert_allclose(scans.poses, [[1.0, 2.0, 0.5]])
    assert scans.angles_rad[0][0] == pytest.approx(-math.pi / 2)
    assert scans.angles_rad[0][90] == pytest.approx(0.0)
    bad = tmp_path / "bad.log"
    bad.write_text("FLASER 3 1.0 x 1.0 0 0 0\n", encoding="utf-8")
    with pytest.raises(EstimationError, match=r"bad\.log:1: malformed FLASER line"):
        read_carmen_scans(bad)
    empty = tmp_path / "empty.log"
    empty.write_text("ODOM 1 2 0.5 0 0 0 12.0 host 12.0\n", encoding="utf-8")
    with pytest.raises(EstimationError, match="no FLASER lines"):
        read_carmen_scans(empty)


def _trial(error_m: float, error_deg: float, curve: tuple[float, ...]) -> Trial:
    return Trial("case", "ceiling", (0, 0, 0), (0, 0, 0), error_m, error_deg, 10.0, 0.1, curve)


def test_calibration_picks_the_beta_of_best_mean_log_likelihood() -> None:
    peak = 7
    curve = tuple(-abs(i - peak) - 1.0 for i in range(len(BETAS)))
    best, mean = calibrate_beta([_trial(0.01, 0.1, curve), _trial(0.02, 0.2, curve)])
    assert best == pytest.approx(BETAS[peak])
    assert mean[peak] == pytest.approx(-1.0)
    with pytest.raises(EstimationError, match="no trial"):
        calibrate_beta([_trial(0.0, 0.0, ())])


def test_summary_counts_successes_and_formats_a_table() -> None:
    trials = [_trial(0.01, 0.1, ()), _trial(0.07, 0.3, ()), _trial(2.0, 90.0, ())]
    summary = summarise(trials)
    assert summary["success"] == pytest.approx(2 / 3)
    assert summary["strict"] == pytest.approx(1 / 3)
    assert summary["median_m"] == pytest.approx(0.07)
    text = format_report(
        {"rows": [{"case": "x", "band": "ceiling", **summary}], "skipped": [], "seconds": 1.0}
    )
    assert "| x | ceiling | 3 | 67 % | 33 % | 7.0 cm, 0.30° |" in text


def test_trials_split_by_the_kind_of_room_holding_the_truth() -> None:
    trials = [
        dataclasses.replace(_trial(0.01, 0.1, ()), case="w", room=room)
        for room in ("corridor_south", "office_n2", "corridor_east", "")
    ]
    split = by_room_kind(trials)
    assert [t.case for t in split] == [
        "w: truth in corridors", "w: truth in offices", "w: truth in corridors",
        "w: truth in rooms",
    ]  # fmt: skip
    assert [t.error_m for t in split] == [t.error_m for t in trials]


def test_evaluate_localization_rejects_an_unknown_part() -> None:
    result = CliRunner().invoke(app, ["evaluate-localization", "--only", "moon"])
    assert result.exit_code == 2
    assert "--only must be sim, geb079 or carmen, got moon" in result.stderr
