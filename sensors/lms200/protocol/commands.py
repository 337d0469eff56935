"""Commands of the SICK LMS 200 (host → sensor) and its 34-byte configuration block; no I/O.

The ``cmd_*`` functions encode every command a driver needs (§5); :class:`LmsConfig` holds the
configuration read with 74 and written with 77 (§5.4). Sections (§n) cite
docs/lms200-protocol.md.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Final

from sensors.lms200.protocol.telegram import (
    BAUD_RATES,
    DISTANCE_MASK,
    MODE_CONTINUOUS,
    MODE_INSTALLATION,
    MODE_ON_REQUEST,
    MODE_TEST_PASSWORD,
    ProtocolError,
    frame,
)

__all__ = [
    "LmsConfig",
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
]

_BAUD_MODE: Final = {38400: 0x40, 19200: 0x41, 9600: 0x42, 500000: 0x48}


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
            if measuring_mode not in DISTANCE_MASK:
                raise ProtocolError(f"unknown measuring mode {measuring_mode}")
            raw[5] = measuring_mode
        if unit_mm is not None:
            raw[6] = 0x01 if unit_mm else 0x00
        if realtime_indices is not None:
            raw[4] = (raw[4] | 0x02) if realtime_indices else (raw[4] & ~0x02 & 0xFF)
        return LmsConfig(bytes(raw))
