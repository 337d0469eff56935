"""Paper eq. 3 and its log-odds form, through the grid: updates, clamping and merging."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapping.errors import MapError
from mapping.grid import GridParams, OccupancyGrid
from mapping.logodds import bayes_update, logodds, probability

#: Clamps so wide that no sequence below reaches them: the pure eq. 3 regime.
WIDE = GridParams(clamp_min=1e-12, clamp_max=1 - 1e-12)
CELL = np.array([[3, -2, 7]])


def test_logodds_and_probability_are_inverse() -> None:
    p = np.linspace(0.001, 0.999, 999)
    np.testing.assert_allclose(probability(logodds(p)), p, atol=1e-15)
    assert logodds(0.5) == 0.0
    assert probability(0.0) == 0.5


def test_eq3_matches_the_closed_form_on_known_values() -> None:
    # A prior of 0.5 takes the evidence's value; two hits of 0.7 give 0.7² / (0.7² + 0.3²).
    assert bayes_update(0.5, 0.7) == pytest.approx(0.7, abs=1e-15)
    assert bayes_update(0.7, 0.7) == pytest.approx(0.49 / 0.58, abs=1e-15)
    assert bayes_update(0.3, 0.5) == pytest.approx(0.3, abs=1e-15)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(0.02, 0.98), min_size=1, max_size=40))
def test_grid_updates_equal_eq3_over_random_evidence(evidence: list[float]) -> None:
    grid = OccupancyGrid(WIDE)
    expected = 0.5
    for e in evidence:
        grid.apply_evidence(CELL, np.array([e]))
        expected = float(bayes_update(expected, e))
        got = float(probability(grid.logodds_at(CELL))[0])
        assert abs(got - expected) < 1e-6  # float32 storage: one rounding (≤ 2.4e-7) a step


def test_evidence_listed_twice_counts_twice_in_order() -> None:
    grid = OccupancyGrid(WIDE)
    grid.apply_evidence(np.array([[0, 0, 0], [0, 0, 0], [1, 0, 0]]), np.array([0.8, 0.3, 0.6]))
    p = probability(grid.logodds_at(np.array([[0, 0, 0], [1, 0, 0]])))
    np.testing.assert_allclose(p, [bayes_update(bayes_update(0.5, 0.8), 0.3), 0.6], atol=1e-12)


def test_clamping_keeps_the_map_updatable() -> None:
    params = GridParams()  # OctoMap's clamps: 0.1192 and 0.971
    grid = OccupancyGrid(params)
    grid.apply_evidence(np.repeat(CELL, 50, axis=0), np.full(50, params.prob_hit))
    # float32 storage: the clamp is the float32 nearest to l(0.971) from inside.
    assert probability(grid.logodds_at(CELL))[0] == pytest.approx(params.clamp_max, abs=1e-7)
    assert probability(grid.logodds_at(CELL))[0] <= params.clamp_max
    # One miss after saturation moves the cell at once (no hidden excess of evidence).
    grid.apply_evidence(CELL, np.array([params.prob_miss]))
    expected = bayes_update(params.clamp_max, params.prob_miss)
    assert probability(grid.logodds_at(CELL))[0] == pytest.approx(expected, abs=1e-7)
    grid.apply_evidence(np.repeat(CELL, 50, axis=0), np.full(50, params.prob_miss))
    assert probability(grid.logodds_at(CELL))[0] == pytest.approx(params.clamp_min, abs=1e-7)
    assert probability(grid.logodds_at(CELL))[0] >= params.clamp_min


def test_scans_saturate_at_the_clamps() -> None:
    params = GridParams()
    grid = OccupancyGrid(params)
    for _ in range(20):
        grid.integrate_scan(np.array([[1.05, 0.05, 0.05]]), np.array([0.05, 0.05, 0.05]))
    values = grid.logodds_at(np.array([[10, 0, 0], [5, 0, 0]]))
    np.testing.assert_allclose(values, [params.logodds_max, params.logodds_min], atol=1e-12)


def test_merging_two_grids_is_eq3_per_cell() -> None:
    rng = np.random.default_rng(4)
    a, b = OccupancyGrid(WIDE), OccupancyGrid(WIDE)
    cells_a = rng.integers(-40, 40, (300, 3))
    cells_b = np.vstack([cells_a[:150], rng.integers(-40, 40, (150, 3))])
    a.apply_evidence(cells_a, rng.uniform(0.05, 0.95, len(cells_a)))
    b.apply_evidence(cells_b, rng.uniform(0.05, 0.95, len(cells_b)))
    both = np.unique(np.vstack([cells_a, cells_b]), axis=0)
    pa = probability(np.nan_to_num(a.logodds_at(both)))
    pb = probability(np.nan_to_num(b.logodds_at(both)))
    a.merge(b)
    merged = probability(a.logodds_at(both))
    np.testing.assert_allclose(merged, bayes_update(pa, pb), atol=1e-9)
    assert a.known_count() == len(both)


@pytest.mark.parametrize(
    ("evidence", "message"),
    [([0.0], r"evidence must lie in \(0, 1\), got 0\.0 at index 0"),
     ([0.5, 1.0], r"need one evidence value per cell: 2 for 1"),
     ([float("nan")], r"evidence must lie in \(0, 1\), got nan")],
)  # fmt: skip
def test_bad_evidence_is_rejected(evidence: list[float], message: str) -> None:
    grid = OccupancyGrid()
    with pytest.raises(MapError, match=message):
        grid.apply_evidence(CELL, np.array(evidence))
    assert grid.known_count() == 0
