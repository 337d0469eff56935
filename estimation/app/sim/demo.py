"""``coopmap demo``: one simulated 360° 3D view of the default world.

Until the mission pipeline exists this is the whole demo: build the default world, ray-cast a
full 360° view from a robot's scanner with the LMS range noise, and write the world's figure,
the point cloud (PLY, map frame, coloured and labelled), a panoramic range image, the world and
the effective configuration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estimation import __version__
from estimation.app.config import Config, config_to_yaml
from estimation.app.figures import render_range_panorama, render_world
from estimation.app.resources import resolve_builtin
from mapping.formats.ply import write_ply
from sensors.atomic import write_text_atomic
from sensors.errors import WorldError
from sensors.geometry.frames import pose2_matrix, transform_points, transform_vectors
from sensors.sim.scene import RaycastScene, build_mesh, view_directions
from sensors.sim.world import World, load_world, world_to_yaml

__all__ = ["DEFAULT_POSE", "DEFAULT_WORLD", "DemoResult", "run_demo", "simulate_view"]

DEFAULT_WORLD = "essex_lab"
#: Robot pose (x_m, y_m, yaw_deg) of the demo view in the default world.
DEFAULT_POSE = (6.0, 4.5, 90.0)


@dataclass(frozen=True)
class View:
    """A simulated 360° view: the lattice, what each ray returned, and the sensor pose."""

    T_map_scanner: np.ndarray
    azimuth_rad: np.ndarray  # (A,)
    elevation_rad: np.ndarray  # (E,)
    range_m: np.ndarray  # (E, A), inf where no valid return
    surface_id: np.ndarray  # (E, A), −1 where no valid return
    points_scanner: np.ndarray  # (N, 3) valid returns

    @property
    def valid(self) -> np.ndarray:
        return np.asarray(np.isfinite(self.range_m))


def simulate_view(
    world: World,
    pose: tuple[float, float, float],
    config: Config,
    rng: np.random.Generator,
    scene: RaycastScene | None = None,
) -> View:
    """Ray-cast a 360° view from the scanner of a robot at ``pose`` (x_m, y_m, yaw_deg).

    Ranges get Gaussian noise of ``simulation.range_sigma_m`` and are quantised to the LMS unit;
    returns beyond ``scanner.max_range_m`` or closer than ``scanner.min_range_m`` are invalid.
    """
    sim = config.simulation
    if scene is None:
        scene = RaycastScene(build_mesh(world, cylinder_segments=sim.cylinder_segments))
    x_m, y_m, yaw_deg = pose
    T_map_robot = pose2_matrix(x_m, y_m, math.radians(yaw_deg))
    T_robot_scanner = pose2_matrix(
        config.robot.scanner_x_m, 0.0, 0.0, z_m=config.robot.scanner_height_m
    )
    T_map_scanner = T_map_robot @ T_robot_scanner
    directions, azimuth, elevation = view_directions(
        math.radians(sim.view_azimuth_step_deg),
        math.radians(sim.view_elevation_min_deg),
        math.radians(sim.view_elevation_max_deg),
        math.radians(sim.view_elevation_step_deg),
    )
    hits = scene.cast(
        np.broadcast_to(T_map_scanner[:3, 3], directions.shape),
        transform_vectors(T_map_scanner, directions),
    )
    unit_m = 0.001 if config.scanner.unit == "mm" else 0.01
    noisy = hits.range_m + rng.normal(0.0, sim.range_sigma_m, hits.range_m.shape)
    noisy = np.round(noisy / unit_m) * unit_m
    valid = hits.hit & (noisy >= config.scanner.min_range_m) & (noisy <= config.scanner.max_range_m)
    range_m = np.where(valid, noisy, np.inf)
    surface = np.where(valid, hits.surface_id, -1)
    shape = (len(elevation), len(azimuth))
    return View(
        T_map_scanner=T_map_scanner,
        azimuth_rad=azimuth,
        elevation_rad=elevation,
        range_m=range_m.reshape(shape),
        surface_id=surface.reshape(shape),
        points_scanner=directions[valid] * range_m[valid, None],
    )


def _distance_colors(distance_m: np.ndarray) -> np.ndarray:
    """Near points light, far points dark (the paper's Fig. 4b), as uint8 RGB."""
    from matplotlib import colormaps

    span = max(float(np.percentile(distance_m, 98)), 1e-6) if len(distance_m) else 1.0
    shade = np.clip(distance_m / span, 0.0, 1.0)
    return np.asarray(colormaps["magma_r"](shade)[:, :3] * 255, dtype=np.uint8)


@dataclass(frozen=True)
class DemoResult:
    out_dir: Path
    world: str
    pose: tuple[float, float, float]
    rays: int
    points: int
    surfaces_hit: int
    outputs: list[tuple[str, Path]] = field(default_factory=list)


def run_demo(
    out_dir: Path | str,
    config: Config,
    *,
    world: str | Path = DEFAULT_WORLD,
    pose: tuple[float, float, float] = DEFAULT_POSE,
    seed: int = 0,
) -> DemoResult:
    """Simulate one 360° view of ``world`` and write the outputs into ``out_dir``."""
    out_dir = Path(out_dir)
    world_model = load_world(resolve_builtin("worlds", world))
    if world_model.room_at(pose[:2]) is None:
        raise WorldError(
            f"demo pose ({pose[0]:g}, {pose[1]:g}) lies outside every room of {world_model.name!r}"
        )
    rng = np.random.default_rng(seed)
    view = simulate_view(world_model, pose, config, rng)

    points_map = transform_points(view.T_map_scanner, view.points_scanner)
    distance_m = np.linalg.norm(view.points_scanner, axis=1)
    surface = view.surface_id[view.valid]
    outputs: list[tuple[str, Path]] = []

    ply = out_dir / "view.ply"
    write_ply(
        ply,
        points_map,
        colors=_distance_colors(distance_m),
        fields={"range_m": distance_m.astype(np.float32), "surface_id": surface.astype(np.int32)},
    )
    outputs.append(("point cloud (map frame, PLY)", ply))
    top = render_world(
        world_model,
        out_dir / "world_top.png",
        band_m=(config.bands.ceiling.min_m, config.bands.ceiling.max_m),
        band_resolution_m=config.grid.resolution_m,
        cylinder_segments=config.simulation.cylinder_segments,
    )
    outputs.append(("world top view + ceiling band", top))
    panorama = render_range_panorama(
        view.range_m,
        view.azimuth_rad,
        view.elevation_rad,
        out_dir / "view_range.png",
        title=f"{world_model.name}: 360° view from ({pose[0]:g}, {pose[1]:g}, {pose[2]:g}°)",
    )
    outputs.append(("panoramic range image", panorama))
    world_file = out_dir / "world.yaml"
    write_text_atomic(world_file, world_to_yaml(world_model))
    outputs.append(("world", world_file))
    config_file = out_dir / "config.yaml"
    header = f"# effective configuration; coopmap {__version__}, seed {seed}\n"
    write_text_atomic(config_file, header + config_to_yaml(config))
    outputs.append(("effective config", config_file))
    return DemoResult(
        out_dir=out_dir,
        world=world_model.name,
        pose=pose,
        rays=int(view.range_m.size),
        points=len(points_map),
        surfaces_hit=len(np.unique(surface)),
        outputs=outputs,
    )
