"""The LMS 200 driver: pyserial, the start-up sequence of real drivers, and streaming scans.

Ports are opened with ``serial.serial_for_url``, so a device path (``/dev/ttyUSB0``, a pty of
the emulator), ``socket://host:port`` and ``loop://`` all work. :meth:`Lms200.start` runs the
sequence of docs/lms200-protocol.md §9: find the sensor's current baud rate, stop a stream
left running, switch to the configured rate (the reply arrives at the old rate), read type,
status and configuration, write the configuration only when it differs (EEPROM wear) in
installation mode, set the variant, and start continuous output. :meth:`Lms200.scans` yields
decoded scans with host receive timestamps. Every failure is a ``DeviceError`` that says what
was happening.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import serial

from sensors.errors import DeviceError
from sensors.lms200.protocol.commands import (
    LmsConfig,
    cmd_continuous,
    cmd_installation_mode,
    cmd_permanent_baud,
    cmd_read_config,
    cmd_request_status,
    cmd_request_type,
    cmd_set_baud,
    cmd_stop,
    cmd_variant,
    cmd_write_config,
)
from sensors.lms200.protocol.plausibility import ScanCheck, ScanLimits
from sensors.lms200.protocol.replies import (
    ConfigReply,
    ModeReply,
    StatusReply,
    TypeReply,
    VariantReply,
    decode_reply,
)
from sensors.lms200.protocol.scan import Scan, decode_scan
from sensors.lms200.protocol.stream import Event, Handshake, ParserStats, StreamParser, Telegram
from sensors.lms200.protocol.telegram import BAUD_RATES, ProtocolError

__all__ = ["Lms200", "SensorInfo"]

Tap = Callable[[float, bytes], None]


@dataclass(frozen=True)
class SensorInfo:
    """What start-up learned about the sensor."""

    type_text: str
    found_baud: int
    baud_rate: int
    angle_deg: int
    resolution_deg: float
    measuring_mode: int
    unit_mm: bool
    realtime_indices: bool
    config_written: bool


class Lms200:
    """A SICK LMS 200 on a serial port (thin: the protocol module does the bytes)."""

    def __init__(
        self,
        port: str,
        *,
        baud_rate: int = 38400,
        address: int = 0,
        password: str = "SICK_LMS",
        angle_deg: int = 100,
        resolution_deg: float = 1.0,
        measuring_mode: int = 1,
        unit_mm: bool = True,
        realtime_indices: bool = True,
        permanent_baud: bool = False,
        ack_timeout_s: float = 0.2,
        reply_timeout_s: float = 3.0,
        config_write_timeout_s: float = 15.0,
        stream_timeout_s: float = 1.0,
        nak_wait_s: float = 0.03,
        baud_switch_wait_s: float = 0.25,
        retries: int = 3,
        tap: Tap | None = None,
    ) -> None:
        if baud_rate not in BAUD_RATES:
            raise DeviceError(f"baud rate must be one of {BAUD_RATES}, got {baud_rate}")
        cmd_variant(angle_deg, resolution_deg)  # validates the variant
        self.port = port
        self.baud_rate = baud_rate
        self.address = address
        self.password = password
        self.angle_deg = angle_deg
        self.resolution_deg = resolution_deg
        self.measuring_mode = measuring_mode
        self.unit_mm = unit_mm
        self.realtime_indices = realtime_indices
        self.permanent_baud = permanent_baud
        self.ack_timeout_s = ack_timeout_s
        self.reply_timeout_s = reply_timeout_s
        self.config_write_timeout_s = config_write_timeout_s
        self.stream_timeout_s = stream_timeout_s
        self.nak_wait_s = nak_wait_s
        self.baud_switch_wait_s = baud_switch_wait_s
        self.retries = retries
        self.tap = tap
        #: What stamps the bytes read (the tap's and the parser's stamps); the timeouts are on
        #: the wall clock. An emulated sensor on a simulated clock sets both to that clock.
        self.clock: Callable[[], float] = time.monotonic
        self.info: SensorInfo | None = None
        self.streaming = False
        self._serial: serial.SerialBase | None = None
        self._parser = StreamParser("from_sensor")
        self.plausibility: ScanCheck | None = None  # of the stream: its rejections by reason

    # ---------------------------------------------------------------------------------------
    # Port

    def open(self, baud_rate: int | None = None) -> None:
        if self._serial is not None:
            return
        try:
            self._serial = serial.serial_for_url(
                self.port, baudrate=baud_rate or self.baud_rate, timeout=0.01, write_timeout=2.0
            )
        except (serial.SerialException, ValueError, OSError) as exc:
            raise DeviceError(f"cannot open {self.port}: {exc}") from None

    def close(self) -> None:
        """Stop a running stream (best effort) and close the port."""
        if self._serial is None:
            return
        if self.streaming:
            with contextlib.suppress(DeviceError):
                self.stop()
        try:
            self._serial.close()
        finally:
            self._serial = None

    def __enter__(self) -> Lms200:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def _port(self) -> serial.SerialBase:
        if self._serial is None:
            raise DeviceError(f"{self.port} is not open")
        return self._serial

    def _set_port_baud(self, rate: int) -> None:
        try:
            self._port.baudrate = rate
            self._port.reset_input_buffer()
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(f"{self.port}: cannot set {rate} Bd: {exc}") from None
        self._parser = StreamParser("from_sensor")

    def _write(self, data: bytes, doing: str) -> None:
        try:
            self._port.write(data)
            self._port.flush()
        except (serial.SerialException, OSError) as exc:
            raise DeviceError(f"{self.port} failed while {doing}: {exc}") from None

    def _read_events(self, doing: str) -> list[Event]:
        """Whatever the port has now (waits up to the port's short read timeout)."""
        try:
            chunk = self._port.read(max(1, self._port.in_waiting))
        except (serial.SerialException, OSError, TypeError) as exc:
            raise DeviceError(f"{self.port} disappeared while {doing}: {exc}") from None
        if not chunk:
            return []
        stamp = self.clock()
        if self.tap is not None:
            self.tap(stamp, chunk)
        return self._parser.feed(chunk, stamp)

    # ---------------------------------------------------------------------------------------
    # Request / reply

    def _transact(
        self,
        command: bytes,
        reply_code: int,
        doing: str,
        timeout_s: float,
        *,
        retry_silence: bool = True,
    ) -> Telegram:
        """Send ``command``; wait for its ACK (retrying on NAK and silence) and then its reply."""
        for attempt in range(self.retries + 1):
            self._write(command, doing)
            state = self._await(reply_code, doing, timeout_s)
            if isinstance(state, Telegram):
                return state
            if state == "nak":
                time.sleep(self.nak_wait_s)
            if attempt == self.retries or (state == "silent" and not retry_silence):
                what = "NAKed it" if state == "nak" else "did not answer"
                raise DeviceError(
                    f"{self.port}: the sensor {what} while {doing} "
                    f"({self.retries + 1} tries at {self._port.baudrate} Bd)"
                )
        raise AssertionError("unreachable")

    def _await(self, reply_code: int, doing: str, timeout_s: float) -> Telegram | str:
        acked = False
        start = time.monotonic()
        while True:
            for event in self._read_events(doing):
                if isinstance(event, Handshake):
                    # The sensor answers a command once; a 06 before a 15 was a stray byte
                    # of an earlier stream, and the NAK is the answer.
                    if not event.ack:
                        return "nak"
                    acked = True
                elif isinstance(event, Telegram):
                    if event.code == reply_code:
                        return event
                    if event.code == 0x92:
                        raise DeviceError(
                            f"{self.port}: the sensor refused the command while {doing} "
                            "(reply 92: incorrect command)"
                        )
                    # Anything else (a stream's B0 frames) is left over from before.
            elapsed = time.monotonic() - start
            if not acked and elapsed > self.ack_timeout_s:
                return "silent"
            if elapsed > timeout_s + self.ack_timeout_s:
                return "silent"

    def _mode(self, command: bytes, doing: str, *, retry_silence: bool = True) -> ModeReply:
        reply = decode_reply(
            self._transact(command, 0xA0, doing, self.reply_timeout_s, retry_silence=retry_silence)
        )
        assert isinstance(reply, ModeReply)
        if not reply.ok:
            reason = {1: "wrong password", 2: "sensor fault"}.get(
                reply.result, f"result {reply.result}"
            )
            raise DeviceError(f"{self.port}: mode switch refused while {doing}: {reason}")
        return reply

    # ---------------------------------------------------------------------------------------
    # Start-up

    def detect_baud(self) -> int:
        """Find the rate the sensor talks at now: try the configured rate first, then the rest."""
        self.open()
        order = [self.baud_rate, *(r for r in (9600, 19200, 38400, 500000) if r != self.baud_rate)]
        for rate in order:
            self._set_port_baud(rate)
            try:
                # 20 25 is harmless, and stops a stream left running by an earlier client.
                # Silence means "not this rate"; a NAK means the sensor heard us: retry.
                self._mode(cmd_stop(self.address), "probing the baud rate", retry_silence=False)
                return rate
            except DeviceError as exc:
                if "NAKed" in str(exc) or "refused" in str(exc):
                    raise
                continue
        raise DeviceError(
            f"{self.port}: no LMS answered at any of {order} Bd (is it powered and connected?)"
        )

    def set_baud(self, rate: int) -> None:
        """Switch the sensor (reply at the old rate), then the port, then pause."""
        self._mode(cmd_set_baud(rate, self.address), f"switching to {rate} Bd")
        self._set_port_baud(rate)
        time.sleep(self.baud_switch_wait_s)

    def start(self) -> SensorInfo:
        """The whole start-up sequence, ending with continuous output."""
        self.open()
        found = self.detect_baud()
        if found != self.baud_rate:
            self.set_baud(self.baud_rate)
        type_reply = decode_reply(
            self._transact(
                cmd_request_type(self.address), 0xBA, "reading the type", self.reply_timeout_s
            )
        )
        assert isinstance(type_reply, TypeReply)
        status = decode_reply(
            self._transact(
                cmd_request_status(self.address), 0xB1, "reading the status", self.reply_timeout_s
            )
        )
        assert isinstance(status, StatusReply)
        current = decode_reply(
            self._transact(
                cmd_read_config(self.address),
                0xF4,
                "reading the configuration",
                self.reply_timeout_s,
            )
        )
        assert isinstance(current, ConfigReply)
        assert current.config is not None
        wanted = current.config.with_changes(
            measuring_mode=self.measuring_mode,
            unit_mm=self.unit_mm,
            realtime_indices=self.realtime_indices,
        )
        written = wanted != current.config
        if written:
            self.write_config(wanted)
        if (status.angle_deg, status.resolution_deg) != (self.angle_deg, self.resolution_deg):
            self.set_variant(self.angle_deg, self.resolution_deg)
        if self.permanent_baud != status.permanent_baud:
            self._transact(
                cmd_permanent_baud(self.permanent_baud, self.address), 0xE6,
                "setting the permanent baud flag", self.reply_timeout_s,
            )  # fmt: skip
        self.info = SensorInfo(
            type_text=type_reply.text.strip(),
            found_baud=found,
            baud_rate=self.baud_rate,
            angle_deg=self.angle_deg,
            resolution_deg=self.resolution_deg,
            measuring_mode=wanted.measuring_mode,
            unit_mm=wanted.unit_mm,
            realtime_indices=wanted.realtime_indices,
            config_written=written,
        )
        self._mode(cmd_continuous(self.address), "starting continuous output")
        self.plausibility = ScanCheck(ScanLimits.for_variant(
            self.angle_deg, self.resolution_deg, unit_mm=wanted.unit_mm,
            baud_rate=self.baud_rate, realtime_indices=wanted.realtime_indices,
        ))  # fmt: skip
        self.streaming = True
        return self.info

    def write_config(self, config: LmsConfig) -> None:
        """Installation mode, 77 with all 34 bytes, check the result, back to monitoring."""
        self._mode(cmd_installation_mode(self.password, self.address), "entering installation mode")
        reply = decode_reply(
            self._transact(
                cmd_write_config(config, self.address), 0xF7, "writing the configuration",
                self.config_write_timeout_s,
            )
        )  # fmt: skip
        assert isinstance(reply, ConfigReply)
        if not reply.ok:
            raise DeviceError(
                f"{self.port}: the sensor rejected the configuration {config.raw.hex()}"
            )
        self._mode(cmd_stop(self.address), "leaving installation mode")

    def set_variant(self, angle_deg: int, resolution_deg: float) -> None:
        reply = decode_reply(
            self._transact(
                cmd_variant(angle_deg, resolution_deg, self.address), 0xBB,
                f"switching to the {angle_deg}°/{resolution_deg}° variant", self.reply_timeout_s,
            )
        )  # fmt: skip
        assert isinstance(reply, VariantReply)
        if not reply.ok:
            raise DeviceError(
                f"{self.port}: the sensor refused the {angle_deg}°/{resolution_deg}° variant "
                f"(kept {reply.angle_deg}°/{reply.resolution_deg}°)"
            )

    # ---------------------------------------------------------------------------------------
    # Streaming

    def scans(self, limit: int | None = None) -> Iterator[Scan]:
        """Decoded scans of the running stream, stamped with their host receive time."""
        if not self.streaming:
            raise DeviceError(f"{self.port}: not streaming; call start() first")
        delivered = 0
        last = time.monotonic()
        while limit is None or delivered < limit:
            events = self._read_events("streaming scans")
            got = False
            for event in events:
                if isinstance(event, Telegram) and event.code == 0xB0:
                    try:
                        scan = decode_scan(event, self.measuring_mode)
                    except ProtocolError:
                        continue  # counted by the caller via the parser; never raised
                    got = True
                    if self.plausibility is not None and self.plausibility.check(scan) is not None:
                        continue  # counted in self.plausibility.rejected
                    delivered += 1
                    yield scan
                    if limit is not None and delivered >= limit:
                        return
            now = time.monotonic()
            if got:
                last = now
            elif now - last > self.stream_timeout_s:
                self.streaming = False
                raise DeviceError(
                    f"{self.port}: no scan for {now - last:.1f} s while streaming "
                    f"at {self._port.baudrate} Bd: the sensor stopped talking"
                )

    @property
    def parser_stats(self) -> ParserStats:
        return self._parser.stats

    def stop(self) -> None:
        """End continuous output (20 25) and wait for the sensor to confirm."""
        self._mode(cmd_stop(self.address), "stopping continuous output")
        self.streaming = False
