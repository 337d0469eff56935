"""The search benchmark's best-pose comparison: the same answer, both times reported."""

from __future__ import annotations

import math

from estimation.app.bench.search import compare_best_pose
from estimation.search.exhaustive import SearchParams

PARAMS = SearchParams(angular_resolution_rad=math.radians(4.0))


def test_best_pose_and_full_search_agree_on_a_case_where_bounds_prune_little() -> None:
    case = compare_best_pose("6 m map, 2 m view", 6.0, 2.0, PARAMS, 0.1, repeats=2, seed=1)
    assert case["case"] == "6 m map, 2 m view"
    assert case["same_score"] is True
    assert 0 < case["best_pose_seconds"] <= case["best_pose_seconds_max"]
    assert 0 < case["full_seconds"] <= case["full_seconds_max"]
    assert case["best_over_full"] == case["best_pose_seconds"] / case["full_seconds"]


def test_coarse_to_fine_case_reports_time_memory_and_agreement_with_the_exhaustive_search() -> None:
    from estimation.app.bench.search import run_coarse_to_fine_case

    case = run_coarse_to_fine_case(PARAMS, 20.0, 8.0, 0.1, repeats=1, compare=True, seed=2)
    assert case["poses"] == 200 * 200 * 90
    assert 0 < case["poses_evaluated"] < case["poses"]
    assert case["same_lattice_pose"] is True
    assert case["pose_difference_m"] < 1e-6
    assert case["exhaustive_mass_outside"] <= case["unevaluated_mass"] + 1e-7
    assert case["total_variation"] <= case["unevaluated_mass"] + 1e-4
    assert case["error_m"] < 0.1
    assert case["error_deg"] < 1.0
    assert 0 < case["peak_numpy_bytes"] < 500e6
    assert 0 < case["seconds"] <= case["seconds_max"]
