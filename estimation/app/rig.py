"""The ``from_config`` glue: core parameter objects built from the configuration.

Core code takes explicit arguments; these factories read them from a
:class:`~estimation.app.config.Config` so that every command builds the same scanner, mirror,
beacon detector, simulated robot, graph settings and search parameters from one file.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from estimation.app.config import Config, SearchConfig
from estimation.posegraph.graph import GraphSettings
from estimation.search.exhaustive import SearchParams
from estimation.search.registration import RegistrationParams
from estimation.search.stations import StationParams
from mapping.band import Band, CeilingRule, extract_band, extract_ceiling_band
from mapping.grid import GridParams, OccupancyGrid
from sensors.geometry.frames import scanner_mount, scanner_pose_matrix
from sensors.lms200.driver import Lms200
from sensors.lms200.protocol.plausibility import ScanLimits
from sensors.scan3d.mirror import MirrorGeometry
from sensors.sim.scene import RaycastScene, build_mesh
from sensors.sim.sensing import RobotBody, SimulatedScanner, world_with_robots
from sensors.sim.world import World

if TYPE_CHECKING:  # the mission simulator (and its planner) is imported when a command simulates
    from sensors.sim.mission import OdometryNoise

__all__ = [
    "T_robot_scanner",
    "beacon_parameters",
    "ceiling_rule",
    "cut_ceiling_band",
    "driver_from_config",
    "dwell_seconds",
    "graph_settings",
    "mirror_geometry",
    "odometry_noise",
    "robot_body",
    "search_params",
    "simulated_scan_source",
    "simulated_scanner",
    "station_params",
]


def mirror_geometry(config: Config) -> MirrorGeometry:
    m = config.mirror
    return MirrorGeometry(
        axis_offset_m=m.axis_offset_m,
        gear_ratio=m.gear_ratio,
        nominal_motor_period_s=m.period_s / m.gear_ratio,
        elevation_offset_rad=m.elevation_offset_rad,
        elevation_min_rad=m.elevation_min_rad,
        elevation_max_rad=m.elevation_max_rad,
        arm_samples=m.arm_samples,
        arm_max_range_m=m.arm_max_range_m,
        edge_on_half_width_rad=m.edge_on_half_width_rad,
        edge_on_beams_rad=math.radians(m.edge_on_beams_deg),
        edge_on_motor_phase_rad=math.radians(m.edge_on_motor_phase_deg),
    )


def robot_body(config: Config) -> RobotBody:
    r, b = config.robot, config.beacon
    return RobotBody(
        footprint_radius_m=r.footprint_radius_m,
        body_height_m=r.body_height_m,
        scanner_x_m=r.scanner_x_m,
        beacon_offset_m=b.offset_m,
        beacon_height_m=b.height_m,
        beacon_radius_m=b.radius_m,
        beacon_length_m=b.length_m,
    )


def beacon_parameters(config: Config) -> dict[str, Any]:
    """Keyword arguments of :func:`sensors.scan3d.beacon.detect_beacons`."""
    b = config.beacon
    return {
        "radius_m": b.radius_m,
        "center_height_m": b.height_m - config.robot.scanner_height_m,
        "length_m": b.length_m,
        "height_tolerance_m": b.height_tolerance_m,
        "radius_tolerance_m": b.radius_tolerance_m,
        "min_returns": b.min_returns,
        "min_quality": b.min_quality,
        "max_range_m": b.max_range_m,
        "blind_wedge_rad": b.blind_wedge_rad,
    }


def T_robot_scanner(config: Config, *, planar: bool = False) -> np.ndarray:
    """Where the robot carries its scanner (``planar``: at the floor's height, for range and
    bearing in the plane)."""
    r = config.robot
    return scanner_mount(r.scanner_x_m, 0.0 if planar else r.scanner_height_m)


def graph_settings(config: Config) -> GraphSettings:
    g = config.graph
    return GraphSettings(
        prior_sigma_m=g.prior_sigma_m,
        prior_sigma_rad=g.prior_sigma_rad,
        odometry_sigma_m=g.odometry_sigma_m,
        odometry_sigma_per_m=g.odometry_sigma_per_m,
        odometry_sigma_rad=g.odometry_sigma_rad,
        odometry_sigma_rad_per_rad=math.radians(g.odometry_sigma_deg_per_rad),
        range_sigma_m=g.beacon_range_sigma_m,
        bearing_sigma_rad=g.beacon_bearing_sigma_rad,
        beacon_offset_m=config.beacon.offset_m,
        scanner_x_m=config.robot.scanner_x_m,
        global_min_sigma_m=g.global_min_sigma_m,
        global_min_sigma_rad=g.global_min_sigma_rad,
        gate_sigmas=g.gate_sigmas,
        dominance_ratio=config.search.dominance_ratio,
        peak_radius_m=config.search.peak_radius_m,
        peak_radius_rad=math.radians(config.search.peak_radius_deg),
        mutual_scale_min=g.mutual_scale_min,
    )


def search_params(section: SearchConfig, workers: int = 0) -> SearchParams:
    """The search parameters of the configuration's ``search`` section."""
    return SearchParams(
        angular_resolution_rad=section.angular_resolution_rad,
        free_weight=section.free_weight,
        occupied_level=section.occupied_level,
        beta=section.beta,
        peak_radius_m=section.peak_radius_m,
        peak_radius_rad=math.radians(section.peak_radius_deg),
        dominance_ratio=section.dominance_ratio,
        workers=workers,
        score=section.score,
    )


def station_params(config: Config) -> StationParams:
    """The station searches' parameters: β of station maps is ``search.station_beta``."""
    search = search_params(config.search)
    b = config.bands
    return StationParams(
        search=search,
        station_search=replace(search, beta=config.search.station_beta),
        grid=GridParams(**config.grid.model_dump()),
        T_robot_scanner=T_robot_scanner(config),
        ceiling_m=(b.ceiling.min_m, b.ceiling.max_m),
        floor_m=(b.floor.min_m, b.floor.max_m),
        free_min_observed=b.free_min_observed,
        window_m=config.search.window_m,
        max_window_m=config.search.max_window_m,
        ceiling_rule=ceiling_rule(config),
        reuse_tolerance_m=config.search.station_map_reuse_m,
        registration=registration_params(config),
    )


def registration_params(config: Config) -> RegistrationParams | None:
    """How links and loop closures are refined on the points (None when turned off)."""
    r = config.search.registration
    if not r.enabled:
        return None
    return RegistrationParams(
        voxel_m=r.voxel_m, max_distance_m=r.max_distance_m, inlier_m=r.inlier_m,
        min_inliers=r.min_inliers, inflation=r.inflation, min_sigma_m=r.min_sigma_m,
        min_sigma_rad=math.radians(r.min_sigma_deg),
    )  # fmt: skip


def ceiling_rule(config: Config) -> CeilingRule | None:
    """The rule of a ceiling band that follows the ceiling (``bands.ceiling_mode: follow``),
    else None (the fixed band)."""
    b = config.bands
    if b.ceiling_mode == "fixed":
        return None
    return CeilingRule(depth_m=b.ceiling_depth_m, gap_m=b.ceiling_gap_m,
                       smooth_m=b.ceiling_smooth_m,
                       fallback_m=(b.ceiling.min_m, b.ceiling.max_m),
                       clip=b.ceiling_mode == "clip")  # fmt: skip


def cut_ceiling_band(grid: OccupancyGrid, config: Config) -> Band:
    """The configuration's ceiling band of ``grid`` (fixed, or following the ceiling);
    MapError when it holds no observed cell."""
    b = config.bands
    rule = ceiling_rule(config)
    if rule is not None:
        return extract_ceiling_band(grid, rule, free_min_observed=b.free_min_observed)
    return extract_band(grid, b.ceiling.min_m, b.ceiling.max_m,
                        free_min_observed=b.free_min_observed)  # fmt: skip


def simulated_scanner(
    config: Config,
    rng: np.random.Generator,
    *,
    field_of_view_deg: int | None = None,
    resolution_deg: float | None = None,
) -> SimulatedScanner:
    """A simulated LMS + mirror with a random motor-rate error and phase (seeded)."""
    sim, scanner, m = config.simulation, config.scanner, config.mirror
    nominal = m.period_s / m.gear_ratio
    return SimulatedScanner(
        mirror_geometry(config),
        motor_period_s=nominal * (1.0 + rng.uniform(-1.0, 1.0) * sim.motor_rate_jitter),
        arm_phase_time_s=float(rng.uniform(0.0, nominal)),
        edge_on_turn=int(rng.integers(0, int(m.gear_ratio // 2))),
        arm_width_rad=math.radians(m.arm_width_deg),
        arm_drop_fraction=sim.arm_edge_drop_fraction,
        field_of_view_deg=field_of_view_deg or scanner.field_of_view_deg,
        resolution_deg=resolution_deg or scanner.angular_resolution_deg,
        max_range_m=scanner.max_range_m,
        min_range_m=scanner.min_range_m,
        range_sigma_m=sim.range_sigma_m,
        seed=int(rng.integers(0, 2**31)),
    )


_VARIANT_BY_COUNT = {101: (100, 1.0), 201: (100, 0.5), 401: (100, 0.25), 181: (180, 1.0),
                     361: (180, 0.5)}  # fmt: skip


def simulated_scan_source(
    world: World,
    pose: tuple[float, float, float],
    config: Config,
    seed: int = 0,
    others: dict[str, tuple[float, float, float]] | None = None,
) -> Callable[[float, int], tuple[np.ndarray, np.ndarray]]:
    """Ranges and reflector flags of the scanner of a robot at ``pose`` (x_m, y_m, yaw_rad),
    for the device emulator: ``source(t_s, count)`` simulates the scan measured at t_s with the
    variant that has ``count`` values. Other robots (name → pose) stand in the world.
    """
    scene_world = world_with_robots(world, others or {}, robot_body(config)) if others else world
    scene = RaycastScene(
        build_mesh(scene_world, cylinder_segments=config.simulation.cylinder_segments)
    )
    T_map_scanner = scanner_pose_matrix(
        *pose, config.robot.scanner_x_m, config.robot.scanner_height_m
    )
    rng = np.random.default_rng(seed)
    scanners: dict[int, SimulatedScanner] = {}
    mechanics = simulated_scanner(config, np.random.default_rng(seed))

    def source(t_s: float, count: int) -> tuple[np.ndarray, np.ndarray]:
        if count not in scanners:
            fov, res = _VARIANT_BY_COUNT[count]
            scanners[count] = replace(mechanics, field_of_view_deg=fov, resolution_deg=res)
        scans = scanners[count].scan(scene, T_map_scanner, np.array([t_s]), rng)
        return scans.ranges_m[0], scans.flags[0]

    return source


def driver_from_config(config: Config, port: str | None = None, **overrides: Any) -> Lms200:
    """The LMS 200 driver set up as the configuration says (``port`` overrides serial.port)."""
    s, scanner = config.serial, config.scanner
    options: dict[str, Any] = {
        "baud_rate": s.baud_rate,
        "address": s.address,
        "password": s.password,
        "angle_deg": scanner.field_of_view_deg,
        "resolution_deg": scanner.angular_resolution_deg,
        "measuring_mode": scanner.measuring_mode,
        "unit_mm": scanner.unit == "mm",
        "permanent_baud": s.permanent_baud,
        "ack_timeout_s": s.ack_timeout_s,
        "reply_timeout_s": s.reply_timeout_s,
        "config_write_timeout_s": s.config_write_timeout_s,
        "stream_timeout_s": s.stream_timeout_s,
        "nak_wait_s": s.nak_wait_s,
        "baud_switch_wait_s": s.baud_switch_wait_s,
        "retries": s.retries,
    }
    options.update(overrides)
    return Lms200(port or s.port, **options)


def scan_limits(config: Config) -> ScanLimits:
    """What the configured LMS 200 can send (variant, unit, baud rate): the plausibility rules."""
    scanner = config.scanner
    return ScanLimits.for_variant(
        scanner.field_of_view_deg, scanner.angular_resolution_deg,
        unit_mm=scanner.unit == "mm", baud_rate=config.serial.baud_rate,
    )  # fmt: skip


def dwell_seconds(config: Config) -> float:
    """Long enough for every scanner, whatever its phase, to complete one valid sweep."""
    half_turn = config.mirror.period_s / 2
    return 1.5 * half_turn * (1 + config.simulation.motor_rate_jitter) + 1.0


def odometry_noise(config: Config) -> OdometryNoise:
    """The simulated odometry's error per leg, as configured."""
    from sensors.sim.mission import OdometryNoise

    sim = config.simulation
    return OdometryNoise(
        sigma_m=sim.odometry_sigma_m,
        sigma_per_m=sim.odometry_sigma_per_m,
        sigma_rad=math.radians(sim.odometry_sigma_deg),
        sigma_rad_per_rad=math.radians(sim.odometry_sigma_deg_per_rad),
    )
