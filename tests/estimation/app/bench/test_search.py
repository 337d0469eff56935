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
