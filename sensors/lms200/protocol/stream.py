"""The SICK LMS 200 serial telegram protocol: bytes ↔ telegrams, no I/O.

Frame (both directions): ``STX 02 | ADDR | LEN (LE u16) | CMD/REPLY | DATA | [STATUS] | CRC (LE)``
where LEN counts the bytes after LEN up to, not including, the checksum; replies carry a status
byte as their last data byte. The checksum is SICK's own 16-bit signature (generator 0x8005,
one shift per byte, XOR with the previous and current byte) — not a library CRC-16 preset.

* :func:`checksum`, :func:`frame` build telegrams; the ``cmd_*`` functions encode every command
  a driver needs; the ``encode_*`` functions build the sensor's replies (for the emulator).
* :class:`StreamParser` takes arbitrary chunks of a byte stream and yields telegrams and lone
  ACK/NAK bytes, resynchronising after garbage, truncated frames, absurd lengths and bad
  checksums — counted in :class:`ParserStats`, never raised.
* :func:`decode_scan` turns a measured-values reply (``B0``) into ranges in metres (NaN for the
  special codes: no return, dazzle, out of range, …), flag bits and angles in the scanner frame
  (0 straight ahead, counter-clockwise positive — the LMS's own 0° is to the right);
  :func:`decode_reply` decodes the other replies.

Reference: specs/lms200-protocol.md (sections cited as §n).
"""

from __future__ import annotations

import enum
import math
import struct
from dataclasses import dataclass, field, replace
from typing import Final

import numpy as np
from numba import njit

from sensors.errors import SensorError

__all__ = [
    "ACK",
    "BAUD_RATES",
    "MAX_LEN",
    "NAK",
    "STX",
    "ConfigReply",
    "Event",
    "Handshake",
    "IncorrectCommand",
    "LmsConfig",
    "ModeReply",
    "ParserStats",
    "PermanentBaudReply",
    "PowerOn",
    "ProtocolError",
    "Rejected",
    "Reply",
    "ResetAck",
    "Scan",
    "SpecialCode",
    "StatusReply",
    "StreamParser",
    "Telegram",
    "TypeReply",
    "VariantReply",
    "checksum",
    "cmd_continuous",
    "cmd_installation_mode",
    "cmd_mode",
    "cmd_permanent_baud",
    "cmd_read_config",
    "cmd_request_errors",
    "cmd_request_scan",
    "cmd_request_status",
    "cmd_request_type",
    "cmd_reset",
    "cmd_set_baud",
    "cmd_stop",
    "cmd_variant",
    "cmd_write_config",
    "decode_reply",
    "decode_scan",
    "encode_config_reply",
    "encode_mode_reply",
    "encode_scan",
    "encode_status_reply",
    "encode_variant_reply",
    "frame",
    "reply_frame",
    "scan_interval_s",
]

STX: Final = 0x02
ACK: Final = 0x06
NAK: Final = 0x15
#: Largest LEN of any standard reply (401 values with real-time indices, §2).
MAX_LEN: Final = 812
BAUD_RATES: Final = (9600, 19200, 38400, 500000)
#: One internal mirror turn of the LMS (75 Hz); 0.5° needs 2 turns, 0.25° 4 (§6.5).
TURN_S: Final = 0.01332

# Operating-mode sub-codes of command 20 (§5.2).
MODE_INSTALLATION: Final = 0x00
MODE_CONTINUOUS: Final = 0x24
MODE_ON_REQUEST: Final = 0x25
MODE_TEST_PASSWORD: Final = 0x30
_BAUD_MODE: Final = {38400: 0x40, 19200: 0x41, 9600: 0x42, 500000: 0x48}
_BAUD_STATUS_CODE: Final = {9600: 0x8067, 19200: 0x8033, 38400: 0x8019, 500000: 0x8001}


class ProtocolError(SensorError):
    """A telegram cannot be built or decoded; the message says what was wrong."""


# --------------------------------------------------------------------------------------------
# Checksum and framing


@njit(cache=True)
def _checksum(buf: np.ndarray, start: int, stop: int) -> int:  # pragma: no cover - numba
    register = 0
    previous = 0
    for k in range(start, stop):
        byte = buf[k]
        carry = 0x8005 if register & 0x8000 else 0
        register = ((register << 1) & 0xFFFF) ^ carry ^ ((previous << 8) | byte)
        previous = byte
    return register


def checksum(data: bytes | bytearray | memoryview) -> int:
    """SICK's checksum over ``data`` (STX through the last byte before the checksum), §3.1."""
    buf = np.frombuffer(bytes(data), dtype=np.uint8)
    return int(_checksum(buf, 0, len(buf)))


def _framed(addr: int, body: bytes) -> bytes:
    if not 0 <= addr <= 0xFF:
        raise ProtocolError(f"address must be 0-255, got {addr}")
    if not 1 <= len(body) <= MAX_LEN:
        raise ProtocolError(f"telegram body must be 1-{MAX_LEN} bytes, got {len(body)}")
    head = bytes((STX, addr)) + struct.pack("<H", len(body)) + body
    return head + struct.pack("<H", checksum(head))


def frame(command: int, data: bytes = b"", addr: int = 0x00) -> bytes:
    """A host → sensor telegram: command code and parameters (no status byte)."""
    if not 0 <= command <= 0x8F:
        raise ProtocolError(f"host command codes are 00-8F, got {command:#04x}")
    return _framed(addr, bytes((command,)) + bytes(data))


def reply_frame(code: int, data: bytes = b"", status: int = 0x10, addr: int = 0x80) -> bytes:
    """A sensor → host telegram: reply code, data and the status byte (§7)."""
    if not 0x90 <= code <= 0xFF:
        raise ProtocolError(f"reply codes are 90-FF, got {code:#04x}")
    return _framed(addr | 0x80, bytes((code,)) + bytes(data) + bytes((status,)))


# --------------------------------------------------------------------------------------------
# Commands (host → sensor), §5


def cmd_reset(addr: int = 0) -> bytes:
    return frame(0x10, addr=addr)


def cmd_mode(sub_mode: int, params: bytes = b"", addr: int = 0) -> bytes:
    """Switch operating mode (command 20) to ``sub_mode`` with its parameters."""
    if not 0 <= sub_mode <= 0xFF:
        raise ProtocolError(f"operating mode must be a byte, got {sub_mode}")
    return frame(0x20, bytes((sub_mode,)) + params, addr)


def _password(password: str) -> bytes:
    raw = password.encode("ascii", errors="replace")
    if len(raw) != 8:
        raise ProtocolError(f"the LMS password has 8 ASCII characters, got {password!r}")
    return raw


def cmd_installation_mode(password: str = "SICK_LMS", addr: int = 0) -> bytes:
    return cmd_mode(MODE_INSTALLATION, _password(password), addr)


def cmd_test_password(password: str = "SICK_LMS", addr: int = 0) -> bytes:
    return cmd_mode(MODE_TEST_PASSWORD, _password(password), addr)


def cmd_set_baud(baud_rate: int, addr: int = 0) -> bytes:
    if baud_rate not in _BAUD_MODE:
        raise ProtocolError(f"the LMS 200 talks at {BAUD_RATES} Bd, not {baud_rate}")
    return cmd_mode(_BAUD_MODE[baud_rate], addr=addr)


def cmd_continuous(addr: int = 0) -> bytes:
    """Continuous output of all measured values (20 24)."""
    return cmd_mode(MODE_CONTINUOUS, addr=addr)


def cmd_stop(addr: int = 0) -> bytes:
    """Measured values on request only (20 25): ends continuous output."""
    return cmd_mode(MODE_ON_REQUEST, addr=addr)


def cmd_request_scan(kind: int = 0x01, addr: int = 0) -> bytes:
    """Request measured values (30 01: all values of the current scan)."""
    return frame(0x30, bytes((kind,)), addr)


def cmd_request_status(addr: int = 0) -> bytes:
    return frame(0x31, addr=addr)


def cmd_request_errors(addr: int = 0) -> bytes:
    return frame(0x32, addr=addr)


def cmd_request_type(addr: int = 0) -> bytes:
    return frame(0x3A, addr=addr)


def _variant_words(angle_deg: int, resolution_deg: float) -> bytes:
    hundredths = round(resolution_deg * 100)
    if (angle_deg, hundredths) not in ((100, 100), (100, 50), (100, 25), (180, 100), (180, 50)):
        raise ProtocolError(
            f"no LMS 200 variant {angle_deg}°/{resolution_deg}° "
            "(100° at 1/0.5/0.25°, 180° at 1/0.5°)"
        )
    return struct.pack("<HH", angle_deg, hundredths)


def cmd_variant(angle_deg: int, resolution_deg: float, addr: int = 0) -> bytes:
    """Switch variant (3B): 100° or 180° field of view at 1, 0.5 or 0.25° (§5.3)."""
    return frame(0x3B, _variant_words(angle_deg, resolution_deg), addr)


def cmd_permanent_baud(keep: bool, addr: int = 0) -> bytes:
    """66 01: keep the configured rate over power cycles; 66 00: 9600 Bd at power-on."""
    return frame(0x66, bytes((1 if keep else 0,)), addr)


def cmd_read_config(addr: int = 0) -> bytes:
    return frame(0x74, addr=addr)


def cmd_write_config(config: LmsConfig, addr: int = 0) -> bytes:
    return frame(0x77, config.raw, addr)


# --------------------------------------------------------------------------------------------
# The 34-byte configuration block (§5.4)

_FACTORY_CONFIG: Final = bytes.fromhex(
    "00004600000001000002020200000a0a5064000a0a5080000a0a5064000000000200"
)


@dataclass(frozen=True)
class LmsConfig:
    """The sensor configuration read with 74 and written with 77; all 34 bytes are kept."""

    raw: bytes

    def __post_init__(self) -> None:
        if len(self.raw) != 34:
            raise ProtocolError(f"an LMS configuration has 34 bytes, got {len(self.raw)}")

    @classmethod
    def factory(cls) -> LmsConfig:
        """The manual's delivery example (Table 7-123): mode 00, mm, no real-time indices."""
        return cls(_FACTORY_CONFIG)

    @property
    def blanking_cm(self) -> int:
        return int(struct.unpack_from("<H", self.raw, 0)[0])

    @property
    def realtime_indices(self) -> bool:
        """Availability bit 1: every measured-value telegram carries scan/telegram counters."""
        return bool(self.raw[4] & 0x02)

    @property
    def measuring_mode(self) -> int:
        return self.raw[5]

    @property
    def unit_mm(self) -> bool:
        return self.raw[6] == 0x01

    def with_changes(
        self,
        *,
        measuring_mode: int | None = None,
        unit_mm: bool | None = None,
        realtime_indices: bool | None = None,
    ) -> LmsConfig:
        raw = bytearray(self.raw)
        if measuring_mode is not None:
            if measuring_mode not in _DISTANCE_MASK:
                raise ProtocolError(f"unknown measuring mode {measuring_mode}")
            raw[5] = measuring_mode
        if unit_mm is not None:
            raw[6] = 0x01 if unit_mm else 0x00
        if realtime_indices is not None:
            raw[4] = (raw[4] | 0x02) if realtime_indices else (raw[4] & ~0x02 & 0xFF)
        return LmsConfig(bytes(raw))


# --------------------------------------------------------------------------------------------
# The stream parser (§4.4)

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
    if _checksum(buf, p, end - 2) != (buf[end - 2] | (buf[end - 1] << 8)):
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
    while p < n:
        byte = buf[p]
        if byte != 0x02:
            if byte == 0x06 or byte == 0x15:
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


# --------------------------------------------------------------------------------------------
# Measured values (B0), §6


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


#: Distance mask and flag shift per measuring mode (block D), §6.2.
_DISTANCE_MASK: Final = {
    0: 0x1FFF, 1: 0x1FFF, 2: 0x1FFF, 3: 0x3FFF, 4: 0x3FFF, 5: 0x7FFF, 6: 0x7FFF, 15: 0x7FFF,
}  # fmt: skip
_FLAG_SHIFT: Final = {0: 13, 1: 13, 2: 13, 3: 14, 4: 14, 5: 15, 6: 15, 15: 16}
#: Modes whose flag bits are a reflector (intensity) value.
REFLECTOR_MODES: Final = frozenset({1, 3, 5})
# mask − raw → code; raw values ≥ mask − 8 are never distances.
_SPECIAL_BY_GAP: Final = {
    0: SpecialCode.NO_RETURN, 1: SpecialCode.DAZZLE, 2: SpecialCode.OVERFLOW,
    4: SpecialCode.SIGNAL_TO_NOISE, 5: SpecialCode.CHANNEL_ERROR, 8: SpecialCode.OUT_OF_RANGE,
}  # fmt: skip
_RAW_FOR_CODE: Final = {code: gap for gap, code in _SPECIAL_BY_GAP.items()}
#: Complete-scan sizes → (field of view °, resolution °).
_VARIANT_BY_COUNT: Final = {101: (100, 1.0), 201: (100, 0.5), 401: (100, 0.25), 181: (180, 1.0),
                            361: (180, 0.5)}  # fmt: skip


@dataclass(frozen=True)
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
    if partial:
        return np.radians(-90.0 + offset_deg + np.arange(count, dtype=float))
    if count not in _VARIANT_BY_COUNT:
        raise ProtocolError(f"a complete scan has 101, 201, 401, 181 or 361 values, got {count}")
    fov, res = _VARIANT_BY_COUNT[count]
    return np.radians(-fov / 2 + res * np.arange(count, dtype=float))


def decode_scan(telegram: Telegram, measuring_mode: int = 1) -> Scan:
    """Decode a ``B0`` measured-values reply (§6); raises ProtocolError if it is malformed.

    ``measuring_mode`` (block D of the configuration) says which bits are distance and which
    are flags; the sensor does not send it (§6.2), the driver knows it from 74/B1.
    """
    if telegram.code != 0xB0:
        raise ProtocolError(f"not a measured-values reply: code {telegram.code:#04x}")
    if measuring_mode not in _DISTANCE_MASK:
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
    mask = _DISTANCE_MASK[measuring_mode]
    distance = (raw & mask).astype(np.int64)
    flags = (raw.astype(np.uint32) >> _FLAG_SHIFT[measuring_mode]).astype(np.uint8)
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
    if count not in _VARIANT_BY_COUNT:
        raise ProtocolError(f"a complete scan has 101, 201, 401, 181 or 361 values, got {count}")
    mask = _DISTANCE_MASK[measuring_mode]
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
        shift = _FLAG_SHIFT[measuring_mode]
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


# --------------------------------------------------------------------------------------------
# Other replies


@dataclass(frozen=True)
class Reply:
    """A reply telegram that has no richer decoding here (e.g. the B2 error list)."""

    code: int
    data: bytes
    status: int
    name: str = "reply"


@dataclass(frozen=True)
class PowerOn(Reply):
    text: str = ""


@dataclass(frozen=True)
class ResetAck(Reply):
    """91: the sensor acknowledged a reset; the 90 power-on message follows."""


@dataclass(frozen=True)
class IncorrectCommand(Reply):
    """92: the frame was fine but the command was not allowed (§4.3)."""


@dataclass(frozen=True)
class ModeReply(Reply):
    """A0: result 0 = switched, 1 = wrong password, 2 = sensor fault."""

    result: int = 0

    @property
    def ok(self) -> bool:
        return self.result == 0


@dataclass(frozen=True)
class TypeReply(Reply):
    text: str = ""


@dataclass(frozen=True)
class VariantReply(Reply):
    ok: bool = False
    angle_deg: int = 0
    resolution_deg: float = 0.0


@dataclass(frozen=True)
class ConfigReply(Reply):
    """F4 (read-back) or F7 (write result; ``ok`` False means rejected)."""

    ok: bool = True
    config: LmsConfig | None = None


@dataclass(frozen=True)
class PermanentBaudReply(Reply):
    ok: bool = False
    keep: bool = False


@dataclass(frozen=True)
class StatusReply(Reply):
    """B1 (152 bytes): the fields a driver uses (§5.6)."""

    version: str = ""
    operating_mode: int = 0
    measuring_mode: int = 0
    angle_deg: int = 0
    resolution_deg: float = 0.0
    baud_rate: int | None = None
    permanent_baud: bool = False
    address: int = 0
    unit_mm: bool = True


_STATUS_LEN: Final = 152


def encode_status_reply(
    *,
    version: str = "V02.10 ",
    operating_mode: int = MODE_ON_REQUEST,
    measuring_mode: int = 0,
    angle_deg: int = 180,
    resolution_deg: float = 0.5,
    baud_rate: int = 9600,
    permanent_baud: bool = False,
    address: int = 0,
    unit_mm: bool = True,
    status: int = 0x10,
) -> bytes:
    data = bytearray(_STATUS_LEN)
    data[0:7] = version.encode("ascii")[:7].ljust(7)
    data[7] = operating_mode
    data[101] = measuring_mode
    struct.pack_into("<HH", data, 106, angle_deg, round(resolution_deg * 100))
    struct.pack_into("<H", data, 115, _BAUD_STATUS_CODE[baud_rate])
    data[118] = 1 if permanent_baud else 0
    data[119] = address
    data[121] = 1 if unit_mm else 0
    data[122] = 1
    return reply_frame(0xB1, bytes(data), status)


def encode_mode_reply(result: int = 0, status: int = 0x10) -> bytes:
    return reply_frame(0xA0, bytes((result,)), status)


def encode_variant_reply(
    ok: bool, angle_deg: int, resolution_deg: float, status: int = 0x10
) -> bytes:
    words = struct.pack("<HH", angle_deg, round(resolution_deg * 100))
    return reply_frame(0xBB, bytes((1 if ok else 0,)) + words, status)


def encode_config_reply(config: LmsConfig, *, write_result: bool | None = None) -> bytes:
    """F4 (read-back) when ``write_result`` is None, else F7 with the result byte."""
    if write_result is None:
        return reply_frame(0xF4, config.raw)
    return reply_frame(0xF7, bytes((1 if write_result else 0,)) + config.raw)


def _text(data: bytes) -> str:
    return data.decode("ascii", errors="replace")


def decode_reply(telegram: Telegram) -> Reply:
    """Decode a sensor reply other than B0 (use :func:`decode_scan` for those)."""
    code, data = telegram.code, telegram.data
    status = telegram.status if telegram.status is not None else 0

    def need(size: int, name: str) -> None:
        if len(data) < size:
            raise ProtocolError(f"{name} reply ({code:#04x}) too short: {len(data)} bytes")

    if code == 0x90:
        return PowerOn(code, data, status, "power_on", _text(data))
    if code == 0x91:
        return ResetAck(code, data, status, "reset")
    if code == 0x92:
        return IncorrectCommand(code, data, status, "incorrect_command")
    if code == 0xA0:
        need(1, "mode")
        return ModeReply(code, data, status, "mode", data[0])
    if code == 0xBA:
        return TypeReply(code, data, status, "type", _text(data))
    if code == 0xBB:
        need(5, "variant")
        angle, hundredths = struct.unpack_from("<HH", data, 1)
        return VariantReply(code, data, status, "variant", data[0] == 1, angle, hundredths / 100)
    if code == 0xF4:
        need(34, "configuration")
        return ConfigReply(code, data, status, "config", True, LmsConfig(bytes(data[:34])))
    if code == 0xF7:
        need(35, "configuration write")
        return ConfigReply(
            code, data, status, "config_write", data[0] == 1, LmsConfig(bytes(data[1:35]))
        )
    if code == 0xE6:
        need(2, "permanent baud")
        return PermanentBaudReply(code, data, status, "permanent_baud", data[0] == 1, data[1] == 1)
    if code == 0xB1:
        need(_STATUS_LEN, "status")
        baud_code = struct.unpack_from("<H", data, 115)[0]
        rates = {v: k for k, v in _BAUD_STATUS_CODE.items()}
        angle, hundredths = struct.unpack_from("<HH", data, 106)
        return StatusReply(
            code, data, status, "status",
            version=_text(data[0:7]),
            operating_mode=data[7],
            measuring_mode=data[101],
            angle_deg=angle,
            resolution_deg=hundredths / 100,
            baud_rate=rates.get(baud_code),
            permanent_baud=data[118] == 1,
            address=data[119],
            unit_mm=data[121] == 1,
        )  # fmt: skip
    if code == 0xB0:
        raise ProtocolError("B0 is a measured-values reply: decode it with decode_scan")
    return Reply(code, data, status)
