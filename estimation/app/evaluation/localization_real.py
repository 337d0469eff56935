"""Localization trials on real data: the geb079 OctoMap and the CARMEN Intel and Freiburg 079
logs."""

from __future__ import annotations

import gzip
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from estimation.app.config import Config
from estimation.app.evaluation.trials import Progress, Trial, run_trial
from estimation.app.rig import search_params
from estimation.errors import EstimationError
from mapping.band import Band, extract_band
from mapping.fusion import Scan, fuse_scans
from mapping.grid import GridParams
from sensors.geometry.frames import pose2_matrix


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
        if not len(centres):
            low, high = heights[name]
            raise EstimationError(
                f"{path}: no known voxel between {low} and {high} m (the {name} band): not a "
                "building's map"
            )
        lower = np.floor(centres.min(axis=0) / res) * res
        upper = np.ceil(centres.max(axis=0) / res) * res + res
        shape = (round((upper[1] - lower[1]) / res), round((upper[0] - lower[0]) / res))
        maps[name] = _grid_points(centres, occupied.astype(float), lower, shape, res)
    # Robot positions: known, free cells of the floor band with plenty of ceiling around.
    floor = maps["floor"]
    fx, fy = floor.cell_centers()
    empty = floor.known & (floor.occupancy == 0)
    candidates = np.column_stack([fx[empty], fy[empty]])
    if not len(candidates):
        raise EstimationError(f"{path}: no free cell in the floor band to place a robot on")
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
            out.append(run_trial("geb079", name, local, maps[name], truth, params))
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
        out.append(run_trial(case, "2D laser", local, global_, truth, search_with))
        if progress is not None:
            progress(f"{case}: trial {k + 1}/{trials}")
    return out


# -- figures -----------------------------------------------------------------------------------
