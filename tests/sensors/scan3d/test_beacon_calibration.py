"""Beacon offset from synthetic mutual observations; the beacon band's centre height."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sensors.errors import SensorError
from sensors.scan3d.beacon_calibration import (
    OffsetEstimate,
    beacon_centre_height,
    beacon_separations,
    estimate_beacon_offset,
)

OFFSET_M = 0.27


def observations(
    rng: np.random.Generator, count: int, *, offset_m: float = OFFSET_M, noise: bool = True
) -> tuple[np.ndarray, ...]:
    """(a, α, b, β) of robot pairs 1.5–4 m apart, one seeing the other 10–20° off its heading and
    the other 30–45° off (design §4), with LMS-like noise."""
    rows: list[list[float]] = []
    while len(rows) < count:
        distance = rng.uniform(1.5, 4.0)
        near, far = rng.uniform(10, 20), rng.uniform(30, 45)
        pair = (near, far) if rng.random() < 0.5 else (far, near)
        alpha0, beta0 = np.radians(pair) * rng.choice([-1.0, 1.0], 2)
        c = distance * np.exp(1j * alpha0)  # C's scanner in A's frame
        heading = np.angle(-c) - beta0  # C looks back at A at about β0
        u = c + offset_m * np.exp(1j * heading)  # C's beacon, seen by A
        v = (offset_m - c) * np.exp(-1j * heading)  # A's beacon, seen by C
        rows.append([abs(u), np.angle(u), abs(v), np.angle(v)])
    a, alpha, b, beta = np.asarray(rows).T
    if noise:
        a = a + rng.normal(0, 0.005, count)
        b = b + rng.normal(0, 0.005, count)
        alpha = alpha + rng.normal(0, math.radians(0.1), count)
        beta = beta + rng.normal(0, math.radians(0.1), count)
    return a, alpha, b, beta


def estimate(
    a: np.ndarray, alpha: np.ndarray, b: np.ndarray, beta: np.ndarray, **kw: float
) -> OffsetEstimate:
    options = {"start_offset_m": 0.2, "range_sigma_m": 0.02,
               "bearing_sigma_rad": math.radians(0.25), **kw}  # fmt: skip
    return estimate_beacon_offset(a, alpha, b, beta, **options)


def test_noise_free_observations_give_the_offset_exactly() -> None:
    found = estimate(*observations(np.random.default_rng(0), 5, noise=False))
    assert found.offset_m == pytest.approx(OFFSET_M, abs=1e-9)
    assert found.separation_rms_after_m < 1e-9
    assert found.separation_rms_before_m > 1e-3


def test_noisy_observations_give_the_offset_within_a_centimetre() -> None:
    found = estimate(*observations(np.random.default_rng(1), 20))
    assert found.offset_m == pytest.approx(OFFSET_M, abs=0.01)
    assert found.sigma_m < 0.01
    assert abs(found.offset_m - OFFSET_M) < 4 * found.sigma_m
    assert found.separation_rms_after_m < found.separation_rms_before_m
    assert found.used == 20
    assert found.skipped_degenerate == 0


def test_an_outlier_is_down_weighted() -> None:
    a, alpha, b, beta = observations(np.random.default_rng(2), 15)
    a[3] += 0.5  # a wrong beacon
    found = estimate(a, alpha, b, beta)
    assert found.downweighted >= 1
    assert found.offset_m == pytest.approx(OFFSET_M, abs=0.015)


def test_symmetric_observations_are_skipped_as_degenerate() -> None:
    a, alpha, b, beta = observations(np.random.default_rng(3), 10)
    # Equal ranges and bearings: s1 = s2 for every offset.
    found = estimate(np.r_[a, 3.0, 2.0], np.r_[alpha, 0.3, -0.4], np.r_[b, 3.0, 2.0],
                     np.r_[beta, 0.3, -0.4])  # fmt: skip
    assert found.skipped_degenerate == 2
    assert found.used == 10
    assert found.offset_m == pytest.approx(OFFSET_M, abs=0.015)


@pytest.mark.parametrize(
    ("values", "message"),
    [
        (
            ([3.0, 2.0], [0.3, -0.4], [3.0, 2.0], [0.3, -0.4]),
            r"all 2 mutual observations are degenerate",
        ),
        (([], [], [], []), r"no mutual observations"),
        (([3.0], [float("nan")], [3.0], [0.2]), r"NaN or infinite"),
        (([3.0], [0.1], [0.0], [0.2]), r"range <= 0"),
        (([3.0, 2.0], [0.1], [2.0], [0.2]), r"one value per observation"),
    ],
)
def test_offset_errors_name_the_problem(values: tuple[list[float], ...], message: str) -> None:
    with pytest.raises(SensorError, match=message):
        estimate(*(np.asarray(v) for v in values))


def test_separations_agree_at_the_true_offset() -> None:
    a, alpha, b, beta = observations(np.random.default_rng(4), 6, noise=False)
    s1, s2 = beacon_separations(a, alpha, b, beta, OFFSET_M)
    np.testing.assert_allclose(s1, s2, atol=1e-12)
    s1, s2 = beacon_separations(a, alpha, b, beta, 0.1)
    assert np.max(np.abs(s1 - s2)) > 0.01


def test_centre_height_is_the_middle_of_the_reflective_band() -> None:
    rng = np.random.default_rng(5)
    angle = rng.uniform(-1.2, 1.2, 300) + math.pi  # the side facing the scanner
    z = rng.uniform(0.9, 1.5, 300)
    beacon = np.column_stack([3.0 + 0.1 * np.cos(angle), 1.0 + 0.1 * np.sin(angle), z])
    sign = np.array([[5.0, -2.0, 1.8], [5.0, -2.1, 1.9], [5.0, -2.2, 2.0]])  # elsewhere
    wall = np.column_stack([np.full(50, 6.0), np.linspace(-1, 1, 50), np.full(50, 1.0)])
    points = np.vstack([beacon, sign, wall])
    flagged = np.r_[np.ones(303, dtype=bool), np.zeros(50, dtype=bool)]
    z_centre = beacon_centre_height(points, flagged, np.array([3.0, 1.0]), radius_m=0.1,
                                    band_center_m=1.0, band_half_m=1.0)  # fmt: skip
    assert z_centre == pytest.approx(1.2, abs=0.005)
    # Only returns within the band searched count; too few is no answer.
    assert beacon_centre_height(points, flagged, np.array([3.0, 1.0]), radius_m=0.1,
                                band_center_m=3.0, band_half_m=0.2) is None  # fmt: skip
    assert beacon_centre_height(points, flagged, np.array([0.0, 0.0]), radius_m=0.1,
                                band_center_m=1.2, band_half_m=1.0) is None  # fmt: skip
