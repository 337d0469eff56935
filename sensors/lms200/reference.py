"""The per-telegram decoding path that :class:`~sensors.lms200.decoder.ScanDecoder` replaced.

Kept as it was (names aside) as the reference that the tests and ``coopmap bench decode``
compare the vectorised path against: a capture's records read one by one
(:func:`reference_records`), each chunk through
:class:`~sensors.lms200.protocol.stream.StreamParser` into ``Telegram`` objects, each
measured-values telegram decoded with numpy on its own (:func:`decode_scan`) and judged by the
rules in Python (:class:`ReferenceCheck`); :class:`ReferenceDecoder` strings them together as
the mission's decoder did. Nothing in production uses this module.
"""

from __future__ import annotations

import math
import mmap
import os
import struct
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from sensors.lms200.capture import MAX_RECORD, MAX_RECORD_GAP_S, STAMP_SLACK_S, CaptureReader
from sensors.lms200.protocol.plausibility import (
    CM_MAX_RANGE_M,
    MODE_MAX_RANGE_M,
    RANGE_MARGIN,
    Implausible,
    ScanLimits,
)
from sensors.lms200.protocol.scan import Scan, SpecialCode, scan_bearings
from sensors.lms200.protocol.stream import StreamParser, Telegram
from sensors.lms200.protocol.telegram import (
    DISTANCE_MASK,
    FLAG_SHIFT,
    TURN_S,
    ProtocolError,
)

__all__ = [
    "ReferenceCheck",
    "ReferenceDecoder",
    "decode_scan",
    "implausibility",
    "reference_records",
]

# The protocol's constants, as the reference used them.
SPECIAL_BY_GAP = {
    0: SpecialCode.NO_RETURN, 1: SpecialCode.DAZZLE, 2: SpecialCode.OVERFLOW,
    4: SpecialCode.SIGNAL_TO_NOISE, 5: SpecialCode.CHANNEL_ERROR, 8: SpecialCode.OUT_OF_RANGE,
}  # fmt: skip
_DOCUMENTED_GAPS = (0, 1, 2, 4, 5, 8)
_COUNT_BITS = 0x03FF
_UNIT_SHIFT = 14
_RECORD = struct.Struct("<dI")


def decode_scan(telegram: Telegram, measuring_mode: int = 1) -> Scan:
    """Decode a ``B0`` measured-values reply (§6); raises ProtocolError if it is malformed.

    ``measuring_mode`` (block D of the configuration) says which bits are distance and which
    are flags; the sensor does not send it (§6.2), the driver knows it from 74/B1.
    """
    if telegram.code != 0xB0:
        raise ProtocolError(f"not a measured-values reply: code {telegram.code:#04x}")
    if measuring_mode not in DISTANCE_MASK:
        raise ProtocolError(f"unknown measuring mode {measuring_mode}")
    data = telegram.data
    if len(data) < 2:
        raise ProtocolError(f"B0 reply too short: {len(data)} data bytes")
    (count_word,) = struct.unpack_from("<H", data, 0)
    count = count_word & 0x03FF
    partial = bool(count_word & 0x2000)
    unit_bits = count_word >> 14
    if unit_bits > 1:
        raise ProtocolError(f"B0 reply has a reserved unit code {unit_bits}")
    unit_m = 0.001 if unit_bits == 1 else 0.01
    extra = len(data) - 2 - 2 * count
    if extra not in (0, 2):
        raise ProtocolError(
            f"B0 reply announces {count} values but carries {len(data) - 2} bytes of them"
        )
    offset_deg = 0.25 * ((count_word >> 11) & 0x03) if partial else 0.0
    bearings = scan_bearings(count, partial, offset_deg)
    raw = np.frombuffer(data, dtype="<u2", count=count, offset=2).astype(np.uint16)
    mask = DISTANCE_MASK[measuring_mode]
    distance = (raw & mask).astype(np.int64)
    flags = (raw.astype(np.uint32) >> FLAG_SHIFT[measuring_mode]).astype(np.uint8)
    gap = mask - distance
    code = np.zeros(count, dtype=np.uint8)
    special = gap <= 8
    if special.any():
        lookup = np.full(9, SpecialCode.UNDOCUMENTED, dtype=np.uint8)
        for g, c in SPECIAL_BY_GAP.items():
            lookup[g] = c
        code[special] = lookup[gap[special]]
    ranges = np.where(special, np.nan, distance * unit_m)
    scan_index = telegram_index = None
    if extra == 2:
        scan_index, telegram_index = data[2 + 2 * count], data[3 + 2 * count]
    return Scan(
        ranges_m=ranges,
        bearing_rad=bearings,
        flags=flags,
        code=code,
        unit_m=unit_m,
        partial=partial,
        partial_offset_deg=offset_deg,
        scan_index=scan_index,
        telegram_index=telegram_index,
        status=telegram.status if telegram.status is not None else 0,
        stamp_s=telegram.stamp_s,
        measuring_mode=measuring_mode,
        raw=raw,
        count_word=count_word,
    )


def implausibility(
    scan: Scan, limits: ScanLimits, realtime_indices: bool | None = None
) -> Implausible | None:
    """The first rule a scan breaks that needs no other scan, or None if it breaks none.

    ``realtime_indices`` overrides ``limits.realtime_indices`` (a stream's learnt choice).
    """
    if len(scan.raw) != limits.count or scan.partial:
        return Implausible.COUNT
    if scan.count_word is not None and scan.count_word & ~(_COUNT_BITS | 3 << _UNIT_SHIFT):
        return Implausible.COUNT
    indices = limits.realtime_indices if realtime_indices is None else realtime_indices
    if indices is not None and indices != (scan.scan_index is not None):
        return Implausible.LENGTH
    if (scan.unit_m == 0.001) != limits.unit_mm:
        return Implausible.UNIT
    mask = DISTANCE_MASK[scan.measuring_mode]
    shift = FLAG_SHIFT[scan.measuring_mode]
    raw = scan.raw.astype(np.int64)
    if np.any(raw & ~(mask | (0xFFFF >> shift << shift))):
        return Implausible.FLAGS
    max_m = MODE_MAX_RANGE_M[scan.measuring_mode] if limits.unit_mm else CM_MAX_RANGE_M
    longest = min(mask - 9, math.floor(max_m * RANGE_MARGIN / scan.unit_m + 1e-9))
    gap = mask - (raw & mask)
    coded = np.isin(gap, _DOCUMENTED_GAPS)
    if np.any(~coded & ((raw & mask) > longest)):
        return Implausible.RANGE
    if scan.status & 0x07 > 4:
        return Implausible.STATUS
    return None


@dataclass(frozen=True)
class _Mark:
    """A scan's place in the sequence: its turn count since the anchor epoch began."""

    turn: int
    scan_index: int
    telegram_index: int
    stamp_s: float | None


class ReferenceCheck:
    """ScanCheck as it was: the rules and the sequence in Python, one scan at a time.

    The sequence rule compares each scan with the last accepted one, so a corrupted telegram is
    rejected alone and the good ones after it are kept; gaps from lost telegrams are allowed.
    The host stamps place the scan index (the mirror-turn counter mod 256) in time: a scan
    measured earlier than the host clock allows, relative to the earliest arrival seen in the
    last ``window`` scans, is rejected. Two consecutive rejected scans that agree with each
    other start the sequence anew (the sensor was reset or the stream restarted).
    ``rejected`` counts the rejections by reason.
    """

    def __init__(self, limits: ScanLimits, window: int = 64) -> None:
        self.limits = limits
        self.accepted = 0
        self.rejected: dict[str, int] = {}
        self._indices = limits.realtime_indices
        self._turns = limits.turns_per_telegram
        self._anchor: _Mark | None = None
        self._candidate: _Mark | None = None
        self._former: _Mark | None = None  # the anchor before a telegram counter restart
        self._arrivals: deque[float] = deque(maxlen=window)  # stamp − turn·T of accepted scans

    def check(self, scan: Scan) -> Implausible | None:
        """Why ``scan`` is implausible after the scans before it, or None (it is accepted)."""
        reason = implausibility(scan, self.limits, self._indices)
        if reason is None and scan.scan_index is not None and scan.telegram_index is not None:
            reason = self._sequence(scan)
        if reason is None:
            self.accepted += 1
            if self._indices is None:
                self._indices = scan.scan_index is not None
        else:
            self.rejected[reason.value] = self.rejected.get(reason.value, 0) + 1
        return reason

    def copy(self) -> ReferenceCheck:
        """An independent copy: what it is fed next does not change this one."""
        twin = ReferenceCheck(self.limits, self._arrivals.maxlen or 64)
        twin.__dict__.update(self.__dict__)
        twin.rejected = dict(self.rejected)
        twin._arrivals = deque(self._arrivals, maxlen=self._arrivals.maxlen)
        return twin

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    def _start(self, scan: Scan) -> None:
        self._anchor = _Mark(0, int(scan.scan_index or 0), int(scan.telegram_index or 0),
                             scan.stamp_s)  # fmt: skip
        self._candidate = self._former = None
        self._arrivals.clear()
        if scan.stamp_s is not None:
            self._arrivals.append(scan.stamp_s)

    def _sequence(self, scan: Scan) -> Implausible | None:
        if self._anchor is None:
            self._start(scan)
            return None
        earliest = min(self._arrivals) if self._arrivals else None
        before = self._anchor
        turn = self._follows(before, scan, earliest)
        if turn is None and self._former is not None:
            before = self._former  # the telegram counter had not restarted after all
            turn = self._follows(before, scan, earliest)
        if turn is not None:
            restarted = scan.telegram_index == 0 and before.telegram_index != 255
            self._former = before if restarted else None
            self._anchor = _Mark(turn, int(scan.scan_index or 0), int(scan.telegram_index or 0),
                                 scan.stamp_s)  # fmt: skip
            self._candidate = None
            if scan.stamp_s is not None:
                self._arrivals.append(scan.stamp_s - turn * TURN_S)
            return None
        candidate = self._candidate
        if candidate is not None and self._follows(candidate, scan, candidate.stamp_s) is not None:
            self._start(scan)
            return None
        self._candidate = _Mark(0, int(scan.scan_index or 0), int(scan.telegram_index or 0),
                                scan.stamp_s)  # fmt: skip
        return Implausible.SEQUENCE

    def _follows(self, before: _Mark, scan: Scan, earliest_s: float | None) -> int | None:
        """The scan's turn count if it can follow ``before``, else None.

        ``earliest_s`` is the earliest arrival (stamp − turn·T) seen so far in this epoch.
        """
        telegrams = (int(scan.telegram_index or 0) - before.telegram_index) % 256
        if scan.telegram_index == 0:
            # A telegram counter that starts again from 0 needs one interval at least (the
            # simulator restarts it with every chunk of scans it writes to a capture).
            telegrams = 1
        if telegrams == 0:
            return None  # the same telegram index twice
        fewest = self._turns * telegrams  # a telegram leaves at most every K turns (§8)
        step = (int(scan.scan_index or 0) - before.scan_index) % 256
        if scan.stamp_s is None or before.stamp_s is None or earliest_s is None:
            # No host clock: allow up to one more lost scan per telegram (§11).
            wraps = max(0, math.ceil((fewest - step) / 256))
            turns = step + 256 * wraps
            return before.turn + turns if turns <= (self._turns + 1) * telegrams else None
        # Unwrap the turn counter: the fewest turns that the telegram index needs and that have
        # the scan arrive at most late_s after the earliest arrival.
        lower = max(fewest, (scan.stamp_s - earliest_s - self.limits.late_s) / TURN_S - before.turn)
        turns = step + 256 * max(0, math.ceil((lower - step) / 256))
        arrival = scan.stamp_s - (before.turn + turns) * TURN_S
        if arrival < earliest_s - self.limits.early_s:
            return None  # measured later than it arrived: the counter ran ahead
        return before.turn + turns


# --------------------------------------------------------------------------------------------
# Records one by one (CaptureReader.chunks as it was)


def reference_records(reader: CaptureReader) -> Iterator[tuple[float | None, bytes]]:
    """(stamp_s, bytes) of the reader's file in order, read a record at a time; counts what it
    drops in the reader's ``truncated_bytes``, ``corrupt_bytes`` and ``resyncs``."""
    with open(reader.path, "rb") as handle:
        if not reader.is_capture:
            while chunk := handle.read(1 << 16):
                yield None, chunk
            return
        offset = len(handle.readline()) + len(handle.readline())  # the magic and JSON lines
        size = os.fstat(handle.fileno()).st_size
        if size <= offset:
            return
        with mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ) as view:
            yield from _records(reader, view, offset, size)


def _records(
    reader: CaptureReader, view: mmap.mmap, pos: int, end: int
) -> Iterator[tuple[float, bytes]]:
    last = None
    while pos < end:
        if end - pos < _RECORD.size:
            reader.truncated_bytes += end - pos
            return
        stamp, size = _RECORD.unpack_from(view, pos)
        if not _plausible(stamp, size, last):
            found = _resync(view, pos + 1, end, last)
            reader.resyncs += 1
            reader.corrupt_bytes += found - pos
            pos = found
            continue
        body_end = pos + _RECORD.size + size
        if body_end > end:
            reader.truncated_bytes += end - pos
            return
        yield stamp, bytes(view[pos + _RECORD.size : body_end])
        last, pos = stamp, body_end


def _resync(view: mmap.mmap, pos: int, end: int, last: float | None) -> int:
    """The first offset from ``pos`` where two plausible records follow each other."""
    while pos + _RECORD.size <= end:
        stamp, size = _RECORD.unpack_from(view, pos)
        if _plausible(stamp, size, last):
            after = pos + _RECORD.size + size
            if after == end:
                return pos
            if after + _RECORD.size <= end:
                next_stamp, next_size = _RECORD.unpack_from(view, after)
                if _plausible(next_stamp, next_size, stamp):
                    return pos
        pos += 1
    return end


def _plausible(stamp: float, size: int, last: float | None) -> bool:
    if not (0 < size <= MAX_RECORD and math.isfinite(stamp)):
        return False
    return last is None or last - STAMP_SLACK_S <= stamp <= last + MAX_RECORD_GAP_S


# --------------------------------------------------------------------------------------------
# The decoder of a stream (the mission's LmsDecoder as it was, without the scan clock)


@dataclass
class ReferenceDecoder:
    """Chunks → plausible stamped scans, one telegram at a time; counters as ScanDecoder's."""

    measuring_mode: int = 1
    limits: ScanLimits | None = None

    def __post_init__(self) -> None:
        self.parser = StreamParser()
        self.check = ReferenceCheck(self.limits) if self.limits is not None else None
        self.decoded = self.undecodable = 0
        self.last_stamp: float | None = None

    def feed(self, chunk: bytes, stamp_s: float | None = None) -> list[Scan]:
        self.last_stamp = stamp_s
        scans = []
        for event in self.parser.feed(chunk, stamp_s):
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
                    scans.append(scan)
        return scans

    def close(self) -> None:
        self.parser.close(self.last_stamp)

    def decode(self, reader: CaptureReader) -> list[Scan]:
        """Every plausible stamped scan of a capture, then :meth:`close`."""
        scans = []
        for stamp, chunk in reference_records(reader):
            scans += self.feed(chunk, stamp)
        self.close()
        return scans
