"""Driving a robot base: the goal line protocol, its client, and a simulated base that speaks it.

A robot agent on real hardware (``coopmap robot --port ... --drive tcp://HOST:PORT``) hands each
goal to the robot's base controller over TCP, one ASCII line each way (docs/recording.md)::

    agent → base:  goal ID X_M Y_M YAW_RAD [WX_M WY_M ...]
    base → agent:  arrived ID
                   failed ID REASON...

Goals are in the base's **odometry frame** (the frame of the odometry lines it streams): the
agent turns the mission's map-frame goal into it from where the odometry says the robot stood
when the goal was planned. The optional pairs are waypoints to pass, in order, before the goal.
``ID`` is a positive integer; a base answers each goal once, and a goal sent again with the same
ID (after a reconnection) is the same goal. Lines are at most 256 bytes; anything else the base
sends is counted and ignored. The agent sends ``stop`` when it gives up on a goal (timeout).

:class:`SimulatedBase` is the other side for rehearsals and tests: a base that drives at a
given speed and turn rate along the waypoints, streams its odometry in the odometry line format
(``sensors.recording.odometry``) on a second port, and can be told to fail goals.
"""

from __future__ import annotations

import contextlib
import math
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlsplit

from sensors.errors import RecordingError
from sensors.recording.odometry import MAX_LINE_BYTES

__all__ = ["DriveClient", "DriveCounts", "DriveResult", "SimulatedBase", "parse_drive_endpoint"]


def parse_drive_endpoint(spec: str) -> tuple[str, int]:
    """``tcp://HOST:PORT`` → (host, port); RecordingError naming the spec otherwise."""
    parts = urlsplit(spec)
    try:
        port = parts.port
    except ValueError:
        port = None
    if parts.scheme != "tcp" or not parts.hostname or port is None:
        raise RecordingError(f"drive {spec!r}: expected tcp://HOST:PORT")
    return parts.hostname, port


def goal_line(goal_id: int, pose: tuple[float, float, float],
              waypoints: list[tuple[float, float]]) -> bytes:  # fmt: skip
    """One ``goal`` line (odometry frame, metres and radians)."""
    values = [*pose, *(v for p in waypoints for v in p)]
    if not all(math.isfinite(v) for v in values):
        raise RecordingError(f"drive: goal {goal_id} has a non-finite coordinate")
    text = " ".join(f"{v:.6f}" for v in values)
    return f"goal {goal_id} {text}\n".encode("ascii")


@dataclass(frozen=True)
class DriveResult:
    ok: bool
    reason: str | None = None
    seconds: float = 0.0


@dataclass
class DriveCounts:
    goals: int = 0
    arrived: int = 0
    failed: int = 0
    ignored_lines: int = 0
    reconnects: int = 0


class DriveClient:
    """The agent's side of the goal protocol (see the module's docstring)."""

    def __init__(self, spec: str, connect_timeout_s: float = 2.0) -> None:
        self.host, self.port = parse_drive_endpoint(spec)
        self.name = f"tcp://{self.host}:{self.port}"
        self.connect_timeout_s = connect_timeout_s
        self.counts = DriveCounts()
        self._sock: socket.socket | None = None
        self._buffer = b""

    def connect(self) -> None:
        self.close()
        try:
            self._sock = socket.create_connection((self.host, self.port),
                                                  timeout=self.connect_timeout_s)  # fmt: skip
        except OSError as exc:
            why = exc.strerror or exc
            raise RecordingError(f"drive {self.name}: cannot connect: {why}") from None
        self._buffer = b""

    def go(self, goal_id: int, pose: tuple[float, float, float],
           waypoints: list[tuple[float, float]], timeout_s: float,
           stop: threading.Event | None = None) -> DriveResult:  # fmt: skip
        """Send one goal and wait for its answer: arrived, failed, or given up (timeout, stop,
        or a link that cannot be re-established; then ``stop`` is sent)."""
        line = goal_line(goal_id, pose, waypoints)
        self.counts.goals += 1
        began = time.monotonic()
        deadline = began + timeout_s
        sent = False
        while time.monotonic() < deadline and not (stop is not None and stop.is_set()):
            try:
                if not sent:
                    self._send(line)
                    sent = True
                answer = self._answer(goal_id, min(0.2, max(0.0, deadline - time.monotonic())))
            except RecordingError:
                sent = False  # send it again once the link is back: same ID, same goal
                with contextlib.suppress(RecordingError):
                    time.sleep(0.2)
                    self.connect()
                    self.counts.reconnects += 1
                continue
            if answer is not None:
                ok, reason = answer
                self.counts.arrived += ok
                self.counts.failed += not ok
                return DriveResult(ok, reason, time.monotonic() - began)
        with contextlib.suppress(RecordingError):
            self._send(b"stop\n")
        self.counts.failed += 1
        why = "stopped" if stop is not None and stop.is_set() else f"no answer in {timeout_s:g} s"
        return DriveResult(False, f"goal {goal_id}: {why}", time.monotonic() - began)

    def _send(self, data: bytes) -> None:
        if self._sock is None:
            raise RecordingError(f"drive {self.name}: not connected")
        try:
            self._sock.sendall(data)
        except OSError as exc:
            raise RecordingError(f"drive {self.name}: {exc.strerror or exc}") from None

    def _answer(self, goal_id: int, timeout_s: float) -> tuple[bool, str | None] | None:
        """The answer to ``goal_id`` among the lines that arrive within ``timeout_s``."""
        assert self._sock is not None
        while b"\n" not in self._buffer:
            self._sock.settimeout(max(timeout_s, 1e-3))
            try:
                data = self._sock.recv(4096)
            except TimeoutError:
                return None
            except OSError as exc:
                raise RecordingError(f"drive {self.name}: {exc.strerror or exc}") from None
            if not data:
                raise RecordingError(f"drive {self.name}: the base closed the link")
            self._buffer += data
            if len(self._buffer) > 16 * MAX_LINE_BYTES:
                self._buffer = b""
                self.counts.ignored_lines += 1
        while b"\n" in self._buffer:
            raw, self._buffer = self._buffer.split(b"\n", 1)
            words = raw.decode("ascii", errors="replace").split()
            if len(raw) > MAX_LINE_BYTES or len(words) < 2 or words[0] not in ("arrived", "failed"):
                self.counts.ignored_lines += 1
                continue
            if words[1] != str(goal_id):
                self.counts.ignored_lines += 1  # an earlier goal's late answer
                continue
            if words[0] == "arrived":
                return True, None
            return False, " ".join(words[2:]) or "the base gave no reason"
        return None

    def close(self) -> None:
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.close()
            self._sock = None


@dataclass
class _Motion:
    pose: list[float]
    legs: list[tuple[float, float, float | None]] = field(default_factory=list)
    goal_id: int | None = None
    conn: socket.socket | None = None


class SimulatedBase:
    """A robot base on loopback that speaks the goal protocol and streams odometry lines.

    It turns on the spot towards each waypoint, drives straight to it, then turns to the goal's
    heading, at ``speed_m_s`` and ``turn_rate_rad_s``; odometry lines ``t_s x y yaw`` go to every
    client of the odometry port every ``period_s``, stamped by ``clock``. ``fail`` decides, per
    goal, a reason to refuse it (None: drive).
    """

    def __init__(self, start: tuple[float, float, float] = (0.0, 0.0, 0.0), *,
                 speed_m_s: float = 2.0, turn_rate_rad_s: float = 2.0, period_s: float = 0.05,
                 clock: Callable[[], float] = time.monotonic,
                 fail: Callable[[int, tuple[float, float, float]], str | None] | None = None,
                 host: str = "127.0.0.1") -> None:  # fmt: skip
        self.speed_m_s, self.turn_rate_rad_s, self.period_s = speed_m_s, turn_rate_rad_s, period_s
        self.clock, self.fail, self.host = clock, fail, host
        self.motion = _Motion(list(start))
        self.goals: list[tuple[int, tuple[float, float, float], list[tuple[float, float]]]] = []
        self.malformed = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._odometry_clients: list[socket.socket] = []
        self._servers: list[socket.socket] = []
        self._threads: list[threading.Thread] = []
        self.odometry_port = self.drive_port = 0

    def start(self) -> SimulatedBase:
        odometry, drive = (socket.create_server((self.host, 0)) for _ in range(2))
        self._servers = [odometry, drive]
        self.odometry_port, self.drive_port = odometry.getsockname()[1], drive.getsockname()[1]
        jobs: list[tuple[Callable[..., None], tuple[Any, ...]]] = [
            (self._accept, (odometry, self._odometry_client)),
            (self._accept, (drive, self._drive_client)),
            (self._run, ()),
        ]
        for target, args in jobs:
            thread = threading.Thread(target=target, args=args, daemon=True)
            thread.start()
            self._threads.append(thread)
        return self

    @property
    def pose(self) -> tuple[float, float, float]:
        with self._lock:
            x, y, yaw = self.motion.pose
        return x, y, yaw

    def _accept(self, server: socket.socket, serve: Callable[[socket.socket], None]) -> None:
        server.settimeout(0.1)
        while not self._stop.is_set():
            try:
                conn, _ = server.accept()
            except (TimeoutError, OSError):
                continue
            threading.Thread(target=serve, args=(conn,), daemon=True).start()

    def _odometry_client(self, conn: socket.socket) -> None:
        with self._lock:
            self._odometry_clients.append(conn)

    def _drive_client(self, conn: socket.socket) -> None:
        buffer = b""
        conn.settimeout(0.1)
        while not self._stop.is_set():
            try:
                data = conn.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            if not data:
                return
            buffer += data
            while b"\n" in buffer:
                raw, buffer = buffer.split(b"\n", 1)
                self._command(conn, raw.decode("ascii", errors="replace").split())

    def _command(self, conn: socket.socket, words: list[str]) -> None:
        if words == ["stop"]:
            with self._lock:
                self.motion.legs, self.motion.goal_id = [], None
            return
        try:
            if words[0] != "goal" or len(words) < 5 or len(words) % 2 == 0:
                raise ValueError
            goal_id = int(words[1])
            values = [float(w) for w in words[2:]]
            if not all(math.isfinite(v) for v in values):
                raise ValueError
        except (ValueError, IndexError):
            self.malformed += 1
            return
        pose = (values[0], values[1], values[2])
        waypoints = [(values[k], values[k + 1]) for k in range(3, len(values), 2)]
        with self._lock:
            if any(g[0] == goal_id for g in self.goals):
                return  # the same goal sent again after a reconnection
            self.goals.append((goal_id, pose, waypoints))
            reason = self.fail(goal_id, pose) if self.fail is not None else None
            if reason is not None:
                _send(conn, f"failed {goal_id} {reason}\n")
                return
            legs: list[tuple[float, float, float | None]] = [(x, y, None) for x, y in waypoints]
            self.motion.legs = [*legs, (pose[0], pose[1], pose[2])]
            self.motion.goal_id, self.motion.conn = goal_id, conn

    def _run(self) -> None:
        next_odometry = 0.0
        last = time.monotonic()
        while not self._stop.wait(0.01):
            now = time.monotonic()
            with self._lock:
                self._advance(now - last)
                pose = list(self.motion.pose)
            last = now
            if now >= next_odometry:
                next_odometry = now + self.period_s
                line = f"{self.clock():.6f} {pose[0]:.6f} {pose[1]:.6f} {pose[2]:.6f}\n"
                with self._lock:
                    clients = list(self._odometry_clients)
                for client in clients:
                    if not _send(client, line):
                        with self._lock:
                            self._odometry_clients.remove(client)

    def _advance(self, dt_s: float) -> None:
        """Move along the legs for ``dt_s`` (turn towards the leg's point, drive, final turn)."""
        m = self.motion
        while m.legs and dt_s > 0:
            x, y, final_yaw = m.legs[0]
            dx, dy = x - m.pose[0], y - m.pose[1]
            distance = math.hypot(dx, dy)
            heading = math.atan2(dy, dx) if distance > 1e-6 else m.pose[2]
            turn = _wrap(heading - m.pose[2])
            if abs(turn) > 1e-9 and distance > 1e-6:
                step = min(abs(turn), self.turn_rate_rad_s * dt_s)
                m.pose[2] = _wrap(m.pose[2] + math.copysign(step, turn))
                dt_s -= step / self.turn_rate_rad_s
                continue
            if distance > 1e-6:
                step = min(distance, self.speed_m_s * dt_s)
                m.pose[0] += step * dx / distance
                m.pose[1] += step * dy / distance
                dt_s -= step / self.speed_m_s
                continue
            turn = 0.0 if final_yaw is None else _wrap(final_yaw - m.pose[2])
            if abs(turn) > 1e-9:
                step = min(abs(turn), self.turn_rate_rad_s * dt_s)
                m.pose[2] = _wrap(m.pose[2] + math.copysign(step, turn))
                dt_s -= step / self.turn_rate_rad_s
                continue
            m.legs.pop(0)
            if not m.legs and m.goal_id is not None and m.conn is not None:
                _send(m.conn, f"arrived {m.goal_id}\n")
                m.goal_id = None

    def close(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=2.0)
        for sock in [*self._servers, *self._odometry_clients]:
            with contextlib.suppress(OSError):
                sock.close()

    def __enter__(self) -> SimulatedBase:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


def _send(conn: socket.socket, text: str) -> bool:
    try:
        conn.sendall(text.encode("ascii"))
    except OSError:
        return False
    return True


def _wrap(angle_rad: float) -> float:
    return (angle_rad + math.pi) % (2 * math.pi) - math.pi
