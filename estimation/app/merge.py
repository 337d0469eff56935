"""``coopmap dataset merge``: robots' recordings → one mission dataset (docs/recording.md).

Each recording's local stamps go to the reference clock through its clock mapping, then to the
mission clock (0 at the mission start): LMS capture stamps, odometry stamps (unless they are on
the reference clock already) and operator events. Events of all recordings are merged: the same
event seen by several robots is kept once (within ``tolerance_s``), dwells that overlap in time
are one dwell whose poses are the union of what each robot logged, and everything is ordered in
time. The result is validated with ``load_dataset`` before it replaces ``--out``; clock.json
beside mission.yaml keeps each robot's mapping and the mission start.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from estimation import __version__
from estimation.app.config import ConfigError
from estimation.app.dataset import load_dataset
from sensors.atomic import check_replaceable, replace_directory, write_text_atomic
from sensors.errors import RecordingError, SensorError
from sensors.lms200.capture import CaptureReader, CaptureWriter
from sensors.recording.clock import ClockMapping
from sensors.recording.folder import Recording, read_recording
from sensors.trajio import read_tum, write_tum
from sensors.yamlio import merge_mappings, read_yaml_mapping

__all__ = ["MergeResult", "merge_events", "merge_recordings"]

#: Order of events at the same time: starts, then roles and changes, then moves, then dwells.
_PRIORITY = {"start": 0, "roles": 1, "changes": 2, "move": 3, "dwell": 4}
_TIMES = ("t_s", "start_s", "end_s")


@dataclass(frozen=True)
class MergeResult:
    out_dir: Path
    robots: list[str]
    mission_start_ref_s: float
    events: int
    dwells: int
    clocks: dict[str, ClockMapping]
    warnings: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class _Timed:
    """One robot's recording with its mapping onto the mission clock."""

    recording: Recording
    zero_s: float

    def mission(self, local_s: float | np.ndarray) -> float | np.ndarray:
        return self.recording.mapping.to_reference(local_s) - self.zero_s


def _mission_document(
    mission: Path | None, robots: list[str] | None, overrides: dict[str, Any] | None
) -> dict[str, Any]:
    if (mission is None) == (robots is None):
        raise ConfigError("give either --mission FILE or --robot NAME=X,Y,YAW for every robot")
    if mission is not None:
        document = read_yaml_mapping(mission, ConfigError)
        if "robots" not in document:
            raise ConfigError(f"{mission}: not a mission (no robots)")
    else:
        assert robots is not None
        document = {"robots": [_robot_entry(text) for text in robots]}
    if overrides:
        document["config"] = merge_mappings(document.get("config") or {}, overrides)
    return document


def _robot_entry(text: str) -> dict[str, Any]:
    name, sep, pose = text.partition("=")
    try:
        values = [float(v) for v in pose.split(",")]
    except ValueError:
        values = []
    if not sep or len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ConfigError(f"--robot {text!r}: expected NAME=X_M,Y_M,YAW_DEG (e.g. a=2,3.5,20)")
    return {"name": name.strip(), "start": values}


def _robot_names(document: dict[str, Any], source: str) -> list[str]:
    entries = document["robots"]
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise ConfigError(f"{source}: robots: must be a list of {{name, start}}")
    return [str(e.get("name")) for e in entries]


def _mission_start(
    recordings: list[Recording], given: float | None, events: dict[str, list[dict[str, Any]]]
) -> float:
    """The reference time of mission time 0: given, recorded, or the first operator start."""
    if given is not None:
        return given
    recorded = {
        r.robot: r.mission_start_ref_s for r in recordings if r.mission_start_ref_s is not None
    }
    if recorded:
        values = sorted(set(recorded.values()))
        if values[-1] - values[0] > 1e-6:
            listed = ", ".join(f"{k} {v:.6f}" for k, v in sorted(recorded.items()))
            raise RecordingError(f"the recordings disagree on the mission start ({listed}); "
                                 "give --mission-start")  # fmt: skip
        return values[0]
    starts = [
        float(r.mapping.to_reference(float(e["t_s"])))
        for r in recordings
        if r.events_clock == "local"
        for e in events[r.robot]
        if e.get("event") == "start"
    ]
    if not starts:
        raise RecordingError(
            "cannot place mission time 0: no recording has a start event or a mission start; "
            "give --mission-start REFERENCE_S"
        )
    return min(starts)


def _read_events(recording: Recording) -> list[dict[str, Any]]:
    if recording.events is None:
        return []
    events = []
    text = recording.events.read_text(encoding="utf-8")
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            event = json.loads(line)
        except json.JSONDecodeError:
            if number == len(text.splitlines()):
                continue  # the last line of a log cut short mid-write
            raise RecordingError(f"{recording.events}:{number}: not JSON") from None
        if not isinstance(event, dict) or not all(
            isinstance(event.get(k, 0.0), int | float) for k in _TIMES
        ):
            raise RecordingError(f"{recording.events}:{number}: not an event with times")
        events.append(event)
    return events


def _to_mission(event: dict[str, Any], timed: _Timed) -> dict[str, Any]:
    if timed.recording.events_clock == "mission":
        return dict(event)
    out = dict(event)
    for key in _TIMES:
        if key in out:
            out[key] = round(float(timed.mission(float(out[key]))), 6)
    return out


def merge_events(
    by_robot: dict[str, list[dict[str, Any]]], robots: list[str], tolerance_s: float = 0.5
) -> list[dict[str, Any]]:
    """Events of all recordings on the mission clock → one ordered log (see module docstring).

    ``by_robot`` lists each recording's events in its file order; a duplicate is kept from the
    recording of the robot it concerns, or else from the first.
    """
    order = {r: k for k, r in enumerate(robots)}
    tagged = [(e, r, n) for r, events in by_robot.items() for n, e in enumerate(events)]
    kept: list[tuple[dict[str, Any], str, int]] = []
    dwells: list[tuple[dict[str, Any], str, int]] = []
    seen: dict[tuple[Any, ...], int] = {}
    for event, robot, number in tagged:
        kind = event.get("event")
        if kind == "dwell":
            dwells.append((dict(event), robot, number))
            continue
        key = _key(event)
        if key is None:
            kept.append((event, robot, number))
            continue
        if key in seen:
            other = kept[seen[key]][0]
            gap = max(abs(float(event.get(k, 0.0)) - float(other.get(k, 0.0))) for k in _TIMES)
            if gap > tolerance_s and kind == "move":
                raise RecordingError(
                    f"recordings disagree on the move of robot {event['robot']} from pose "
                    f"{event['from_index']}: at {other['t_s']} s and at {event['t_s']} s"
                )
            if event.get("robot") == robot and kept[seen[key]][1] != robot:
                kept[seen[key]] = (event, robot, number)
            continue
        seen[key] = len(kept)
        kept.append((event, robot, number))
    kept += _combine_dwells(dwells)
    kept.sort(
        key=lambda item: (
            float(item[0]["t_s"]),
            _PRIORITY.get(str(item[0].get("event")), 5),
            order.get(item[1], len(order)),
            item[2],
        )
    )
    return [event for event, _, _ in kept]


def _key(event: dict[str, Any]) -> tuple[Any, ...] | None:
    kind = event.get("event")
    if kind == "start":
        return (kind, event.get("robot"))
    if kind == "move":
        return (kind, event.get("robot"), event.get("from_index"))
    if kind == "roles":
        return (kind, event.get("reference"), event.get("mapper"), event.get("step"))
    if kind == "changes":
        return (kind,)
    return None


def _combine_dwells(
    dwells: list[tuple[dict[str, Any], str, int]],
) -> list[tuple[dict[str, Any], str, int]]:
    """Dwells that overlap in time are one: all stood still in the intersection."""
    dwells = sorted(dwells, key=lambda d: float(d[0]["t_s"]))
    out: list[tuple[dict[str, Any], str, int]] = []
    for event, robot, number in dwells:
        if out and float(event["t_s"]) < float(out[-1][0]["end_s"]):
            merged = out[-1][0]
            merged["t_s"] = max(float(merged["t_s"]), float(event["t_s"]))
            merged["end_s"] = min(float(merged["end_s"]), float(event["end_s"]))
            poses = dict(merged.get("poses") or {})
            for name, index in (event.get("poses") or {}).items():
                if poses.get(name, index) != index:
                    raise RecordingError(
                        f"the dwell at {merged['t_s']} s has robot {name} at pose "
                        f"{poses[name]} in one recording and {index} in another"
                    )
                poses[name] = index
            merged["poses"] = poses
            for role in ("reference", "mapper", "phase", "step"):
                if event.get(role) is None:
                    continue
                if merged.get(role) is None:
                    merged[role] = event[role]
                elif merged[role] != event[role]:
                    raise RecordingError(
                        f"the dwell at {merged['t_s']} s has {role} {merged[role]!r} in one "
                        f"recording and {event[role]!r} in another"
                    )
        else:
            out.append((event, robot, number))
    return out


def _span(timed: _Timed) -> tuple[float, float]:
    capture = timed.recording.capture
    stamps = [s for s, _ in CaptureReader(capture).chunks() if s is not None] if capture else []
    if not stamps:
        raise RecordingError(f"{timed.recording.path}: no LMS capture with stamps")
    return float(timed.mission(stamps[0])), float(timed.mission(stamps[-1]))


def _write_capture(timed: _Timed, path: Path) -> None:
    recording = timed.recording
    assert recording.capture is not None
    reader = CaptureReader(recording.capture)
    header = {key: value for key, value in (reader.header or {}).items()
              if key in ("baud_rate", "port")}  # fmt: skip
    header.update(
        robot=recording.robot,
        recording=str(recording.path),
        clock="mission",
        clock_mapping=recording.mapping.as_dict(),
        mission_start_ref_s=timed.zero_s,
    )
    writer = CaptureWriter(path, header)
    try:
        for stamp, chunk in reader.chunks():
            if stamp is not None:
                writer.write(float(timed.mission(stamp)), chunk)
    except BaseException:
        writer.discard()
        raise
    writer.close()


def _odometry(timed: _Timed) -> tuple[np.ndarray, np.ndarray]:
    recording = timed.recording
    if recording.odometry is None:
        raise RecordingError(f"{recording.path}: no odometry.tum")
    stamps, poses = read_tum(recording.odometry)
    clock = recording.odometry_clock
    if clock == "reference":
        return stamps - timed.zero_s, poses
    if clock == "unix":
        stamps = stamps - recording.unix_offset_s
    elif clock != "local":
        raise RecordingError(f"{recording.path}: unknown odometry clock {clock!r}")
    return np.asarray(timed.mission(stamps)), poses


def _check_coverage(
    events: list[dict[str, Any]], spans: dict[str, tuple[float, float]], what: str
) -> None:
    for event in events:
        if event.get("event") != "move" or event["robot"] not in spans:
            continue
        first, last = spans[event["robot"]]
        for key in ("start_s", "t_s"):
            if not first <= float(event[key]) <= last:
                raise RecordingError(
                    f"the move of robot {event['robot']} to pose {event['to_index']} "
                    f"({key} {event[key]} s) lies outside its {what} "
                    f"({first:.3f} s to {last:.3f} s)"
                )


def merge_recordings(
    recordings: list[Path],
    out_dir: Path | str,
    *,
    mission: Path | None = None,
    robots: list[str] | None = None,
    overrides: dict[str, Any] | None = None,
    mission_start_ref_s: float | None = None,
    tolerance_s: float = 0.5,
) -> MergeResult:
    """Merge the robots' recording folders into a dataset at ``out_dir`` (module docstring)."""
    out_dir = Path(out_dir)
    check_replaceable(out_dir, "dataset")
    document = _mission_document(mission, robots, overrides)
    names = _robot_names(document, str(mission or "--robot"))
    read = [read_recording(path) for path in recordings]
    by_name: dict[str, Recording] = {}
    for recording in read:
        if recording.robot in by_name:
            first = by_name[recording.robot].path
            raise RecordingError(
                f"two recordings of robot {recording.robot}: {first} and {recording.path}"
            )
        if recording.robot not in names:
            raise RecordingError(
                f"{recording.path}: robot {recording.robot} is not in the mission "
                f"({', '.join(names)})"
            )
        if out_dir.resolve() == recording.path.resolve():
            raise RecordingError(f"{out_dir}: is a recording; choose another --out")
        by_name[recording.robot] = recording
    missing = [n for n in names if n not in by_name]
    if missing:
        raise RecordingError(f"no recording of robot(s) {', '.join(missing)}")
    raw_events = {r.robot: _read_events(r) for r in read}
    zero = _mission_start(read, mission_start_ref_s, raw_events)
    timed = {name: _Timed(by_name[name], zero) for name in names}
    spans = {name: _span(t) for name, t in timed.items()}
    if max(s[0] for s in spans.values()) >= min(s[1] for s in spans.values()):
        listed = "; ".join(f"{n} {a:.1f} s to {b:.1f} s" for n, (a, b) in spans.items())
        raise RecordingError(f"the recordings do not overlap in time ({listed}): not one mission")
    events = merge_events(
        {n: [_to_mission(e, timed[n]) for e in raw_events[n]] for n in names}, names, tolerance_s
    )
    for event in events:
        if event.get("event") == "dwell":
            absent = [n for n in names if n not in (event.get("poses") or {})]
            if absent:
                raise RecordingError(
                    f"the dwell at {event['t_s']} s (mission clock) has no pose index of robot(s) "
                    f"{', '.join(absent)}: log it in their recordings, or track them (--robots)"
                )
    warnings = [w for r in read for w in r.warnings]
    for name, t in timed.items():
        if t.recording.mapping.uncertainty_s > 0.05:
            warnings.append(f"robot {name}: the clock mapping is uncertain by "
                            f"±{t.recording.mapping.uncertainty_s:.3f} s")  # fmt: skip
    with replace_directory(out_dir, "dataset") as work:
        odometry_spans = {}
        for name, t in timed.items():
            folder = work / "robots" / name
            folder.mkdir(parents=True)
            _write_capture(t, folder / "lms.cap")
            stamps, poses = _odometry(t)
            odometry_spans[name] = (float(stamps[0]), float(stamps[-1]))
            write_tum(folder / "odometry.tum", stamps, poses)
        _check_coverage(events, odometry_spans, "odometry")
        lines = [json.dumps(e, separators=(",", ":")) for e in events]
        write_text_atomic(work / "events.jsonl", "\n".join(lines) + "\n")
        header = f"# merged from {len(read)} recordings; coopmap {__version__}\n"
        write_text_atomic(work / "mission.yaml", header + yaml.safe_dump(document, sort_keys=False))
        clocks = {
            "format": "coopmap dataset clocks",
            "mission_start_ref_s": zero,
            "robots": {n: {"recording": str(t.recording.path), **t.recording.mapping.as_dict(),
                           "odometry_clock": t.recording.odometry_clock,
                           "events_clock": t.recording.events_clock}
                       for n, t in timed.items()},
        }  # fmt: skip
        write_text_atomic(work / "clock.json", json.dumps(clocks, indent=1) + "\n")
        try:
            load_dataset(work)
        except (ConfigError, SensorError) as exc:
            raise RecordingError(
                f"the merged dataset is not valid: {str(exc).replace(str(work), str(out_dir))}"
            ) from None
    return MergeResult(
        out_dir=out_dir,
        robots=names,
        mission_start_ref_s=zero,
        events=len(events),
        dwells=sum(e.get("event") == "dwell" for e in events),
        clocks={n: t.recording.mapping for n, t in timed.items()},
        warnings=warnings,
    )
