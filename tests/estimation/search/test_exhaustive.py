"""The exhaustive search: exact against the per-pose loop, accurate, honest about ambiguity."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from estimation.errors import EstimationError
from estimation.posepdf import PosePdf
from estimation.search.correlate import correlate_all, score_poses_loop
from estimation.search.exhaustive import (
    SearchParams,
    SearchResult,
    best_pose,
    overlap_fraction,
    search,
    windowed_search,
)
from estimation.search.lattice import Metric, match_values, pose_lattice, yaw_lattice
from estimation.search.peak import normalise, refine_peak
from estimation.search.scenes import (
    corridor,
    distinctive_room,
    local_view,
    random_building,
    rasterise,
)
from mapping.band import Band

METRIC = Metric(free_weight=0.5, occupied_level=0.3)


def random_band(rng: np.random.Generator, shape: tuple[int, int], origin: list[float]) -> Band:
    occupancy = rng.random(shape)
    known = rng.random(shape) < 0.8
    return Band(
        occupancy=np.where(known, occupancy, 0.0),
        known=known,
        lower_xy=np.array(origin),
        resolution_m=0.1,
    )


def pose_error(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    d = np.asarray(estimate, dtype=float) - truth
    return math.hypot(d[0], d[1]), abs(math.degrees((d[2] + math.pi) % (2 * math.pi) - math.pi))


@pytest.fixture(scope="module")
def room() -> tuple[Band, object]:
    scene = distinctive_room(8.0)
    return rasterise(scene, np.zeros(3), (-0.5, -0.5), (66, 90), 0.1), scene


# -- exactness ---------------------------------------------------------------------------------

CASES = [
    # local grid origin (cells on a corner: quarter-turn shortcut), window, angular step
    pytest.param([-0.6, -0.5], None, 10.0, id="corner-aligned"),
    pytest.param([-0.55, -0.45], None, 3.0, id="centre-aligned-ties-at-30-45-60"),
    pytest.param([0.33, -0.71], None, 10.0, id="off-lattice-direct"),
    pytest.param([-0.6, -0.5], (1.5, 2.2, -1.5, -0.3), 5.0, id="window"),
    pytest.param([-0.4, -0.4], (0.2, 5.0, -1.0, 0.0), 7.2, id="corner-window-not-quarter"),
]


@pytest.mark.parametrize(("origin", "window", "step_deg"), CASES)
def test_fast_search_equals_the_per_pose_loop(
    origin: list[float], window: tuple[float, float, float, float] | None, step_deg: float
) -> None:
    rng = np.random.default_rng(7)
    local = random_band(rng, (9, 11), origin)
    global_ = random_band(rng, (19, 24), [1.0, -2.0])
    x_m, y_m, _ = pose_lattice(local, global_, window)
    yaw = yaw_lattice(math.radians(step_deg))
    fast = correlate_all(local, global_, x_m, y_m, yaw, METRIC, workers=2)
    slow = score_poses_loop(local, global_, x_m, y_m, yaw, METRIC)
    assert fast.shape == slow.shape == (len(yaw), len(y_m), len(x_m))
    scale = np.abs(match_values(local, METRIC)).sum()
    assert np.abs(fast - slow).max() <= 1e-6 * scale
    assert np.abs(slow).max() > 0.1 * scale  # not a trivially empty comparison
    beta = 2.0
    expected = np.exp(beta * (slow - slow.max()))
    expected /= expected.sum()
    np.testing.assert_allclose(normalise(fast, beta), expected, rtol=1e-4, atol=1e-12)


def test_exactness_holds_on_a_structured_scene_at_one_degree(room: tuple[Band, object]) -> None:
    global_, scene = room
    rng = np.random.default_rng(3)
    local = local_view(scene, np.array([4.03, 2.51, 0.6]), 1.2, 0.1, rng, noise=0.1)
    window = (3.0, 5.0, 1.8, 3.2)
    x_m, y_m, _ = pose_lattice(local, global_, window)
    yaw = yaw_lattice(math.radians(1.0))
    fast = correlate_all(local, global_, x_m, y_m, yaw, METRIC, workers=1)
    slow = score_poses_loop(local, global_, x_m, y_m, yaw, METRIC)
    assert np.abs(fast - slow).max() <= 1e-6 * np.abs(match_values(local, METRIC)).sum()


def test_lattice_lands_local_cell_centres_on_global_centres() -> None:
    rng = np.random.default_rng(0)
    local = random_band(rng, (4, 4), [-0.23, 0.41])
    global_ = random_band(rng, (10, 10), [0.05, -0.02])
    x_m, y_m, _ = pose_lattice(local, global_)
    # At θ = 0, a local centre (−0.23 + 0.05) + x lands at a global centre 0.05 + 0.1·(i + ½).
    offsets = (x_m + (-0.23 + 0.05) - 0.05) / 0.1 - 0.5
    assert np.allclose(offsets, np.round(offsets))
    assert len(x_m) == len(y_m) == 10


# -- the peak ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "truth",
    [
        [4.03, 2.46, math.radians(0.4)],
        [5.47, 3.12, math.radians(61.7)],
        [3.61, 2.78, math.radians(-133.3)],
    ],
)
def test_refinement_recovers_sub_cell_shifts(room: tuple[Band, object], truth: list[float]) -> None:
    global_, scene = room
    truth_pose = np.array(truth)
    local = local_view(scene, truth_pose, 4.0, 0.1, np.random.default_rng(1))
    result = search(local, global_, SearchParams(), (2.5, 7.0, 1.0, 4.5))
    lattice_m, lattice_deg = pose_error(result.lattice_pose, truth_pose)
    error_m, error_deg = pose_error(result.pose, truth_pose)
    # The lattice is off by up to a cell or two; the refinement lands within a fraction.
    # (The scene is rasterised at 1/3 of a cell: near 0° the two grids alias, hence 0.4°.)
    assert 0.02 < lattice_m < 0.2
    assert lattice_deg <= 2.0 + 1e-9
    assert error_m < min(0.02, 0.6 * lattice_m)
    assert error_deg < 0.4


def test_refine_peak_finds_the_vertex_of_a_quadratic() -> None:
    t, y, x = np.meshgrid(np.arange(7), np.arange(6), np.arange(8), indexing="ij")
    centre = np.array([3.3, 2.6, 3.8])  # (x, y, t)
    d = np.stack([x - centre[0], y - centre[1], t - centre[2]], -1)
    H = np.array([[2.0, 0.3, 0.1], [0.3, 1.5, -0.2], [0.1, -0.2, 1.0]])
    scores = -np.einsum("...i,ij,...j->...", d, H, d)
    step = refine_peak(scores, (4, 3, 3), yaw_wraps=False)
    np.testing.assert_allclose(np.array([3, 3, 4]) + step, centre, atol=1e-9)


def test_peak_ratio_and_covariance_agree_with_posepdf() -> None:
    rng = np.random.default_rng(5)
    local = random_band(rng, (7, 7), [-0.3, -0.3])
    global_ = random_band(rng, (25, 25), [0.0, 0.0])
    params = SearchParams(beta=0.5, angular_resolution_rad=math.radians(5.0), peak_radius_m=0.3)
    result = search(local, global_, params)
    pdf = result.pdf
    assert isinstance(pdf, PosePdf)
    assert pdf.best_index() == result.best_index
    radii = (params.peak_radius_m, params.peak_radius_rad)
    assert result.peak_ratio == pytest.approx(pdf.peak_ratio(*radii), rel=1e-4)
    np.testing.assert_allclose(result.covariance, pdf.covariance(*radii), rtol=1e-4, atol=1e-12)
    assert result.prob.sum() == pytest.approx(1.0, abs=1e-5)


def corridor_search() -> tuple[SearchResult, np.ndarray]:
    """A 3 m view in a featureless 20 m corridor searched against it, and its true pose."""
    scene = corridor(20.0, 2.4)
    global_ = rasterise(scene, np.zeros(3), (0.0, -0.5), (34, 200), 0.1)
    truth = np.array([9.0, 1.2, 0.3])
    local = local_view(scene, truth, 3.0, 0.1, np.random.default_rng(2), noise=0.05)
    return search(local, global_, SearchParams()), truth


def test_dominance_is_low_in_a_symmetric_corridor() -> None:
    result, truth = corridor_search()
    assert result.peak_ratio < 1.5
    # The PDF spreads along the corridor and over both directions.
    marginal_x = result.prob.sum(axis=(0, 1))
    assert (marginal_x > 1e-3 * marginal_x.max()).sum() > 50
    yaw_mass = result.prob.sum(axis=(1, 2))
    near = np.abs((result.yaw_rad - truth[2] + math.pi) % (2 * math.pi) - math.pi) < 0.2
    flipped = np.abs((result.yaw_rad - truth[2]) % (2 * math.pi) - math.pi) < 0.2
    assert yaw_mass[near].sum() > 0.1
    assert yaw_mass[flipped].sum() > 0.1


def test_the_modes_of_a_corridor_are_distinct_and_most_probable_first() -> None:
    result, _ = corridor_search()
    radius_m, radius_rad = 0.5, math.radians(10.0)
    modes = result.modes(5, radius_m, radius_rad)
    assert len(modes) == 5
    assert np.array_equal(modes[0], result.pose)
    for i, a in enumerate(modes):
        for b in modes[i + 1 :]:
            apart = abs(math.remainder(a[2] - b[2], 2 * math.pi))
            assert math.hypot(a[0] - b[0], a[1] - b[1]) > radius_m or apart > radius_rad
    pdf = result.pdf

    def density(pose: np.ndarray) -> float:
        ix = int(np.argmin(np.abs(result.x_m - pose[0])))
        iy = int(np.argmin(np.abs(result.y_m - pose[1])))
        it = int(
            np.argmin(
                np.abs(np.remainder(result.yaw_rad - pose[2] + math.pi, 2 * math.pi) - math.pi)
            )
        )
        return float(pdf.prob[it, iy, ix])

    later = [density(m) for m in modes[1:]]
    assert later == sorted(later, reverse=True)
    assert len(result.modes(1, radius_m, radius_rad)) == 1


def test_dominance_is_high_in_a_distinctive_room(room: tuple[Band, object]) -> None:
    global_, scene = room
    truth = np.array([4.6, 3.0, math.radians(140.0)])
    rng = np.random.default_rng(4)
    local = local_view(scene, truth, 3.5, 0.1, rng, noise=0.1, drop_fraction=0.2)
    result = search(local, global_, SearchParams())
    assert result.peak_ratio > 1e3
    error_m, error_deg = pose_error(result.pose, truth)
    assert error_m < 0.05
    assert error_deg < 0.5
    sigma = np.sqrt(np.diag(result.covariance))
    assert 0.02 < sigma[0] < 0.2
    assert 0.02 < sigma[1] < 0.2


# -- windowed search ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def building() -> tuple[Band, object]:
    scene = random_building(np.random.default_rng(11), 16.0)
    return rasterise(scene, np.zeros(3), (0.0, 0.0), (160, 160), 0.1), scene


def test_windowed_search_stops_at_the_first_window_with_a_good_prior(
    building: tuple[Band, object],
) -> None:
    global_, scene = building
    truth = np.array([7.2, 8.9, 1.1])
    local = local_view(scene, truth, 5.0, 0.1, np.random.default_rng(0), noise=0.1)
    out = windowed_search(local, global_, SearchParams(), truth[:2] + 0.4, 2.0, 40.0)
    assert len(out.steps) == 1
    assert out.dominant
    assert out.result.x_m.size == out.result.y_m.size == 20
    assert pose_error(out.result.pose, truth)[0] < 0.05


def test_windowed_search_grows_until_the_peak_is_dominant(building: tuple[Band, object]) -> None:
    global_, scene = building
    truth = np.array([5.1, 11.3, -2.0])
    local = local_view(scene, truth, 5.0, 0.1, np.random.default_rng(0), noise=0.1)
    prior = truth[:2] + np.array([3.1, -2.6])  # 4 m off: the first windows miss the truth
    out = windowed_search(local, global_, SearchParams(), prior, 1.0, 40.0)
    sides = [step.side_m for step in out.steps]
    assert sides[:4] == [1.0, 2.0, 4.0, 8.0]
    assert len(sides) >= 4
    assert not any(step.peak_ratio >= 2.0 and not step.on_edge for step in out.steps[:-1])
    assert out.dominant
    assert not out.steps[-1].covers_map
    error_m, error_deg = pose_error(out.result.pose, truth)
    assert error_m < 0.05
    assert error_deg < 0.5


def test_windowed_search_stops_when_the_map_is_covered() -> None:
    scene = corridor(12.0, 2.4)
    global_ = rasterise(scene, np.zeros(3), (0.0, -0.5), (34, 120), 0.1)
    local = local_view(scene, np.array([6.0, 1.2, 0.0]), 2.0, 0.1, np.random.default_rng(1))
    out = windowed_search(local, global_, SearchParams(), (6.0, 1.2), 2.0, 100.0)
    assert [step.side_m for step in out.steps] == [2.0, 4.0, 8.0, 16.0]
    assert out.steps[-1].covers_map
    assert not out.dominant
    assert len(out.result.x_m) == 120


# -- bad inputs --------------------------------------------------------------------------------


def test_overlap_fraction_counts_local_known_cells_on_known_map_cells() -> None:
    known = np.zeros((10, 20), bool)
    known[:, :10] = True  # the map knows x in [0, 1) only
    global_ = Band(np.zeros((10, 20)), known, np.zeros(2), 0.1)
    local = Band(np.zeros((4, 4)), np.ones((4, 4), bool), np.zeros(2), 0.1)
    assert overlap_fraction(local, global_, np.zeros(3)) == 1.0
    # shifted by 0.8 m: columns at x 0.85 and 0.95 inside, 1.05 and 1.15 on unknown cells
    assert overlap_fraction(local, global_, np.array([0.8, 0.0, 0.0])) == 0.5
    # off the grid entirely
    assert overlap_fraction(local, global_, np.array([5.0, 5.0, 0.0])) == 0.0
    # a half turn about the origin puts every centre at negative x: off the map
    assert overlap_fraction(local, global_, np.array([0.0, 0.0, math.pi])) == 0.0
    # ... and about (0.4, 0.4) it lands on the same 4 × 4 cells
    assert overlap_fraction(local, global_, np.array([0.4, 0.4, math.pi])) == 1.0
    # only the local grid's known cells count
    sparse = Band(np.zeros((4, 4)), np.eye(4, dtype=bool), np.zeros(2), 0.1)
    assert overlap_fraction(sparse, global_, np.array([0.7, 0.0, 0.0])) == 0.75


def test_overlap_fraction_rejects_bad_input() -> None:
    global_ = Band(np.zeros((10, 10)), np.ones((10, 10), bool), np.zeros(2), 0.1)
    empty = Band(np.zeros((4, 4)), np.zeros((4, 4), bool), np.zeros(2), 0.1)
    with pytest.raises(EstimationError, match="no known cell"):
        overlap_fraction(empty, global_, np.zeros(3))
    local = Band(np.zeros((4, 4)), np.ones((4, 4), bool), np.zeros(2), 0.1)
    with pytest.raises(EstimationError, match="3 finite numbers"):
        overlap_fraction(local, global_, np.array([0.0, math.nan, 0.0]))
    with pytest.raises(EstimationError, match="3 finite numbers"):
        overlap_fraction(local, global_, np.zeros(2))
    coarse = Band(np.zeros((4, 4)), np.ones((4, 4), bool), np.zeros(2), 0.2)
    with pytest.raises(EstimationError, match="differs from the map's"):
        overlap_fraction(coarse, global_, np.zeros(3))


def test_empty_scan_grid_is_rejected() -> None:
    rng = np.random.default_rng(0)
    empty = Band(np.zeros((5, 5)), np.zeros((5, 5), bool), np.zeros(2), 0.1)
    with pytest.raises(EstimationError, match="scan grid has no known cell"):
        search(empty, random_band(rng, (10, 10), [0, 0]), SearchParams())
    unknown_map = Band(np.zeros((10, 10)), np.zeros((10, 10), bool), np.zeros(2), 0.1)
    with pytest.raises(EstimationError, match="map grid has no known cell"):
        search(random_band(rng, (5, 5), [0, 0]), unknown_map, SearchParams())


def test_mismatched_resolution_is_rejected() -> None:
    rng = np.random.default_rng(0)
    local = Band(np.zeros((5, 5)), np.ones((5, 5), bool), np.zeros(2), 0.05)
    with pytest.raises(EstimationError, match=r"resolution 0\.05 m differs from the map's 0\.1 m"):
        search(local, random_band(rng, (10, 10), [0, 0]), SearchParams())


def test_window_outside_the_map_is_rejected() -> None:
    rng = np.random.default_rng(0)
    local, global_ = random_band(rng, (5, 5), [0, 0]), random_band(rng, (10, 10), [0, 0])
    with pytest.raises(EstimationError, match="lies outside the map"):
        search(local, global_, SearchParams(), (5.0, 6.0, 0.0, 1.0))
    with pytest.raises(EstimationError, match="lies outside the map"):
        windowed_search(local, global_, SearchParams(), (30.0, 30.0), 2.0, 4.0)


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        ({"angular_resolution_rad": math.radians(7.0)}, "must divide 360"),
        ({"beta": 0.0}, "beta must be a positive number"),
        ({"free_weight": -1.0}, "free_weight must be >= 0"),
        ({"occupied_level": 1.0}, r"occupied_level must lie in \(0, 1\)"),
        ({"dominance_ratio": 0.5}, "dominance_ratio must be >= 1"),
    ],
)
def test_bad_parameters_are_rejected(kwargs: dict[str, float], pattern: str) -> None:
    rng = np.random.default_rng(0)
    local, global_ = random_band(rng, (5, 5), [0, 0]), random_band(rng, (9, 9), [0, 0])

    def attempt() -> None:
        search(local, global_, SearchParams(**kwargs))  # type: ignore[arg-type]

    with pytest.raises(EstimationError, match=pattern):
        attempt()


def test_occupancy_outside_the_unit_interval_is_rejected() -> None:
    rng = np.random.default_rng(0)
    bad = Band(np.full((5, 5), 1.5), np.ones((5, 5), bool), np.zeros(2), 0.1)
    with pytest.raises(EstimationError, match=r"within \[0, 1\]"):
        search(bad, random_band(rng, (9, 9), [0, 0]), SearchParams())


def test_metric_values_free_and_occupied_evidence() -> None:
    occupancy = np.array([[0.0, 0.05, 0.1, 0.15, 0.2, 0.9]])
    known = np.array([[True, True, True, True, True, False]])
    band = Band(occupancy, known, np.zeros(2), 0.1)
    values = match_values(band, Metric(free_weight=0.4, occupied_level=0.1))
    np.testing.assert_allclose(values, [[-0.4, -0.2, 0.0, 0.5, 1.0, 0.0]], atol=1e-12)


def test_best_pose_alone_matches_the_full_search(building: tuple[Band, object]) -> None:
    global_, scene = building
    truth = np.array([9.3, 6.1, 2.4])
    local = local_view(scene, truth, 5.0, 0.1, np.random.default_rng(6), noise=0.1)
    full = search(local, global_, SearchParams())
    pose, score, seconds = best_pose(local, global_, SearchParams())
    assert score == pytest.approx(full.best_score, rel=1e-6)
    np.testing.assert_allclose(pose, full.pose, atol=1e-6)
    assert pose_error(pose, truth)[0] < 0.05
    assert seconds > 0


@pytest.mark.parametrize("beta", [0.005, 0.04, 0.5])
def test_large_pdfs_are_valid_posepdfs(building: tuple[Band, object], beta: float) -> None:
    global_, scene = building
    local = local_view(scene, np.array([8.1, 7.7, 0.9]), 6.0, 0.1, np.random.default_rng(8))
    result = search(local, global_, SearchParams(beta=beta))
    assert abs(float(result.prob.sum(dtype=np.float64)) - 1.0) < 2e-7
    pdf = result.pdf  # PosePdf checks the sum to 1e-6, non-negativity, the lattices
    assert pdf.prob.shape == (360, 160, 160)
    assert pdf.best_index() == result.best_index


# -- dominance beside a prediction --------------------------------------------------------------


def two_mode_result(strong_x: float = 3.0, weak_share: float = 0.2) -> SearchResult:
    """A PDF over x −2…5 m, y −1…1 m, yaw ±5° with a strong mode at (``strong_x``, 0, 0) and
    one ``weak_share`` as high at the origin."""
    x_m, y_m = np.round(np.arange(-2.0, 5.0001, 0.1), 6), np.round(np.arange(-1.0, 1.0001, 0.1), 6)
    yaw_rad = np.radians(np.arange(-5.0, 5.5, 1.0))
    yaw, y, x = np.meshgrid(yaw_rad, y_m, x_m, indexing="ij")

    def bump(cx: float) -> np.ndarray:
        return np.exp(-0.5 * (((x - cx) / 0.1) ** 2 + (y / 0.1) ** 2 + (yaw / 0.02) ** 2))

    prob = (bump(strong_x) + weak_share * bump(0.0)).astype(np.float32)
    prob /= prob.sum()
    best = np.unravel_index(int(np.argmax(prob)), prob.shape)
    t, iy, ix = (int(i) for i in best)
    pose = np.array([x_m[ix], y_m[iy], yaw_rad[t]])
    return SearchResult(x_m=x_m, y_m=y_m, yaw_rad=yaw_rad, scores=None, prob=prob, beta=1.0,
                        best_index=(t, iy, ix), best_score=0.0, pose=pose,
                        covariance=np.diag([0.01, 0.01, 4e-4]), peak_ratio=5.0,
                        seconds=0.0)  # fmt: skip


@pytest.mark.parametrize(
    ("predicted", "sigma_m", "expected"),
    [
        pytest.param([0.0, 0.0, 0.0], 1.0, False, id="prediction-at-the-weak-mode"),
        pytest.param([0.0, 0.0, 0.0], 100.0, True, id="a-prediction-that-says-nothing"),
        pytest.param([3.0, 0.0, 0.0], 1.0, True, id="prediction-at-the-peak"),
        pytest.param([1.5, 0.0, 0.0], 1.0, True, id="prediction-halfway"),
        pytest.param([1.0, 0.0, 0.0], 1.0, False, id="nearer-the-weak-mode: 5x is too little"),
    ],
)
def test_a_peak_must_stay_dominant_beside_the_prediction(
    predicted: list[float], sigma_m: float, expected: bool
) -> None:
    result = two_mode_result()
    covariance = np.diag([sigma_m**2, sigma_m**2, math.radians(5.0) ** 2])
    assert result.dominant_given(np.array(predicted), covariance, SearchParams()) is expected


def test_the_prediction_is_taken_in_its_own_axes() -> None:
    """A prediction turned 90° whose uncertainty lies along its own x (the world's y) does not
    excuse a peak 3 m away along the world's x."""
    result = two_mode_result()
    along_own_x = np.diag([100.0**2, 0.5**2, math.radians(5.0) ** 2])
    turned = np.array([0.0, 0.0, math.pi / 2])
    result_turned = dataclasses.replace(result, yaw_rad=result.yaw_rad + math.pi / 2)
    assert not result_turned.dominant_given(turned, along_own_x, SearchParams())
    assert result.dominant_given(np.zeros(3), along_own_x, SearchParams())


def test_a_prediction_breaks_the_tie_of_a_repeating_corridor() -> None:
    """Pillars every 3.6 m along a plain corridor: a 2 m view matches every repeat alike, so
    the scores alone are not dominant; with the robot's prediction (σ 1 m) the repeat it is
    at wins, and a prediction one repeat away refuses the peak the scores picked."""
    period = 3.6
    scene = corridor(22.0, 2.4)
    pillars = [[1.0 + period * k, 0.35, 0.4, 0.4, 0.0] for k in range(6)]
    scene = dataclasses.replace(scene, boxes=np.array(pillars))
    global_ = rasterise(scene, np.zeros(3), (0.0, -0.5), (34, 220), 0.1)
    truth = np.array([8.2 + 0.05, 1.2, 0.02])
    local = local_view(scene, truth, 2.0, 0.1, np.random.default_rng(4), noise=0.02)
    params = SearchParams()
    result = search(local, global_, params, window_m=(2.0, 16.0, 0.8, 1.6))
    assert not result.is_dominant(params.dominance_ratio)
    picked = result.lattice_pose
    covariance = np.diag([1.0, 1.0, math.radians(3.0) ** 2])
    assert result.dominant_given(picked, covariance, params)
    repeat = picked + np.array([period if picked[0] < 9.0 else -period, 0.0, 0.0])
    assert not result.dominant_given(repeat, covariance, params)


@pytest.mark.parametrize(
    ("predicted", "covariance"),
    [
        (np.zeros(2), np.eye(3)),
        (np.zeros(3), np.eye(2)),
        (np.array([0.0, math.nan, 0.0]), np.eye(3)),
        (np.zeros(3), np.full((3, 3), math.inf)),
    ],
)
def test_a_bad_prediction_is_refused(predicted: np.ndarray, covariance: np.ndarray) -> None:
    with pytest.raises(EstimationError, match="prediction"):
        two_mode_result().dominant_given(predicted, covariance, SearchParams())


def test_a_pdf_without_mass_is_never_dominant() -> None:
    result = two_mode_result()
    empty = dataclasses.replace(result, prob=np.zeros_like(result.prob))
    assert not empty.dominant_given(np.zeros(3), np.eye(3), SearchParams())
