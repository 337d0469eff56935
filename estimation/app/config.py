"""The configuration schema of coopmap, validated at load.

``configs/default.yaml`` holds every default below (a test checks that the two agree). A user's
``--config FILE`` is a partial YAML document merged key by key over these defaults; the merged
result is validated as a whole. Unknown keys, wrong types, NaN and out-of-range values are
``ConfigError``s that name the key path and the bad value.

Files speak in the units people think in (degrees where a key ends in ``_deg``); the code reads
SI values through the ``*_rad`` properties. Core functions take explicit arguments, never this
object: the ``from_config`` glue lives in the app layer.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal, Self

import yaml
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from sensors.yamlio import merge_mappings, read_yaml_mapping, validate_mapping

__all__ = [
    "BandConfig",
    "BandsConfig",
    "BeaconConfig",
    "Config",
    "ConfigError",
    "GraphConfig",
    "GridConfig",
    "MirrorConfig",
    "RobotConfig",
    "ScannerConfig",
    "SearchConfig",
    "SerialConfig",
    "SimulationConfig",
    "config_to_yaml",
    "load_config",
]


class ConfigError(ValueError):
    """A configuration file or value is invalid; the message names the key path and value."""


class _Section(BaseModel):
    model_config = ConfigDict(
        extra="forbid", frozen=True, strict=True, allow_inf_nan=False, validate_default=True
    )


Positive = Field(gt=0)
NonNegative = Field(ge=0)


class ScannerConfig(_Section):
    """The SICK LMS 200 and how it is set up (protocol details: docs/lms200-protocol.md)."""

    field_of_view_deg: Literal[100, 180] = Field(
        100, description="scan variant: 100° (−50…+50°) or 180° (−90…+90°)"
    )
    angular_resolution_deg: float = Field(1.0, description="1, 0.5 or 0.25 (variant)")
    unit: Literal["mm", "cm"] = Field("mm", description="measured value unit (block E)")
    measuring_mode: int = Field(
        1, description="LMS block D; 1 = 8 m range with 3 reflector bits per sample"
    )
    max_range_m: float = Field(8.0, gt=0, le=81.91, description="largest valid range")
    min_range_m: float = Field(0.05, ge=0, description="returns closer than this are ignored")

    @field_validator("angular_resolution_deg")
    @classmethod
    def _known_resolution(cls, value: float) -> float:
        if value not in (1.0, 0.5, 0.25):
            raise ValueError("must be one of 1, 0.5, 0.25")
        return value

    @field_validator("measuring_mode")
    @classmethod
    def _known_mode(cls, value: int) -> int:
        if value not in (0, 1, 2, 3, 4, 5, 6, 15):
            raise ValueError("must be an LMS 200 measuring mode: 0-6 or 15")
        return value

    @model_validator(mode="after")
    def _ranges_ordered(self) -> Self:
        if self.min_range_m >= self.max_range_m:
            raise ValueError(
                f"min_range_m ({self.min_range_m}) must be below max_range_m ({self.max_range_m})"
            )
        if self.field_of_view_deg == 180 and self.angular_resolution_deg == 0.25:
            raise ValueError("the LMS 200 has no 180° variant at 0.25°")
        return self

    @property
    def angular_resolution_rad(self) -> float:
        return math.radians(self.angular_resolution_deg)


class MirrorConfig(_Section):
    """The rotating mirror in front of the scanner (docs/design.md §3, paper eq. 4)."""

    axis_offset_m: float = Field(
        0.10, gt=0, description="d of eq. 4: scanner origin to mirror axis, along x"
    )
    period_s: float = Field(40.0, gt=0, description="one mirror revolution")
    gear_ratio: float = Field(80.0, gt=0, description="motor revolutions per mirror revolution")
    elevation_offset_deg: float = Field(0.0, ge=-180, le=180, description="φ0 in φ = 2ψ + φ0")
    elevation_min_deg: float = Field(-90.0, ge=-180, le=180, description="valid sweep start")
    elevation_max_deg: float = Field(90.0, ge=-180, le=180, description="valid sweep end")
    arm_samples: int = Field(3, ge=1, le=20, description="right-most samples the arm blocks")
    arm_max_range_m: float = Field(0.25, gt=0, description="a blocked sample reads below this")
    edge_on_half_width_deg: float = Field(
        3.0, ge=0, le=45, description="mirror angles this close to edge-on are blind"
    )
    edge_on_beams_deg: float = Field(
        30.0, gt=0, le=50, description="edge-on, the mirror's edge blocks beams within ± this"
    )
    arm_width_deg: float = Field(
        90.0, gt=0, lt=360, description="motor angle over which the arm blocks the beams"
    )
    edge_on_motor_phase_deg: float = Field(
        0.0, ge=0, lt=360, description="calibration: motor angle after an arm edge at edge-on"
    )

    @model_validator(mode="after")
    def _sweep_ordered(self) -> Self:
        if self.elevation_min_deg >= self.elevation_max_deg:
            raise ValueError(
                f"elevation_min_deg ({self.elevation_min_deg}) must be below "
                f"elevation_max_deg ({self.elevation_max_deg})"
            )
        return self

    @property
    def motor_rate_hz(self) -> float:
        return self.gear_ratio / self.period_s

    @property
    def elevation_offset_rad(self) -> float:
        return math.radians(self.elevation_offset_deg)

    @property
    def elevation_min_rad(self) -> float:
        return math.radians(self.elevation_min_deg)

    @property
    def elevation_max_rad(self) -> float:
        return math.radians(self.elevation_max_deg)

    @property
    def edge_on_half_width_rad(self) -> float:
        return math.radians(self.edge_on_half_width_deg)


class BeaconConfig(_Section):
    """The retro-reflective cylinder every robot carries, and how it is detected (docs/design.md
    §4)."""

    offset_m: float = Field(
        0.25, gt=0, description="d of eq. 1-2: straight ahead of the scanner origin"
    )
    height_m: float = Field(
        1.6, gt=0, description="centre above the floor; high enough to clear the edge-on blind band"
    )
    radius_m: float = Field(0.1, gt=0)
    length_m: float = Field(0.6, gt=0, description="vertical extent of the reflective band")
    blind_wedge_deg: float = Field(
        20.0, ge=0, lt=180, description="forward wedge where beacons cannot be seen"
    )
    min_returns: int = Field(3, ge=1, description="flagged returns needed for a detection")
    height_tolerance_m: float = Field(0.15, gt=0)
    radius_tolerance_m: float = Field(0.03, gt=0)
    min_quality: float = Field(
        0.6, ge=0, le=1,
        description="a detection's fit quality (returns and RMS off the cylinder) needed",
    )  # fmt: skip
    max_range_m: float = Field(8.0, gt=0)

    @property
    def blind_wedge_rad(self) -> float:
        return math.radians(self.blind_wedge_deg)


class RobotConfig(_Section):
    """The robot body and where the scanner sits on it (robot frame: x forward, z up)."""

    footprint_radius_m: float = Field(0.30, gt=0)
    body_height_m: float = Field(0.35, gt=0)
    scanner_x_m: float = Field(0.10, description="scanner origin ahead of the robot origin")
    scanner_height_m: float = Field(0.45, gt=0, description="scanner origin above the floor")
    speed_m_s: float = Field(0.4, gt=0, le=5, description="driving speed in simulated missions")
    turn_rate_deg_s: float = Field(45.0, gt=0, le=720, description="turning in place")


class GridConfig(_Section):
    """The 3D Bayesian occupancy grid (docs/design.md §6, paper eq. 3). Defaults are OctoMap's."""

    # At least 5 mm: finer cells than the LMS 200's range noise only multiply memory (a 0.5 mm
    # grid of one building is terabytes).
    resolution_m: float = Field(0.1, ge=0.005, le=10)  # mapping.grid.MIN_RESOLUTION_M
    prob_hit: float = Field(0.7, gt=0.5, lt=1)
    prob_miss: float = Field(0.4, gt=0, lt=0.5)
    clamp_min: float = Field(0.1192, gt=0, lt=1)
    clamp_max: float = Field(0.971, gt=0, lt=1)
    occupied_threshold: float = Field(0.5, gt=0, lt=1)
    no_return_free_m: float = Field(
        4.0, ge=0, description="no-return beams are free up to this range"
    )
    block_size_cells: int = Field(16, ge=2, le=256, description="edge of a storage block")

    @model_validator(mode="after")
    def _clamps_ordered(self) -> Self:
        if not self.clamp_min < self.occupied_threshold < self.clamp_max:
            raise ValueError(
                f"need clamp_min < occupied_threshold < clamp_max, got {self.clamp_min}, "
                f"{self.occupied_threshold}, {self.clamp_max}"
            )
        return self


class BandConfig(_Section):
    """A horizontal slice of the 3D map, heights above the floor."""

    min_m: float
    max_m: float

    @model_validator(mode="after")
    def _ordered(self) -> Self:
        if self.min_m >= self.max_m:
            raise ValueError(f"min_m ({self.min_m}) must be below max_m ({self.max_m})")
        return self


class BandsConfig(_Section):
    """The 2D bands cut from 3D maps: the paper's ceiling band, and a floor band to compare."""

    ceiling: BandConfig = BandConfig(min_m=2.3, max_m=2.9)
    floor: BandConfig = BandConfig(min_m=0.2, max_m=1.5)
    ceiling_mode: Literal["fixed", "clip", "follow"] = Field(
        "fixed",
        description="fixed: the ceiling band is [ceiling.min_m, ceiling.max_m) everywhere; "
        "clip: that band, cut off ceiling_gap_m below the ceiling seen around each column "
        "where the ceiling is lower (at least two layers deep); follow: under every column, "
        "ceiling_depth_m of layers ending ceiling_gap_m below the ceiling seen around it (the "
        "fixed band where no ceiling was seen)",
    )
    ceiling_depth_m: float = Field(0.6, gt=0, le=5)
    ceiling_gap_m: float = Field(0.1, ge=0, le=2)
    ceiling_smooth_m: float = Field(1.0, ge=0, le=10)
    free_min_observed: float = Field(
        0.5, ge=0, le=1,
        description="a column without an occupied layer is free only when at least this share "
        "of its layers was observed, else unknown",
    )  # fmt: skip


SearchScore = Literal["agreement", "centred", "excess"]


class RegistrationConfig(_Section):
    """Station links and loop closures refined on the stations' 3D points: planar
    point-to-plane ICP seeded by the search (docs/design.md §7)."""

    enabled: bool = Field(
        True, description="false: the search's pose is the measurement (docs/design.md §7)"
    )
    voxel_m: float = Field(0.05, gt=0, le=1, description="points averaged per voxel")
    max_distance_m: float = Field(
        0.3, gt=0, le=5, description="farthest correspondence while iterating"
    )
    inlier_m: float = Field(
        0.1, gt=0, le=5, description="a point with a match this close is an inlier"
    )
    min_inliers: float = Field(
        0.5, ge=0, le=1, description="share of the overlapping points that must be inliers"
    )
    inflation: float = Field(
        100.0, ge=1, description="covariance factor for the correlation of neighbouring points"
    )
    min_sigma_m: float = Field(0.01, gt=0, description="floor on the factor's sigma")
    min_sigma_deg: float = Field(0.2, gt=0)


class SearchConfig(_Section):
    """The exhaustive (x, y, θ) correlation search (docs/design.md §7)."""

    resolution_m: float = Field(0.1, gt=0)
    angular_resolution_deg: float = Field(1.0, gt=0, le=45)
    window_m: float = Field(4.0, gt=0, description="first window side around a prior")
    max_window_m: float = Field(40.0, gt=0, description="the window grows up to this side")
    dominance_ratio: float = Field(
        2.0, ge=1, description="peak is dominant when best / best elsewhere >= this"
    )
    peak_radius_m: float = Field(0.5, gt=0, description="neighbourhood of the peak")
    peak_radius_deg: float = Field(10.0, gt=0)
    free_weight: float = Field(0.5, ge=0, description="weight of free-space agreement")
    occupied_level: float = Field(
        0.1, gt=0, lt=1, description="band occupancy from which a cell is occupied evidence"
    )
    score: SearchScore = Field(
        "agreement",
        description="agreement: Σ v_L·v_G over known cells; centred: the values less their "
        "band's mean; excess: agreement − m_L·m_G·overlap (no gain from overlap alone)",
    )
    beta: float = Field(0.04, gt=0, description="PDF ∝ exp(beta · score), calibrated")
    station_beta: float = Field(
        0.125, gt=0,
        description="beta of the searches between station maps inside a mission (links, loop "
        "closures), calibrated on simulated missions",
    )  # fmt: skip
    registration: RegistrationConfig = RegistrationConfig()
    station_map_reuse_m: float = Field(
        0.002, ge=0,
        description="a station map is kept across the search stages until a view moved "
        "relative to its station by more than this at any of its points (0: fused again "
        "whenever a relative pose changed at all)",
    )  # fmt: skip

    @model_validator(mode="after")
    def _windows_ordered(self) -> Self:
        if self.window_m > self.max_window_m:
            raise ValueError(
                f"window_m ({self.window_m}) must not exceed max_window_m ({self.max_window_m})"
            )
        return self

    @property
    def angular_resolution_rad(self) -> float:
        return math.radians(self.angular_resolution_deg)


RobustKernel = Literal["gnc_tls", "huber", "cauchy", "none"]


class GraphConfig(_Section):
    """Noise models and solver settings of the GTSAM pose graph (docs/design.md §5)."""

    prior_sigma_m: float = Field(0.001, gt=0)
    prior_sigma_deg: float = Field(0.01, gt=0)
    odometry_sigma_m: float = Field(0.01, gt=0, description="per step")
    odometry_sigma_per_m: float = Field(0.05, ge=0, description="added per metre travelled")
    odometry_sigma_deg: float = Field(0.5, gt=0, description="per step")
    odometry_sigma_deg_per_rad: float = Field(2.0, ge=0, description="added per radian turned")
    beacon_range_sigma_m: float = Field(0.02, gt=0)
    beacon_bearing_sigma_deg: float = Field(0.25, gt=0)
    global_min_sigma_m: float = Field(0.02, gt=0, description="floor on the search covariance")
    global_min_sigma_deg: float = Field(0.3, gt=0)
    search_factors: bool = Field(
        True, description="add the station-map searches (links, loop closures) as factors"
    )
    robust: RobustKernel = "gnc_tls"
    gate_sigmas: float = Field(3.0, gt=0, description="s1/s2 gate in predicted standard devs")
    mutual_scale_min: float | None = Field(
        0.1,
        gt=0,
        le=1,
        description="scale the mutual observations' noise by the spread of their s1/s2 gaps "
        "so far, down to this factor (null: the beacon noise as configured)",
    )
    validator_mass: float = Field(
        0.99, gt=0, lt=1, description="PDF mass of the high-probability region"
    )
    isam2_relinearize_threshold: float = Field(0.01, gt=0)
    isam2_relinearize_skip: int = Field(1, ge=1)

    @property
    def prior_sigma_rad(self) -> float:
        return math.radians(self.prior_sigma_deg)

    @property
    def odometry_sigma_rad(self) -> float:
        return math.radians(self.odometry_sigma_deg)

    @property
    def beacon_bearing_sigma_rad(self) -> float:
        return math.radians(self.beacon_bearing_sigma_deg)

    @property
    def global_min_sigma_rad(self) -> float:
        return math.radians(self.global_min_sigma_deg)


class SimulationConfig(_Section):
    """Noise and sampling of the simulator (docs/design.md §9)."""

    range_sigma_m: float = Field(0.005, ge=0, description="LMS range noise")
    odometry_sigma_m: float = Field(0.005, ge=0, description="per step")
    odometry_sigma_per_m: float = Field(0.02, ge=0, description="added per metre travelled")
    odometry_sigma_deg: float = Field(0.2, ge=0, description="per step")
    odometry_sigma_deg_per_rad: float = Field(1.0, ge=0, description="added per radian turned")
    motor_rate_jitter: float = Field(0.01, ge=0, lt=0.5, description="relative")
    arm_edge_drop_fraction: float = Field(0.0, ge=0, lt=1)
    cylinder_segments: int = Field(48, ge=8, le=1024, description="facets of a simulated cylinder")
    view_azimuth_step_deg: float = Field(1.0, gt=0, le=45, description="360° view (demo)")
    view_elevation_step_deg: float = Field(1.0, gt=0, le=45)
    view_elevation_min_deg: float = Field(-45.0, ge=-90, le=90)
    view_elevation_max_deg: float = Field(60.0, ge=-90, le=90)

    @model_validator(mode="after")
    def _view_ordered(self) -> Self:
        if self.view_elevation_min_deg >= self.view_elevation_max_deg:
            raise ValueError(
                f"view_elevation_min_deg ({self.view_elevation_min_deg}) must be below "
                f"view_elevation_max_deg ({self.view_elevation_max_deg})"
            )
        return self


class SerialConfig(_Section):
    """The serial link to a real LMS 200 (docs/lms200-protocol.md §1, §4, §9)."""

    port: str = Field("/dev/ttyUSB0", min_length=1, description="a device path or pyserial URL")
    baud_rate: Literal[9600, 19200, 38400, 500000] = 38400
    address: int = Field(0, ge=0, le=255)
    password: str = Field("SICK_LMS", min_length=8, max_length=8, pattern=r"^[\x20-\x7e]{8}$")
    ack_timeout_s: float = Field(0.2, gt=0, description="spec: 60 ms; USB adapters add latency")
    reply_timeout_s: float = Field(3.0, gt=0, description="mode switches take up to 3 s")
    config_write_timeout_s: float = Field(15.0, gt=0)
    stream_timeout_s: float = Field(1.0, gt=0, description="silence that ends a stream")
    nak_wait_s: float = Field(0.03, ge=0.03, description="wait after a NAK before resending")
    baud_switch_wait_s: float = Field(0.25, ge=0)
    retries: int = Field(3, ge=0, le=20)
    permanent_baud: bool = False


class Config(_Section):
    """Every parameter of coopmap, in sections."""

    scanner: ScannerConfig = ScannerConfig()
    mirror: MirrorConfig = MirrorConfig()
    beacon: BeaconConfig = BeaconConfig()
    robot: RobotConfig = RobotConfig()
    grid: GridConfig = GridConfig()
    bands: BandsConfig = BandsConfig()
    search: SearchConfig = SearchConfig()
    graph: GraphConfig = GraphConfig()
    simulation: SimulationConfig = SimulationConfig()
    serial: SerialConfig = SerialConfig()

    @model_validator(mode="after")
    def _beacon_above_scanner(self) -> Self:
        if self.beacon.height_m - self.beacon.length_m / 2 <= self.robot.scanner_height_m:
            raise ValueError(
                f"beacon (height_m {self.beacon.height_m}, length_m {self.beacon.length_m}) "
                f"must sit above the scanner (robot.scanner_height_m {self.robot.scanner_height_m})"
            )
        return self


def config_from_mapping(overrides: dict[str, Any], source: str = "config") -> Config:
    """Merge ``overrides`` (a partial document) over the defaults and validate the result."""
    merged = merge_mappings(Config().model_dump(), overrides)
    return validate_mapping(Config, merged, ConfigError, source)


def load_config(path: Path | str | None = None) -> Config:
    """The defaults, with the YAML file at ``path`` (if any) merged over them."""
    if path is None:
        return Config()
    path = Path(path)
    return config_from_mapping(read_yaml_mapping(path, ConfigError), source=str(path))


def config_to_yaml(config: Config) -> str:
    """The effective configuration as a YAML document (written next to every run's outputs)."""
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)
