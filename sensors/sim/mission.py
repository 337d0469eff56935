"""Simulated missions: the leapfrog of docs/design.md §8, and the dataset a real mission would
record.

A mission file names a world, the robots and their start poses, and a plan: explicit leapfrog
steps (a reference robot at a station, a mapper and its scan poses) or ``auto``. The mission
runs as a timeline in which one robot moves at a time: the reference drives to its station
while the mapper watches, then the mapper drives from scan pose to scan pose; every time all
robots stand still they dwell long enough for each scanner to complete a sweep, so that every
stop yields a 3D scan and, when the beacons are in view, a mutual observation. Roles swap as
the plan says. An optional ``changes`` step then moves the movable objects and each robot scans
once more, to be globally localized against the map.

The dataset (docs/design.md §12) holds what robots would record: each robot's raw LMS byte stream
with receive stamps (``robots/<name>/lms.cap``), its odometry (``odometry.tum``, noisy, integrated
per leg), the mission's event log (``events.jsonl``: starts, moves, dwells, roles, changes), and the
ground truth (``ground_truth/<name>.tum``), plus the world(s) and the effective mission.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal, Self

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, model_validator

from sensors.atomic import write_text_atomic
from sensors.errors import SensorError
from sensors.geometry import se2
from sensors.geometry.frames import scanner_pose_matrix
from sensors.lms200.capture import CaptureWriter
from sensors.sim.planner import FreeSpace
from sensors.sim.scene import RaycastScene
from sensors.sim.sensing import (
    RobotBody,
    SimulatedScanner,
    robot_cylinders,
    scan_stream,
    telegram_times,
)
from sensors.trajio import write_tum
from sensors.yamlio import read_yaml_mapping, validate_mapping

__all__ = [
    "CHUNK_SCANS",
    "ChangesSpec",
    "CollisionError",
    "MissionError",
    "MissionSpec",
    "Odometer",
    "OdometryNoise",
    "SensorRecorder",
    "StepSpec",
    "Timeline",
    "TimelineBuilder",
    "build_timeline",
    "load_mission",
    "mission_from_mapping",
    "mission_to_yaml",
    "odometry",
    "write_dataset",
]

Pose3 = Annotated[list[float], Field(min_length=3, max_length=3)]  # x_m, y_m, yaw_deg


class MissionError(SensorError, ValueError):
    """A mission is invalid or cannot be flown; the message names the step, robot or station."""


class CollisionError(MissionError):
    """A robot's path would collide: ``at_xy`` is where its centre would first come too close
    to what is really there (world frame)."""

    def __init__(self, message: str, at_xy: np.ndarray) -> None:
        super().__init__(message)
        self.at_xy = np.asarray(at_xy, dtype=float)[:2].copy()


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


class RobotSpec(_Model):
    name: Annotated[str, Field(pattern=r"^[a-z]$")]  # one letter: it names the robot's graph keys
    start: Pose3


class StepSpec(_Model):
    """The reference stands at ``at`` (driving there first if needed); the mapper scans at each
    of ``scans``."""

    reference: str
    at: Pose3 | None = None
    mapper: str
    scans: list[Pose3] = Field(min_length=1)


class ChangesSpec(_Model):
    movable_fraction: float = Field(0.5, ge=0, le=1)
    shift_m: float = Field(0.5, ge=0)
    yaw_deg: float = Field(30.0, ge=0)
    remove_fraction: float = Field(0.0, ge=0, le=1)


class AutoSpec(_Model):
    """Parameters of ``plan: auto``."""

    stations: int = Field(4, ge=1, le=500)
    scans_per_station: int = Field(3, ge=1, le=10)
    coverage: float = Field(0.9, gt=0, le=1)
    mapper_distance_m: Annotated[list[float], Field(min_length=2, max_length=2)] = [1.5, 4.5]
    #: Optional waypoints (x_m, y_m) to follow in order, e.g. around a loop and back; with a
    #: route, poses are chosen by progress along it rather than by coverage alone.
    route: list[Annotated[list[float], Field(min_length=2, max_length=2)]] = []
    #: ``truth``: the stations and scan poses are planned before the mission on the true world
    #: (a simulation-only shortcut); ``map``: the mission loop plans them during the mission on
    #: the map as estimated, exploring until no reachable frontier is left or ``stations`` are
    #: spent (``route`` and ``coverage`` then do not apply).
    planner: Literal["truth", "map"] = "truth"


class MissionSpec(_Model):
    world: str = Field(min_length=1)
    seed: int = Field(0, ge=0)  # numpy's generators take non-negative seeds
    robots: list[RobotSpec] = Field(min_length=2)
    plan: Literal["auto"] | list[StepSpec]
    auto: AutoSpec = AutoSpec()
    changes: ChangesSpec | None = None
    config: dict[str, Any] = {}

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        names = [r.name for r in self.robots]
        if len(set(names)) != len(names):
            raise ValueError(f"robot names must be unique, got {names}")
        if isinstance(self.plan, list):
            if not self.plan:
                raise ValueError("plan has no steps")
            for k, step in enumerate(self.plan):
                for role in ("reference", "mapper"):
                    if getattr(step, role) not in names:
                        raise ValueError(
                            f"plan[{k}]: {role} {getattr(step, role)!r} is not one of the "
                            f"robots {names}"
                        )
                if step.reference == step.mapper:
                    raise ValueError(
                        f"plan[{k}]: robot {step.reference!r} cannot map around itself"
                    )
        return self

    def robot_names(self) -> list[str]:
        return [r.name for r in self.robots]


def mission_from_mapping(data: dict[str, Any], source: str = "mission") -> MissionSpec:
    try:
        return validate_mapping(MissionSpec, data, MissionError, source)
    except MissionError:
        raise
    except SensorError as exc:  # pragma: no cover - validate_mapping raises the class it is given
        raise MissionError(str(exc)) from None


def load_mission(path: Path | str) -> MissionSpec:
    path = Path(path)
    return mission_from_mapping(read_yaml_mapping(path, MissionError), str(path))


def _pose(spec: list[float]) -> np.ndarray:
    return np.array([spec[0], spec[1], math.radians(spec[2])])


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


@dataclass
class _Track:
    """A robot's true trajectory as keyframes (t, x, y, yaw), linear in between."""

    keys: list[tuple[float, float, float, float]]

    @property
    def pose(self) -> np.ndarray:
        return np.array(self.keys[-1][1:])

    def hold_until(self, t: float) -> None:
        if t > self.keys[-1][0]:
            self.keys.append((t, *self.keys[-1][1:]))

    def at(self, times: np.ndarray) -> np.ndarray:
        keys = np.array(self.keys)
        yaw = np.unwrap(keys[:, 3])
        return np.column_stack(
            [np.interp(times, keys[:, 0], keys[:, c]) for c in (1, 2)]
            + [np.interp(times, keys[:, 0], yaw)]
        )


@dataclass
class Timeline:
    """The true motion of every robot, the stops that number their poses, and the event log."""

    tracks: dict[str, _Track]
    events: list[dict[str, Any]] = field(default_factory=list)
    stops: dict[str, list[tuple[float, np.ndarray]]] = field(default_factory=dict)
    legs: dict[str, list[tuple[float, float, int]]] = field(default_factory=dict)
    end_s: float = 0.0
    change_s: float | None = None

    def poses_at(self, robot: str, times: np.ndarray) -> np.ndarray:
        return self.tracks[robot].at(np.asarray(times, dtype=float))


class TimelineBuilder:
    """The timeline as it is flown: one robot moves at a time, everybody dwells together.

    ``move`` plans its path through the free space of the true world (as ``simulate`` does for a
    plan), or follows the ``path`` it is given (as a robot follows the mission loop's plan on
    the estimated map), refusing a path that would collide in the true world."""

    def __init__(self, starts: dict[str, np.ndarray], space: FreeSpace, speed_m_s: float,
                 turn_rate_rad_s: float, dwell_s: float) -> None:  # fmt: skip
        self.t = 0.0
        self.space = space
        self.speed, self.turn, self.dwell_s = speed_m_s, turn_rate_rad_s, dwell_s
        self.timeline = Timeline({n: _Track([(0.0, *p)]) for n, p in starts.items()})
        self.index = dict.fromkeys(starts, 0)
        for name, pose in starts.items():
            if not space.is_free(pose[:2]):
                raise MissionError(
                    f"robot {name!r} starts at ({pose[0]:g}, {pose[1]:g}), where it does not fit"
                )
            self.timeline.stops[name] = [(0.0, pose)]
            self.timeline.legs[name] = []
            self.log("start", robot=name, index=0)

    def log(self, event: str, **fields: Any) -> None:
        self.timeline.events.append({"t_s": round(self.t, 6), "event": event, **fields})

    def move(
        self, robot: str, target: np.ndarray, where: str, path: list[np.ndarray] | None = None
    ) -> bool:
        """Drive ``robot`` to ``target`` (x, y, yaw); False if it already stands there.
        MissionError (nothing moved) when the target or the path is not free in the world."""
        track = self.timeline.tracks[robot]
        start = track.pose
        if (
            np.allclose(start[:2], target[:2], atol=1e-6)
            and abs(_wrap(target[2] - start[2])) < 1e-6
        ):
            return False
        if not self.space.is_free(target[:2]):
            raise MissionError(
                f"{where}: robot {robot!r} cannot stand at ({target[0]:g}, {target[1]:g}): "
                "inside or too close to an obstacle, or outside the rooms"
            )
        if path is None:
            legs = self.space.path(start[:2], target[:2])
        else:
            legs = self._follow(robot, start[:2], target[:2], path, where)
        if legs is None:
            raise MissionError(
                f"{where}: robot {robot!r} cannot reach ({target[0]:g}, {target[1]:g}) "
                f"from ({start[0]:.2f}, {start[1]:.2f}): no collision-free path"
            )
        for other in self.timeline.tracks.values():
            other.hold_until(self.t)
        begin = self.t
        t, (x, y, yaw) = self.t, start
        keys = track.keys
        for point in legs[1:]:
            heading = math.atan2(point[1] - y, point[0] - x)
            turn = _wrap(heading - yaw)
            if abs(turn) > 1e-9:
                t += abs(turn) / self.turn
                yaw += turn
                keys.append((t, x, y, yaw))
            t += math.hypot(point[0] - x, point[1] - y) / self.speed
            x, y = float(point[0]), float(point[1])
            keys.append((t, x, y, yaw))
        turn = _wrap(target[2] - yaw)
        if abs(turn) > 1e-9:
            t += abs(turn) / self.turn
            keys.append((t, x, y, yaw + turn))
        self.t = t
        self.index[robot] += 1
        self.timeline.legs[robot].append((begin, t, self.index[robot]))
        self.timeline.stops[robot].append((t, target.copy()))
        self.log("move", robot=robot, from_index=self.index[robot] - 1,
                 to_index=self.index[robot], start_s=round(begin, 6))  # fmt: skip
        return True

    def _follow(self, robot: str, start: np.ndarray, target: np.ndarray,
                path: list[np.ndarray], where: str) -> list[np.ndarray]:  # fmt: skip
        """The legs a robot drives along a planned ``path``: its local control keeps the body
        clear of what is really there by deviating up to ``LOCAL_DEVIATION_M`` from a leg (as a
        robot's own obstacle avoidance would); a leg that cannot be driven so is a collision."""
        points = [start, *(np.asarray(p, dtype=float)[:2] for p in path[1:-1]), target]
        legs = [start]
        for b in points[1:]:
            a = legs[-1]
            if b is not target and not self.space.is_free(b):
                continue  # a corner of the plan that the body cannot reach: cut it
            if self.space.segment_free(a, b):
                legs.append(b)
                continue
            local = None
            if self.space.is_free(b):
                local = self.space.path(a, b)
            if local is None or any(
                _distance_to_segment(q, a, b) > LOCAL_DEVIATION_M for q in local
            ):
                at = self.space.first_blocked(a, b)
                raise CollisionError(
                    f"{where}: robot {robot!r} would collide on the leg ({a[0]:.2f}, "
                    f"{a[1]:.2f}) → ({b[0]:.2f}, {b[1]:.2f}) of its path",
                    b if at is None else at,
                )
            legs += local[1:]
        return legs

    def dwell(self, **fields: Any) -> None:
        begin = self.t
        self.t += self.dwell_s
        for track in self.timeline.tracks.values():
            track.hold_until(self.t)
        self.timeline.events.append(
            {"t_s": round(begin, 6), "event": "dwell", "end_s": round(self.t, 6),
             "poses": dict(self.index), **fields}
        )  # fmt: skip


#: Scans simulated per ray-casting call (bounds the memory of one call).
CHUNK_SCANS = 1500
#: How far a robot's own obstacle avoidance may take it from a leg of its planned path (m).
LOCAL_DEVIATION_M = 0.3


def _distance_to_segment(q: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    length2 = float(ab @ ab)
    t = 0.0 if length2 == 0 else float(np.clip((q - a) @ ab / length2, 0.0, 1.0))
    return float(np.linalg.norm(q - (a + t * ab)))


def build_timeline(
    mission: MissionSpec,
    steps: list[StepSpec],
    space: FreeSpace,
    *,
    speed_m_s: float,
    turn_rate_rad_s: float,
    dwell_s: float,
    changes_at_end: bool,
) -> Timeline:
    """The leapfrog as a timeline: one robot moves at a time; all dwell at every stop."""
    builder = TimelineBuilder(
        {r.name: _pose(r.start) for r in mission.robots}, space, speed_m_s, turn_rate_rad_s, dwell_s
    )
    builder.dwell(phase="start", reference=steps[0].reference, mapper=steps[0].mapper, step=-1)
    for k, step in enumerate(steps):
        builder.log("roles", reference=step.reference, mapper=step.mapper, step=k)
        if step.at is not None and builder.move(
            step.reference, _pose(step.at), f"plan[{k}] station"
        ):
            builder.dwell(phase="station", reference=step.reference, mapper=step.mapper, step=k)
        for j, scan in enumerate(step.scans):
            builder.move(step.mapper, _pose(scan), f"plan[{k}].scans[{j}]")
            builder.dwell(phase="mapping", reference=step.reference, mapper=step.mapper, step=k)
    if changes_at_end:
        builder.timeline.change_s = builder.t
        builder.log("changes")
        builder.dwell(phase="relocalize", step=len(steps))
    builder.timeline.end_s = builder.t
    return builder.timeline


# --------------------------------------------------------------------------------------------
# Odometry


@dataclass(frozen=True)
class OdometryNoise:
    """Error of one leg: σ = base + per unit (translation per metre, rotation per radian)."""

    sigma_m: float = 0.005
    sigma_per_m: float = 0.02
    sigma_rad: float = math.radians(0.2)
    sigma_rad_per_rad: float = math.radians(1.0)


class Odometer:
    """A robot's odometry over a timeline that may still grow: each leg's error is drawn when
    the leg is first needed, in leg order, and accrues in proportion to the leg's elapsed time;
    the poses are integrated from the start pose."""

    def __init__(self, timeline: Timeline, robot: str, noise: OdometryNoise,
                 rng: np.random.Generator) -> None:  # fmt: skip
        self.timeline, self.robot, self.noise, self.rng = timeline, robot, noise, rng
        self.errors: list[np.ndarray] = []
        self.stops = [timeline.stops[robot][0][1].astype(float)]

    def _draw(self) -> None:
        stops = [pose for _, pose in self.timeline.stops[self.robot]]
        noise = self.noise
        for k in range(len(self.errors), len(self.timeline.legs[self.robot])):
            delta = se2.between(stops[k], stops[k + 1])
            travelled = math.hypot(delta[0], delta[1])
            turned = abs(delta[2]) + (
                abs(math.atan2(delta[1], delta[0])) if travelled > 1e-6 else 0.0
            )
            st = noise.sigma_m + noise.sigma_per_m * travelled
            sr = noise.sigma_rad + noise.sigma_rad_per_rad * turned
            rng = self.rng
            error = np.array([rng.normal(0, st), rng.normal(0, st), rng.normal(0, sr)])
            self.errors.append(error)
            self.stops.append(se2.compose(self.stops[-1], delta + error))

    def at(self, times: np.ndarray) -> np.ndarray:
        """Odometry poses (N, 3) at ``times`` (none later than the timeline's last keyframe)."""
        self._draw()
        true = self.timeline.poses_at(self.robot, times)
        out = np.empty_like(true)
        legs = self.timeline.legs[self.robot]
        stops = [pose for _, pose in self.timeline.stops[self.robot]]
        for i, t in enumerate(times):
            leg = next((k for k, (t0, t1, _) in enumerate(legs) if t0 <= t < t1), None)
            if leg is None:
                done = sum(1 for (_, t1, _) in legs if t1 <= t)
                out[i] = self.stops[done]
                continue
            t0, t1, _ = legs[leg]
            fraction = (t - t0) / (t1 - t0)
            delta = se2.between(stops[leg], true[i])
            out[i] = se2.compose(self.stops[leg], delta + fraction * self.errors[leg])
        out[:, 2] = np.angle(np.exp(1j * out[:, 2]))
        return out


def odometry(
    timeline: Timeline,
    robot: str,
    times: np.ndarray,
    noise: OdometryNoise,
    rng: np.random.Generator,
) -> np.ndarray:
    """Odometry poses (N, 3) at ``times`` of a finished timeline (:class:`Odometer`)."""
    return Odometer(timeline, robot, noise, rng).at(times)


# --------------------------------------------------------------------------------------------
# The dataset


def write_dataset(
    out_dir: Path,
    timeline: Timeline,
    scanners: dict[str, SimulatedScanner],
    scenes: Callable[[float], RaycastScene],
    body: RobotBody,
    *,
    scanner_height_m: float,
    odometry_noise: OdometryNoise,
    rng: np.random.Generator,
    baud_rate: int = 38400,
    odometry_rate_hz: float = 10.0,
    chunk_scans: int = CHUNK_SCANS,
    progress: Callable[[str, float], None] | None = None,
) -> dict[str, Any]:
    """Record every robot's sensors over the timeline into ``out_dir`` (docs/design.md §12).

    ``scenes(t)`` gives the static world the scanners see at time t (it changes once if the
    mission has a ``changes`` step). Returns counts for the report.
    """
    robots = list(timeline.tracks)
    stats: dict[str, Any] = {"duration_s": timeline.end_s, "robots": {}}
    odo_times = np.arange(0.0, timeline.end_s + 1e-9, 1.0 / odometry_rate_hz)
    for name in robots:
        truth = timeline.poses_at(name, odo_times)
        write_tum(out_dir / "ground_truth" / f"{name}.tum", odo_times, truth, decimals=6)
        noisy = odometry(timeline, name, odo_times, odometry_noise, rng)
        write_tum(out_dir / "robots" / name / "odometry.tum", odo_times, noisy, decimals=6)
    lines = [json.dumps(event, separators=(",", ":")) for event in timeline.events]
    write_text_atomic(out_dir / "events.jsonl", "\n".join(lines) + "\n")

    for r, name in enumerate(robots):
        scanner = scanners[name]
        count = len(scanner.bearing_rad)
        times = telegram_times(0.0, timeline.end_s, baud_rate, count, scanner.resolution_deg)
        capture = out_dir / "robots" / name / "lms.cap"
        capture.unlink(missing_ok=True)
        writer = CaptureWriter(capture, {"robot": name, "baud_rate": baud_rate, "simulated": True})
        recorder = SensorRecorder(writer, name, scanner, body, scanner_height_m, baud_rate)
        try:
            for start in range(0, len(times), chunk_scans):
                recorder.record(timeline, scenes, times[start : start + chunk_scans], rng)
                if progress is not None:
                    done = (start + chunk_scans) / max(len(times), 1)
                    progress(name, (r + min(done, 1.0)) / len(robots))
        except BaseException:
            writer.discard()
            raise
        writer.close()
        stats["robots"][name] = {
            "telegrams": recorder.telegrams,
            "poses": len(timeline.stops[name]),
            "bytes": writer.bytes_written,
            "motor_period_s": scanner.motor_period_s,
        }
    return stats


class SensorRecorder:
    """One robot's LMS 200 as the simulator runs it: the scans measured at given instants of a
    timeline, encoded as the sensor's telegrams and appended to ``writer`` (when there is one;
    they are returned either way)."""

    def __init__(self, writer: CaptureWriter | None, robot: str, scanner: SimulatedScanner,
                 body: RobotBody, scanner_height_m: float, baud_rate: int) -> None:  # fmt: skip
        self.robot, self.scanner, self.body = robot, scanner, body
        self.scanner_height_m, self.baud_rate = scanner_height_m, baud_rate
        self.writer = writer
        self.telegrams = 0

    def due(self, until_s: float) -> np.ndarray:
        """The instants of the telegrams not yet recorded that begin before ``until_s``."""
        times = telegram_times(0.0, until_s, self.baud_rate, len(self.scanner.bearing_rad),
                               self.scanner.resolution_deg)  # fmt: skip
        return times[self.telegrams :]

    def record(
        self,
        timeline: Timeline,
        scenes: Callable[[float], RaycastScene],
        chunk: np.ndarray,
        rng: np.random.Generator,
    ) -> list[tuple[float, bytes]]:
        """Measure, encode and record the telegrams at the instants ``chunk`` (the next ones of
        the continuous output); returns them as (receive stamp, bytes)."""
        if not len(chunk):
            return []
        body, scanner = self.body, self.scanner
        pose = timeline.poses_at(self.robot, chunk)
        T = np.stack([
            scanner_pose_matrix(x, y, yaw, body.scanner_x_m, self.scanner_height_m)
            for x, y, yaw in pose
        ])  # fmt: skip
        others = [o for o in timeline.tracks if o != self.robot]
        cylinders = robot_cylinders(
            body, np.stack([timeline.poses_at(o, chunk) for o in others], axis=1)
        )
        scans: list[Any] = []
        for scene_time in sorted({_scene_key(timeline, t) for t in chunk}):
            rows = np.array([_scene_key(timeline, t) == scene_time for t in chunk])
            scans.append((rows, scanner.scan(scenes(scene_time), T[rows], chunk[rows], rng,
                                             cylinders=cylinders[rows])))  # fmt: skip
        merged = _merge(scans, len(chunk))
        written = scan_stream(merged, baud_rate=self.baud_rate, first_telegram=self.telegrams)
        if self.writer is not None:
            for stamp, data in written:
                self.writer.write(stamp, data)
        self.telegrams += len(written)
        return written


def _scene_key(timeline: Timeline, t: float) -> float:
    return 0.0 if timeline.change_s is None or t < timeline.change_s else timeline.change_s


def _merge(parts: list[tuple[np.ndarray, Any]], n: int) -> Any:
    """Put per-scene pieces of a chunk back in time order."""
    if len(parts) == 1:
        return parts[0][1]
    first = parts[0][1]
    fields: dict[str, Any] = {}
    for name in ("times_s", "ranges_m", "codes", "flags", "elevation_rad", "truth_scanner",
                 "surface_id"):  # fmt: skip
        sample = getattr(first, name)
        merged = np.empty((n, *sample.shape[1:]), dtype=sample.dtype)
        for rows, part in parts:
            merged[rows] = getattr(part, name)
        fields[name] = merged
    return type(first)(bearing_rad=first.bearing_rad, **fields)


def mission_to_yaml(mission: MissionSpec, steps: list[StepSpec], config: dict[str, Any]) -> str:
    """The effective mission: the plan as flown (explicit steps) and the effective config."""
    document = mission.model_dump(mode="json")
    document["plan"] = [s.model_dump(mode="json") for s in steps]
    document["config"] = config
    return yaml.safe_dump(document, sort_keys=False)
