"""Localization trials in simulated worlds: global maps of 360° views, local views at random free
poses, station maps, moved clutter."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from estimation.app.config import Config
from estimation.app.evaluation.trials import Progress, Trial, run_trial
from estimation.app.resources import resolve_builtin
from estimation.app.rig import T_robot_scanner, search_params
from estimation.errors import EstimationError
from mapping.band import Band, extract_band
from mapping.fusion import Scan, fuse_scans
from mapping.grid import GridParams
from sensors.geometry.frames import pose2_matrix


def free_positions(world: Any, config: Config, clearance_m: float) -> np.ndarray:
    """(N, 2) cell centres (at the grid resolution) where a robot fits: inside the rooms, at
    least ``clearance_m`` from walls and from every object that reaches below the top of its
    beacon (luminaires and beams above it do not block it)."""
    from sensors.sim.planner import free_space

    resolution_m = config.grid.resolution_m
    space = free_space(
        world,
        robot_radius_m=clearance_m,
        robot_height_m=config.beacon.height_m + config.beacon.length_m / 2,
        margin_m=0.0,
        resolution_m=resolution_m,
    )
    rows, cols = np.nonzero(space.free)
    return np.asarray(space.lower_xy + (np.column_stack([cols, rows]) + 0.5) * resolution_m)


def view_scan(
    world: Any,
    pose: tuple[float, float, float],
    config: Config,
    rng: np.random.Generator,
    scene: Any,
) -> Scan:
    from estimation.app.sim.demo import simulate_view

    return Scan(simulate_view(world, pose, config, rng, scene).points_scanner)


def world_map(
    world: Any,
    config: Config,
    rng: np.random.Generator,
    scene: Any,
    bands: tuple[str, ...] = ("ceiling",),
) -> dict[str, Band]:
    """The bands of 360° views taken every 2.5 m over the world's free floor, fused in the map
    frame: the map a mapping mission would have left."""
    params = GridParams(**config.grid.model_dump())
    free = free_positions(world, config, 0.5)
    lower, upper = world.bounds_xy()
    stations = []
    for x in np.arange(lower[0] + 1.25, upper[0], 2.5):
        for y in np.arange(lower[1] + 1.25, upper[1], 2.5):
            nearest = free[np.argmin(np.hypot(*(free - (x, y)).T))]
            if math.dist(nearest, (x, y)) < 1.0:
                stations.append((float(nearest[0]), float(nearest[1]), 0.0))
    mount = T_robot_scanner(config)
    scans = [view_scan(world, pose, config, rng, scene) for pose in stations]
    frames = [pose2_matrix(x, y, 0.0) @ mount for x, y, _ in stations]
    grid = fuse_scans(scans, frames, params)
    maps = {}
    for name in bands:
        limits = getattr(config.bands, name)
        maps[name] = extract_band(
            grid, limits.min_m, limits.max_m, free_min_observed=config.bands.free_min_observed
        )
    return maps


def simulated_trials(
    world_name: str,
    config: Config,
    rng: np.random.Generator,
    trials: int,
    *,
    bands: tuple[str, ...] = ("ceiling",),
    perturb: tuple[float, float, float, float] | None = None,
    prior_sigma_m: float | None = None,
    views: int = 1,
    progress: Progress | None = None,
) -> list[Trial]:
    """Global localization of local maps in a simulated world (see the module): one view at
    the true pose, or with ``views`` > 1 a station's map — that view and ``views`` − 1 more from
    free positions 2–5 m away in line of sight (a mapper's scans around a still reference,
    placed in its frame as mutual localization places them).

    ``perturb``: (fraction, shift_m, yaw_deg, remove_fraction) of ``perturb_movables``, applied
    after the map is built and before the local views are taken. ``prior_sigma_m``: search a
    window (``search.window_m``, growing) around the truth displaced by that much noise per
    axis, instead of the whole map.
    """
    from sensors.sim.scene import RaycastScene, build_mesh
    from sensors.sim.world import load_world, perturb_movables

    world = load_world(resolve_builtin("worlds", world_name))
    params = GridParams(**config.grid.model_dump())
    segments = config.simulation.cylinder_segments
    free = free_positions(world, config, 0.5)
    if len(free) == 0:
        raise EstimationError(f"{world_name}: no free position for a robot")
    scene = RaycastScene(build_mesh(world, cylinder_segments=segments))
    maps = world_map(world, config, rng, scene, bands)
    mount = T_robot_scanner(config)
    changed = world
    case = world_name
    if prior_sigma_m is not None:
        case += f" (prior ±{prior_sigma_m:g} m)"
    if views > 1:
        case += f" (station map, {views} views)"
    if perturb is not None:
        fraction, shift_m, yaw_deg, remove = perturb
        changed, _ = perturb_movables(
            world, rng, fraction=fraction, shift_m=shift_m, yaw_deg=yaw_deg, remove_fraction=remove
        )
        case += " (clutter moved)"
        scene = RaycastScene(build_mesh(changed, cylinder_segments=segments))
        free = free_positions(changed, config, 0.5)
    out: list[Trial] = []
    for k in range(trials):
        x, y = free[rng.integers(len(free))]
        truth = np.array([float(x), float(y), float(rng.uniform(-math.pi, math.pi))])
        poses = [truth, *_mapper_poses(truth, views - 1, free, scene, config, rng)]
        scans = [
            view_scan(changed, (p[0], p[1], math.degrees(p[2])), config, rng, scene) for p in poses
        ]
        T_truth_map = np.linalg.inv(pose2_matrix(*truth))
        frames = [T_truth_map @ pose2_matrix(*p) @ mount for p in poses]
        local_grid = fuse_scans(scans, frames, params)
        for name in bands:
            limits = getattr(config.bands, name)
            local = extract_band(
                local_grid, limits.min_m, limits.max_m,
                free_min_observed=config.bands.free_min_observed,
            )  # fmt: skip
            calibrate = perturb is None and prior_sigma_m is None and name == "ceiling"
            search_with = search_params(config.search)
            prior = None
            if prior_sigma_m is not None:
                guess = truth[:2] + rng.normal(0.0, prior_sigma_m, 2)
                prior = (guess, config.search.window_m, config.search.max_window_m)
            room = changed.room_at(truth[:2])
            out.append(
                run_trial(
                    case, name, local, maps[name], truth, search_with, calibrate, prior,
                    "" if room is None else room.name,
                )
            )  # fmt: skip
        if progress is not None:
            progress(f"{case}: trial {k + 1}/{trials}")
    return out


def _mapper_poses(
    reference: np.ndarray,
    count: int,
    free: np.ndarray,
    scene: Any,
    config: Config,
    rng: np.random.Generator,
) -> list[np.ndarray]:
    """``count`` poses at free positions 2–5 m from ``reference`` whose scanners see each
    other (nothing between them at scanner height), random headings."""
    if count <= 0:
        return []
    distance = np.hypot(*(free - reference[:2]).T)
    candidates = free[(distance >= 2.0) & (distance <= 5.0)]
    height = config.robot.scanner_height_m
    out: list[np.ndarray] = []
    for k in rng.permutation(len(candidates)):
        offset = candidates[k] - reference[:2]
        origin = np.array([reference[0], reference[1], height])
        hit = scene.cast(origin, np.array([[offset[0], offset[1], 0.0]]), normals=False)
        if hit.range_m[0] >= float(np.hypot(*offset)):
            out.append(np.array([*candidates[k], rng.uniform(-math.pi, math.pi)]))
            if len(out) == count:
                break
    return out


# -- geb079 ------------------------------------------------------------------------------------
