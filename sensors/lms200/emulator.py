"""An LMS 200 on a pseudo-terminal: the real driver, or any LMS 200 client, can open it.

The emulator holds the master side of a pty (``os.openpty``) and answers on it like the sensor:
the power-on message at the power-on rate, ACK/NAK within milliseconds, the replies of §5 of the
protocol spec (mode switches incl. installation mode with its password, baud rates, variant,
configuration read/write, status, type, single and continuous measured values), with output
paced at the configured baud rate. It reads the host's port speed from the pty: when the two
rates differ, what each side sends arrives as garbage, as on a real line.

Measured values come from ``scan_source(t_s, count) -> (ranges_m, flags)``, called with the
emulator's time since start and the number of values of the current variant; ranges that are
NaN or out of the mode's field go out as "no return".

Replay: ``clock`` (default ``time.monotonic``) is the emulator's time base for its pacing, delays
and scan cadence, so a simulated clock running faster than real time speeds the whole device up;
``stream(after_s) -> (start_s, telegram) | None`` replaces the scan source in continuous mode
with given telegrams, each sent as it is, never before its ``start_s`` on that clock.

Faults for tests: :attr:`Lms200Emulator.nak_next` (NAK the next n telegrams), ``mute()`` (stops
talking and listening), ``disconnect()`` (the device disappears: the pty closes).
"""

from __future__ import annotations

import contextlib
import math
import os
import select
import termios
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from sensors.errors import DeviceError
from sensors.lms200.protocol.commands import LmsConfig
from sensors.lms200.protocol.replies import (
    encode_config_reply,
    encode_mode_reply,
    encode_status_reply,
    encode_variant_reply,
)
from sensors.lms200.protocol.scan import encode_scan, scan_interval_s
from sensors.lms200.protocol.stream import Rejected, StreamParser, Telegram
from sensors.lms200.protocol.telegram import (
    ACK,
    BAUD_RATES,
    MODE_CONTINUOUS,
    MODE_INSTALLATION,
    MODE_ON_REQUEST,
    MODE_TEST_PASSWORD,
    NAK,
    TURN_S,
    ProtocolError,
    reply_frame,
)

__all__ = ["EmulatorState", "Lms200Emulator", "ScanSource", "TelegramStream"]

ScanSource = Callable[[float, int], tuple[np.ndarray, np.ndarray]]
#: The first telegram that starts after a time (the emulator's clock): (start_s, bytes), or None.
TelegramStream = Callable[[float], tuple[float, bytes] | None]

_TERMIOS_BAUD = {
    termios.B9600: 9600, termios.B19200: 19200, termios.B38400: 38400,
    getattr(termios, "B500000", 0o010005): 500000,
}  # fmt: skip
_COUNT = {(100, 1.0): 101, (100, 0.5): 201, (100, 0.25): 401, (180, 1.0): 181, (180, 0.5): 361}
_MODE_BY_BAUD_CODE = {0x40: 38400, 0x41: 19200, 0x42: 9600, 0x48: 500000}


@dataclass
class EmulatorState:
    """What the emulated sensor is set to (read it in tests; the emulator thread writes it)."""

    baud_rate: int
    operating_mode: int = MODE_ON_REQUEST
    angle_deg: int = 180
    resolution_deg: float = 0.5
    config: LmsConfig = LmsConfig.factory()  # noqa: RUF009 - frozen, shared safely
    permanent_baud: bool = False
    streaming: bool = False
    commands: int = 0
    naks_sent: int = 0
    scans_sent: int = 0
    bytes_dropped: int = 0  # output the host did not read in time (overrun)


class Lms200Emulator:
    """A SICK LMS 200 speaking the real protocol on a pseudo-terminal."""

    def __init__(
        self,
        scan_source: ScanSource,
        *,
        power_on_baud: int = 9600,
        type_text: str = "LMS200;301063;V02.10 ",
        password: str = "SICK_LMS",
        address: int = 0,
        power_on_message: bool = True,
        boot_s: float = 0.02,
        reply_delay_s: float = 0.005,
        pace: bool = True,
        clock: Callable[[], float] = time.monotonic,
        stream: TelegramStream | None = None,
    ) -> None:
        if power_on_baud not in BAUD_RATES:
            raise DeviceError(f"power-on baud must be one of {BAUD_RATES}, got {power_on_baud}")
        self.scan_source = scan_source
        self.type_text = type_text
        self.password = password
        self.address = address
        self.boot_s = boot_s
        self.reply_delay_s = reply_delay_s
        self.pace = pace
        self._clock = clock
        self.stream = stream
        self._streamed: tuple[float, bytes] | None = None
        self._more = False
        self.state = EmulatorState(baud_rate=power_on_baud)
        self._power_on_baud = power_on_baud
        self._power_on_message = power_on_message
        self.nak_next = 0
        self._muted = False
        self._master = -1
        self._slave = -1
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._out = bytearray()
        self._out_is_scan = False
        self._tx_time = 0.0
        self._t0 = 0.0
        self._turn = 0
        self._next_scan = 0.0
        self._pending: list[tuple[float, bytes, Callable[[], None] | None]] = []
        self._parser = StreamParser("to_sensor", report_failures=True)
        self.device_path = ""

    # ---------------------------------------------------------------------------------------
    # Life cycle

    def start(self) -> str:
        """Open the pty, start answering, and return the device path clients open."""
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self.device_path = os.ttyname(slave)
        self._set_host_baud(self._power_on_baud)
        self._t0 = self._clock()
        self._tx_time = self._t0
        if self._power_on_message:
            self._schedule(self.boot_s, reply_frame(0x90, self.type_text.encode("ascii")))
        self._thread = threading.Thread(target=self._run, name="lms200-emulator", daemon=True)
        self._thread.start()
        return self.device_path

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        for fd in (self._master, self._slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = -1

    def __enter__(self) -> Lms200Emulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def stream_more(self) -> None:
        """Replay fed as it goes: ``stream`` has telegrams again after it ran dry (returned
        None); the emulator asks it again (in its own thread, so no telegram is taken twice)."""
        self._more = True

    def mute(self, muted: bool = True) -> None:
        """Stop (or resume) talking and listening, as a sensor that hangs."""
        self._muted = muted

    def disconnect(self) -> None:
        """The device disappears: the pty's master side closes under the client."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._master = self._slave = -1

    @property
    def time_s(self) -> float:
        return self._clock() - self._t0

    # ---------------------------------------------------------------------------------------
    # The line

    def _set_host_baud(self, rate: int) -> None:
        """Initial speed of the slave side (what a client finds before it sets its own)."""
        attrs = termios.tcgetattr(self._slave)
        code = next(k for k, v in _TERMIOS_BAUD.items() if v == rate)
        attrs[4] = attrs[5] = code
        termios.tcsetattr(self._slave, termios.TCSANOW, attrs)

    def _host_baud(self) -> int | None:
        try:
            return _TERMIOS_BAUD.get(termios.tcgetattr(self._master)[5])
        except termios.error:
            return None

    def _line_ok(self) -> bool:
        return self._host_baud() == self.state.baud_rate

    @staticmethod
    def _garble(data: bytes) -> bytes:
        # What a UART receives from a sender at another rate: framing errors, wrong bytes.
        return bytes(((b * 37 + 11) & 0xFF) | 0x80 for b in data)

    def _schedule(
        self, delay_s: float, data: bytes, then: Callable[[], None] | None = None
    ) -> None:
        self._pending.append((self._clock() + delay_s, data, then))

    def _send(self, data: bytes) -> None:
        self._out += data if self._line_ok() else self._garble(data)

    def _flush_output(self, now: float) -> None:
        if not self._out:
            self._tx_time = now
            return
        if self.pace:
            rate = self.state.baud_rate / 10.0
            allowed = int((now - self._tx_time) * rate)
            if allowed <= 0:
                return
            chunk = bytes(self._out[: min(allowed, 256)])
        else:
            chunk = bytes(self._out)
        try:
            written = os.write(self._master, chunk)
        except BlockingIOError:
            written = 0
        except OSError:
            self._stop.set()
            return
        if written < len(chunk):
            # The host is not reading: a real line loses these bytes.
            self.state.bytes_dropped += len(chunk) - written
            written = len(chunk)
        del self._out[:written]
        if self.pace:
            self._tx_time += written / (self.state.baud_rate / 10.0)
        if not self._out:
            self._out_is_scan = False

    # ---------------------------------------------------------------------------------------
    # The loop

    def _run(self) -> None:
        while not self._stop.is_set():
            now = self._clock()
            wait = 0.002 if (self._out or self._pending or self.state.streaming) else 0.02
            try:
                readable, _, _ = select.select([self._master], [], [], wait)
            except (OSError, ValueError):
                return
            if readable:
                try:
                    data = os.read(self._master, 4096)
                except BlockingIOError:
                    data = b""
                except OSError:
                    return
                if data and not self._muted:
                    self._receive(data)
            now = self._clock()
            due = [item for item in self._pending if item[0] <= now]
            if due:
                self._pending = [item for item in self._pending if item[0] > now]
                for _, payload, then in sorted(due, key=lambda item: item[0]):
                    if payload and not self._muted:
                        self._send(payload)
                    if then is not None:
                        then()
            if self._more:
                self._more = False
                if self.stream is not None and self.state.streaming and self._streamed is None:
                    self._streamed = self.stream(now)
                    self._next_scan = math.inf if self._streamed is None else self._streamed[0]
            if self.state.streaming and not self._muted and now >= self._next_scan:
                self._emit_scan(now)
            if not self._muted:
                self._flush_output(now)

    def _receive(self, data: bytes) -> None:
        if not self._line_ok():
            return  # framing errors at the wrong rate: nothing the sensor can understand
        for event in self._parser.feed(data):
            if isinstance(event, Rejected):
                self._interrupt()
                self._send(bytes((NAK,)))
                self.state.naks_sent += 1
            elif isinstance(event, Telegram):
                if event.addr not in (0x00, self.address):
                    continue  # addressed to another unit: silence
                self._interrupt()
                if self.nak_next > 0:
                    self.nak_next -= 1
                    self._send(bytes((NAK,)))
                    self.state.naks_sent += 1
                    continue
                self.state.commands += 1
                self._send(bytes((ACK,)))
                self._handle(event)

    def _interrupt(self) -> None:
        """Any host request interrupts the sensor's transmission (a truncated telegram)."""
        if self._out_is_scan:
            self._out.clear()
            self._out_is_scan = False

    def _reply(
        self, data: bytes, then: Callable[[], None] | None = None, delay: float = -1
    ) -> None:
        self._schedule(self.reply_delay_s if delay < 0 else delay, data, then)

    def _handle(self, telegram: Telegram) -> None:
        code, data, state = telegram.code, telegram.data, self.state
        if code == 0x10:
            self._reply(reply_frame(0x91), then=self._reset)
        elif code == 0x20 and data:
            self._switch_mode(data[0], data[1:])
        elif code == 0x30 and data[:1] == b"\x01":
            self._reply(self._scan_telegram(self.time_s))
        elif code == 0x31:
            self._reply(
                encode_status_reply(
                    operating_mode=state.operating_mode,
                    measuring_mode=state.config.measuring_mode,
                    angle_deg=state.angle_deg,
                    resolution_deg=state.resolution_deg,
                    baud_rate=state.baud_rate,
                    permanent_baud=state.permanent_baud,
                    address=self.address,
                    unit_mm=state.config.unit_mm,
                )
            )
        elif code == 0x32:
            self._reply(reply_frame(0xB2, bytes(2)))
        elif code == 0x3A:
            self._reply(reply_frame(0xBA, self.type_text.encode("ascii")))
        elif code == 0x3B and len(data) == 4:
            self._switch_variant(
                int.from_bytes(data[:2], "little"), int.from_bytes(data[2:], "little")
            )
        elif code == 0x66 and len(data) == 1:
            state.permanent_baud = data[0] == 1
            self._reply(reply_frame(0xE6, bytes((1, data[0]))))
        elif code == 0x74:
            self._reply(encode_config_reply(state.config))
        elif code == 0x77:
            accepted = state.operating_mode == MODE_INSTALLATION and len(data) == 34
            if accepted:
                try:
                    state.config = LmsConfig(bytes(data))
                except ProtocolError:
                    accepted = False
            self._reply(encode_config_reply(state.config, write_result=accepted), delay=0.05)
        else:
            self._reply(reply_frame(0x92))

    def _switch_mode(self, sub_mode: int, params: bytes) -> None:
        state = self.state
        if sub_mode in (MODE_INSTALLATION, MODE_TEST_PASSWORD):
            ok = params == self.password.encode("ascii")
            if ok and sub_mode == MODE_INSTALLATION:
                state.streaming = False
                state.operating_mode = MODE_INSTALLATION
            self._reply(encode_mode_reply(0 if ok else 1))
        elif sub_mode == MODE_CONTINUOUS:
            state.operating_mode = sub_mode
            self._reply(encode_mode_reply(0), then=self._start_stream)
        elif sub_mode == MODE_ON_REQUEST:
            state.operating_mode = sub_mode
            state.streaming = False
            self._reply(encode_mode_reply(0))
        elif sub_mode in _MODE_BY_BAUD_CODE:
            new_rate = _MODE_BY_BAUD_CODE[sub_mode]
            # The reply goes out at the old rate; the sensor switches afterwards (§10).
            self._reply(encode_mode_reply(0), then=lambda: self._set_baud_after_reply(new_rate))
        else:
            self._reply(reply_frame(0x92))

    def _set_baud_after_reply(self, rate: int) -> None:
        def switch() -> None:
            self.state.baud_rate = rate

        # Wait until the reply has left the line at the old rate, then switch.
        remaining = len(self._out) * 10.0 / self.state.baud_rate if self.pace else 0.0
        self._schedule(remaining + 0.001, b"", switch)

    def _switch_variant(self, angle_deg: int, hundredths: int) -> None:
        state = self.state
        resolution = hundredths / 100.0
        ok = (angle_deg, resolution) in _COUNT
        if ok:
            state.angle_deg, state.resolution_deg = angle_deg, resolution
            state.streaming = False  # a variant change stops the stream (§5.3)
            if state.operating_mode == MODE_CONTINUOUS:
                state.operating_mode = MODE_ON_REQUEST
        self._reply(encode_variant_reply(ok, state.angle_deg, state.resolution_deg))

    def _reset(self) -> None:
        state = self.state
        state.streaming = False
        state.operating_mode = MODE_ON_REQUEST
        if not state.permanent_baud:
            state.baud_rate = self._power_on_baud
        self._schedule(self.boot_s, reply_frame(0x90, self.type_text.encode("ascii")))

    def _start_stream(self) -> None:
        self.state.streaming = True
        if self.stream is not None:
            self._streamed = self.stream(self._clock())
            self._next_scan = math.inf if self._streamed is None else self._streamed[0]
            return
        # Telegrams start at mirror-turn boundaries: the next turn after now.
        self._turn = int(self.time_s / TURN_S) + 1
        self._next_scan = self._t0 + self._turn * TURN_S

    # ---------------------------------------------------------------------------------------
    # Measured values

    def _count(self) -> int:
        return _COUNT[(self.state.angle_deg, self.state.resolution_deg)]

    def _scan_telegram(self, t_s: float, turn: int | None = None) -> bytes:
        state = self.state
        count = self._count()
        ranges, flags = self.scan_source(t_s, count)
        turn = round(t_s / TURN_S) if turn is None else turn
        indices = state.config.realtime_indices
        return encode_scan(
            np.asarray(ranges, dtype=float)[:count],
            flags=np.asarray(flags)[:count],
            measuring_mode=state.config.measuring_mode,
            unit_mm=state.config.unit_mm,
            scan_index=(turn & 0xFF) if indices else None,
            telegram_index=(state.scans_sent & 0xFF) if indices else None,
        )

    def _emit_scan(self, now: float) -> None:
        state = self.state
        if self.stream is not None:
            if self._out or self._streamed is None:
                return  # the line is busy: send it when free, never before its start
            start_s, telegram = self._streamed
            self._tx_time = max(self._tx_time, start_s)
            self._send(telegram)
            self._out_is_scan = True
            state.scans_sent += 1
            self._streamed = self.stream(start_s)
            self._next_scan = math.inf if self._streamed is None else self._streamed[0]
            return
        interval = scan_interval_s(
            state.baud_rate, self._count(), state.resolution_deg, state.config.realtime_indices
        )
        turns = round(interval / TURN_S)
        if not self._out:  # else still sending the previous telegram: this scan is lost (§8)
            self._send(self._scan_telegram(self._turn * TURN_S, self._turn))
            self._out_is_scan = True
            state.scans_sent += 1
        self._turn += turns
        if self._t0 + self._turn * TURN_S < now - 1.0:
            # Fell far behind (a stalled process): skip ahead rather than burst.
            self._turn = int((now - self._t0) / TURN_S) + 1
        self._next_scan = self._t0 + self._turn * TURN_S
