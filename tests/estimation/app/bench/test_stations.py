"""The station benchmark's growth exponent on synthetic per-station timings."""

from __future__ import annotations

import numpy as np
import pytest

from estimation.app.bench.stations import growth_exponent


@pytest.mark.parametrize("alpha", [0.0, 0.5, 1.0])
def test_growth_exponent_recovers_a_power_law_through_noise(alpha: float) -> None:
    rng = np.random.default_rng(1)
    n = np.arange(1, 201, dtype=np.float64)
    work = 0.02 * n**alpha * rng.lognormal(0.0, 0.3, len(n))
    assert growth_exponent(work) == pytest.approx(alpha, abs=0.08)


def test_growth_exponent_of_work_that_grows_with_the_mission_is_above_the_target() -> None:
    """Re-fusing every older station per search: work ∝ n, far above 0.2; stations without
    work (no search) are left out."""
    n = np.arange(1, 161, dtype=np.float64)
    work = np.where(n % 7 == 0, 0.0, 1e4 * (5 + n))
    assert growth_exponent(work) > 0.5


def test_growth_exponent_needs_enough_stations() -> None:
    with pytest.raises(ValueError, match="need at least 16 stations with work, got 3"):
        growth_exponent(np.array([1.0, 2.0, 0.0, 3.0]))


def test_the_route_visits_every_room_nearest_first_and_comes_back_the_same_way() -> None:
    from estimation.app.bench.stations import _route

    class Site:
        def __init__(self) -> None:
            self.places_xy = [np.array(p) for p in ([9.0, 0.0], [1.0, 0.0], [4.0, 0.0], [2.0, 5.0])]

        def rooms_by_floor(self) -> list[tuple[str, np.ndarray]]:
            return [(f"room{k}", p[None, :]) for k, p in enumerate(self.places_xy)]

        def places(self, points: np.ndarray, rng: np.random.Generator) -> list[np.ndarray]:
            return [points[0]]

    route = _route(Site(), np.array([0.0, 0.0, 0.0]), np.random.default_rng(0))
    there = [[1.0, 0.0], [4.0, 0.0], [9.0, 0.0], [2.0, 5.0]]  # nearest neighbour from (0, 0)
    assert route == there + there[-2::-1]
