"""The station benchmark's growth exponent on synthetic per-station timings."""

from __future__ import annotations

import numpy as np
import pytest

from estimation.app.bench.stations import growth_exponent, growth_exponent_by_kind


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


@pytest.mark.parametrize("alpha", [0.0, 0.1, 0.6])
def test_growth_exponent_by_kind_holds_the_mix_apart(alpha: float) -> None:
    """Stations of the second kind cost twice as much and become the rule in the mission's
    second half (an out-and-back route's loop closures): the plain exponent takes that mix for
    growth, the one by kind recovers each kind's own."""
    rng = np.random.default_rng(2)
    n = np.arange(1, 161, dtype=np.float64)
    kind = rng.uniform(size=len(n)) < np.clip((n - 40) / 100, 0.0, 0.95)
    work = 0.4 * n**alpha * np.where(kind, 2.0, 1.0) * rng.lognormal(0.0, 0.2, len(n))
    assert growth_exponent_by_kind(work, kind) == pytest.approx(alpha, abs=0.05)
    assert growth_exponent(work) > alpha + 0.2
    # One kind alone: the plain least-squares slope.
    assert growth_exponent_by_kind(0.4 * n**alpha, np.zeros(len(n))) == pytest.approx(alpha)


def test_growth_exponent_by_kind_refuses_what_it_cannot_fit() -> None:
    with pytest.raises(ValueError, match="3 kinds for 4 stations"):
        growth_exponent_by_kind(np.ones(4), np.zeros(3))
    with pytest.raises(ValueError, match="need at least 16 stations with work, got 15"):
        growth_exponent_by_kind(np.r_[np.ones(15), np.zeros(5)], np.zeros(20))


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


def test_work_parts_split_the_time_and_the_stations_with_a_loop_closure() -> None:
    """Stations whose loop closure became a factor cost twice the others and come late: the
    split shows it, and each part's exponent is its own."""
    from estimation.app.bench.stations import format_stations_report, work_parts

    n = 160
    work = [
        {"station": f"a{k}", "rays": 1000, "fusions": 1, "seconds": 1.0 + (k >= 100),
         "own_seconds": 0.5, "older_seconds": 0.0 if k < 150 else 0.5, "search_seconds": 0.5}
        for k in range(n)
    ]  # fmt: skip
    searches = [{"station": f"a{k}", "kind": "loop", "used": k >= 100} for k in range(90, n)] + [
        {"station": "a5", "kind": "link", "used": True}
    ]
    parts = work_parts(work, searches)
    assert parts["closure_median_s"] == pytest.approx(2.0)
    assert parts["no_closure_median_s"] == pytest.approx(1.0)
    assert parts["closure_share_by_eighth"] == [0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0]
    assert parts["part_exponents"]["own"] == pytest.approx(0.0, abs=1e-9)
    assert parts["part_exponents"]["search"] == pytest.approx(0.0, abs=1e-9)
    assert parts["part_exponents"]["older"] is None  # 10 stations with that work
    assert parts["closure_exponent"] == pytest.approx(0.0, abs=1e-9)  # each kind flat
    assert parts["no_closure_exponent"] == pytest.approx(0.0, abs=1e-9)
    assert parts["kind_exponent"] == pytest.approx(0.0, abs=1e-9)  # the mix held apart
    result = {
        "seed": 2, "rooms": 32, "robots": 4, "stations": n, "steps": 1, "sweeps": 1,
        "mission_s": 60.0, "simulate_s": 1.0, "batch_s": 2.0, "batch_cpu_s": 3.0,
        "timings_s": {"search": 1.0}, "rays_exponent": 0.0, "seconds_exponent": 0.3,
        "per_station": work, **parts,
    }  # fmt: skip
    text = format_stations_report(result)
    assert "own map 0.000, older stations' map -, searches 0.000" in text
    assert "either kind of station (an offset per kind, a loop closure taken or not): 0.000" in text
    assert "with a loop closure taken: median 2.000 s, exponent 0.000; without: median " in text
    assert text.endswith("0.00 0.00 0.00 0.00 0.00 1.00 1.00 1.00")
    assert growth_exponent(np.array([w["seconds"] for w in work])) > 0.2  # the mix grows
