"""A robot's event log: moves and dwells typed by an operator, or taken from a mission file.

Events have the fields of a dataset's ``events.jsonl`` (docs/dataset.md). In a recording their
times are on the clock the recording names: the local clock for the operator prompt (each
command is stamped on arrival), the mission clock for a mission file.

Operator commands (one per line; an optional robot defaults to the recording's own)::

    start                        the mission starts: a start event per tracked robot
    depart [ROBOT]               ROBOT starts driving
    arrive [ROBOT]               ROBOT stops: a move event from its departure to now
    dwell [reference=R] [mapper=M] [phase=P] [step=N]
                                 every tracked robot stands still from now
    end                          the dwell ends: a dwell event with every tracked pose index
    roles REFERENCE MAPPER [STEP]
    note TEXT                    a note in the log (ignored by the processing)
    quit                         stop recording

A command that does not fit (unknown, a robot not tracked, ``arrive`` without ``depart``,
``dwell`` while a robot drives, ``end`` without ``dwell``) is answered with an error line and
changes nothing.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from sensors.errors import RecordingError

__all__ = ["EventLog", "MissionSchedule", "OperatorLog", "Reply", "read_events_file"]

_PHASES = ("start", "station", "mapping", "relocalize")


class EventLog:
    """JSON lines appended to ``<name>.partial`` (flushed per event), renamed when closed."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.partial = path.with_name(path.name + ".partial")
        self._file: TextIO | None = open(self.partial, "x", encoding="utf-8")  # noqa: SIM115
        self.events = 0

    def write(self, event: dict[str, Any]) -> None:
        if self._file is None:
            raise RecordingError(f"{self.path}: event log already closed")
        self._file.write(json.dumps(event, separators=(",", ":")) + "\n")
        self._file.flush()
        self.events += 1

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None
            os.replace(self.partial, self.path)


@dataclass(frozen=True)
class Reply:
    ok: bool
    message: str
    events: tuple[dict[str, Any], ...] = ()
    quit: bool = False


@dataclass
class OperatorLog:
    """The state behind the operator prompt: pose indices, departures, the open dwell."""

    robot: str
    robots: list[str]
    index: dict[str, int] = field(default_factory=dict)
    departed: dict[str, float] = field(default_factory=dict)
    dwell: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        if self.robot not in self.robots:
            self.robots = [self.robot, *self.robots]
        self.index = dict.fromkeys(self.robots, 0)

    def command(self, line: str, t_s: float) -> Reply:
        """Apply one command typed at local time ``t_s``."""
        words = line.split()
        if not words:
            return Reply(True, "")
        verb, args = words[0].lower(), words[1:]
        t = round(t_s, 6)
        try:
            if verb == "start":
                events = tuple(
                    {"t_s": t, "event": "start", "robot": r, "index": 0} for r in self.robots
                )
                return Reply(True, f"mission started ({', '.join(self.robots)})", events)
            if verb == "depart":
                robot = self._robot(args)
                if self.dwell is not None:
                    return Reply(False, "a dwell is open: type 'end' before anyone drives")
                if robot in self.departed:
                    return Reply(False, f"robot {robot} is already driving")
                self.departed[robot] = t
                return Reply(True, f"{robot} departs from pose {self.index[robot]}")
            if verb == "arrive":
                robot = self._robot(args)
                if robot not in self.departed:
                    return Reply(False, f"robot {robot} has not departed")
                start = self.departed.pop(robot)
                self.index[robot] += 1
                event = {"t_s": t, "event": "move", "robot": robot,
                         "from_index": self.index[robot] - 1, "to_index": self.index[robot],
                         "start_s": start}  # fmt: skip
                return Reply(True, f"{robot} arrived at pose {self.index[robot]}", (event,))
            if verb == "dwell":
                if self.dwell is not None:
                    return Reply(False, "a dwell is already open")
                if self.departed:
                    return Reply(False, f"still driving: {', '.join(sorted(self.departed))}")
                self.dwell = {"t_s": t, **self._dwell_fields(args)}
                return Reply(True, "dwell begins: everyone stands still")
            if verb == "end":
                if self.dwell is None:
                    return Reply(False, "no dwell is open")
                begun, self.dwell = self.dwell, None
                began_s = float(begun.pop("t_s"))
                event = {"t_s": began_s, "event": "dwell", "end_s": t,
                         "poses": dict(self.index), **begun}  # fmt: skip
                return Reply(True, f"dwell of {t - began_s:.1f} s logged", (event,))
            if verb == "roles":
                if len(args) not in (2, 3):
                    return Reply(False, "usage: roles REFERENCE MAPPER [STEP]")
                ref, mapper = self._robot(args[:1]), self._robot(args[1:2])
                step = int(args[2]) if len(args) == 3 else 0
                event = {"t_s": t, "event": "roles", "reference": ref, "mapper": mapper,
                         "step": step}  # fmt: skip
                return Reply(True, f"roles: reference {ref}, mapper {mapper}", (event,))
            if verb == "note":
                text = line.split(None, 1)[1] if args else ""
                return Reply(True, "noted", ({"t_s": t, "event": "note", "text": text},))
            if verb == "quit":
                return Reply(True, "stopping", quit=True)
        except ValueError as exc:
            return Reply(False, str(exc))
        return Reply(False, f"unknown command {verb!r} (start, depart, arrive, dwell, end, "
                            "roles, note, quit)")  # fmt: skip

    def _robot(self, args: list[str]) -> str:
        robot = args[0] if args else self.robot
        if robot not in self.index:
            raise ValueError(f"robot {robot!r} is not tracked ({', '.join(self.robots)})")
        return robot

    def _dwell_fields(self, args: list[str]) -> dict[str, Any]:
        fields: dict[str, Any] = {}
        for arg in args:
            key, sep, value = arg.partition("=")
            if not sep or key not in ("reference", "mapper", "phase", "step"):
                raise ValueError(
                    f"dwell: expected reference=, mapper=, phase= or step=, got {arg!r}"
                )
            if key in ("reference", "mapper"):
                fields[key] = self._robot([value])
            elif key == "phase":
                if value not in _PHASES:
                    raise ValueError(f"dwell: phase must be one of {', '.join(_PHASES)}")
                fields[key] = value
            else:
                try:
                    fields[key] = int(value)
                except ValueError:
                    raise ValueError(f"dwell: step must be a whole number, got {value!r}") from None
        return fields


def read_events_file(path: Path, limit_bytes: int = 64 * 2**20) -> list[dict[str, Any]]:
    """A mission file: JSON events, one per line, on the mission clock (docs/dataset.md)."""
    try:
        if not path.is_file():
            raise RecordingError(f"{path}: no such file (expected a mission's events, JSON lines)")
        if path.stat().st_size > limit_bytes:
            raise RecordingError(f"{path}: larger than {limit_bytes} bytes")
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{path}: cannot read: {exc}") from None
    events = []
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            event = json.loads(line)
        except json.JSONDecodeError as exc:
            raise RecordingError(f"{path}:{number}: not JSON: {exc.msg}") from None
        if not isinstance(event, dict) or "event" not in event or "t_s" not in event:
            raise RecordingError(f"{path}:{number}: an event needs 'event' and 't_s'")
        for key in ("t_s", "start_s", "end_s"):
            value = event.get(key, 0.0)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise RecordingError(f"{path}:{number}: {key} must be a number")
            if not math.isfinite(value):
                raise RecordingError(f"{path}:{number}: {key} must be a finite number")
        events.append(event)
    return events


class MissionSchedule:
    """Events of a mission file, released in file order once the mission clock has passed their
    last time (a dwell when it has ended)."""

    def __init__(self, events: list[dict[str, Any]]) -> None:
        self.events = events
        self.released = 0

    @staticmethod
    def due_s(event: dict[str, Any]) -> float:
        return float(max(event["t_s"], event.get("end_s", event["t_s"])))

    @property
    def last_s(self) -> float:
        return max((self.due_s(e) for e in self.events), default=0.0)

    @property
    def done(self) -> bool:
        return self.released == len(self.events)

    def due(self, mission_s: float) -> list[dict[str, Any]]:
        out = []
        while self.released < len(self.events):
            event = self.events[self.released]
            if self.due_s(event) > mission_s:
                break
            out.append(event)
            self.released += 1
        return out
