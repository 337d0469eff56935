"""Odometry lines: the format, the TCP and serial sources, malformed lines and dropped streams."""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from sensors.errors import RecordingError
from sensors.recording.odometry import (
    OdometryReader,
    SerialSource,
    TcpSource,
    open_source,
    parse_line,
)
from sensors.trajio import read_tum


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        ("1.5 2 3 0.25", (1.5, 2.0, 3.0, 0.25)),
        ("1.5,2,3,0.25,0.1,0.0", (1.5, 2.0, 3.0, 0.25)),
        ("1.5\t2\t3\t0.25", (1.5, 2.0, 3.0, 0.25)),
        ("1.5 2 3", None),
        ("1.5 2 x 0.2", None),
        ("1.5 2 nan 0.2", None),
        ("1 2 3 4 5 6 7 8 9", None),
    ],
)
def test_lines_parse_or_are_malformed(line: str, expected: tuple[float, ...] | None) -> None:
    assert parse_line(line) == expected


@pytest.fixture
def listener() -> Iterator[socket.socket]:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen(2)
        sock.settimeout(5)
        yield sock


def wait_for(condition: object, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():  # type: ignore[operator]
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_tcp_stream_with_garbage_and_a_drop(listener: socket.socket, tmp_path: Path) -> None:
    port = listener.getsockname()[1]
    reader = OdometryReader(
        TcpSource("127.0.0.1", port), tmp_path / "o.tum", tmp_path / "o.lines", retry_s=0.05
    )
    reader.start()
    try:
        client, _ = listener.accept()
        client.sendall(b"# a comment\n0.0 0 0 0\n0.1 0.05 0 0.01\ngarbage here\n\xff\xfe 1 2 3\n")
        client.sendall(b"0.05 9 9 9\n" + b"7" * 300 + b"\n0.2 0.1 0.0 0.02\r\n0.3 0.1")
        client.close()  # the stream drops mid-line
        again, _ = listener.accept()
        with again:
            again.sendall(b"5 0.15 0 0.03\n")
            wait_for(lambda: reader.counts.poses == 4)
    finally:
        counts = reader.close()
    stamps, poses = read_tum(tmp_path / "o.tum")
    assert stamps.tolist() == [0.0, 0.1, 0.2, 5.0]
    assert poses[:, 0] == pytest.approx([0, 0.05, 0.1, 0.15])
    assert poses[:, 2] == pytest.approx([0, 0.01, 0.02, 0.03], abs=1e-9)
    # garbage, non-ASCII, a stamp going back, an over-long line
    assert counts.malformed == 4
    assert counts.reconnects == 1
    raw = (tmp_path / "o.lines").read_text().splitlines()
    assert len(raw) == 9
    assert raw[3].split("\t")[1] == "garbage here"
    assert not (tmp_path / "o.tum.partial").exists()


def test_arrival_stamps_replace_the_lines_own(listener: socket.socket, tmp_path: Path) -> None:
    port = listener.getsockname()[1]
    reader = OdometryReader(
        open_source(f"tcp://127.0.0.1:{port}"), tmp_path / "o.tum", tmp_path / "o.lines",
        clock="arrival",
    )  # fmt: skip
    reader.start()
    try:
        client, _ = listener.accept()
        with client:
            before = time.monotonic()
            client.sendall(b"999 1 2 3\n")
            wait_for(lambda: reader.counts.poses == 1)
    finally:
        reader.close()
    stamps, _ = read_tum(tmp_path / "o.tum")
    assert before <= stamps[0] <= time.monotonic()


def test_a_serial_device_is_read_raw(tmp_path: Path) -> None:
    master, slave = os.openpty()
    try:
        source = open_source(f"serial://{os.ttyname(slave)}?baud=57600")
        assert isinstance(source, SerialSource)
        assert source.baud == 57600
        reader = OdometryReader(source, tmp_path / "o.tum", tmp_path / "o.lines")
        reader.start()
        try:
            os.write(master, b"1.0 2.0 3.0 0.5\n")
            wait_for(lambda: reader.counts.poses == 1)
        finally:
            reader.close()
    finally:
        os.close(master)
        os.close(slave)
    _, poses = read_tum(tmp_path / "o.tum")
    assert poses[0] == pytest.approx([2.0, 3.0, 0.5])


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("udp://x:1", "expected tcp://HOST:PORT, serial://"),
        ("tcp://nohostport", "expected tcp://HOST:PORT"),
        ("serial:///dev/ttyS9?baud=fast", "baud must be a number"),
        ("serial:///dev/ttyS9?baud=1234", "baud must be one of"),
    ],
)
def test_bad_sources_are_errors(spec: str, message: str) -> None:
    with pytest.raises(RecordingError, match=message):
        open_source(spec)


def test_unreachable_sources_are_errors(tmp_path: Path) -> None:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]  # bound, not listening: connections are refused
        with pytest.raises(RecordingError, match=rf"tcp://127.0.0.1:{port}: cannot connect"):
            TcpSource("127.0.0.1", port, connect_timeout_s=1.0).connect()
    with pytest.raises(RecordingError, match="cannot open: No such file"):
        SerialSource(str(tmp_path / "ttyNONE")).connect()
