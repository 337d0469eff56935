"""The validator: optimized stations against their search PDFs; flag, disable, re-optimize."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimation.chi2 import chi2_cdf
from estimation.errors import EstimationError
from estimation.posegraph.events import Localize
from estimation.posegraph.graph import GraphBuilder
from estimation.posegraph.keys import pose_key
from estimation.posegraph.smoother import optimize_batch
from estimation.posegraph.synthetic import leapfrog, search_pdf
from estimation.posegraph.validate import validate_and_repair, validate_stations
from sensors.geometry import se2

SIGMA_M, SIGMA_RAD = 0.05, math.radians(1.0)


@pytest.fixture(scope="module")
def mission():  # type: ignore[no-untyped-def]
    return leapfrog(30, 5, seed=4, map_prior_every=3, loop_closures=False)


def with_wrong_loop_closure(mission) -> tuple[GraphBuilder, int]:  # type: ignore[no-untyped-def]
    """The mission plus a loop closure of a20 against a10 that is 1.7 m and 11° off."""
    truth = mission.truth
    rel = se2.between(truth[pose_key("a", 10)], truth[pose_key("a", 20)])
    wrong = rel + np.array([1.5, -0.8, 0.2])
    builder = GraphBuilder()
    builder.add_all(mission.events)
    builder.add(Localize("a", 20, search_pdf(wrong, SIGMA_M, SIGMA_RAD), ("a", 10)))
    return builder, len(builder.factors) - 1


def test_clean_mission_validates(mission) -> None:  # type: ignore[no-untyped-def]
    builder = GraphBuilder()
    builder.add_all(mission.events)
    result = optimize_batch(builder.factors, builder.initial_values(), "none")
    validation = validate_stations(result.estimate, builder.factors, builder.pdfs)
    assert len(validation.checks) == 9  # a3, a6, …, a27 against the prior map
    assert validation.ok
    assert validation.flagged == ()
    assert all(c.mass_above < 0.99 for c in validation.checks)


def test_validator_flags_the_factor_that_pulled_stations_out(mission) -> None:  # type: ignore[no-untyped-def]
    builder, wrong = with_wrong_loop_closure(mission)
    result = optimize_batch(builder.factors, builder.initial_values(), "none")
    validation = validate_stations(result.estimate, builder.factors, builder.pdfs)
    failed = {(c.key, c.reference) for c in validation.failed}
    assert (pose_key("a", 20), pose_key("a", 10)) in failed  # the wrong search itself
    assert len(failed) >= 3  # and map-frame stations dragged along
    assert validation.flagged == (wrong,)
    assert "OUTSIDE the search region" in validation.failed[0].describe()


def test_repair_disables_the_flagged_factor_and_brings_stations_back(mission) -> None:  # type: ignore[no-untyped-def]
    builder, wrong = with_wrong_loop_closure(mission)
    result, rounds, enabled = validate_and_repair(
        builder.factors, builder.initial_values(), builder.pdfs, robust="none"
    )
    assert [r.flagged for r in rounds] == [(wrong,), ()]
    assert not enabled[wrong]
    assert enabled.sum() == len(builder.factors) - 1
    last = rounds[-1]
    # Only the wrong search disagrees now, and its factor is out: it flags nothing.
    assert [(c.key, c.reference, c.search_factor_kept) for c in last.failed] == [
        (pose_key("a", 20), pose_key("a", 10), False)
    ]
    keys = sorted(result.estimate)
    error = np.hypot(
        *(np.array([result.estimate[k] for k in keys]) - mission.truth_array(keys))[:, :2].T
    )
    assert error.max() < 0.3


def test_a_search_rejected_by_gnc_is_reported_but_flags_nothing(mission) -> None:  # type: ignore[no-untyped-def]
    builder, wrong = with_wrong_loop_closure(mission)
    result = optimize_batch(builder.factors, builder.initial_values(), "gnc_tls")
    assert result.outliers == [wrong]
    validation = validate_stations(
        result.estimate, builder.factors, builder.pdfs, active=result.inliers
    )
    assert [(c.key, c.search_factor_kept) for c in validation.failed] == [
        (pose_key("a", 20), False)
    ]
    assert validation.flagged == ()


def test_validator_errors(mission) -> None:  # type: ignore[no-untyped-def]
    builder = GraphBuilder()
    builder.add_all(mission.events)
    result = optimize_batch(builder.factors, builder.initial_values(), "none")
    with pytest.raises(EstimationError, match="validator: 3 flags for"):
        validate_stations(result.estimate, builder.factors, builder.pdfs, active=np.ones(3, bool))
    estimate = dict(result.estimate)
    del estimate[pose_key("a", 3)]
    with pytest.raises(EstimationError, match="validator: a3 is not in the estimate"):
        validate_stations(estimate, builder.factors, builder.pdfs)


def test_a_search_refined_by_registration_is_checked_against_its_own_factor(mission) -> None:  # type: ignore[no-untyped-def]
    """A registered search's factor carries the registration's pose and covariance, not the
    PDF's: the station is checked against that Gaussian. Here the PDF on its lattice peaks 8 cm
    (4σ) from the truth, the registration found the truth."""
    key = pose_key("a", 9)
    truth = mission.truth[key]
    events = [e for e in mission.events
              if not (isinstance(e, Localize) and (e.robot, e.index) == ("a", 9))]  # fmt: skip
    pdf = search_pdf(truth + np.array([0.08, 0.0, 0.0]), 0.02, SIGMA_RAD, half_width=10)
    tight = np.diag([0.005**2, 0.005**2, math.radians(0.1) ** 2])
    builder = GraphBuilder()
    builder.add_all(events)
    builder.add(Localize("a", 9, pdf, pose=truth.copy(), covariance=tight))
    result = optimize_batch(builder.factors, builder.initial_values(), "none")
    validation = validate_stations(result.estimate, builder.factors, builder.pdfs)
    (check,) = [c for c in validation.checks if c.key == key]
    assert check.search_factor_kept
    assert check.inside
    assert not pdf.contains(check.pose, 0.99)  # against its PDF it would lie outside
    assert validation.ok
    # 3 cm off the registration (6σ): outside, with the Gaussian's mass above it.
    moved = dict(result.estimate)
    moved[key] = moved[key] + np.array([0.0, 0.03, 0.0])
    (check,) = [c for c in validate_stations(moved, builder.factors, builder.pdfs).checks
                if c.key == key]  # fmt: skip
    assert not check.inside
    assert check.search_factor_kept
    assert check.mass_above == pytest.approx(chi2_cdf(36.0, 3), abs=0.02)
