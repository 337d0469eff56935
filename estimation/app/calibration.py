"""Calibration of a rig from a recorded dataset: the mirror and the beacon (docs/calibration.md).

The dataset and configuration glue around the core estimators
(:mod:`sensors.scan3d.mirror_calibration`, :mod:`sensors.scan3d.beacon_calibration`): which
dwells and sweeps are used, the starting values (the dataset's configuration with ``--config``
merged over it), and the configuration fragment that holds the calibrated keys.

* **Mirror** (one robot's scanner): the motor phase at the edge-on moment from every dwell's arm
  and edge-on signature (``mirror.edge_on_motor_phase_deg``, when the gear ratio lets the
  assembly use it), then the axis offset and the elevation offset from the sweeps' planes
  (``mirror.axis_offset_m``, ``mirror.elevation_offset_deg``).
* **Beacon**: the centre height from the detected beacons (``beacon.height_m``), searched with a
  wide height tolerance first, since the detector gates returns by the configured height; then
  the offset from the mutual observations (``beacon.offset_m``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from estimation import __version__
from estimation.app.config import Config, ConfigError, config_from_mapping
from estimation.app.dataset import (
    DWELL_SETTLE_S,
    Dataset,
    RobotStream,
    decode_robot,
    load_dataset,
    sweep_in,
)
from estimation.app.rig import beacon_parameters, mirror_geometry
from sensors.atomic import write_text_atomic
from sensors.errors import OutputError, SensorError
from sensors.scan3d.beacon import BeaconDetection, detect_beacons
from sensors.scan3d.beacon_calibration import (
    OffsetEstimate,
    beacon_centre_height,
    beacon_separations,
    estimate_beacon_offset,
)
from sensors.scan3d.mirror import Scan3D, elevation_at, estimate_mirror
from sensors.scan3d.mirror_calibration import (
    MirrorCalibration,
    MirrorFitSettings,
    PhaseEstimate,
    SweepSamples,
    edge_on_motor_phase,
    fit_mirror,
)
from sensors.yamlio import merge_mappings, parse_yaml, read_text_file

__all__ = [
    "FRAGMENT_HEADER",
    "BeaconResult",
    "MirrorResult",
    "calibrate_beacon",
    "calibrate_mirror",
    "check_fragment_target",
    "fragment_text",
    "write_fragment",
]

#: The first line of every fragment coopmap writes: how an earlier fragment is recognised.
FRAGMENT_HEADER = "# coopmap calibration fragment"
#: A fragment is a few hundred bytes; anything much larger is not one.
FRAGMENT_LIMIT_BYTES = 64 * 1024
#: The edge-on signature's timing scatter (motor phase) above which the phase is doubtful.
PHASE_SPREAD_WARN_DEG = 45.0
#: A beacon offset standard error above this says the observations hardly constrain it.
OFFSET_SIGMA_WARN_M = 0.01


@dataclass(frozen=True)
class MirrorResult:
    """The mirror calibration of one robot's scanner, and its starting values."""

    dataset: Path
    config: Config  # the starting configuration
    robot: str
    start: dict[str, float]  # mirror keys as configured
    estimate: dict[str, float]  # the same keys, calibrated
    fit: MirrorCalibration
    phase: PhaseEstimate | None  # None: the assembly does not use the motor phase
    dwells: int
    missing: tuple[str, ...]  # dwells without a sweep, and why
    warnings: tuple[str, ...]

    @property
    def section(self) -> str:
        return "mirror"

    def summary(self) -> str:
        f = self.fit
        return (
            f"mirror of robot {self.robot} from {self.dataset}: {f.sweeps} sweeps, {f.points:,} "
            f"points on {sum(f.planes.values())} planes; point-to-plane RMS "
            f"{f.rms_before_m * 1e3:.1f} -> {f.rms_after_m * 1e3:.1f} mm"
        )

    def to_json(self) -> dict[str, Any]:
        f = self.fit
        return {
            "calibration": "mirror",
            "dataset": str(self.dataset),
            "robot": self.robot,
            "start": self.start,
            "estimate": self.estimate,
            "rms_before_mm": f.rms_before_m * 1e3,
            "rms_after_mm": f.rms_after_m * 1e3,
            "sweeps": f.sweeps,
            "points": f.points,
            "floor_points": f.floor_points,
            "planes": f.planes,
            "sigma_axis_offset_mm": f.sigma_axis_offset_m * 1e3,
            "sigma_elevation_offset_deg": math.degrees(f.sigma_elevation_rad),
            "correlation": f.correlation,
            "phase_spread_deg": None if self.phase is None else math.degrees(self.phase.spread_rad),
            "dwells": self.dwells,
            "missing_sweeps": list(self.missing),
            "warnings": list(self.warnings),
        }


@dataclass(frozen=True)
class BeaconResult:
    """The beacon calibration from a dataset's mutual observations."""

    dataset: Path
    config: Config  # the starting configuration
    start: dict[str, float]  # beacon keys as configured
    estimate: dict[str, float]
    offset: OffsetEstimate
    heights: int  # beacon detections the height rests on
    height_spread_m: float  # robust standard deviation of their centre heights
    observations: int  # mutual observations found (both beacons detected)
    at_configured_height: int  # of those, found with the configured height and tolerance
    warnings: tuple[str, ...]

    @property
    def section(self) -> str:
        return "beacon"

    def summary(self) -> str:
        o = self.offset
        return (
            f"beacon from {self.dataset}: {o.used} mutual observations used, "
            f"{o.skipped_degenerate} degenerate skipped; |s1 - s2| RMS "
            f"{o.separation_rms_before_m * 1e3:.1f} -> {o.separation_rms_after_m * 1e3:.1f} mm; "
            f"height from {self.heights} detections"
        )

    def to_json(self) -> dict[str, Any]:
        o = self.offset
        return {
            "calibration": "beacon",
            "dataset": str(self.dataset),
            "start": self.start,
            "estimate": self.estimate,
            "separation_rms_before_mm": o.separation_rms_before_m * 1e3,
            "separation_rms_after_mm": o.separation_rms_after_m * 1e3,
            "sigma_offset_mm": o.sigma_m * 1e3,
            "observations": self.observations,
            "used": o.used,
            "skipped_degenerate": o.skipped_degenerate,
            "downweighted": o.downweighted,
            "heights": self.heights,
            "height_spread_mm": self.height_spread_m * 1e3,
            "at_configured_height": self.at_configured_height,
            "warnings": list(self.warnings),
        }


def _dwell_windows(dataset: Dataset) -> list[tuple[int, float, float]]:
    """(event number, start, end) of every dwell; scans from 0.2 s after it began, as in batch."""
    return [(n, float(e["t_s"]) + DWELL_SETTLE_S, float(e["end_s"]))
            for n, e in enumerate(dataset.events) if e["event"] == "dwell"]  # fmt: skip


def _with_mirror(config: Config, **keys: float) -> Config:
    return config_from_mapping(merge_mappings(config.model_dump(), {"mirror": keys}))


def calibrate_mirror(
    dataset_path: Path | str,
    robot: str | None = None,
    overrides: dict[str, Any] | None = None,
    *,
    seed: int = 0,
) -> MirrorResult:
    """Calibrate ``robot``'s mirror (default: the mission's first robot) from its dwells.

    The starting values are the dataset's configuration with ``overrides`` merged over it.
    """
    dataset = load_dataset(dataset_path, overrides)
    config = dataset.config
    robot = dataset.robots[0] if robot is None else robot
    if robot not in dataset.robots:
        raise ConfigError(
            f"robot {robot!r} is not in the mission (robots: {', '.join(dataset.robots)})"
        )
    stream = decode_robot(
        dataset.path / "robots" / robot / "lms.cap", config.scanner.measuring_mode
    )
    windows = _dwell_windows(dataset)
    if not windows:
        raise SensorError(f"{dataset.path}: the event log has no dwell: no static sweeps")
    start_geometry = mirror_geometry(config)
    coarse_geometry = replace(start_geometry, edge_on_motor_phase_rad=None)
    m = config.mirror
    start = {"axis_offset_m": m.axis_offset_m, "elevation_offset_deg": m.elevation_offset_deg,
             "edge_on_motor_phase_deg": m.edge_on_motor_phase_deg}  # fmt: skip
    missing: list[str] = []
    coarse = []
    for number, begin, end in windows:
        rows = np.flatnonzero((stream.times_s >= begin) & (stream.times_s <= end))
        if len(rows) < 50:
            missing.append(f"dwell {number}: only {len(rows)} scans")
            continue
        try:
            coarse.append(
                estimate_mirror(
                    [stream.scans[k] for k in rows], stream.times_s[rows], coarse_geometry
                )
            )
        except SensorError as exc:
            missing.append(f"dwell {number}: {exc}")
    if not coarse:
        why = missing[0] if missing else "no dwell"
        raise SensorError(f"{dataset.path}: no dwell of robot {robot} yields a sweep ({why})")
    warnings: list[str] = []
    phase: PhaseEstimate | None = None
    calibrated = config
    if float(start_geometry.half_turn_motor_turns).is_integer():
        phase = edge_on_motor_phase(coarse)
        degrees = round(math.degrees(phase.phase_rad), 3) % 360.0
        calibrated = _with_mirror(config, edge_on_motor_phase_deg=degrees)
        if math.degrees(phase.spread_rad) > PHASE_SPREAD_WARN_DEG:
            warnings.append(
                f"the edge-on signatures scatter by {math.degrees(phase.spread_rad):.0f}° of motor "
                "phase: check the arm and the edge-on beams"
            )
    samples, missing_sweeps = _mirror_samples(stream, windows, config, calibrated)
    if not samples:
        why = missing_sweeps[0] if missing_sweeps else "no dwell"
        raise SensorError(f"{dataset.path}: no dwell of robot {robot} yields a sweep ({why})")
    r = config.robot
    settings = MirrorFitSettings(
        scanner_height_m=r.scanner_height_m,
        scanner_x_m=r.scanner_x_m,
        exclude_radius_m=r.footprint_radius_m + 0.1,
        seed=seed,
    )
    fit = fit_mirror(samples, m.axis_offset_m, settings)
    elevation = math.remainder(
        m.elevation_offset_deg + math.degrees(fit.elevation_correction_rad), 360.0
    )
    estimate = {"axis_offset_m": round(fit.axis_offset_m, 5),
                "elevation_offset_deg": round(elevation, 3)}  # fmt: skip
    if phase is not None:
        estimate["edge_on_motor_phase_deg"] = calibrated.mirror.edge_on_motor_phase_deg
    return MirrorResult(
        dataset=dataset.path,
        config=config,
        robot=robot,
        start={k: start[k] for k in estimate},
        estimate=estimate,
        fit=fit,
        phase=phase,
        dwells=len(windows),
        missing=tuple(missing + missing_sweeps),
        warnings=tuple(warnings) + fit.warnings,
    )


def _mirror_samples(
    stream: RobotStream,
    windows: list[tuple[int, float, float]],
    start: Config,
    calibrated: Config,
) -> tuple[list[SweepSamples], list[str]]:
    """Each dwell's sweep assembled with the calibrated phase, and the elevation shift that the
    starting calibration adds to it (one constant per dwell: both share the motor fit)."""
    samples: list[SweepSamples] = []
    missing: list[str] = []
    start_geometry, geometry = mirror_geometry(start), mirror_geometry(calibrated)
    for number, begin, end in windows:
        sweep, why = sweep_in(stream, begin, end, calibrated)
        if sweep is None:
            missing.append(f"dwell {number}: {why}")
            continue
        rows = np.flatnonzero((stream.times_s >= begin) & (stream.times_s <= end))
        scans, times = [stream.scans[k] for k in rows], stream.times_s[rows]
        at = times[:1]
        shift = elevation_at(at, estimate_mirror(scans, times, start_geometry)) - elevation_at(
            at, estimate_mirror(scans, times, geometry)
        )
        samples.append(
            SweepSamples(
                sweep.range_m,
                sweep.bearing_rad,
                sweep.elevation_rad,
                start_shift_rad=math.remainder(float(shift[0]), 2 * math.pi),
            )
        )
    return samples, missing


@dataclass(frozen=True)
class _Sighting:
    """Both robots' detections of each other in one dwell, with their sweeps."""

    seen_by_reference: BeaconDetection
    seen_by_mapper: BeaconDetection
    reference_scan: Scan3D
    mapper_scan: Scan3D


def _pair(
    at_reference: list[BeaconDetection], at_mapper: list[BeaconDetection], offset_m: float
) -> tuple[BeaconDetection, BeaconDetection] | None:
    """The detections that agree best on the beacon-to-beacon distance (|s1 − s2|)."""
    best: tuple[float, BeaconDetection, BeaconDetection] | None = None
    for u in at_reference:
        for v in at_mapper:
            s1, s2 = beacon_separations(
                np.array([u.range_m]), np.array([u.bearing_rad]),
                np.array([v.range_m]), np.array([v.bearing_rad]), offset_m,
            )  # fmt: skip
            gap = float(abs(s1[0] - s2[0]))
            if best is None or gap < best[0]:
                best = (gap, u, v)
    return None if best is None else (best[1], best[2])


def _sightings(
    scans: list[tuple[Scan3D, Scan3D]], params: dict[str, Any], offset_m: float
) -> list[_Sighting]:
    found = []
    for reference_scan, mapper_scan in scans:
        pair = _pair(
            detect_beacons(reference_scan.points_scanner, reference_scan.reflector, **params)[0],
            detect_beacons(mapper_scan.points_scanner, mapper_scan.reflector, **params)[0],
            offset_m,
        )
        if pair is not None:
            found.append(_Sighting(pair[0], pair[1], reference_scan, mapper_scan))
    return found


def _centre_heights(sightings: list[_Sighting], config: Config, center_m: float,
                    half_m: float) -> np.ndarray:  # fmt: skip
    heights = []
    for s in sightings:
        for detection, scan in ((s.seen_by_reference, s.reference_scan),
                                (s.seen_by_mapper, s.mapper_scan)):  # fmt: skip
            z = beacon_centre_height(
                scan.points_scanner, scan.reflector, detection.center_scanner[:2],
                radius_m=config.beacon.radius_m, band_center_m=center_m, band_half_m=half_m,
            )  # fmt: skip
            if z is not None:
                heights.append(z)
    return np.asarray(heights)


def calibrate_beacon(
    dataset_path: Path | str,
    overrides: dict[str, Any] | None = None,
    *,
    height_search_m: float = 1.0,
    min_asymmetry_m: float = 0.05,
) -> BeaconResult:
    """Calibrate the beacons' height and offset from the dataset's mutual observations.

    The beacon is first searched within ``height_search_m`` (plus half its length) of the
    configured height, then detected as configured around the height found there.
    """
    if not (math.isfinite(height_search_m) and height_search_m > 0):
        raise ConfigError(f"the height search must be a positive distance, got {height_search_m!r}")
    dataset = load_dataset(dataset_path, overrides)
    config = dataset.config
    b = config.beacon
    start = {"height_m": b.height_m, "offset_m": b.offset_m}
    dwells = [
        (n, e)
        for n, e in enumerate(dataset.events)
        if e["event"] == "dwell"
        and e.get("reference")
        and e.get("mapper") not in (None, e["reference"])
    ]
    if not dwells:
        raise SensorError(
            f"{dataset.path}: no dwell names a reference and a mapper: no mutual observations"
        )
    robots = sorted({r for _, e in dwells for r in (e["reference"], e["mapper"])})
    streams = {r: decode_robot(dataset.path / "robots" / r / "lms.cap",
                               config.scanner.measuring_mode) for r in robots}  # fmt: skip
    scans: list[tuple[Scan3D, Scan3D]] = []
    for _, e in dwells:
        pair = [sweep_in(streams[r], float(e["t_s"]) + DWELL_SETTLE_S, float(e["end_s"]), config)[0]
                for r in (e["reference"], e["mapper"])]  # fmt: skip
        if pair[0] is not None and pair[1] is not None:
            scans.append((pair[0], pair[1]))
    params = beacon_parameters(config)
    configured = _sightings(scans, params, b.offset_m)
    wide = _sightings(scans, {**params, "height_tolerance_m": height_search_m}, b.offset_m)
    if not wide:
        raise SensorError(
            f"{dataset.path}: no mutual observations: in none of {len(dwells)} dwells did both "
            f"robots detect each other's beacon (searched {b.height_m:g} m ± "
            f"{b.length_m / 2 + height_search_m:g} m; {len(scans)} dwells had both sweeps)"
        )
    scanner_h = config.robot.scanner_height_m
    searched = _centre_heights(
        wide, config, params["center_height_m"], b.length_m / 2 + height_search_m
    )
    if len(searched) == 0:
        raise SensorError(f"{dataset.path}: no beacon returns to measure the height from")
    first = float(np.median(searched))
    found = _sightings(scans, {**params, "center_height_m": first}, b.offset_m) or wide
    heights = _centre_heights(found, config, first, b.length_m / 2 + b.height_tolerance_m)
    if len(heights) == 0:
        raise SensorError(f"{dataset.path}: no beacon returns to measure the height from")
    centre = float(np.median(heights))
    spread = 1.4826 * float(np.median(np.abs(heights - centre)))
    rg = config.graph
    offset = estimate_beacon_offset(
        np.array([s.seen_by_reference.range_m for s in found]),
        np.array([s.seen_by_reference.bearing_rad for s in found]),
        np.array([s.seen_by_mapper.range_m for s in found]),
        np.array([s.seen_by_mapper.bearing_rad for s in found]),
        start_offset_m=b.offset_m,
        range_sigma_m=rg.beacon_range_sigma_m,
        bearing_sigma_rad=rg.beacon_bearing_sigma_rad,
        min_asymmetry_m=min_asymmetry_m,
    )
    if offset.offset_m <= 0:
        raise SensorError(
            f"the mutual observations give a beacon offset of {offset.offset_m:.3f} m (not "
            "ahead of the scanner): check the pairing of robots and beacons"
        )
    warnings = []
    if offset.sigma_m > OFFSET_SIGMA_WARN_M:
        warnings.append(
            f"the observations constrain the beacon offset poorly (σ {offset.sigma_m * 1e3:.0f} "
            "mm): record more observations in which the two bearings differ"
        )
    return BeaconResult(
        dataset=dataset.path,
        config=config,
        start=start,
        estimate={"height_m": round(centre + scanner_h, 4), "offset_m": round(offset.offset_m, 4)},
        offset=offset,
        heights=len(heights),
        height_spread_m=spread,
        observations=len(found),
        at_configured_height=len(configured),
        warnings=tuple(warnings),
    )


Result = MirrorResult | BeaconResult


def _previous(path: Path) -> tuple[dict[str, Any], list[str]]:
    """An earlier fragment at ``path``: its keys and its summary lines. Anything else there is
    refused (a user's file, a folder, a link)."""
    if path.is_symlink():
        raise OutputError(f"{path}: is a symbolic link; refusing to replace it")
    if not path.exists():
        return {}, []
    if path.is_dir():
        raise OutputError(f"{path}: is a folder; --out names the fragment file to write")
    text = read_text_file(path, OutputError, FRAGMENT_LIMIT_BYTES)
    if not text.startswith(FRAGMENT_HEADER):
        raise OutputError(
            f"{path}: exists and is not a coopmap calibration fragment; refusing to replace it"
        )
    document = parse_yaml(text, str(path), OutputError) or {}
    if not isinstance(document, dict):
        raise OutputError(f"{path}: a calibration fragment must be a YAML mapping")
    summaries = [line for line in text.splitlines()
                 if line.startswith(("# mirror ", "# beacon "))]  # fmt: skip
    return document, summaries


def fragment_text(result: Result, previous: tuple[dict[str, Any], list[str]] = ({}, [])) -> str:
    """The YAML fragment of the calibrated keys, over those of an earlier fragment, with a
    header saying what produced each part. Checked against the configuration schema, merged over
    the configuration the calibration started from."""
    keys, summaries = previous
    merged = merge_mappings(keys, {result.section: result.estimate})
    try:
        config_from_mapping(
            merge_mappings(result.config.model_dump(), merged), source="calibration fragment"
        )
    except ConfigError as exc:
        raise SensorError(f"the calibration gave values the configuration refuses: {exc}") from None
    kept = [line for line in summaries if not line.startswith(f"# {result.section} ")]
    header = [
        f"{FRAGMENT_HEADER}, written by coopmap calibrate (coopmap {__version__}).",
        "# Use it with --config FILE (batch, isam, calibrate); see docs/calibration.md.",
        *kept,
        f"# {result.summary()}",
    ]
    return "\n".join(header) + "\n" + yaml.safe_dump(merged, sort_keys=True)


def check_fragment_target(path: Path | str) -> None:
    """Refuse, before any work, an ``--out`` that is not a new file or an earlier fragment."""
    _previous(Path(path))


def write_fragment(path: Path | str, result: Result) -> str:
    """Write the fragment to ``path`` atomically, keeping the keys of an earlier fragment there
    that this calibration does not set; returns the text written."""
    path = Path(path)
    text = fragment_text(result, _previous(path))
    write_text_atomic(path, text)
    return text
