"""The live commands' bad input: one line each, nothing touched that coopmap did not make."""

from __future__ import annotations

import json
import socket
from pathlib import Path

import numpy as np

from estimation.app.live.base import BaseState
from sensors.recording.drive import SimulatedBase
from tests.estimation.app.cli.clirun import assert_one_line_error, run


def test_a_robot_not_in_the_mission_is_refused(tmp_path: Path) -> None:
    assert_one_line_error(*run("robot", "essex_lab", "--name", "z", "--simulate", "--dir",
                               tmp_path / "z"), r"robot 'z' is not in mission essex_lab")  # fmt: skip


def test_a_robot_needs_a_source(tmp_path: Path) -> None:
    assert_one_line_error(*run("robot", "essex_lab", "--name", "a", "--dir", tmp_path / "a"),
                          r"a real robot needs --port, --odometry and --drive; a simulated one "
                          r"--simulate or --emulate")  # fmt: skip


def _closed_port() -> int:
    with socket.create_server(("127.0.0.1", 0)) as server:
        return int(server.getsockname()[1])


def test_a_real_robots_options_are_checked_in_one_line(tmp_path: Path) -> None:
    real = ["robot", "essex_lab", "--name", "a", "--dir", tmp_path / "a"]
    assert_one_line_error(*run(*real, "--port", "/dev/ttyUSB0", "--simulate"),
                          r"--port name a real robot; --simulate and --emulate a simulated one")  # fmt: skip
    assert_one_line_error(*run(*real, "--port", "/dev/ttyUSB0"),
                          r"a real robot needs --odometry, --drive too")  # fmt: skip
    links = ["--odometry", "tcp://127.0.0.1:1", "--drive", "tcp://127.0.0.1:1"]
    assert_one_line_error(*run(*real, "--port", "/dev/ttyUSB0", *links, "--seed", "3"),
                          r"--faults, --seed and --clock-\* are for simulated robots")  # fmt: skip
    assert_one_line_error(*run(*real, "--port", tmp_path / "no-such-tty", *links),
                          r"cannot open .*no-such-tty")  # fmt: skip
    assert not (tmp_path / "a").exists()  # nothing written before every link answered


def test_a_real_robots_unreachable_links_are_one_line(tmp_path: Path) -> None:
    from sensors.lms200.emulator import Lms200Emulator

    with Lms200Emulator(lambda t, n: (np.full(n, 4.0), np.zeros(n, dtype=bool))) as emulator:
        port = emulator.device_path
        real = ["robot", "essex_lab", "--name", "a", "--dir", tmp_path / "a", "--port", port]
        closed = f"tcp://127.0.0.1:{_closed_port()}"
        assert_one_line_error(*run(*real, "--odometry", closed, "--drive", closed),
                              r"odometry tcp://127.0.0.1:\d+: cannot connect")  # fmt: skip
        with SimulatedBase() as base:
            odometry = f"tcp://127.0.0.1:{base.odometry_port}"
            assert_one_line_error(*run(*real, "--odometry", odometry, "--drive", closed),
                                  r"drive tcp://127.0.0.1:\d+: cannot connect")  # fmt: skip
            assert_one_line_error(*run(*real, "--odometry", odometry, "--drive", "udp://x:1"),
                                  r"drive 'udp://x:1': expected tcp://HOST:PORT")  # fmt: skip
    assert not (tmp_path / "a").exists()


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
