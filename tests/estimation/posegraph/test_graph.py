"""The graph builder: keys, factors from events, covariance conventions, the gate in front."""

from __future__ import annotations

import math
import re

import gtsam
import numpy as np
import pytest

from estimation.errors import EstimationError
from estimation.posegraph.events import Localize, Move, Observe, Start
from estimation.posegraph.graph import (
    FactorSpec,
    GraphBuilder,
    GraphSettings,
    mutual_between,
    odometry_covariance,
)
from estimation.posegraph.gtsam_factors import to_gtsam_factor, to_gtsam_values
from estimation.posegraph.keys import key_label, pose_key, split_key
from estimation.posegraph.mutual import localize_mutual
from estimation.posegraph.structure import check_constrained
from estimation.posegraph.synthetic import leapfrog, mutual_measurements, search_pdf, visible
from sensors.geometry import se2

S = GraphSettings()


def test_keys_come_from_gtsam_symbols() -> None:
    key = pose_key("b", 17)
    assert key == gtsam.symbol("b", 17)
    assert split_key(key) == ("b", 17)
    assert key_label(key) == "b17"
    for bad, pattern in [("ab", "one lowercase letter"), ("B", "one lowercase letter")]:
        with pytest.raises(EstimationError, match=pattern):
            pose_key(bad, 0)
    with pytest.raises(EstimationError, match="pose index must be an integer"):
        pose_key("a", -1)


def test_se2_helpers_agree_with_gtsam() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        p, q = rng.normal(size=3), rng.normal(size=3)
        gp, gq = gtsam.Pose2(*p), gtsam.Pose2(*q)
        c = gp.compose(gq)
        np.testing.assert_allclose(se2.compose(p, q), [c.x(), c.y(), c.theta()], atol=1e-12)
        b = gp.between(gq)
        np.testing.assert_allclose(se2.between(p, q), [b.x(), b.y(), b.theta()], atol=1e-12)
        np.testing.assert_allclose(se2.adjoint(p), gp.AdjointMap(), atol=1e-12)
        log = gtsam.Pose2.Logmap(gp)
        np.testing.assert_allclose(se2.log(p), log, atol=1e-10)
        e = gtsam.Pose2.Expmap(log)
        np.testing.assert_allclose(se2.exp(log), [e.x(), e.y(), e.theta()], atol=1e-10)


def test_mutual_between_covariance_matches_monte_carlo_in_gtsam_chart() -> None:
    """The factor's covariance is what GTSAM's BetweenFactorPose2 expects: the spread of
    ``measured⁻¹ ∘ sample`` of relative robot poses built from noisy raw measurements."""
    rng = np.random.default_rng(1)
    T_a, T_c = np.array([1.0, 2.0, 0.3]), np.array([3.5, 0.5, 2.2])
    z0 = mutual_measurements(T_a, T_c, S)
    noise = np.array([S.range_sigma_m, S.bearing_sigma_rad] * 2)
    fix = localize_mutual(*z0, S.beacon_offset_m, S.range_sigma_m, S.bearing_sigma_rad)
    T_true, cov = mutual_between(fix.pose, fix.covariance, S.scanner_x_m)
    np.testing.assert_allclose(T_true, se2.between(T_a, T_c), atol=1e-9)
    samples = []
    for _ in range(4000):
        z = z0 + rng.normal(size=4) * noise
        f = localize_mutual(*z, S.beacon_offset_m, S.range_sigma_m, S.bearing_sigma_rad)
        T, _ = mutual_between(f.pose, f.covariance, S.scanner_x_m)
        samples.append(se2.between(T_true, T))
    empirical = np.cov(np.array(samples).T)
    np.testing.assert_allclose(np.sqrt(np.diag(empirical)), np.sqrt(np.diag(cov)), rtol=0.06)


def test_factor_residual_matches_gtsam_error() -> None:
    cov = np.diag([0.01, 0.02, 0.003])
    spec = FactorSpec(
        "mutual", (pose_key("a", 0), pose_key("b", 0)), np.array([1.0, 0.2, 0.1]), cov, 0
    )
    poses = {
        pose_key("a", 0): np.array([0.3, 0.1, 0.2]),
        pose_key("b", 0): np.array([1.4, 0.3, 0.25]),
    }
    factor = to_gtsam_factor(spec)
    assert factor.error(to_gtsam_values(poses)) == pytest.approx(0.5 * spec.mahalanobis2(poses))
    prior = FactorSpec("prior", (pose_key("a", 0),), np.array([0.2, 0.0, 0.1]), cov, 0)
    assert to_gtsam_factor(prior).error(to_gtsam_values(poses)) == pytest.approx(
        0.5 * prior.mahalanobis2(poses)
    )
    robust = to_gtsam_factor(spec, "cauchy")
    assert robust.error(to_gtsam_values(poses)) < factor.error(to_gtsam_values(poses))


def test_odometry_sigmas_grow_with_distance_and_turn() -> None:
    cov = odometry_covariance(np.array([3.0, 4.0, -1.0]), 0.01, 0.05, math.radians(0.5),
                              math.radians(2.0))  # fmt: skip
    assert math.sqrt(cov[0, 0]) == pytest.approx(0.01 + 0.05 * 5.0)
    assert math.sqrt(cov[2, 2]) == pytest.approx(math.radians(0.5) + math.radians(2.0))


def test_odometry_sigmas_follow_the_motion_driven_not_the_net_move() -> None:
    """A sideways step of 1 m (forward 1 m, left 1 m, back to the heading: 1.57 rad of turns
    each way, 3 rad in all, 2 m driven) ends at net yaw 0 and a net 1 m."""
    delta = np.array([0.0, 1.0, 0.0])
    sigmas = (0.01, 0.05, math.radians(0.5), math.radians(2.0))
    net = odometry_covariance(delta, *sigmas)
    driven = odometry_covariance(delta, *sigmas, motion=(2.0, 3.0))
    assert math.sqrt(net[0, 0]) == pytest.approx(0.01 + 0.05 * 1.0)
    assert math.sqrt(net[2, 2]) == pytest.approx(math.radians(0.5))  # no net turn
    assert math.sqrt(driven[0, 0]) == pytest.approx(0.01 + 0.05 * 2.0)
    assert math.sqrt(driven[1, 1]) == pytest.approx(0.01 + 0.05 * 2.0)
    assert math.sqrt(driven[2, 2]) == pytest.approx(math.radians(0.5) + math.radians(2.0) * 3.0)
    np.testing.assert_array_equal(driven, np.diag(np.diag(driven)))
    # A turn in place: no distance, but the angle turned (not the net yaw, wrapped to 0.28 rad).
    spun = odometry_covariance(np.array([0.0, 0.0, 2 * math.pi - 6.0]), *sigmas,
                               motion=(0.0, 6.0))  # fmt: skip
    assert math.sqrt(spun[0, 0]) == pytest.approx(0.01)
    assert math.sqrt(spun[2, 2]) == pytest.approx(math.radians(0.5) + math.radians(2.0) * 6.0)
    # motion=None is the net move: the old behaviour.
    np.testing.assert_array_equal(odometry_covariance(delta, *sigmas, motion=None), net)


def test_a_moves_motion_sets_its_factors_covariance() -> None:
    builder = GraphBuilder(S)
    builder.add(Start("a", 0, (0.0, 0.0, 0.0)))
    delta = (0.0, 1.0, 0.0)
    plain = builder.add(Move("a", 1, delta)).factors[0]
    driven = builder.add(Move("a", 2, delta, motion=(2.0, 3.0))).factors[0]
    sigmas = (S.odometry_sigma_m, S.odometry_sigma_per_m, S.odometry_sigma_rad,
              S.odometry_sigma_rad_per_rad)  # fmt: skip
    np.testing.assert_array_equal(plain.covariance, odometry_covariance(np.array(delta), *sigmas))
    np.testing.assert_array_equal(
        driven.covariance, odometry_covariance(np.array(delta), *sigmas, motion=(2.0, 3.0))
    )
    assert driven.covariance[2, 2] > 50 * plain.covariance[2, 2]
    assert driven.kind == "odometry"
    assert driven.keys == (pose_key("a", 1), pose_key("a", 2))
    np.testing.assert_array_equal(driven.measurement, delta)
    # The motion changes the uncertainty only, not the guess.
    np.testing.assert_allclose(builder.guesses[pose_key("a", 2)], [0.0, 2.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("motion", [(math.nan, 0.0), (1.0, math.inf), (-1.0, 0.0), (1.0, -0.5)])
def test_a_move_with_an_impossible_motion_is_an_error(motion: tuple[float, float]) -> None:
    """Distance driven and angle turned are finite and >= 0, as ``Move.delta`` is checked for
    being finite: otherwise the factor's covariance is NaN, or its sigmas shrink with the
    motion (down to 0 and below) instead of growing."""
    builder = GraphBuilder(S)
    builder.add(Start("a", 0, (0.0, 0.0, 0.0)))
    with pytest.raises(EstimationError, match=r"Move\.motion"):
        builder.add(Move("a", 1, (1.0, 0.0, 0.0), motion=motion))
    assert [f.kind for f in builder.factors] == ["prior"]


def two_robots() -> tuple[GraphBuilder, np.ndarray, np.ndarray]:
    builder = GraphBuilder(S)
    T_a, T_b = np.array([0.0, 0.0, 0.0]), np.array([2.0, 1.5, -2.0])
    builder.add(Start("a", 0, (0.0, 0.0, 0.0)))
    builder.add(Observe(("a", 0), ("b", 0), *mutual_measurements(T_a, T_b, S)))
    return builder, T_a, T_b


def test_events_become_factors_and_initial_values() -> None:
    builder, _, T_b = two_robots()
    assert [f.kind for f in builder.factors] == ["prior", "mutual"]
    np.testing.assert_allclose(builder.guesses[pose_key("b", 0)], T_b, atol=1e-9)
    increment = builder.add(Move("b", 1, (1.0, 0.0, 0.5)))
    np.testing.assert_allclose(
        increment.values[pose_key("b", 1)], se2.compose(T_b, [1.0, 0.0, 0.5])
    )
    assert increment.factors[0].kind == "odometry"
    assert increment.factors[0].keys == (pose_key("b", 0), pose_key("b", 1))
    assert builder.events == 3


def test_a_dominant_search_seeds_a_station_and_a_flat_one_does_not() -> None:
    builder, _, _ = two_robots()
    truth = np.array([4.0, 3.0, 1.0])
    increment = builder.add(Localize("a", 5, search_pdf(truth, 0.05, math.radians(1.0))))
    np.testing.assert_allclose(increment.values[pose_key("a", 5)], truth, atol=1e-6)
    assert increment.factors[0].kind == "global"
    # An existing, odometry-only station: a dominant search that agrees with the dead
    # reckoning (within its uncertainty) replaces the guess; a gross one does not.
    builder.add(Move("a", 6, (1.0, 0.0, 0.0)))
    dead_reckoned = se2.compose(truth, np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(builder.guesses[pose_key("a", 6)], dead_reckoned)
    builder.add(Move("a", 7, (1.0, 0.0, 0.0)))
    wrong = se2.compose(dead_reckoned, np.array([2.0, 0.5, 0.0]))
    builder.add(Localize("a", 7, search_pdf(se2.compose(wrong, [1.0, 0, 0]), 0.05, 0.02)))
    np.testing.assert_allclose(
        builder.guesses[pose_key("a", 7)], se2.compose(dead_reckoned, [1.0, 0, 0])
    )
    seeded = se2.compose(dead_reckoned, np.array([0.06, -0.04, 0.02]))
    builder.add(Localize("a", 6, search_pdf(seeded, 0.05, math.radians(1.0))))
    np.testing.assert_allclose(builder.guesses[pose_key("a", 6)], seeded, atol=1e-6)
    flat = search_pdf(truth, 2.0, 0.5)  # no dominant peak
    assert not flat.is_dominant(S.dominance_ratio, S.peak_radius_m, S.peak_radius_rad)
    rejected = builder.add(Localize("a", 9, flat))
    assert rejected.rejection is not None
    assert "a9 is new and its search peak is not dominant" in rejected.rejection.reason


def test_a_search_result_pose_is_the_factor_measurement_and_seed() -> None:
    """A ``Localize`` that carries the search's refined pose measures that pose, not the PDF's
    lattice peak; it also seeds a new station with it. A non-finite pose is an error."""
    builder, _, _ = two_robots()
    truth = np.array([4.0, 3.0, 1.0])
    pdf = search_pdf(truth, 0.05, math.radians(1.0))
    refined = truth + np.array([0.013, -0.021, math.radians(0.3)])
    increment = builder.add(Localize("a", 5, pdf, pose=tuple(refined)))
    np.testing.assert_allclose(increment.factors[0].measurement, refined, atol=1e-12)
    np.testing.assert_allclose(increment.values[pose_key("a", 5)], refined, atol=1e-12)
    assert np.abs(pdf.best_pose() - refined).max() > 0.005  # the PDF alone would differ
    with pytest.raises(EstimationError, match=r"Localize\.pose must be 3 finite numbers"):
        builder.add(Localize("a", 6, pdf, pose=(1.0, math.nan, 0.0)))


def test_loop_closure_relative_to_an_earlier_station() -> None:
    builder, _, _ = two_robots()
    builder.add(Move("a", 1, (2.0, 0.0, 0.1)))
    rel = np.array([2.0, 0.0, 0.1])
    increment = builder.add(Localize("a", 1, search_pdf(rel, 0.05, 0.02), ("a", 0)))
    spec = increment.factors[0]
    assert spec.keys == (pose_key("a", 0), pose_key("a", 1))
    np.testing.assert_allclose(spec.measurement, rel, atol=1e-6)
    # The factor's covariance: the PDF's, in the measurement's tangent space, floored.
    assert np.sqrt(spec.covariance[0, 0]) > S.global_min_sigma_m


@pytest.mark.parametrize(
    ("events", "pattern"),
    [
        ([Move("a", 1, (1.0, 0.0, 0.0))], "robot 'a' moves but has no pose yet"),
        (
            [Start("a", 3), Move("a", 2, (1.0, 0.0, 0.0))],
            "moves to pose 2, not after its latest pose 3",
        ),
        (
            [Start("a", 0), Observe(("b", 0), ("c", 0), 2.0, 0.5, 2.0, 0.5)],
            "neither b0 nor c0 is known",
        ),
        (
            [Start("a", 0), Observe(("a", 0), ("a", 1), 2.0, 0.5, 2.0, 0.5)],
            "robot 'a' cannot observe itself",
        ),
        (
            [Start("a", 0), Observe(("a", 0), ("b", 0), math.nan, 0.5, 2.0, 0.5)],
            r"Observe measurement holds NaN or inf: \[nan",
        ),
        ([Start("a", 0), Move("a", 1, (math.inf, 0.0, 0.0))], "Move.delta holds NaN or inf"),
        (
            [Start("a", 0), Localize("a", 1, search_pdf(np.zeros(3), 0.05, 0.02), ("a", 7))],
            "reference station a7 is not in the graph",
        ),
        (
            [Start("a", 0), Localize("a", 0, search_pdf(np.zeros(3), 0.05, 0.02), ("a", 0))],
            "cannot be localized against itself",
        ),
        ([Start("ab", 0)], "robot name must be one lowercase letter"),
        ([Start("a", 0), "not an event"], "unknown event type str"),
    ],
)
def test_inconsistent_event_streams_are_errors(events: list, pattern: str) -> None:  # type: ignore[type-arg]
    builder = GraphBuilder(S)
    builder.add_all(events[:-1])
    with pytest.raises(EstimationError, match=pattern):
        builder.add(events[-1])


def test_degenerate_and_inconsistent_observations_are_rejected_with_a_reason() -> None:
    builder, _, _ = two_robots()
    d = S.beacon_offset_m
    degenerate = builder.add(Observe(("a", 0), ("b", 0), 2.0, 0.5, d, 0.0))
    assert degenerate.rejection is not None
    assert "degenerate geometry: b·e^(iβ) ≈ d" in degenerate.rejection.reason
    z = mutual_measurements(np.zeros(3), np.array([2.0, 1.5, -2.0]), S)
    inconsistent = builder.add(Observe(("a", 0), ("b", 0), z[0] + 0.3, z[1], z[2], z[3]))
    assert inconsistent.rejection is not None
    pattern = r"s1/s2 gate: \|s1 - s2\| = 0\.(29|30)\d m is \d+\.\d sigma \(limit 3\)"
    assert re.match(pattern, inconsistent.rejection.reason)
    assert len(builder.rejections) == 2
    assert [f.kind for f in builder.factors] == ["prior", "mutual"]


def test_settings_are_validated() -> None:
    with pytest.raises(
        EstimationError, match=r"GraphSettings\.range_sigma_m must be positive, got 0"
    ):
        GraphSettings(range_sigma_m=0.0)
    with pytest.raises(EstimationError, match=r"prediction_gate_probability must be in \(0, 1\)"):
        GraphSettings(prediction_gate_probability=1.0)


# -- the gate against distractors ----------------------------------------------------------------


def gate_trial(rng: np.random.Generator, distractor: bool) -> bool:
    """One trial: b seen at b0, moves (odometry), is observed again; is the event rejected?

    A distractor is a reflective object at beacon height somewhere in a 12 m × 9 m room around
    the robots, detected instead of one of the two beacons (either robot's observation).
    """
    while True:
        T_b0 = np.array([*rng.uniform(-4.0, 4.0, 2), rng.uniform(-np.pi, np.pi)])
        step = np.array([rng.uniform(0.3, 1.5), rng.normal(0, 0.3), rng.normal(0, 0.8)])
        T_b1 = se2.compose(T_b0, step)
        if visible(np.zeros(3), T_b0, S) and visible(np.zeros(3), T_b1, S):
            break
    cov = odometry_covariance(step, S.odometry_sigma_m, S.odometry_sigma_per_m,
                              S.odometry_sigma_rad, S.odometry_sigma_rad_per_rad)  # fmt: skip
    measured_step = se2.compose(step, rng.multivariate_normal(np.zeros(3), cov))
    noise = np.array([S.range_sigma_m, S.bearing_sigma_rad] * 2)
    z0 = mutual_measurements(np.zeros(3), T_b0, S) + rng.normal(size=4) * noise
    z1 = mutual_measurements(np.zeros(3), T_b1, S) + rng.normal(size=4) * noise
    if distractor:
        T_r_s = np.array([S.scanner_x_m, 0.0, 0.0])
        true_beacon = se2.compose(T_b1, np.array([S.scanner_x_m + S.beacon_offset_m, 0, 0]))[:2]
        observer = (
            se2.compose(np.zeros(3), T_r_s) if rng.random() < 0.5 else se2.compose(T_b1, T_r_s)
        )
        while True:
            p = np.array([rng.uniform(-6.0, 6.0), rng.uniform(-4.5, 4.5)])
            local = se2.between(observer, np.array([*p, 0.0]))
            r, phi = math.hypot(local[0], local[1]), math.atan2(local[1], local[0])
            if 0.5 < r < 7.5 and abs(phi) > math.radians(10) and np.hypot(*(p - true_beacon)) > 0.3:
                break
        slot = 0 if observer[0] == S.scanner_x_m and observer[1] == 0.0 else 2
        z1[slot], z1[slot + 1] = (
            r + rng.normal(0, S.range_sigma_m),
            phi + rng.normal(0, S.bearing_sigma_rad),
        )
    builder = GraphBuilder(S)
    builder.add(Start("a", 0))
    first = builder.add(Observe(("a", 0), ("b", 0), *z0))
    if first.rejection is not None:  # the reference fix itself fell in the tail: start over
        return gate_trial(rng, distractor)
    builder.add(
        Move("b", 1, (float(measured_step[0]), float(measured_step[1]), float(measured_step[2])))
    )
    return builder.add(Observe(("a", 0), ("b", 1), *z1)).rejection is not None


def test_gate_rejects_99_percent_of_distractors_and_at_most_2_percent_of_true_events() -> None:
    rng = np.random.default_rng(7)
    trials = 1500
    false_rejections = np.mean([gate_trial(rng, distractor=False) for _ in range(trials)])
    rejections = np.mean([gate_trial(rng, distractor=True) for _ in range(trials)])
    assert rejections >= 0.99
    assert false_rejections <= 0.02


def test_prediction_gate_catches_what_the_separation_check_cannot() -> None:
    """A wrong geometry that keeps s1 = s2 passes the paper's check; the prediction gate stops it."""
    builder, T_a, T_b = two_robots()
    builder.add(Move("b", 1, (0.5, 0.0, 0.2)))
    T_b1 = se2.compose(T_b, np.array([0.5, 0.0, 0.2]))
    wrong = se2.compose(np.array([1.5, -1.0, 0.8]), T_b1)
    z = mutual_measurements(T_a, wrong, S)
    increment = builder.add(Observe(("a", 0), ("b", 1), *z))
    assert increment.rejection is not None
    assert increment.rejection.reason.startswith("prediction gate: Mahalanobis²")
    right = builder.add(Observe(("a", 0), ("b", 1), *mutual_measurements(T_a, T_b1, S)))
    assert right.rejection is None


def test_prediction_gate_takes_the_tightest_chain_through_a_third_robot() -> None:
    """Generated building 402 in shape: a and c last saw each other before long drives with
    many turns, so their own fix predicts their relative heading to about 20°; b has just seen
    both. An observation of c 50° off the truth (s1 = s2 kept) passes the pair's own prediction
    and not the one through b; the true one passes both."""
    T_a0, T_c0 = np.array([0.0, 0.0, 0.0]), np.array([2.2, 0.3, 3.0])
    T_a1, T_c1 = np.array([4.0, 3.0, 1.2]), np.array([5.5, 5.0, -2.0])
    T_b0 = np.array([6.0, 2.5, 2.4])
    wrong = se2.compose(T_c1, np.array([0.0, 0.0, math.radians(50.0)]))

    def mission(with_b: bool) -> GraphBuilder:
        builder = GraphBuilder(S)
        builder.add(Start("a", 0, tuple(T_a0)))  # type: ignore[arg-type]
        builder.add(Observe(("a", 0), ("c", 0), *mutual_measurements(T_a0, T_c0, S)))
        builder.add(Move("a", 1, tuple(se2.between(T_a0, T_a1)), motion=(6.0, 3.0)))
        builder.add(Move("c", 1, tuple(se2.between(T_c0, T_c1)), motion=(8.5, 8.0)))
        if with_b:
            builder.add(Observe(("a", 1), ("b", 0), *mutual_measurements(T_a1, T_b0, S)))
            builder.add(Observe(("b", 0), ("c", 1), *mutual_measurements(T_b0, T_c1, S)))
        return builder

    false = Observe(("a", 1), ("c", 1), *mutual_measurements(T_a1, wrong, S))
    assert mission(with_b=False).add(false).rejection is None  # 50° is 2.4 σ of 21°
    rejected = mission(with_b=True).add(false).rejection
    assert rejected is not None
    assert rejected.reason.startswith("prediction gate")
    # The prediction is the chain through b (its two fresh fixes), not the pair's drives.
    builder = mission(with_b=True)
    predicted = builder._predict("a", 1, "c", 1)
    assert predicted is not None
    np.testing.assert_allclose(predicted[0], se2.between(T_a1, T_c1), atol=1e-6)
    assert math.sqrt(predicted[1][2, 2]) < math.radians(1.0)
    true = Observe(("a", 1), ("c", 1), *mutual_measurements(T_a1, T_c1, S))
    assert builder.add(true).rejection is None


def test_leapfrog_stream_builds_a_consistent_graph() -> None:
    scenario = leapfrog(20, 5, seed=3)
    builder = GraphBuilder(S)
    builder.add_all(scenario.events)
    assert len(builder.guesses) == 20 * 6
    check_constrained(builder.factors, builder.guesses)
    chi2_at_truth = [f.mahalanobis2(scenario.truth) for f in builder.factors if f.kind != "prior"]
    # calibrated noise: mean χ² per 3-dof factor near 3
    assert np.mean(chi2_at_truth) == pytest.approx(3.0, abs=0.6)


@pytest.mark.parametrize(
    ("noise", "low", "high"),
    [(0.03, 0.1, 0.1), (1.0, 0.75, 1.3), (2.0, 1.5, 2.6), (1.0, 1.0, 1.0)],
)
def test_mutual_noise_follows_the_gaps_accepted_so_far(
    noise: float, low: float, high: float
) -> None:
    # Measurements ``noise`` times as noisy as configured: after ten observations each factor's
    # standard deviations are the configured ones times the gaps' robust spread (≈ noise),
    # never below ``mutual_scale_min``; the last case switches the scaling off.
    off = (noise, low, high) == (1.0, 1.0, 1.0)
    settings = GraphSettings(mutual_scale_min=None) if off else S
    builder = GraphBuilder(settings)
    builder.add(Start("a", 0, (0.0, 0.0, 0.0)))
    rng = np.random.default_rng(4)
    sigmas = np.array([S.range_sigma_m, S.bearing_sigma_rad] * 2)
    ratios = []
    for i in range(60):
        T_b = np.array([2.0 + 0.02 * i, 1.5 - 0.03 * i, math.pi - 0.4 + 0.01 * i])
        z = mutual_measurements(np.zeros(3), T_b, S) + noise * sigmas * rng.standard_normal(4)
        before = builder.mutual_scale()
        increment = builder.add(Observe(("a", 0), ("b", i), *z))
        if increment.rejection is not None:
            continue
        fix = localize_mutual(*z, S.beacon_offset_m, S.range_sigma_m, S.bearing_sigma_rad,
                              S.gate_sigmas, "ml")  # fmt: skip
        factor = increment.factors[0]
        # The factor's covariance against the configured one, in the robot frames.
        _, configured = mutual_between(fix.pose, fix.covariance, S.scanner_x_m)
        ratio = math.sqrt(float(np.trace(factor.covariance) / np.trace(configured)))
        assert ratio == pytest.approx(before)
        ratios.append(ratio)
    assert len(ratios) >= 50  # the s1/s2 gate (3σ of the configured noise) kept most
    assert ratios[:10] == pytest.approx([1.0] * 10)
    # Within the clip always; near the truth once the gaps are many (a median of ten still
    # scatters by tens of per cent).
    assert all(0.1 - 1e-9 <= r <= 3.0 + 1e-9 for r in ratios)
    assert low - 1e-9 <= float(np.mean(ratios[-10:])) <= high + 1e-9


def test_mutual_scale_min_is_validated() -> None:
    with pytest.raises(EstimationError, match=r"mutual_scale_min must be at most 1"):
        GraphSettings(mutual_scale_min=1.5)
    with pytest.raises(EstimationError, match=r"GraphSettings\.mutual_scale_min must be positive"):
        GraphSettings(mutual_scale_min=0.0)


def test_an_observation_far_outside_the_gaps_spread_is_rejected() -> None:
    # Clean observations (a tenth of the configured noise), then one whose s1 - s2 gap passes
    # the configured 3σ gate but lies far beyond the spread of the gaps so far: a false
    # detection that would enter with the clean ones' small covariance. It is rejected; with
    # the scaling off, or before ten gaps are in, it passes.
    rng = np.random.default_rng(9)
    sigmas = np.array([S.range_sigma_m, S.bearing_sigma_rad] * 2)

    def observations(builder: GraphBuilder, count: int) -> None:
        for i in range(count):
            T_b = np.array([2.0 + 0.02 * i, 1.5 - 0.03 * i, math.pi - 0.4 + 0.01 * i])
            z = mutual_measurements(np.zeros(3), T_b, S) + 0.1 * sigmas * rng.standard_normal(4)
            builder.add(Observe(("a", 0), ("b", i), *z))

    T_b = np.array([2.5, 1.0, math.pi - 0.3])
    z = mutual_measurements(np.zeros(3), T_b, S)
    z[0] += 0.04  # A's range to C's beacon 4 cm long: s1 - s2 ≈ 1.4σ of the configured noise
    fix = localize_mutual(*z, S.beacon_offset_m, S.range_sigma_m, S.bearing_sigma_rad,
                          S.gate_sigmas, "ml")  # fmt: skip
    assert fix.accepted
    assert 0.7 < fix.gap_sigmas < 3.0
    for settings, count, rejected in ((S, 30, True), (GraphSettings(mutual_scale_min=None), 30,
                                                        False), (S, 5, False)):  # fmt: skip
        builder = GraphBuilder(settings)
        builder.add(Start("a", 0, (0.0, 0.0, 0.0)))
        observations(builder, count)
        before = len(builder.rejections)
        increment = builder.add(Observe(("a", 0), ("b", 99), *z))
        assert (increment.rejection is not None) == rejected
        if rejected:
            assert len(builder.rejections) == before + 1
            assert re.search(r"times the gaps' spread \(limit 5\)", increment.rejection.reason)
