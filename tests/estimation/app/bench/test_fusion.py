"""``coopmap bench fusion``: the cases, the figures' consistency, the JSON contract, the CLI."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from estimation.app.bench.fusion import (
    FusionCase,
    grid_params,
    map_agreement,
    measure_case,
    measure_refusion,
    real_scan,
    run_fusion_benchmark,
    simulated_scan,
)
from estimation.app.cli.common import cli_errors
from estimation.app.cli.main import app
from estimation.app.config import Config
from mapping.errors import MapError
from mapping.grid import GridParams, OccupancyGrid
from tests.paths import DATA

pyoctomap = pytest.importorskip("pyoctomap")
FIGURES = {"benchmark", "ratio", "rays_per_s", "peer_rays_per_s", "agreement", "cases"}


def test_grid_parameters_come_from_the_grid_section() -> None:
    assert grid_params(Config().grid) == GridParams()
    cfg = Config().model_copy(update={"grid": Config().grid.model_copy(update={"prob_hit": 0.8})})
    assert grid_params(cfg.grid).prob_hit == 0.8


def test_the_simulated_scan_is_25000_returns_of_essex_lab() -> None:
    case = simulated_scan(Config())
    assert case.points.shape == (25_000, 3)
    np.testing.assert_allclose(case.origin, [6.0, 4.6, 0.45], atol=1e-9)  # demo pose + mount
    assert case.points[:, 0].min() >= -0.05  # the lab's walls, plus the range noise
    assert case.points[:, 0].max() <= 12.05
    assert np.linalg.norm(case.points - case.origin, axis=1).max() <= 8.0 + 1e-9
    again = simulated_scan(Config())
    np.testing.assert_array_equal(case.points, again.points)


def small_case(points: int = 3000) -> FusionCase:
    return simulated_scan(Config(), points=points)


def test_a_case_measures_both_tools_on_the_same_scan() -> None:
    result = measure_case(small_case(), GridParams(), repeats=2)
    assert result["points"] == 3000
    assert result["rays_per_s"] == pytest.approx(3000 / result["seconds"])
    assert result["peer_rays_per_s"] == pytest.approx(3000 / result["peer_seconds"])
    assert result["ratio"] == pytest.approx(result["peer_seconds"] / result["seconds"])
    # Two threads: timed too (a scan this small is walked on one; the grid is the same).
    assert result["ratio_two_threads"] == pytest.approx(
        result["ratio"] * result["rays_per_s_two_threads"] / result["rays_per_s"]
    )
    assert result["agreement"] >= 0.99
    assert result["cells_compared"] > 0.95 * result["cell_updates"]
    assert result["repeats"] >= 2
    assert result["npz_bytes"] > 0
    assert result["peer_bt_bytes"] > 0
    # Memory per known cell: each tool's own count over the cells it knows.
    assert result["bytes_per_known_cell"] == result["memory_bytes"] / result["known_cells"]
    assert result["known_cells"] == result["cell_updates"]  # one scan: each cell once
    assert result["peer_known_cells"] >= result["peer_leaves"] > 0
    assert result["peer_bytes_per_known_cell"] == pytest.approx(
        result["peer_memory_bytes"] / result["peer_known_cells"]
    )
    assert 8 < result["peer_bytes_per_known_cell"] < 200  # OctoMap: 16 B nodes + pointer arrays


def test_octomap_runs_in_its_fair_mode() -> None:
    """Lazy insertion and one updateInnerOccupancy give the tree the default mode gives."""
    case = small_case(1000)
    lazy = pyoctomap.OcTree(0.1)
    lazy.insertPointCloud(case.points, case.origin, -1.0, True)
    lazy.updateInnerOccupancy()
    default = pyoctomap.OcTree(0.1)
    default.insertPointCloud(case.points, case.origin)
    grid = OccupancyGrid(GridParams())
    grid.integrate_scan(case.points, case.origin)
    assert map_agreement(grid, lazy) == map_agreement(grid, default)


def test_agreement_counts_cells_known_to_both() -> None:
    case = small_case(500)
    params = GridParams()
    grid = OccupancyGrid(params)
    grid.integrate_scan(case.points, case.origin)
    tree = pyoctomap.OcTree(params.resolution_m)
    tree.insertPointCloud(case.points, case.origin)
    agreement, compared = map_agreement(grid, tree)
    assert agreement >= 0.99
    assert compared == pytest.approx(grid.known_count(), rel=0.02)
    # A map that says the opposite everywhere disagrees everywhere.
    cells, values = grid.cells()
    flipped = OccupancyGrid.from_cells(params, cells, -values)
    assert map_agreement(flipped, tree)[0] <= 0.01
    assert map_agreement(OccupancyGrid(params), tree) == (0.0, 0)


@pytest.fixture(scope="module")
def measured(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """One run of the benchmark (9 s), without the shared data: the simulated scan alone."""
    return run_fusion_benchmark(
        Config(), tmp_path_factory.mktemp("nodata"), repeats=1, refusion_scans=0
    )


def test_the_benchmark_object_follows_design_11(measured: dict[str, Any]) -> None:
    result = measured
    assert result.keys() >= FIGURES
    assert result["benchmark"] == "fusion"
    assert [c["name"] for c in result["cases"]] == ["essex_lab"] * 3  # no shared data in tmp_path
    assert [c["resolution_m"] for c in result["cases"]] == [0.05, 0.1, 0.2]
    case = min(result["cases"], key=lambda c: c["ratio"])
    for key in ("ratio", "rays_per_s", "peer_rays_per_s"):
        assert result[key] == case[key]
    assert result["agreement"] == min(c["agreement"] for c in result["cases"])
    assert result["worst_resolution_m"] == case["resolution_m"]
    assert "refusion" not in result
    json.dumps(result)  # plain JSON types only


def test_refusion_fuses_every_scan() -> None:
    result = measure_refusion(Config(), scans=3, points=2000)
    assert result["scans"] == 3
    assert result["points"] == 6000
    assert result["no_return_beams"] > 0
    assert result["seconds"] > 0
    assert result["cpu_seconds"] > 0
    assert result["repeats"] == 2
    assert result["known_cells"] > 10_000
    assert result["extent_m"][2] <= 3.2  # floor to ceiling of the 3 m hall, no leaks


@pytest.mark.skipif(not (DATA / "octomap_fr079").is_dir(), reason="../shared/data is absent")
def test_the_real_scan_is_read() -> None:
    case = real_scan(DATA)
    assert case is not None
    assert case.points.shape == (88_206, 3)
    np.testing.assert_array_equal(case.origin, [0.0, 0.0, 0.0])
    ranges = np.linalg.norm(case.points, axis=1)
    assert 0.4 < ranges.min() < 0.5
    assert 28.0 < ranges.max() < 30.0


def test_cli_prints_json_and_text(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, measured: dict[str, Any]
) -> None:
    """The command passes its options on and prints the benchmark's figures as JSON or as text
    (the figures of one run, not measured again for each)."""
    from estimation.app.bench import fusion

    calls: list[tuple[Path, int, int]] = []

    def run(config: Config, data: Path, *, repeats: int, refusion_scans: int) -> dict[str, Any]:
        calls.append((data, repeats, refusion_scans))
        return measured

    monkeypatch.setattr(fusion, "run_fusion_benchmark", run)
    runner = CliRunner()
    args = ["bench", "fusion", "--repeats", "1", "--refusion-scans", "0", "--data", str(tmp_path)]
    result = runner.invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    figures = json.loads(result.stdout)
    assert figures.keys() >= FIGURES
    assert figures == json.loads(json.dumps(measured))
    text = runner.invoke(app, args)
    assert text.exit_code == 0
    assert text.stdout == fusion.format_fusion_report(measured) + "\n"
    assert "essex_lab" in text.stdout
    assert "× OctoMap's rays/s" in text.stdout
    assert calls == [(tmp_path, 1, 0)] * 2


def test_map_errors_are_one_line_in_the_cli() -> None:
    @cli_errors
    def failing() -> None:
        raise MapError("map.npz: map format version 9 is not supported")

    with pytest.raises(typer.Exit) as exit_info:
        failing()
    assert exit_info.value.exit_code == 2
