"""Measured values (``B0``) of the SICK LMS 200: decoding and encoding scans (§6); no I/O.

:func:`decode_scan` turns a measured-values reply into ranges in metres (NaN for the special
codes: no return, dazzle, out of range, …), flag bits and angles in the scanner frame (0 straight
ahead, counter-clockwise positive — the LMS's own 0° is to the right); :func:`encode_scan` builds
the reply as the sensor sends it (for the emulator). Sections (§n) cite docs/lms200-protocol.md.
"""

from __future__ import annotations

import enum
import functools
import math
import struct
from dataclasses import dataclass, field, fields, replace
from typing import Final

import numpy as np
from numba import njit

from sensors.lms200.protocol.stream import Telegram
from sensors.lms200.protocol.telegram import (
    DISTANCE_MASK,
    FLAG_SHIFT,
    TURN_S,
    ProtocolError,
    reply_frame,
)

__all__ = [
    "VARIANT_BY_COUNT",
    "Scan",
    "ScanBatch",
    "SpecialCode",
    "decode_scan",
    "decode_scans",
    "encode_scan",
    "scan_bearings",
    "scan_interval_s",
]


class SpecialCode(enum.IntEnum):
    """Why a sample has no range (raw values at the top of the distance field, §6.4)."""

    VALID = 0
    NO_RETURN = 1
    DAZZLE = 2
    OVERFLOW = 3
    SIGNAL_TO_NOISE = 4
    CHANNEL_ERROR = 5
    OUT_OF_RANGE = 6
    UNDOCUMENTED = 7


#: Modes whose flag bits are a reflector (intensity) value.
REFLECTOR_MODES: Final = frozenset({1, 3, 5})
# mask − raw → code; raw values ≥ mask − 8 are never distances.
_SPECIAL_BY_GAP: Final = {
    0: SpecialCode.NO_RETURN, 1: SpecialCode.DAZZLE, 2: SpecialCode.OVERFLOW,
    4: SpecialCode.SIGNAL_TO_NOISE, 5: SpecialCode.CHANNEL_ERROR, 8: SpecialCode.OUT_OF_RANGE,
}  # fmt: skip
_RAW_FOR_CODE: Final = {code: gap for gap, code in _SPECIAL_BY_GAP.items()}
#: Complete-scan sizes → (field of view °, resolution °).
VARIANT_BY_COUNT: Final = {101: (100, 1.0), 201: (100, 0.5), 401: (100, 0.25), 181: (180, 1.0),
                            361: (180, 0.5)}  # fmt: skip


@dataclass(frozen=True, slots=True)
class Scan:
    """One planar scan: per sample a range (NaN when invalid), its bearing and its flag bits.

    Bearings are in the scanner frame: 0 straight ahead, counter-clockwise positive.
    """

    ranges_m: np.ndarray  # (N,) float64
    bearing_rad: np.ndarray  # (N,) float64
    flags: np.ndarray  # (N,) uint8: the flag bits of the measuring mode
    code: np.ndarray  # (N,) uint8 SpecialCode
    unit_m: float
    partial: bool = False
    partial_offset_deg: float = 0.0
    scan_index: int | None = None
    telegram_index: int | None = None
    status: int = 0x10
    stamp_s: float | None = None
    measuring_mode: int = 1
    raw: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint16), repr=False)
    count_word: int | None = None  # as received (§6.3); None for a scan not decoded from bytes

    @property
    def valid(self) -> np.ndarray:
        return np.asarray(self.code == SpecialCode.VALID)

    @property
    def reflector(self) -> np.ndarray:
        """Samples marked as retro-reflective (modes with reflector bits only)."""
        if self.measuring_mode not in REFLECTOR_MODES:
            return np.zeros(len(self.flags), dtype=bool)
        return np.asarray(self.flags > 0)

    def with_stamp(self, stamp_s: float) -> Scan:
        return replace(self, stamp_s=stamp_s)


# Each field's slot, set without the frozen dataclass's guard (``_decoded_scan``).
_SCAN_FIELDS = ("ranges_m", "bearing_rad", "flags", "code", "unit_m", "partial",
                "partial_offset_deg", "scan_index", "telegram_index", "status", "stamp_s",
                "measuring_mode", "raw", "count_word")  # fmt: skip
if tuple(f.name for f in fields(Scan)) != _SCAN_FIELDS:  # pragma: no cover - a changed Scan
    raise ImportError("sensors.lms200.protocol.scan: _SCAN_FIELDS no longer lists Scan's fields")
(_set_ranges, _set_bearings, _set_flags, _set_code, _set_unit, _set_partial, _set_offset,
 _set_scan_index, _set_telegram_index, _set_status, _set_stamp, _set_mode, _set_raw,
 _set_count_word) = (getattr(Scan, name).__set__ for name in _SCAN_FIELDS)  # fmt: skip


def _decoded_scan(
    ranges_m: np.ndarray, bearing_rad: np.ndarray, flags: np.ndarray, code: np.ndarray,
    unit_m: float, partial: bool, partial_offset_deg: float, scan_index: int | None,
    telegram_index: int | None, status: int, stamp_s: float | None, measuring_mode: int,
    raw: np.ndarray, count_word: int,
) -> Scan:  # fmt: skip
    """``Scan(...)`` of every field, in their order, with the slots set directly: a capture
    decodes tens of thousands of scans, and the frozen dataclass's ``__init__`` (each field
    through ``object.__setattr__``) took 2.2 µs of a scan's 4.4."""
    scan: Scan = object.__new__(Scan)
    _set_ranges(scan, ranges_m)
    _set_bearings(scan, bearing_rad)
    _set_flags(scan, flags)
    _set_code(scan, code)
    _set_unit(scan, unit_m)
    _set_partial(scan, partial)
    _set_offset(scan, partial_offset_deg)
    _set_scan_index(scan, scan_index)
    _set_telegram_index(scan, telegram_index)
    _set_status(scan, status)
    _set_stamp(scan, stamp_s)
    _set_mode(scan, measuring_mode)
    _set_raw(scan, raw)
    _set_count_word(scan, count_word)
    return scan


@functools.lru_cache(maxsize=64)
def _shared_bearings(count: int, partial: bool, offset_deg: float) -> np.ndarray:
    """One read-only array per variant, shared by every scan of it (a mission decodes tens of
    thousands of scans: a copy each was a third of their memory)."""
    if partial:
        bearings = np.radians(-90.0 + offset_deg + np.arange(count, dtype=float))
    else:
        fov, res = VARIANT_BY_COUNT[count]
        bearings = np.radians(-fov / 2 + res * np.arange(count, dtype=float))
    bearings.flags.writeable = False
    return bearings


def scan_bearings(count: int, partial: bool, offset_deg: float) -> np.ndarray:
    """The bearings (rad, scanner frame) of a scan's samples; read-only, shared per variant."""
    if not partial and count not in VARIANT_BY_COUNT:
        raise ProtocolError(f"a complete scan has 101, 201, 401, 181 or 361 values, got {count}")
    return _shared_bearings(count, partial, offset_deg)


# Why a B0 telegram is malformed, in the order decode_scan checks (0: it is not).
_SHORT, _UNIT, _SIZE, _COUNT = 1, 2, 3, 4
_COMPLETE = np.zeros(1024, dtype=np.bool_)
_COMPLETE[list(VARIANT_BY_COUNT)] = True
# Special code by gap (mask − raw); row 9 stands for every gap above 8 (a distance).
_CODE_BY_GAP = np.full(10, SpecialCode.UNDOCUMENTED, dtype=np.uint8)
_CODE_BY_GAP[9] = SpecialCode.VALID
for _gap, _code in _SPECIAL_BY_GAP.items():
    _CODE_BY_GAP[_gap] = _code


@njit(cache=True)
def _split_scans(  # pragma: no cover - numba
    buf: np.ndarray, data: np.ndarray, complete: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The count words, real-time indices and raw values of many B0 telegrams at once.

    ``data`` (n, 2) holds where each telegram's data (after the reply code, before the status
    byte) starts in ``buf`` and its size. Returns ``errors`` (n,) int8 (0 or why the telegram
    is malformed), ``words`` (n, 4) int64: count word, first value row, scan index and
    telegram index (-1 without), and ``raw`` (V,) uint16: the values of the well-formed ones,
    concatenated in telegram order.
    """
    n = len(data)
    errors = np.zeros(n, np.int8)
    words = np.full((n, 4), -1, np.int64)
    total = 0
    for k in range(n):
        start, size = data[k, 0], data[k, 1]
        if size < 2:
            errors[k] = _SHORT
            continue
        word = buf[start] | (np.int64(buf[start + 1]) << 8)
        count = word & 0x03FF
        partial = (word & 0x2000) != 0
        extra = size - 2 - 2 * count
        words[k, 0] = word
        if word >> 14 > 1:
            errors[k] = _UNIT
        elif extra != 0 and extra != 2:
            errors[k] = _SIZE
        elif not partial and not complete[count]:
            errors[k] = _COUNT
        else:
            words[k, 1] = total
            total += count
            if extra == 2:
                words[k, 2] = buf[start + 2 + 2 * count]
                words[k, 3] = buf[start + 3 + 2 * count]
    raw = np.empty(total, np.uint16)
    for k in range(n):
        if errors[k] == 0:
            start, first = data[k, 0] + 2, words[k, 1]
            for j in range(words[k, 0] & 0x03FF):
                raw[first + j] = buf[start + 2 * j] | (np.uint16(buf[start + 2 * j + 1]) << 8)
    return errors, words, raw


@njit(cache=True)
def _decode_values(  # pragma: no cover - numba
    raw: np.ndarray, bounds: np.ndarray, unit_m: np.ndarray, mask: int, shift: int,
    code_by_gap: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Ranges (m, NaN for special codes), flag bits and special codes of every value (§6.2,
    §6.4); scan ``k`` is rows ``bounds[k]:bounds[k + 1]``, in the unit ``unit_m[k]``."""
    ranges = np.empty(len(raw), np.float64)
    flags = np.empty(len(raw), np.uint8)
    code = np.empty(len(raw), np.uint8)
    for k in range(len(unit_m)):
        unit = unit_m[k]
        for v in range(bounds[k], bounds[k + 1]):
            word = np.int64(raw[v])
            distance = word & mask
            gap = mask - distance
            code[v] = code_by_gap[min(int(gap), 9)]
            ranges[v] = np.nan if gap <= 8 else distance * unit
            flags[v] = np.uint8(word >> shift)
    return ranges, flags, code


@dataclass(frozen=True)
class ScanBatch:
    """Measured-value telegrams decoded together (:func:`decode_scans`).

    Per telegram ``k``: ``errors[k]`` (0 when it is well formed), its count word, real-time
    indices (-1 without) and status; the values of well-formed telegram ``k`` are rows
    ``bounds[k]:bounds[k + 1]`` of the per-value arrays (empty for a malformed one).
    """

    errors: np.ndarray  # (n,) int8
    count_word: np.ndarray  # (n,) int64
    bounds: np.ndarray  # (n + 1,) int64
    scan_index: np.ndarray  # (n,) int64
    telegram_index: np.ndarray  # (n,) int64
    status: np.ndarray  # (n,) int64
    raw: np.ndarray  # (V,) uint16
    ranges_m: np.ndarray  # (V,) float64, NaN for special codes
    flags: np.ndarray  # (V,) uint8
    code: np.ndarray  # (V,) uint8 SpecialCode
    measuring_mode: int

    @property
    def unit_mm(self) -> np.ndarray:
        """(n,) bool: the values are in millimetres (else centimetres)."""
        return np.asarray(self.count_word >> 14 == 1)

    def scans(self, rows: np.ndarray, stamps_s: list[float | None]) -> list[Scan]:
        """The well-formed telegrams ``rows`` as :class:`Scan` (views of the batch's arrays)."""
        rows = np.asarray(rows, np.int64)
        words = self.count_word[rows].tolist()
        starts = self.bounds[rows].tolist()
        stops = self.bounds[rows + 1].tolist()
        scan_index = self.scan_index[rows].tolist()
        telegram_index = self.telegram_index[rows].tolist()
        status = self.status[rows].tolist()
        ranges, flags, code, raw = self.ranges_m, self.flags, self.code, self.raw
        mode = self.measuring_mode
        scans = []
        for k, word in enumerate(words):
            a, b = starts[k], stops[k]
            partial = bool(word & 0x2000)
            offset_deg = 0.25 * ((word >> 11) & 0x03) if partial else 0.0
            indexed = scan_index[k] >= 0
            scans.append(
                _decoded_scan(
                    ranges[a:b],
                    _shared_bearings(b - a, partial, offset_deg),
                    flags[a:b],
                    code[a:b],
                    0.001 if word >> 14 == 1 else 0.01,
                    partial,
                    offset_deg,
                    scan_index[k] if indexed else None,
                    telegram_index[k] if indexed else None,
                    status[k],
                    stamps_s[k],
                    mode,
                    raw[a:b],
                    word,
                )
            )
        return scans


def decode_scans(
    buf: np.ndarray, data: np.ndarray, status: np.ndarray, measuring_mode: int
) -> ScanBatch:
    """Decode many ``B0`` replies at once (§6): ranges, flags and special codes of every value.

    ``buf`` (uint8) holds the telegrams; ``data`` (n, 2) the start and size of each one's data
    (after the reply code, before the status byte); ``status`` (n,) their status bytes. The
    values are those :func:`decode_scan` gives; a malformed telegram is marked in ``errors``.
    """
    if measuring_mode not in DISTANCE_MASK:
        raise ProtocolError(f"unknown measuring mode {measuring_mode}")
    errors, words, raw = _split_scans(buf, np.asarray(data, np.int64).reshape(-1, 2), _COMPLETE)
    count = np.where(errors == 0, words[:, 0] & 0x03FF, 0)
    bounds = np.zeros(len(errors) + 1, np.int64)
    np.cumsum(count, out=bounds[1:])
    unit = np.where(words[:, 0] >> 14 == 1, 0.001, 0.01)
    ranges, flags, code = _decode_values(
        raw, bounds, unit, DISTANCE_MASK[measuring_mode], FLAG_SHIFT[measuring_mode], _CODE_BY_GAP
    )
    return ScanBatch(
        errors=errors,
        count_word=words[:, 0],
        bounds=bounds,
        scan_index=words[:, 2],
        telegram_index=words[:, 3],
        status=np.asarray(status, np.int64),
        raw=raw,
        ranges_m=ranges,
        flags=flags,
        code=code,
        measuring_mode=measuring_mode,
    )


def _malformed(error: int, data: bytes) -> str:
    count_word = data[0] | data[1] << 8 if len(data) >= 2 else 0
    count = count_word & 0x03FF
    return {
        _SHORT: f"B0 reply too short: {len(data)} data bytes",
        _UNIT: f"B0 reply has a reserved unit code {count_word >> 14}",
        _SIZE: f"B0 reply announces {count} values but carries {len(data) - 2} bytes of them",
        _COUNT: f"a complete scan has 101, 201, 401, 181 or 361 values, got {count}",
    }[error]


def decode_scan(telegram: Telegram, measuring_mode: int = 1) -> Scan:
    """Decode a ``B0`` measured-values reply (§6); raises ProtocolError if it is malformed.

    ``measuring_mode`` (block D of the configuration) says which bits are distance and which
    are flags; the sensor does not send it (§6.2), the driver knows it from 74/B1. One telegram
    of :func:`decode_scans`.
    """
    if telegram.code != 0xB0:
        raise ProtocolError(f"not a measured-values reply: code {telegram.code:#04x}")
    data = telegram.data
    status = telegram.status if telegram.status is not None else 0
    batch = decode_scans(
        np.frombuffer(data, dtype=np.uint8), np.array([[0, len(data)]]), np.array([status]),
        measuring_mode,
    )  # fmt: skip
    if batch.errors[0]:
        raise ProtocolError(_malformed(int(batch.errors[0]), data))
    return batch.scans(np.zeros(1, np.int64), [telegram.stamp_s])[0]


def encode_scan(
    ranges_m: np.ndarray,
    *,
    flags: np.ndarray | None = None,
    codes: np.ndarray | None = None,
    measuring_mode: int = 1,
    unit_mm: bool = True,
    scan_index: int | None = None,
    telegram_index: int | None = None,
    status: int = 0x10,
    addr: int = 0x80,
) -> bytes:
    """A ``B0`` reply as the sensor sends it: ranges rounded to the unit, flags in the high bits.

    NaN ranges, ranges beyond the mode's field, and samples whose ``codes`` entry is not VALID
    become special codes (default: no return).
    """
    ranges_m = np.asarray(ranges_m, dtype=float)
    count = len(ranges_m)
    if count not in VARIANT_BY_COUNT:
        raise ProtocolError(f"a complete scan has 101, 201, 401, 181 or 361 values, got {count}")
    mask = DISTANCE_MASK[measuring_mode]
    unit_m = 0.001 if unit_mm else 0.01
    with np.errstate(invalid="ignore"):
        distance = np.round(ranges_m / unit_m)
    special = ~np.isfinite(distance) | (distance < 0) | (distance > mask - 9)
    gaps = np.zeros(count, dtype=np.int64)
    if codes is not None:
        codes = np.asarray(codes, dtype=np.uint8)
        for code, gap in _RAW_FOR_CODE.items():
            gaps[codes == code] = gap
        special |= codes != SpecialCode.VALID
    words = np.where(special, mask - gaps, np.nan_to_num(distance)).astype(np.uint32)
    if flags is not None:
        shift = FLAG_SHIFT[measuring_mode]
        limit = (0xFFFF >> shift) if shift < 16 else 0
        flag_bits = np.clip(np.asarray(flags, dtype=np.uint32), 0, limit)
        words |= (flag_bits << shift) & (0xFFFF ^ mask)
    count_word = count | (0x4000 if unit_mm else 0x0000)
    payload = struct.pack("<H", count_word) + words.astype("<u2").tobytes()
    if scan_index is not None or telegram_index is not None:
        payload += bytes(((scan_index or 0) & 0xFF, (telegram_index or 0) & 0xFF))
    return reply_frame(0xB0, payload, status, addr)


def scan_interval_s(baud_rate: int, count: int, resolution_deg: float, indices: bool) -> float:
    """Time between measured-value telegrams in continuous mode (§8).

    The sensor finishes a scan every T = 13.32 ms × (1, 2, 4) for 1°, 0.5°, 0.25° and only starts
    a telegram at a scan boundary: scans completed during a transmission are dropped.
    """
    period = TURN_S * {1.0: 1, 0.5: 2, 0.25: 4}[resolution_deg]
    transmit = (10 + 2 * count + (2 if indices else 0)) * 10.0 / baud_rate
    lost = math.ceil(transmit / period - 1e-9) if transmit > period else 0
    return (lost + 1) * period
