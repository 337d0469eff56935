"""``coopmap bench stations``: per-station work of the station searches against mission length.

A large building is generated (``--rooms``, up to 40), four robots leapfrog through it along a
route that visits every room (a nearest-neighbour tour of the rooms' most open places) and comes
back the same way to the first room (loop closures all along), planned on the true world
(``plan: auto``, ``planner: truth``). The mission is simulated and processed by ``coopmap
batch``; its report's ``station_work`` gives, per station in mission order, the rays fused for
its maps and the wall time of that fusion and of its searches. The benchmark fits the growth
exponent of per-station work in the station index (work ∝ index^α, least squares on log–log
over bins of stations; α near 0: flat) and reports the batch's total time per step. The route
closes its loops on the way back, so late stations are more often ones whose loop closure
became a factor (about twice the work); the exponent is also fitted with an offset per kind of
station, which measures the growth of either kind with the mission's length.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from estimation.app.config import Config

__all__ = [
    "bench_mission",
    "format_stations_report",
    "growth_exponent",
    "growth_exponent_by_kind",
    "run_stations_benchmark",
    "work_parts",
]

ROBOTS = ("a", "b", "c", "d")


def growth_exponent(work: np.ndarray, bins: int = 8, index: np.ndarray | None = None) -> float:
    """α of work ∝ n^α over stations n = 1…N (``work`` in mission order; ``index``: the
    stations' places n when ``work`` is some of them): the least-squares slope of log(median
    work) on log(median n) over ``bins`` equal-count groups of stations (medians damp the
    searches' spread); stations without work are left out."""
    work = np.asarray(work, dtype=np.float64)
    index = (
        np.arange(1, len(work) + 1, dtype=np.float64)
        if index is None
        else np.asarray(index, dtype=np.float64)
    )
    keep = work > 0
    index, work = index[keep], work[keep]
    if len(work) < 2 * bins:
        raise ValueError(f"need at least {2 * bins} stations with work, got {len(work)}")
    groups = np.array_split(np.arange(len(work)), bins)
    x = np.log([np.median(index[g]) for g in groups])
    y = np.log([np.median(work[g]) for g in groups])
    slope, _ = np.polyfit(x, y, 1)
    return float(slope)


def growth_exponent_by_kind(work: np.ndarray, kind: np.ndarray) -> float:
    """α of work ∝ n^α · β^kind (``kind``: a 0/1 flag per station, in mission order): the
    least-squares slope of log(work) on log(n) with an own offset per kind, over every station
    with work. On an out-and-back route the stations whose loop closure became a factor (about
    twice the work) come late; :func:`growth_exponent` then measures that mix as growth, this
    the growth of either kind of station with the mission's length."""
    work = np.asarray(work, dtype=np.float64)
    kind = np.asarray(kind, dtype=np.float64)
    if kind.shape != work.shape:
        raise ValueError(f"{len(kind)} kinds for {len(work)} stations")
    n = np.arange(1, len(work) + 1, dtype=np.float64)
    keep = work > 0
    if keep.sum() < 16:
        raise ValueError(f"need at least 16 stations with work, got {int(keep.sum())}")
    columns = [np.log(n[keep]), np.ones(int(keep.sum()))]
    if 0 < kind[keep].sum() < keep.sum():
        columns.append(kind[keep])
    fit, *_ = np.linalg.lstsq(np.column_stack(columns), np.log(work[keep]), rcond=None)
    return float(fit[0])


def _route(site: Any, start: np.ndarray, rng: np.random.Generator) -> list[list[float]]:
    """The most open place of every room, in nearest-neighbour order from ``start``, then the
    same places in reverse order back to the first (the mission comes back through the
    building)."""
    places = [site.places(points, rng)[0] for _, points in site.rooms_by_floor()]
    tour: list[np.ndarray] = []
    here = start[:2]
    while places:
        k = int(np.argmin([np.hypot(*(p - here)) for p in places]))
        here = places.pop(k)
        tour.append(here)
    tour += tour[-2::-1]
    return [[round(float(p[0]), 3), round(float(p[1]), 3)] for p in tour]


def bench_mission(folder: Path, seed: int, rooms: int, stations: int, config: Config) -> Path:
    """Write the benchmark's building and mission into ``folder``; returns the mission file."""
    from estimation.app.evaluation.missions import Site, furnish_params, start_poses
    from sensors.sim.generate import write_generated_world
    from sensors.sim.world import load_world

    folder.mkdir(parents=True, exist_ok=True)
    world_path = folder / "building.yaml"
    write_generated_world(world_path, seed, rooms, furnish_params(config))
    world = load_world(world_path)
    starts = start_poses(world, config, seed, 3)
    site = Site(world, config)
    rng = np.random.default_rng([seed, 11])
    # The fourth robot waits in the most open place at least 3 m from the others.
    for _, points in site.rooms_by_floor():
        spot = site.places(points, rng)[0]
        if min(np.hypot(*(spot - s[:2])) for s in starts) >= 3.0:
            starts.append(np.array([spot[0], spot[1], 0.0]))
            break
    if len(starts) < len(ROBOTS):
        raise ValueError(f"{world.name}: no place for a fourth robot")
    mission = {
        "world": world_path.name,
        "seed": seed,
        "robots": [
            {
                "name": name,
                "start": [
                    round(float(p[0]), 3),
                    round(float(p[1]), 3),
                    round(math.degrees(float(p[2])), 2),
                ],
            }
            for name, p in zip(ROBOTS, starts, strict=True)
        ],
        "plan": "auto",
        "auto": {
            "stations": stations,
            "scans_per_station": 2,
            "planner": "truth",
            "route": _route(site, starts[0], rng),
        },
    }
    path = folder / "mission.yaml"
    path.write_text(yaml.safe_dump(mission, sort_keys=False))
    return path


def run_stations_benchmark(
    out: Path, seed: int = 2, rooms: int = 32, stations: int = 160, progress: Any = None
) -> dict[str, Any]:
    """Generate, simulate and process the benchmark mission in ``out``; its figures."""
    from estimation.app.pipeline import run_batch
    from estimation.app.sim.simulate import run_simulation

    out = Path(out)
    config = Config()
    clock = time.perf_counter()
    mission = bench_mission(out / "building", seed, rooms, stations, config)
    simulated = run_simulation(mission, out / "dataset")
    simulate_s = time.perf_counter() - clock
    clock, cpu = time.perf_counter(), time.process_time()
    output = run_batch(out / "dataset", out / "result", progress=progress)
    batch_s, batch_cpu_s = time.perf_counter() - clock, time.process_time() - cpu
    work = output.report["global_localization"]["station_work"]
    rays = np.array([w["rays"] for w in work], dtype=np.float64)
    seconds = np.array([w["seconds"] for w in work], dtype=np.float64)
    return {
        "benchmark": "stations",
        "seed": seed,
        "rooms": rooms,
        "robots": len(ROBOTS),
        "stations": len(work),
        "steps": simulated.steps,
        "sweeps": output.report["sweeps"],
        "mission_s": simulated.duration_s,
        "simulate_s": simulate_s,
        "batch_s": batch_s,
        "batch_cpu_s": batch_cpu_s,
        "timings_s": output.report["timings_s"],
        "rays_exponent": growth_exponent(rays),
        "seconds_exponent": growth_exponent(seconds),
        **work_parts(work, output.report["global_localization"]["searches"]),
        "per_station": work,
    }


def _exponent_or_none(work: np.ndarray, index: np.ndarray | None = None) -> float | None:
    try:
        return growth_exponent(work, index=index)
    except ValueError:
        return None


def work_parts(work: list[dict[str, Any]], searches: list[dict[str, Any]]) -> dict[str, Any]:
    """Where per-station time goes (``work``: the report's ``station_work``; ``searches``: its
    search records): the growth exponent of each part (own map, older stations' map,
    searches; None when too few stations have that work), and the median seconds of the
    stations whose loop closure became a factor and of the others, the growth exponent of
    each kind alone, and the share of the former in each eighth of the mission: an
    out-and-back route closes loops only on its way back, so the exponent over all stations
    also measures that mix."""
    closed = {r["station"] for r in searches if r.get("kind") == "loop" and r.get("used")}
    seconds = np.array([w["seconds"] for w in work], dtype=np.float64)
    with_closure = np.array([w["station"] in closed for w in work], dtype=bool)
    parts = {
        part: _exponent_or_none(np.array([w.get(f"{part}_seconds", 0.0) for w in work]))
        for part in ("own", "older", "search")
    }

    def median(mask: np.ndarray) -> float | None:
        return float(np.median(seconds[mask])) if mask.any() else None

    index = np.arange(1, len(work) + 1, dtype=np.float64)
    try:
        by_kind = growth_exponent_by_kind(seconds, with_closure)
    except ValueError:
        by_kind = None
    return {
        "part_exponents": parts,
        "kind_exponent": by_kind,
        "closure_median_s": median(with_closure),
        "no_closure_median_s": median(~with_closure),
        "closure_exponent": _exponent_or_none(seconds[with_closure], index[with_closure]),
        "no_closure_exponent": _exponent_or_none(seconds[~with_closure], index[~with_closure]),
        "closure_share_by_eighth": [
            round(float(with_closure[g].mean()), 3)
            for g in np.array_split(np.arange(len(work)), 8)
            if len(g)
        ],
    }


def format_stations_report(result: dict[str, Any], every: int = 10) -> str:
    lines = [
        f"bench stations: generated building seed {result['seed']}, {result['rooms']} rooms, "
        f"{result['robots']} robots, {result['stations']} stations ({result['steps']} steps, "
        f"{result['sweeps']} sweeps, {result['mission_s'] / 60:.0f} min of mission)",
        f"  simulate {result['simulate_s']:.0f} s; batch {result['batch_s']:.1f} s wall, "
        f"{result['batch_cpu_s']:.1f} s CPU ("
        + ", ".join(f"{k} {v:.2f}" for k, v in result["timings_s"].items())
        + ")",
        "  station  index  rays      fusions  seconds",
    ]
    for n, w in enumerate(result["per_station"], 1):
        if n % every == 1 or n == len(result["per_station"]):
            lines.append(f"  {w['station']:<8} {n:>5}  {w['rays']:>9,}  {w['fusions']:>7}  "
                         f"{w['seconds']:.3f}")  # fmt: skip
    lines.append(
        f"  growth exponent of per-station work: rays {result['rays_exponent']:.3f}, "
        f"seconds {result['seconds_exponent']:.3f} (target <= 0.2)"
    )
    names = {"own": "own map", "older": "older stations' map", "search": "searches"}

    def alpha(value: float | None) -> str:
        return "-" if value is None else f"{round(value, 3) + 0.0:.3f}"

    def seconds(value: float | None) -> str:
        return "-" if value is None else f"{value:.3f} s"

    lines.append("  of its parts, in seconds: " + ", ".join(
        f"{names[part]} {alpha(value)}" for part, value in result["part_exponents"].items()
    ))  # fmt: skip

    lines.append(
        "  growth exponent of either kind of station (an offset per kind, a loop closure taken "
        f"or not): {alpha(result.get('kind_exponent'))}"
    )
    lines.append(
        f"  per station, with a loop closure taken: median {seconds(result['closure_median_s'])}"
        f", exponent {alpha(result['closure_exponent'])}; without: median "
        f"{seconds(result['no_closure_median_s'])}, exponent "
        f"{alpha(result['no_closure_exponent'])}"
    )
    lines.append(
        "  share of stations with a loop closure taken, by eighth of the mission: "
        + " ".join(f"{share:.2f}" for share in result["closure_share_by_eighth"])
    )
    return "\n".join(lines)
