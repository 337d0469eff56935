"""The recording folder one robot writes during a mission (docs/recording.md), and reading it.

::

    REC/
    ├── .coopmap         marks a coopmap recording
    ├── recording.json   robot, sources, the clocks of each file, counts, how it ended
    ├── clock.json       the clock exchanges (raw samples) and the fitted mapping to the reference
    ├── lms.cap          LMS bytes with receive stamps on the local clock (sensors.lms200.capture)
    ├── odometry.tum     poses; stamps on the clock recording.json names (local or reference)
    ├── odometry.lines   every odometry line received, with its local arrival stamp
    └── events.jsonl     events; times on the local clock (operator) or the mission clock (file)

Files being written are ``<name>.partial`` and renamed when the recording stops; a recording cut
short keeps its ``.partial`` files, which :func:`read_recording` accepts in their place.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sensors.atomic import MARKER, check_replaceable, output_kind, write_text_atomic
from sensors.errors import OutputError, RecordingError
from sensors.recording.clock import ClockMapping, ClockSample, fit_mapping

__all__ = [
    "KIND",
    "Recording",
    "create_folder",
    "read_recording",
    "unix_pair",
    "write_json",
]

KIND = "recording"
FORMAT = "coopmap recording"
CLOCK_FORMAT = "coopmap clock"
_LIMIT = 64 * 2**20


def create_folder(out_dir: Path) -> None:
    """A new, marked recording folder. A recording is never replaced: an existing folder is
    refused unless it is empty."""
    check_replaceable(out_dir, KIND)  # a user's folder, a file, a link, the working folder
    if out_dir.exists() and any(out_dir.iterdir()):
        raise OutputError(
            f"{out_dir}: holds a recording already; recordings are never replaced "
            "(choose another folder)"
        )
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / MARKER).write_text(json.dumps({"kind": KIND}) + "\n", encoding="utf-8")


def write_json(path: Path, document: dict[str, Any]) -> None:
    write_text_atomic(path, json.dumps(document, indent=1, sort_keys=True) + "\n")


def unix_pair() -> tuple[float, float]:
    """(monotonic, unix) read as close together as this process can: the tightest of three."""
    best: tuple[float, float, float] | None = None
    for _ in range(3):
        a = time.monotonic()
        unix = time.time()
        b = time.monotonic()
        if best is None or b - a < best[0]:
            best = (b - a, 0.5 * (a + b), unix)
    assert best is not None
    return best[1], best[2]


@dataclass(frozen=True)
class Recording:
    """A recording folder as read back: its files and what recording.json and clock.json say."""

    path: Path
    robot: str
    meta: dict[str, Any]
    mapping: ClockMapping  # local clock → reference clock
    unix_offset_s: float  # unix − monotonic on this robot (for odometry stamped in unix time)
    capture: Path | None
    odometry: Path | None
    events: Path | None
    warnings: list[str] = field(default_factory=list)

    @property
    def odometry_clock(self) -> str:
        return str((self.meta.get("odometry") or {}).get("clock", "local"))

    @property
    def events_clock(self) -> str:
        return str((self.meta.get("events") or {}).get("clock", "local"))

    @property
    def mission_start_ref_s(self) -> float | None:
        value = self.meta.get("mission_start_ref_s")
        return float(value) if isinstance(value, int | float) else None


def _read_json(path: Path) -> dict[str, Any]:
    try:
        if path.stat().st_size > _LIMIT:
            raise RecordingError(f"{path}: larger than {_LIMIT} bytes")
        document = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RecordingError(f"{path}: missing (not a complete coopmap recording)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RecordingError(f"{path}: unreadable: {exc}") from None
    if not isinstance(document, dict):
        raise RecordingError(f"{path}: not a JSON object")
    return document


def _file(path: Path, name: str, warnings: list[str]) -> Path | None:
    final, partial = path / name, path / f"{name}.partial"
    if final.is_file():
        return final
    if partial.is_file():
        warnings.append(f"{path}: {name} was cut short; using {partial.name}")
        return partial
    return None


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def read_recording(path: Path | str) -> Recording:
    """Read a recording folder; a missing or inconsistent piece is a RecordingError."""
    path = Path(path)
    if not path.is_dir():
        raise RecordingError(f"{path}: no such recording folder")
    if output_kind(path) != KIND:
        raise RecordingError(f"{path}: not a coopmap recording (no {MARKER} marker of a recording)")
    meta = _read_json(path / "recording.json")
    if meta.get("format") != FORMAT:
        raise RecordingError(f"{path / 'recording.json'}: not a coopmap recording")
    robot = meta.get("robot")
    if not (isinstance(robot, str) and len(robot) == 1 and "a" <= robot <= "z"):
        raise RecordingError(f"{path / 'recording.json'}: robot must be one letter, got {robot!r}")
    clock = _read_json(path / "clock.json")
    if clock.get("format") != CLOCK_FORMAT:
        raise RecordingError(f"{path / 'clock.json'}: not a coopmap clock file")
    mapping = _mapping(path / "clock.json", clock)
    pairs = clock.get("unix_pairs") or []
    if not (isinstance(pairs, list) and pairs and all(_pair(p) for p in pairs)):
        raise RecordingError(f"{path / 'clock.json'}: unix_pairs must be [[monotonic, unix], ...]")
    unix_offset = sum(u - m for m, u in pairs) / len(pairs)
    warnings: list[str] = []
    if meta.get("state") != "complete":
        warnings.append(f"{path}: the recording did not stop cleanly ({meta.get('state')!r})")
    return Recording(
        path=path,
        robot=robot,
        meta=meta,
        mapping=mapping,
        unix_offset_s=unix_offset,
        capture=_file(path, "lms.cap", warnings),
        odometry=_file(path, "odometry.tum", warnings),
        events=_file(path, "events.jsonl", warnings),
        warnings=warnings,
    )


def _pair(value: Any) -> bool:
    return isinstance(value, list) and len(value) == 2 and all(_number(v) for v in value)


def _mapping(path: Path, clock: dict[str, Any]) -> ClockMapping:
    """The stored fit; refitted from the samples when the file was written before the end."""
    samples = clock.get("samples") or []
    if not isinstance(samples, list) or not all(
        isinstance(s, list) and len(s) == 4 and all(_number(v) for v in s) for s in samples
    ):
        raise RecordingError(f"{path}: samples must be [[t1, t2, t3, t4], ...]")
    stored = clock.get("mapping")
    if clock.get("final") is not True and samples:
        return fit_mapping([ClockSample(*s) for s in samples])
    if not isinstance(stored, dict) or not all(
        _number(stored.get(k)) for k in ("offset_s", "rate")
    ):
        raise RecordingError(f"{path}: mapping must hold offset_s and rate")
    if stored["rate"] <= 0:
        raise RecordingError(f"{path}: mapping rate must be > 0, got {stored['rate']}")
    return ClockMapping(
        offset_s=float(stored["offset_s"]),
        rate=float(stored["rate"]),
        source=str(stored.get("source", "given")),
        samples_used=int(stored.get("samples_used", 0)),
        residual_rms_s=float(stored.get("residual_rms_s", 0.0)),
        max_round_trip_s=float(stored.get("max_round_trip_s", 0.0)),
    )
