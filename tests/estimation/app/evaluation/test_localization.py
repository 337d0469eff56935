"""Localization evaluation: simulated worlds, and real data when ../shared/data is present."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from estimation.app.cli.main import app
from estimation.app.config import load_config
from estimation.app.evaluation.localization import format_report
from estimation.app.evaluation.localization_real import (
    carmen_trials,
    geb079_trials,
    read_carmen_scans,
)
from estimation.app.evaluation.localization_sim import (
    free_positions,
    simulated_trials,
    view_scan,
    world_map,
)
from estimation.app.evaluation.trials import BETAS, Trial, by_room_kind, calibrate_beta, summarise
from estimation.app.resources import resolve_builtin
from estimation.app.rig import T_robot_scanner, search_params
from estimation.errors import EstimationError
from estimation.search.exhaustive import search
from mapping.band import extract_band
from mapping.fusion import fuse_scans
from mapping.grid import GridParams
from sensors.geometry.se2 import wrap_angle
from sensors.sim.scene import RaycastScene, build_mesh
from sensors.sim.world import load_world
from tests.paths import DATA

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


def test_robots_stand_under_luminaires_but_not_beside_desks() -> None:
    world = load_world(resolve_builtin("worlds", "office_loop"))
    free = free_positions(world, load_config(), 0.5)

    def nearest(xy: tuple[float, float]) -> float:
        return float(np.hypot(*(free - xy).T).min())

    assert nearest((13.52, 5.77)) < 0.08  # under office_s2_lamp2, which hangs at 2.45-2.6 m
    assert nearest((4.3, 1.25)) < 0.08  # under the corridor beam beam_s1 (2.4-3.0 m)
    assert nearest((4.82, 9.0)) > 0.85  # office_s1_desk (0-0.75 m, 0.4 m to its long side)
    assert nearest((15.0, 10.0)) > 0.5  # the solid block between the office rows


def test_a_view_inside_each_office_finds_that_office() -> None:
    """office_loop's offices share one footprint; their own luminaires and bulkheads in the
    ceiling band tell them apart, so a single view in each is localized in the whole map.
    (Without those fixtures, every one of these views landed in another office.)"""
    config = load_config()
    rng = np.random.default_rng(7)
    world = load_world(resolve_builtin("worlds", "office_loop"))
    scene = RaycastScene(build_mesh(world, cylinder_segments=config.simulation.cylinder_segments))
    global_ = world_map(world, config, rng, scene)["ceiling"]
    params = search_params(config.search)
    free = free_positions(world, config, 0.5)
    offices = [room for room in world.rooms if room.name.startswith("office")]
    assert len(offices) == 8
    limits = config.bands.ceiling
    for room in offices:
        middle = room.footprint_xy.mean(axis=0)
        x, y = free[np.argmin(np.hypot(*(free - middle).T))]
        scan = view_scan(world, (x, y, -120.0), config, rng, scene)
        grid = fuse_scans([scan], [T_robot_scanner(config)], GridParams(**config.grid.model_dump()))
        local = extract_band(
            grid, limits.min_m, limits.max_m, free_min_observed=config.bands.free_min_observed
        )
        result = search(local, global_, params)
        found_x, found_y, found_yaw = result.pose
        assert math.hypot(found_x - x, found_y - y) < 0.05, (room.name, result.pose)
        assert abs(math.degrees(wrap_angle(found_yaw + math.radians(120.0)))) < 0.5, room.name
        assert result.is_dominant(params.dominance_ratio), room.name


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
