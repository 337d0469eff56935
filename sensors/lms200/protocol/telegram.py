"""Telegram framing of the SICK LMS 200 serial protocol: constants, checksum, frames; no I/O.

Frame (both directions): ``STX 02 | ADDR | LEN (LE u16) | CMD/REPLY | DATA | [STATUS] | CRC (LE)``
where LEN counts the bytes after LEN up to, not including, the checksum; replies carry a status
byte as their last data byte. The checksum is SICK's own 16-bit signature (generator 0x8005,
one shift per byte, XOR with the previous and current byte) — not a library CRC-16 preset.

:func:`checksum`, :func:`frame` and :func:`reply_frame` build telegrams; the constants here are
shared by the other modules of the package. Sections (§n) cite docs/lms200-protocol.md.
"""

from __future__ import annotations

import struct
from typing import Final

import numpy as np
from numba import njit

from sensors.errors import SensorError

__all__ = [
    "ACK",
    "BAUD_RATES",
    "DISTANCE_MASK",
    "FLAG_SHIFT",
    "MAX_LEN",
    "NAK",
    "STX",
    "ProtocolError",
    "checksum",
    "checksum_kernel",
    "frame",
    "reply_frame",
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

#: Distance mask and flag shift per measuring mode (block D), §6.2.
DISTANCE_MASK: Final = {
    0: 0x1FFF, 1: 0x1FFF, 2: 0x1FFF, 3: 0x3FFF, 4: 0x3FFF, 5: 0x7FFF, 6: 0x7FFF, 15: 0x7FFF,
}  # fmt: skip
FLAG_SHIFT: Final = {0: 13, 1: 13, 2: 13, 3: 14, 4: 14, 5: 15, 6: 15, 15: 16}


class ProtocolError(SensorError):
    """A telegram cannot be built or decoded; the message says what was wrong."""


# --------------------------------------------------------------------------------------------
# Checksum and framing


@njit(cache=True)
def checksum_kernel(buf: np.ndarray, start: int, stop: int) -> int:  # pragma: no cover - numba
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
    return int(checksum_kernel(buf, 0, len(buf)))


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
