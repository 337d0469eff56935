"""Captures of a raw LMS byte stream with receive timestamps, and their decoding.

A capture file (``.cap``) is::

    COOPMAP-LMSCAP 1\\n
    {"port": ..., "baud_rate": ..., "started_unix_s": ..., ...}\\n      one JSON line
    record*                                                          until the end of the file

where each record is ``stamp_s`` (float64, seconds since the capture started), ``size``
(uint32), then ``size`` bytes exactly as they came off the port, little-endian. The same
:class:`~sensors.lms200.protocol.stream.StreamParser` that reads a live port replays a capture.

A recording is written to ``<name>.partial`` and renamed when it ends, so an existing capture is
never overwritten and a recording cut short still leaves every complete record readable. Any
file that does not start with the magic line is read as a plain binary dump (no timestamps).
"""

from __future__ import annotations

import json
import math
import os
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from numba import njit

from sensors.errors import SensorError
from sensors.lms200.protocol.plausibility import ScanCheck, ScanLimits
from sensors.lms200.protocol.replies import decode_reply
from sensors.lms200.protocol.scan import decode_scan
from sensors.lms200.protocol.stream import Event, Handshake, Rejected, StreamParser, Telegram
from sensors.lms200.protocol.telegram import BAUD_RATES, ProtocolError
from sensors.yamlio import regular_file

__all__ = [
    "CaptureError",
    "CaptureReader",
    "CaptureStream",
    "CaptureWriter",
    "DecodeSummary",
    "capture_head",
    "decode_stream",
    "describe_event",
]

MAGIC = b"COOPMAP-LMSCAP 1\n"
_RECORD = struct.Struct("<dI")
#: Largest record a reader accepts (a serial read never returns more in one go).
MAX_RECORD = 1 << 24
#: Stamps of consecutive records: at most this far back (clock jitter) ...
STAMP_SLACK_S = 1.0
#: ... and this far ahead (a recording paused for a day is still one capture).
MAX_RECORD_GAP_S = 86400.0


class CaptureError(SensorError):
    """A capture file is unreadable or malformed; the message names the file."""


def capture_head(header: dict[str, Any]) -> bytes:
    """A capture file's first two lines: the magic and the JSON header (records follow)."""
    meta = {"format": "coopmap lms capture", **header}
    return MAGIC + json.dumps(meta, sort_keys=True).encode("utf-8") + b"\n"


class CaptureWriter:
    """Append timestamped chunks to a new capture; ``close()`` publishes it under its name."""

    def __init__(self, path: Path | str, header: dict[str, Any] | None = None) -> None:
        self.path = Path(path)
        if self.path.exists():
            raise CaptureError(f"{self.path}: already exists; choose another name or remove it")
        self.partial = self.path.with_name(self.path.name + ".partial")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            # "xb": a recording cut short earlier is kept, never truncated by the next one
            self._file: BinaryIO | None = open(self.partial, "xb")  # noqa: SIM115 - see close()
        except FileExistsError:
            raise CaptureError(
                f"{self.partial}: a recording that was cut short is there (readable as a "
                f"capture); rename or remove it before recording to {self.path.name}"
            ) from None
        self._file.write(capture_head({"started_unix_s": time.time(), **(header or {})}))
        self.bytes_written = 0
        self.records = 0

    def write(self, stamp_s: float, chunk: bytes) -> None:
        if self._file is None:
            raise CaptureError(f"{self.path}: capture already closed")
        if not chunk:
            return
        self._file.write(_RECORD.pack(stamp_s, len(chunk)) + chunk)
        self.bytes_written += len(chunk)
        self.records += 1

    def flush(self) -> None:
        if self._file is not None:
            self._file.flush()
            os.fsync(self._file.fileno())

    def close(self) -> Path:
        """Finish the capture and rename ``.partial`` to the final name."""
        if self._file is not None:
            self.flush()
            self._file.close()
            self._file = None
            if self.path.exists():
                raise CaptureError(f"{self.path}: appeared while recording; kept {self.partial}")
            os.replace(self.partial, self.path)
        return self.path

    def discard(self) -> None:
        """Abandon the recording: remove the ``.partial`` file, publish nothing."""
        if self._file is not None:
            self._file.close()
            self._file = None
            self.partial.unlink(missing_ok=True)

    def __enter__(self) -> CaptureWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class CaptureReader:
    """Chunks of a capture (with stamps) or of a plain binary dump (stamps None).

    ``truncated_bytes`` counts the bytes of an incomplete last record, dropped while reading;
    ``corrupt_bytes`` and ``resyncs`` count what was skipped after corrupted record headers.
    """

    header: dict[str, Any] | None

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self.truncated_bytes = 0
        self.corrupt_bytes = 0
        self.resyncs = 0
        self._offset = 0
        regular_file(self.path, CaptureError)
        try:
            with open(self.path, "rb") as handle:
                head = handle.read(len(MAGIC))
                if head == MAGIC:
                    line = handle.readline(1 << 20)
                    if not line.endswith(b"\n"):
                        raise CaptureError(f"{self.path}: capture header line is truncated")
                    try:
                        self.header = json.loads(line)
                    except json.JSONDecodeError as exc:
                        raise CaptureError(
                            f"{self.path}: capture header is not JSON: {exc}"
                        ) from None
                    if not isinstance(self.header, dict):
                        raise CaptureError(f"{self.path}: capture header is not a JSON object")
                    self._offset = len(MAGIC) + len(line)
                else:
                    self.header = None
                    self._offset = 0
        except OSError as exc:
            raise CaptureError(f"{self.path}: cannot read: {exc.strerror or exc}") from None

    @property
    def is_capture(self) -> bool:
        return self.header is not None

    def chunks(self, dump_chunk: int = 1 << 16) -> Iterator[tuple[float | None, bytes]]:
        """(stamp_s, bytes) in file order: the records of :meth:`stream`, one by one."""
        stream = self.stream(dump_chunk)
        ends = stream.ends.tolist()
        stamps = stream.stamps_s.tolist() if self.is_capture else [None] * len(ends)
        for start, end, stamp in zip([0, *ends][:-1], ends, stamps, strict=True):
            yield stamp, stream.data[start:end].tobytes()

    def stream(self, dump_chunk: int = 1 << 16) -> CaptureStream:
        """The whole byte stream at once, with where each record ends and its stamp.

        A truncated last record is counted in ``truncated_bytes``. A corrupted record header
        (an impossible size or stamp) is skipped: the reader searches forward for the next
        header that is plausible and followed by another plausible header (or the end of the
        file), counting the bytes passed over in ``corrupt_bytes`` and each search in
        ``resyncs``; the stream parser then resynchronises on the telegrams themselves. A plain
        dump comes in pieces of ``dump_chunk`` bytes, without stamps (NaN).
        """
        try:
            with open(self.path, "rb") as handle:
                handle.seek(self._offset)
                body = np.frombuffer(handle.read(), dtype=np.uint8)
        except OSError as exc:
            raise CaptureError(f"{self.path}: cannot read: {exc.strerror or exc}") from None
        if not self.is_capture:
            ends = np.append(np.arange(dump_chunk, len(body), dump_chunk), len(body))
            ends = ends[ends > 0].astype(np.int64)
            return CaptureStream(body, ends, np.full(len(ends), np.nan))
        table, counts = _record_table(body, MAX_RECORD, STAMP_SLACK_S, MAX_RECORD_GAP_S)
        truncated, corrupt, resyncs = counts.tolist()
        self.truncated_bytes += truncated
        self.corrupt_bytes += corrupt
        self.resyncs += resyncs
        data = _gather(body, table[:, 0], table[:, 1])
        return CaptureStream(data, np.cumsum(table[:, 1]), table[:, 2].view(np.float64).copy())


@dataclass(frozen=True)
class CaptureStream:
    """A capture's bytes in one array: record ``k`` is ``data[ends[k-1]:ends[k]]``."""

    data: np.ndarray  # (B,) uint8
    ends: np.ndarray  # (R,) int64, increasing
    stamps_s: np.ndarray  # (R,) float64 s since the capture started (NaN: a plain dump)


_HEADER = _RECORD.size


@njit(cache=True)
def _plausible(  # pragma: no cover - numba
    stamp: float, size: int, last: float, limits: tuple[int, float, float]
) -> bool:
    """A record header the writer could have written after one stamped ``last`` (NaN: none).

    The writer never writes an empty record, and its stamps come from one monotonic clock.
    """
    if not (0 < size <= limits[0] and math.isfinite(stamp)):
        return False
    return math.isnan(last) or last - limits[1] <= stamp <= last + limits[2]


@njit(cache=True)
def _header(body: np.ndarray, pos: int, scratch: np.ndarray) -> tuple[float, int]:
    """The (stamp, size) record header at ``pos``: a little-endian float64 and uint32."""
    scratch[:_HEADER] = body[pos : pos + _HEADER]  # pragma: no cover - numba
    return scratch[:8].view(np.float64)[0], int(scratch[8:12].view(np.uint32)[0])


@njit(cache=True)
def _resync(  # pragma: no cover - numba
    body: np.ndarray, pos: int, last: float, limits: tuple[int, float, float], scratch: np.ndarray
) -> int:
    """The first offset from ``pos`` where two plausible records follow each other."""
    end = len(body)
    while pos + _HEADER <= end:
        stamp, size = _header(body, pos, scratch)
        if _plausible(stamp, size, last, limits):
            after = pos + _HEADER + size
            if after == end:
                return pos
            if after + _HEADER <= end:
                next_stamp, next_size = _header(body, after, scratch)
                if _plausible(next_stamp, next_size, stamp, limits):
                    return pos
        pos += 1
    return end


@njit(cache=True)
def _record_table(  # pragma: no cover - numba
    body: np.ndarray, max_record: int, slack_s: float, gap_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """(R, 3) int64 rows of body start, size and stamp (float64 bits) of every record, and
    [truncated bytes, corrupt bytes, resyncs]."""
    limits = (max_record, slack_s, gap_s)
    scratch = np.zeros(16, np.uint8)
    end = len(body)
    rows = np.empty((max(16, end // 64), 3), np.int64)
    found = truncated = corrupt = resyncs = 0
    pos, last = 0, math.nan
    while pos < end:
        if end - pos < _HEADER:
            truncated += end - pos
            break
        stamp, size = _header(body, pos, scratch)
        if not _plausible(stamp, size, last, limits):
            at = _resync(body, pos + 1, last, limits, scratch)
            resyncs += 1
            corrupt += at - pos
            pos = at
            continue
        body_end = pos + _HEADER + size
        if body_end > end:
            truncated += end - pos
            break
        if found == len(rows):
            bigger = np.empty((2 * len(rows), 3), np.int64)
            bigger[:found] = rows[:found]
            rows = bigger
        rows[found, 0] = pos + _HEADER
        rows[found, 1] = size
        scratch[:8] = body[pos : pos + 8]
        rows[found, 2] = scratch[:8].view(np.int64)[0]
        found += 1
        last, pos = stamp, body_end
    return rows[:found], np.array([truncated, corrupt, resyncs], np.int64)


@njit(cache=True)
def _gather(body: np.ndarray, starts: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """The record bodies, end to end."""
    out = np.empty(sizes.sum(), np.uint8)  # pragma: no cover - numba
    at = 0
    for k in range(len(starts)):
        out[at : at + sizes[k]] = body[starts[k] : starts[k] + sizes[k]]
        at += sizes[k]
    return out


# --------------------------------------------------------------------------------------------
# Decoding a stream into records (``coopmap lms decode``)


@dataclass
class DecodeSummary:
    bytes: int = 0
    telegrams: int = 0
    scans: int = 0
    replies: int = 0
    commands: int = 0
    acks: int = 0
    naks: int = 0
    checksum_failures: int = 0
    undecodable: int = 0
    implausible: int = 0  # checksum-valid scans the plausibility rules rejected
    implausible_reasons: dict[str, int] = field(default_factory=dict)
    bytes_skipped: int = 0
    truncated_bytes: int = 0
    corrupt_bytes: int = 0  # records lost to damaged record headers (CaptureReader)
    kinds: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items() if k != "kinds"}


def _json_number(value: float) -> float | None:
    return None if not math.isfinite(value) else round(float(value), 6)


def describe_event(event: Event, measuring_mode: int = 1) -> dict[str, Any]:
    """One JSON-ready record of an event (the line format of ``coopmap lms decode --json``)."""
    if isinstance(event, Handshake):
        return {"offset": event.offset, "kind": "ack" if event.ack else "nak",
                "stamp_s": event.stamp_s}  # fmt: skip
    if isinstance(event, Rejected):
        return {"offset": event.offset, "addr": event.addr, "code": event.code,
                "crc_ok": False, "kind": "bad_checksum", "length": event.length,
                "stamp_s": event.stamp_s}  # fmt: skip
    record: dict[str, Any] = {
        "offset": event.offset,
        "addr": event.addr,
        "code": event.code,
        "crc_ok": True,
        "stamp_s": event.stamp_s,
    }
    if not event.from_sensor:
        record.update(kind="command", data=event.data.hex())
        return record
    record["status"] = event.status
    try:
        if event.code == 0xB0:
            scan = decode_scan(event, measuring_mode)
            record.update(
                kind="scan",
                ranges_m=[_json_number(r) for r in scan.ranges_m],
                flags=scan.flags.tolist(),
                codes=scan.code.tolist(),
                unit="mm" if scan.unit_m == 0.001 else "cm",
                partial=scan.partial,
                scan_index=scan.scan_index,
                telegram_index=scan.telegram_index,
            )
            return record
        reply = decode_reply(event)
    except ProtocolError as exc:
        record.update(kind="invalid", error=str(exc), data=event.data.hex())
        return record
    record.update(kind="reply", name=reply.name)
    for key in ("text", "result", "ok", "angle_deg", "resolution_deg", "keep", "version",
                "operating_mode", "measuring_mode", "baud_rate", "unit_mm"):  # fmt: skip
        if hasattr(reply, key):
            record[key] = getattr(reply, key)
    config = getattr(reply, "config", None)
    if config is not None:
        record["config"] = config.raw.hex()
    if reply.name == "reply":
        record["data"] = event.data.hex()
    return record


def decode_stream(
    reader: CaptureReader,
    measuring_mode: int = 1,
    direction: str = "any",
    limits: ScanLimits | None = None,
) -> tuple[Iterator[dict[str, Any]], DecodeSummary]:
    """Records of every telegram, ACK/NAK and checksum failure in a capture or dump.

    With ``limits``, a scan that breaks a plausibility rule becomes an ``implausible`` record
    with its ``reason`` (the capture header's baud rate, when it has one, overrides theirs).
    The summary fills in as the iterator is consumed.
    """
    summary = DecodeSummary()
    parser = StreamParser(direction, report_failures=True)
    baud = (reader.header or {}).get("baud_rate")
    if limits is not None and baud in BAUD_RATES:
        limits = replace(limits, baud_rate=baud)
    check = ScanCheck(limits) if limits is not None else None

    def judged(event: Event) -> dict[str, Any]:
        record = describe_event(event, measuring_mode)
        if check is not None and record["kind"] == "scan" and isinstance(event, Telegram):
            reason = check.check(decode_scan(event, measuring_mode))
            if reason is not None:
                record.update(kind="implausible", reason=reason.value)
        return record

    def records() -> Iterator[dict[str, Any]]:
        stamp: float | None = None
        for stamp, chunk in reader.chunks():
            summary.bytes += len(chunk)
            for event in parser.feed(chunk, stamp):
                yield count(judged(event))
        for event in parser.close(stamp):
            yield count(judged(event))
        summary.implausible_reasons = dict(check.rejected) if check is not None else {}
        summary.checksum_failures = parser.stats.checksum_failures
        summary.bytes_skipped = parser.stats.bytes_skipped
        summary.truncated_bytes = reader.truncated_bytes
        summary.corrupt_bytes = reader.corrupt_bytes

    def count(record: dict[str, Any]) -> dict[str, Any]:
        kind = record["kind"]
        summary.kinds[kind] = summary.kinds.get(kind, 0) + 1
        if record.get("crc_ok"):
            summary.telegrams += 1
        summary.scans += kind == "scan"
        summary.replies += kind == "reply"
        summary.commands += kind == "command"
        summary.acks += kind == "ack"
        summary.naks += kind == "nak"
        summary.undecodable += kind == "invalid"
        summary.implausible += kind == "implausible"
        return record

    return records(), summary
