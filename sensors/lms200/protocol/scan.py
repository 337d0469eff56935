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
from dataclasses import dataclass, field, replace
from typing import Final

import numpy as np

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
    "SpecialCode",
    "decode_scan",
    "encode_scan",
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


def _bearings(count: int, partial: bool, offset_deg: float) -> np.ndarray:
    if not partial and count not in VARIANT_BY_COUNT:
        raise ProtocolError(f"a complete scan has 101, 201, 401, 181 or 361 values, got {count}")
    return _shared_bearings(count, partial, offset_deg)


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
    bearings = _bearings(count, partial, offset_deg)
    raw = np.frombuffer(data, dtype="<u2", count=count, offset=2).astype(np.uint16)
    mask = DISTANCE_MASK[measuring_mode]
    distance = (raw & mask).astype(np.int64)
    flags = (raw.astype(np.uint32) >> FLAG_SHIFT[measuring_mode]).astype(np.uint8)
    gap = mask - distance
    code = np.zeros(count, dtype=np.uint8)
    special = gap <= 8
    if special.any():
        lookup = np.full(9, SpecialCode.UNDOCUMENTED, dtype=np.uint8)
        for g, c in _SPECIAL_BY_GAP.items():
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
