"""Replies of the SICK LMS 200 other than measured values: decoding and encoding; no I/O.

:func:`decode_reply` decodes a sensor reply other than ``B0`` (those go to
:func:`~sensors.lms200.protocol.scan.decode_scan`) into a :class:`Reply` subclass; the
``encode_*_reply`` functions build the sensor's replies (for the emulator). Sections (§n) cite
docs/lms200-protocol.md.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Final

from sensors.lms200.protocol.commands import LmsConfig
from sensors.lms200.protocol.stream import Telegram
from sensors.lms200.protocol.telegram import MODE_ON_REQUEST, ProtocolError, reply_frame

__all__ = [
    "ConfigReply",
    "IncorrectCommand",
    "ModeReply",
    "PermanentBaudReply",
    "PowerOn",
    "Reply",
    "ResetAck",
    "StatusReply",
    "TypeReply",
    "VariantReply",
    "decode_reply",
    "encode_config_reply",
    "encode_mode_reply",
    "encode_status_reply",
    "encode_variant_reply",
]

_BAUD_STATUS_CODE: Final = {9600: 0x8067, 19200: 0x8033, 38400: 0x8019, 500000: 0x8001}


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
