"""What travels between the robot agents and the base station (docs/live.md, "On the wire").

Keys, all under ``coopmap/<mission>/``:

* ``robot/<r>/<stream>/<seq>`` — a robot's immutable numbered chunks. ``stream`` is ``lms`` (LMS
  capture records exactly as ``lms.cap`` holds them: float64 receive stamp, uint32 size, the
  bytes off the port), ``odom`` (float64 rows ``t_s x_m y_m yaw_rad``), ``event`` (JSON lines:
  what the robot did) or ``summary`` (JSON: the sweep the robot assembled from a dwell and the
  beacons it detected in it, on board). ``seq`` counts a robot's chunks over all its streams,
  from 0.
* ``robot/<r>/cmd`` — the robot's queryable for the base's commands (numbered; a reply per
  command, the same reply again when a command is sent twice).
* ``robot/<r>/store`` — the robot's queryable serving chunks from its disk (``?from=A;to=B``).
* ``robot/<r>/info`` — the robot's queryable for its capture header and state.
* ``alive/<r>`` — the robot's liveliness token.
* ``base/state``, ``base/estimate``, ``base/map`` — what the base publishes after every dwell;
  ``base/**`` is also a queryable, so a viewer that joins late gets the current values.

A chunk is ``MAGIC``, one JSON header line (mission, run, robot, stream, seq, size, CRC-32) and
the payload. :func:`decode_chunk` and :func:`decode_json` turn anything malformed into a
:class:`WireError` — one line, which the receiver counts and drops.
"""

from __future__ import annotations

import json
import math
import os
import re
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sensors.errors import SensorError

__all__ = [
    "MAX_CHUNK",
    "STREAMS",
    "Chunk",
    "WireError",
    "append_journal",
    "chunk_key",
    "decode_chunk",
    "decode_json",
    "decode_lms",
    "decode_odometry",
    "encode_chunk",
    "encode_json",
    "encode_lms",
    "encode_odometry",
    "mission_key",
    "parse_chunk_key",
    "read_journal",
]

MAGIC = b"COOPMAP-CHUNK 1\n"
STREAMS = ("lms", "odom", "event", "summary")
#: Largest chunk accepted (a dwell of one robot's LMS output is ~2 MB).
MAX_CHUNK = 1 << 27
_MAX_HEADER = 4096
_MAX_JSON = 1 << 22
_LMS_RECORD = struct.Struct("<dI")
_NAME = re.compile(r"[a-z]")
_MISSION = re.compile(r"[A-Za-z0-9_.-]{1,64}")


class WireError(SensorError):
    """A message on the mission's keys that is not what coopmap sends."""


@dataclass(frozen=True)
class Chunk:
    """One immutable piece of a robot's recording."""

    mission: str
    run: str
    robot: str
    stream: str
    seq: int
    payload: bytes
    #: When the robot wrote it to its disk (its unix clock): the start of its scan → map time.
    recorded_unix_s: float = 0.0


def mission_key(mission: str) -> str:
    if not _MISSION.fullmatch(mission):
        raise WireError(f"mission name {mission!r}: letters, digits, '_', '-' or '.' only")
    return f"coopmap/{mission}"


def chunk_key(mission: str, robot: str, stream: str, seq: int) -> str:
    return f"{mission_key(mission)}/robot/{robot}/{stream}/{seq}"


def parse_chunk_key(key: str, mission: str) -> tuple[str, str, int] | None:
    """(robot, stream, seq) of a chunk key of ``mission``; None for any other key."""
    parts = key.split("/")
    if len(parts) != 6 or parts[:2] != ["coopmap", mission] or parts[2] != "robot":
        return None
    robot, stream, seq = parts[3], parts[4], parts[5]
    if not _NAME.fullmatch(robot) or stream not in STREAMS or not seq.isdigit():
        return None
    return robot, stream, int(seq)


def encode_chunk(chunk: Chunk) -> bytes:
    header = {
        "mission": chunk.mission, "run": chunk.run, "robot": chunk.robot,
        "stream": chunk.stream, "seq": chunk.seq, "size": len(chunk.payload),
        "crc32": zlib.crc32(chunk.payload), "recorded_unix_s": chunk.recorded_unix_s,
    }  # fmt: skip
    return MAGIC + json.dumps(header, sort_keys=True).encode() + b"\n" + chunk.payload


def decode_chunk(data: bytes) -> Chunk:
    """The chunk in ``data``; WireError when it is not one, or not whole."""
    if len(data) > MAX_CHUNK:
        raise WireError(f"chunk of {len(data):,} bytes (at most {MAX_CHUNK:,})")
    if not data.startswith(MAGIC):
        raise WireError("not a coopmap chunk (no magic line)")
    end = data.find(b"\n", len(MAGIC), len(MAGIC) + _MAX_HEADER)
    if end < 0:
        raise WireError("chunk header: no end of line within 4 kB")
    try:
        header = json.loads(data[len(MAGIC) : end])
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise WireError(f"chunk header: not JSON ({exc.__class__.__name__})") from None
    if not isinstance(header, dict):
        raise WireError("chunk header: not a JSON object")
    fields = {"mission": str, "run": str, "robot": str, "stream": str, "seq": int,
              "size": int, "crc32": int}  # fmt: skip
    for name, kind in fields.items():
        value = header.get(name)
        if not isinstance(value, kind) or isinstance(value, bool):
            raise WireError(f"chunk header: {name!r} missing or not {kind.__name__}")
    payload = data[end + 1 :]
    if header["stream"] not in STREAMS or not _NAME.fullmatch(header["robot"]):
        raise WireError(f"chunk header: stream {header['stream']!r} / robot {header['robot']!r}")
    if header["seq"] < 0 or len(payload) != header["size"]:
        raise WireError(f"chunk {header['seq']}: {len(payload)} payload bytes, header says "
                        f"{header['size']}")  # fmt: skip
    if zlib.crc32(payload) != header["crc32"]:
        raise WireError(f"chunk {header['seq']}: CRC-32 mismatch")
    recorded = header.get("recorded_unix_s", 0.0)
    if not isinstance(recorded, int | float) or isinstance(recorded, bool):
        raise WireError("chunk header: 'recorded_unix_s' is not a number")
    return Chunk(header["mission"], header["run"], header["robot"], header["stream"],
                 header["seq"], bytes(payload), float(recorded))  # fmt: skip


def encode_json(value: Any) -> bytes:
    return json.dumps(value, separators=(",", ":"), allow_nan=False).encode()


def decode_json(data: bytes | None, what: str) -> dict[str, Any]:
    """A JSON object message; WireError for anything else."""
    if data is None:
        raise WireError(f"{what}: empty")
    if len(data) > _MAX_JSON:
        raise WireError(f"{what}: {len(data):,} bytes of JSON (at most {_MAX_JSON:,})")
    try:
        value = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise WireError(f"{what}: not JSON ({exc.__class__.__name__})") from None
    if not isinstance(value, dict):
        raise WireError(f"{what}: not a JSON object")
    return value


def encode_lms(records: list[tuple[float, bytes]]) -> bytes:
    """Capture records (the ``lms.cap`` record format) of (receive stamp, bytes)."""
    return b"".join(_LMS_RECORD.pack(stamp, len(data)) + data for stamp, data in records)


def decode_lms(payload: bytes) -> list[tuple[float, bytes]]:
    records, pos = [], 0
    while pos < len(payload):
        if pos + _LMS_RECORD.size > len(payload):
            raise WireError("lms chunk: a record header is cut short")
        stamp, size = _LMS_RECORD.unpack_from(payload, pos)
        pos += _LMS_RECORD.size
        if not math.isfinite(stamp) or pos + size > len(payload):
            raise WireError("lms chunk: a record's stamp is not finite or its bytes are cut short")
        records.append((stamp, payload[pos : pos + size]))
        pos += size
    return records


def encode_odometry(times: np.ndarray, poses: np.ndarray) -> bytes:
    rows = np.column_stack([np.asarray(times, float), np.asarray(poses, float).reshape(-1, 3)])
    return rows.astype("<f8").tobytes()


def decode_odometry(payload: bytes) -> tuple[np.ndarray, np.ndarray]:
    if len(payload) % 32:
        raise WireError(f"odom chunk: {len(payload)} bytes is not a whole number of rows")
    rows = np.frombuffer(payload, dtype="<f8").reshape(-1, 4).astype(float)
    if not np.isfinite(rows).all():
        raise WireError("odom chunk: a value is not finite")
    return rows[:, 0].copy(), rows[:, 1:].copy()


def append_journal(path: Path, entry: dict[str, Any]) -> None:
    """Append one JSON line to a journal (the robots' and the base's command logs), on disk
    before this returns."""
    with open(path, "ab") as f:
        f.write(encode_json(entry) + b"\n")
        f.flush()
        os.fsync(f.fileno())


def read_journal(path: Path) -> list[dict[str, Any]]:
    """A journal's entries. A last line cut short by a kill is cut off the file too, so that
    what is appended next starts on a line of its own."""
    if not path.is_file():
        return []
    data = path.read_bytes()
    entries, pos = [], 0
    while pos < len(data):
        end = data.find(b"\n", pos)
        if end < 0:
            break
        try:
            entry = json.loads(data[pos:end])
        except (UnicodeDecodeError, json.JSONDecodeError):
            break
        if not isinstance(entry, dict):
            break
        entries.append(entry)
        pos = end + 1
    if pos < len(data):
        with open(path, "r+b") as f:
            f.truncate(pos)
    return entries
