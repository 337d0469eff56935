"""A recorded dataset (docs/dataset.md), read and turned into the estimator's event stream.

Per robot, the raw LMS bytes are decoded with the real parser; every dwell (all robots still)
yields one full sweep per robot — the mirror's motor rate and phase estimated from the arm and
edge-on signatures inside that dwell — converted to 3D points, in which the beacons are found.
The dataset's event log becomes the estimator's event stream: a gauge prior on the first robot's
start, odometry between each robot's stops, and the mutual observations of every dwell between
its reference and mapper (gated by s1/s2 in the graph builder).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from estimation.app.config import Config, ConfigError, config_from_mapping
from estimation.app.rig import T_robot_scanner, beacon_parameters, graph_settings, mirror_geometry
from estimation.posegraph.events import Event, Move, Observe, Start
from estimation.posegraph.graph import GraphBuilder
from estimation.posegraph.keys import pose_key
from estimation.search.stations import Dwell, Station, View
from sensors.errors import SensorError
from sensors.geometry import se2
from sensors.geometry.frames import pose2_matrix
from sensors.lms200.capture import CaptureReader
from sensors.lms200.protocol.plausibility import ScanCheck, ScanLimits
from sensors.lms200.protocol.scan import Scan, decode_scan
from sensors.lms200.protocol.stream import StreamParser, Telegram
from sensors.lms200.protocol.telegram import BAUD_RATES, ProtocolError
from sensors.scan3d.beacon import BeaconDetection, detect_beacons
from sensors.scan3d.mirror import Scan3D, ScanClock, assemble_sweeps, estimate_mirror
from sensors.trajio import read_tum
from sensors.yamlio import merge_mappings, read_text_file, read_yaml_mapping

__all__ = [
    "Counts",
    "Dataset",
    "EventMaker",
    "EventStream",
    "LmsDecoder",
    "RobotStream",
    "Sweep",
    "build_events",
    "decode_robot",
    "load_dataset",
    "mapping_sweeps",
    "parse_event",
    "read_pose_stamps",
    "read_robots",
    "relocalization_dwells",
    "stations",
    "stations_of",
    "sweep_in",
    "sweeps_before_changes",
]

Progress = Callable[[str], None]
#: events.jsonl of a very long mission (a line per move and dwell) stays far below this.
EVENTS_LIMIT_BYTES = 256 * 2**20
#: A pose is stamped at least this long after the robot arrived (docs/results.md).
SETTLE_S = 0.5


@dataclass(frozen=True)
class Dataset:
    """A recorded mission (docs/dataset.md), as read from its folder."""

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

    def pose_stamps(self, robot: str, odometry_stamps_s: np.ndarray) -> dict[int, float]:
        """The instant each pose index of ``robot`` is stamped with (``poses/<robot>.tum``).

        The robot stands still from its arrival until it next departs, so its pose holds at any
        instant in between: the stamp is the first odometry sample at least ``SETTLE_S`` after
        the arrival, or arrival + ``SETTLE_S`` when no sample comes before the departure. On
        the odometry's grid, trajectory tools associate the pose with samples logged at the
        odometry's instants (the simulator's ground truth shares them) without a tolerance.
        """
        stamps = np.sort(np.asarray(odometry_stamps_s, dtype=float))
        departures = {
            int(e["from_index"]): float(e["start_s"])
            for e in self.events
            if e["event"] == "move" and e["robot"] == robot
        }
        out = {}
        for index, arrived in self.stop_times(robot).items():
            wanted = arrived + SETTLE_S
            leaves = departures.get(index, math.inf)
            # A microsecond of slack: odometry logs keep 6 decimals.
            k = int(np.searchsorted(stamps, wanted - 1e-6))
            if k < len(stamps) and stamps[k] < leaves:
                out[index] = float(stamps[k])
            else:
                out[index] = wanted if wanted < leaves else arrived
        return out


def read_pose_stamps(dataset: Dataset) -> dict[str, dict[int, float]]:
    """Every robot's pose stamps (:meth:`Dataset.pose_stamps`) from its ``odometry.tum``."""
    return {
        robot: dataset.pose_stamps(
            robot, read_tum(dataset.path / "robots" / robot / "odometry.tum")[0]
        )
        for robot in dataset.robots
    }


def load_dataset(path: Path | str, overrides: dict[str, Any] | None = None) -> Dataset:
    """Read ``mission.yaml`` and ``events.jsonl``; the effective config is the mission's, with
    ``overrides`` merged over it."""
    path = Path(path)
    mission_file = path / "mission.yaml"
    events_file = path / "events.jsonl"
    for needed in (mission_file, events_file):
        if not needed.exists():  # a FIFO or a folder in its place is refused when it is read
            raise ConfigError(f"{path}: not a coopmap dataset ({needed.name} is missing)")
    mission = read_yaml_mapping(mission_file, ConfigError)
    if "robots" not in mission:
        raise ConfigError(f"{mission_file}: not a mission (no robots)")
    robots, starts = read_robots(mission["robots"], mission_file)
    config_doc = mission.get("config") or {}
    if not isinstance(config_doc, dict):
        raise ConfigError(f"{mission_file}: config: must be a mapping")
    merged = merge_mappings(config_doc, overrides or {})
    config = config_from_mapping(merged, source=str(mission_file))
    events = []
    text = read_text_file(events_file, ConfigError, EVENTS_LIMIT_BYTES)
    for number, line in enumerate(text.splitlines(), 1):
        if line.strip():
            events.append(parse_event(line, robots, f"{events_file}:{number}"))
    return Dataset(path, config, robots, starts, events, mission)


def parse_event(line: str, robots: list[str], where: str) -> dict[str, Any]:
    """One line of ``events.jsonl``, checked for the fields ``build_events`` reads."""
    try:
        event = json.loads(line)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{where}: not JSON: {exc.msg}") from None
    except RecursionError:
        raise ConfigError(f"{where}: not an event: JSON nested too deeply") from None
    if not isinstance(event, dict) or "event" not in event or "t_s" not in event:
        raise ConfigError(f"{where}: an event needs 'event' and 't_s'")
    _check_event(event, robots, where)
    return event


def read_robots(entries: Any, source: Path | str) -> tuple[list[str], dict[str, np.ndarray]]:
    """The mission's robot names (one lowercase letter each, unique) and start poses."""
    if not isinstance(entries, list) or len(entries) < 1:
        raise ConfigError(f"{source}: robots: must be a list of {{name, start}}")
    robots: list[str] = []
    starts: dict[str, np.ndarray] = {}
    for n, entry in enumerate(entries):
        where = f"{source}: robots[{n}]"
        if not isinstance(entry, dict):
            raise ConfigError(f"{where}: must be a mapping with name and start")
        name = entry.get("name")
        if not (isinstance(name, str) and len(name) == 1 and "a" <= name <= "z"):
            raise ConfigError(f"{where}: name must be one lowercase letter a-z, got {name!r}")
        if name in starts:
            raise ConfigError(f"{where}: robot {name!r} is listed twice")
        start = entry.get("start")
        if not (isinstance(start, list) and len(start) == 3 and all(_finite(v) for v in start)):
            raise ConfigError(f"{where}: start must be [x_m, y_m, yaw_deg], got {start!r}")
        robots.append(name)
        starts[name] = np.array([start[0], start[1], math.radians(start[2])], dtype=float)
    return robots, starts


def _finite(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _is_index(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _check_event(event: dict[str, Any], robots: list[str], where: str) -> None:
    """The fields ``build_events`` reads, with their types (docs/dataset.md)."""
    kind = event["event"]
    if not _finite(event["t_s"]):
        raise ConfigError(f"{where}: t_s must be a finite number, got {event['t_s']!r}")
    if kind == "move":
        robot = event.get("robot")
        if robot not in robots:
            raise ConfigError(f"{where}: move of robot {robot!r}, not one of the mission's robots")
        for key in ("from_index", "to_index"):
            if not _is_index(event.get(key)):
                raise ConfigError(
                    f"{where}: move: {key} must be an index >= 0, got {event.get(key)!r}"
                )
        if event["to_index"] != event["from_index"] + 1:
            raise ConfigError(f"{where}: move: to_index must be from_index + 1")
        if not _finite(event.get("start_s")) or event["start_s"] > event["t_s"]:
            raise ConfigError(f"{where}: move: start_s must be a number <= t_s")
    elif kind == "dwell":
        if not _finite(event.get("end_s")) or event["end_s"] < event["t_s"]:
            raise ConfigError(f"{where}: dwell: end_s must be a number >= t_s")
        poses = event.get("poses")
        if not isinstance(poses, dict) or sorted(poses) != sorted(robots):
            raise ConfigError(
                f"{where}: dwell: poses must give the pose index of every robot "
                f"({', '.join(robots)}), got {poses!r}"
            )
        for robot, index in poses.items():
            if not _is_index(index):
                raise ConfigError(f"{where}: dwell: poses.{robot} must be an index >= 0")
        for role in ("reference", "mapper"):
            if event.get(role) is not None and event[role] not in robots:
                raise ConfigError(
                    f"{where}: dwell: {role} {event[role]!r} is not one of the mission's robots"
                )


@dataclass
class Sweep:
    """One robot's 3D scan during one dwell, and the beacons found in it."""

    robot: str
    index: int
    dwell: int
    scan: Scan3D
    detections: list[BeaconDetection]

    def view(self) -> View:
        """The sweep as the station searches see it."""
        return View(self.robot, self.index, self.scan.points_scanner)


@dataclass
class RobotStream:
    scans: list[Scan]
    times_s: np.ndarray
    telegrams: int = 0
    undecodable: int = 0
    checksum_failures: int = 0
    bytes_skipped: int = 0
    truncated_bytes: int = 0
    corrupt_bytes: int = 0  # records lost to damaged record headers (the capture resynchronised)
    implausible: dict[str, int] = field(default_factory=dict)  # scans rejected, by reason

    @property
    def implausible_scans(self) -> int:
        return sum(self.implausible.values())


class LmsDecoder:
    """One robot's LMS byte stream decoded as it arrives: measured-value telegrams become scans
    with measurement times (:class:`~sensors.scan3d.mirror.ScanClock`); ``stream()`` is the
    :class:`RobotStream` of everything so far, the same as :func:`decode_robot` of the same
    bytes."""

    def __init__(self, measuring_mode: int, limits: ScanLimits | None = None,
                 header: dict[str, Any] | None = None) -> None:  # fmt: skip
        self.measuring_mode = measuring_mode
        self.parser = StreamParser()
        self.check: ScanCheck | None = None
        if limits is not None:
            baud = (header or {}).get("baud_rate")
            self.check = ScanCheck(
                replace(limits, baud_rate=int(baud)) if baud in BAUD_RATES else limits
            )
        self.scans: list[Scan] = []
        self.clock = ScanClock()
        self.decoded = self.undecodable = 0
        self.last_stamp: float | None = None

    def feed(self, stamp: float | None, chunk: bytes) -> int:
        """Parse one received chunk; returns how many scans it completed."""
        before = len(self.scans)
        self.last_stamp = stamp
        for event in self.parser.feed(chunk, stamp):
            if isinstance(event, Telegram) and event.code == 0xB0:
                try:
                    scan = decode_scan(event, self.measuring_mode)
                except ProtocolError:
                    self.undecodable += 1
                    continue
                self.decoded += 1
                if scan.stamp_s is not None and (
                    self.check is None or self.check.check(scan) is None
                ):
                    self.scans.append(scan)
                    self.clock.add(scan)
        return len(self.scans) - before

    def close(self) -> None:
        self.parser.close(self.last_stamp)

    @property
    def implausible(self) -> dict[str, int]:
        return dict(self.check.rejected) if self.check is not None else {}

    def stream(self, truncated_bytes: int = 0, corrupt_bytes: int = 0) -> RobotStream:
        return RobotStream(
            scans=self.scans,
            times_s=self.clock.times(),
            telegrams=self.parser.stats.telegrams,
            undecodable=self.undecodable,
            checksum_failures=self.parser.stats.checksum_failures,
            bytes_skipped=self.parser.stats.bytes_skipped,
            truncated_bytes=truncated_bytes,
            corrupt_bytes=corrupt_bytes,
            implausible=self.implausible,
        )


def decode_robot(
    capture: Path, measuring_mode: int, limits: ScanLimits | None = None
) -> RobotStream:
    """Every measured-value telegram of a capture, decoded, with its measurement time.

    With ``limits`` (the configured variant, unit and baud rate), scans that passed the checksum
    but cannot come from that sensor are dropped and counted by reason; the baud rate in the
    capture's header, when it has one, sets the telegram interval.
    """
    reader = CaptureReader(capture)
    decoder = LmsDecoder(measuring_mode, limits, reader.header)
    for stamp, chunk in reader.chunks():
        decoder.feed(stamp, chunk)
    decoder.close()
    if not decoder.decoded:
        raise SensorError(f"{capture}: no measured values in the capture")
    implausible = decoder.implausible
    if not decoder.scans and implausible:
        raise SensorError(
            f"{capture}: all {decoder.decoded} scans are implausible for the configured scanner "
            f"({', '.join(f'{n} {why}' for why, n in sorted(implausible.items()))}): check "
            "scanner.field_of_view_deg, angular_resolution_deg, unit and serial.baud_rate"
        )
    return decoder.stream(reader.truncated_bytes, reader.corrupt_bytes)


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


def _pose_at(stamps: np.ndarray, poses: np.ndarray, t: float) -> np.ndarray:
    yaw = np.unwrap(poses[:, 2])
    return np.array(
        [
            np.interp(t, stamps, poses[:, 0]),
            np.interp(t, stamps, poses[:, 1]),
            np.interp(t, stamps, yaw),
        ]
    )


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
    """Range and bearing, in the observer's scanner frame, of the observed robot's beacon as the
    estimate so far places them (in the plane: heights do not enter range and bearing)."""
    guesses = builder.guesses
    if observer not in guesses or observed not in guesses:
        return None
    T_a = pose2_matrix(*guesses[observer]) @ T_robot_scanner(config, planar=True)
    beacon = pose2_matrix(*guesses[observed]) @ np.array(
        [config.robot.scanner_x_m + config.beacon.offset_m, 0, 0, 1]
    )
    local = np.linalg.inv(T_a) @ beacon
    return float(math.hypot(local[0], local[1])), float(math.atan2(local[1], local[0]))


@dataclass(frozen=True)
class Counts:
    """What the event stream made of the dataset's dwells."""

    dwells: int
    observations: int
    missing_sweeps: tuple[str, ...]  # "a3 (dwell 7): why"
    unseen: tuple[str, ...]  # "a3–b4": a pair whose beacons were not both found
    moves_before_first_fix: int  # odometry held back until its robot was anchored


@dataclass(frozen=True)
class EventStream:
    """The estimator's event stream of a dataset, the sweeps, the counts, and the graph builder
    that consumed the events (its guesses are the estimate so far)."""

    events: list[Event]
    sweeps: list[Sweep]
    counts: Counts
    builder: GraphBuilder


class EventMaker:
    """The estimator's event stream of a mission, made one dataset event (an ``events.jsonl``
    entry) at a time, as :func:`build_events` reads a recorded mission and the mission loop
    runs a live one. A builder consumes the events as they are made, so that each observation
    can be matched to the beacon predicted by the estimate so far.

    ``odometry`` maps each robot to its odometry so far (stamps, poses); a move is fed once the
    odometry covers its end. ``streams`` (each robot's decoded LMS stream so far) are passed to
    :meth:`feed`, since they grow."""

    def __init__(self, config: Config, robots: list[str], starts: dict[str, np.ndarray],
                 odometry: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:  # fmt: skip
        self.config, self.robots, self.odometry = config, robots, odometry
        self.builder = GraphBuilder(graph_settings(config))
        self.params = beacon_parameters(config)
        self.events: list[Event] = []
        self.sweeps: list[Sweep] = []
        self.dwells = self.observations = self.held_back = 0
        self.missing: list[str] = []
        self.unseen: list[str] = []
        # Odometry of a robot that moved before its first fix: (to_index, delta) per robot.
        self.pending: dict[str, list[Move]] = {}
        gauge = robots[0]
        self._emit(Start(gauge, 0, tuple(float(v) for v in starts[gauge])))  # type: ignore[arg-type]

    def _emit(self, event: Event) -> None:
        self.builder.add(event)
        self.events.append(event)

    def feed(
        self, number: int, entry: dict[str, Any], streams: dict[str, RobotStream]
    ) -> list[Event]:
        """Turn dataset event ``number`` into estimator events; returns the new ones."""
        before = len(self.events)
        kind = entry["event"]
        if kind == "move":
            self._move(entry)
        elif kind == "dwell":
            self._dwell(number, entry, streams)
        return self.events[before:]

    def _move(self, entry: dict[str, Any]) -> None:
        robot = entry["robot"]
        stamps, poses = self.odometry[robot]
        start_s, end_s = float(entry["start_s"]), float(entry["t_s"])
        before = _pose_at(stamps, poses, start_s)
        after = _pose_at(stamps, poses, end_s)
        dx, dy, dyaw = (float(v) for v in se2.between(before, after))
        step = Move(robot, int(entry["to_index"]), (dx, dy, dyaw),
                    _motion(stamps, poses, start_s, end_s, before, after))  # fmt: skip
        if pose_key(robot, int(entry["from_index"])) in self.builder.guesses:
            self._emit(step)
        else:
            self.held_back += 1
            self.pending.setdefault(robot, []).append(step)

    def _dwell(self, number: int, entry: dict[str, Any], streams: dict[str, RobotStream]) -> None:
        config, builder = self.config, self.builder
        self.dwells += 1
        start, end = float(entry["t_s"]), float(entry["end_s"])
        in_dwell: dict[str, Sweep] = {}
        for robot in self.robots:
            scan, why = sweep_in(streams[robot], start + 0.2, end, config)
            index = int(entry["poses"][robot])
            if scan is None:
                self.missing.append(f"{robot}{index} (dwell {number}): {why}")
                continue
            detections, _ = detect_beacons(scan.points_scanner, scan.reflector, **self.params)
            sweep = Sweep(robot, index, number, scan, detections)
            self.sweeps.append(sweep)
            in_dwell[robot] = sweep
        reference, mapper = entry.get("reference"), entry.get("mapper")
        if reference in in_dwell and mapper in in_dwell:
            ka = pose_key(reference, in_dwell[reference].index)
            kc = pose_key(mapper, in_dwell[mapper].index)
            seen_a = _choose(in_dwell[reference].detections, _predict(builder, ka, kc, config))
            seen_c = _choose(in_dwell[mapper].detections, _predict(builder, kc, ka, config))
            if seen_a is None or seen_c is None:
                self.unseen.append(
                    f"{reference}{in_dwell[reference].index}–{mapper}{in_dwell[mapper].index}"
                )
            elif ka in builder.guesses or kc in builder.guesses:
                observer = (reference, in_dwell[reference].index)
                observed = (mapper, in_dwell[mapper].index)
                self._emit(
                    Observe(
                        observer, observed,
                        seen_a.range_m, seen_a.bearing_rad, seen_c.range_m, seen_c.bearing_rad,
                    )
                )  # fmt: skip
                self.observations += 1
                _flush_pending(self.pending, builder, self._emit)

    def counts(self) -> Counts:
        return Counts(self.dwells, self.observations, tuple(self.missing), tuple(self.unseen),
                      self.held_back)  # fmt: skip

    def result(self) -> EventStream:
        return EventStream(self.events, self.sweeps, self.counts(), self.builder)


def build_events(
    dataset: Dataset,
    streams: dict[str, RobotStream],
    progress: Progress | None = None,
) -> EventStream:
    """The estimator's event stream of a dataset, the sweeps, and the counts of what failed
    (:class:`EventMaker` over the dataset's event log)."""
    odometry = {r: read_tum(dataset.path / "robots" / r / "odometry.tum") for r in dataset.robots}
    maker = EventMaker(dataset.config, dataset.robots, dataset.starts, odometry)
    for number, entry in enumerate(dataset.events):
        maker.feed(number, entry, streams)
        if progress is not None:
            progress(f"event {number + 1}/{len(dataset.events)}")
    return maker.result()


def _motion(stamps: np.ndarray, poses: np.ndarray, start_s: float, end_s: float,
            before: np.ndarray, after: np.ndarray) -> tuple[float, float]:  # fmt: skip
    """How far the odometry says the robot drove and how much it turned between two instants
    (the samples in between, and the poses at both ends)."""
    inside = (stamps > start_s) & (stamps < end_s)
    track = np.vstack([before, poses[inside], after])
    driven = float(np.hypot(*np.diff(track[:, :2], axis=0).T).sum())
    turned = float(np.abs(np.angle(np.exp(1j * np.diff(track[:, 2])))).sum())
    return driven, turned


def _flush_pending(
    pending: dict[str, list[Move]],
    builder: GraphBuilder,
    emit: Callable[[Event], None],
) -> None:
    """Odometry of a robot that moved before its first fix joins once it is anchored."""
    for robot, moves in list(pending.items()):
        while moves and pose_key(robot, moves[0].index - 1) in builder.guesses:
            step = moves.pop(0)
            if pose_key(robot, step.index) not in builder.guesses:
                emit(step)
        if not moves:
            del pending[robot]


def _relocalization_numbers(events: list[dict[str, Any]]) -> set[int]:
    return {n for n, e in enumerate(events)
            if e["event"] == "dwell" and e.get("phase") == "relocalize"}  # fmt: skip


def mapping_sweeps(dataset: Dataset, sweeps: list[Sweep]) -> list[Sweep]:
    """The sweeps of the mapping: not those taken after the world changed."""
    return sweeps_before_changes(dataset.events, sweeps)


def sweeps_before_changes(events: list[dict[str, Any]], sweeps: list[Sweep]) -> list[Sweep]:
    """:func:`mapping_sweeps` of a mission's event entries (so far)."""
    after = _relocalization_numbers(events)
    return [s for s in sweeps if s.dwell not in after]


def stations(dataset: Dataset, sweeps: list[Sweep]) -> list[Station]:
    """Every reference station of the mapping with the sweeps of its dwells, in time order."""
    return stations_of(dataset.events, sweeps)


def stations_of(events: list[dict[str, Any]], sweeps: list[Sweep]) -> list[Station]:
    """:func:`stations` of a mission's event entries (so far)."""
    by_dwell: dict[int, list[Sweep]] = {}
    for sweep in sweeps:
        by_dwell.setdefault(sweep.dwell, []).append(sweep)
    found: dict[tuple[str, int], tuple[float, list[Sweep]]] = {}
    for number, event in enumerate(events):
        if (
            event["event"] != "dwell"
            or event.get("phase") == "relocalize"
            or not event.get("reference")
        ):
            continue
        reference = event["reference"]
        key = (reference, int(event["poses"][reference]))
        t, taken = found.get(key, (float(event["t_s"]), []))
        found[key] = (t, taken + by_dwell.get(number, []))
    ordered = sorted(found.items(), key=lambda kv: kv[1][0])
    return [Station(r, i, t, tuple(s.view() for s in taken)) for (r, i), (t, taken) in ordered]


def relocalization_dwells(dataset: Dataset, sweeps: list[Sweep]) -> list[Dwell]:
    """The dwells after the world changed, each with every robot's sweep in it."""
    return [
        Dwell(float(dataset.events[n]["t_s"]), tuple(s.view() for s in sweeps if s.dwell == n))
        for n in sorted(_relocalization_numbers(dataset.events))
    ]
