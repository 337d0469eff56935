"""A recorded mission served as robots' hardware presents it: the rehearsal of a real recording.

For each robot of a dataset (docs/dataset.md) the replay runs an LMS 200 emulator on a pty that
sends the dataset's own measured-value telegrams, byte for byte, each finishing at its recorded
receive stamp; a TCP port that streams the robot's odometry as lines ``t_s x_m y_m yaw_rad``
(docs/recording.md) at their stamps; and one clock server for all robots. Everything runs on one
simulated clock, ``t = start_s + speed · (monotonic − m0)``: the emulator's baud pacing and scan
cadence, the odometry, and the clock served — so a mission of minutes replays in seconds, and a
recorder's clock exchange sees a reference running ``speed`` times faster than its own clock.

The clock starts ``lead_s`` before mission time 0, so the recorders can start up first. Before
the first recorded telegram and after the last, the emulator streams the first (last) recorded
scan again at the same cadence with consistent real-time indices, as a sensor streams before and
after a mission; odometry repeats the first pose before the mission at the recorded rate.
"""

from __future__ import annotations

import bisect
import math
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sensors.errors import SensorError
from sensors.lms200.capture import CaptureReader
from sensors.lms200.emulator import Lms200Emulator
from sensors.lms200.protocol.scan import decode_scan, encode_scan
from sensors.lms200.protocol.stream import StreamParser, Telegram
from sensors.lms200.protocol.telegram import TURN_S
from sensors.recording.clock import ClockServer
from sensors.trajio import read_tum

__all__ = ["OdometryServer", "Replay", "ReplayEndpoint", "SimClock", "TelegramSchedule"]


class SimClock:
    """``start_s + speed · (monotonic − m0)``, m0 taken when it is made."""

    def __init__(self, start_s: float, speed: float) -> None:
        if not (speed > 0 and math.isfinite(speed)):
            raise SensorError(f"replay speed must be > 0, got {speed}")
        self.start_s = start_s
        self.speed = speed
        self._m0 = time.monotonic()

    def now(self) -> float:
        return self.start_s + self.speed * (time.monotonic() - self._m0)

    def sleep_until(self, t_s: float, stop: threading.Event) -> bool:
        """Wait until the clock reads ``t_s``; False when ``stop`` was set first."""
        while (left := t_s - self.now()) > 0:
            if stop.wait(min(left / self.speed, 0.05)):
                return False
        return not stop.is_set()


class TelegramSchedule:
    """When each telegram starts on the line: it finishes at its recorded stamp at ``baud``.

    Built from a capture's measured-value telegrams, padded with the first (last) one re-sent
    at the recorded cadence from ``from_s`` (until ``until_s``).
    """

    def __init__(
        self, capture: Path, baud: int, from_s: float, until_s: float, measuring_mode: int = 1
    ) -> None:
        parser = StreamParser("from_sensor")
        recorded: list[tuple[float, bytes]] = []
        for stamp, chunk in CaptureReader(capture).chunks():
            for event in parser.feed(chunk, stamp):
                if isinstance(event, Telegram) and event.code == 0xB0 and event.stamp_s is not None:
                    raw = event.raw
                    recorded.append((event.stamp_s - len(raw) * 10.0 / baud, raw))
        if len(recorded) < 2:
            raise SensorError(f"{capture}: fewer than two measured-value telegrams to replay")
        self.recorded = len(recorded)
        self.first_s, self.last_s = recorded[0][0], recorded[-1][0]
        interval = float(np.median(np.diff([s for s, _ in recorded])))
        turns = max(1, round(interval / TURN_S))
        before = self._padding(recorded[0], -turns, from_s, measuring_mode)
        after = self._padding(recorded[-1], turns, until_s, measuring_mode)
        self.telegrams = [*reversed(before), *recorded, *after]
        self.starts = [s for s, _ in self.telegrams]

    @staticmethod
    def _padding(
        anchor: tuple[float, bytes], step: int, limit_s: float, measuring_mode: int
    ) -> list[tuple[float, bytes]]:
        start, raw = anchor
        telegram = next(e for e in StreamParser("from_sensor").feed(raw) if isinstance(e, Telegram))
        scan = decode_scan(telegram, measuring_mode)
        index, counter = scan.scan_index or 0, scan.telegram_index or 0
        sign = 1 if step > 0 else -1
        count = max(0, math.floor((limit_s - start) * sign / (abs(step) * TURN_S)))
        return [
            (start + k * step * TURN_S, encode_scan(
                scan.ranges_m, flags=scan.flags, codes=scan.code, measuring_mode=measuring_mode,
                unit_mm=scan.unit_m == 0.001, scan_index=(index + k * step) & 0xFF,
                telegram_index=(counter + k * sign) & 0xFF,
            ))
            for k in range(1, count + 1)
        ]  # fmt: skip

    def __call__(self, after_s: float) -> tuple[float, bytes] | None:
        """The first telegram that starts after ``after_s``."""
        k = bisect.bisect_right(self.starts, after_s)
        return self.telegrams[k] if k < len(self.telegrams) else None


class OdometryServer:
    """Streams poses as lines at their stamps to every client of a TCP port."""

    def __init__(
        self, stamps_s: np.ndarray, poses: np.ndarray, clock: SimClock, host: str, port: int = 0
    ) -> None:
        self.stamps_s, self.poses, self.clock = stamps_s, poses, clock
        self.host, self.port = host, port
        self.clients = 0
        self._sock: socket.socket | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    def start(self) -> int:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((self.host, self.port))
        except OSError as exc:
            sock.close()
            raise SensorError(
                f"odometry replay: cannot listen on {self.host}:{self.port}: {exc.strerror}"
            ) from None
        sock.listen(4)
        sock.settimeout(0.1)
        self._sock = sock
        self.port = sock.getsockname()[1]
        self._spawn(self._accept)
        return self.port

    def _spawn(self, target: object, *args: object) -> None:
        thread = threading.Thread(target=target, args=args, daemon=True)  # type: ignore[arg-type]
        thread.start()
        self._threads.append(thread)

    def _accept(self) -> None:
        assert self._sock is not None
        while not self._stop.is_set():
            try:
                client, _ = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            self.clients += 1
            self._spawn(self._serve, client)

    def _serve(self, client: socket.socket) -> None:
        first = int(np.searchsorted(self.stamps_s, self.clock.now()))
        with client:
            for k in range(first, len(self.stamps_s)):
                if not self.clock.sleep_until(float(self.stamps_s[k]), self._stop):
                    return
                x, y, yaw = self.poses[k]
                line = f"{self.stamps_s[k]:.9f} {x:.9f} {y:.9f} {yaw:.12f}\n"
                try:
                    client.sendall(line.encode("ascii"))
                except OSError:
                    return
            self._stop.wait()  # the stream ends; the connection stays open, as a quiet base's

    def close(self) -> None:
        self._stop.set()
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        for thread in self._threads:
            thread.join(timeout=2.0)


@dataclass(frozen=True)
class ReplayEndpoint:
    robot: str
    device_path: str
    odometry_port: int


class Replay:
    """Serves the robots of a dataset (see the module docstring); ``close`` ends everything."""

    def __init__(
        self,
        dataset: Path | str,
        robots: list[str],
        *,
        speed: float = 1.0,
        lead_s: float = 30.0,
        tail_s: float = 30.0,
        host: str = "127.0.0.1",
        clock_port: int = 0,
        measuring_mode: int = 1,
    ) -> None:
        self.dataset = Path(dataset)
        self.robots = robots
        self.speed, self.lead_s, self.tail_s = speed, lead_s, tail_s
        self.host, self.clock_port = host, clock_port
        self.measuring_mode = measuring_mode
        self.clock: SimClock | None = None
        self.end_s = 0.0
        self.endpoints: dict[str, ReplayEndpoint] = {}
        self.emulators: dict[str, Lms200Emulator] = {}
        self._odometry: list[OdometryServer] = []
        self._server: ClockServer | None = None
        for robot in robots:
            for name in ("lms.cap", "odometry.tum"):
                if not (self.dataset / "robots" / robot / name).is_file():
                    raise SensorError(f"{self.dataset}: robot {robot!r} has no {name} to replay")

    def start(self) -> dict[str, ReplayEndpoint]:
        """Read every robot's recording, start the clock at −lead_s, start serving."""
        schedules, tracks = {}, {}
        for robot in self.robots:
            folder = self.dataset / "robots" / robot
            header = CaptureReader(folder / "lms.cap").header or {}
            baud = int(header.get("baud_rate", 38400))
            stamps, poses = read_tum(folder / "odometry.tum")
            end = float(stamps[-1])
            schedules[robot] = (baud, folder / "lms.cap")
            tracks[robot] = (stamps, poses)
            self.end_s = max(self.end_s, end)
        try:
            built = {
                r: (baud, TelegramSchedule(cap, baud, -self.lead_s, self.end_s + self.tail_s,
                                           self.measuring_mode))
                for r, (baud, cap) in schedules.items()
            }  # fmt: skip
            self.end_s = max([self.end_s, *(s.last_s for _, s in built.values())])
            clock = self.clock = SimClock(-self.lead_s, self.speed)
            self._server = ClockServer(clock.now, self.host, self.clock_port)
            self.clock_port = self._server.start()[1]
            for robot in self.robots:
                baud, schedule = built[robot]
                emulator = Lms200Emulator(
                    _no_scan, power_on_baud=baud, clock=clock.now, stream=schedule
                )
                self.emulators[robot] = emulator
                path = emulator.start()
                stamps, poses = _with_lead(*tracks[robot], -self.lead_s)
                server = OdometryServer(stamps, poses, clock, self.host)
                self._odometry.append(server)
                self.endpoints[robot] = ReplayEndpoint(robot, path, server.start())
        except BaseException:
            self.close()
            raise
        return self.endpoints

    @property
    def finished(self) -> bool:
        return self.clock is not None and self.clock.now() > self.end_s + self.tail_s

    def close(self) -> None:
        for emulator in self.emulators.values():
            emulator.close()
        for server in self._odometry:
            server.close()
        if self._server is not None:
            self._server.close()

    def __enter__(self) -> Replay:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _no_scan(t_s: float, count: int) -> tuple[np.ndarray, np.ndarray]:
    """On-request scans of a replay: no returns (the stream carries the recorded ones)."""
    return np.full(count, np.nan), np.zeros(count, dtype=np.uint8)


def _with_lead(stamps: np.ndarray, poses: np.ndarray, from_s: float) -> tuple[np.ndarray, ...]:
    """The first pose repeated back to ``from_s`` at the recorded rate."""
    step = float(np.median(np.diff(stamps))) if len(stamps) > 1 else 0.1
    count = max(0, math.floor((stamps[0] - from_s) / step))
    lead = stamps[0] - step * np.arange(count, 0, -1)
    return np.concatenate([lead, stamps]), np.vstack([np.repeat(poses[:1], count, 0), poses])
