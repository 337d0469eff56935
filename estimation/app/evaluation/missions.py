"""``coopmap evaluate-missions``: generated buildings, one cooperative mission in each, flown,
processed and scored (docs/evaluate-missions.md).

Building k of N is the generated building of seed S + k (``sensors.sim.generate``, as
``coopmap world generate`` writes it). :func:`generated_mission` places the robots as a user
would, on the true world, and lets the planner choose the stations (``plan: auto``); simulate,
batch and evaluate run on it, and :func:`evaluate_missions` gathers one row per building and the
distribution over the buildings. A building whose mission fails with a coopmap error keeps a row
with that error, and the run goes on with the next one.

Start poses (:func:`start_poses`): the first two robots stand 1.5–3.5 m apart (2.5 m first) in
open floor of the roomiest rooms of the main connected free space, each turned 25° off the line
to the other so that the other's beacon lies outside the forward blind wedge; their beacons
must see each other as the planner requires of a mapper pose (``planning.BeaconGeometry``:
range, bearings between the blind wedge and 45°, clear 3D line), with either heading 5° off
too. A third robot stands near the pair, seen by one of them, clear of the line between
them. Every choice is deterministic for a seed.
"""

from __future__ import annotations

import itertools
import json
import math
import statistics
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy import ndimage

from estimation import __version__
from estimation.app.config import Config, ConfigError, config_from_mapping
from estimation.app.mission.simulated import MISSION_FAILURES
from sensors.atomic import replace_directory, write_text_atomic
from sensors.sim.furnish import FurnishParams
from sensors.sim.generate import MAX_ROOMS, MIN_ROOMS
from sensors.sim.mission import MissionError, mission_from_mapping
from sensors.sim.planner import FreeSpace
from sensors.sim.scene import RaycastScene
from sensors.sim.world import Room, World

__all__ = [
    "KIND",
    "ROBOT_NAMES",
    "Site",
    "check_arguments",
    "evaluate_missions",
    "furnish_params",
    "generated_mission",
    "scores",
    "start_poses",
    "summarise",
]

#: The marker kind of an evaluate-missions output folder (``sensors.atomic``).
KIND = "evaluation"
ROBOT_NAMES = ("a", "b", "c")
#: What a mission asks of the planner (the mission loop, planning on the estimated map, with a
#: station budget) and of the changes. The budget: a robot knows the floor only within a few
#: metres of where it stood, so a building of 9–14 rooms needs well over 60 stations (building
#: 0 of evaluate-missions: 32 % of its floor at 60, 88 % at 140, where exploration stalled). The
#: budget is a safety stop, not the end of exploring: building 4 (two 125 m² halls, 12 rooms)
#: spent 150 at 83 % of its floor and 8 of 12 rooms, and with a larger budget was done after
#: 181 (99.9 %, every room).
DEFAULT_STATIONS, MAX_STATIONS = 250, 500
AUTO = {"stations": DEFAULT_STATIONS, "scans_per_station": 2, "planner": "map"}
CHANGES = {"movable_fraction": 0.5, "shift_m": 0.5, "yaw_deg": 30.0}
#: Distances tried between the first two robots, in order (m).
PAIR_DISTANCES_M = (2.5, 2.0, 3.0, 3.5, 1.5)
#: Distances tried from the robot that sees the third one (m).
THIRD_DISTANCES_M = (2.0, 2.5, 3.0, 1.5, 3.5)
#: Each robot turns this far off the line to the other: the other's beacon leaves the blind wedge.
FACING_OFFSET_DEG = 25.0
#: Visibility must also hold with either robot's heading this far off.
YAW_MARGIN_DEG = 5.0
#: Directions tried from a first robot's place, and places tried per room.
HEADINGS = 16
PLACES_PER_ROOM = 24
#: Places of a room are taken from its cells with at least this clearance (or its best ones).
OPEN_FLOOR_M = 1.0
#: An error is "within" when it is below these, as everywhere in coopmap (docs/results.md).
STRICT = (0.05, 0.5)
WITHIN = (0.1, 1.0)
#: The errors a building's mission may end with; any other error stops the whole run.
Progress = Callable[[str], None]


def check_arguments(
    worlds: int, seed: int, robots: int, rooms: int | None, stations: int = DEFAULT_STATIONS
) -> None:
    """Refuse bad arguments before any work, one line naming the option."""
    if not 1 <= stations <= MAX_STATIONS:
        raise ConfigError(f"--stations must be within 1-{MAX_STATIONS}, got {stations}")
    if worlds < 1:
        raise ConfigError(f"--worlds must be >= 1, got {worlds}")
    if seed < 0:
        raise ConfigError(f"--seed must be >= 0, got {seed}")
    if robots not in (2, 3):
        raise ConfigError(f"--robots must be 2 or 3, got {robots}")
    if rooms is not None and not MIN_ROOMS <= rooms <= MAX_ROOMS:
        raise ConfigError(f"--rooms must be within {MIN_ROOMS}-{MAX_ROOMS}, got {rooms}")


def furnish_params(config: Config) -> FurnishParams:
    """What the building generator needs of the configuration (as ``coopmap world generate``)."""
    return FurnishParams(
        band_m=(config.bands.ceiling.min_m, config.bands.ceiling.max_m),
        robot_radius_m=config.robot.footprint_radius_m,
        beacon_height_m=config.beacon.height_m,
        beacon_length_m=config.beacon.length_m,
    )


# -- the mission --------------------------------------------------------------------------------


def generated_mission(
    world_path: Path | str,
    seed: int,
    robots: int,
    config: Config | None = None,
    stations: int = DEFAULT_STATIONS,
) -> dict[str, Any]:
    """The mission of a generated building, as a mission-file mapping (docs/design.md §12).

    ``world`` is the world file's name: the mission file goes beside it. The start poses come
    from :func:`start_poses` (deterministic for ``seed``), the stations from ``plan: auto``;
    half the movable objects move at the end, to be relocalized against. Raises
    ``MissionError`` when no start poses fit.
    """
    from sensors.sim.world import load_world

    if robots not in (2, 3):
        raise ConfigError(f"robots must be 2 or 3, got {robots}")
    config = config or Config()
    world_path = Path(world_path)
    starts = start_poses(load_world(world_path), config, seed, robots)
    mission = {
        "world": world_path.name,
        "seed": seed,
        "robots": [
            {"name": name, "start": _as_spec(pose)}
            for name, pose in zip(ROBOT_NAMES, starts, strict=False)
        ],
        "plan": "auto",
        "auto": {**AUTO, "stations": stations},
        "changes": dict(CHANGES),
    }
    mission_from_mapping(mission, f"mission of {world_path}")  # what simulate will read back
    return mission


def _as_spec(pose: np.ndarray) -> list[float]:
    """A pose as a mission writes it: x_m, y_m to 1 mm, yaw_deg to 0.01° in (−180, 180]."""
    return [round(float(pose[0]), 3), round(float(pose[1]), 3),
            round(math.degrees(math.remainder(float(pose[2]), 2 * math.pi)), 2)]  # fmt: skip


def _rounded(pose: np.ndarray) -> np.ndarray:
    """The pose as the mission file will hold it, so that what is checked is what is flown."""
    x, y, yaw_deg = _as_spec(pose)
    return np.array([x, y, math.radians(yaw_deg)])


class Site:
    """The true world as the person placing the robots sees it: where a robot fits (in the main
    connected part of the free space) and whether two beacons see each other."""

    def __init__(self, world: World, config: Config) -> None:
        from estimation.app.sim.planning import BeaconGeometry
        from estimation.app.sim.simulate import robot_free_space
        from sensors.sim.scene import build_mesh

        self.world, self.config = world, config
        self.space: FreeSpace = robot_free_space(world, config)
        labels, count = ndimage.label(self.space.free, structure=np.ones((3, 3)))
        if count == 0:
            raise MissionError(f"{world.name}: no floor where a robot fits")
        sizes = np.bincount(labels.ravel())[1:]
        self.main = labels == 1 + int(np.argmax(sizes))
        segments = config.simulation.cylinder_segments
        scene = RaycastScene(build_mesh(world, cylinder_segments=segments))
        self.geometry = BeaconGeometry(config, scene)
        self.band = (0.5, config.beacon.max_range_m)
        self.spacing_m = 2 * config.robot.footprint_radius_m + 0.3

    def fits(self, xy: np.ndarray) -> bool:
        return self.space.is_free(xy) and bool(self.main[self.space.cell(xy)])

    def sees(self, observer: np.ndarray, observed: np.ndarray) -> bool:
        """Both beacons see each other as the planner requires of a mapper pose (range, bearings
        outside the blind wedge and within 45°, clear 3D line), also with either robot's
        heading ``YAW_MARGIN_DEG`` off."""
        turn = np.array([0.0, 0.0, math.radians(YAW_MARGIN_DEG)])
        pairs = [(observer, observed)]
        pairs += [(observer + s * turn, observed) for s in (-1, 1)]
        pairs += [(observer, observed + s * turn) for s in (-1, 1)]
        return all(self.geometry.mutual(p, q, self.band) for p, q in pairs)

    def rooms_by_floor(self) -> list[tuple[Room, np.ndarray]]:
        """Each room with the centres of its main free cells (N, 2), roomiest first: by the
        floor at least ``OPEN_FLOOR_M`` from any obstacle (a corridor has little of it, and the
        planner needs room around a reference), then by all of its free floor."""
        cells = np.argwhere(self.main)
        centres = self.space.lower_xy + (cells[:, ::-1] + 0.5) * self.space.resolution_m
        open_floor = self.space.clearance_m[cells[:, 0], cells[:, 1]] >= OPEN_FLOOR_M
        rooms = []
        for room in self.world.rooms:
            inside = room.contains(centres)
            if inside.any():
                rooms.append((-int((inside & open_floor).sum()), -int(inside.sum()), room.name,
                              room, centres[inside]))  # fmt: skip
        return [(room, points) for *_, room, points in sorted(rooms, key=lambda r: r[:3])]

    def places(self, points: np.ndarray, rng: np.random.Generator) -> list[np.ndarray]:
        """Up to ``PLACES_PER_ROOM`` of a room's points, the most open first, 0.5 m apart."""
        clearance = np.array([self.space.clearance_m[self.space.cell(p)] for p in points])
        open_floor = clearance >= min(OPEN_FLOOR_M, float(clearance.max()))
        points, clearance = points[open_floor], clearance[open_floor]
        order = np.argsort(-(clearance + rng.uniform(0.0, 0.2, len(clearance))), kind="stable")
        chosen: list[np.ndarray] = []
        for point in points[order]:
            if all(np.hypot(*(point - c)) >= 0.5 for c in chosen):
                chosen.append(point)
                if len(chosen) == PLACES_PER_ROOM:
                    break
        return chosen


def _facing(xy: np.ndarray, target_xy: np.ndarray, side: int) -> np.ndarray:
    """A pose at ``xy`` turned ``FACING_OFFSET_DEG`` to ``side`` off the line to ``target_xy``."""
    heading = math.atan2(target_xy[1] - xy[1], target_xy[0] - xy[0])
    return _rounded(np.array([xy[0], xy[1], heading + side * math.radians(FACING_OFFSET_DEG)]))


def _pair_candidates(site: Site, rng: np.random.Generator) -> Iterator[tuple[np.ndarray, ...]]:
    for _room, points in site.rooms_by_floor():
        for a_xy in site.places(points, rng):
            first = rng.uniform(0.0, 2 * math.pi)
            for distance, k in itertools.product(PAIR_DISTANCES_M, range(HEADINGS)):
                heading = first + 2 * math.pi * k / HEADINGS
                b_xy = a_xy + distance * np.array([math.cos(heading), math.sin(heading)])
                if not site.fits(b_xy) or not site.space.segment_free(a_xy, b_xy):
                    continue
                for side_a, side_b in itertools.product((1, -1), repeat=2):
                    yield _facing(a_xy, b_xy, side_a), _facing(b_xy, a_xy, side_b)


def _clear_of(point: np.ndarray, a: np.ndarray, b: np.ndarray, margin_m: float) -> bool:
    """Whether ``point`` (xy) is at least ``margin_m`` from the segment a–b (xy)."""
    ab = b - a
    t = float(np.clip(np.dot(point - a, ab) / max(float(np.dot(ab, ab)), 1e-12), 0.0, 1.0))
    return float(np.hypot(*(point - (a + t * ab)))) >= margin_m


def _third(site: Site, a: np.ndarray, b: np.ndarray) -> np.ndarray | None:
    """A third start near the pair, seen by one of them, whose body blocks no line between the
    beacons of the others."""
    margin = site.config.robot.footprint_radius_m + 0.3
    for anchor, other in ((a, b), (b, a)):
        for distance, bearing_deg in itertools.product(
            THIRD_DISTANCES_M, (30, -30, 20, -20, 40, -40)
        ):
            direction = anchor[2] + math.radians(bearing_deg)
            c_xy = anchor[:2] + distance * np.array([math.cos(direction), math.sin(direction)])
            if (
                not site.fits(c_xy)
                or min(np.hypot(*(c_xy - p[:2])) for p in (a, b)) < site.spacing_m
                or not _clear_of(c_xy, a[:2], b[:2], margin)
                or not _clear_of(other[:2], anchor[:2], c_xy, margin)
            ):
                continue
            for side in (1, -1):
                c = _facing(c_xy, anchor[:2], side)
                if site.sees(anchor, c):
                    return c
    return None


def start_poses(world: World, config: Config, seed: int, robots: int) -> list[np.ndarray]:
    """Start poses (x_m, y_m, yaw_rad) of ``robots`` robots in ``world`` (module docstring),
    rounded as a mission file holds them; ``MissionError`` when none fit."""
    site = Site(world, config)
    rng = np.random.default_rng([seed, 7])
    for a, b in _pair_candidates(site, rng):
        if not site.sees(a, b):
            continue
        if robots == 2:
            return [a, b]
        c = _third(site, a, b)
        if c is not None:
            return [a, b, c]
    third = " and a third one sees one of them" if robots == 3 else ""
    raise MissionError(
        f"{world.name}: no start poses for {robots} robots: nowhere in open floor do two robots "
        f"{min(PAIR_DISTANCES_M):g}-{max(PAIR_DISTANCES_M):g} m apart see each other's beacon"
        f"{third}"
    )


# -- the evaluation -----------------------------------------------------------------------------


def evaluate_missions(
    worlds: int,
    seed: int,
    out_dir: Path | str,
    *,
    robots: int = 2,
    rooms: int | None = None,
    stations: int = DEFAULT_STATIONS,
    overrides: dict[str, Any] | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Fly, process and score a mission in each of ``worlds`` generated buildings (seeds
    ``seed`` … ``seed + worlds - 1``) into ``out_dir``; returns ``evaluation.json``'s document
    (``rows`` and ``summary``).

    ``out_dir`` may only be missing, empty or an earlier output of this function (a user's
    folder is refused before any work). It is emptied and marked when the run starts, so that
    every path a building's files record is final; each building's folder appears as it is
    done, and ``evaluation.json`` last (a run cut short has none)."""
    check_arguments(worlds, seed, robots, rooms, stations)
    config = config_from_mapping(overrides or {}, source="--config")
    run = _Run(robots, rooms, stations, config, overrides)
    out = Path(out_dir)
    with replace_directory(out, KIND):
        pass  # an empty folder marked as an evaluation takes the place of an earlier one
    rows = []
    for k in range(worlds):
        step = _prefixed(progress, f"building {k + 1} of {worlds} (seed {seed + k})")
        rows.append(_evaluate_building(out, seed + k, run, step))
    document = {
        "coopmap": __version__,
        "worlds": worlds,
        "seed": seed,
        "robots": robots,
        "rooms": rooms,
        "stations": stations,
        "rows": rows,
        "summary": summarise(rows),
    }
    write_text_atomic(out / "evaluation.json", json.dumps(document, indent=1) + "\n")
    return document


def _blank_row(seed: int, folder: str, rooms: int | None) -> dict[str, Any]:
    return {
        "seed": seed,
        "folder": folder,
        "world": None,
        "rooms": rooms,
        "error": None,
        "robots": {},
        "coverage": None,
        "rooms_entered": None,
        "rooms_reachable": None,
        "relocalization": None,
        "map_precision": None,
        "map_recall": None,
        "wall_time_s": None,
    }


def _prefixed(progress: Progress | None, prefix: str) -> Progress:
    def step(text: str) -> None:
        if progress is not None:
            progress(f"{prefix}: {text}")

    return step


@dataclass(frozen=True)
class _Run:
    """What every building of a run shares."""

    robots: int
    rooms: int | None
    stations: int
    config: Config
    overrides: dict[str, Any] | None


def _evaluate_building(out: Path, seed: int, run: _Run, step: Progress) -> dict[str, Any]:
    """The row of the building of ``seed``, its files in ``out/seed-NNNN``; a coopmap error
    ends the building's mission and becomes the row's ``error``."""
    from sensors.sim.generate import write_generated_world

    folder = out / f"seed-{seed:04d}"
    row = _blank_row(seed, folder.name, run.rooms)
    started = time.perf_counter()
    try:
        step("generating")
        world = folder / "world.yaml"
        building = write_generated_world(world, seed, run.rooms, furnish_params(run.config))
        row.update(world=building.world.name, rooms=len(building.rooms))
        step("placing the robots")
        mission = generated_mission(world, seed, run.robots, run.config, run.stations)
        row.update(_fly(folder, mission, run.overrides, step))
    except MISSION_FAILURES as exc:
        row["error"] = " ".join(str(exc).split()) or type(exc).__name__
    row["wall_time_s"] = round(time.perf_counter() - started, 2)
    return row


def _fly(
    folder: Path, mission: dict[str, Any], overrides: dict[str, Any] | None, step: Progress
) -> dict[str, Any]:
    """Simulate, batch and evaluate the mission in ``folder``; its scores (:func:`scores`)."""
    from estimation.app.evaluation.evaluate import evaluate
    from estimation.app.pipeline import run_batch
    from estimation.app.sim.simulate import run_simulation

    header = f"# coopmap evaluate-missions: the mission of building seed {mission['seed']}\n"
    write_text_atomic(folder / "mission.yaml", header + yaml.safe_dump(mission, sort_keys=False))
    dataset = folder / "dataset"
    flown = run_simulation(
        folder / "mission.yaml",
        dataset,
        overrides=overrides,
        progress=lambda robot, f: step(f"simulating the sensors of robot {robot} ({f:.0%})"),
        status=lambda text: step(f"mission loop: {text}"),
    )
    if flown.loop is None:  # planned before the mission: the result comes from batch
        run_batch(dataset, overrides=overrides, progress=lambda text: step(f"batch: {text}"))
    step("evaluating against the ground truth")
    row = scores(evaluate(dataset))
    if flown.loop is not None:
        row["loop"] = {
            "stop_reason": flown.loop["stop_reason"],
            "stations": len({s["step"] for s in flown.loop["stations"]}),
            "pivots": flown.loop["pivots"],
            "work_per_dwell_p99_s": flown.loop["work_per_dwell_s"]["p99"],
            "localizations_late": sum(
                not item["in_time"] for item in flown.loop["concurrent_localization"]
            ),
        }
    return row


def scores(metrics: dict[str, Any]) -> dict[str, Any]:
    """A row's scores from ``metrics.json``: each robot's ATE (None without a pose), coverage,
    rooms, relocalization (both bands; None without changes), map precision and recall."""
    robots = {
        name: {"poses": m.get("poses", 0), "ate_m": m.get("ate_m"), "ate_deg": m.get("ate_deg")}
        for name, m in sorted(metrics["robots"].items())
    }
    found = metrics.get("global_localization", {})
    bands = [
        found[key] for key in ("relocalization_ceiling", "relocalization_floor") if key in found
    ]
    coverage = metrics.get("coverage") or {}
    return {
        "robots": robots,
        "coverage": coverage.get("coverage"),
        "rooms_entered": len(coverage.get("rooms_entered", [])),
        "rooms_reachable": len(coverage.get("rooms", [])),
        "relocalization": (
            {
                "success": sum(b["success"] for b in bands),
                "searches": sum(b["searches"] for b in bands),
            }
            if bands
            else None
        ),
        "map_precision": metrics["map"]["precision"],
        "map_recall": metrics["map"]["recall"],
    }


def _all_within(row: dict[str, Any], limits: tuple[float, float]) -> bool:
    robots = row["robots"].values()
    return (
        row["error"] is None
        and bool(robots)
        and all(
            m["ate_m"] is not None and m["ate_m"] < limits[0] and m["ate_deg"] < limits[1]
            for m in robots
        )
    )


def _spread(values: list[float], worst: Callable[[list[float]], float]) -> dict[str, Any]:
    if not values:
        return {"median": None, "worst": None}
    return {"median": statistics.median(values), "worst": worst(values)}


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The distribution over the buildings: median and worst ATE over every robot placed in a
    building that ran, coverage min and median, and the share of all buildings (failed ones
    count against it) in which every robot is below 5 cm and 0.5° (``within_5cm_05deg``) or
    10 cm and 1° (``within_10cm_1deg``)."""
    ran = [r for r in rows if r["error"] is None]
    placed = [m for r in ran for m in r["robots"].values() if m["ate_m"] is not None]
    coverage = [r["coverage"] for r in ran if r["coverage"] is not None]
    found = [r["relocalization"] for r in ran if r["relocalization"] is not None]
    n = len(rows)
    return {
        "buildings": n,
        "failed": n - len(ran),
        "robots_lost": sum(m["ate_m"] is None for r in ran for m in r["robots"].values()),
        "ate_m": _spread([m["ate_m"] for m in placed], max),
        "ate_deg": _spread([m["ate_deg"] for m in placed], max),
        "coverage": {
            "min": min(coverage) if coverage else None,
            "median": statistics.median(coverage) if coverage else None,
        },
        "map_precision": _spread([r["map_precision"] for r in ran], min),
        "map_recall": _spread([r["map_recall"] for r in ran], min),
        "relocalization": {
            "success": sum(f["success"] for f in found),
            "searches": sum(f["searches"] for f in found),
        },
        "within_5cm_05deg": sum(_all_within(r, STRICT) for r in rows) / n if n else 0.0,
        "within_10cm_1deg": sum(_all_within(r, WITHIN) for r in rows) / n if n else 0.0,
        "wall_time_s": round(sum(r["wall_time_s"] or 0.0 for r in rows), 2),
    }
