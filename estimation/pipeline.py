"""``coopmap batch``: a recorded dataset → optimized poses and the global 3D map (DESIGN §1).

Per robot, the raw LMS bytes are decoded with the real parser; every dwell (all robots still)
yields one full sweep per robot — the mirror's motor rate and phase estimated from the arm and
edge-on signatures inside that dwell — converted to 3D points, in which the beacons are found.
The dataset's event log becomes the estimator's event stream: a gauge prior on the first robot's
start, odometry between each robot's stops, and the mutual observations of every dwell between
its reference and mapper (gated by s1/s2 in the graph builder). The graph is optimized in batch
(Levenberg–Marquardt, graduated non-convexity on mutual and global factors), and every sweep is
re-fused into the global occupancy grid at its optimized pose. Outputs follow DESIGN §12.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from estimation import __version__
from estimation.config import Config, ConfigError, config_from_mapping
from estimation.errors import EstimationError
from estimation.events import Event, Localize, Move, Observe, Start
from estimation.graph import FactorSpec, GraphBuilder, GraphSettings
from estimation.keys import key_label, pose_key, split_key
from estimation.loopclosure import SEARCH_STAGES, SearchRecord, records_json, relocalize
from estimation.rig import beacon_parameters, mirror_geometry
from estimation.smoother import BatchResult, optimize_batch
from estimation.validate import validate_and_repair
from mapping.fusion import Scan as MapScan
from mapping.fusion import fuse_scans
from mapping.grid import GridParams, OccupancyGrid
from sensors.beacon import BeaconDetection, detect_beacons
from sensors.errors import SensorError
from sensors.frames import pose2_matrix
from sensors.lms200.capture import CaptureReader
from sensors.lms200.protocol import ProtocolError, Scan, StreamParser, Telegram, decode_scan
from sensors.mirror import Scan3D, assemble_sweeps, estimate_mirror, scan_times

__all__ = ["BatchOutput", "Dataset", "Sweep", "graph_settings", "load_dataset", "run_batch"]

Progress = Callable[[str], None]


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
    )


@dataclass(frozen=True)
class Dataset:
    """A recorded mission (DESIGN §12), as read from its folder."""

    path: Path
    config: Config
    robots: list[str]
    starts: dict[str, np.ndarray]  # declared start poses (x_m, y_m, yaw_rad): the map frame
    events: list[dict[str, Any]]
    mission: dict[str, Any]

    def stop_times(self, robot: str) -> dict[int, float]:
        """When each pose index of ``robot`` began (index 0 at the start)."""
        times = {0: 0.0}
        for e in self.events:
            if e["event"] == "move" and e["robot"] == robot:
                times[int(e["to_index"])] = float(e["t_s"])
        return times


def load_dataset(path: Path | str, overrides: dict[str, Any] | None = None) -> Dataset:
    """Read ``mission.yaml`` and ``events.jsonl``; the effective config is the mission's, with
    ``overrides`` merged over it."""
    path = Path(path)
    mission_file = path / "mission.yaml"
    events_file = path / "events.jsonl"
    for needed in (mission_file, events_file):
        if not needed.is_file():
            raise ConfigError(f"{path}: not a coopmap dataset ({needed.name} is missing)")
    try:
        mission = yaml.safe_load(mission_file.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise ConfigError(f"{mission_file}: malformed YAML: {exc}") from None
    if not isinstance(mission, dict) or "robots" not in mission:
        raise ConfigError(f"{mission_file}: not a mission (no robots)")
    config_doc = mission.get("config") or {}
    merged = _merge(config_doc, overrides or {})
    config = config_from_mapping(merged, source=str(mission_file))
    events = []
    for number, line in enumerate(events_file.read_text(encoding="utf-8").splitlines(), 1):
        if not line.strip():
            continue
        try:
            event = json.loads(line)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"{events_file}:{number}: not JSON: {exc.msg}") from None
        if not isinstance(event, dict) or "event" not in event or "t_s" not in event:
            raise ConfigError(f"{events_file}:{number}: an event needs 'event' and 't_s'")
        events.append(event)
    robots = [str(r["name"]) for r in mission["robots"]]
    starts = {
        str(r["name"]): np.array([r["start"][0], r["start"][1], math.radians(r["start"][2])])
        for r in mission["robots"]
    }
    return Dataset(path, config, robots, starts, events, mission)


def _merge(base: dict[str, Any], top: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in top.items():
        both = isinstance(value, dict) and isinstance(out.get(key), dict)
        out[key] = _merge(out[key], value) if both else value
    return out


@dataclass
class Sweep:
    """One robot's 3D scan during one dwell, and the beacons found in it."""

    robot: str
    index: int
    dwell: int
    scan: Scan3D
    detections: list[BeaconDetection]


@dataclass
class RobotStream:
    scans: list[Scan]
    times_s: np.ndarray
    telegrams: int = 0
    undecodable: int = 0
    checksum_failures: int = 0
    bytes_skipped: int = 0
    truncated_bytes: int = 0


def decode_robot(capture: Path, measuring_mode: int) -> RobotStream:
    """Every measured-value telegram of a capture, decoded, with its measurement time."""
    reader = CaptureReader(capture)
    parser = StreamParser()
    scans: list[Scan] = []
    undecodable = 0
    stamp: float | None = None
    for stamp, chunk in reader.chunks():
        for event in parser.feed(chunk, stamp):
            if isinstance(event, Telegram) and event.code == 0xB0:
                try:
                    scans.append(decode_scan(event, measuring_mode))
                except ProtocolError:
                    undecodable += 1
    parser.close(stamp)
    if not scans:
        raise SensorError(f"{capture}: no measured values in the capture")
    scans = [s for s in scans if s.stamp_s is not None]
    return RobotStream(
        scans=scans,
        times_s=scan_times(scans),
        telegrams=parser.stats.telegrams,
        undecodable=undecodable,
        checksum_failures=parser.stats.checksum_failures,
        bytes_skipped=parser.stats.bytes_skipped,
        truncated_bytes=reader.truncated_bytes,
    )


def sweep_in(
    stream: RobotStream, start_s: float, end_s: float, config: Config
) -> tuple[Scan3D | None, str | None]:
    """The most complete sweep among the scans measured in [start_s, end_s], or why none."""
    rows = np.flatnonzero((stream.times_s >= start_s) & (stream.times_s <= end_s))
    if len(rows) < 50:
        return None, f"only {len(rows)} scans in the dwell"
    scans = [stream.scans[k] for k in rows]
    try:
        estimate = estimate_mirror(scans, stream.times_s[rows], mirror_geometry(config))
    except SensorError as exc:
        return None, str(exc)
    sweeps = assemble_sweeps(scans, stream.times_s[rows], estimate, min_scans=60)
    if not sweeps:
        return None, "no complete sweep"
    best = max(sweeps, key=lambda s: s.scans)
    expected = 0.5 * estimate.sweep_period_s / np.median(np.diff(stream.times_s[rows]))
    if best.scans < 0.75 * expected:
        return None, f"sweep incomplete ({best.scans} of ~{expected:.0f} scans)"
    return best, None


def _odometry(path: Path) -> tuple[np.ndarray, np.ndarray]:
    from estimation.trajio import read_tum

    stamps, poses = read_tum(path)
    return stamps, poses


def _pose_at(stamps: np.ndarray, poses: np.ndarray, t: float) -> np.ndarray:
    yaw = np.unwrap(poses[:, 2])
    return np.array(
        [
            np.interp(t, stamps, poses[:, 0]),
            np.interp(t, stamps, poses[:, 1]),
            np.interp(t, stamps, yaw),
        ]
    )


def _between(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return (c * dx + s * dy, -s * dx + c * dy, math.remainder(b[2] - a[2], 2 * math.pi))


def _choose(
    detections: list[BeaconDetection], predicted: tuple[float, float] | None
) -> BeaconDetection | None:
    """The detection that is the other robot's beacon: nearest the prediction, or the only one."""
    if not detections:
        return None
    if predicted is None:
        return detections[0] if len(detections) == 1 else max(detections, key=lambda d: d.quality)
    a, alpha = predicted
    return min(
        detections,
        key=lambda d: math.hypot(
            d.range_m - a, a * math.remainder(d.bearing_rad - alpha, 2 * math.pi)
        ),
    )


def _predict(
    builder: GraphBuilder, observer: int, observed: int, config: Config
) -> tuple[float, float] | None:
    guesses = builder.guesses
    if observer not in guesses or observed not in guesses:
        return None
    T_a = pose2_matrix(*guesses[observer]) @ pose2_matrix(config.robot.scanner_x_m, 0, 0)
    beacon = pose2_matrix(*guesses[observed]) @ np.array(
        [config.robot.scanner_x_m + config.beacon.offset_m, 0, 0, 1]
    )
    local = np.linalg.inv(T_a) @ beacon
    return float(math.hypot(local[0], local[1])), float(math.atan2(local[1], local[0]))


@dataclass
class BatchOutput:
    out_dir: Path
    poses: dict[str, dict[int, np.ndarray]]
    stamps: dict[str, dict[int, float]]
    sweeps: list[Sweep]
    factors: list[FactorSpec]
    inliers: np.ndarray
    grid: OccupancyGrid
    report: dict[str, Any] = field(default_factory=dict)


def build_events(
    dataset: Dataset,
    streams: dict[str, RobotStream],
    progress: Progress | None = None,
) -> tuple[list[Event], list[Sweep], dict[str, Any], GraphBuilder]:
    """The estimator's event stream of a dataset, the sweeps, and the counts of what failed.

    A builder consumes the events as they are made, so that each observation can be matched to
    the beacon predicted by the estimate so far.
    """
    config = dataset.config
    builder = GraphBuilder(graph_settings(config))
    params = beacon_parameters(config)
    odometry = {r: _odometry(dataset.path / "robots" / r / "odometry.tum") for r in dataset.robots}
    gauge = dataset.robots[0]
    events: list[Event] = []
    sweeps: list[Sweep] = []
    counts: dict[str, Any] = {"dwells": 0, "observations": 0, "missing_sweeps": [], "unseen": []}

    def emit(event: Event) -> None:
        builder.add(event)
        events.append(event)

    emit(Start(gauge, 0, tuple(float(v) for v in dataset.starts[gauge])))  # type: ignore[arg-type]
    for number, entry in enumerate(dataset.events):
        kind = entry["event"]
        if kind == "move":
            robot = entry["robot"]
            stamps, poses = odometry[robot]
            before = _pose_at(stamps, poses, float(entry["start_s"]))
            after = _pose_at(stamps, poses, float(entry["t_s"]))
            if pose_key(robot, int(entry["from_index"])) in builder.guesses:
                emit(Move(robot, int(entry["to_index"]), _between(before, after)))
            else:
                counts.setdefault("moves_before_first_fix", 0)
                counts["moves_before_first_fix"] += 1
                pending = counts.setdefault("pending_moves", {})
                pending.setdefault(robot, []).append(
                    (int(entry["to_index"]), _between(before, after))
                )
        elif kind == "dwell":
            counts["dwells"] += 1
            start, end = float(entry["t_s"]), float(entry["end_s"])
            in_dwell: dict[str, Sweep] = {}
            for robot in dataset.robots:
                scan, why = sweep_in(streams[robot], start + 0.2, end, config)
                index = int(entry["poses"][robot])
                if scan is None:
                    counts["missing_sweeps"].append(f"{robot}{index} (dwell {number}): {why}")
                    continue
                detections, _ = detect_beacons(scan.points_scanner, scan.reflector, **params)
                sweep = Sweep(robot, index, number, scan, detections)
                sweeps.append(sweep)
                in_dwell[robot] = sweep
            reference, mapper = entry.get("reference"), entry.get("mapper")
            if reference in in_dwell and mapper in in_dwell:
                ka = pose_key(reference, in_dwell[reference].index)
                kc = pose_key(mapper, in_dwell[mapper].index)
                seen_a = _choose(in_dwell[reference].detections, _predict(builder, ka, kc, config))
                seen_c = _choose(in_dwell[mapper].detections, _predict(builder, kc, ka, config))
                if seen_a is None or seen_c is None:
                    counts["unseen"].append(
                        f"{reference}{in_dwell[reference].index}–{mapper}{in_dwell[mapper].index}"
                    )
                elif ka in builder.guesses or kc in builder.guesses:
                    observer = (reference, in_dwell[reference].index)
                    observed = (mapper, in_dwell[mapper].index)
                    emit(
                        Observe(
                            observer, observed,
                            seen_a.range_m, seen_a.bearing_rad, seen_c.range_m, seen_c.bearing_rad,
                        )
                    )  # fmt: skip
                    counts["observations"] += 1
                    _flush_pending(counts, builder, emit)
        if progress is not None:
            progress(f"event {number + 1}/{len(dataset.events)}")
    return events, sweeps, counts, builder


def _flush_pending(
    counts: dict[str, Any], builder: GraphBuilder, emit: Callable[[Event], None]
) -> None:
    """Odometry of a robot that moved before its first fix joins once it is anchored."""
    pending: dict[str, list[tuple[int, tuple[float, float, float]]]] = counts.get(
        "pending_moves", {}
    )
    for robot, moves in list(pending.items()):
        while moves and pose_key(robot, moves[0][0] - 1) in builder.guesses:
            index, delta = moves.pop(0)
            if pose_key(robot, index) not in builder.guesses:
                emit(Move(robot, index, delta))
        if not moves:
            del pending[robot]


def _mapping_sweeps(dataset: Dataset, sweeps: list[Sweep]) -> list[Sweep]:
    """The sweeps of the mapping: not those taken after the world changed."""
    after = {n for n, e in enumerate(dataset.events)
             if e["event"] == "dwell" and e.get("phase") == "relocalize"}  # fmt: skip
    return [s for s in sweeps if s.dwell not in after]


def _connected(factors: list[FactorSpec], root: int) -> set[int]:
    parent: dict[int, int] = {}

    def find(k: int) -> int:
        parent.setdefault(k, k)
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for f in factors:
        for k in f.keys:
            find(k)
        for k in f.keys[1:]:
            parent[find(k)] = find(f.keys[0])
    return {k for k in parent if find(k) == find(root)}


def scanner_matrix(pose: np.ndarray, config: Config) -> np.ndarray:
    return pose2_matrix(*pose) @ pose2_matrix(
        config.robot.scanner_x_m, 0.0, 0.0, config.robot.scanner_height_m
    )


def _prepare(
    dataset_dir: Path | str, overrides: dict[str, Any] | None, progress: Progress | None
) -> tuple[
    Dataset,
    dict[str, RobotStream],
    list[Event],
    list[Sweep],
    dict[str, Any],
    GraphBuilder,
    dict[str, float],
]:
    timings: dict[str, float] = {}
    clock = time.perf_counter()
    dataset = load_dataset(dataset_dir, overrides)
    streams: dict[str, RobotStream] = {}
    for robot in dataset.robots:
        if progress is not None:
            progress(f"decoding robot {robot}")
        capture = dataset.path / "robots" / robot / "lms.cap"
        streams[robot] = decode_robot(capture, dataset.config.scanner.measuring_mode)
    timings["decode"] = time.perf_counter() - clock
    clock = time.perf_counter()
    events, sweeps, counts, builder = build_events(dataset, streams, progress)
    timings["sweeps_and_beacons"] = time.perf_counter() - clock
    return dataset, streams, events, sweeps, counts, builder, timings


def _as_used(records: list[SearchRecord], factors: bool) -> list[SearchRecord]:
    """The records as the run used them: none became a factor when the searches are off."""
    return records if factors else [dataclasses.replace(r, used=False) for r in records]


def _observation_rows(
    builder: GraphBuilder, factors: list[FactorSpec], inliers: np.ndarray
) -> list[dict[str, Any]]:
    """Every mutual observation the gate saw: the poses it joins, the relative pose it measured,
    whether the gate accepted it and whether the optimizer kept it (for ``evaluate``)."""
    rows: list[dict[str, Any]] = []
    for factor, inlier in zip(factors, inliers, strict=True):
        if factor.kind == "mutual":
            rows.append({"event": factor.event, "pair": [key_label(k) for k in factor.keys],
                         "measurement": [float(v) for v in factor.measurement],
                         "accepted": True, "inlier": bool(inlier)})  # fmt: skip
    for rejection in builder.rejections:
        if len(rejection.keys) == 2:
            measured = rejection.measurement
            rows.append({"event": rejection.event,
                         "pair": [key_label(k) for k in rejection.keys],
                         "measurement": None if measured is None else [float(v) for v in measured],
                         "accepted": False, "reason": rejection.reason})  # fmt: skip
    return sorted(rows, key=lambda row: row["event"])


def _finish(
    dataset: Dataset,
    streams: dict[str, RobotStream],
    sweeps: list[Sweep],
    counts: dict[str, Any],
    builder: GraphBuilder,
    factors: list[FactorSpec],
    estimate: dict[int, np.ndarray],
    inliers: np.ndarray,
    dropped: list[int],
    timings: dict[str, float],
    out: Path,
    extra: dict[str, Any],
) -> BatchOutput:
    """Re-fuse every sweep at its optimized pose, then write the result directory."""
    from estimation.results import write_results

    config = dataset.config
    clock = time.perf_counter()
    poses: dict[str, dict[int, np.ndarray]] = {r: {} for r in dataset.robots}
    for key, pose in estimate.items():
        robot, index = split_key(key)
        poses[robot][index] = pose
    used = [s for s in _mapping_sweeps(dataset, sweeps) if s.index in poses[s.robot]]
    transforms = (
        np.stack([scanner_matrix(poses[s.robot][s.index], config) for s in used])
        if used
        else np.zeros((0, 4, 4))
    )
    grid = fuse_scans(
        [MapScan(s.scan.points_scanner) for s in used],
        transforms,
        GridParams(**config.grid.model_dump()),
    )
    timings["fusion"] = time.perf_counter() - clock
    stamps = {r: dataset.stop_times(r) for r in dataset.robots}
    report = {
        "coopmap": __version__,
        "dataset": str(dataset.path),
        "robots": {
            r: {
                "telegrams": streams[r].telegrams,
                "undecodable": streams[r].undecodable,
                "checksum_failures": streams[r].checksum_failures,
                "bytes_skipped": streams[r].bytes_skipped,
                "truncated_bytes": streams[r].truncated_bytes,
                "poses": len(poses[r]),
            }
            for r in dataset.robots
        },
        "dwells": counts["dwells"],
        "sweeps": len(sweeps),
        "missing_sweeps": counts["missing_sweeps"],
        "observations": counts["observations"],
        "unseen_pairs": counts["unseen"],
        "gate_rejections": [r.reason for r in builder.rejections],
        "mutual_observations": _observation_rows(builder, factors, inliers),
        "factors": len(factors),
        "outlier_factors": [factors[i].describe() for i in np.flatnonzero(~inliers)],
        "dropped_poses": [f"{split_key(k)[0]}{split_key(k)[1]}" for k in dropped],
        "timings_s": timings,
        **extra,
    }
    output = BatchOutput(out, poses, stamps, sweeps, factors, inliers, grid, report)
    clock = time.perf_counter()
    timings["total"] = sum(timings.values())
    write_results(output, config)
    timings["write"] = time.perf_counter() - clock
    return output


@dataclasses.dataclass
class _Searched:
    """The search stages' outcome: their records, the ``Localize`` events they added (in order),
    and the batch optimum of the graph after the last stage (its factors, initial values, and
    the poses connected to the gauge)."""

    records: list[SearchRecord]
    events: list[Localize]
    factors: list[FactorSpec]
    initial: dict[int, np.ndarray]
    keep: set[int]
    result: BatchResult


def _search_stages(
    dataset: Dataset,
    sweeps: list[Sweep],
    builder: GraphBuilder,
    gauge: int,
    timings: dict[str, float],
    progress: Progress | None,
) -> _Searched:
    """Optimize the graph of the mission's events in batch, then run the search stages, each on
    the batch optimum of the graph so far (adding what it found to ``builder``).

    Both pipelines run this on the same events, so their searches see the same poses bit for
    bit: station maps are not continuous in the poses (a ray that moves across a cell face
    changes a cell), so a difference of 1e-7 m in the estimate could move a station link's
    answer by millimetres and the final poses by a centimetre."""
    config = dataset.config
    clock = time.perf_counter()
    keep = _connected(builder.factors, gauge)
    factors = [f for f in builder.factors if all(k in keep for k in f.keys)]
    initial = {k: v for k, v in builder.initial_values().items() if k in keep}
    if not initial:
        raise EstimationError(f"{dataset.path}: no pose is connected to the gauge")
    if progress is not None:
        progress("optimizing the pose graph")
    result = optimize_batch(factors, initial, robust=config.graph.robust)
    timings["optimize"] = timings.get("optimize", 0.0) + time.perf_counter() - clock
    records: list[SearchRecord] = []
    events: list[Localize] = []
    for name, stage in SEARCH_STAGES:
        if progress is not None:
            progress(f"global localization: {name}")
        found, stage_records = stage(
            dataset, _mapping_sweeps(dataset, sweeps), result.estimate, builder.factors
        )
        records += _as_used(stage_records, config.graph.search_factors)
        if not config.graph.search_factors or not found:
            continue
        for event in found:
            builder.add(event)
        events += found
        keep = _connected(builder.factors, gauge)
        factors = [f for f in builder.factors if all(k in keep for k in f.keys)]
        initial = {
            k: result.estimate.get(k, v) for k, v in builder.initial_values().items() if k in keep
        }
        result = optimize_batch(factors, initial, robust=config.graph.robust)
    return _Searched(records, events, factors, initial, keep, result)


def run_batch(
    dataset_dir: Path | str,
    out_dir: Path | str | None = None,
    *,
    overrides: dict[str, Any] | None = None,
    progress: Progress | None = None,
) -> BatchOutput:
    """Decode, detect, build the graph, optimize in batch, re-fuse the map, write the results."""
    dataset, streams, _, sweeps, counts, builder, timings = _prepare(
        dataset_dir, overrides, progress
    )
    config = dataset.config
    out = Path(out_dir) if out_dir is not None else dataset.path / "result"
    clock = time.perf_counter()
    gauge = pose_key(dataset.robots[0], 0)
    dropped = sorted(set(builder.initial_values()) - _connected(builder.factors, gauge))
    searched = _search_stages(dataset, sweeps, builder, gauge, timings, progress)
    records, added, factors, result = (
        searched.records, len(searched.events), searched.factors, searched.result
    )  # fmt: skip
    validation = None
    if added:
        # The validator (DESIGN §5): optimized stations against their search PDFs; a factor
        # that drags stations out of their regions is disabled and the graph solved again.
        searches = {
            k: [(pdf, ref) for pdf, ref in found if ref is None or ref in searched.keep]
            for k, found in builder.pdfs.items()
            if k in searched.keep
        }
        result, rounds, _ = validate_and_repair(
            factors, {k: result.estimate[k] for k in searched.initial}, searches,
            config.graph.validator_mass, config.graph.robust,
        )  # fmt: skip
        validation = {
            "checks": len(rounds[-1].checks),
            "outside": [c.describe() for c in rounds[-1].failed],
            "flagged": [factors[i].describe() for r in rounds for i in r.flagged],
        }
    relocalized = relocalize(dataset, sweeps, result.estimate)
    timings["search"] = time.perf_counter() - clock - timings["optimize"]
    extra = {
        "graph_error": result.error,
        "global_localization": {
            "searches": records_json(records),
            "factors": added,
            "validation": validation,
            "relocalization": records_json(relocalized),
        },
    }
    return _finish(
        dataset, streams, sweeps, counts, builder, factors, result.estimate, result.inliers,
        dropped, timings, out, extra,
    )  # fmt: skip


def run_isam(
    dataset_dir: Path | str,
    out_dir: Path | str | None = None,
    *,
    overrides: dict[str, Any] | None = None,
    resume: bool = False,
    checkpoint_every: int = 5,
    stop_after: int | None = None,
    progress: Progress | None = None,
) -> BatchOutput | None:
    """The same events fed one by one to iSAM2, checkpointing as it goes.

    ``resume`` continues from the checkpoint of an earlier run that was cut short.
    ``stop_after`` ends the run after that many events without writing results (as a kill would).
    """
    from estimation.smoother import IncrementalSmoother

    dataset, streams, events, sweeps, counts, prepared, timings = _prepare(
        dataset_dir, overrides, progress
    )
    config = dataset.config
    out = Path(out_dir) if out_dir is not None else dataset.path / "result_isam"
    checkpoint = out.with_name(f".{out.name}.checkpoint.npz")
    robust = config.graph.robust
    kernel: Any = robust if robust in ("huber", "cauchy") else "none"
    options = {
        "settings": graph_settings(config),
        "relinearize_threshold": config.graph.isam2_relinearize_threshold,
        "relinearize_skip": config.graph.isam2_relinearize_skip,
        "kernel": kernel,
    }
    clock = time.perf_counter()
    if resume:
        if not checkpoint.is_file():
            raise EstimationError(f"{checkpoint}: no checkpoint to resume from")
        smoother = IncrementalSmoother.restore(checkpoint, iter(events), **options)
        remaining = events[smoother.events :]
    else:
        smoother = IncrementalSmoother(**options)
        remaining = events
    for event in remaining:
        smoother.add(event)
        if smoother.events % checkpoint_every == 0:
            smoother.save_checkpoint(checkpoint)
        if stop_after is not None and smoother.events >= stop_after:
            smoother.save_checkpoint(checkpoint)
            return None
    timings["optimize"] = time.perf_counter() - clock
    clock = time.perf_counter()
    # The searches run as in batch, on the batch optimum of the same events (see
    # _search_stages): the station maps then see the same poses bit for bit, and what they find
    # is fed to iSAM2 as events. Settled (every variable relinearized until nothing moves), the
    # estimate no longer depends on the order in which iSAM2 relinearized, so a resumed run ends
    # where an uninterrupted one does.
    gauge = pose_key(dataset.robots[0], 0)
    searched = _search_stages(dataset, sweeps, prepared, gauge, {}, progress)
    records, added = searched.records, len(searched.events)
    for event in searched.events:
        smoother.add(event)
    smoother.settle()
    estimate = smoother.estimate()
    relocalized = relocalize(dataset, sweeps, estimate)
    timings["search"] = time.perf_counter() - clock
    builder = smoother.builder
    factors = list(builder.factors)
    update_ms = np.array(smoother.update_seconds) * 1e3
    output = _finish(
        dataset, streams, sweeps, counts, builder, factors, estimate,
        np.ones(len(factors), dtype=bool), [], timings, out,
        {"global_localization": {"searches": records_json(records), "factors": added,
                                 "relocalization": records_json(relocalized)},
         "isam2": {"events": smoother.events, "resumed": resume,
                   "update_median_ms": float(np.median(update_ms)) if len(update_ms) else 0.0,
                   "update_max_ms": float(update_ms.max()) if len(update_ms) else 0.0}},
    )  # fmt: skip
    checkpoint.unlink(missing_ok=True)
    return output
