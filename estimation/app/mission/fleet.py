"""The robots as the mission loop sees them: one narrow interface (docs/design.md §13).

Goals go out — drive to a pose along a path, dwell for a sweep, log what the mission decided —
and what the robots recorded comes back: the raw LMS bytes with their receive stamps, odometry
samples, and the mission's event entries (moves and dwells, as ``events.jsonl`` holds them).
Nothing else crosses: the loop decodes, detects and estimates on its side, so a transport over
the network only has to carry these values. :class:`SimulatedFleet` runs the robots in the
simulator (the only place that reads the true world); a network implementation is the
robots-over-Zenoh issue's.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from estimation.app.config import Config
from estimation.app.rig import dwell_seconds, odometry_noise, robot_body, simulated_scanner
from sensors.atomic import write_text_atomic
from sensors.geometry import se2
from sensors.sim.mission import (
    CHUNK_SCANS,
    ChangesSpec,
    CollisionError,
    MissionError,
    Odometer,
    SensorRecorder,
    TimelineBuilder,
)
from sensors.sim.planner import FreeSpace
from sensors.sim.scene import RaycastScene, build_mesh
from sensors.sim.world import World, perturb_movables, world_to_yaml
from sensors.trajio import tum_text

__all__ = ["Fleet", "Goal", "Received", "SimulatedFleet", "Status"]


@dataclass(frozen=True)
class Goal:
    """Drive ``robot`` to ``pose`` (x_m, y_m, yaw_rad, map frame) along ``path`` (waypoints
    from where it stands to the goal, through free space of the estimated map; empty: the
    robot finds its own way). ``believed`` is where the loop believes the robot stands: a robot
    localized by that belief reaches the goal as far off as the belief is (None: the goal is
    absolute, as an explicit plan gives it)."""

    robot: str
    pose: tuple[float, float, float]
    path: tuple[tuple[float, float], ...] = ()
    believed: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class Status:
    """How a goal ended: ``ok`` and the robot's new pose index, or why it was refused;
    ``blocked_xy``, where the robot found its way blocked (map frame), if it knows."""

    robot: str
    ok: bool
    index: int
    reason: str | None = None
    blocked_xy: tuple[float, float] | None = None


@dataclass
class Received:
    """What the robots recorded since the last :meth:`Fleet.receive`."""

    events: list[dict[str, Any]] = field(default_factory=list)
    lms: dict[str, list[tuple[float, bytes]]] = field(default_factory=dict)
    odometry: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    now_s: float = 0.0


class Fleet(ABC):
    """The robots of one mission behind one interface."""

    robots: list[str]
    starts: dict[str, np.ndarray]  # declared start poses (x_m, y_m, yaw_rad): the map frame

    @abstractmethod
    def capture_header(self, robot: str) -> dict[str, Any]:
        """The header of the robot's capture (baud rate, whether simulated)."""

    @abstractmethod
    def move(self, goal: Goal) -> Status:
        """Drive one robot (the others stand still) and wait until it arrived or gave up."""

    @abstractmethod
    def dwell(self, **fields: Any) -> None:
        """Every robot stands still long enough for a full sweep; ``fields`` tag the dwell
        (phase, reference, mapper, step)."""

    @abstractmethod
    def log(self, event: str, **fields: Any) -> None:
        """Record a mission decision (roles, changes) in the event log."""

    @abstractmethod
    def receive(self) -> Received:
        """Everything recorded since the last call."""

    @abstractmethod
    def change_world(self, changes: ChangesSpec) -> list[str]:
        """Simulation only: move the movable objects (the ``changes`` step); what moved."""

    @abstractmethod
    def finish(self, out_dir: Path) -> dict[str, Any]:
        """Write what the fleet alone knows into the dataset folder (e.g. the simulator's
        ground truth); counts for the report."""

    @abstractmethod
    def close(self) -> None:
        """Release what the fleet holds (processes, ports, sessions)."""


class SimulatedFleet(Fleet):
    """The robots in the simulator: their bodies move through the true world along the paths
    the loop plans (a path that would collide is refused), their LMS 200s and odometry are
    simulated over each interval as the mission goes."""

    def __init__(self, world: World, space: FreeSpace, config: Config,
                 starts: dict[str, np.ndarray], seed: int) -> None:  # fmt: skip
        self.world, self.config, self.seed = world, config, seed
        self.robots = list(starts)
        self.starts = {r: np.asarray(p, dtype=float) for r, p in starts.items()}
        self.builder = TimelineBuilder(
            self.starts, space, config.robot.speed_m_s, math.radians(config.robot.turn_rate_deg_s),
            dwell_seconds(config),
        )  # fmt: skip
        self.timeline = self.builder.timeline
        segments = config.simulation.cylinder_segments
        self.scene = RaycastScene(build_mesh(world, cylinder_segments=segments))
        self.changed_world: World | None = None
        self._changed_scene: RaycastScene | None = None
        body = robot_body(config)
        self.recorders = {
            name: SensorRecorder(None, name, simulated_scanner(config, np.random.default_rng(
                [seed, 3, k])), body, config.robot.scanner_height_m, config.serial.baud_rate)
            for k, name in enumerate(self.robots)
        }  # fmt: skip
        self.scan_rng = np.random.default_rng([seed, 4])
        noise_rng = np.random.default_rng([seed, 5])
        self.odometers = {
            r: Odometer(self.timeline, r, odometry_noise(config), noise_rng) for r in self.robots
        }
        self.odometry_period_s = 0.1
        self._odometry_sent = dict.fromkeys(self.robots, 0)
        self._events_sent = 0
        self.refused: list[str] = []

    def capture_header(self, robot: str) -> dict[str, Any]:
        return {"robot": robot, "baud_rate": self.config.serial.baud_rate, "simulated": True}

    def _scenes(self, t: float) -> RaycastScene:
        change = self.timeline.change_s
        if self._changed_scene is not None and change is not None and t >= change:
            return self._changed_scene
        return self.scene

    def move(self, goal: Goal) -> Status:
        target = np.array(goal.pose, dtype=float)
        path = [np.array(p, dtype=float) for p in goal.path]
        true_now = self.timeline.tracks[goal.robot].pose
        believed = true_now if goal.believed is None else np.array(goal.believed, dtype=float)
        if goal.believed is not None:
            # The robot drives by its belief: the goal and the path, relative to where it
            # believes it stands, start from where it truly stands.
            def truly(p: np.ndarray) -> np.ndarray:
                return se2.compose(true_now, se2.between(believed, p))

            target = truly(target)
            path = [truly(np.array([p[0], p[1], 0.0]))[:2] for p in path]
        try:
            self.builder.move(goal.robot, target, f"goal of robot {goal.robot}", path or None)
        except MissionError as exc:
            self.refused.append(str(exc))
            blocked = None
            if isinstance(exc, CollisionError):
                # Where the body met the obstacle, as the robot believes it: the map frame.
                at = se2.compose(believed, se2.between(true_now, np.r_[exc.at_xy, 0.0]))
                blocked = (float(at[0]), float(at[1]))
            return Status(goal.robot, False, self.builder.index[goal.robot], str(exc), blocked)
        return Status(goal.robot, True, self.builder.index[goal.robot])

    def dwell(self, **fields: Any) -> None:
        self.builder.dwell(**fields)

    def log(self, event: str, **fields: Any) -> None:
        self.builder.log(event, **fields)

    def change_world(self, changes: ChangesSpec) -> list[str]:
        self.changed_world, moved = perturb_movables(
            self.world, np.random.default_rng([self.seed, 2]), fraction=changes.movable_fraction,
            shift_m=changes.shift_m, yaw_deg=changes.yaw_deg,
            remove_fraction=changes.remove_fraction,
        )  # fmt: skip
        segments = self.config.simulation.cylinder_segments
        self._changed_scene = RaycastScene(
            build_mesh(self.changed_world, cylinder_segments=segments)
        )
        self.timeline.change_s = self.builder.t
        objects = [{"name": c.name, "action": c.action} for c in moved]
        self.builder.log("changes", objects=objects)
        return [f"{c.name} {c.action}" for c in moved]

    def receive(self, robots: list[str] | None = None) -> Received:
        """What the robots (all, or ``robots``: a robot agent records its own only) measured
        since the last call."""
        now = self.builder.t
        got = Received(now_s=now)
        got.events = [dict(e) for e in self.timeline.events[self._events_sent :]]
        self._events_sent = len(self.timeline.events)
        for name, recorder in self.recorders.items():
            if robots is not None and name not in robots:
                continue
            due = recorder.due(now)
            chunks: list[tuple[float, bytes]] = []
            for start in range(0, len(due), CHUNK_SCANS):
                piece = due[start : start + CHUNK_SCANS]
                chunks += recorder.record(self.timeline, self._scenes, piece, self.scan_rng)
            got.lms[name] = chunks
            times = self._odometry_times(now)[self._odometry_sent[name] :]
            self._odometry_sent[name] += len(times)
            poses = self.odometers[name].at(times) if len(times) else np.zeros((0, 3))
            got.odometry[name] = (times, poses)
        return got

    def _odometry_times(self, until_s: float) -> np.ndarray:
        return np.arange(0.0, until_s + 1e-9, self.odometry_period_s)

    def finish(self, out_dir: Path) -> dict[str, Any]:
        for name, text in self.truth_files().items():
            write_text_atomic(out_dir / name, text)
        return {"refused_goals": list(self.refused)}

    def truth_files(self, robots: list[str] | None = None) -> dict[str, str]:
        """The simulator's own files of the dataset (relative path → text): the true
        trajectories of ``robots`` (all by default) and the world, as it was and as changed."""
        self.timeline.end_s = self.builder.t
        times = self._odometry_times(self.builder.t)
        files = {}
        for name in robots or self.robots:
            truth = self.timeline.poses_at(name, times)
            files[f"ground_truth/{name}.tum"] = tum_text(times, truth, decimals=6)
        files["world.yaml"] = world_to_yaml(self.world)
        if self.changed_world is not None:
            files["world_changed.yaml"] = world_to_yaml(self.changed_world)
        return files

    def state(self) -> dict[str, Any]:
        """What the sensors consumed so far (telegrams, odometry samples, the noise streams),
        as JSON: with the goals replayed (:meth:`restore`), the simulation goes on exactly as
        it would have — a restarted robot agent's checkpoint."""
        return {
            "telegrams": {r: rec.telegrams for r, rec in self.recorders.items()},
            "odometry_sent": dict(self._odometry_sent),
            "events_sent": self._events_sent,
            "scan_rng": self.scan_rng.bit_generator.state,
        }

    def restore(self, state: dict[str, Any]) -> None:
        """Take the sensors' :meth:`state` back after the goals were replayed (without
        :meth:`receive`); the odometry noise is drawn again in leg order, as it was."""
        for r, rec in self.recorders.items():
            rec.telegrams = int(state["telegrams"][r])
        self._odometry_sent = {r: int(v) for r, v in state["odometry_sent"].items()}
        self._events_sent = int(state["events_sent"])
        self.scan_rng.bit_generator.state = state["scan_rng"]

    def close(self) -> None:
        """Nothing to release: the simulated robots live in this process."""
