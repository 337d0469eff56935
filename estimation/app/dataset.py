"""A recorded dataset (docs/dataset.md), read: the mission, its event log, the robots' streams.

Per robot, the raw LMS bytes are decoded with the real parser; every dwell (all robots still)
yields one full sweep per robot — the mirror's motor rate and phase estimated from the arm and
edge-on signatures inside that dwell — converted to 3D points, in which the beacons are found
(:mod:`estimation.app.events` turns all this into the estimator's event stream).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from estimation.app.config import Config, ConfigError, config_from_mapping
from estimation.app.rig import beacon_parameters, mirror_geometry
from estimation.search.stations import Dwell, Station, View
from sensors.errors import SensorError
from sensors.lms200.capture import CaptureReader, CaptureStream
from sensors.lms200.decoder import ScanDecoder
from sensors.lms200.protocol.plausibility import ScanLimits
from sensors.lms200.protocol.scan import Scan
from sensors.lms200.protocol.telegram import BAUD_RATES
from sensors.scan3d.beacon import BeaconDetection, detect_beacons
from sensors.scan3d.mirror import Scan3D, ScanClock, assemble_sweeps, estimate_mirror
from sensors.trajio import read_tum
from sensors.yamlio import merge_mappings, read_text_file, read_yaml_mapping

__all__ = [
    "DWELL_SETTLE_S",
    "Dataset",
    "LmsDecoder",
    "RobotStream",
    "Sweep",
    "decode_dwells",
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
    "with_dwell_sweeps",
]

#: A dwell's sweep is taken from this long after the dwell began (the robot has settled).
DWELL_SETTLE_S = 0.2

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
    partial: str | None = None  # why the mission failed under way (partial.json), else None
    _odometry: dict[str, tuple[np.ndarray, np.ndarray]] = field(
        default_factory=dict, repr=False, compare=False
    )

    def odometry(self, robot: str) -> tuple[np.ndarray, np.ndarray]:
        """(stamps_s, poses (N, 3)) of ``robots/<robot>/odometry.tum``, read once per dataset
        (read-only arrays: several stages use them)."""
        cached = self._odometry.get(robot)
        if cached is None:
            stamps, poses = read_tum(self.path / "robots" / robot / "odometry.tum")
            stamps.flags.writeable = poses.flags.writeable = False
            cached = self._odometry[robot] = (stamps, poses)
        return cached

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
        robot: dataset.pose_stamps(robot, dataset.odometry(robot)[0]) for robot in dataset.robots
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
    return Dataset(path, config, robots, starts, events, mission, _partial(path / "partial.json"))


def _partial(note: Path) -> str | None:
    """The failure ``partial.json`` records (a mission that failed under way), or None."""
    if not note.exists():
        return None
    try:
        document = json.loads(read_text_file(note, ConfigError, 1 << 16))
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{note}: not JSON ({exc.msg}, line {exc.lineno})") from None
    failure = document.get("failure") if isinstance(document, dict) else None
    if not isinstance(failure, str):
        raise ConfigError(f"{note}: no failure (a string) recorded")
    return failure


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
    """One robot's 3D scan during one dwell, and the beacons found in it. Of the scan only its
    points are kept: each point's range, bearing, elevation, flags and time served the beacon
    detection and would be 60 % of the sweep's memory (office_loop: 55 MB)."""

    robot: str
    index: int
    dwell: int
    points_scanner: np.ndarray  # (N, 3)
    detections: list[BeaconDetection]

    def view(self) -> View:
        """The sweep as the station searches see it."""
        return View(self.robot, self.index, self.points_scanner, self.dwell)


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
    # The sweep (or why none) of each dwell, by its number in the event log, made while the
    # scans were at hand (:func:`with_dwell_sweeps`); a dwell not in it is made from the scans.
    dwell_sweeps: dict[int, tuple[Scan3D | None, str | None]] = field(default_factory=dict)
    # The beacons found in each of those sweeps, found as it was made (in the decoding's job).
    dwell_beacons: dict[int, list[BeaconDetection]] = field(default_factory=dict)

    @property
    def implausible_scans(self) -> int:
        return sum(self.implausible.values())

    def sweep_of(self, number: int, entry: dict[str, Any],
                 config: Config) -> tuple[Scan3D | None, str | None]:  # fmt: skip
        """The sweep of dwell ``number`` (its event-log ``entry``), or why there is none."""
        made = self.dwell_sweeps.get(number)
        if made is not None:
            return made
        return sweep_in(self, float(entry["t_s"]) + DWELL_SETTLE_S, float(entry["end_s"]), config)


class LmsDecoder:
    """One robot's LMS byte stream decoded as it arrives: measured-value telegrams become scans
    with measurement times (:class:`~sensors.scan3d.mirror.ScanClock`); ``stream()`` is the
    :class:`RobotStream` of everything so far, the same as :func:`decode_robot` of the same
    bytes (both run :class:`~sensors.lms200.decoder.ScanDecoder`)."""

    def __init__(self, measuring_mode: int, limits: ScanLimits | None = None,
                 header: dict[str, Any] | None = None) -> None:  # fmt: skip
        self.measuring_mode = measuring_mode
        if limits is not None:
            baud = (header or {}).get("baud_rate")
            limits = replace(limits, baud_rate=int(baud)) if baud in BAUD_RATES else limits
        self.decoder = ScanDecoder(measuring_mode, limits)
        self.scans: list[Scan] = []
        self.clock = ScanClock()

    @property
    def decoded(self) -> int:
        return self.decoder.stats.decoded

    @property
    def undecodable(self) -> int:
        return self.decoder.stats.undecodable

    def feed(self, stamp: float | None, chunk: bytes) -> int:
        """Parse one received chunk; returns how many scans it completed."""
        return self._add(self.decoder.feed(chunk, stamp))

    def feed_chunks(self, chunks: Sequence[tuple[float | None, bytes]]) -> int:
        """Received chunks (stamp, bytes) at once: the same as feeding them one by one."""
        return self._add(self.decoder.feed_chunks(chunks))

    def feed_stream(self, stream: CaptureStream) -> int:
        """A whole capture at once: the same as feeding its records one by one."""
        return self._add(self.decoder.feed_stream(stream))

    def close(self) -> None:
        self._add(self.decoder.close())

    def _add(self, scans: list[Scan]) -> int:
        self.scans += scans
        self.clock.extend(scans)
        return len(scans)

    @property
    def implausible(self) -> dict[str, int]:
        check = self.decoder.check
        return dict(check.rejected) if check is not None else {}

    def stream(self, truncated_bytes: int = 0, corrupt_bytes: int = 0) -> RobotStream:
        stats = self.decoder.stats
        return RobotStream(
            scans=list(self.scans),  # a snapshot: the decoder goes on appending
            times_s=self.clock.times(),
            telegrams=stats.telegrams,
            undecodable=stats.undecodable,
            checksum_failures=stats.checksum_failures,
            bytes_skipped=stats.bytes_skipped,
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
    decoder.feed_stream(reader.stream())
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


def with_dwell_sweeps(stream: RobotStream, events: list[dict[str, Any]],
                      config: Config) -> RobotStream:  # fmt: skip
    """``stream`` holding the sweep of every dwell of the event log, and the beacons found in
    it, instead of its scans: what the estimator takes of a decoded capture (office_loop, per
    robot: 75 sweeps of points and reflector marks (:meth:`~sensors.scan3d.mirror.Scan3D.trimmed`),
    21 MB, instead of 38,000 scans, 130 MB). ``sweep_of`` gives the same sweeps, trimmed, as
    from the scans; the beacons are those the event stream would find in them."""
    sweeps, beacons, params = {}, {}, beacon_parameters(config)
    for n, entry in enumerate(events):
        if entry["event"] == "dwell":
            sweep, why = stream.sweep_of(n, entry, config)
            sweeps[n] = (None if sweep is None else sweep.trimmed(), why)
            if sweep is not None:
                beacons[n] = detect_beacons(sweep.points_scanner, sweep.reflector, **params)[0]
    return replace(stream, scans=[], times_s=stream.times_s[:0], dwell_sweeps=sweeps,
                   dwell_beacons=beacons)  # fmt: skip


def decode_dwells(
    capture: Path,
    measuring_mode: int,
    limits: ScanLimits | None,
    events: list[dict[str, Any]],
    config: Config,
) -> tuple[RobotStream, float, float]:
    """:func:`decode_robot`, then :func:`with_dwell_sweeps`: one robot's capture as the
    estimator keeps it, and the seconds each took (a worker process's job: it sends back the
    sweeps, not the scans)."""
    clock = time.perf_counter()
    decoded = decode_robot(capture, measuring_mode, limits)
    decoded_s = time.perf_counter() - clock
    stream = with_dwell_sweeps(decoded, events, config)
    return stream, decoded_s, time.perf_counter() - clock - decoded_s


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


def next_map_seconds(entries: list[dict[str, Any]]) -> dict[str, float | None]:
    """Per reference station of a mission's event log (``entries``): how long (mission time)
    the next local map took to make — the time its concurrent global localization had; None
    for the last station."""
    starts = [
        (f"{s['reference']}{s['poses'][s['reference']]}", float(s["t_s"]))
        for s in entries
        if s["event"] == "dwell" and s.get("reference") and s.get("phase") != "relocalize"
    ]
    order: list[tuple[str, float]] = []
    for label, t in starts:
        if not order or order[-1][0] != label:
            order.append((label, t))
    end = float(entries[-1].get("end_s", entries[-1]["t_s"])) if entries else 0.0
    out: dict[str, float | None] = {}
    for n, (label, _) in enumerate(order):
        if n + 1 == len(order):
            out[label] = None  # no local map was made after the last station's
            continue
        finish = order[n + 2][1] if n + 2 < len(order) else end
        out[label] = finish - order[n + 1][1]
    return out
