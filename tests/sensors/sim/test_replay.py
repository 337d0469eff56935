"""The replay's pieces: the simulated clock, the telegram schedule, the odometry stream."""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from sensors.errors import SensorError
from sensors.lms200.capture import CaptureWriter
from sensors.lms200.protocol.scan import decode_scan, encode_scan
from sensors.lms200.protocol.stream import StreamParser, Telegram
from sensors.lms200.protocol.telegram import TURN_S
from sensors.recording.odometry import parse_line
from sensors.sim.replay import OdometryServer, SimClock, TelegramSchedule


def capture(path: Path, turns: list[int], baud: int = 38400) -> list[bytes]:
    writer = CaptureWriter(path, {"baud_rate": baud})
    telegrams = []
    for k, turn in enumerate(turns):
        raw = encode_scan(np.full(101, 1.0 + k), scan_index=turn & 0xFF, telegram_index=k)
        writer.write(turn * TURN_S + 0.07, raw)
        telegrams.append(raw)
    writer.close()
    return telegrams


def indices(raw: bytes) -> tuple[int | None, int | None]:
    event = next(e for e in StreamParser().feed(raw) if isinstance(e, Telegram))
    scan = decode_scan(event, 1)
    return scan.scan_index, scan.telegram_index


def test_the_schedule_ends_each_telegram_at_its_stamp_and_pads_both_ends(tmp_path: Path) -> None:
    recorded = capture(tmp_path / "c.cap", [300, 305, 310, 315])
    schedule = TelegramSchedule(tmp_path / "c.cap", 38400, from_s=300 * TURN_S - 0.2,
                                until_s=315 * TURN_S + 0.1)  # fmt: skip
    assert schedule.recorded == 4
    start, raw = schedule(schedule.first_s)  # type: ignore[misc]
    assert raw == recorded[1]
    assert start + len(raw) * 10 / 38400 == pytest.approx(305 * TURN_S + 0.07)
    before = [t for t, _ in schedule.telegrams if t < schedule.first_s]
    assert len(before) == 3  # 0.2 s back at 5 turns each
    assert np.diff(schedule.starts) == pytest.approx(5 * TURN_S)
    first_pad = schedule.telegrams[2][1]
    assert indices(first_pad) == ((300 - 5) & 0xFF, 255)
    assert indices(schedule.telegrams[-1][1]) == ((315 + 5) & 0xFF, 4)
    assert schedule(schedule.starts[-1]) is None


def test_a_capture_without_telegrams_cannot_be_replayed(tmp_path: Path) -> None:
    capture(tmp_path / "c.cap", [3])
    with pytest.raises(SensorError, match="fewer than two"):
        TelegramSchedule(tmp_path / "c.cap", 38400, 0.0, 1.0)


def test_the_simulated_clock_runs_at_its_speed() -> None:
    clock = SimClock(-10.0, 20.0)
    start, t0 = clock.now(), time.monotonic()
    assert start == pytest.approx(-10.0, abs=0.05)
    assert clock.sleep_until(start + 2.0, threading.Event())
    assert time.monotonic() - t0 == pytest.approx(0.1, abs=0.05)
    stop = threading.Event()
    stop.set()
    assert not clock.sleep_until(clock.now() + 100, stop)
    with pytest.raises(SensorError, match="speed must be > 0"):
        SimClock(0, 0)


def test_odometry_lines_arrive_at_their_stamps() -> None:
    clock = SimClock(0.0, 10.0)
    stamps = np.arange(0.0, 1.0, 0.1) + 0.5
    poses = np.column_stack([stamps, 2 * stamps, np.zeros_like(stamps)])
    server = OdometryServer(stamps, poses, clock, "127.0.0.1")
    port = server.start()
    received: list[tuple[float, tuple[float, float, float, float]]] = []
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=5) as client:
            buffer = b""
            while len(received) < len(stamps):
                buffer += client.recv(4096)
                *lines, buffer = buffer.split(b"\n")
                for line in lines:
                    pose = parse_line(line.decode())
                    assert pose is not None
                    received.append((clock.now(), pose))
    finally:
        server.close()
    arrival = np.array([t for t, _ in received])
    sent = np.array([p[0] for _, p in received])
    assert sent == pytest.approx(stamps)
    assert (arrival >= sent - 1e-6).all()
    assert np.median(arrival - sent) < 0.1  # 10 ms of real time at 10x
    assert received[3][1][1:3] == pytest.approx((stamps[3], 2 * stamps[3]))
