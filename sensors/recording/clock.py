"""A robot's clock mapped onto a reference clock: an NTP-style exchange over UDP, and the fit.

The exchange (docs/recording.md): the client sends ``MAGIC t1`` (t1: its local send time); the
server answers ``MAGIC t1 t2 t3`` (t2: when the request arrived, t3: when the answer left, both
on the reference clock); the client notes t4, its local receive time. Assuming the two legs take
equally long, the reference time ``(t2 + t3) / 2`` was read at the local time ``(t1 + t4) / 2``,
to within half the round trip ``t4 − t1``. Repeated exchanges give samples of that relation; a
straight line through the ones with the shortest round trips gives the mapping
``reference = offset_s + rate · local``: the offset, and the drift as ``rate − 1``. A rate far
from 1 is also fine: a simulator's clock that runs K times faster than real time has rate K.

Every datagram is 16 (request) or 32 (reply) bytes, float64 little-endian after the 8-byte magic.
Datagrams of any other shape are counted and ignored on both sides.
"""

from __future__ import annotations

import contextlib
import math
import socket
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from sensors.errors import RecordingError

__all__ = [
    "ClockMapping",
    "ClockSample",
    "ClockServer",
    "ClockSync",
    "exchange",
    "fit_mapping",
    "parse_endpoint",
]

MAGIC = b"COOPCLK1"
_REQUEST = struct.Struct("<8sd")
_REPLY = struct.Struct("<8sddd")
Clock = Callable[[], float]


def parse_endpoint(text: str, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """``HOST:PORT`` (or ``:PORT``, ``PORT``) → (host, port); a bad value is a RecordingError."""
    host, _, port = text.rpartition(":")
    try:
        number = int(port)
    except ValueError:
        raise RecordingError(f"{text!r}: expected HOST:PORT") from None
    if not 0 <= number <= 65535:
        raise RecordingError(f"{text!r}: port must be 0-65535")
    return (host.strip("[]") or default_host), number


@dataclass(frozen=True)
class ClockSample:
    """One exchange: t1, t4 on the local clock; t2, t3 on the reference clock (seconds)."""

    t1: float
    t2: float
    t3: float
    t4: float

    @property
    def local_s(self) -> float:
        return 0.5 * (self.t1 + self.t4)

    @property
    def reference_s(self) -> float:
        return 0.5 * (self.t2 + self.t3)

    @property
    def round_trip_s(self) -> float:
        """The local round trip (including the server's turnaround)."""
        return self.t4 - self.t1

    def as_list(self) -> list[float]:
        return [self.t1, self.t2, self.t3, self.t4]


@dataclass(frozen=True)
class ClockMapping:
    """``reference_s = offset_s + rate · local_s``, and how it was obtained."""

    offset_s: float
    rate: float = 1.0
    source: str = "given"  # "server" (fitted from exchanges) or "given" (by the user)
    samples_used: int = 0
    residual_rms_s: float = 0.0  # of the used samples about the line (reference seconds)
    max_round_trip_s: float = 0.0  # of the used samples (local seconds)

    def to_reference(self, local_s: float | np.ndarray) -> float | np.ndarray:
        return self.offset_s + self.rate * local_s

    def to_local(self, reference_s: float) -> float:
        return (reference_s - self.offset_s) / self.rate

    @property
    def uncertainty_s(self) -> float:
        """Half the longest round trip used, on the reference clock: the bound of the
        symmetric-path assumption."""
        return 0.5 * self.max_round_trip_s * abs(self.rate)

    def as_dict(self) -> dict[str, float | int | str]:
        return {
            "offset_s": self.offset_s,
            "rate": self.rate,
            "drift_ppm": (self.rate - 1.0) * 1e6,
            "source": self.source,
            "samples_used": self.samples_used,
            "residual_rms_s": self.residual_rms_s,
            "max_round_trip_s": self.max_round_trip_s,
            "uncertainty_s": self.uncertainty_s,
        }


def fit_mapping(
    samples: Sequence[ClockSample],
    *,
    keep_fraction: float = 0.5,
    min_rate_span_s: float = 0.1,
) -> ClockMapping:
    """The mapping from the best samples: the ``keep_fraction`` with the shortest round trips
    (at least two, when there are two), fitted by least squares to a line. When the kept samples
    span less than ``min_rate_span_s`` of local time the rate cannot be told from noise: it is
    fixed at 1 and the offset is their median."""
    if not samples:
        raise RecordingError("no clock samples to fit")
    ordered = sorted(samples, key=lambda s: s.round_trip_s)
    keep = ordered[: max(min(2, len(ordered)), math.ceil(keep_fraction * len(ordered)))]
    local = np.array([s.local_s for s in keep])
    reference = np.array([s.reference_s for s in keep])
    centre = float(np.mean(local))
    if float(np.ptp(local)) < min_rate_span_s:
        rate = 1.0
        offset = float(np.median(reference - local))
    else:
        rate, intercept = np.polyfit(local - centre, reference, 1)
        rate = float(rate)
        offset = float(intercept - rate * centre)
    residual = reference - (offset + rate * local)
    return ClockMapping(
        offset_s=offset,
        rate=rate,
        source="server",
        samples_used=len(keep),
        residual_rms_s=float(np.sqrt(np.mean(residual**2))),
        max_round_trip_s=float(max(s.round_trip_s for s in keep)),
    )


def exchange(
    sock: socket.socket,
    server: tuple[str, int],
    local_clock: Clock = time.monotonic,
    timeout_s: float = 0.2,
) -> ClockSample | None:
    """One exchange on a UDP socket; None when no valid answer came within ``timeout_s``."""
    t1 = local_clock()
    try:
        sock.sendto(_REQUEST.pack(MAGIC, t1), server)
    except OSError:
        return None
    deadline = t1 + timeout_s
    while (left := deadline - local_clock()) > 0:
        sock.settimeout(left)
        try:
            data, _ = sock.recvfrom(64)
        except TimeoutError:
            return None
        except OSError:
            return None  # e.g. ICMP port unreachable: nobody listens there
        t4 = local_clock()
        if len(data) != _REPLY.size:
            continue
        magic, echo, t2, t3 = _REPLY.unpack(data)
        if magic != MAGIC or echo != t1 or not (math.isfinite(t2) and math.isfinite(t3)):
            continue  # garbage, or the late answer to an earlier request
        return ClockSample(t1, t2, t3, t4)
    return None


class ClockServer:
    """Serves ``clock`` (the reference clock) to exchanges on a UDP port, in a thread."""

    def __init__(self, clock: Clock = time.time, host: str = "127.0.0.1", port: int = 0) -> None:
        self.clock = clock
        self.host = host
        self.port = port
        self.answered = 0
        self.ignored = 0
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def start(self) -> tuple[str, int]:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((self.host, self.port))
        except OSError as exc:
            sock.close()
            raise RecordingError(
                f"clock server: cannot listen on {self.host}:{self.port}: {exc.strerror or exc}"
            ) from None
        sock.settimeout(0.1)
        self._sock = sock
        self.port = sock.getsockname()[1]
        self._thread = threading.Thread(target=self._run, name="clock-server", daemon=True)
        self._thread.start()
        return self.host, self.port

    def _run(self) -> None:
        assert self._sock is not None
        while not self._stop.is_set():
            try:
                data, peer = self._sock.recvfrom(64)
            except TimeoutError:
                continue
            except OSError:
                if self._stop.is_set():
                    return
                continue
            t2 = self.clock()
            if len(data) != _REQUEST.size or data[:8] != MAGIC:
                self.ignored += 1
                continue
            _, t1 = _REQUEST.unpack(data)
            self.answered += 1
            with contextlib.suppress(OSError):
                self._sock.sendto(_REPLY.pack(MAGIC, t1, t2, self.clock()), peer)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> ClockServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ClockSync:
    """The client side: exchanges with one clock server, the samples so far, and their fit."""

    def __init__(
        self,
        server: tuple[str, int],
        *,
        local_clock: Clock = time.monotonic,
        timeout_s: float = 0.2,
    ) -> None:
        self.server = server
        self.local_clock = local_clock
        self.timeout_s = timeout_s
        self.samples: list[ClockSample] = []
        self.lost = 0
        self._lock = threading.Lock()
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    @property
    def endpoint(self) -> str:
        return f"{self.server[0]}:{self.server[1]}"

    def sample(self) -> ClockSample | None:
        """One exchange; kept when answered, counted as lost when not."""
        found = exchange(self._sock, self.server, self.local_clock, self.timeout_s)
        with self._lock:
            if found is None:
                self.lost += 1
            else:
                self.samples.append(found)
        return found

    def burst(self, count: int = 8, *, tries: int = 20, pause_s: float = 0.02) -> int:
        """Up to ``count`` answered exchanges in at most ``tries``; a server that answers none is
        a RecordingError."""
        got = 0
        for _ in range(tries):
            if self.sample() is not None:
                got += 1
                if got >= count:
                    break
            time.sleep(pause_s)
        if got == 0:
            raise RecordingError(
                f"clock server {self.endpoint} did not answer ({tries} tries, "
                f"{self.timeout_s:g} s each)"
            )
        return got

    def snapshot(self) -> list[ClockSample]:
        """The samples so far (a copy; the sync thread appends to the list)."""
        with self._lock:
            return list(self.samples)

    def mapping(self) -> ClockMapping:
        return fit_mapping(self.snapshot())

    def close(self) -> None:
        self._sock.close()
