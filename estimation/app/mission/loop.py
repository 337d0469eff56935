"""The mission loop: estimate during the mission, plan on the map as estimated (docs/design.md
§13, the paper's Fig. 2).

After every dwell the robots' recordings reach the loop through the :class:`Fleet` interface:
the raw LMS bytes are decoded as they arrive (``LmsDecoder``), odometry is taken as it is logged,
and the mission's event entries become estimator events through the same ``EventMaker`` that
``batch`` runs over a recorded dataset. iSAM2 takes each event; the sweeps are fused into the
global grid at their estimated poses (re-fused when the estimate of a fused pose moved); the
next goals are chosen on that grid (:mod:`estimation.app.mission.explore`). When a station's
local map is complete, its global localization runs in a worker process while the next local map
is made, and enters the graph at the first dwell after (in time for the next plans).

Whatever the loop receives is also written, as it comes, into a dataset of the usual shape; at
the end the result is written from that dataset by the same finish as ``coopmap isam`` (the
searches on the batch optimum of all events, iSAM2 settled), so ``batch`` or ``isam`` on the
recorded dataset reproduce the loop's final estimate. The report adds the loop's own figures:
the work per dwell, each concurrent localization against the local map it ran beside, the
retried observations and refused goals, and where the exploration stopped.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from estimation import __version__
from estimation.app.config import Config
from estimation.app.dataset import (
    LmsDecoder,
    next_map_seconds,
    stations_of,
    sweeps_before_changes,
)
from estimation.app.events import EventMaker
from estimation.app.mission.closing import closing_target
from estimation.app.mission.estimated_map import EstimatedMap
from estimation.app.mission.explore import Explorer, StallWatch
from estimation.app.mission.fleet import Fleet, Goal
from estimation.app.mission.localizer import ConcurrentLocalizer
from estimation.app.mission.turns import RETRIES, fly_turn
from estimation.app.mission.view import MapView
from estimation.app.mission.warm import warm_up
from estimation.app.mission.work import WorkClock
from estimation.app.pipeline import finish_isam, isam_options, prepare
from estimation.app.results import BatchOutput
from estimation.app.rig import scan_limits, station_params
from estimation.app.sim.planning import as_spec
from estimation.posegraph.keys import pose_key
from estimation.posegraph.smoother import IncrementalSmoother
from estimation.search.records import records_json
from mapping.errors import MapError
from mapping.traversability import Room
from sensors.atomic import write_text_atomic
from sensors.geometry import se2
from sensors.lms200.capture import CaptureWriter
from sensors.sim.mission import MissionSpec, StepSpec, mission_to_yaml
from sensors.trajio import as_logged, write_tum

__all__ = ["PARTIAL", "LoopResult", "MissionLoop"]

#: A dataset whose mission failed holds this file: why, and how far the mission had gone.
PARTIAL = "partial.json"

Progress = Callable[[str], None]
#: Frontiers given up in a row because no pair of robots found a scan pose toward them (a goal
#: refused on a leg the estimated map shows free, a doorway too tight) before exploring ends.
_UNREACHED = 3


@dataclass
class LoopResult:
    """A finished mission: its result folder's contents and the loop's own figures."""

    output: BatchOutput
    steps: list[StepSpec]
    stop_reason: str
    loop: dict[str, Any]


@dataclass
class _Station:
    robot: str
    index: int
    started_s: float


#: A station as flown: the reference's turn (None: it stayed), the scan poses, the station.
_Flown = tuple[list[float] | None, list[list[float]], _Station]


@dataclass
class MissionLoop:
    """One mission, run on the estimated state (see the module's docstring)."""

    fleet: Fleet
    mission: MissionSpec
    config: Config
    work: Path
    concurrent: bool = True
    progress: Progress | None = None
    #: Called with the loop after every dwell, once it took in what the robots recorded (a
    #: live view publishes the estimate); its time does not count as the loop's work.
    observe: Callable[[MissionLoop], None] | None = None
    entries: list[dict[str, Any]] = field(default_factory=list)
    steps: list[StepSpec] = field(default_factory=list)

    def __post_init__(self) -> None:
        config, fleet = self.config, self.fleet
        self.robots = list(fleet.robots)
        limits = scan_limits(config)
        self.decoders = {
            r: LmsDecoder(config.scanner.measuring_mode, limits, fleet.capture_header(r))
            for r in self.robots
        }
        self.writers: dict[str, CaptureWriter] = {}
        for r in self.robots:
            capture = self.work / "robots" / r / "lms.cap"
            capture.parent.mkdir(parents=True, exist_ok=True)
            self.writers[r] = CaptureWriter(capture, fleet.capture_header(r))
        self.odometry: dict[str, tuple[np.ndarray, np.ndarray]] = {
            r: (np.zeros(0), np.zeros((0, 3))) for r in self.robots
        }
        self.maker = EventMaker(config, self.robots, fleet.starts, self.odometry)
        self.smoother = IncrementalSmoother(**isam_options(config))
        for event in self.maker.events:  # the gauge
            self.smoother.add(event)
        self.map = EstimatedMap(config)
        self.localizer = ConcurrentLocalizer(station_params(config), self.concurrent)
        self.estimate: dict[int, np.ndarray] = {}
        self.index = dict.fromkeys(self.robots, 0)
        self.now_s = 0.0
        self._fed = 0
        self.clock = WorkClock()
        self.warm_up_s = 0.0  # compiling the kernels before the first dwell (``run``)
        self._dwells = 0
        self.localizations: list[dict[str, Any]] = []
        self.retries: list[str] = []
        self.refused: list[str] = []
        #: Where refused goals found their way blocked (map frame): obstacles for the planner.
        self.blocked: list[tuple[float, float]] = []
        self.unobserved: list[str] = []
        self.pivots = 0  # pivot poses driven to, to tie the reference's turns
        self.untied: dict[str, str] = {}  # stations whose turn no mutual observation ties: why
        self.closing: list[str] = []  # per closing station, the first station of the tail
        self.given_up: list[list[float]] = []
        self.abandoned = 0  # stalls after which an untried frontier was taken up
        self.retried_frontiers: list[list[float]] = []
        self.changed: list[str] = []
        self.trace: list[dict[str, Any]] = []  # per station of an exploration
        self._cached: tuple[tuple[Any, ...], MapView | None] | None = None

    # -- what the robots recorded -------------------------------------------------------------

    def _sync(self) -> None:
        began = time.perf_counter()
        got = self.fleet.receive()
        self.clock.exclude(time.perf_counter() - began, received=True)
        clock = self.clock.mark()
        for robot in self.robots:
            decoder, writer = self.decoders[robot], self.writers[robot]
            chunks = got.lms.get(robot, [])
            for stamp, data in chunks:
                writer.write(stamp, data)
            decoder.feed_chunks(chunks)
            times, poses = got.odometry.get(robot, (np.zeros(0), np.zeros((0, 3))))
            if len(times):
                times, poses = as_logged(times, poses, decimals=6)
                old_t, old_p = self.odometry[robot]
                self.odometry[robot] = (np.concatenate([old_t, times]), np.vstack([old_p, poses]))
        self.entries += got.events
        for entry in got.events:
            if entry["event"] == "move":
                self.index[entry["robot"]] = int(entry["to_index"])
        streams = {r: d.stream() for r, d in self.decoders.items()}
        new = []
        for number in range(self._fed, len(self.entries)):
            new += self.maker.feed(number, self.entries[number], streams)
        self._fed = len(self.entries)
        clock = self.clock.part("events", clock)
        for event in new:
            self.smoother.add(event)
        self.now_s = got.now_s
        if self.localizer.busy:
            self._collect(wait=True)
        self.estimate = self.smoother.estimate()
        clock = self.clock.part("isam2", clock)
        self.map.update(sweeps_before_changes(self.entries, self.maker.sweeps), self.estimate)
        self.clock.part("fusion", clock)

    def _mutual_factors(self) -> int:
        return sum(1 for f in self.smoother.builder.factors if f.kind == "mutual")

    def dwell(self, **fields: Any) -> bool:
        """Every robot dwells for a sweep; the loop takes in what they recorded. True if the
        dwell's reference and mapper gave an accepted mutual observation."""
        self.clock.done()
        self.fleet.dwell(**fields)
        self.clock.start(
            f"{self._dwells} (station {len(self.trace)}, {fields.get('phase', 'map')})"
        )
        before = self._mutual_factors()
        self._sync()
        self._dwells += 1
        if self.observe is not None:
            began = time.perf_counter()
            self.observe(self)
            self.clock.exclude(time.perf_counter() - began)
        return self._mutual_factors() > before

    @property
    def dwells(self) -> int:
        """How many dwells the loop took in."""
        return self._dwells

    def pose(self, robot: str) -> np.ndarray:
        """Where the loop believes ``robot`` stands now: its estimate, or, before its first
        fix, its declared start moved by its odometry."""
        key = pose_key(robot, self.index[robot])
        if key in self.estimate:
            return self.estimate[key]
        times, poses = self.odometry[robot]
        if not len(times):
            return self.fleet.starts[robot]
        return se2.compose(self.fleet.starts[robot], se2.between(poses[0], poses[-1]))

    # -- concurrent global localization --------------------------------------------------------

    def _station_done(self, station: _Station) -> None:
        """A station's local map is complete: localize it while the mission goes on."""
        self._collect(wait=True)
        key = pose_key(station.robot, station.index)
        if key not in self.estimate:
            return
        sweeps = sweeps_before_changes(self.entries, self.maker.sweeps)
        stations = [s for s in stations_of(self.entries, sweeps) if s.key in self.estimate]
        self.localizer.submit(stations, dict(self.estimate), list(self.smoother.builder.factors),
                              key, self.now_s)  # fmt: skip

    def _collect(self, wait: bool) -> None:
        """Take the finished station's searches into the graph. The loop does so at the first
        dwell after they were submitted (waiting there if they are late), not whenever the
        worker happens to finish, so that a simulated mission flies the same way every time;
        later (at the next station) the plans would rest on an uncorrected turn for a whole
        local map."""
        was_ready = self.localizer.ready
        pending = self.localizer.busy and not was_ready
        began = time.perf_counter()
        done = self.localizer.collect(self.now_s, wait=wait)
        if pending:
            # Waiting on the worker is not the loop's work: a simulated dwell takes no time,
            # a real one the 31 s of a sweep, in which the worker runs (its own time and
            # budget are reported per station).
            self.clock.exclude(time.perf_counter() - began, waited=True)
        if done is None:
            return
        _, submitted_s, collected_s = self.localizer.done[-1]
        for event in done.events:
            self.smoother.add(event)
        if done.events:
            self.estimate = self.smoother.estimate()
        self.localizations.append({
            "station": done.station, "seconds": round(done.seconds, 3),
            "factors": len(done.events), "searches": len(done.records),
            "submitted_mission_s": round(submitted_s, 3),
            "collected_mission_s": round(collected_s, 3),
            "waited": not was_ready, "records": records_json(done.records),
        })  # fmt: skip

    # -- goals ---------------------------------------------------------------------------------

    def go(self, robot: str, pose: np.ndarray, path: list[np.ndarray] | None) -> bool:
        """Send one goal; ``path`` None: an absolute goal of an explicit plan."""
        believed = None if path is None else tuple(float(v) for v in self.pose(robot))
        self.clock.done()
        status = self.fleet.move(Goal(
            robot, (float(pose[0]), float(pose[1]), float(pose[2])),
            tuple((float(p[0]), float(p[1])) for p in path or []),
            believed,  # type: ignore[arg-type]
        ))  # fmt: skip
        if not status.ok:
            self.refused.append(status.reason or f"robot {robot}: goal refused")
            if status.blocked_xy is not None and all(map(math.isfinite, status.blocked_xy)):
                self.blocked.append(status.blocked_xy)
        # A real robot that moved before its goal failed stands at a new pose all the same.
        self.index[robot] = status.index
        return status.ok

    # -- the mission ---------------------------------------------------------------------------

    def run(self) -> str:
        """Fly the mission's plan (explicit steps, or exploration); returns why it stopped."""
        self.warm_up_s = warm_up(self.config, self.fleet.capture_header(self.robots[0]))
        try:
            if isinstance(self.mission.plan, list):
                reason = self._scripted(self.mission.plan)
            else:
                reason = self._explore()
            self._collect(wait=True)
            if self.mission.changes is not None:
                self.changed = self.fleet.change_world(self.mission.changes)
                self.dwell(phase="relocalize", step=len(self.steps))
            self.clock.done()
        finally:
            self.localizer.close()
        return reason

    def _scripted(self, plan: list[StepSpec]) -> str:
        self.dwell(phase="start", reference=plan[0].reference, mapper=plan[0].mapper, step=-1)
        for k, step in enumerate(plan):
            self.fleet.log("roles", reference=step.reference, mapper=step.mapper, step=k)
            station = _Station(step.reference, self.index[step.reference], self.now_s)
            if step.at is not None:
                target = np.array([step.at[0], step.at[1], math.radians(step.at[2])])
                before = self.index[step.reference]
                if self.go(step.reference, target, None) and self.index[step.reference] != before:
                    station = _Station(step.reference, self.index[step.reference], self.now_s)
                    self.dwell(phase="station", reference=step.reference, mapper=step.mapper,
                               step=k)  # fmt: skip
            for scan in step.scans:
                target = np.array([scan[0], scan[1], math.radians(scan[2])])
                if self.go(step.mapper, target, None):
                    self.dwell(phase="mapping", reference=step.reference, mapper=step.mapper,
                               step=k)  # fmt: skip
            self.steps.append(step)
            self._station_done(station)
        return "plan flown"

    def _explore(self) -> str:
        auto = self.mission.auto
        explorer = Explorer(self.config, (auto.mapper_distance_m[0], auto.mapper_distance_m[1]))
        names = self.robots
        reference, mapper = names[0], names[1]
        self.dwell(phase="start", reference=reference, mapper=mapper, step=-1)
        for r in names:
            explorer.taken.append(self.pose(r))
        reason = f"station budget ({auto.stations}) spent"
        stall = StallWatch()
        unreached = 0  # frontiers given up in a row for want of a scan pose
        for k in range(auto.stations):
            self.fleet.log("roles", reference=reference, mapper=mapper, step=len(self.steps))
            if self.progress is not None:
                self.progress(
                    f"station {k + 1} (budget {auto.stations}): robot {reference} references, "
                    f"robot {mapper} maps; {self.now_s:.0f} s flown"
                )
            view = self.view()
            if view is None:
                reason = "the estimated map holds no floor"
                break
            ref_pose, map_pose = self.pose(reference), self.pose(mapper)
            frontier = explorer.frontier(view, [ref_pose[:2], map_pose[:2]])
            if frontier is None and k > 0:
                self._collect(wait=True)  # the last station's searches: is the tail tied?
                frontier = closing_target(self, view)
                explorer.frame_xy = view.floor.lower_xy.copy()
                if frontier is None:
                    reason = "no reachable frontier or unvisited room left"
                    break
            flown = self._station(k, explorer, reference, mapper, frontier)
            for other_reference, other_mapper in self._other_pairs(reference, mapper):
                if flown is not None:
                    break
                # Stuck (a corner, a doorway, a robot in the way): another pair tries, the
                # reference among the robots the estimate already places.
                reference, mapper = other_reference, other_mapper
                self.fleet.log("roles", reference=reference, mapper=mapper, step=len(self.steps))
                flown = self._station(k, explorer, reference, mapper, frontier)
            if flown is None and frontier is not None and k > 0 and unreached < _UNREACHED:
                # Generated building 17 ended at half its floor here: every goal toward one
                # frontier was refused on the same leg. Another frontier may still be reached.
                explorer.given_up.append(np.array(frontier.centroid_xy, dtype=float))
                unreached += 1
                continue
            if flown is None:
                where = "at the start " if k == 0 else ""
                reason = f"no mapper pose around robot {reference} {where}sees its beacon"
                if k > 0:
                    reason = f"no mapper pose around robot {reference} or {mapper} sees its beacon"
                break
            unreached = 0
            at, scans, station = flown
            self.steps.append(StepSpec(reference=reference, at=at, mapper=mapper, scans=scans))
            self._station_done(station)
            view = self.view()
            nearer = False
            if view is not None and frontier is not None:
                reach = view.distances_from([self.pose(mapper)[:2], self.pose(reference)[:2]])
                away = min(view.at(reach, c) for c in explorer.centres(view, frontier))
                nearer = explorer.progress(frontier, away, view)
            if view is not None:
                res = view.floor.resolution_m
                if stall.add(float((~view.floor.unknown).sum()) * res * res, nearer):
                    here = [self.pose(mapper)[:2], self.pose(reference)[:2]]
                    if explorer.abandon(view, here):
                        # Stalled on the frontiers tried lately, while one never tried is
                        # left: go there (generated building 2 stopped with half a hall
                        # unexplored after three hopeless doorways).
                        self.abandoned += 1
                        stall.restart()
                    else:
                        reason = f"exploration stalled: {stall.why()}"
                        break
            reference, mapper = mapper, names[(names.index(mapper) + 1) % len(names)]
            if mapper == reference:
                mapper = names[(names.index(reference) + 1) % len(names)]
        self.given_up = [list(map(float, g)) for g in explorer.given_up]
        self.retried_frontiers = [list(map(float, g)) for g in explorer.retried]
        return reason

    def _other_pairs(self, reference: str, mapper: str) -> list[tuple[str, str]]:
        """The (reference, mapper) pairs to try when ``reference`` and ``mapper`` found no
        scan pose: the same two swapped first, then the others; a reference must be placed
        by the estimate."""
        placed = [r for r in self.robots if pose_key(r, self.index[r]) in self.estimate]
        pairs = [(mapper, reference)] + [
            (r, m) for r in placed for m in self.robots if m != r and {r, m} != {reference, mapper}
        ]
        return [(r, m) for r, m in pairs if r in placed]

    def _station(self, k: int, explorer: Explorer, reference: str, mapper: str,
                 frontier: Any) -> _Flown | None:  # fmt: skip
        """One station: the reference turns to its best heading (after the first), the mapper
        takes its scan poses around it. None when no scan pose was possible."""
        at: list[float] | None = None
        scans: list[list[float]] = []
        station = _Station(reference, self.index[reference], self.now_s)
        # First a heading that may face floor nobody has seen yet (the turn's own sweep shows
        # it); if no scan pose comes of it, one from which a scan pose is already known.
        for look_first in (True, False) if k > 0 else (False,):
            if k > 0:
                view = self.view()
                if view is None:
                    return None
                ref_pose, map_pose = self.pose(reference), self.pose(mapper)
                others = [self.pose(n) for n in self.robots if n not in (reference, mapper)]
                plan = explorer.heading(view, ref_pose, map_pose, [ref_pose, *others],
                                        frontier, look_first)  # fmt: skip
                if plan is None:
                    continue
                at = fly_turn(self, explorer, reference, mapper, plan, at)
            station = _Station(reference, self.index[reference], self.now_s)
            for _ in range(self.mission.auto.scans_per_station):
                if not self._scan(explorer, reference, mapper, frontier, scans):
                    break
            if scans:
                break
        self.trace.append({
            "step": k, "reference": f"{reference}{self.index[reference]}",
            "pose": as_spec(self.pose(reference)), "scans": len(scans),
            "frontier": None if frontier is None else [round(float(v), 2)
                                                       for v in frontier.centroid_xy],
            "room": isinstance(frontier, Room),  # a room nobody stood in, not a frontier
            "refused": len(self.refused),
        })  # fmt: skip
        return (at, scans, station) if scans else None

    def _scan(self, explorer: Explorer, reference: str, mapper: str, frontier: Any,
              scans: list[list[float]]) -> bool:  # fmt: skip
        """One scan pose of the mapper around the reference, retried from other poses when
        the mutual observation fails; False when no pose is left."""
        failed: list[np.ndarray] = []
        for attempt in range(RETRIES + 1):
            view = self.view()
            if view is None:
                return False
            others = [self.pose(n) for n in self.robots if n != mapper]
            goal = explorer.scan_pose(view, self.pose(reference), self.pose(mapper), others,
                                      frontier, failed)  # fmt: skip
            if goal is None:
                return False
            if not self.go(mapper, goal.pose, goal.path):
                failed.append(goal.pose)
                continue
            explorer.taken.append(goal.pose)
            seen = self.dwell(phase="mapping", reference=reference, mapper=mapper,
                              step=len(self.steps))  # fmt: skip
            scans.append(as_spec(goal.pose))
            if seen:
                return True
            failed.append(goal.pose)
            label = f"{mapper}{self.index[mapper]} around {reference}{self.index[reference]}"
            if attempt < RETRIES:
                self.retries.append(label)
            else:
                self.unobserved.append(label)
        return True

    def view(self) -> MapView | None:
        """The planner's view of the map now; built again only when a dwell, an event or a
        move changed what it is made of (a station asks for it several times)."""
        state = (self._dwells, self.smoother.events, tuple(self.index.values()), len(self.blocked))
        if self._cached is not None and self._cached[0] == state:
            return self._cached[1]
        stood = [self.estimate[pose_key(r, i)][:2] for r in self.robots
                 for i in range(self.index[r] + 1) if pose_key(r, i) in self.estimate]  # fmt: skip
        now = [self.pose(r)[:2] for r in self.robots]
        try:
            view: MapView | None = MapView(
                self.map.grid, self.config, np.array(stood + now), robots_xy=np.array(now),
                blocked_xy=np.array(self.blocked).reshape(-1, 2),
            )  # fmt: skip
        except MapError:
            view = None
        self._cached = (state, view)
        return view

    # -- the record ----------------------------------------------------------------------------

    def record(self) -> dict[str, Any]:
        """Close the dataset: captures, odometry, events, the mission as flown, the fleet's
        own files. Returns the fleet's counts."""
        for writer in self.writers.values():
            writer.close()
        for robot, (times, poses) in self.odometry.items():
            write_tum(self.work / "robots" / robot / "odometry.tum", times, poses, decimals=6)
        lines = [json.dumps(e, separators=(",", ":")) for e in self.entries]
        write_text_atomic(self.work / "events.jsonl", "\n".join(lines) + "\n")
        steps = self.steps or []
        header = f"# effective mission; coopmap {__version__}, seed {self.mission.seed}\n"
        write_text_atomic(
            self.work / "mission.yaml",
            header + mission_to_yaml(self.mission, steps, self.config.model_dump(mode="json")),
        )
        return self.fleet.finish(self.work)

    def keep(self, failure: str) -> None:
        """Close the dataset as far as the mission was flown when it failed with ``failure``
        and mark it partial (:data:`PARTIAL`): its recording can then be examined offline
        (``coopmap batch`` reads it like any other)."""
        self.record()
        note = {"failure": failure, "mission_s": round(self.now_s, 3), "dwells": self._dwells,
                "stations": len(self.trace)}  # fmt: skip
        write_text_atomic(self.work / PARTIAL, json.dumps(note) + "\n")

    def discard(self) -> None:
        for writer in self.writers.values():
            writer.discard()

    def figures(self, stop_reason: str, fleet_counts: dict[str, Any]) -> dict[str, Any]:
        next_map = next_map_seconds(self.entries)
        localizations = []
        for item in self.localizations:
            budget = next_map.get(item["station"])
            in_time = budget is None or item["seconds"] <= budget
            localizations.append({**item, "next_map_mission_s": budget, "in_time": in_time})
        return {
            "stop_reason": stop_reason,
            "duration_s": self.now_s,
            "changed": self.changed,
            "dwells": self._dwells,
            **self.clock.summary(),
            "warm_up_s": round(self.warm_up_s, 3),
            "map_refusions": self.map.refusions,
            "map_refusions_from_scratch": self.map.from_scratch,
            "concurrent_localization": localizations,
            "retried_observations": self.retries,
            "unobserved_scans": self.unobserved,
            "pivots": self.pivots,
            "untied_turns": self.untied,
            "closing_stations": self.closing,
            "refused_goals": self.refused + list(fleet_counts.get("refused_goals", [])),
            "blocked_at": [[round(x, 3), round(y, 3)] for x, y in self.blocked],
            "given_up_frontiers": self.given_up,
            "retried_frontiers": self.retried_frontiers,
            "stalls_resumed": self.abandoned,
            "stations": self.trace,
            **{k: v for k, v in fleet_counts.items() if k != "refused_goals"},
        }  # fmt: skip

    def finish(self, out: Path, stop_reason: str, dataset_path: Path | None = None) -> LoopResult:
        """Write the result from the recorded dataset (as ``coopmap isam`` would);
        ``dataset_path`` is where the dataset will be (``work`` is replaced into it)."""
        counts = self.record()
        loop = self.figures(stop_reason, counts)
        prepared = prepare(self.work, None, self.progress)
        clock = time.perf_counter()
        smoother = IncrementalSmoother(**isam_options(prepared.dataset.config))
        for event in prepared.events:
            smoother.add(event)
        online = dict(self.estimate)
        report = {"mission_loop": loop, "dataset": str(dataset_path or self.work)}
        output = finish_isam(prepared, smoother, out, optimize_s=time.perf_counter() - clock,
                             progress=self.progress, report=report)  # fmt: skip
        final = {pose_key(r, i): p for r, poses in output.poses.items() for i, p in poses.items()}
        shared = [k for k in final if k in online]
        # After the report: how far the estimate that steered the mission lay from the final one.
        loop["online_vs_final_m"] = max(
            (math.hypot(*(final[k][:2] - online[k][:2])) for k in shared), default=0.0
        )
        return LoopResult(output, self.steps, stop_reason, loop)
