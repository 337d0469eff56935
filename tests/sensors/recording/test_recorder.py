"""The recorder against the LMS emulator on a pty, a TCP odometry stream and a clock server."""

from __future__ import annotations

import json
import queue
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from sensors.errors import OutputError, RecordingError
from sensors.lms200.driver import Lms200
from sensors.lms200.emulator import Lms200Emulator
from sensors.recording.clock import ClockServer, ClockSync
from sensors.recording.folder import read_recording
from sensors.recording.odometry import TcpSource
from sensors.recording.recorder import Recorder, run_recorder
from sensors.trajio import read_tum


def flat(t_s: float, count: int) -> tuple[np.ndarray, np.ndarray]:
    return np.full(count, 2.0), np.zeros(count, dtype=np.uint8)


def driver(port: str) -> Lms200:
    return Lms200(port, reply_timeout_s=0.5, baud_switch_wait_s=0.02)


@pytest.fixture
def emulator() -> Iterator[Lms200Emulator]:
    with Lms200Emulator(flat, power_on_baud=38400) as emu:
        yield emu


@pytest.fixture
def reference() -> Iterator[ClockServer]:
    with ClockServer(lambda: time.monotonic() + 1000.0) as server:
        yield server


@pytest.fixture
def odometry() -> Iterator[socket.socket]:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen(1)
        sock.settimeout(5)
        yield sock


def test_a_recording_with_the_operator_prompt(
    tmp_path: Path, emulator: Lms200Emulator, reference: ClockServer, odometry: socket.socket
) -> None:
    out = tmp_path / "rec"
    recorder = Recorder(
        out, "a", lms=driver(emulator.device_path),
        odometry=TcpSource("127.0.0.1", odometry.getsockname()[1]), odometry_clock="monotonic",
        clock=ClockSync((reference.host, reference.port)), robots=["a", "b"], sync_interval_s=0.1,
    )  # fmt: skip
    recorder.start()
    client, _ = odometry.accept()
    lines: queue.Queue[str | None] = queue.Queue()
    answers: list[str] = []
    with client:
        for command in ("start", "depart b", "fly"):
            lines.put(command)
        client.sendall(f"{time.monotonic():.6f} 0 0 0\nnot odometry\n".encode())
        time.sleep(0.3)
        for command in ("arrive b", "dwell reference=a mapper=b", "end", "quit"):
            lines.put(command)
        summary = run_recorder(recorder, lines=lines, answer=lambda r: answers.append(r.message))
    assert summary.reason == "quit"
    assert summary.error == ""
    assert summary.lms_telegrams >= 3
    assert (summary.odometry_poses, summary.odometry_malformed) == (1, 1)
    assert summary.events == 4
    assert summary.clock.rate == pytest.approx(1.0, abs=0.01)
    assert any("unknown command 'fly'" in a for a in answers)
    recording = read_recording(out)
    assert recording.warnings == []
    assert recording.meta["state"] == "complete"
    assert recording.events_clock == "local"
    # the reference runs 1000 s ahead of the local monotonic clock
    now = time.monotonic()
    assert float(recording.mapping.to_reference(now)) == pytest.approx(now + 1000.0, abs=0.002)
    events = [json.loads(line) for line in (out / "events.jsonl").read_text().splitlines()]
    assert [e["event"] for e in events] == ["start", "start", "move", "dwell"]
    assert events[3]["poses"] == {"a": 0, "b": 1}
    stamps, _ = read_tum(out / "odometry.tum")
    assert abs(stamps[0] - events[0]["t_s"]) < 2.0
    clock = json.loads((out / "clock.json").read_text())
    assert clock["final"] is True
    assert len(clock["samples"]) == summary.clock_samples >= 9
    assert sorted(p.name for p in out.iterdir()) == [
        ".coopmap", "clock.json", "events.jsonl", "lms.cap", "odometry.lines", "odometry.tum",
        "recording.json",
    ]  # fmt: skip


def test_a_given_offset_and_a_mission_file(tmp_path: Path, emulator: Lms200Emulator) -> None:
    events = [{"t_s": 0.0, "event": "start", "robot": "a", "index": 0},
              {"t_s": 0.0, "event": "dwell", "end_s": 0.2, "poses": {"a": 0}},
              {"t_s": 1e9, "event": "note"}]  # fmt: skip
    unix_now = time.time()
    recorder = Recorder(
        tmp_path / "rec", "a", lms=driver(emulator.device_path), clock_offset_s=5.0,
        mission_events=events, mission_start_ref_s=unix_now + 5.0, until_mission_s=0.5,
    )  # fmt: skip
    recorder.start()
    summary = run_recorder(recorder, poll_s=0.01)
    assert summary.reason == "mission time 0.5 s reached"
    assert summary.events == 2  # the note lies beyond the end
    recording = read_recording(tmp_path / "rec")
    assert recording.mapping.source == "given"
    assert recording.mapping.rate == 1.0
    assert float(recording.mapping.to_reference(time.monotonic())) == pytest.approx(
        time.time() + 5.0, abs=0.01
    )
    assert recording.events_clock == "mission"


def test_a_silent_clock_server_fails_the_start_and_leaves_nothing(
    tmp_path: Path, emulator: Lms200Emulator
) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as silent:
        silent.bind(("127.0.0.1", 0))
        recorder = Recorder(
            tmp_path / "rec", "a", lms=driver(emulator.device_path),
            clock=ClockSync(silent.getsockname(), timeout_s=0.02),
        )  # fmt: skip
        started = time.monotonic()
        with pytest.raises(RecordingError, match="did not answer"):
            recorder.start()
    assert time.monotonic() - started < 3.0
    assert not (tmp_path / "rec").exists()


def test_an_lms_that_disappears_ends_the_recording_and_keeps_the_files(
    tmp_path: Path, emulator: Lms200Emulator
) -> None:
    recorder = Recorder(tmp_path / "rec", "a", lms=driver(emulator.device_path), clock_offset_s=0)
    recorder.start()
    time.sleep(0.3)
    emulator.disconnect()
    summary = run_recorder(recorder, seconds=10)
    assert summary.reason.startswith("LMS failed")
    assert summary.lms_telegrams >= 2
    recording = read_recording(tmp_path / "rec")
    assert recording.meta["state"] == "failed"
    assert recording.capture == tmp_path / "rec" / "lms.cap"


def test_recordings_are_never_replaced(tmp_path: Path) -> None:
    out = tmp_path / "rec"
    Recorder(out, "a", clock_offset_s=0.0).start()  # never stopped: cut short
    with pytest.raises(OutputError, match="recordings are never replaced"):
        Recorder(out, "a", clock_offset_s=0.0).start()
    recording = read_recording(out)
    assert any("did not stop cleanly" in w for w in recording.warnings)
    assert recording.events == out / "events.jsonl.partial"
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("x")
    with pytest.raises(OutputError, match="holds files coopmap did not write"):
        Recorder(tmp_path / "mine", "a", clock_offset_s=0.0).start()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({}, "either a clock server or a clock offset"),
        ({"clock_offset_s": 0.0, "odometry_clock": "gps"}, "odometry clock must be one of"),
    ],
)
def test_bad_recorder_settings(tmp_path: Path, kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(RecordingError, match=message):
        Recorder(tmp_path / "rec", "a", **kwargs)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("recording.json", "{", "recording.json: unreadable"),
        ("recording.json", '{"format": "coopmap recording", "robot": "A"}', "robot must be one"),
        ("clock.json", '{"format": "x"}', "not a coopmap clock file"),
        ("clock.json", '{"format": "coopmap clock", "samples": [[1, 2]]}', "samples must be"),
        (
            "clock.json",
            '{"format": "coopmap clock", "final": true, "mapping": {"offset_s": 0, '
            '"rate": 0}, "unix_pairs": [[1, 2]]}',
            "rate must be > 0",
        ),
        (
            "clock.json",
            '{"format": "coopmap clock", "final": true, "mapping": {"offset_s": 0, "rate": 1}}',
            "unix_pairs must be",
        ),
    ],
)
def test_broken_recordings_are_named_errors(
    tmp_path: Path, name: str, content: str, message: str
) -> None:
    out = tmp_path / "rec"
    recorder = Recorder(out, "a", clock_offset_s=0.0)
    recorder.start()
    recorder.stop("done")
    (out / name).write_text(content)
    with pytest.raises(RecordingError, match=message):
        read_recording(out)


def test_a_folder_that_is_not_a_recording(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="no such recording folder"):
        read_recording(tmp_path / "none")
    with pytest.raises(RecordingError, match="not a coopmap recording"):
        read_recording(tmp_path)
