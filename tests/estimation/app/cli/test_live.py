"""The live commands' bad input: one line each, nothing touched that coopmap did not make."""

from __future__ import annotations

import json
from pathlib import Path

from estimation.app.live.base import BaseState
from tests.estimation.app.cli.clirun import assert_one_line_error, run


def test_a_robot_not_in_the_mission_is_refused(tmp_path: Path) -> None:
    assert_one_line_error(*run("robot", "essex_lab", "--name", "z", "--simulate", "--dir",
                               tmp_path / "z"), r"robot 'z' is not in mission essex_lab")  # fmt: skip


def test_a_robot_needs_a_source(tmp_path: Path) -> None:
    assert_one_line_error(*run("robot", "essex_lab", "--name", "a", "--dir", tmp_path / "a"),
                          r"only simulated robots exist so far")  # fmt: skip


def test_bad_endpoints_are_one_line(tmp_path: Path) -> None:
    assert_one_line_error(*run("robot", "essex_lab", "--name", "a", "--simulate", "--connect",
                               "localhost:7447", "--dir", tmp_path / "a"),
                          r"expected PROTOCOL/HOST:PORT")  # fmt: skip
    assert_one_line_error(*run("base", "essex_lab", "--out", tmp_path / "out", "--listen",
                               "tcp/127.0.0.1:99999"), r"expected PROTOCOL/HOST:PORT")  # fmt: skip


def test_the_base_refuses_folders_that_are_not_its_own(tmp_path: Path) -> None:
    user = tmp_path / "notes"
    user.mkdir()
    (user / "todo.txt").write_text("mine")
    assert_one_line_error(*run("base", "essex_lab", "--out", tmp_path / "out", "--state", user),
                          r"not a coopmap base checkpoint")  # fmt: skip
    assert (user / "todo.txt").read_text() == "mine"
    assert_one_line_error(*run("base", "essex_lab", "--out", user),
                          r"notes")  # fmt: skip
    assert (user / "todo.txt").read_text() == "mine"
    other = BaseState(tmp_path / "state", "office_loop")
    assert_one_line_error(*run("base", "essex_lab", "--out", tmp_path / "out", "--state",
                               other.folder), r"checkpoint of mission 'office_loop'")  # fmt: skip


def test_a_checkpoint_cut_short_resumes_from_its_last_whole_line(tmp_path: Path) -> None:
    state = BaseState(tmp_path / "state", "essex_lab")
    state.commit({"seq": 0, "op": "dwell", "args": {}, "replies": {}})
    with open(state.folder / "commands.jsonl", "ab") as f:
        f.write(b'{"seq": 1, "op": "dw')
    again = BaseState(tmp_path / "state", "essex_lab")
    assert again.resumed
    assert again.run == state.run
    assert [e["seq"] for e in again.log] == [0]
    assert json.loads((state.folder / "state.json").read_text())["mission"] == "essex_lab"


def test_a_base_without_robots_gives_up_in_one_line(tmp_path: Path) -> None:
    from estimation.app.live.supervisor import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    assert_one_line_error(*run("base", "essex_lab", "--out", tmp_path / "out", "--listen",
                               endpoint, "--join-timeout", "1"),
                          r"robots a, b did not join mission essex_lab within 1 s")  # fmt: skip
    assert not (tmp_path / "out").exists()
