"""Every problem of a dataset folder at once (``coopmap dataset check``; docs/dataset.md).

``load_dataset`` stops at the first problem, as a run must. A user preparing a real mission wants
the whole list: this module runs the same per-file and per-line checks, keeps going after each
failure, and adds the checks that need the robots' files (captures, odometry coverage of the
moves, pose indices following the moves, a sweep in every dwell). Errors make ``batch`` fail or
compute something wrong; warnings are what ``batch`` would report and work around.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from estimation.app.config import Config, ConfigError, config_from_mapping
from estimation.app.dataset import (
    DWELL_SETTLE_S,
    EVENTS_LIMIT_BYTES,
    decode_robot,
    parse_event,
    read_robots,
    sweep_in,
)
from estimation.app.rig import scan_limits
from estimation.errors import EstimationError
from mapping.errors import MapError
from sensors.errors import SensorError
from sensors.lms200.capture import CaptureReader
from sensors.trajio import read_tum
from sensors.yamlio import read_text_file, read_yaml_mapping

__all__ = ["DatasetCheck", "Problem", "check_dataset"]

_KNOWN = (ConfigError, SensorError, MapError, EstimationError, OSError)
Progress = Callable[[str], None]


@dataclass(frozen=True)
class Problem:
    level: Literal["error", "warning"]
    where: str  # file (relative to the dataset), with ':line' for events
    message: str

    def line(self) -> str:
        return f"{self.level}: {self.where}: {self.message}"


@dataclass
class DatasetCheck:
    path: Path
    problems: list[Problem] = field(default_factory=list)
    robots: list[str] = field(default_factory=list)
    events: int = 0
    dwells: int = 0
    sweeps: int = 0

    @property
    def errors(self) -> int:
        return sum(p.level == "error" for p in self.problems)

    @property
    def warnings(self) -> int:
        return sum(p.level == "warning" for p in self.problems)

    def add(self, level: Literal["error", "warning"], where: str, message: str) -> None:
        self.problems.append(Problem(level, where, message))

    def as_dict(self) -> dict[str, Any]:
        return {
            "dataset": str(self.path),
            "errors": self.errors,
            "warnings": self.warnings,
            "robots": self.robots,
            "events": self.events,
            "dwells": self.dwells,
            "sweeps": self.sweeps,
            "problems": [p.__dict__ for p in self.problems],
        }


def _failed(check: DatasetCheck, where: str, exc: BaseException, file: Path | str) -> None:
    """An error raised while reading ``file``, as a problem of ``where`` (its line kept)."""
    if isinstance(exc, OSError) and exc.strerror:
        check.add("error", where, exc.strerror.lower())
        return
    text = str(exc) or type(exc).__name__
    prefix = str(file)
    if text.startswith(prefix + ":"):
        text = text[len(prefix) + 1 :].lstrip()
        line, _, rest = text.partition(": ")
        if line.isdigit() and rest:
            where, text = f"{where}:{line}", rest
    check.add("error", where, text)


def check_dataset(
    path: Path | str, *, decode: bool = True, progress: Progress | None = None
) -> DatasetCheck:
    """Check a dataset folder; with ``decode``, also decode every capture and cut every sweep."""
    path = Path(path)
    check = DatasetCheck(path)
    if not path.is_dir():
        check.add("error", str(path), "not a folder")
        return check
    config, robots = _check_mission(path, check)
    events = _check_events(path, robots, check)
    if robots is None:
        return check
    check.robots = robots
    odometry = _check_robot_files(path, robots, check)
    _check_indices(events, robots, check)
    _check_coverage(events, odometry, check)
    for name in ("world.yaml", "world_changed.yaml"):
        _check_world(path, name, check)
    if decode and config is not None and check.errors == 0:
        _check_sweeps(path, config, robots, events, check, progress)
    return check


def _check_mission(path: Path, check: DatasetCheck) -> tuple[Config | None, list[str] | None]:
    where = "mission.yaml"
    file = path / where
    if not file.exists():
        check.add("error", where, "missing (required)")
        return None, None
    try:
        mission = read_yaml_mapping(file, ConfigError)
    except _KNOWN as exc:
        _failed(check, where, exc, str(file))
        return None, None
    robots: list[str] | None = None
    if "robots" not in mission:
        check.add("error", where, "robots: required key is missing")
    else:
        try:
            robots, _ = read_robots(mission["robots"], where)
        except ConfigError as exc:
            _failed(check, where, exc, where)
    doc = mission.get("config") or {}
    if not isinstance(doc, dict):
        check.add("error", where, "config: must be a mapping")
        return None, robots
    try:
        config = config_from_mapping(doc, source=where)
    except ConfigError as exc:
        _failed(check, where, exc, where)
        return None, robots
    return config, robots


def _check_events(
    path: Path, robots: list[str] | None, check: DatasetCheck
) -> list[tuple[int, dict[str, Any]]]:
    where = "events.jsonl"
    file = path / where
    if not file.exists():
        check.add("error", where, "missing (required)")
        return []
    try:
        text = read_text_file(file, ConfigError, EVENTS_LIMIT_BYTES)
    except _KNOWN as exc:
        _failed(check, where, exc, str(file))
        return []
    events: list[tuple[int, dict[str, Any]]] = []
    last_t = -math.inf
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        here = f"{where}:{number}"
        try:
            event = parse_event(line, robots or [], here)
        except ConfigError as exc:
            # Without the mission's robots only the line's own shape can be judged.
            message = str(exc).removeprefix(here + ": ")
            if robots is not None or "robot" not in message:
                check.add("error", here, message)
            continue
        check.events += 1
        check.dwells += event["event"] == "dwell"
        if event["t_s"] < last_t:
            check.add(
                "error", here, f"t_s {event['t_s']} goes back (previous event at {last_t}); "
                "events are processed in file order"
            )  # fmt: skip
        last_t = max(last_t, event["t_s"])
        if event["event"] == "dwell":
            ref, mapper = event.get("reference"), event.get("mapper")
            if ref is not None and ref == mapper:
                check.add("error", here, f"dwell: reference and mapper are both {ref!r}")
            elif (ref is None) != (mapper is None):
                check.add("warning", here, "dwell: a reference without a mapper (or the other "
                          "way round) gives no mutual observation")  # fmt: skip
        events.append((number, event))
    if check.dwells == 0 and check.errors == 0:
        check.add("error", where, "no dwell: nothing to map")
    return events


def _check_robot_files(
    path: Path, robots: list[str], check: DatasetCheck
) -> dict[str, tuple[float, float]]:
    """Each robot's capture and odometry; returns the time span of each readable odometry."""
    spans: dict[str, tuple[float, float]] = {}
    for robot in robots:
        cap = f"robots/{robot}/lms.cap"
        try:
            reader = CaptureReader(path / cap)
            if not reader.is_capture:
                check.add("error", cap, "a plain binary dump (no capture header): a mission "
                          "needs receive stamps (docs/dataset.md)")  # fmt: skip
        except _KNOWN as exc:
            _failed(check, cap, exc, str(path / cap))
        odo = f"robots/{robot}/odometry.tum"
        try:
            stamps, _ = read_tum(path / odo)
            spans[robot] = (float(stamps[0]), float(stamps[-1]))
        except _KNOWN as exc:
            _failed(check, odo, exc, str(path / odo))
        truth = path / "ground_truth" / f"{robot}.tum"
        if truth.exists():
            try:
                read_tum(truth)
            except _KNOWN as exc:
                _failed(check, f"ground_truth/{robot}.tum", exc, str(truth))
    return spans


def _check_indices(
    events: list[tuple[int, dict[str, Any]]], robots: list[str], check: DatasetCheck
) -> None:
    """Pose indices follow the moves: +1 per move, and every dwell names the current ones."""
    current = dict.fromkeys(robots, 0)
    for number, event in events:
        here = f"events.jsonl:{number}"
        if event["event"] == "move":
            robot = event["robot"]
            if event["from_index"] != current[robot]:
                check.add(
                    "error", here, f"move of {robot} from pose {event['from_index']}, but "
                    f"{robot} is at pose {current[robot]}"
                )  # fmt: skip
                current[robot] += 1  # one move all the same: later lines are judged alone
            else:
                current[robot] = event["to_index"]
        elif event["event"] == "dwell":
            wrong = [f"{r}: {i} (at {current[r]})" for r, i in event["poses"].items()
                     if i != current[r]]  # fmt: skip
            if wrong:
                check.add(
                    "error", here, "dwell: poses do not follow the moves: " + ", ".join(wrong)
                )


def _check_coverage(
    events: list[tuple[int, dict[str, Any]]],
    spans: dict[str, tuple[float, float]],
    check: DatasetCheck,
) -> None:
    """A move's odometry is interpolated at its start and arrival; outside the file it clamps."""
    for number, event in events:
        if event["event"] != "move" or event["robot"] not in spans:
            continue
        first, last = spans[event["robot"]]
        outside = [t for t in (event["start_s"], event["t_s"]) if not first <= t <= last]
        if outside:
            check.add(
                "error", f"events.jsonl:{number}", f"move of {event['robot']} at "
                f"{', '.join(f'{t:g}' for t in outside)} s lies outside its odometry "
                f"({first:g}–{last:g} s)"
            )  # fmt: skip


def _check_world(path: Path, name: str, check: DatasetCheck) -> None:
    file = path / name
    if not file.exists():
        return
    from sensors.sim.world import load_world

    try:
        load_world(file)
    except _KNOWN as exc:
        _failed(check, name, exc, str(file))


def _check_sweeps(
    path: Path,
    config: Config,
    robots: list[str],
    events: list[tuple[int, dict[str, Any]]],
    check: DatasetCheck,
    progress: Progress | None,
) -> None:
    """Decode each capture and cut the sweep of every dwell, as batch will."""
    streams = {}
    for robot in robots:
        cap = f"robots/{robot}/lms.cap"
        if progress is not None:
            progress(f"decoding {cap}")
        try:
            stream = decode_robot(path / cap, config.scanner.measuring_mode, scan_limits(config))
        except _KNOWN as exc:
            _failed(check, cap, exc, str(path / cap))
            continue
        streams[robot] = stream
        damage = {
            "bytes of records with damaged headers": stream.corrupt_bytes,
            "checksum failures": stream.checksum_failures,
            "undecodable telegrams": stream.undecodable,
            "bytes skipped": stream.bytes_skipped,
            "bytes of a truncated last record": stream.truncated_bytes,
            "implausible scans": stream.implausible_scans,
        }
        found = [f"{n:,} {what}" for what, n in damage.items() if n]
        if found:
            check.add("warning", cap, ", ".join(found) + f" ({len(stream.scans):,} scans kept)")
    for number, event in events:
        if event["event"] != "dwell":
            continue
        for robot, stream in streams.items():
            scan, why = sweep_in(stream, event["t_s"] + DWELL_SETTLE_S, event["end_s"], config)
            if scan is None:
                check.add("warning", f"events.jsonl:{number}", f"dwell: robot {robot}: no sweep "
                          f"({why})")  # fmt: skip
            else:
                check.sweeps += 1
    if streams and len(streams) == len(robots) and check.sweeps == 0:
        check.add("error", "events.jsonl", "no dwell yields a sweep: batch has nothing to map")
