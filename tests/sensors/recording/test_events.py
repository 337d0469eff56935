"""The operator prompt's commands, mission files and their release on the mission clock."""

from __future__ import annotations

from pathlib import Path

import pytest

from sensors.errors import RecordingError
from sensors.recording.events import EventLog, MissionSchedule, OperatorLog, read_events_file


def test_a_leapfrog_typed_at_the_prompt_becomes_dataset_events() -> None:
    log = OperatorLog("a", ["a", "b"])
    script = [
        (0.0, "start"),
        (0.5, "dwell reference=a mapper=b phase=start step=-1"),
        (31.0, "end"),
        (31.5, "roles a b 0"),
        (32.0, "depart b"),
        (40.0, "arrive b"),
        (40.2, "dwell reference=a mapper=b phase=mapping"),
        (71.0, "end"),
    ]
    events = [e for t, line in script for e in log.command(line, t).events]
    assert [e["event"] for e in events] == ["start", "start", "dwell", "roles", "move", "dwell"]
    assert events[2] == {"t_s": 0.5, "event": "dwell", "end_s": 31.0, "poses": {"a": 0, "b": 0},
                         "reference": "a", "mapper": "b", "phase": "start", "step": -1}  # fmt: skip
    assert events[4] == {"t_s": 40.0, "event": "move", "robot": "b", "from_index": 0,
                         "to_index": 1, "start_s": 32.0}  # fmt: skip
    assert events[5]["poses"] == {"a": 0, "b": 1}


@pytest.mark.parametrize(
    ("lines", "message"),
    [
        (["arrive"], "robot a has not departed"),
        (["depart c"], "robot 'c' is not tracked"),
        (["depart", "depart"], "already driving"),
        (["depart", "dwell"], "still driving: a"),
        (["end"], "no dwell is open"),
        (["dwell", "dwell"], "already open"),
        (["dwell", "depart"], "type 'end' before"),
        (["dwell phase=parked"], "phase must be one of"),
        (["dwell step=two"], "step must be a whole number"),
        (["dwell colour=red"], "expected reference="),
        (["roles a"], "usage: roles"),
        (["fly"], "unknown command 'fly'"),
    ],
)
def test_commands_that_do_not_fit_change_nothing(lines: list[str], message: str) -> None:
    log = OperatorLog("a", ["a"])
    replies = [log.command(line, float(k)) for k, line in enumerate(lines)]
    assert not replies[-1].ok
    assert message in replies[-1].message
    assert replies[-1].events == ()


def test_quit_and_notes() -> None:
    log = OperatorLog("b", [])
    assert log.robots == ["b"]
    assert log.command("quit", 1.0).quit
    assert log.command("note beacon was dirty", 2.0).events[0]["text"] == "beacon was dirty"


def test_mission_events_are_released_in_order_when_done(tmp_path: Path) -> None:
    path = tmp_path / "m.jsonl"
    path.write_text(
        '{"t_s":0,"event":"start","robot":"a","index":0}\n\n'
        '{"t_s":0,"event":"dwell","end_s":31.3,"poses":{"a":0}}\n'
        '{"t_s":31.3,"event":"roles","reference":"a","mapper":"b","step":0}\n'
    )
    schedule = MissionSchedule(read_events_file(path))
    assert schedule.last_s == 31.3
    assert [e["event"] for e in schedule.due(5.0)] == ["start"]
    assert schedule.due(31.0) == []
    assert [e["event"] for e in schedule.due(31.3)] == ["dwell", "roles"]
    assert schedule.done


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("{oops\n", r"m.jsonl:1: not JSON"),
        ('{"event":"start"}\n', r"m.jsonl:1: an event needs"),
        ('{"t_s":"0","event":"start"}\n', r"t_s must be a number"),
        ('{"t_s":1,"event":"dwell","end_s":NaN}\n', r"end_s must be a finite number"),
    ],
)
def test_bad_mission_files_name_the_line(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "m.jsonl"
    path.write_text(text)
    with pytest.raises(RecordingError, match=message):
        read_events_file(path)


def test_a_missing_mission_file_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="no such file"):
        read_events_file(tmp_path / "none.jsonl")


def test_the_event_log_is_published_when_closed(tmp_path: Path) -> None:
    log = EventLog(tmp_path / "events.jsonl")
    log.write({"t_s": 1.0, "event": "note"})
    assert (tmp_path / "events.jsonl.partial").read_text() == '{"t_s":1.0,"event":"note"}\n'
    log.close()
    assert (tmp_path / "events.jsonl").is_file()
    assert not (tmp_path / "events.jsonl.partial").exists()
    with pytest.raises(RecordingError, match="already closed"):
        log.write({"t_s": 2.0, "event": "note"})
