"""``coopmap simulate``: a mission file → a recorded dataset (docs/design.md §8, §12).

The app layer resolves the world, merges the configuration (defaults ← the mission's
``config:`` ← ``--config``), builds each robot's simulated scanner, plans (``plan: auto``) or
checks the explicit plan, runs the timeline and records the dataset. Output goes to a fresh
sibling directory that replaces ``--out`` only when the whole run succeeded: a failed run never
deletes an earlier dataset.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from estimation import __version__
from estimation.app.config import Config, ConfigError, config_from_mapping
from estimation.app.resources import resolve_builtin
from estimation.app.rig import dwell_seconds, odometry_noise, robot_body, simulated_scanner
from sensors.atomic import check_replaceable, replace_directory, write_text_atomic
from sensors.sim.mission import (
    MissionError,
    MissionSpec,
    StepSpec,
    build_timeline,
    load_mission,
    mission_to_yaml,
    write_dataset,
)
from sensors.sim.planner import FreeSpace, free_space
from sensors.sim.scene import RaycastScene, build_mesh
from sensors.sim.world import ObjectChange, World, load_world, perturb_movables, world_to_yaml
from sensors.yamlio import merge_mappings

__all__ = ["SimulationResult", "load_simulated", "resolve_mission_world", "run_simulation"]


@dataclass(frozen=True)
class SimulationResult:
    out_dir: Path
    mission: str
    world: str
    seed: int
    duration_s: float
    steps: int
    poses: dict[str, int]
    telegrams: dict[str, int]
    changed: list[str]
    #: With the mission loop (``auto.planner: map``): why it stopped and its figures; the
    #: result is written into ``out_dir/result``.
    loop: dict[str, Any] | None = None


def resolve_mission_world(mission: MissionSpec, mission_path: Path) -> Path:
    """A world named in a mission: a path relative to the mission file, or a built-in name."""
    relative = mission_path.parent / mission.world
    if relative.is_file():
        return relative
    return resolve_builtin("worlds", mission.world)


def mission_config(mission: MissionSpec, overrides: dict[str, Any] | None, source: str) -> Config:
    """Defaults ← the mission's ``config:`` ← overrides (from ``--config``)."""
    merged = Config().model_dump()
    for layer in (mission.config, overrides or {}):
        merged = merge_mappings(merged, layer)
    return config_from_mapping(merged, source=source)


def robot_free_space(world: World, config: Config) -> FreeSpace:
    robot = config.robot
    return free_space(
        world, robot_radius_m=robot.footprint_radius_m, robot_height_m=robot.body_height_m
    )


def load_simulated(
    mission_path: Path, overrides: dict[str, Any] | None, seed: int | None
) -> tuple[MissionSpec, Config, World, FreeSpace, int]:
    """A mission file and what simulating it needs: the effective configuration, the world,
    the robots' free space (with the planning margin) and the seed (the mission's, or
    ``seed``)."""
    mission = load_mission(mission_path)
    config = mission_config(mission, overrides, str(mission_path))
    world = load_world(resolve_mission_world(mission, mission_path))
    seed = mission.seed if seed is None else seed
    if seed < 0:
        raise ConfigError(f"seed must be >= 0, got {seed}")
    return mission, config, world, robot_free_space(world, config), seed


def run_simulation(
    mission_path: Path | str,
    out_dir: Path | str,
    *,
    overrides: dict[str, Any] | None = None,
    seed: int | None = None,
    progress: Callable[[str, float], None] | None = None,
    status: Callable[[str], None] | None = None,
    observe: Callable[[Any], None] | None = None,
) -> SimulationResult:
    """Simulate the mission into ``out_dir``. ``observe`` is called with the mission loop after
    every dwell (missions flown by the loop only: ``plan: auto``, ``auto.planner: map``)."""
    mission_path = Path(mission_path)
    check_replaceable(Path(out_dir), "dataset")  # before the work, not after it
    mission, config, world, space, seed = load_simulated(mission_path, overrides, seed)

    if mission.plan == "auto" and mission.auto.planner == "map":
        return _fly_loop(mission, config, world, space, seed, Path(out_dir), mission_path,
                         status, observe)  # fmt: skip
    if mission.plan == "auto":
        from estimation.app.sim.planning import plan_leapfrog

        steps = plan_leapfrog(mission, world, space, config, np.random.default_rng([seed, 1]))
    else:
        steps = list(mission.plan)
    if not isinstance(steps, list) or not all(isinstance(s, StepSpec) for s in steps):
        raise ConfigError(f"{mission_path}: the plan has no steps")
    timeline = build_timeline(
        mission,
        steps,
        space,
        speed_m_s=config.robot.speed_m_s,
        turn_rate_rad_s=math.radians(config.robot.turn_rate_deg_s),
        dwell_s=dwell_seconds(config),
        changes_at_end=mission.changes is not None,
    )
    segments = config.simulation.cylinder_segments
    scene = RaycastScene(build_mesh(world, cylinder_segments=segments))
    from estimation.app.sim.planning import mutual_dwells

    seen = mutual_dwells(timeline.events, timeline.stops, config, scene)
    if len(mission.robots) > 1 and seen == 0:
        raise ConfigError(
            f"{mission_path}: in no dwell of the plan can the reference and the mapper see each "
            "other's beacon (range, field of view, blind wedge, line of sight): the dataset "
            "would give no mutual observation"
        )
    changed_world, changes = world, list[ObjectChange]()
    if mission.changes is not None:
        c = mission.changes
        changed_world, changes = perturb_movables(
            world, np.random.default_rng([seed, 2]), fraction=c.movable_fraction,
            shift_m=c.shift_m, yaw_deg=c.yaw_deg, remove_fraction=c.remove_fraction,
        )  # fmt: skip
        for event in timeline.events:
            if event["event"] == "changes":
                event["objects"] = [{"name": ch.name, "action": ch.action} for ch in changes]
    changed_scene = (
        RaycastScene(build_mesh(changed_world, cylinder_segments=segments)) if changes else scene
    )

    def scenes(t: float) -> RaycastScene:
        return changed_scene if timeline.change_s is not None and t >= timeline.change_s else scene

    noise = odometry_noise(config)
    scanners = {name: simulated_scanner(config, np.random.default_rng([seed, 3, k]))
                for k, name in enumerate(mission.robot_names())}  # fmt: skip
    with replace_directory(Path(out_dir), "dataset") as work:
        stats = write_dataset(
            work, timeline, scanners, scenes, robot_body(config),
            scanner_height_m=config.robot.scanner_height_m, odometry_noise=noise,
            rng=np.random.default_rng([seed, 4]), baud_rate=config.serial.baud_rate,
            progress=progress,
        )  # fmt: skip
        header = f"# effective mission; coopmap {__version__}, seed {seed}\n"
        write_text_atomic(
            work / "mission.yaml",
            header + mission_to_yaml(mission, steps, config.model_dump(mode="json")),
        )
        write_text_atomic(work / "world.yaml", world_to_yaml(world))
        if mission.changes is not None:
            write_text_atomic(work / "world_changed.yaml", world_to_yaml(changed_world))
    return SimulationResult(
        out_dir=Path(out_dir),
        mission=mission_path.stem,
        world=world.name,
        seed=seed,
        duration_s=timeline.end_s,
        steps=len(steps),
        poses={n: len(v) for n, v in timeline.stops.items()},
        telegrams={n: r["telegrams"] for n, r in stats["robots"].items()},
        changed=[f"{c.name} {c.action}" for c in changes],
    )


def _fly_loop(mission: MissionSpec, config: Config, world: World, space: FreeSpace, seed: int,
              out_dir: Path, mission_path: Path,
              status: Callable[[str], None] | None,
              observe: Callable[[Any], None] | None = None) -> SimulationResult:  # fmt: skip
    """``plan: auto`` with the mission loop: estimation and planning during the mission."""
    from estimation.app.mission.simulated import PartialMissionError, fly

    failed: PartialMissionError | None = None
    with replace_directory(out_dir, "dataset") as work:
        try:
            flown = fly(mission, config, world, space, seed, work, final=out_dir, status=status,
                        observe=observe)  # fmt: skip
        except PartialMissionError as exc:
            failed = exc  # the recording so far still takes out_dir's place
    if failed is not None:
        raise MissionError(
            f"the mission failed: {failed}; its recording up to the failure is "
            f"in {out_dir} (partial.json says how far it went)"
        ) from failed
    report = flown.output.report
    return SimulationResult(
        out_dir=out_dir, mission=mission_path.stem, world=world.name, seed=seed,
        duration_s=float(flown.loop.get("duration_s", 0.0)), steps=len(flown.steps),
        poses={r: v["poses"] for r, v in report["robots"].items()},
        telegrams={r: v["telegrams"] for r, v in report["robots"].items()},
        changed=list(flown.loop["changed"]), loop={"stop_reason": flown.stop_reason, **flown.loop},
    )  # fmt: skip
