"""The goal protocol: the agent's client against the simulated base, and what goes wrong."""

from __future__ import annotations

import math
import socket
import threading
import time
from pathlib import Path

import pytest

from sensors.errors import RecordingError
from sensors.recording.drive import DriveClient, SimulatedBase, goal_line, parse_drive_endpoint
from sensors.recording.odometry import OdometryReader, TcpSource


def client(base: SimulatedBase) -> DriveClient:
    drive = DriveClient(f"tcp://127.0.0.1:{base.drive_port}")
    drive.connect()
    return drive


def test_a_goal_is_driven_along_its_waypoints_and_answered() -> None:
    with SimulatedBase((1.0, 2.0, 0.0), speed_m_s=5.0, turn_rate_rad_s=10.0) as base:
        drive = client(base)
        result = drive.go(7, (3.0, 2.0, math.pi / 2), [(2.0, 3.0)], timeout_s=10.0)
        drive.close()
    assert result.ok
    assert result.reason is None
    assert base.pose == pytest.approx((3.0, 2.0, math.pi / 2), abs=1e-6)
    [(goal_id, pose, waypoints)] = base.goals
    assert goal_id == 7
    assert waypoints == [(2.0, 3.0)]
    assert pose == pytest.approx((3.0, 2.0, math.pi / 2), abs=1e-6)  # sent to the µm, µrad
    assert drive.counts.arrived == 1


def test_a_refused_goal_says_why() -> None:
    with SimulatedBase(fail=lambda goal_id, pose: "path blocked by a door") as base:
        drive = client(base)
        result = drive.go(1, (1.0, 0.0, 0.0), [], timeout_s=5.0)
        drive.close()
    assert not result.ok
    assert result.reason == "path blocked by a door"
    assert base.pose == (0.0, 0.0, 0.0)


def test_a_goal_without_an_answer_times_out_and_stops_the_base() -> None:
    with SimulatedBase(speed_m_s=0.1) as base:
        drive = client(base)
        began = time.monotonic()
        result = drive.go(1, (50.0, 0.0, 0.0), [], timeout_s=0.5)
        time.sleep(0.1)
        drive.close()
        x_after_stop = base.pose[0]
        time.sleep(0.2)
        assert base.pose[0] == x_after_stop  # "stop" halted it
    assert not result.ok
    assert "no answer in 0.5 s" in (result.reason or "")
    assert time.monotonic() - began < 2.0


def test_a_stop_request_ends_the_wait() -> None:
    stop = threading.Event()
    with SimulatedBase(speed_m_s=0.1) as base:
        drive = client(base)
        threading.Timer(0.2, stop.set).start()
        result = drive.go(1, (50.0, 0.0, 0.0), [], timeout_s=30.0, stop=stop)
        drive.close()
    assert not result.ok
    assert "stopped" in (result.reason or "")
    assert result.seconds < 2.0


class _Scripted:
    """A base that answers with the given lines, then closes the link."""

    def __init__(self, lines: list[bytes]) -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.lines = lines
        self.received = b""
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        conn, _ = self.server.accept()
        self.received = conn.recv(4096)
        for line in self.lines:
            conn.sendall(line)
        time.sleep(0.3)
        conn.close()
        self.server.close()


def test_foreign_and_late_lines_are_counted_and_ignored() -> None:
    base = _Scripted([b"hello\n", b"arrived 6\n", b"x" * 300 + b"\n", b"arrived 7\n"])
    drive = DriveClient(f"tcp://127.0.0.1:{base.port}")
    drive.connect()
    result = drive.go(7, (0.0, 0.0, 0.0), [], timeout_s=5.0)
    drive.close()
    assert result.ok
    assert drive.counts.ignored_lines == 3
    assert base.received == b"goal 7 0.000000 0.000000 0.000000\n"


def test_a_link_that_drops_is_reconnected_and_the_goal_sent_again() -> None:
    with SimulatedBase(speed_m_s=5.0) as base:
        drive = client(base)
        assert drive._sock is not None
        drive._sock.close()  # the link breaks before the goal goes out
        result = drive.go(3, (1.0, 0.0, 0.0), [], timeout_s=10.0)
        drive.close()
    assert result.ok
    assert drive.counts.reconnects >= 1
    assert [g[0] for g in base.goals] == [3]


def test_the_base_streams_odometry_in_the_line_format(tmp_path: Path) -> None:
    poses: list[tuple[float, float, float, float]] = []
    with SimulatedBase((1.0, -1.0, 0.25), period_s=0.02) as base:
        reader = OdometryReader(TcpSource("127.0.0.1", base.odometry_port), None, None,
                                clock="arrival", on_pose=lambda *p: poses.append(p))  # fmt: skip
        reader.start()
        time.sleep(0.3)
        counts = reader.close()
    assert counts.poses >= 5
    assert counts.malformed == 0
    assert poses[-1][1:] == pytest.approx((1.0, -1.0, 0.25))
    assert not list(tmp_path.iterdir())  # no files without paths


def test_malformed_goal_lines_are_counted_by_the_base() -> None:
    with SimulatedBase() as base:
        with socket.create_connection(("127.0.0.1", base.drive_port)) as conn:
            conn.sendall(b"goal x 1 2 3\ngoal 1 1 2\nnonsense\ngoal 2 nan 0 0\ngoal 4 1 0 0\n")
            time.sleep(0.3)
        assert base.malformed == 4
        assert [g[0] for g in base.goals] == [4]


@pytest.mark.parametrize(
    "spec", ["udp://h:1", "tcp://:5", "tcp://host", "tcp://host:99999", "/dev/ttyUSB0"]
)
def test_bad_endpoints_are_one_line_errors(spec: str) -> None:
    with pytest.raises(RecordingError, match=r"expected tcp://HOST:PORT"):
        parse_drive_endpoint(spec)


def test_an_unreachable_base_is_a_one_line_error() -> None:
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]
    with pytest.raises(RecordingError, match=r"drive tcp://127.0.0.1:\d+: cannot connect"):
        DriveClient(f"tcp://127.0.0.1:{port}").connect()


def test_a_goal_with_a_non_finite_coordinate_is_refused() -> None:
    with pytest.raises(RecordingError, match="non-finite"):
        goal_line(1, (0.0, math.nan, 0.0), [])
    with pytest.raises(RecordingError, match="not connected"):
        DriveClient("tcp://127.0.0.1:1")._send(b"x")
