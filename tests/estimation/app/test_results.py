"""The result folder as other tools read it: map_server, evo, OctoMap; and the covariances."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from estimation.app.config import load_config
from estimation.app.evaluation.evaluate import evaluate
from estimation.app.pipeline import run_batch
from estimation.app.results import BatchOutput, figure_worker, write_figures
from estimation.app.rig import cut_ceiling_band
from mapping.band import extract_band
from mapping.formats.npz import load_map
from mapping.formats.pgm import UNKNOWN_PIXEL, read_band_pgm
from sensors.trajio import read_tum
from tests.estimation.app.missions import copy_of
from tests.mapping.formats.map_server import load_map_server, read_pgm_pixels


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory, essex_simulated: Path) -> Path:
    out = copy_of(essex_simulated, tmp_path_factory, "results")
    run_batch(out)
    return out


def test_map_server_loads_the_ceiling_unknown_free_and_occupied(dataset: Path) -> None:
    result = dataset / "result"
    cells, doc = load_map_server(result / "ceiling.yaml")
    assert doc["mode"] == "trinary"
    pixels = read_pgm_pixels(result / "ceiling.pgm")[::-1]
    config = load_config(result / "config.yaml")
    band = extract_band(load_map(result / "map.npz"), config.bands.ceiling.min_m,
                        config.bands.ceiling.max_m,
                        free_min_observed=config.bands.free_min_observed)  # fmt: skip
    assert cells.shape == band.shape
    np.testing.assert_array_equal(cells == -1, ~band.known)
    np.testing.assert_array_equal(pixels == UNKNOWN_PIXEL, ~band.known)
    # Known cells: occupied from a fifth of the band's layers up, free below.
    share = band.occupancy[band.known]
    np.testing.assert_array_equal(cells[band.known], np.where(share > 50.5 / 255, 100, 0))
    assert set(np.unique(cells).tolist()) == {-1, 0, 100}
    assert 0.05 < (cells == 100).sum() / band.known.sum() < 0.5
    assert (cells == 0).sum() > 5000


def test_coopmaps_reader_still_reads_the_graded_band(dataset: Path) -> None:
    result = dataset / "result"
    back = read_band_pgm(result / "ceiling.yaml")
    config = load_config(result / "config.yaml")
    band = extract_band(load_map(result / "map.npz"), config.bands.ceiling.min_m,
                        config.bands.ceiling.max_m,
                        free_min_observed=config.bands.free_min_observed)  # fmt: skip
    np.testing.assert_array_equal(back.known, band.known)
    np.testing.assert_allclose(back.occupancy, band.occupancy, atol=1 / 255 + 1e-12)
    np.testing.assert_allclose(back.lower_xy, band.lower_xy)
    assert len(np.unique(back.occupancy[back.known])) > 3  # grades, not three levels


def test_evo_associates_every_pose_and_matches_coopmaps_ate(dataset: Path) -> None:
    from evo.core import metrics, sync
    from evo.tools import file_interface

    ours = evaluate(dataset)
    for robot in ("a", "b"):
        truth = file_interface.read_tum_trajectory_file(
            str(dataset / "ground_truth" / f"{robot}.tum")
        )
        estimate = file_interface.read_tum_trajectory_file(
            str(dataset / "result" / "poses" / f"{robot}.tum")
        )
        truth, matched = sync.associate_trajectories(truth, estimate)
        assert matched.num_poses == estimate.num_poses == ours["robots"][robot]["poses"]
        ape = metrics.APE(metrics.PoseRelation.translation_part)
        ape.process_data((truth, matched))  # no alignment: the gauge fixes the map frame
        rmse = ape.get_statistic(metrics.StatisticsType.rmse)
        assert rmse == pytest.approx(ours["robots"][robot]["ate_m"], abs=1e-3)
        assert 1e-4 < rmse < 0.05


def test_pose_stamps_lie_on_the_odometry_grid_inside_the_standstill(dataset: Path) -> None:
    events = [json.loads(line) for line in (dataset / "events.jsonl").read_text().splitlines()]
    for robot in ("a", "b"):
        stamps, _ = read_tum(dataset / "result" / "poses" / f"{robot}.tum")
        odometry, _ = read_tum(dataset / "robots" / robot / "odometry.tum")
        arrivals = [0.0] + [
            e["t_s"] for e in events if e["event"] == "move" and e["robot"] == robot
        ]
        departures = [e["start_s"] for e in events if e["event"] == "move" and e["robot"] == robot]
        assert len(stamps) == len(arrivals)
        assert np.isin(stamps, odometry).all()
        waited = stamps - np.array(arrivals)
        assert (waited >= 0.5 - 1e-6).all()
        assert (waited < 0.6 + 1e-6).all()
        assert (stamps[:-1] < np.array(departures)).all()


def test_map_bt_opens_in_octomap_with_the_occupied_cells_of_the_map(dataset: Path) -> None:
    import pyoctomap

    grid = load_map(dataset / "result" / "map.npz")
    tree = pyoctomap.OcTree(0.5)
    assert tree.readBinary(str(dataset / "result" / "map.bt"))
    res = tree.getResolution()
    assert res == pytest.approx(grid.resolution_m)
    occupied: set[tuple[int, int, int]] = set()
    free = 0
    for leaf in tree.begin_leafs():
        edge = round(leaf.getSize() / res)
        corner = np.rint((np.array(leaf.getCoordinate()) - leaf.getSize() / 2) / res).astype(int)
        if not tree.isNodeOccupied(leaf.current_node):
            free += edge**3
            continue
        for offset in np.ndindex(edge, edge, edge):
            occupied.add(tuple(int(v) for v in corner + offset))
    expected, _ = grid.occupied()
    assert occupied == {tuple(c) for c in expected.tolist()}
    assert free + len(occupied) == grid.known_count()


def test_covariances_are_the_marginals_of_every_pose(dataset: Path) -> None:
    result = dataset / "result"
    document = json.loads((result / "covariances.json").read_text())
    assert (document["format"], document["version"]) == ("coopmap.covariances", 1)
    config = load_config(result / "config.yaml")
    prior = np.array([config.graph.prior_sigma_m] * 2 + [config.graph.prior_sigma_rad]) ** 2
    for robot, entry in document["robots"].items():
        stamps, _ = read_tum(result / "poses" / f"{robot}.tum")
        covariances = np.array(entry["covariances"])
        assert covariances.shape == (len(stamps), 3, 3)
        assert entry["indices"] == list(range(len(stamps)))
        np.testing.assert_allclose(covariances, covariances.transpose(0, 2, 1), atol=1e-15)
        assert (np.linalg.eigvalsh(covariances) > 0).all()
    gauge = np.diag(np.array(document["robots"]["a"]["covariances"][0]))
    # The gauge is pinned by its prior: other factors can only tighten it a little.
    assert ((gauge <= prior * (1 + 1e-9)) & (gauge > 0.5 * prior)).all()
    later = np.array(document["robots"]["b"]["covariances"])
    assert (later[:, 0, 0] > 10 * gauge[0]).all()
    assert math.sqrt(later[:, 0, 0].max()) < 0.1


def test_every_result_draws_a_sweep_and_the_relocalization_pdfs(dataset: Path) -> None:
    report = json.loads((dataset / "result" / "report.json").read_text())
    figures = report["figures"]
    relocalizations = report["global_localization"]["relocalization"]
    # essex_lab: two robots relocalized after the changes, in the ceiling and the floor band;
    # the ceiling band's are drawn
    assert len(relocalizations) == 4
    expected = {
        f"pdf_relocalization_{r['station']}_map_ceiling.png"
        for r in relocalizations
        if r["band"] == "ceiling"
    }
    assert len(expected) == 2
    assert set(figures["pdfs"]) == expected
    assert figures["pdfs_not_drawn"] == 0
    assert figures["sweep"] == {"file": "sweep.png", "pose": "a0"}
    folder = dataset / "result" / "figures"
    for name in [*figures["pdfs"], "sweep.png", "ceiling_trajectories.png", "map_cubes.png"]:
        assert (folder / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    markdown = (dataset / "result" / "report.md").read_text()
    assert "figures/sweep.png" in markdown
    assert all(n in markdown for n in figures["pdfs"])


def test_evaluate_draws_the_ceiling_under_the_true_walls(dataset: Path) -> None:
    metrics = evaluate(dataset)
    assert metrics["figures"] == {"ceiling_truth": "ceiling_truth.png"}
    path = dataset / "result" / "figures" / "ceiling_truth.png"
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def plain(dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, BatchOutput]:
    out = tmp_path_factory.mktemp("plain") / "plain"
    return out, run_batch(dataset, out, figures=False)


def test_a_result_without_figures_is_the_same_result_without_them(
    dataset: Path, plain: tuple[Path, BatchOutput]
) -> None:
    out, output = plain
    assert not (out / "figures").exists()
    assert output.report["figures"] == {"drawn": False}
    assert json.loads((out / "report.json").read_text())["figures"] == {"drawn": False}
    assert "figures/" not in (out / "report.md").read_text()
    for robot in ("a", "b"):
        drawn = read_tum(dataset / "result" / "poses" / f"{robot}.tum")
        plain_poses = read_tum(out / "poses" / f"{robot}.tum")
        np.testing.assert_array_equal(plain_poses[1], drawn[1])
    assert (out / "map.npz").read_bytes() == (dataset / "result" / "map.npz").read_bytes()


def test_figures_drawn_beside_a_worker_equal_those_drawn_alone(
    dataset: Path, plain: tuple[Path, BatchOutput], tmp_path: Path
) -> None:
    _, output = plain
    ceiling = cut_ceiling_band(output.grid, load_config(dataset / "result" / "config.yaml"))
    alone = write_figures(output, ceiling, tmp_path / "alone")
    with figure_worker() as worker:
        assert worker is not None
        shared = write_figures(output, ceiling, tmp_path / "shared", worker)
    assert shared == alone
    names = sorted(p.name for p in (tmp_path / "alone").iterdir())
    assert len(names) == 3 + len(alone["pdfs"])
    assert len(alone["pdfs"]) == 2
    assert sorted(p.name for p in (tmp_path / "shared").iterdir()) == names
    for name in names:
        assert (tmp_path / "shared" / name).read_bytes() == (tmp_path / "alone" / name).read_bytes()
    # The result's own figures (drawn with a worker by run_batch) are the same pictures.
    for name in names:
        drawn = (dataset / "result" / "figures" / name).read_bytes()
        assert drawn == (tmp_path / "alone" / name).read_bytes(), name
