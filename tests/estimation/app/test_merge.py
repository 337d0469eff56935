"""Merging robots' recordings: clocks, events from several robots, and every inconsistency."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from estimation.app.config import ConfigError
from estimation.app.merge import merge_events, merge_recordings
from sensors.errors import OutputError, RecordingError
from sensors.lms200.capture import CaptureReader, CaptureWriter
from sensors.recording.recorder import Recorder
from sensors.trajio import read_tum, write_tum

T0 = 5000.0  # local monotonic time of the mission start on every test robot


def make_recording(
    root: Path, robot: str, events: list[dict[str, Any]], span: tuple[float, float] = (-5, 60)
) -> Path:
    """A recording with a given clock offset; ``events`` and stamps relative to T0 (local)."""
    folder = root / f"rec_{robot}"
    recorder = Recorder(folder, robot, clock_offset_s=0.0)
    recorder.start()
    assert recorder.events is not None
    for event in events:
        recorder.events.write({k: (v + T0 if k in ("t_s", "start_s", "end_s") else v)
                               for k, v in event.items()})  # fmt: skip
    recorder.stop("done")
    writer = CaptureWriter(folder / "lms.cap", {"baud_rate": 38400})
    for stamp in np.linspace(T0 + span[0], T0 + span[1], 5):
        writer.write(float(stamp), b"\x02\x80")
    writer.close()
    stamps = np.arange(T0 + span[0], T0 + span[1], 0.5)
    write_tum(folder / "odometry.tum", stamps, np.zeros((len(stamps), 3)))
    return folder


MOVE = {"t_s": 20.0, "event": "move", "robot": "b", "from_index": 0, "to_index": 1, "start_s": 10}


@pytest.fixture
def pair(tmp_path: Path) -> list[Path]:
    a = make_recording(tmp_path, "a", [
        {"t_s": 0.0, "event": "start", "robot": "a", "index": 0},
        {"t_s": 1.0, "event": "dwell", "end_s": 9.0, "poses": {"a": 0}, "reference": "a"},
        {"t_s": 21.0, "event": "dwell", "end_s": 40.0, "poses": {"a": 0}},
    ])  # fmt: skip
    b = make_recording(tmp_path, "b", [
        {"t_s": 0.5, "event": "start", "robot": "b", "index": 0},
        {"t_s": 1.5, "event": "dwell", "end_s": 8.5, "poses": {"b": 0}, "mapper": "b"},
        MOVE,
        {"t_s": 20.5, "event": "dwell", "end_s": 39.0, "poses": {"b": 1}, "reference": "a",
         "mapper": "b", "phase": "mapping"},
    ])  # fmt: skip
    return [a, b]


ROBOTS = ["a=2,3.5,20", "b=3.5,5.75,220"]


def test_operator_logs_of_two_robots_merge_on_the_mission_clock(
    pair: list[Path], tmp_path: Path
) -> None:
    out = tmp_path / "dataset"
    result = merge_recordings(pair, out, robots=ROBOTS)
    assert result.robots == ["a", "b"]
    assert (result.events, result.dwells) == (5, 2)
    events = [json.loads(line) for line in (out / "events.jsonl").read_text().splitlines()]
    assert [e["event"] for e in events] == ["start", "start", "dwell", "move", "dwell"]
    # the first start is mission time 0; overlapping dwells are one, in their intersection
    assert events[1]["t_s"] == pytest.approx(0.5, abs=1e-6)
    assert events[2] == {"t_s": pytest.approx(1.5), "event": "dwell", "end_s": pytest.approx(8.5),
                         "poses": {"a": 0, "b": 0}, "reference": "a", "mapper": "b"}  # fmt: skip
    assert events[3]["start_s"] == pytest.approx(10.0, abs=1e-6)
    assert events[4]["poses"] == {"a": 0, "b": 1}
    assert events[4]["t_s"] == pytest.approx(21.0, abs=1e-6)
    stamps, _ = read_tum(out / "robots" / "b" / "odometry.tum")
    assert stamps[0] == pytest.approx(-5.0, abs=1e-6)
    capture = CaptureReader(out / "robots" / "a" / "lms.cap")
    assert [s for s, _ in capture.chunks()][-1] == pytest.approx(60.0, abs=1e-6)
    assert capture.header is not None
    assert capture.header["clock"] == "mission"
    clocks = json.loads((out / "clock.json").read_text())
    assert clocks["robots"]["a"]["source"] == "given"
    assert (out / ".coopmap").is_file()
    # a second merge replaces the first (a coopmap dataset), never a user's folder
    merge_recordings(pair, out, robots=ROBOTS, mission_start_ref_s=clocks["mission_start_ref_s"])


def test_a_mission_file_gives_robots_and_config(pair: list[Path], tmp_path: Path) -> None:
    mission = tmp_path / "mission.yaml"
    mission.write_text("robots:\n  - {name: a, start: [0, 0, 0]}\n  - {name: b, start: [1, 0, 0]}\n"
                       "config: {robot: {scanner_height_m: 0.5}}\n")  # fmt: skip
    out = tmp_path / "dataset"
    merge_recordings(pair, out, mission=mission, overrides={"beacon": {"offset_m": 0.3}})
    text = (out / "mission.yaml").read_text()
    assert "scanner_height_m: 0.5" in text
    assert "offset_m: 0.3" in text


def test_bad_merges_are_clear_errors(pair: list[Path], tmp_path: Path) -> None:
    out = tmp_path / "dataset"
    with pytest.raises(RecordingError, match="two recordings of robot a"):
        merge_recordings([pair[0], pair[0], pair[1]], out, robots=ROBOTS)
    with pytest.raises(RecordingError, match=r"no recording of robot\(s\) b"):
        merge_recordings(pair[:1], out, robots=ROBOTS)
    with pytest.raises(RecordingError, match="robot b is not in the mission"):
        merge_recordings(pair, out, robots=ROBOTS[:1])
    with pytest.raises(ConfigError, match="give either --mission"):
        merge_recordings(pair, out)
    with pytest.raises(ConfigError, match="expected NAME=X_M,Y_M,YAW_DEG"):
        merge_recordings(pair, out, robots=["a=1,2"])
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "x.txt").write_text("x")
    with pytest.raises(OutputError, match="holds files coopmap did not write"):
        merge_recordings(pair, tmp_path / "mine", robots=ROBOTS)
    assert not out.exists()


def test_recordings_of_different_missions_do_not_overlap(tmp_path: Path) -> None:
    a = make_recording(tmp_path, "a", [{"t_s": 0.0, "event": "start", "robot": "a"}], (0, 10))
    b = make_recording(tmp_path, "b", [], (100, 110))
    with pytest.raises(RecordingError, match="do not overlap in time"):
        merge_recordings([a, b], tmp_path / "out", robots=ROBOTS)


def test_without_a_start_the_mission_clock_needs_its_zero(tmp_path: Path) -> None:
    paths = [make_recording(tmp_path, r, []) for r in "ab"]
    with pytest.raises(RecordingError, match="cannot place mission time 0"):
        merge_recordings(paths, tmp_path / "out", robots=ROBOTS)


def test_a_dwell_without_every_pose_is_an_error(tmp_path: Path) -> None:
    a = make_recording(tmp_path, "a", [{"t_s": 0.0, "event": "start", "robot": "a"},
                                       {"t_s": 1, "event": "dwell", "end_s": 9, "poses": {"a": 0}}])  # fmt: skip
    b = make_recording(tmp_path, "b", [])
    with pytest.raises(RecordingError, match=r"dwell at 1.0 s .* no pose index of robot\(s\) b"):
        merge_recordings([a, b], tmp_path / "out", robots=ROBOTS)


def test_a_move_beyond_the_odometry_is_an_error(tmp_path: Path) -> None:
    late = dict(MOVE, t_s=70.0)
    a = make_recording(tmp_path, "a", [{"t_s": 0.0, "event": "start", "robot": "a"}])
    b = make_recording(tmp_path, "b", [late])
    with pytest.raises(RecordingError, match="lies outside its odometry"):
        merge_recordings([a, b], tmp_path / "out", robots=ROBOTS)
    assert not (tmp_path / "out").exists()


def test_the_same_event_from_two_robots_is_kept_once() -> None:
    seen_by_b = dict(MOVE)
    seen_by_a = dict(MOVE, t_s=20.2)
    merged = merge_events({"a": [seen_by_a], "b": [seen_by_b]}, ["a", "b"])
    assert merged == [seen_by_b]  # the moving robot's own log wins
    roles = {"t_s": 3.0, "event": "roles", "reference": "a", "mapper": "b", "step": 0}
    assert merge_events({"a": [roles], "b": [dict(roles, t_s=3.1)]}, ["a", "b"]) == [roles]


@pytest.mark.parametrize(
    ("first", "second", "message"),
    [
        (MOVE, dict(MOVE, t_s=25.0), "disagree on the move of robot b from pose 0"),
        ({"t_s": 1, "event": "dwell", "end_s": 9, "poses": {"a": 0}},
         {"t_s": 2, "event": "dwell", "end_s": 8, "poses": {"a": 1}}, "robot a at pose 0"),
        ({"t_s": 1, "event": "dwell", "end_s": 9, "poses": {}, "reference": "a"},
         {"t_s": 2, "event": "dwell", "end_s": 8, "poses": {}, "reference": "b"}, "reference 'a'"),
    ],
)  # fmt: skip
def test_recordings_that_disagree_are_errors(
    first: dict[str, Any], second: dict[str, Any], message: str
) -> None:
    with pytest.raises(RecordingError, match=message):
        merge_events({"a": [first], "b": [second]}, ["a", "b"])


def test_events_at_the_same_time_keep_the_dataset_order() -> None:
    dwell = {"t_s": 5.0, "event": "dwell", "end_s": 9.0, "poses": {"a": 0, "b": 1}}
    move = dict(MOVE, t_s=5.0, start_s=1.0)
    start = {"t_s": 0.0, "event": "start", "robot": "a", "index": 0}
    note = {"t_s": 5.0, "event": "note", "text": "x"}
    merged = merge_events({"a": [note, dwell, move, start]}, ["a"])
    assert [e["event"] for e in merged] == ["start", "move", "dwell", "note"]
