"""The stream parser of the SICK LMS 200 protocol: byte chunks → telegrams (§4.4); no I/O.

:class:`StreamParser` takes arbitrary chunks of a byte stream and yields telegrams and lone
ACK/NAK bytes, resynchronising after garbage, truncated frames, absurd lengths and bad
checksums — counted in :class:`ParserStats`, never raised. Sections (§n) cite
docs/lms200-protocol.md.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
from numba import njit

from sensors.lms200.protocol.telegram import MAX_LEN, STX, ProtocolError, checksum, checksum_kernel

__all__ = [
    "Event",
    "Handshake",
    "ParserStats",
    "Rejected",
    "StreamParser",
    "Telegram",
    "scan_chunks",
]

_KIND_FRAME, _KIND_ACK, _KIND_NAK, _KIND_REJECTED = 0, 1, 2, 3
_DIRECTION = {"from_sensor": 0, "to_sensor": 1, "any": 2}


_INVALID, _INCOMPLETE, _BAD_CHECKSUM = -1, -2, -3


@njit(cache=True)
def _frame_at(buf: np.ndarray, p: int, direction: int, max_len: int) -> int:  # pragma: no cover
    """Length of the checksum-valid frame at ``p``, or _INVALID, _INCOMPLETE, _BAD_CHECKSUM."""
    n = len(buf)
    if p + 4 > n:
        return _INCOMPLETE
    reply = (buf[p + 1] & 0x80) != 0
    if (direction == 0 and not reply) or (direction == 1 and reply):
        return _INVALID
    length = buf[p + 2] | (buf[p + 3] << 8)
    if length < (2 if reply else 1) or length > max_len:
        return _INVALID
    end = p + length + 6
    if end > n:
        return _INCOMPLETE
    if checksum_kernel(buf, p, end - 2) != (buf[end - 2] | (buf[end - 1] << 8)):
        return _BAD_CHECKSUM
    return length + 6


@njit(cache=True)
def _scan_stream(  # pragma: no cover - numba
    buf: np.ndarray, direction: int, max_len: int, final: bool, report_failures: bool
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, int, int, int]:
    """Find frames, ACK and NAK bytes in ``buf``.

    A frame that is not complete yet stops the scan (its bytes are kept for the next chunk)
    unless the stream has ended (``final``) or a complete valid frame already follows within
    the held bytes — then the incomplete one was a false start and is skipped.
    Returns (count, kinds, offsets, lengths, consumed, skipped, checksum_failures).
    """
    n = len(buf)
    kinds = np.empty(n, np.int8)
    offsets = np.empty(n, np.int64)
    lengths = np.empty(n, np.int64)
    count = 0
    skipped = 0
    failures = 0
    p = 0
    # Bytes inside a frame that failed its checksum are that frame's payload, not handshakes:
    # the scan resumes after its STX (a real frame may start inside it) but reports no ACK or
    # NAK before the rejected frame's end.
    quiet_until = 0
    while p < n:
        byte = buf[p]
        if byte != 0x02:
            if (byte == 0x06 or byte == 0x15) and p >= quiet_until:
                kinds[count] = 1 if byte == 0x06 else 2
                offsets[count] = p
                lengths[count] = 1
                count += 1
            else:
                skipped += 1
            p += 1
            continue
        size = _frame_at(buf, p, direction, max_len)
        if size == _INCOMPLETE:
            false_start = final
            q = p + 1
            while not false_start and q + 6 <= n:
                if buf[q] == 0x02 and _frame_at(buf, q, direction, max_len) > 0:
                    false_start = True
                q += 1
            if not false_start:
                break
            skipped += 1
            p += 1
            continue
        if size < 0:
            if size == _BAD_CHECKSUM:
                quiet_until = max(quiet_until, p + (buf[p + 2] | (buf[p + 3] << 8)) + 6)
                failures += 1
                if report_failures:
                    kinds[count] = 3
                    offsets[count] = p
                    lengths[count] = (buf[p + 2] | (buf[p + 3] << 8)) + 6
                    count += 1
            skipped += 1
            p += 1
            continue
        kinds[count] = 0
        offsets[count] = p
        lengths[count] = size
        count += 1
        p += size
    return count, kinds, offsets, lengths, p, skipped, failures


@njit(cache=True)
def _grown_rows(rows: np.ndarray, used: int) -> np.ndarray:  # pragma: no cover - numba
    bigger = np.empty((2 * len(rows), rows.shape[1]), rows.dtype)
    bigger[:used] = rows[:used]
    return bigger


@njit(cache=True)
def scan_chunks(  # pragma: no cover - numba
    buf: np.ndarray, ends: np.ndarray, direction: int, max_len: int, final: bool
) -> tuple[np.ndarray, np.ndarray]:
    """What :meth:`StreamParser.feed` finds, chunk after chunk, in one call (no events built).

    ``buf`` holds the bytes the parser held followed by the new chunks; chunk ``c`` ends at
    ``ends[c]`` (non-decreasing, at most ``len(buf)``). Each chunk is parsed exactly as ``feed``
    parses it, the bytes still held plus the chunk, with ``final`` as ``close`` sets it. Returns
    ``frames`` (F, 3) int64: offset in ``buf``, length and chunk of each checksum-valid frame,
    and ``counts`` [bytes consumed, skipped, checksum failures, ACKs, NAKs].
    """
    frames = np.empty((max(16, len(buf) // 64), 3), np.int64)
    found = 0
    consumed = skipped = failures = acks = naks = 0
    for c in range(len(ends)):
        count, kinds, offsets, lengths, used, skip, fail = _scan_stream(
            buf[consumed : ends[c]], direction, max_len, final, False
        )
        for k in range(count):
            if kinds[k] == _KIND_FRAME:
                if found == len(frames):
                    frames = _grown_rows(frames, found)
                frames[found, 0] = consumed + offsets[k]
                frames[found, 1] = lengths[k]
                frames[found, 2] = c
                found += 1
            elif kinds[k] == _KIND_ACK:
                acks += 1
            else:
                naks += 1
        consumed += used
        skipped += skip
        failures += fail
    counts = np.array([consumed, skipped, failures, acks, naks], np.int64)
    return frames[:found], counts


@dataclass(frozen=True)
class Telegram:
    """One checksum-valid frame found in a stream."""

    offset: int  # of the STX in the whole stream
    addr: int
    code: int
    data: bytes  # after the code, without the status byte
    status: int | None  # replies only
    stamp_s: float | None = None  # receive time of the chunk that completed it

    @property
    def from_sensor(self) -> bool:
        return bool(self.addr & 0x80)

    @property
    def raw(self) -> bytes:
        body = (
            bytes((self.code,))
            + self.data
            + (b"" if self.status is None else bytes((self.status,)))
        )
        head = bytes((STX, self.addr)) + struct.pack("<H", len(body)) + body
        return head + struct.pack("<H", checksum(head))


@dataclass(frozen=True)
class Handshake:
    """A lone ACK (06) or NAK (15) byte seen between frames."""

    offset: int
    ack: bool
    stamp_s: float | None = None


@dataclass(frozen=True)
class Rejected:
    """A frame whose header was plausible but whose checksum was wrong (when reported)."""

    offset: int
    addr: int
    code: int
    length: int  # bytes the frame claimed, checksum included
    stamp_s: float | None = None


Event = Telegram | Handshake | Rejected


@dataclass
class ParserStats:
    bytes_in: int = 0
    telegrams: int = 0
    acks: int = 0
    naks: int = 0
    checksum_failures: int = 0
    bytes_skipped: int = 0


class StreamParser:
    """Incremental LMS 2xx stream parser; feed it any chunks, it never raises on their bytes.

    ``direction`` is ``"from_sensor"`` (replies: ADDR bit 7 set, LEN ≥ 2, a status byte),
    ``"to_sensor"`` (host commands) or ``"any"`` (decided per frame by ADDR bit 7).
    Memory is bounded: at most one incomplete frame (≤ 818 bytes) is held between feeds.
    """

    def __init__(
        self,
        direction: str = "from_sensor",
        max_len: int = MAX_LEN,
        *,
        report_failures: bool = False,
    ) -> None:
        if direction not in _DIRECTION:
            raise ProtocolError(f"direction must be one of {sorted(_DIRECTION)}, got {direction!r}")
        self._direction = _DIRECTION[direction]
        self._report_failures = report_failures
        self._max_len = max_len
        self._buffer = bytearray()
        self._base = 0  # stream offset of self._buffer[0]
        self.stats = ParserStats()

    @property
    def pending(self) -> int:
        """Bytes held while waiting for the rest of a frame."""
        return len(self._buffer)

    def feed(self, chunk: bytes, stamp_s: float | None = None) -> list[Event]:
        """Parse the next chunk of the stream; returns what it completed, in stream order."""
        self.stats.bytes_in += len(chunk)
        self._buffer += chunk
        return self._parse(stamp_s, final=False)

    def close(self, stamp_s: float | None = None) -> list[Event]:
        """End of stream: no frame can complete any more; parse what is held and drop the rest."""
        return self._parse(stamp_s, final=True)

    def _parse(self, stamp_s: float | None, final: bool) -> list[Event]:
        buf = np.frombuffer(bytes(self._buffer), dtype=np.uint8)
        count, kinds, offsets, lengths, consumed, skipped, failures = _scan_stream(
            buf, self._direction, self._max_len, final, self._report_failures
        )
        events: list[Event] = []
        for k in range(count):
            start = int(offsets[k])
            if kinds[k] == _KIND_FRAME:
                end = start + int(lengths[k])
                reply = bool(buf[start + 1] & 0x80)
                body_end = end - 3 if reply else end - 2
                events.append(
                    Telegram(
                        offset=self._base + start,
                        addr=int(buf[start + 1]),
                        code=int(buf[start + 4]),
                        data=bytes(self._buffer[start + 5 : body_end]),
                        status=int(buf[end - 3]) if reply else None,
                        stamp_s=stamp_s,
                    )
                )
                self.stats.telegrams += 1
            elif kinds[k] == _KIND_REJECTED:
                size = int(lengths[k])
                events.append(
                    Rejected(
                        self._base + start, int(buf[start + 1]), int(buf[start + 4]), size, stamp_s
                    )
                )
            else:
                events.append(Handshake(self._base + start, bool(kinds[k] == _KIND_ACK), stamp_s))
                if kinds[k] == _KIND_ACK:
                    self.stats.acks += 1
                else:
                    self.stats.naks += 1
        self.stats.bytes_skipped += int(skipped)
        self.stats.checksum_failures += int(failures)
        del self._buffer[: int(consumed)]
        self._base += int(consumed)
        return events
