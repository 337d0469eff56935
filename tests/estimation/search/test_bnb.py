"""The best pose alone by branch and bound: the exhaustive search's argmax, from true bounds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimation.errors import EstimationError
from estimation.search import bnb as search_bnb
from estimation.search.bnb import LatticeBest, lattice_best, lattice_scores, pose_bounds
from estimation.search.correlate import correlate_all, score_poses_loop
from estimation.search.exhaustive import SearchParams, best_pose, search
from estimation.search.lattice import Metric, match_values, pose_lattice, yaw_lattice
from estimation.search.scenes import Scene, corridor, local_view, random_building, rasterise
from mapping.band import Band

PARAMS = SearchParams(angular_resolution_rad=math.radians(2.0))
ONLY_BOUNDS = math.inf  # fft_share: never hand over to the FFT search


def moved(band: Band, shift_m: tuple[float, float]) -> Band:
    """The same cells, in a frame shifted by ``shift_m``."""
    return Band(band.occupancy, band.known, band.lower_xy + np.asarray(shift_m), 0.1)


def random_band(rng: np.random.Generator, shape: tuple[int, int], origin: list[float]) -> Band:
    occupancy = rng.random(shape)
    known = rng.random(shape) < 0.8
    return Band(np.where(known, occupancy, 0.0), known, np.array(origin), 0.1)


@pytest.fixture(scope="module")
def building() -> tuple[Band, Scene]:
    scene = random_building(np.random.default_rng(5), 8.0)
    return rasterise(scene, np.zeros(3), (0.0, 0.0), (80, 80), 0.1), scene


def assert_exhaustive_argmax(
    local: Band,
    global_: Band,
    params: SearchParams = PARAMS,
    window: tuple[float, float, float, float] | None = None,
    fft_share: float = ONLY_BOUNDS,
) -> LatticeBest:
    """lattice_best gives the argmax of the full search's scores: the same lattice pose, or one
    whose score ties with it within the FFT's round-off; its score is the exact one."""
    x_m, y_m, _ = pose_lattice(local, global_, window)
    yaw = yaw_lattice(params.angular_resolution_rad)
    scores = correlate_all(local, global_, x_m, y_m, yaw, params.metric)
    best = lattice_best(local, global_, x_m, y_m, yaw, params.metric, fft_share=fft_share)
    tolerance = 1e-6 * np.abs(match_values(local, params.metric)).sum()
    top = float(scores.max())
    assert best.score == pytest.approx(top, abs=tolerance)
    assert scores[best.index] >= top - tolerance
    if np.count_nonzero(scores >= top - 2 * tolerance) == 1:
        assert best.index == np.unravel_index(int(np.argmax(scores)), scores.shape)
    at = [np.array([i]) for i in best.index]
    exact = lattice_scores(local, global_, x_m, y_m, yaw, params.metric, *at)
    assert best.score == exact.item()
    return best


# -- the argmax --------------------------------------------------------------------------------


@pytest.mark.parametrize("truth", [[4.1, 3.3, 0.7], [6.3, 1.7, 2.9]], ids=["a", "c"])
def test_branch_and_bound_finds_the_centred_scores_argmax(
    building: tuple[Band, Scene], truth: list[float]
) -> None:
    global_, scene = building
    rng = np.random.default_rng(1)
    local = local_view(scene, np.array(truth), 3.0, 0.1, rng, noise=0.1, drop_fraction=0.2)
    params = SearchParams(angular_resolution_rad=math.radians(2.0), score="centred")
    best = assert_exhaustive_argmax(local, global_, params)
    assert best.pruned
    whole = search(local, global_, params)
    assert best.index == whole.best_index
    assert np.allclose(best_pose(local, global_, params)[0], whole.pose, atol=1e-9)


@pytest.mark.parametrize(
    "truth", [[4.1, 3.3, 0.7], [2.2, 5.9, -2.5], [6.3, 1.7, 2.9]], ids=["a", "b", "c"]
)
def test_branch_and_bound_finds_the_full_searchs_argmax(
    building: tuple[Band, Scene], truth: list[float]
) -> None:
    global_, scene = building
    rng = np.random.default_rng(1)
    local = local_view(scene, np.array(truth), 3.0, 0.1, rng, noise=0.1, drop_fraction=0.2)
    best = assert_exhaustive_argmax(local, global_)
    assert best.pruned
    assert best.blocks_expanded < 0.4 * best.blocks  # the bound prunes
    assert best.quarters_scored < 4 * best.blocks_expanded


@pytest.mark.parametrize(
    ("shift", "window", "step_deg"),
    [
        pytest.param((0.033, -0.071), None, 2.0, id="off-lattice-frame-no-quarter-turns"),
        pytest.param((0.0, 0.0), (2.0, 5.5, 1.0, 4.0), 2.0, id="window"),
        pytest.param((0.033, -0.071), (2.05, 2.9, 1.0, 4.0), 2.0, id="window-off-lattice"),
        pytest.param((5.0, -3.0), None, 2.0, id="frame-far-from-its-cells"),
        pytest.param((0.0, 0.0), None, 7.2, id="50-rotations"),
    ],
)
def test_argmax_on_a_non_square_map(
    building: tuple[Band, Scene],
    shift: tuple[float, float],
    window: tuple[float, float, float, float] | None,
    step_deg: float,
) -> None:
    _, scene = building
    global_ = rasterise(scene, np.zeros(3), (0.03, -0.41), (70, 90), 0.1)
    rng = np.random.default_rng(2)
    local = local_view(scene, np.array([4.1, 3.3, 0.7]), 2.5, 0.1, rng, noise=0.1)
    params = SearchParams(angular_resolution_rad=math.radians(step_deg))
    assert_exhaustive_argmax(moved(local, shift), global_, params, window)


def test_argmax_in_a_symmetric_corridor_is_one_of_the_tied_poses() -> None:
    scene = corridor(12.0, 2.4)
    global_ = rasterise(scene, np.zeros(3), (0.0, -0.5), (34, 120), 0.1)
    local = local_view(scene, np.array([6.0, 1.2, 0.3]), 2.0, 0.1, np.random.default_rng(3))
    assert_exhaustive_argmax(local, global_, SearchParams())


def test_argmax_of_an_all_free_scan_grid(building: tuple[Band, Scene]) -> None:
    global_, _ = building
    free = Band(np.zeros((20, 20)), np.ones((20, 20), bool), np.array([-1.0, -1.0]), 0.1)
    assert_exhaustive_argmax(free, global_)


def test_argmax_with_few_splats_kept_at_once(
    building: tuple[Band, Scene], monkeypatch: pytest.MonkeyPatch
) -> None:
    global_, scene = building
    monkeypatch.setattr(search_bnb, "_SLOTS", 2)  # splats are computed again when needed
    local = local_view(scene, np.array([2.2, 5.9, -2.5]), 3.0, 0.1, np.random.default_rng(6))
    best = assert_exhaustive_argmax(local, global_)
    assert best.rotations_expanded > 2


def test_the_fft_search_answers_where_the_bounds_prune_too_little(
    building: tuple[Band, Scene],
) -> None:
    global_, scene = building
    local = local_view(scene, np.array([4.1, 3.3, 0.7]), 3.0, 0.1, np.random.default_rng(1))
    best = assert_exhaustive_argmax(local, global_, fft_share=0.0)
    assert not best.pruned


def test_the_cap_is_checked_before_the_blocks_are_collected(
    building: tuple[Band, Scene],
) -> None:
    """A small noisy view leaves far more blocks reaching the first best score than the budget
    could expand: the FFT answers after the top block alone, with the same argmax as the
    bounds would find uncapped."""
    global_, scene = building
    rng = np.random.default_rng(2)
    local = local_view(scene, np.array([4.1, 3.3, 0.7]), 2.0, 0.1, rng, noise=0.1,
                       drop_fraction=0.2, flip_fraction=0.02)  # fmt: skip
    capped = assert_exhaustive_argmax(local, global_, fft_share=0.5)  # lattice_best's default
    assert not capped.pruned
    assert capped.blocks_expanded == 1
    uncapped = assert_exhaustive_argmax(local, global_)
    assert uncapped.pruned
    assert uncapped.blocks_expanded > 1000
    assert uncapped.index == capped.index


# -- the bounds and the exact scores -----------------------------------------------------------

BOUND_CASES = [
    pytest.param([-0.6, -0.5], None, 10.0, id="quarter-turns"),
    pytest.param([0.33, -0.71], None, 10.0, id="no-quarter-turns"),
    pytest.param([-0.6, -0.5], (1.5, 2.9, -1.5, -0.3), 5.0, id="window"),
    pytest.param([-0.55, -0.45], None, 3.0, id="centre-aligned-ties-at-45"),
]


@pytest.mark.parametrize(("origin", "window", "step_deg"), BOUND_CASES)
def test_bounds_hold_every_pose_score(
    origin: list[float], window: tuple[float, float, float, float] | None, step_deg: float
) -> None:
    rng = np.random.default_rng(7)
    local = random_band(rng, (9, 11), origin)
    global_ = random_band(rng, (19, 24), [1.0, -2.0])
    metric = Metric(free_weight=0.5, occupied_level=0.3)
    x_m, y_m, _ = pose_lattice(local, global_, window)
    yaw = yaw_lattice(math.radians(step_deg))
    scores = correlate_all(local, global_, x_m, y_m, yaw, metric)
    tolerance = 1e-6 * np.abs(match_values(local, metric)).sum()
    blocks = pose_bounds(local, global_, x_m, y_m, yaw, metric, level=2)
    quarters = pose_bounds(local, global_, x_m, y_m, yaw, metric, level=1)
    assert np.all(blocks >= scores - tolerance)
    assert np.all(quarters >= scores - tolerance)
    # A quarter's windows lie in its block's: its bound is the tighter one.
    assert np.all(quarters <= blocks + tolerance)
    assert np.any(quarters < blocks - 1.0)


def test_exact_scores_equal_the_per_pose_loop(building: tuple[Band, Scene]) -> None:
    global_, scene = building
    local = local_view(scene, np.array([4.1, 3.3, 0.7]), 2.0, 0.1, np.random.default_rng(4))
    local = moved(local, (0.02, 0.05))
    x_m, y_m, _ = pose_lattice(local, global_)
    yaw = yaw_lattice(math.radians(5.0))
    t, y, x = np.array([0, 11, 30]), np.array([0, 17, 79]), np.array([3, 40])
    exact = lattice_scores(local, global_, x_m, y_m, yaw, PARAMS.metric, t, y, x)
    loop = score_poses_loop(local, global_, x_m[x], y_m[y], yaw[t], PARAMS.metric)
    np.testing.assert_allclose(exact, loop, rtol=0.0, atol=1e-9)


# -- best pose ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("shift", "window"),
    [
        pytest.param((0.0, 0.0), None, id="whole-map"),
        pytest.param((0.033, -0.071), (2.0, 6.0, 1.5, 5.0), id="window-off-lattice"),
    ],
)
def test_best_pose_is_the_full_searchs_refined_pose(
    building: tuple[Band, Scene],
    shift: tuple[float, float],
    window: tuple[float, float, float, float] | None,
) -> None:
    global_, scene = building
    truth = np.array([4.1, 3.3, 0.7])
    rng = np.random.default_rng(5)
    local = moved(local_view(scene, truth, 3.0, 0.1, rng, noise=0.1, drop_fraction=0.2), shift)
    full = search(local, global_, PARAMS, window)
    pose, score, seconds = best_pose(local, global_, PARAMS, window)
    assert score == pytest.approx(full.best_score, rel=1e-6)
    np.testing.assert_allclose(pose, full.pose, atol=1e-6)
    c, s = math.cos(truth[2]), math.sin(truth[2])
    frame_xy = truth[:2] - np.array([[c, -s], [s, c]]) @ np.asarray(shift)  # the moved frame
    assert math.hypot(*(pose[:2] - frame_xy)) < 0.05
    assert seconds > 0


def test_best_pose_rejects_what_the_search_rejects(building: tuple[Band, Scene]) -> None:
    global_, _ = building
    empty = Band(np.zeros((5, 5)), np.zeros((5, 5), bool), np.zeros(2), 0.1)
    with pytest.raises(EstimationError, match="scan grid has no known cell"):
        best_pose(empty, global_, PARAMS)
    unknown = Band(np.zeros((10, 10)), np.zeros((10, 10), bool), np.zeros(2), 0.1)
    scan = Band(np.ones((5, 5)), np.ones((5, 5), bool), np.zeros(2), 0.1)
    with pytest.raises(EstimationError, match="map grid has no known cell"):
        best_pose(scan, unknown, PARAMS)
    with pytest.raises(EstimationError, match="lies outside the map"):
        best_pose(scan, global_, PARAMS, (20.0, 21.0, 0.0, 1.0))
