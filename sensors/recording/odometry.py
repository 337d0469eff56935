"""Odometry from a robot base: the line format, its sources (TCP, a serial device) and the reader.

The line format (docs/recording.md): one ASCII line per pose, fields separated by spaces, tabs
or commas::

    t_s x_m y_m yaw_rad [more numbers...]

``t_s`` is the source's own stamp, ``x_m y_m yaw_rad`` its dead-reckoned pose in its odometry
frame; up to four more numbers (velocities, say) may follow and are ignored. Blank lines and
lines starting with ``#`` are skipped silently; anything else that does not parse (too few
fields, a word, NaN, a stamp going back, a line longer than 256 bytes) is counted as malformed
and skipped. Every received line is kept in the raw log with its arrival stamp.

Sources: ``tcp://HOST:PORT`` (the recorder connects, and reconnects when the stream drops) and a
serial device ``/dev/ttyUSB1`` or ``serial:///dev/ttyUSB1?baud=115200`` (opened raw with
termios, 8N1; default 115200 Bd).
"""

from __future__ import annotations

import abc
import contextlib
import math
import os
import select
import socket
import termios
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO
from urllib.parse import parse_qs, urlsplit

from sensors.errors import RecordingError

__all__ = [
    "MAX_LINE_BYTES",
    "OdometryCounts",
    "OdometryReader",
    "OdometrySource",
    "SerialSource",
    "TcpSource",
    "TumAppender",
    "open_source",
    "parse_line",
]

MAX_LINE_BYTES = 256
_BAUD = {rate: getattr(termios, f"B{rate}") for rate in (9600, 19200, 38400, 57600, 115200)}


def parse_line(line: str) -> tuple[float, float, float, float] | None:
    """(t_s, x_m, y_m, yaw_rad) of one line, or None when it is malformed."""
    fields = line.replace(",", " ").split()
    if not 4 <= len(fields) <= 8:
        return None
    try:
        values = [float(f) for f in fields]
    except ValueError:
        return None
    if not all(math.isfinite(v) for v in values):
        return None
    return values[0], values[1], values[2], values[3]


class OdometrySource(abc.ABC):
    """A byte stream of odometry lines: ``read(timeout_s)`` returns b"" when nothing came."""

    name = ""

    @abc.abstractmethod
    def connect(self) -> None:
        """Open the stream; RecordingError naming the endpoint when it cannot."""

    @abc.abstractmethod
    def read(self, timeout_s: float) -> bytes:
        """What arrived within ``timeout_s`` (b"" if nothing); RecordingError when it closed."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the stream (safe to call twice)."""


class TcpSource(OdometrySource):
    """A TCP stream the recorder connects to (``tcp://HOST:PORT``)."""

    def __init__(self, host: str, port: int, connect_timeout_s: float = 2.0) -> None:
        self.host, self.port = host, port
        self.name = f"tcp://{host}:{port}"
        self.connect_timeout_s = connect_timeout_s
        self._sock: socket.socket | None = None

    def connect(self) -> None:
        self.close()
        try:
            self._sock = socket.create_connection(
                (self.host, self.port), timeout=self.connect_timeout_s
            )
        except OSError as exc:
            raise RecordingError(
                f"odometry {self.name}: cannot connect: {exc.strerror or exc}"
            ) from None

    def read(self, timeout_s: float) -> bytes:
        if self._sock is None:
            raise RecordingError(f"odometry {self.name}: not connected")
        self._sock.settimeout(timeout_s)
        try:
            data = self._sock.recv(4096)
        except TimeoutError:
            return b""
        except OSError as exc:
            raise RecordingError(f"odometry {self.name}: {exc.strerror or exc}") from None
        if not data:
            raise RecordingError(f"odometry {self.name}: the stream closed")
        return data

    def close(self) -> None:
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.close()
            self._sock = None


class SerialSource(OdometrySource):
    """A serial device (or a pty) read raw at ``baud`` (8N1)."""

    def __init__(self, path: str, baud: int = 115200) -> None:
        if baud not in _BAUD:
            raise RecordingError(f"odometry {path}: baud must be one of {sorted(_BAUD)}")
        self.path, self.baud = path, baud
        self.name = f"serial://{path}?baud={baud}"
        self._fd = -1

    def connect(self) -> None:
        self.close()
        try:
            fd = os.open(self.path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError as exc:
            raise RecordingError(f"odometry {self.path}: cannot open: {exc.strerror}") from None
        try:
            if os.isatty(fd):
                tty.setraw(fd)
                attrs = termios.tcgetattr(fd)
                attrs[4] = attrs[5] = _BAUD[self.baud]
                termios.tcsetattr(fd, termios.TCSANOW, attrs)
        except termios.error as exc:
            os.close(fd)
            raise RecordingError(f"odometry {self.path}: cannot set up the port: {exc}") from None
        self._fd = fd

    def read(self, timeout_s: float) -> bytes:
        if self._fd < 0:
            raise RecordingError(f"odometry {self.path}: not open")
        try:
            readable, _, _ = select.select([self._fd], [], [], timeout_s)
            if not readable:
                return b""
            data = os.read(self._fd, 4096)
        except BlockingIOError:
            return b""
        except OSError as exc:
            raise RecordingError(f"odometry {self.path}: {exc.strerror or exc}") from None
        if not data:
            raise RecordingError(f"odometry {self.path}: the device closed")
        return data

    def close(self) -> None:
        if self._fd >= 0:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = -1


def open_source(spec: str, connect_timeout_s: float = 2.0) -> OdometrySource:
    """``tcp://HOST:PORT``, ``serial://PATH?baud=N`` or a device path → its source."""
    if spec.startswith("tcp://"):
        parts = urlsplit(spec)
        if not parts.hostname or parts.port is None:
            raise RecordingError(f"odometry {spec!r}: expected tcp://HOST:PORT")
        return TcpSource(parts.hostname, parts.port, connect_timeout_s)
    if spec.startswith("serial://"):
        parts = urlsplit(spec)
        query = parse_qs(parts.query)
        try:
            baud = int(query.get("baud", ["115200"])[0])
        except ValueError:
            raise RecordingError(f"odometry {spec!r}: baud must be a number") from None
        return SerialSource(parts.path, baud)
    if spec.startswith("/"):
        return SerialSource(spec)
    raise RecordingError(
        f"odometry {spec!r}: expected tcp://HOST:PORT, serial://PATH?baud=N or a device path"
    )


class TumAppender:
    """A TUM file written line by line to ``<name>.partial``, renamed when closed."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.partial = path.with_name(path.name + ".partial")
        self._file: TextIO | None = open(self.partial, "x", encoding="utf-8")  # noqa: SIM115
        self._file.write("# timestamp tx ty tz qx qy qz qw\n")
        self.poses = 0

    def write(self, t_s: float, x_m: float, y_m: float, yaw_rad: float) -> None:
        assert self._file is not None
        half = 0.5 * yaw_rad
        self._file.write(
            f"{t_s:.9f} {x_m:.9f} {y_m:.9f} 0 0 0 {math.sin(half):.12f} {math.cos(half):.12f}\n"
        )
        self.poses += 1

    def flush(self) -> None:
        if self._file is not None:
            self._file.flush()

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None
            os.replace(self.partial, self.path)


@dataclass
class OdometryCounts:
    lines: int = 0
    poses: int = 0
    malformed: int = 0
    reconnects: int = 0
    last_error: str = ""


class OdometryReader:
    """Reads a source in a thread: poses to a TUM file (and ``on_pose``), every line to a raw
    log (either file may be None).

    ``clock`` says how poses are stamped: ``"arrival"`` (the local clock at arrival; the line's
    own stamp is only logged), or ``"source"`` (the line's stamp, kept as it is; its clock is
    declared in the recording). A dropped stream is reconnected every ``retry_s``.
    """

    def __init__(
        self,
        source: OdometrySource,
        tum_path: Path | None,
        raw_path: Path | None,
        *,
        clock: str = "source",
        local_clock: Callable[[], float] = time.monotonic,
        retry_s: float = 0.5,
        flush_s: float = 1.0,
        on_pose: Callable[[float, float, float, float], None] | None = None,
    ) -> None:
        if clock not in ("arrival", "source"):
            raise RecordingError(f"odometry clock must be 'arrival' or 'source', got {clock!r}")
        self.source = source
        self.clock = clock
        self.local_clock = local_clock
        self.retry_s = retry_s
        self.flush_s = flush_s
        self.counts = OdometryCounts()
        self.on_pose = on_pose
        self._tum = TumAppender(tum_path) if tum_path is not None else None
        self._raw_path = raw_path
        self._raw: TextIO | None = None
        if raw_path is not None:
            self._raw_partial = raw_path.with_name(raw_path.name + ".partial")
            self._raw = open(self._raw_partial, "x", encoding="utf-8")  # noqa: SIM115
        self._buffer = b""
        self._last_t = -math.inf
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Connect (a failure is a RecordingError), then read in a thread."""
        self.source.connect()
        self._thread = threading.Thread(target=self._run, name="odometry", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        flushed = self.local_clock()
        while not self._stop.is_set():
            try:
                data = self.source.read(0.1)
            except RecordingError as exc:
                self.counts.last_error = str(exc)
                self._buffer = b""
                if self._stop.wait(self.retry_s):
                    break
                with contextlib.suppress(RecordingError):
                    self.source.connect()
                    self.counts.reconnects += 1
                continue
            if data:
                self.feed(data, self.local_clock())
            if self.local_clock() - flushed > self.flush_s:
                self._flush()
                flushed = self.local_clock()

    def feed(self, data: bytes, arrival_s: float) -> None:
        """Split received bytes into lines and record them (the thread calls this)."""
        self._buffer += data
        *lines, self._buffer = self._buffer.split(b"\n")
        if len(self._buffer) > MAX_LINE_BYTES:
            self._buffer = b""
            self.counts.malformed += 1
        for raw in lines:
            self._line(raw.rstrip(b"\r"), arrival_s)

    def _line(self, raw: bytes, arrival_s: float) -> None:
        text = raw.decode("ascii", errors="replace")
        if self._raw is not None:
            self._raw.write(f"{arrival_s:.9f}\t{text[:MAX_LINE_BYTES]}\n")
        stripped = text.strip()
        if not stripped or stripped.startswith("#"):
            return
        self.counts.lines += 1
        pose = parse_line(stripped) if len(raw) <= MAX_LINE_BYTES else None
        if pose is None or "\ufffd" in text:
            self.counts.malformed += 1
            return
        t_s = arrival_s if self.clock == "arrival" else pose[0]
        if t_s < self._last_t:
            self.counts.malformed += 1
            return
        self._last_t = t_s
        if self._tum is not None:
            self._tum.write(t_s, pose[1], pose[2], pose[3])
        if self.on_pose is not None:
            self.on_pose(t_s, pose[1], pose[2], pose[3])
        self.counts.poses += 1

    def _flush(self) -> None:
        if self._tum is not None:
            self._tum.flush()
        if self._raw is not None:
            self._raw.flush()

    def close(self) -> OdometryCounts:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.source.close()
        if self._tum is not None:
            self._tum.close()
        if self._raw is not None and self._raw_path is not None:
            self._raw.close()
            self._raw = None
            os.replace(self._raw_partial, self._raw_path)
        return self.counts
