"""``coopmap batch`` and ``coopmap isam``: a recorded dataset → optimized poses and the global
3D map (docs/design.md §1).

Both read the dataset into the estimator's event stream (:mod:`estimation.app.dataset`), solve
the pose graph — in batch (Levenberg–Marquardt, graduated non-convexity on mutual and global
factors) or event by event in iSAM2 — run the station searches on the batch optimum of the same
events, re-fuse every sweep into the global occupancy grid at its optimized pose and write the
result folder (docs/results.md). What flows between the steps are named frozen values:
:class:`Prepared` (what was read), :class:`Solution` (what was optimized) and :class:`Timings`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from estimation import __version__
from estimation.app.config import Config
from estimation.app.dataset import (
    Dataset,
    RobotStream,
    Sweep,
    decode_dwells,
    load_dataset,
    mapping_sweeps,
    read_pose_stamps,
    relocalization_dwells,
    stations,
)
from estimation.app.events import Counts, build_events
from estimation.app.memory import give_back_memory
from estimation.app.results import BatchOutput, figure_worker, write_results
from estimation.app.rig import T_robot_scanner, graph_settings, scan_limits, station_params
from estimation.app.workers import shared_jobs, worker_beside
from estimation.errors import EstimationError
from estimation.posegraph.events import Event, Localize
from estimation.posegraph.graph import FactorSpec, GraphBuilder
from estimation.posegraph.keys import key_label, pose_key, split_key
from estimation.posegraph.marginals import marginal_covariances
from estimation.posegraph.smoother import BatchResult, IncrementalSmoother, optimize_batch
from estimation.posegraph.structure import connected
from estimation.posegraph.validate import validate_and_repair
from estimation.search.records import SearchRecord, records_json
from estimation.search.relocalization import relocalize
from estimation.search.stations import SEARCH_STAGES, StationMaps, StationParams
from mapping.fusion import Scan as MapScan
from mapping.fusion import fuse_scans
from mapping.grid import GridParams
from sensors.atomic import check_replaceable
from sensors.errors import SensorError
from sensors.geometry.frames import pose2_matrix
from sensors.lms200.capture import CaptureReader

__all__ = [
    "Prepared",
    "Solution",
    "Timings",
    "finish_isam",
    "isam_options",
    "prepare",
    "run_batch",
    "run_isam",
    "unobserved_stations",
]

Progress = Callable[[str], None]


@dataclass(frozen=True)
class Timings:
    """Wall time of each step (s), as ``report.json`` records it."""

    decode: float = 0.0
    sweeps_and_beacons: float = 0.0
    optimize: float = 0.0
    search: float = 0.0
    fusion: float = 0.0

    def as_json(self) -> dict[str, float]:
        steps = dataclasses.asdict(self)
        return {**steps, "total": sum(steps.values())}


@dataclass(frozen=True)
class Prepared:
    """A dataset read: its decoded LMS streams and its event stream, with the graph builder
    that consumed the events."""

    dataset: Dataset
    streams: dict[str, RobotStream]
    events: list[Event]
    sweeps: list[Sweep]
    counts: Counts
    builder: GraphBuilder
    timings: Timings  # decode and sweeps_and_beacons


@dataclass(frozen=True)
class Solution:
    """What an optimizer made of the graph: the factors it solved, their inlier flags, the
    estimate, and the poses left out because nothing tied them to the gauge."""

    builder: GraphBuilder
    factors: list[FactorSpec]
    estimate: dict[int, np.ndarray]
    inliers: np.ndarray
    dropped: list[int]


def prepare(
    dataset_dir: Path | str, overrides: dict[str, Any] | None, progress: Progress | None
) -> Prepared:
    """Read a dataset: decode every robot's capture, then build the event stream."""
    clock = time.perf_counter()
    dataset = load_dataset(dataset_dir, overrides)
    scanner = dataset.config.scanner
    limits = scan_limits(dataset.config)
    for robot in dataset.robots:  # a malformed odometry fails now, not after the decoding
        dataset.odometry(robot)
    captures = [dataset.path / "robots" / robot / "lms.cap" for robot in dataset.robots]
    for capture in captures:
        if not CaptureReader(capture).is_capture:
            # Its scans have no receive stamps, so no dwell could ever select one.
            raise SensorError(f"{capture}: a plain binary dump (no capture header): a mission "
                              "needs receive stamps (docs/dataset.md)")  # fmt: skip
    if progress is not None:
        progress(f"decoding {len(captures)} robots' scans")
    # One robot's scans at a time are in memory on each side (about 3.4 kB each, 38,000 per
    # robot in office_loop); the sweeps hold what the estimator needs.
    jobs = [functools.partial(decode_dwells, capture, scanner.measuring_mode, limits,
                              dataset.events, dataset.config) for capture in captures]  # fmt: skip
    with decoding_worker(captures) as worker:
        made = shared_jobs([], jobs, worker)
    streams = {robot: stream for robot, (stream, _, _) in zip(dataset.robots, made, strict=True)}
    # The robots are decoded side by side: the wall time is split between the steps as the
    # robots' own times are.
    decoding = time.perf_counter() - clock
    decoded, swept = sum(m[1] for m in made), sum(m[2] for m in made)
    decode = decoding * decoded / max(decoded + swept, 1e-9)
    clock = time.perf_counter()
    stream = build_events(dataset, streams, progress)
    if not stream.sweeps:
        why = "; ".join(stream.counts.missing_sweeps[:3]) or "the dataset has no dwells"
        raise EstimationError(f"{dataset.path}: no sweep in any dwell ({why})")
    swept_s = decoding - decode + time.perf_counter() - clock
    timings = Timings(decode=decode, sweeps_and_beacons=swept_s)
    # The events hold the sweeps' points; the streams keep their counts.
    streams = {r: dataclasses.replace(s, dwell_sweeps={}, dwell_beacons={})
               for r, s in streams.items()}  # fmt: skip
    give_back_memory()  # the decoded scans, the sweeps' other fields
    return Prepared(
        dataset, streams, stream.events, stream.sweeps, stream.counts, stream.builder, timings
    )


#: Captures holding this much in all (bytes) are decoded by this process and a worker side by
#: side: about five seconds of decoding on one core, of which the worker's start (importing the
#: decoder, about a second) is a small part.
DECODE_WORKER_BYTES = 32 * 2**20


def decoding_worker(
    captures: list[Path],
) -> contextlib.AbstractContextManager[ProcessPoolExecutor | None]:
    """A worker process that decodes robots beside this one when the captures are large enough
    (else None), shut down on exit."""
    size = sum(c.stat().st_size for c in captures if c.is_file())
    return worker_beside(["estimation.app.dataset"],
                         len(captures) > 1 and size >= DECODE_WORKER_BYTES)  # fmt: skip


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
    prepared: Prepared,
    solution: Solution,
    timings: Timings,
    out: Path,
    extra: dict[str, Any],
    searches: list[SearchRecord],
    figures: bool = True,
) -> BatchOutput:
    """Re-fuse every sweep at its optimized pose, then write the result directory (``searches``:
    the mission's search records, for the figures of their PDFs; ``figures`` False: none drawn).
    The figures' worker process starts first: its imports run while this one fuses the map."""
    with figure_worker(figures) as worker:
        dataset = prepared.dataset
        config = dataset.config
        clock = time.perf_counter()
        poses: dict[str, dict[int, np.ndarray]] = {r: {} for r in dataset.robots}
        for key, pose in solution.estimate.items():
            robot, index = split_key(key)
            poses[robot][index] = pose
        used = [s for s in mapping_sweeps(dataset, prepared.sweeps) if s.index in poses[s.robot]]
        mount = T_robot_scanner(config)
        transforms = (
            np.stack([pose2_matrix(*poses[s.robot][s.index]) @ mount for s in used])
            if used
            else np.zeros((0, 4, 4))
        )
        grid = fuse_scans(
            [MapScan(s.points_scanner) for s in used],
            transforms,
            GridParams(**config.grid.model_dump()),
        )
        timings = dataclasses.replace(timings, fusion=time.perf_counter() - clock)
        stamps = read_pose_stamps(dataset)
        covariances: dict[str, dict[int, np.ndarray]] = {r: {} for r in dataset.robots}
        kept = [f for f, inlier in zip(solution.factors, solution.inliers, strict=True) if inlier]
        try:
            for key, covariance in marginal_covariances(kept, solution.estimate).items():
                robot, index = split_key(key)
                covariances[robot][index] = covariance
        except EstimationError as exc:
            extra = {**extra, "covariances": f"not written: {exc}"}
        builder, factors, inliers, counts = (
            solution.builder, solution.factors, solution.inliers, prepared.counts
        )  # fmt: skip
        report = {
            "coopmap": __version__,
            "dataset": str(dataset.path),
            "robots": {
                r: {
                    "telegrams": prepared.streams[r].telegrams,
                    "undecodable": prepared.streams[r].undecodable,
                    "checksum_failures": prepared.streams[r].checksum_failures,
                    "bytes_skipped": prepared.streams[r].bytes_skipped,
                    "truncated_bytes": prepared.streams[r].truncated_bytes,
                    "corrupt_bytes": prepared.streams[r].corrupt_bytes,
                    "implausible_scans": prepared.streams[r].implausible_scans,
                    "implausible": prepared.streams[r].implausible,
                    "poses": len(poses[r]),
                }
                for r in dataset.robots
            },
            "dwells": counts.dwells,
            "sweeps": len(prepared.sweeps),
            "missing_sweeps": list(counts.missing_sweeps),
            "observations": counts.observations,
            "unseen_pairs": list(counts.unseen),
            "gate_rejections": [r.reason for r in builder.rejections],
            "mutual_observations": _observation_rows(builder, factors, inliers),
            "factors": len(factors),
            "outlier_factors": [factors[i].describe() for i in np.flatnonzero(~inliers)],
            "dropped_poses": [key_label(k) for k in solution.dropped],
            "stations_without_mutual": unobserved_stations(prepared, factors),
            "partial_mission": dataset.partial,
            "timings_s": timings.as_json(),
            **extra,
        }
        output = BatchOutput(
            out,
            poses,
            stamps,
            prepared.sweeps,
            factors,
            inliers,
            grid,
            report,
            covariances,
            searches,
        )
        write_results(output, config, figures=figures, worker=worker)
        return output


def unobserved_stations(prepared: Prepared, factors: list[FactorSpec]) -> list[dict[str, Any]]:
    """The reference stations that no mutual observation ties (their own pose in none): they
    rest on odometry and on what their station searches found (the link factors they got)."""
    mutual = {k for f in factors if f.kind == "mutual" for k in f.keys}
    searched: dict[int, int] = {}
    for f in factors:
        if f.kind not in ("mutual", "odometry", "prior"):
            for k in f.keys:
                searched[k] = searched.get(k, 0) + 1
    found = stations(prepared.dataset, mapping_sweeps(prepared.dataset, prepared.sweeps))
    return [{"station": s.label, "search_factors": searched.get(s.key, 0)}
            for s in found if s.key not in mutual]  # fmt: skip


@dataclass(frozen=True)
class _Searched:
    """The search stages' outcome: their records, the ``Localize`` events they added (in order),
    and the batch optimum of the graph after the last stage (its factors, initial values, and
    the poses connected to the gauge), and the time the optimizer took."""

    records: list[SearchRecord]
    events: list[Localize]
    work: list[dict[str, Any]]  # per station in mission order: fusion and search work
    factors: list[FactorSpec]
    initial: dict[int, np.ndarray]
    keep: set[int]
    result: BatchResult
    optimize_s: float


def _search_stages(
    prepared: Prepared,
    builder: GraphBuilder,
    params: StationParams,
    progress: Progress | None,
) -> _Searched:
    """Optimize the graph of the mission's events in batch, then run the search stages, each on
    the batch optimum of the graph so far (adding what it found to ``builder``).

    Both pipelines run this on the same events, so their searches see the same poses bit for
    bit: station maps are not continuous in the poses (a ray that moves across a cell face
    changes a cell), so a difference of 1e-7 m in the estimate could move a station link's
    answer by millimetres and the final poses by a centimetre."""
    dataset = prepared.dataset
    config = dataset.config
    gauge = pose_key(dataset.robots[0], 0)
    clock = time.perf_counter()
    keep = connected(builder.factors, gauge)
    factors = [f for f in builder.factors if all(k in keep for k in f.keys)]
    initial = {k: v for k, v in builder.initial_values().items() if k in keep}
    if not initial:
        raise EstimationError(f"{dataset.path}: no pose is connected to the gauge")
    if progress is not None:
        progress("optimizing the pose graph")
    result = optimize_batch(factors, initial, robust=config.graph.robust)
    optimize_s = time.perf_counter() - clock
    mission_stations = stations(dataset, mapping_sweeps(dataset, prepared.sweeps))
    records: list[SearchRecord] = []
    events: list[Localize] = []
    maps = StationMaps(params)  # built once, kept across the stages while their views stay put
    for name, stage in SEARCH_STAGES:
        if progress is not None:
            progress(f"global localization: {name}")
        found, stage_records = stage(
            mission_stations, result.estimate, builder.factors, params, maps=maps
        )
        records += _as_used(stage_records, config.graph.search_factors)
        if not config.graph.search_factors or not found:
            continue
        for event in found:
            builder.add(event)
        events += found
        keep = connected(builder.factors, gauge)
        factors = [f for f in builder.factors if all(k in keep for k in f.keys)]
        initial = {
            k: result.estimate.get(k, v) for k, v in builder.initial_values().items() if k in keep
        }
        result = optimize_batch(factors, initial, robust=config.graph.robust)
    work = [
        {"station": s.label, "rays": w.rays, "older_rays": w.older_rays,
         "fusions": w.own_builds, "seconds": round(w.seconds, 6),
         "own_seconds": round(w.own_seconds, 6), "older_seconds": round(w.older_seconds, 6),
         "search_seconds": round(w.search_seconds, 6)}
        for s in mission_stations
        if (w := maps.work.get(s.key)) is not None
    ]  # fmt: skip
    return _Searched(records, events, work, factors, initial, keep, result, optimize_s)


def _relocalized(
    prepared: Prepared, estimate: dict[int, np.ndarray], params: StationParams
) -> list[SearchRecord]:
    """After the changes: each robot's sweep against the mission's map (reported, not used)."""
    dataset, sweeps = prepared.dataset, prepared.sweeps
    mapped = [s.view() for s in mapping_sweeps(dataset, sweeps)]
    return relocalize(relocalization_dwells(dataset, sweeps), mapped, estimate, params)


def run_batch(
    dataset_dir: Path | str,
    out_dir: Path | str | None = None,
    *,
    overrides: dict[str, Any] | None = None,
    progress: Progress | None = None,
    figures: bool = True,
) -> BatchOutput:
    """Decode, detect, build the graph, optimize in batch, re-fuse the map, write the results
    (with their figures unless ``figures`` is False)."""
    out = Path(out_dir) if out_dir is not None else Path(dataset_dir) / "result"
    check_replaceable(out, "result")  # before the work, not after it
    prepared = prepare(dataset_dir, overrides, progress)
    dataset, builder = prepared.dataset, prepared.builder
    config = dataset.config
    params = station_params(config)
    clock = time.perf_counter()
    gauge = pose_key(dataset.robots[0], 0)
    dropped = sorted(set(builder.initial_values()) - connected(builder.factors, gauge))
    searched = _search_stages(prepared, builder, params, progress)
    give_back_memory()  # the search threads' working sets, freed with the stages' maps
    factors, result = searched.factors, searched.result
    validation = None
    if searched.events:
        # The validator (docs/design.md §5): optimized stations against their search PDFs; a
        # factor that drags stations out of their regions is disabled and the graph solved again.
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
    relocalized = _relocalized(prepared, result.estimate, params)
    timings = dataclasses.replace(
        prepared.timings,
        optimize=searched.optimize_s,
        search=time.perf_counter() - clock - searched.optimize_s,
    )
    extra = {
        "graph_error": result.error,
        "global_localization": {
            "searches": records_json(searched.records),
            "factors": len(searched.events),
            "station_work": searched.work,
            "validation": validation,
            "relocalization": records_json(relocalized),
        },
    }
    solution = Solution(builder, factors, result.estimate, result.inliers, dropped)
    return _finish(prepared, solution, timings, out, extra, searched.records + relocalized, figures)


def run_isam(
    dataset_dir: Path | str,
    out_dir: Path | str | None = None,
    *,
    overrides: dict[str, Any] | None = None,
    resume: bool = False,
    checkpoint_every: int = 5,
    stop_after: int | None = None,
    progress: Progress | None = None,
    figures: bool = True,
) -> BatchOutput | None:
    """The same events fed one by one to iSAM2, checkpointing as it goes.

    ``resume`` continues from the checkpoint of an earlier run that was cut short.
    ``stop_after`` ends the run after that many events without writing results (as a kill would).
    """
    out = Path(out_dir) if out_dir is not None else Path(dataset_dir) / "result_isam"
    check_replaceable(out, "result")  # before the work, not after it
    prepared = prepare(dataset_dir, overrides, progress)
    dataset, events = prepared.dataset, prepared.events
    config = dataset.config
    checkpoint = out.with_name(f".{out.name}.checkpoint.npz")
    options = isam_options(config)
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
    optimize_s = time.perf_counter() - clock
    output = finish_isam(prepared, smoother, out, optimize_s=optimize_s, progress=progress,
                         extra={"resumed": resume}, figures=figures)  # fmt: skip
    checkpoint.unlink(missing_ok=True)
    return output


def isam_options(config: Config) -> dict[str, Any]:
    """The :class:`IncrementalSmoother` settings of a configuration."""
    robust = config.graph.robust
    kernel: Any = robust if robust in ("huber", "cauchy") else "none"
    return {
        "settings": graph_settings(config),
        "relinearize_threshold": config.graph.isam2_relinearize_threshold,
        "relinearize_skip": config.graph.isam2_relinearize_skip,
        "kernel": kernel,
    }


def finish_isam(
    prepared: Prepared,
    smoother: IncrementalSmoother,
    out: Path,
    *,
    optimize_s: float,
    progress: Progress | None = None,
    extra: dict[str, Any] | None = None,
    report: dict[str, Any] | None = None,
    figures: bool = True,
) -> BatchOutput:
    """After iSAM2 consumed the mission's events: the searches, settling, the map, the result.

    The searches run as in batch, on the batch optimum of the same events (see
    ``_search_stages``): the station maps then see the same poses bit for bit, and what they
    find is fed to iSAM2 as events. Settled (every variable relinearized until nothing moves),
    the estimate no longer depends on the order in which iSAM2 relinearized, so a resumed run
    ends where an uninterrupted one does. ``extra`` joins the report's ``isam2`` section,
    ``report`` its top level."""
    config = prepared.dataset.config
    clock = time.perf_counter()
    params = station_params(config)
    searched = _search_stages(prepared, prepared.builder, params, progress)
    give_back_memory()  # the search threads' working sets, freed with the stages' maps
    for event in searched.events:
        smoother.add(event)
    # iSAM2 cannot tell an outlier (docs/design.md §5): the factors the batch optimum after the
    # last stage dropped, mutual observations and searches, are left out of the settled estimate.
    dropped = {
        (f.event, f.kind, f.keys)
        for f, ok in zip(searched.factors, searched.result.inliers, strict=True)
        if not ok
    }
    inliers = np.array([(f.event, f.kind, f.keys) not in dropped for f in smoother.builder.factors])
    smoother.settle(leave_out=set(np.flatnonzero(~inliers).tolist()))
    estimate = smoother.estimate()
    relocalized = _relocalized(prepared, estimate, params)
    timings = dataclasses.replace(
        prepared.timings, optimize=optimize_s, search=time.perf_counter() - clock
    )
    builder = smoother.builder
    factors = list(builder.factors)
    update_ms = np.array(smoother.update_seconds) * 1e3
    solution = Solution(builder, factors, estimate, inliers, [])
    return _finish(
        prepared, solution, timings, out,
        {"global_localization": {"searches": records_json(searched.records),
                                 "factors": len(searched.events),
                                 "relocalization": records_json(relocalized)},
         "isam2": {"events": smoother.events, **(extra or {}),
                   "qr_since": smoother.refactorized,
                   "update_median_ms": float(np.median(update_ms)) if len(update_ms) else 0.0,
                   "update_max_ms": float(update_ms.max()) if len(update_ms) else 0.0},
         **(report or {})},
        searched.records + relocalized, figures,
    )  # fmt: skip
