"""The metric's scores: the centred score against its formula, free of the overlap bias."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimation.errors import EstimationError
from estimation.search.correlate import correlate_all, score_poses_loop
from estimation.search.exhaustive import SearchParams, search
from estimation.search.lattice import (
    EDGE,
    Metric,
    match_values,
    pose_lattice,
    value_mean,
    yaw_lattice,
)
from mapping.band import Band

AGREEMENT = Metric(free_weight=0.5, occupied_level=0.3)
CENTRED = Metric(free_weight=0.5, occupied_level=0.3, score="centred")


def random_band(rng: np.random.Generator, shape: tuple[int, int], origin: list[float]) -> Band:
    occupancy = rng.random(shape)
    known = rng.random(shape) < 0.8
    return Band(np.where(known, occupancy, 0.0), known, np.array(origin), 0.1)


def scores_by_loop(
    local: Band, global_: Band, x_m: np.ndarray, y_m: np.ndarray, yaw_rad: np.ndarray, score: str
) -> np.ndarray:
    """Pose by pose, over the local known cells that land on known map cells, written out from
    the agreement values and the known masks: Σ (v_L − m_L)·(v_G − m_G) (``centred``) or
    Σ v_L·v_G − m_L·m_G·N (``excess``)."""
    v_l, v_g = match_values(local, AGREEMENT), match_values(global_, AGREEMENT)
    k_l, k_g = np.asarray(local.known), np.asarray(global_.known)
    m_l, m_g = v_l[k_l].mean(), v_g[k_g].mean()
    rows, cols = np.nonzero(k_l)
    px = local.lower_xy[0] + (cols + 0.5) * 0.1
    py = local.lower_xy[1] + (rows + 0.5) * 0.1
    out = np.zeros((len(yaw_rad), len(y_m), len(x_m)))
    for t, yaw in enumerate(yaw_rad):
        c, s = math.cos(yaw), math.sin(yaw)
        for iy, y in enumerate(y_m):
            for ix, x in enumerate(x_m):
                col = np.floor((x + c * px - s * py - global_.lower_xy[0]) / 0.1 + EDGE)
                row = np.floor((y + s * px + c * py - global_.lower_xy[1]) / 0.1 + EDGE)
                col, row = col.astype(int), row.astype(int)
                on = (col >= 0) & (row >= 0) & (col < k_g.shape[1]) & (row < k_g.shape[0])
                on[on] &= k_g[row[on], col[on]]
                a, b = v_l[rows[on], cols[on]], v_g[row[on], col[on]]
                if score == "centred":
                    out[t, iy, ix] = float(((a - m_l) * (b - m_g)).sum())
                else:
                    out[t, iy, ix] = float((a * b).sum()) - m_l * m_g * int(on.sum())
    return out


@pytest.mark.parametrize("score", ["centred", "excess"])
@pytest.mark.parametrize(
    ("origin", "step_deg"),
    [
        pytest.param([-0.6, -0.5], 10.0, id="quarter-turn-shortcut"),
        pytest.param([0.33, -0.71], 15.0, id="off-lattice-direct"),
    ],
)
def test_fft_scores_equal_a_per_pose_loop_of_the_formula(
    origin: list[float], step_deg: float, score: str
) -> None:
    rng = np.random.default_rng(11)
    local = random_band(rng, (9, 11), origin)
    global_ = random_band(rng, (19, 24), [1.0, -2.0])
    metric = Metric(free_weight=0.5, occupied_level=0.3, score=score)
    x_m, y_m, _ = pose_lattice(local, global_)
    yaw = yaw_lattice(math.radians(step_deg))
    fast = correlate_all(local, global_, x_m, y_m, yaw, metric, workers=2)
    slow = scores_by_loop(local, global_, x_m, y_m, yaw, score)
    scale = float(np.abs(match_values(local, AGREEMENT)).sum())
    assert np.abs(fast - slow).max() <= 1e-5 * scale
    assert np.abs(slow).max() > 0.05 * scale  # not a trivially empty comparison
    assert np.abs(score_poses_loop(local, global_, x_m, y_m, yaw, metric) - slow).max() < 1e-9
    # Another score indeed: the agreement differs by the overlap terms.
    agreement = correlate_all(local, global_, x_m, y_m, yaw, AGREEMENT)
    assert np.abs(agreement - slow).max() > 0.05 * scale


def test_centred_values_have_zero_mean_over_the_known_cells() -> None:
    band = random_band(np.random.default_rng(2), (30, 40), [0.0, 0.0])
    values = match_values(band, CENTRED)
    known = np.asarray(band.known)
    assert abs(values[known].mean()) < 1e-12
    assert (values[~known] == 0.0).all()
    plain = match_values(band, AGREEMENT)
    assert value_mean(band, CENTRED) == pytest.approx(plain[known].mean(), abs=1e-12)
    assert np.allclose(values[known], plain[known] - plain[known].mean(), atol=1e-12)
    # A given centre (a crop of a larger map keeps the map's) replaces the band's own.
    assert np.allclose(match_values(band, CENTRED, 0.25)[known], plain[known] - 0.25)


# -- the overlap bias --------------------------------------------------------------------------


def band_of(occupied: np.ndarray, known: np.ndarray, origin: tuple[float, float]) -> Band:
    return Band(np.where(occupied & known, 1.0, 0.0), known, np.array(origin), 0.1)


@pytest.fixture(scope="module")
def biased_scene() -> tuple[Band, Band, np.ndarray, np.ndarray]:
    """A map whose corner room is known only along its walls, and a wide free hall; a view of
    the corner, free cells all round. At the truth the view's walls land on the map's walls but
    most of its free cells on unknown cells; in the hall all its free cells land on free cells."""
    shape = (60, 100)
    occupied = np.zeros(shape, dtype=bool)
    known = np.zeros(shape, dtype=bool)
    occupied[10, 5:30] = occupied[10:35, 5] = True  # the corner: two walls
    known[8:13, 3:32] = known[8:37, 3:8] = True  # known only within 2 cells of them
    known[5:55, 45:95] = True  # the hall: 50 × 50 free cells
    global_ = band_of(occupied, known, (0.0, 0.0))
    view_occupied = np.zeros((24, 24), dtype=bool)
    view_occupied[2, 2:] = view_occupied[2:, 2] = True
    view = band_of(view_occupied, np.ones((24, 24), dtype=bool), (-0.3, -0.3))
    # View cell (2, 2), centre (−0.05, −0.05) m, sits at map cell (10, 5), centre (0.55, 1.05).
    truth = np.array([0.6, 1.1, 0.0])
    wrong = np.array([6.0, 2.5, 0.0])  # the whole view on the hall's free cells
    return view, global_, truth, wrong


def pose_scores(local: Band, global_: Band, metric: Metric, poses: np.ndarray) -> np.ndarray:
    return np.array(
        [
            score_poses_loop(local, global_, p[:1], p[1:2], p[2:], metric).item()
            for p in np.asarray(poses)
        ]
    )


def test_agreement_prefers_more_free_overlap_and_the_centred_score_the_truth(
    biased_scene: tuple[Band, Band, np.ndarray, np.ndarray],
) -> None:
    view, global_, truth, wrong = biased_scene
    metric = Metric(free_weight=0.5, occupied_level=0.1)
    at_truth, at_wrong = pose_scores(view, global_, metric, np.array([truth, wrong]))
    # At the truth the view's 43 wall cells lie on walls (+1 each) and 172 of its 533 free
    # cells on known free cells (+0.25 each; the rest on unknown ones); in the hall its walls
    # lie on free cells (−0.5 each) and all its free cells on free cells.
    assert at_truth == pytest.approx(43 + 0.25 * 172, abs=1e-9)
    assert at_wrong == pytest.approx(-0.5 * 43 + 0.25 * 533, abs=1e-9)
    assert at_wrong > at_truth
    centred = Metric(free_weight=0.5, occupied_level=0.1, score="centred")
    c_truth, c_wrong = pose_scores(view, global_, centred, np.array([truth, wrong]))
    m_l = (43 - 0.5 * 533) / 576  # the view: 43 walls, 533 free cells
    m_g = (49 - 0.5 * 2716) / 2765  # the map: 49 walls, 2716 free cells
    expected = 43 * (1 - m_l) * (1 - m_g) + 172 * (-0.5 - m_l) * (-0.5 - m_g)
    assert c_truth == pytest.approx(expected, rel=1e-9)
    # In the hall every view cell lands on the same value: Σ (v_L − m_L) = 0.
    assert c_wrong == pytest.approx(0.0, abs=1e-9)
    excess = Metric(free_weight=0.5, occupied_level=0.1, score="excess")
    e_truth, e_wrong = pose_scores(view, global_, excess, np.array([truth, wrong]))
    assert e_truth == pytest.approx(at_truth - m_l * m_g * 215, rel=1e-9)  # 43 + 172 overlap
    assert e_wrong == pytest.approx(at_wrong - m_l * m_g * 576, rel=1e-9)  # the whole view
    assert e_truth > e_wrong + 30.0
    params = SearchParams(angular_resolution_rad=math.radians(5.0))
    old = search(view, global_, params)
    new = search(view, global_, SearchParams(angular_resolution_rad=math.radians(5.0),
                                             score="centred"))  # fmt: skip
    assert old.pose[0] > 4.0  # somewhere in the hall
    assert np.allclose(new.lattice_pose, truth, atol=1e-9)
    assert new.is_dominant(2.0)
    step = math.radians(5.0)
    found = search(view, global_, SearchParams(angular_resolution_rad=step, score="excess"))
    assert np.allclose(found.lattice_pose, truth, atol=1e-9)


# -- degenerate inputs -------------------------------------------------------------------------


@pytest.mark.parametrize("score", ["centred", "excess"])
def test_no_overlap_anywhere_gives_a_flat_pdf(score: str) -> None:
    rng = np.random.default_rng(4)
    global_ = random_band(rng, (40, 40), [0.0, 0.0])
    hole = np.asarray(global_.known).copy()
    hole[:, 20:] = False
    global_ = Band(np.where(hole, global_.occupancy, 0.0), hole, global_.lower_xy, 0.1)
    local = random_band(rng, (5, 5), [-0.25, -0.25])
    params = SearchParams(angular_resolution_rad=math.radians(30.0), score=score)
    # Every position of the window is more than the view's reach from a known map cell.
    result = search(local, global_, params, window_m=(3.0, 4.0, 0.0, 4.0))
    assert np.isfinite(result.prob).all()
    assert np.isfinite(result.pose).all()
    assert np.abs(result.prob - 1.0 / result.prob.size).max() < 1e-9
    assert result.best_score == 0.0
    assert result.peak_ratio == pytest.approx(1.0)


def test_bands_whose_known_cells_are_alike_are_one_line_errors() -> None:
    rng = np.random.default_rng(5)
    global_ = random_band(rng, (30, 30), [0.0, 0.0])
    free = Band(np.zeros((6, 6)), np.ones((6, 6), dtype=bool), np.array([-0.3, -0.3]), 0.1)
    params = SearchParams(angular_resolution_rad=math.radians(30.0), score="centred")
    with pytest.raises(EstimationError, match="known cells all have the same value") as info:
        search(free, global_, params)
    assert "\n" not in str(info.value)
    all_free_map = Band(np.zeros((30, 30)), np.ones((30, 30), dtype=bool), np.zeros(2), 0.1)
    local = random_band(rng, (6, 6), [-0.3, -0.3])
    with pytest.raises(EstimationError, match="map grid has no known cell"):
        search(local, all_free_map, params)
    unknown = Band(np.zeros((6, 6)), np.zeros((6, 6), dtype=bool), np.array([-0.3, -0.3]), 0.1)
    with pytest.raises(EstimationError, match="scan grid has no known cell"):
        search(unknown, global_, params)
    assert value_mean(unknown, CENTRED) == 0.0


def test_an_unknown_score_is_an_error_naming_it() -> None:
    with pytest.raises(
        EstimationError, match="search score must be one of agreement, centred, excess"
    ):
        Metric(score="ncc")
    with pytest.raises(EstimationError, match="got 'ncc'"):
        SearchParams(score="ncc")


def test_the_excess_score_is_searched_exhaustively_for_the_best_pose() -> None:
    from estimation.search.bnb import lattice_best
    from estimation.search.exhaustive import best_pose
    from estimation.search.scenes import local_view, random_building, rasterise

    scene = random_building(np.random.default_rng(5), 8.0)
    global_ = rasterise(scene, np.zeros(3), (0.0, 0.0), (80, 80), 0.1)
    local = local_view(scene, np.array([4.1, 3.3, 0.7]), 2.5, 0.1, np.random.default_rng(1),
                       noise=0.1, drop_fraction=0.2)  # fmt: skip
    params = SearchParams(angular_resolution_rad=math.radians(4.0), score="excess")
    whole = search(local, global_, params)
    pose, score, _ = best_pose(local, global_, params)
    assert np.allclose(pose, whole.pose, atol=1e-12)
    assert score == whole.best_score
    assert math.dist(pose[:2], (4.1, 3.3)) < 0.05
    x_m, y_m, _ = pose_lattice(local, global_)
    yaw = yaw_lattice(params.angular_resolution_rad)
    with pytest.raises(EstimationError, match="the excess score is searched exhaustively"):
        lattice_best(local, global_, x_m, y_m, yaw, params.metric)
