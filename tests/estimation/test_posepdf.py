"""The pose PDF a search yields: best pose, covariance, peak dominance, high-probability region."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimation.errors import EstimationError
from estimation.posegraph.seed import seed_pose
from estimation.posepdf import PosePdf

X = np.arange(-1.0, 1.0001, 0.05)
Y = np.arange(-0.8, 0.8001, 0.05)
FULL_YAW = np.radians(np.arange(-180.0, 180.0, 1.0))
COV = np.array(
    [
        [0.05**2, 0.5 * 0.05 * 0.08, 0.3 * 0.05 * math.radians(2)],
        [0.5 * 0.05 * 0.08, 0.08**2, 0.0],
        [0.3 * 0.05 * math.radians(2), 0.0, math.radians(2) ** 2],
    ]
)


def gaussian(mean: tuple[float, float, float], cov: np.ndarray = COV) -> PosePdf:
    return PosePdf.from_gaussian(np.array(mean), cov, X, Y, FULL_YAW)


def two_peaks(ratio: float) -> PosePdf:
    """A main peak at (0.2, 0.1, 30°) and a second one ``1/ratio`` as high 1 m away."""
    yaw, y, x = np.meshgrid(FULL_YAW, Y, X, indexing="ij")

    def bump(cx: float, cy: float, ct: float) -> np.ndarray:
        dt = np.angle(np.exp(1j * (yaw - ct)))
        return np.exp(-0.5 * (((x - cx) / 0.05) ** 2 + ((y - cy) / 0.05) ** 2 + (dt / 0.03) ** 2))

    scores = bump(0.2, 0.1, math.radians(30)) + bump(-0.7, -0.5, math.radians(-100)) / ratio
    return PosePdf.from_scores(X, Y, FULL_YAW, scores)


def test_best_pose_is_refined_between_lattice_points() -> None:
    pdf = gaussian((0.123, -0.234, 3.1))
    np.testing.assert_allclose(pdf.best_pose(), [0.123, -0.234, 3.1], atol=1e-9)
    coarse = pdf.best_pose(refine=False)
    assert coarse[0] == pytest.approx(0.10) or coarse[0] == pytest.approx(0.15)
    assert abs(coarse[0] - 0.123) > 0.01


def test_best_pose_wraps_yaw_across_pi() -> None:
    pdf = gaussian((0.0, 0.0, -3.13))
    assert pdf.yaw_wraps
    assert pdf.best_pose()[2] == pytest.approx(-3.13, abs=1e-9)


def test_covariance_recovers_a_gaussian_peak() -> None:
    pdf = gaussian((0.1, 0.0, 1.0))
    steps = np.array([0.05, 0.05, math.radians(1)])
    # the sampled Gaussian's moments plus the lattice's own step²/12
    expected = COV + np.diag(steps**2) / 12
    np.testing.assert_allclose(
        pdf.covariance(0.5, math.radians(15)), expected, rtol=0.02, atol=1e-7
    )


def test_peak_ratio_measures_dominance() -> None:
    assert two_peaks(5.0).peak_ratio(0.5, math.radians(10)) == pytest.approx(5.0, rel=1e-3)
    assert two_peaks(1.5).is_dominant(2.0) is False
    assert two_peaks(5.0).is_dominant(2.0) is True
    single = gaussian((0.0, 0.0, 0.0), np.diag([1e-4, 1e-4, 1e-4]))
    assert single.peak_ratio(0.5, math.radians(10)) > 1e6


def test_region_holds_the_requested_mass() -> None:
    pdf = gaussian((0.0, 0.1, 0.5))
    for mass in (0.5, 0.9, 0.99):
        region = pdf.region(mass)
        held = pdf.prob[region].sum()
        assert mass <= held < mass + 0.01
        # the region is the most probable cells: nothing outside beats anything inside
        assert pdf.prob[~region].max() <= pdf.prob[region].min()


def test_contains_matches_the_mahalanobis_ellipsoid() -> None:
    pdf = gaussian((0.0, 0.0, 0.0), np.diag([0.1**2, 0.1**2, math.radians(3) ** 2]))
    # 99 % of a 3-D Gaussian lies within Mahalanobis 3.37
    assert pdf.contains(np.array([0.30, 0.0, 0.0]), 0.99)
    assert not pdf.contains(np.array([0.40, 0.0, 0.0]), 0.99)
    assert pdf.contains(np.array([0.0, 0.0, math.radians(9.0)]), 0.99)
    assert not pdf.contains(np.array([0.0, 0.0, math.radians(12.0)]), 0.99)
    assert pdf.mass_above(np.array([0.0, 0.0, 0.0])) < 0.01
    assert pdf.mass_above(np.array([0.4, 0.0, 0.0])) > 0.99


def test_poses_off_the_lattice_are_outside() -> None:
    pdf = gaussian((0.0, 0.0, 0.0))
    assert pdf.nearest_index(np.array([1.2, 0.0, 0.0])) is None
    assert not pdf.contains(np.array([0.0, 5.0, 0.0]), 0.99)
    assert pdf.mass_above(np.array([0.0, 5.0, 0.0])) == 1.0


def test_partial_yaw_window_may_straddle_pi() -> None:
    yaw = np.radians(np.arange(170.0, 191.0, 1.0))  # 170°…190°: crosses ±180°
    pdf = PosePdf.from_gaussian(
        np.array([0.0, 0.0, math.radians(-178.0)]), np.diag([0.01, 0.01, 1e-4]), X, Y, yaw
    )
    assert not pdf.yaw_wraps
    assert pdf.best_pose()[2] == pytest.approx(math.radians(-178.0), abs=1e-6)
    assert pdf.nearest_index(np.array([0.0, 0.0, math.radians(-178.0)])) == (12, 16, 20)
    assert pdf.nearest_index(np.array([0.0, 0.0, math.radians(150.0)])) is None


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        ({"prob": np.ones((3, 2, 2))}, r"prob must have shape \(T, Y, X\) = \(2, 2, 2\)"),
        ({"prob": np.full((2, 2, 2), 0.2)}, "prob must sum to 1, sums to 1.6"),
        ({"prob": np.full((2, 2, 2), np.nan)}, "prob must be finite and non-negative"),
        ({"x_m": np.array([0.0, 0.1, 0.3])}, "x_m must be uniform and increasing"),
        ({"y_m": np.array([0.1, 0.0])}, "y_m must be uniform and increasing"),
        ({"yaw_rad": np.array([0.0, np.inf])}, "yaw_rad holds NaN or inf"),
        ({"x_m": np.array([])}, "x_m must be a non-empty 1-D lattice"),
    ],
)
def test_invalid_pdfs_are_rejected(kwargs: dict[str, np.ndarray], pattern: str) -> None:
    fields = {
        "x_m": np.array([0.0, 0.1]),
        "y_m": np.array([0.0, 0.1]),
        "yaw_rad": np.array([0.0, 0.1]),
        "prob": np.full((2, 2, 2), 1 / 8),
    }
    fields.update(kwargs)
    if "x_m" in kwargs and len(kwargs["x_m"]) == 3 and "prob" not in kwargs:
        fields["prob"] = np.full((2, 2, 3), 1 / 12)
    with pytest.raises(EstimationError, match=pattern):
        PosePdf(**fields)


def test_yaw_lattice_longer_than_a_turn_and_bad_scores_are_rejected() -> None:
    yaw = np.radians(np.arange(0.0, 400.0, 10.0))
    with pytest.raises(EstimationError, match="covers more than 2π"):
        PosePdf(X[:2], Y[:2], yaw, np.full((len(yaw), 2, 2), 1 / (4 * len(yaw))))
    with pytest.raises(EstimationError, match="scores must be finite, non-negative, not all zero"):
        PosePdf.from_scores(X[:2], Y[:2], FULL_YAW[:2], np.zeros((2, 2, 2)))
    with pytest.raises(EstimationError, match=r"mass must be in \(0, 1\)"):
        gaussian((0, 0, 0)).region(1.0)


def test_pdf_arrays_are_read_only_copies() -> None:
    scores = np.ones((2, 2, 2)) / 8
    pdf = PosePdf(X[:2], Y[:2], FULL_YAW[:2], scores)
    scores[0, 0, 0] = 5.0
    assert pdf.prob[0, 0, 0] == pytest.approx(1 / 8)
    with pytest.raises(ValueError, match="read-only"):
        pdf.prob[0, 0, 0] = 1.0

    with pytest.raises(AttributeError, match="immutable"):
        pdf.x_m = X
    single = PosePdf(X[:2], Y[:2], FULL_YAW[:2], np.full((2, 2, 2), 0.125, np.float32))
    assert single.prob[0, 0, 0] == pytest.approx(1 / 8)
    with pytest.raises(ValueError, match="read-only"):
        single.prob[0, 0, 0] = 1.0


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([1.0, 0.05, 1e-3]), st.booleans())
def test_float32_probabilities_give_the_float64_answers_bit_for_bit(
    seed: int, contrast: float, full_circle: bool
) -> None:
    # A search's float32 PDF (summing to 1 within float32's rounding) kept as float32 answers
    # exactly as its float64 copy normalised in float64 (the way PosePdf kept it before).
    rng = np.random.default_rng(seed)
    yaw = FULL_YAW[::12] if full_circle else FULL_YAW[100:140]
    scores = rng.random((len(yaw), len(Y), len(X))) * contrast
    t, y, x = (int(rng.integers(0, n)) for n in scores.shape)
    scores[t, y, x] += 1.0
    scores[max(t - 1, 0), y, x] += 0.5 * rng.random()
    scores[t, rng.integers(0, len(Y)), rng.integers(0, len(X))] = scores.max()  # a tie
    prob = (scores / scores.sum()).astype(np.float32)
    single, double = PosePdf(X, Y, yaw, prob), PosePdf(X, Y, yaw, prob.astype(np.float64))
    assert single.nbytes * 2 == double.nbytes
    assert np.array_equal(single.prob, double.prob)
    assert single.best_index() == double.best_index()
    assert np.array_equal(single.best_pose(), double.best_pose())
    for radius_m, radius_rad in ((0.5, 0.1745), (0.1, 0.05)):
        assert single.peak_ratio(radius_m, radius_rad) == double.peak_ratio(radius_m, radius_rad)
        assert np.array_equal(single.covariance(radius_m, radius_rad),
                              double.covariance(radius_m, radius_rad))  # fmt: skip
    for mass in (0.5, 0.9, 0.999):
        assert single.density_threshold(mass) == double.density_threshold(mass)
        assert np.array_equal(single.region(mass), double.region(mass))
    for _ in range(5):
        pose = np.array([rng.uniform(-1.1, 1.1), rng.uniform(-0.9, 0.9), rng.uniform(-4, 4)])
        assert single.mass_above(pose) == double.mass_above(pose)
        assert single.contains(pose, 0.9) == double.contains(pose, 0.9)
    # As a mission's processes pass it on.
    back = pickle.loads(pickle.dumps(single))
    assert np.array_equal(back.prob, single.prob)
    assert back.nbytes == single.nbytes
    assert np.array_equal(back.covariance(), single.covariance())
    with pytest.raises(ValueError, match="read-only"):
        back.x_m[0] = 1.0
    with pytest.raises(AttributeError, match="immutable"):
        back.x_m = X


def test_seed_uses_the_search_only_when_its_peak_is_dominant() -> None:
    fallback = np.array([5.0, 5.0, 0.0])
    pose, from_search = seed_pose(two_peaks(5.0), fallback, 2.0, 0.5, math.radians(10))
    assert from_search
    np.testing.assert_allclose(pose, [0.2, 0.1, math.radians(30)], atol=1e-6)  # type: ignore[arg-type]
    pose, from_search = seed_pose(two_peaks(1.5), fallback, 2.0, 0.5, math.radians(10))
    assert not from_search
    np.testing.assert_allclose(pose, fallback)  # type: ignore[arg-type]
    assert seed_pose(two_peaks(1.5), None, 2.0, 0.5, math.radians(10)) == (None, False)
