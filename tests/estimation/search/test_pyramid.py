"""The coarse-to-fine search: the exhaustive search's answer, an honest unevaluated mass."""

from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest

from estimation.errors import EstimationError
from estimation.search.exhaustive import SearchParams, search
from estimation.search.lattice import Metric, match_values
from estimation.search.pyramid import TiledResult, coarsen, search_coarse_to_fine
from estimation.search.scenes import local_view, office_floor, random_building, rasterise
from mapping.band import Band

PARAMS = SearchParams(angular_resolution_rad=math.radians(4.0))


def scene_pair(seed: int, kind: str, side_m: float, radius_m: float) -> tuple[Band, Band]:
    rng = np.random.default_rng(seed)
    scene = office_floor(rng, side_m) if kind == "office" else random_building(rng, side_m)
    cells = round(side_m / 0.1)
    global_ = rasterise(scene, np.zeros(3), (0.0, 0.0), (cells, cells), 0.1)
    truth = np.array([rng.uniform(0.3, 0.7) * side_m, rng.uniform(0.3, 0.7) * side_m,
                      rng.uniform(-math.pi, math.pi)])  # fmt: skip
    local = local_view(scene, truth, radius_m, 0.1, rng, noise=0.1, drop_fraction=0.2,
                       flip_fraction=0.02)  # fmt: skip
    return local, global_


def evaluated(result: TiledResult) -> np.ndarray:
    out = np.zeros((len(result.yaw_rad), len(result.y_m), len(result.x_m)), dtype=bool)
    for p in result.patches:
        _, rows, cols = p.mask.shape
        out[p.t, p.y0 : p.y0 + rows, p.x0 : p.x0 + cols] |= p.mask
    return out


# -- the exhaustive search's answer ------------------------------------------------------------

CASES = [
    # seed, scene, map side, view radius, coarse factor
    pytest.param(1, "office", 24.0, 8.0, 4, id="office-8m-view-F4"),
    pytest.param(2, "office", 24.0, 8.0, 2, id="office-8m-view-F2"),
    pytest.param(3, "building", 20.0, 6.0, 4, id="rooms-6m-view-F4"),
    pytest.param(4, "building", 20.0, 6.0, 3, id="rooms-6m-view-F3"),
    # Views too small for a sharp PDF: the coarse level keeps much, the mass left is larger.
    pytest.param(5, "building", 16.0, 3.0, 4, id="rooms-3m-view-broad"),
    pytest.param(6, "office", 16.0, 2.5, 2, id="office-2.5m-view-broad"),
]


@pytest.mark.parametrize(("seed", "kind", "side", "radius", "factor"), CASES)
def test_same_lattice_pose_pose_and_covariance_as_the_exhaustive_search(
    seed: int, kind: str, side: float, radius: float, factor: int
) -> None:
    local, global_ = scene_pair(seed, kind, side, radius)
    whole = search(local, global_, PARAMS)
    tiled = search_coarse_to_fine(local, global_, PARAMS, coarse_factor=factor)
    assert tiled.best_index == whole.best_index
    assert tiled.best_score == pytest.approx(whole.best_score, rel=1e-5)
    assert np.allclose(tiled.pose, whole.pose, atol=1e-6)
    assert np.allclose(tiled.covariance, whole.covariance, rtol=1e-3, atol=1e-12)
    # The peak ratio is never above the exhaustive one (capped by the unevaluated mass).
    assert tiled.peak_ratio <= whole.peak_ratio * (1 + 1e-3)
    if tiled.unevaluated_mass < 1e-4:
        assert tiled.is_dominant(2.0) == whole.is_dominant(2.0)


@pytest.mark.parametrize("score", ["centred", "excess"])
def test_the_overlap_free_scores_give_the_exhaustive_searchs_answer(score: str) -> None:
    # The crops of the fine level keep the whole map's mean: the fine scores are the same.
    local, global_ = scene_pair(3, "building", 20.0, 6.0)
    params = SearchParams(angular_resolution_rad=math.radians(4.0), score=score)
    whole = search(local, global_, params)
    tiled = search_coarse_to_fine(local, global_, params, coarse_factor=4)
    assert tiled.best_index == whole.best_index
    assert tiled.best_score == pytest.approx(whole.best_score, rel=1e-5)
    assert np.allclose(tiled.pose, whole.pose, atol=1e-6)
    assert np.allclose(tiled.covariance, whole.covariance, rtol=1e-3, atol=1e-12)
    agreement = search(local, global_, PARAMS)
    assert whole.best_score != pytest.approx(agreement.best_score, rel=1e-3)  # another score


@pytest.mark.parametrize(("seed", "kind", "side", "radius", "factor"), CASES)
def test_unevaluated_mass_bounds_the_exhaustive_pdf_outside_the_patches(
    seed: int, kind: str, side: float, radius: float, factor: int
) -> None:
    local, global_ = scene_pair(seed, kind, side, radius)
    whole = search(local, global_, PARAMS)
    tiled = search_coarse_to_fine(local, global_, PARAMS, coarse_factor=factor)
    inside = evaluated(tiled)
    assert tiled.poses_evaluated == int(inside.sum()) < tiled.poses
    outside = float(whole.prob[~inside].sum(dtype=np.float64))
    assert outside <= tiled.unevaluated_mass + 1e-7
    # Inside, the probabilities are the exhaustive ones renormalised over the patches.
    dense = tiled.dense_prob()
    assert float(dense.sum(dtype=np.float64)) == pytest.approx(1.0, abs=1e-5)
    assert float(dense[~inside].max()) == 0.0
    variation = 0.5 * float(np.abs(dense - whole.prob).sum(dtype=np.float64))
    assert variation <= outside + 1e-4
    marginal = tiled.position_marginal()
    assert np.allclose(marginal, dense.sum(axis=0, dtype=np.float64), atol=1e-7)


def test_a_sharp_pdf_is_evaluated_on_a_small_part_of_the_lattice() -> None:
    local, global_ = scene_pair(1, "office", 24.0, 8.0)
    tiled = search_coarse_to_fine(local, global_, PARAMS, coarse_factor=4, mass_tolerance=1e-6)
    assert tiled.unevaluated_mass <= 2e-6
    assert tiled.poses_evaluated < 0.01 * tiled.poses


def test_a_tighter_tolerance_evaluates_more_and_leaves_less() -> None:
    local, global_ = scene_pair(5, "building", 16.0, 3.0)
    loose = search_coarse_to_fine(local, global_, PARAMS, coarse_factor=4, mass_tolerance=1e-2)
    tight = search_coarse_to_fine(local, global_, PARAMS, coarse_factor=4, mass_tolerance=1e-8)
    assert tight.poses_evaluated > loose.poses_evaluated
    assert tight.unevaluated_mass < loose.unevaluated_mass


# -- the coarse level --------------------------------------------------------------------------


def test_coarse_values_are_the_means_of_the_fine_values() -> None:
    rng = np.random.default_rng(0)
    known = rng.random((10, 14)) < 0.7
    band = Band(occupancy=np.where(known, rng.random((10, 14)), 0.0), known=known,
                lower_xy=np.array([-0.5, 0.3]), resolution_m=0.1)  # fmt: skip
    metric = Metric()
    coarse = coarsen(band, 4, metric)
    assert coarse.shape == (3, 4)
    assert coarse.resolution_m == pytest.approx(0.4)
    assert np.array_equal(coarse.lower_xy, band.lower_xy)
    padded = np.zeros((12, 16))
    padded[:10, :14] = match_values(band, metric)
    means = padded.reshape(3, 4, 4, 4).mean(axis=(1, 3))
    assert np.allclose(match_values(coarse, metric), means, atol=1e-12)


# -- degenerate inputs -------------------------------------------------------------------------


def test_empty_scan_unknown_map_nan_and_bad_settings_are_one_line_errors() -> None:
    local, global_ = scene_pair(3, "building", 12.0, 3.0)
    empty = Band(occupancy=np.zeros((20, 20)), known=np.zeros((20, 20), dtype=bool),
                 lower_xy=np.array([-1.0, -1.0]), resolution_m=0.1)  # fmt: skip
    with pytest.raises(EstimationError, match="scan grid has no known cell"):
        search_coarse_to_fine(empty, global_, PARAMS)
    unknown = Band(occupancy=np.zeros(global_.shape), known=np.zeros(global_.shape, dtype=bool),
                   lower_xy=global_.lower_xy, resolution_m=0.1)  # fmt: skip
    with pytest.raises(EstimationError, match="map grid has no known cell"):
        search_coarse_to_fine(local, unknown, PARAMS)
    nan = np.array(global_.occupancy, dtype=float)
    nan[5, 5] = np.nan
    broken = Band(occupancy=nan, known=np.ones(global_.shape, dtype=bool),
                  lower_xy=global_.lower_xy, resolution_m=0.1)  # fmt: skip
    with pytest.raises(EstimationError, match=r"must lie within \[0, 1\]"):
        search_coarse_to_fine(local, broken, PARAMS)
    with pytest.raises(EstimationError, match="coarse_factor must be >= 1"):
        search_coarse_to_fine(local, global_, PARAMS, coarse_factor=0)
    with pytest.raises(EstimationError, match="mass_tolerance must lie in"):
        search_coarse_to_fine(local, global_, PARAMS, mass_tolerance=float("nan"))


def test_a_lattice_beyond_the_limit_is_refused_before_any_large_allocation() -> None:
    n = 2500  # 6.25 M positions × 360 rotations: 2.25 G poses
    band = Band(occupancy=np.zeros((n, n)), known=np.ones((n, n), dtype=bool),
                lower_xy=np.zeros(2), resolution_m=0.1)  # fmt: skip
    local, _ = scene_pair(3, "building", 12.0, 3.0)
    tracemalloc.start()
    with pytest.raises(EstimationError, match=r"would cover 2,250,000,000 poses"):
        search_coarse_to_fine(local, band, SearchParams())
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 20e6
