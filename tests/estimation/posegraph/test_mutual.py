"""Mutual localization: paper eq. 1–2 against geometry, Jacobians, accuracy targets, the gate."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from estimation.errors import EstimationError
from estimation.posegraph.mutual import (
    GAP_SAMPLES,
    MAX_GAP_SCALE,
    _refine_one,
    check_observation,
    closed_form,
    closed_form_jacobian,
    closure_distance,
    cramer_rao_bound,
    gap_scale,
    gap_sigma,
    localize_mutual,
    measurement_jacobian,
    measurements,
    refine_relative_pose,
    relative_pose,
    separations,
    sighting_distance,
)
from sensors.geometry import se2

D = 0.25
SIGMA_R = 0.02
SIGMA_B = math.radians(0.25)
NOISE = np.array([SIGMA_R, SIGMA_B, SIGMA_R, SIGMA_B])


def random_poses(rng: np.random.Generator, n: int, lo: float, hi: float) -> np.ndarray:
    """Poses of C's scanner in A's frame at separations in [lo, hi], beacons well apart."""
    out = []
    while len(out) < n:
        r, phi, yaw = rng.uniform(lo, hi), rng.uniform(-np.pi, np.pi), rng.uniform(-np.pi, np.pi)
        pose = np.array([r * np.cos(phi), r * np.sin(phi), yaw])
        s1, s2 = separations(*measurements(pose, D), D)
        if min(s1, s2) > 0.3:
            out.append(pose)
    return np.array(out)


def test_closed_form_is_exact_on_noise_free_geometry() -> None:
    rng = np.random.default_rng(0)
    poses = random_poses(rng, 5000, 0.4, 10.0)
    z = measurements(poses, D)
    recovered = closed_form(z[:, 0], z[:, 1], z[:, 2], z[:, 3], D)
    np.testing.assert_allclose(recovered[:, :2], poses[:, :2], atol=1e-9)
    assert np.abs(se2.wrap_angle(recovered[:, 2] - poses[:, 2])).max() < 1e-9


def test_relative_pose_against_explicit_geometry() -> None:
    # A at the origin facing +x; C's scanner at (3, 2) facing 120°. Beacons d ahead of each.
    c, yaw = np.array([3.0, 2.0]), math.radians(120.0)
    beacon_c = c + D * np.array([math.cos(yaw), math.sin(yaw)])
    beacon_a = np.array([D, 0.0])
    a, alpha = np.hypot(*beacon_c), math.atan2(beacon_c[1], beacon_c[0])
    v = beacon_a - c  # A's beacon seen from C, rotated into C's frame
    rot = np.array([[math.cos(yaw), math.sin(yaw)], [-math.sin(yaw), math.cos(yaw)]])
    v_c = rot @ v
    b, beta = np.hypot(*v_c), math.atan2(v_c[1], v_c[0])
    x, y, heading = relative_pose(a, alpha, b, beta, D)
    assert (x, y) == pytest.approx((3.0, 2.0), abs=1e-12)
    assert heading == pytest.approx(yaw, abs=1e-12)
    # Paper: heading = θ − β + π with θ the argument of eq. 1.
    theta = np.angle((a * np.exp(1j * alpha) - D) / (b - D * np.exp(-1j * beta)))
    assert float(se2.wrap_angle(theta - beta + np.pi)) == pytest.approx(yaw, abs=1e-12)


def test_separations_follow_the_cosine_rule() -> None:
    a, alpha, b, beta = 3.0, 0.7, 2.5, -1.9
    s1, s2 = separations(a, alpha, b, beta, D)
    assert s1 == pytest.approx(math.sqrt(a * a + D * D - 2 * a * D * math.cos(alpha)))
    assert s2 == pytest.approx(math.sqrt(b * b + D * D - 2 * b * D * math.cos(beta)))


def numerical_jacobian(f, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:  # type: ignore[no-untyped-def]
    columns = []
    for k in range(len(x)):
        dx = np.zeros_like(x)
        dx[k] = eps
        diff = f(x + dx) - f(x - dx)
        columns.append(diff / (2 * eps))
    return np.stack(columns, axis=-1)


def test_closed_form_jacobian_matches_numerical_derivatives() -> None:
    rng = np.random.default_rng(1)
    for pose in random_poses(rng, 50, 0.5, 8.0):
        z = measurements(pose, D)
        numeric = numerical_jacobian(lambda q: closed_form(*q, D), z)
        np.testing.assert_allclose(closed_form_jacobian(*z, D), numeric, atol=1e-6)


def test_measurement_jacobian_matches_numerical_derivatives() -> None:
    rng = np.random.default_rng(2)
    for pose in random_poses(rng, 50, 0.5, 8.0):
        numeric = numerical_jacobian(lambda p: measurements(p, D), pose)
        np.testing.assert_allclose(measurement_jacobian(pose, D), numeric, atol=1e-6)


def test_gap_sigma_matches_monte_carlo_spread() -> None:
    rng = np.random.default_rng(3)
    pose = np.array([2.0, -1.2, 2.4])
    z = measurements(pose, D) + rng.normal(size=(20000, 4)) * NOISE
    s1, s2 = separations(z[:, 0], z[:, 1], z[:, 2], z[:, 3], D)
    predicted = float(gap_sigma(*measurements(pose, D), D, SIGMA_R, SIGMA_B))
    assert np.std(s1 - s2) == pytest.approx(predicted, rel=0.03)


def test_fast_single_event_path_equals_the_vectorised_refinement() -> None:
    rng = np.random.default_rng(4)
    for pose in random_poses(rng, 20, 1.0, 8.0):
        z = measurements(pose, D) + rng.normal(size=4) * NOISE
        vec_pose, vec_cov = refine_relative_pose(z, D, SIGMA_R, SIGMA_B)
        one_pose, one_cov = _refine_one(tuple(z), D, SIGMA_R, SIGMA_B, 6)  # type: ignore[arg-type]
        np.testing.assert_allclose(one_pose, vec_pose, atol=1e-10)
        np.testing.assert_allclose(one_cov, vec_cov, rtol=1e-8)


def monte_carlo(pose: np.ndarray, trials: int, rng: np.random.Generator) -> np.ndarray:
    """ML estimates of ``pose`` from noisy measurements, errors as (trials, 3)."""
    z = measurements(pose, D) + rng.normal(size=(trials, 4)) * NOISE
    est, _ = refine_relative_pose(z, D, SIGMA_R, SIGMA_B)
    err = est - pose
    err[:, 2] = se2.wrap_angle(err[:, 2])
    return err


def test_relative_pose_rms_error_within_3_cm_and_half_a_degree_up_to_4_m() -> None:
    rng = np.random.default_rng(5)
    poses = random_poses(rng, 4000, 0.5, 4.0)
    z = measurements(poses, D) + rng.normal(size=(len(poses), 4)) * NOISE
    est, _ = refine_relative_pose(z, D, SIGMA_R, SIGMA_B)
    err = est - poses
    rms_m = math.sqrt(np.mean(err[:, 0] ** 2 + err[:, 1] ** 2))
    rms_deg = math.degrees(math.sqrt(np.mean(se2.wrap_angle(err[:, 2]) ** 2)))
    assert rms_m <= 0.03
    assert rms_deg <= 0.5
    # And not trivially: the errors are those of the noise, not zero.
    assert rms_m > 0.005
    assert rms_deg > 0.1


@pytest.mark.parametrize("separation_m", [1.0, 2.0, 4.0, 6.0, 8.0])
def test_ml_estimate_reaches_the_cramer_rao_bound(separation_m: float) -> None:
    rng = np.random.default_rng(int(separation_m * 10))
    for phi, yaw in [(0.7, 0.3), (2.5, 2.0), (-1.2, -1.0)]:
        pose = np.array([separation_m * math.cos(phi), separation_m * math.sin(phi), yaw])
        err = monte_carlo(pose, 4000, rng)
        crb = cramer_rao_bound(pose, D, SIGMA_R, SIGMA_B)
        rms_pos = math.sqrt(np.mean(err[:, 0] ** 2 + err[:, 1] ** 2))
        rms_yaw = math.sqrt(np.mean(err[:, 2] ** 2))
        assert rms_pos / math.sqrt(crb[0, 0] + crb[1, 1]) == pytest.approx(1.0, abs=0.15)
        assert rms_yaw / math.sqrt(crb[2, 2]) == pytest.approx(1.0, abs=0.15)


def test_closed_form_alone_misses_the_bound_at_short_range() -> None:
    """Why the graph uses the ML refinement: the closed form is up to ~2× the bound."""
    rng = np.random.default_rng(6)
    pose = np.array([math.cos(0.7), math.sin(0.7), -1.0])
    z = measurements(pose, D) + rng.normal(size=(20000, 4)) * NOISE
    err = closed_form(z[:, 0], z[:, 1], z[:, 2], z[:, 3], D) - pose
    crb = cramer_rao_bound(pose, D, SIGMA_R, SIGMA_B)
    assert math.sqrt(np.mean(err[:, 1] ** 2)) / math.sqrt(crb[1, 1]) > 1.5


@pytest.mark.parametrize("method", ["ml", "closed_form"])
def test_propagated_covariance_is_consistent_nees_over_1000_trials(method: str) -> None:
    rng = np.random.default_rng(7)
    poses = random_poses(rng, 1000, 1.0, 8.0)
    nees = []
    for pose in poses:
        z = measurements(pose, D) + rng.normal(size=4) * NOISE
        fix = localize_mutual(*z, D, SIGMA_R, SIGMA_B, method=method)  # type: ignore[arg-type]
        err = fix.pose - pose
        err[2] = float(se2.wrap_angle(err[2]))
        nees.append(err @ np.linalg.solve(fix.covariance, err))
    n = len(nees)
    lo, hi = chi2.ppf(0.025, 3 * n) / n, chi2.ppf(0.975, 3 * n) / n
    assert lo <= np.mean(nees) <= hi
    inside = np.mean(np.array(nees) <= chi2.ppf(0.95, 3))
    assert inside == pytest.approx(0.95, abs=0.02)


def test_gate_accepts_consistent_and_rejects_inconsistent_separations() -> None:
    z = measurements(np.array([2.0, 1.0, 2.5]), D)
    good = localize_mutual(*z, D, SIGMA_R, SIGMA_B)
    assert good.accepted
    assert abs(good.gap_m) < 1e-12
    assert good.s1_m == pytest.approx(good.s2_m)
    bad = localize_mutual(z[0] + 0.2, z[1], z[2], z[3], D, SIGMA_R, SIGMA_B)
    assert not bad.accepted
    assert bad.gap_m == pytest.approx(0.2, abs=0.05)
    assert bad.gap_sigmas > 3


@pytest.mark.parametrize(
    ("z", "pattern"),
    [
        ((2.0, 0.5, D, 0.0), r"degenerate geometry: b·e\^\(iβ\) ≈ d \(beacon separation s2 = 0 m"),
        ((D + 1e-4, 0.0, 2.0, 0.5), r"degenerate geometry: a·e\^\(iα\) ≈ d"),
        ((0.01, 0.5, 2.0, 0.5), r"range a_m = 0\.01 m is below 0\.05 m"),
        ((2.0, 0.5, 0.0, 0.5), r"range b_m = 0 m is below"),
        ((math.nan, 0.5, 2.0, 0.5), r"a_m must be a finite number, got nan"),
        ((2.0, math.inf, 2.0, 0.5), r"alpha_rad must be a finite number, got inf"),
    ],
)
def test_relative_pose_rejects_degenerate_input(
    z: tuple[float, float, float, float], pattern: str
) -> None:
    with pytest.raises(EstimationError, match=pattern):
        relative_pose(*z, D)


def test_non_positive_beacon_offset_and_sigmas_are_errors() -> None:
    with pytest.raises(EstimationError, match="beacon offset d_m must be positive, got 0"):
        relative_pose(2.0, 0.5, 2.0, 0.5, 0.0)
    with pytest.raises(EstimationError, match="sigmas and gate must be positive"):
        localize_mutual(2.0, 0.5, 2.0, -0.5, D, 0.0, SIGMA_B)
    with pytest.raises(EstimationError, match="unknown method 'lsq'"):
        localize_mutual(2.0, 0.5, 2.0, -0.5, D, SIGMA_R, SIGMA_B, method="lsq")  # type: ignore[arg-type]


def test_check_observation_passes_a_sound_event() -> None:
    check_observation(2.0, 0.5, 2.0, -0.5, D)


def test_gap_scale_is_the_robust_spread_of_the_gaps_within_its_bounds() -> None:
    assert gap_scale([0.01] * (GAP_SAMPLES - 1), 0.1) == 1.0  # too few gaps yet
    assert gap_scale([0.01] * 50, None) == 1.0  # switched off
    assert gap_scale([0.01] * 50, 0.1) == pytest.approx(0.1)  # never below ``low``
    assert gap_scale([0.3] * 50, 0.1) == pytest.approx(1.4826 * 0.3)
    assert gap_scale([10.0] * 50, 0.1) == MAX_GAP_SCALE
    # The median: a few wild gaps do not move it.
    assert gap_scale([0.5] * 40 + [3.0] * 9, 0.1) == pytest.approx(1.4826 * 0.5)


def test_the_closure_of_three_robots_observations_is_chi_square_with_three_dof() -> None:
    rng = np.random.default_rng(11)
    n = 3000
    at, tc = random_poses(rng, n, 0.8, 5.0), random_poses(rng, n, 0.8, 5.0)
    ac = se2.compose(at, tc)
    keep = np.abs(ac[:, 0] + 1j * ac[:, 1] + D * np.exp(1j * ac[:, 2]) - D) > 0.5
    at, tc, ac = at[keep], tc[keep], ac[keep]

    def z(pose: np.ndarray) -> np.ndarray:
        return measurements(pose, D) + rng.normal(size=(len(pose), 4)) * NOISE

    d2 = closure_distance(z(ac), z(at), z(tc), D, SIGMA_R, SIGMA_B)
    assert d2.shape == (len(ac),)
    assert np.mean(d2) == pytest.approx(3.0, rel=0.1)
    assert np.mean(d2 > chi2.ppf(0.99, 3)) == pytest.approx(0.01, abs=0.006)
    # A third robot's detection taken for the partner's: C's pose off by the gap between them.
    swapped = measurements(ac, D)
    swapped[:, :2] = measurements(at, D)[:, :2]
    beacon = measurements(ac, D)[:, 0] * np.exp(1j * measurements(ac, D)[:, 1])
    apart = np.abs(beacon - swapped[:, 0] * np.exp(1j * swapped[:, 1]))
    wrong = closure_distance(swapped, measurements(at, D), measurements(tc, D), D, SIGMA_R, SIGMA_B)
    assert np.all(wrong[apart > 0.3] > 100.0)
    # Broadcast over one pair; degenerate geometry (a beacon on the other's) is not finite.
    one = closure_distance(measurements(ac[0], D), measurements(at, D), measurements(tc, D), D,
                           SIGMA_R, SIGMA_B)  # fmt: skip
    assert one.shape == (len(at),)
    assert not np.isfinite(closure_distance([D, 0.0, D, 0.0], measurements(at[0], D),
                                            measurements(tc[0], D), D, SIGMA_R, SIGMA_B))  # fmt: skip


@pytest.mark.parametrize(("through", "observer"), [("A", 0), ("A", 1), ("C", 0), ("C", 1)])
def test_a_one_way_sighting_is_chi_square_with_two_dof_where_two_observations_put_it(
    through: str, observer: int
) -> None:
    rng = np.random.default_rng(5)
    n = 2000
    ac, at = random_poses(rng, n, 0.8, 5.0), random_poses(rng, n, 0.8, 5.0)
    ct = se2.compose(se2.inverse(ac), at)  # T's scanner in C's frame
    keep = np.abs(ct[:, 0] + 1j * ct[:, 1] + D * np.exp(1j * ct[:, 2]) - D) > 0.5
    ac, at, ct = ac[keep], at[keep], ct[keep]

    def noisy(pose: np.ndarray) -> np.ndarray:
        return measurements(pose, D) + rng.normal(size=(len(pose), 4)) * NOISE

    pair, placed = (at, ct) if through == "A" else (ct, at)
    truth = measurements(placed, D)[:, 2 * observer : 2 * observer + 2]
    seen = truth + rng.normal(size=truth.shape) * NOISE[:2]
    d2 = sighting_distance(noisy(ac), noisy(pair), seen, through, observer, D, SIGMA_R, SIGMA_B)  # type: ignore[arg-type]
    assert d2.shape == (len(ac),)
    assert np.mean(d2) == pytest.approx(2.0, rel=0.12)
    assert np.mean(d2 > chi2.ppf(0.99, 2)) == pytest.approx(0.01, abs=0.006)
    # The sighting half a metre off is far outside.
    off = seen + np.array([0.5, 0.0])
    assert np.all(
        sighting_distance(
            measurements(ac, D), measurements(pair, D), off, through, observer, D, SIGMA_R, SIGMA_B
        )
        > 100.0
    )  # type: ignore[arg-type]
