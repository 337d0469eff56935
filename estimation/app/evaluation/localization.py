"""``coopmap evaluate-localization``: global-localization accuracy on simulated and real data.

Every trial searches the whole map — no prior, unless a row says so — and compares the refined
best pose with the truth. Success: within 0.1 m and 1° (the paper's claim); "strict": within
0.05 m and 0.5°. "Dominant": the search's own verdict (peak ratio ≥ ``search.dominance_ratio``),
and how often a dominant answer was right.

* **Simulated worlds** (``sim``): the global map is the band of 360° views (``demo``'s
  simulated LMS with range noise) taken every 2.5 m over the world and fused in the map frame;
  a local map is the band of one 360° view fused in the robot's own frame, at a random free pose
  (random yaw). office_loop is also searched from a prior (the truth displaced by 1 m σ per
  axis; a 4 m window that doubles until the peak is dominant) and with station maps. In
  ``cluttered_hall`` the clutter is then moved (``perturb_movables``: every movable object
  shifted up to 1 m and turned up to 45°, a fifth removed) before the local views are taken,
  and both the ceiling band and a floor band are searched.
* **geb079** (``../shared/data/octomap_fr079/geb079.bt``, building 079 of the University of
  Freiburg, OctoMap's sample map, 0.08 m): a ceiling band (z 2.30–2.55 m) and a floor band
  (z 0.3–1.5 m) of the whole building; local grids cut at random poses in the corridors — the
  building's voxels within 8 m, re-gridded (2×2 sub-columns per voxel) in a frame turned by a
  random yaw and shifted by a random sub-cell offset, with occupancy noise (σ 0.1), 2 % of the
  cells inverted and 20 % dropped.
* **CARMEN** (``../shared/data/carmen_corrected``: Intel Research Lab, D. Hähnel; Freiburg 079,
  C. Stachniss): the 2D map is fused from the even-numbered scans at their corrected poses; a
  local map is one odd-numbered scan (or a few consecutive ones, fused in the frame of the
  first) in the robot frame; the truth is its corrected pose (itself a SLAM estimate: 6.8 cm
  and 2.4° mean error against the benchmark's relations for Intel, per the data's README).

β is calibrated on the simulated ceiling searches: the value that maximises the mean log
probability the PDF gives to the lattice cell holding the true pose (a proper scoring rule).
"""

from __future__ import annotations

import gzip
import math
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from estimation.app.config import Config
from estimation.app.resources import DATA_DIR
from estimation.app.rig import T_robot_scanner, search_params
from estimation.errors import EstimationError
from estimation.search.exhaustive import SearchParams, SearchResult, search, windowed_search
from mapping.band import Band, extract_band
from mapping.fusion import Scan, fuse_scans
from mapping.grid import GridParams
from sensors.geometry.frames import pose2_matrix

__all__ = [
    "Trial",
    "by_room_kind",
    "calibrate_beta",
    "carmen_trials",
    "format_report",
    "geb079_trials",
    "read_carmen_scans",
    "run_evaluation",
    "simulated_trials",
    "summarise",
    "write_figures",
]

#: The shared real-data folder beside the repository (``../shared/data``).
BETAS = np.geomspace(0.002, 0.5, 25)
Progress = Callable[[str], None]


@dataclass(frozen=True)
class Trial:
    """One search: the truth, the answer, and how well the PDF scored the truth."""

    case: str
    band: str
    truth: tuple[float, float, float]  # x_m, y_m, yaw_rad
    estimate: tuple[float, float, float]
    error_m: float
    error_deg: float
    peak_ratio: float
    seconds: float
    log_likelihood: tuple[float, ...]  # per β of BETAS: log P(true cell); () if not computed
    dominant: bool = True  # the search's own verdict: trust the answer
    room: str = ""  # the simulated world's room holding the truth

    @property
    def success(self) -> bool:
        return self.error_m < 0.1 and self.error_deg < 1.0

    @property
    def strict(self) -> bool:
        return self.error_m < 0.05 and self.error_deg < 0.5


def _log_likelihoods(result: SearchResult, truth: np.ndarray) -> tuple[float, ...]:
    """log P(cell holding the truth) under exp(β·score), for each β of BETAS (−inf off the
    lattice)."""
    x_m, y_m, yaw = result.x_m, result.y_m, result.yaw_rad
    ix = round((truth[0] - x_m[0]) / (x_m[1] - x_m[0]))
    iy = round((truth[1] - y_m[0]) / (y_m[1] - y_m[0]))
    it = round(((truth[2] - yaw[0]) % (2 * math.pi)) / (yaw[1] - yaw[0])) % len(yaw)
    if not (0 <= ix < len(x_m) and 0 <= iy < len(y_m)):
        return tuple(-math.inf for _ in BETAS)
    scores = result.scores
    assert scores is not None
    top = float(result.best_score)
    at_truth = float(scores[it, iy, ix])
    out = []
    for beta in BETAS:
        shifted = np.float32(beta) * (scores - np.float32(top))
        np.maximum(shifted, np.float32(-87.0), out=shifted)
        total = float(np.exp(shifted).sum(dtype=np.float64))
        out.append(beta * (at_truth - top) - math.log(total))
    return tuple(out)


def _trial(
    case: str,
    band: str,
    local: Band,
    global_: Band,
    truth: np.ndarray,
    params: SearchParams,
    calibrate: bool = False,
    prior: tuple[np.ndarray, float, float] | None = None,
    room: str = "",
) -> Trial:
    """Search (the whole map, or given ``prior`` = (position, window_m, max_window_m) a window
    around it that grows) and score the answer against the truth."""
    if prior is None:
        result = search(local, global_, params, keep_scores=calibrate)
        dominant = result.is_dominant(params.dominance_ratio)
        seconds = result.seconds
    else:
        found = windowed_search(local, global_, params, *prior)
        result, dominant = found.result, found.dominant
        seconds = sum(step.seconds for step in found.steps)
    d = result.pose - truth
    return Trial(
        case=case,
        band=band,
        truth=(float(truth[0]), float(truth[1]), float(truth[2])),
        estimate=(float(result.pose[0]), float(result.pose[1]), float(result.pose[2])),
        error_m=math.hypot(d[0], d[1]),
        error_deg=abs(math.degrees(math.remainder(d[2], 2 * math.pi))),
        peak_ratio=result.peak_ratio,
        seconds=seconds,
        log_likelihood=_log_likelihoods(result, truth) if calibrate else (),
        dominant=dominant,
        room=room,
    )


# -- simulated worlds --------------------------------------------------------------------------


def _free_positions(world: Any, config: Config, clearance_m: float) -> np.ndarray:
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


def _view_scan(
    world: Any,
    pose: tuple[float, float, float],
    config: Config,
    rng: np.random.Generator,
    scene: Any,
) -> Scan:
    from estimation.app.sim.demo import simulate_view

    return Scan(simulate_view(world, pose, config, rng, scene).points_scanner)


def _world_map(
    world: Any,
    config: Config,
    rng: np.random.Generator,
    scene: Any,
    bands: tuple[str, ...] = ("ceiling",),
) -> dict[str, Band]:
    """The bands of 360° views taken every 2.5 m over the world's free floor, fused in the map
    frame: the map a mapping mission would have left."""
    params = GridParams(**config.grid.model_dump())
    free = _free_positions(world, config, 0.5)
    lower, upper = world.bounds_xy()
    stations = []
    for x in np.arange(lower[0] + 1.25, upper[0], 2.5):
        for y in np.arange(lower[1] + 1.25, upper[1], 2.5):
            nearest = free[np.argmin(np.hypot(*(free - (x, y)).T))]
            if math.dist(nearest, (x, y)) < 1.0:
                stations.append((float(nearest[0]), float(nearest[1]), 0.0))
    mount = T_robot_scanner(config)
    scans = [_view_scan(world, pose, config, rng, scene) for pose in stations]
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
    from estimation.app.resources import resolve_builtin
    from sensors.sim.scene import RaycastScene, build_mesh
    from sensors.sim.world import load_world, perturb_movables

    world = load_world(resolve_builtin("worlds", world_name))
    params = GridParams(**config.grid.model_dump())
    segments = config.simulation.cylinder_segments
    free = _free_positions(world, config, 0.5)
    if len(free) == 0:
        raise EstimationError(f"{world_name}: no free position for a robot")
    scene = RaycastScene(build_mesh(world, cylinder_segments=segments))
    maps = _world_map(world, config, rng, scene, bands)
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
        free = _free_positions(changed, config, 0.5)
    out: list[Trial] = []
    for k in range(trials):
        x, y = free[rng.integers(len(free))]
        truth = np.array([float(x), float(y), float(rng.uniform(-math.pi, math.pi))])
        poses = [truth, *_mapper_poses(truth, views - 1, free, scene, config, rng)]
        scans = [
            _view_scan(changed, (p[0], p[1], math.degrees(p[2])), config, rng, scene) for p in poses
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
                _trial(
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


def _voxel_columns(
    tree: Any, z_range_m: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray, float]:
    """Centres (N, 2) of the band's known voxels, their occupancy (N,) and the resolution."""
    from mapping.band import band_layers

    first, last = band_layers(0.0, tree.resolution_m, *z_range_m)
    cells, occupied = tree.expand((first, last))
    centres = (cells[:, :2] + 0.5) * tree.resolution_m
    return centres, occupied, float(tree.resolution_m)


def _grid_points(
    points: np.ndarray,
    occupied: np.ndarray,
    lower: np.ndarray,
    shape: tuple[int, int],
    resolution_m: float,
) -> Band:
    """A band from voxel (or sub-column) points: a cell's occupancy is the share of the known
    points falling in it that are occupied; it is known when any point falls in it."""
    rows, cols = shape
    ij = np.floor((points - lower) / resolution_m).astype(np.int64)
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < cols) & (ij[:, 1] >= 0) & (ij[:, 1] < rows)
    flat = ij[inside, 1] * cols + ij[inside, 0]
    total = np.bincount(flat, minlength=rows * cols).reshape(rows, cols)
    hits = np.bincount(flat, weights=occupied[inside], minlength=rows * cols).reshape(rows, cols)
    known = total > 0
    return Band(
        occupancy=np.where(known, hits / np.maximum(total, 1), 0.0),
        known=known,
        lower_xy=np.asarray(lower, dtype=float),
        resolution_m=resolution_m,
    )


def geb079_trials(
    path: Path,
    config: Config,
    rng: np.random.Generator,
    trials: int,
    *,
    bands: tuple[str, ...] = ("ceiling", "floor"),
    capture: Callable[[Band, Band], None] | None = None,
    progress: Progress | None = None,
) -> list[Trial]:
    """Local grids cut from geb079 at random poses, ceiling and floor bands (see the module);
    ``capture`` is handed each (local, global) pair."""
    from mapping.formats.octomap_bt import read_bt

    tree = read_bt(path)
    heights = {"ceiling": (2.30, 2.55), "floor": (0.30, 1.50)}
    columns = {name: _voxel_columns(tree, heights[name]) for name in ("ceiling", "floor")}
    resolution = columns["ceiling"][2]
    maps: dict[str, Band] = {}
    for name, (centres, occupied, res) in columns.items():
        lower = np.floor(centres.min(axis=0) / res) * res
        upper = np.ceil(centres.max(axis=0) / res) * res + res
        shape = (round((upper[1] - lower[1]) / res), round((upper[0] - lower[0]) / res))
        maps[name] = _grid_points(centres, occupied.astype(float), lower, shape, res)
    # Robot positions: known, free cells of the floor band with plenty of ceiling around.
    floor = maps["floor"]
    fx, fy = floor.cell_centers()
    empty = floor.known & (floor.occupancy == 0)
    candidates = np.column_stack([fx[empty], fy[empty]])
    params = search_params(config.search)
    radius = 8.0
    half = math.ceil(radius / resolution)
    sub = (np.array([0.25, 0.75]) - 0.5) * resolution
    out: list[Trial] = []
    for k in range(trials):
        x, y = candidates[rng.integers(len(candidates))]
        yaw = float(rng.uniform(-math.pi, math.pi))
        # The robot frame, off the map's lattice by a random sub-cell offset.
        offset = rng.uniform(-0.5, 0.5, 2) * resolution
        truth = np.array([x + offset[0], y + offset[1], yaw])
        c, s = math.cos(yaw), math.sin(yaw)
        corners = np.stack(np.meshgrid(sub, sub), -1).reshape(1, 4, 2)
        for name, (centres, occupied, res) in columns.items():
            near = np.hypot(*(centres - truth[:2]).T) <= radius + res
            points = (centres[near][:, None, :] + corners).reshape(-1, 2) - truth[:2]
            occ = np.repeat(occupied[near].astype(float), 4)
            local_points = np.column_stack(
                [c * points[:, 0] + s * points[:, 1], -s * points[:, 0] + c * points[:, 1]]
            )
            lower = np.array([-half * res, -half * res])
            local = _grid_points(local_points, occ, lower, (2 * half, 2 * half), res)
            gx, gy = local.cell_centers()
            dropped = rng.random(local.known.shape) < 0.2
            keep = local.known & (np.hypot(gx, gy) <= radius) & ~dropped
            occupancy = np.clip(local.occupancy + rng.normal(0.0, 0.1, keep.shape), 0.0, 1.0)
            flip = rng.random(keep.shape) < 0.02
            occupancy = np.where(flip, 1.0 - occupancy, occupancy)
            local = Band(np.where(keep, occupancy, 0.0), keep, lower, res)
            if name not in bands:
                continue
            if capture is not None:
                capture(local, maps[name])
            out.append(_trial("geb079", name, local, maps[name], truth, params))
        if progress is not None:
            progress(f"geb079: trial {k + 1}/{trials}")
    return out


# -- CARMEN logs -------------------------------------------------------------------------------


@dataclass(frozen=True)
class CarmenScans:
    """The front-laser scans of a CARMEN log: ranges, beam angles, corrected robot poses."""

    ranges_m: list[np.ndarray]
    angles_rad: list[np.ndarray]
    poses: np.ndarray  # (N, 3) corrected robot pose x, y, theta
    max_range_m: float
    laser_offset_m: float


def read_carmen_scans(path: Path) -> CarmenScans:
    """Parse ``FLASER n r_0 … r_{n−1} x y theta …`` lines and the front-laser offset."""
    ranges: list[np.ndarray] = []
    angles: list[np.ndarray] = []
    poses: list[list[float]] = []
    offset, max_range = 0.0, 0.0
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt", encoding="utf-8") as handle:
        for number, line in enumerate(handle, start=1):
            fields = line.split()
            if not fields:
                continue
            if fields[0] == "PARAM" and len(fields) >= 3 and fields[1] == "robot_frontlaser_offset":
                offset = float(fields[2])
            if fields[0] != "FLASER":
                continue
            try:
                n = int(fields[1])
                values = np.array(fields[2 : 2 + n + 3], dtype=float)
            except (ValueError, IndexError) as exc:
                raise EstimationError(f"{path}:{number}: malformed FLASER line ({exc})") from None
            if len(values) != n + 3:
                raise EstimationError(f"{path}:{number}: FLASER line has too few fields")
            step = math.pi / (n - 1) if n in (181, 361) else math.pi / n
            ranges.append(values[:n])
            angles.append(-math.pi / 2 + step * np.arange(n))
            poses.append(list(values[n : n + 3]))
            max_range = max(max_range, float(values[:n].max()))
    if not poses:
        raise EstimationError(f"{path}: no FLASER lines")
    return CarmenScans(ranges, angles, np.asarray(poses), max_range, offset)


def _carmen_scan(scans: CarmenScans, i: int) -> tuple[Scan, np.ndarray]:
    """Scan i in its laser frame (planar, at z = 0.05 m of the band) and T_robot_laser."""
    r, a = scans.ranges_m[i], scans.angles_rad[i]
    valid = (r > 0.05) & (r < min(scans.max_range_m - 0.01, 40.0))
    points = np.column_stack([r * np.cos(a), r * np.sin(a), np.zeros_like(r)])
    directions = np.column_stack([np.cos(a), np.sin(a), np.zeros_like(a)])
    T = np.eye(4)
    T[0, 3], T[2, 3] = scans.laser_offset_m, 0.05
    return Scan(points[valid], directions[~valid]), T


def _pose_matrix(pose: np.ndarray) -> np.ndarray:
    return pose2_matrix(float(pose[0]), float(pose[1]), float(pose[2]))


def carmen_trials(
    path: Path,
    config: Config,
    rng: np.random.Generator,
    trials: int,
    *,
    scans_per_local_map: int = 1,
    progress: Progress | None = None,
) -> list[Trial]:
    """Localize odd-numbered scans (or short runs of them) in the map of the even ones."""
    scans = read_carmen_scans(path)
    params = GridParams(**{**config.grid.model_dump(), "no_return_free_m": 4.0})
    count = len(scans.poses)
    even = list(range(0, count, 2))
    pairs = [_carmen_scan(scans, i) for i in even]
    frames = [_pose_matrix(scans.poses[i]) @ T for i, (_, T) in zip(even, pairs, strict=True)]
    grid = fuse_scans([s for s, _ in pairs], frames, params)
    global_ = extract_band(grid, 0.0, 0.1)
    search_with = search_params(config.search)
    case = path.name.split("-corrected")[0]
    if scans_per_local_map > 1:
        case += f" ({scans_per_local_map} scans)"
    out: list[Trial] = []
    for k in range(trials):
        first = 1 + 2 * int(rng.integers((count - 2 * scans_per_local_map) // 2))
        used = [first + 2 * j for j in range(scans_per_local_map)]
        T_map_robot = _pose_matrix(scans.poses[first])
        T_robot_map = np.linalg.inv(T_map_robot)
        local_pairs = [_carmen_scan(scans, i) for i in used]
        local_frames = [
            T_robot_map @ _pose_matrix(scans.poses[i]) @ T
            for i, (_, T) in zip(used, local_pairs, strict=True)
        ]
        local_grid = fuse_scans([s for s, _ in local_pairs], local_frames, params)
        local = extract_band(local_grid, 0.0, 0.1)
        truth = np.array(scans.poses[first], dtype=float)
        out.append(_trial(case, "2D laser", local, global_, truth, search_with))
        if progress is not None:
            progress(f"{case}: trial {k + 1}/{trials}")
    return out


# -- figures -----------------------------------------------------------------------------------


def write_figures(
    out_dir: Path, config: Config, data_dir: Path = DATA_DIR, seed: int = 0
) -> list[Path]:
    """``search_geb079.png`` (a local ceiling grid placed in geb079, when the data is there) and
    ``search_office_loop.png`` (a single view in office_loop's south corridor: the PDF also
    shows the weaker places along the corridors where the view nearly fits), drawn by
    ``localize.render_pdf``."""
    from estimation.app.localize import Localization, render_pdf
    from estimation.app.resources import resolve_builtin
    from sensors.sim.scene import RaycastScene, build_mesh
    from sensors.sim.world import load_world

    written: list[Path] = []
    params = search_params(config.search)
    rng = np.random.default_rng(seed)
    path = data_dir / "octomap_fr079" / "geb079.bt"
    if path.exists():
        captured: dict[str, Band] = {}

        def keep(local: Band, global_: Band) -> None:
            captured["local"], captured["global"] = local, global_

        geb079_trials(path, config, rng, 1, bands=("ceiling",), capture=keep)
        result = search(captured["local"], captured["global"], params)
        found = Localization(
            result, (), result.is_dominant(params.dominance_ratio), captured["global"],
            captured["local"], result.seconds,
        )  # fmt: skip
        written.append(render_pdf(found, out_dir / "search_geb079.png"))
    world = load_world(resolve_builtin("worlds", "office_loop"))
    grid_params = GridParams(**config.grid.model_dump())
    scene = RaycastScene(build_mesh(world, cylinder_segments=config.simulation.cylinder_segments))
    global_ = _world_map(world, config, rng, scene)["ceiling"]
    scan = _view_scan(world, (7.0, 1.25, 90.0), config, rng, scene)
    local_grid = fuse_scans([scan], [T_robot_scanner(config)], grid_params)
    limits = config.bands.ceiling
    local = extract_band(
        local_grid, limits.min_m, limits.max_m, free_min_observed=config.bands.free_min_observed
    )
    result = search(local, global_, params)
    found = Localization(
        result, (), result.is_dominant(params.dominance_ratio), global_, local, result.seconds
    )
    written.append(render_pdf(found, out_dir / "search_office_loop.png"))
    return written


# -- summary -----------------------------------------------------------------------------------


def calibrate_beta(trials: list[Trial]) -> tuple[float, list[float]]:
    """The β of BETAS maximising the mean log P(true cell) over the trials, and that mean per β
    (trials whose truth lies off the lattice are left out)."""
    table = np.array(
        [
            t.log_likelihood
            for t in trials
            if t.log_likelihood and np.isfinite(t.log_likelihood).all()
        ]
    )
    if len(table) == 0:
        raise EstimationError("no trial to calibrate β on")
    mean = table.mean(axis=0)
    return float(BETAS[int(np.argmax(mean))]), [float(v) for v in mean]


def summarise(trials: list[Trial]) -> dict[str, Any]:
    errors_m = [t.error_m for t in trials]
    errors_deg = [t.error_deg for t in trials]
    return {
        "trials": len(trials),
        "success": sum(t.success for t in trials) / len(trials),
        "strict": sum(t.strict for t in trials) / len(trials),
        "median_m": statistics.median(errors_m),
        "median_deg": statistics.median(errors_deg),
        "p95_m": float(np.percentile(errors_m, 95)),
        "p95_deg": float(np.percentile(errors_deg, 95)),
        "median_seconds": statistics.median(t.seconds for t in trials),
        "dominant": sum(t.dominant for t in trials) / len(trials),
        "dominant_correct": (
            sum(t.success for t in trials if t.dominant) / max(1, sum(t.dominant for t in trials))
        ),
    }


def by_room_kind(trials: list[Trial]) -> list[Trial]:
    """The trials again, each case split by the kind of room holding the truth (the room name
    up to its first "_": office_loop's "corridor" and "office")."""
    import dataclasses

    return [
        dataclasses.replace(t, case=f"{t.case}: truth in {t.room.split('_')[0] or 'room'}s")
        for t in trials
    ]


def run_evaluation(
    config: Config,
    *,
    parts: tuple[str, ...] = ("sim", "geb079", "carmen"),
    trials: int = 40,
    data_dir: Path = DATA_DIR,
    seed: int = 0,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Run the parts asked for; real-data parts are skipped (and said so) without the data."""
    started = time.perf_counter()
    rows: list[dict[str, Any]] = []
    skipped: list[str] = []
    calibration: list[Trial] = []

    def add(trial_list: list[Trial]) -> None:
        by_key: dict[tuple[str, str], list[Trial]] = {}
        for trial in trial_list:
            by_key.setdefault((trial.case, trial.band), []).append(trial)
        for (case, band), group in by_key.items():
            rows.append({"case": case, "band": band, **summarise(group)})

    if "sim" in parts:
        for k, world in enumerate(("essex_lab", "office_loop", "cluttered_hall")):
            found = simulated_trials(
                world, config, np.random.default_rng(seed + k), trials, progress=progress
            )
            calibration += found
            add(found)
            if world == "office_loop":
                add(by_room_kind(found))
        rng = np.random.default_rng(seed + 5)
        add(
            simulated_trials(
                "office_loop", config, rng, trials, prior_sigma_m=1.0, progress=progress
            )
        )
        rng = np.random.default_rng(seed + 6)
        found = simulated_trials("office_loop", config, rng, trials, views=3, progress=progress)
        add(found)
        add(by_room_kind(found))
        perturb = (1.0, 1.0, 45.0, 0.2)
        add(
            simulated_trials(
                "cluttered_hall", config, np.random.default_rng(seed + 10), trials,
                bands=("ceiling", "floor"), perturb=perturb, progress=progress,
            )
        )  # fmt: skip
    if "geb079" in parts:
        path = data_dir / "octomap_fr079" / "geb079.bt"
        if path.exists():
            rng = np.random.default_rng(seed + 20)
            add(geb079_trials(path, config, rng, trials, progress=progress))
        else:
            skipped.append(f"geb079: {path} not found")
    if "carmen" in parts:
        for k, name in enumerate(("intel", "freiburg-079")):
            path = data_dir / "carmen_corrected" / f"{name}-corrected.log.gz"
            if not path.exists():
                skipped.append(f"{name}: {path} not found")
                continue
            for per_map in (1, 5):
                add(
                    carmen_trials(
                        path, config, np.random.default_rng(seed + 30 + k), trials,
                        scans_per_local_map=per_map, progress=progress,
                    )
                )  # fmt: skip
    report: dict[str, Any] = {"rows": rows, "skipped": skipped, "beta": config.search.beta}
    if calibration:
        best, curve = calibrate_beta(calibration)
        report["calibrated_beta"] = best
        report["beta_log_likelihood"] = dict(zip([float(b) for b in BETAS], curve, strict=True))
    report["seconds"] = time.perf_counter() - started
    return report


def format_report(report: dict[str, Any]) -> str:
    lines = [
        "| case | band | trials | success (<0.1 m, <1°) | strict (<0.05 m, <0.5°) | median error | "
        "95th percentile | dominant | correct when dominant | median search |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in report["rows"]:
        lines.append(
            f"| {row['case']} | {row['band']} | {row['trials']} | {row['success'] * 100:.0f} % | "
            f"{row['strict'] * 100:.0f} % | {row['median_m'] * 100:.1f} cm, "
            f"{row['median_deg']:.2f}° | {row['p95_m'] * 100:.1f} cm, {row['p95_deg']:.2f}° | "
            f"{row['dominant'] * 100:.0f} % | {row['dominant_correct'] * 100:.0f} % | "
            f"{row['median_seconds']:.2f} s |"
        )
    for note in report["skipped"]:
        lines.append(f"skipped: {note}")
    if "calibrated_beta" in report:
        lines.append(
            f"β maximising the mean log P(true cell) on the simulated ceiling searches: "
            f"{report['calibrated_beta']:.3g} (configured: {report['beta']:.3g})"
        )
    lines.append(f"({report['seconds']:.0f} s)")
    return "\n".join(lines)
