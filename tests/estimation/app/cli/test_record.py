"""Recording a mission: record, clock, replay and dataset merge, across processes.

The proof: a simulated mission replayed as hardware (LMS 200 emulators on ptys, odometry on
loopback TCP, one reference clock, all at 10x real time), recorded by ``coopmap record`` on each
robot and merged, gives ``batch`` the same poses as the simulated dataset itself.
"""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import threading
from pathlib import Path
from typing import IO

import numpy as np
import pytest
from typer.testing import CliRunner

from estimation.app.cli.main import app
from estimation.app.dataset import decode_robot
from estimation.app.pipeline import run_batch
from estimation.app.sim.simulate import run_simulation
from sensors.trajio import read_tum
from tests.estimation.app.missions import ONE_STEP_MISSION

COOPMAP = Path(sys.executable).parent / "coopmap"
SPEED = 5.0  # fast, yet a recorder descheduled for a moment under load loses no telegram
MISSION = ONE_STEP_MISSION


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("rehearsal")
    (root / "small.yaml").write_text(MISSION)
    run_simulation(root / "small.yaml", root / "sim")
    return root / "sim"


def lines_of(stream: IO[str]) -> queue.Queue[str]:
    found: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: [found.put(line) for line in stream], daemon=True).start()
    return found


def stop(process: subprocess.Popen[str]) -> None:
    if process.poll() is None:
        process.terminate()
    try:
        process.wait(timeout=10)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait(timeout=10)


def test_a_replayed_mission_recorded_and_merged_gives_the_simulated_poses(
    simulated: Path, tmp_path: Path
) -> None:
    replay = subprocess.Popen(
        [str(COOPMAP), "replay", str(simulated), "--robot", "a", "--robot", "b",
         "--speed", str(SPEED), "--lead", "40", "--tail", "20"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    recorders: list[subprocess.Popen[str]] = []
    try:
        assert replay.stdout is not None
        printed = lines_of(replay.stdout)
        clock = printed.get(timeout=20).split()
        robots = {}
        for _ in range(2):
            _, name, device, odometry = printed.get(timeout=20).split()
            robots[name] = (device, odometry)
        assert clock[0] == "clock"
        for name, (device, odometry) in robots.items():
            recorders.append(subprocess.Popen(
                [str(COOPMAP), "record", "--robot", name, "--out", str(tmp_path / f"rec_{name}"),
                 "--lms-port", device, "--odometry", odometry, "--odometry-clock", "reference",
                 "--clock-server", clock[1], "--events", str(simulated / "events.jsonl")],
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            ))  # fmt: skip
        for recorder in recorders:
            out, err = recorder.communicate(timeout=60)
            assert recorder.returncode == 0, err
            assert "mission time 74.24 s reached" in out
    finally:
        for process in [*recorders, replay]:
            stop(process)
        for process in [*recorders, replay]:
            for stream in (process.stdout, process.stderr):
                if stream is not None:
                    stream.close()

    merged = tmp_path / "merged"
    result = CliRunner().invoke(
        app, ["dataset", "merge", str(tmp_path / "rec_a"), str(tmp_path / "rec_b"),
              "--mission", str(simulated / "mission.yaml"), "--out", str(merged)],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "robots a, b, 6 events (2 dwells)" in result.output

    # The events are the mission's, in its order; the clocks ran at the replay's speed.
    def events(folder: Path) -> list[dict[str, object]]:
        return [json.loads(line) for line in (folder / "events.jsonl").read_text().splitlines()]

    assert events(merged) == events(simulated)
    clocks = json.loads((merged / "clock.json").read_text())
    for name in "ab":
        assert clocks["robots"][name]["rate"] == pytest.approx(SPEED, rel=1e-4)
        assert clocks["robots"][name]["uncertainty_s"] < 0.005

    # Scan times land on the mission clock within a few milliseconds: every telegram of the
    # simulation is there, its measurement time shifted by the smallest arrival delay.
    for name in "ab":
        original = decode_robot(simulated / "robots" / name / "lms.cap", 1).times_s
        recorded = decode_robot(merged / "robots" / name / "lms.cap", 1).times_s
        first = int(np.searchsorted(recorded, original[0] - 0.01))
        shift = recorded[first : first + len(original)] - original
        assert len(shift) == len(original)
        assert 0.0 <= shift.min() <= shift.max() < 0.005
        assert np.ptp(shift) < 1e-6
        assert recorded[0] < 0.0  # recording began before the mission

    run_batch(simulated, figures=False)
    run_batch(merged, figures=False)
    for name in "ab":
        t_sim, p_sim = read_tum(simulated / "result" / "poses" / f"{name}.tum")
        t_rec, p_rec = read_tum(merged / "result" / "poses" / f"{name}.tum")
        # Both are stamped at an odometry sample 0.5-0.6 s into each standstill: the merged
        # odometry's samples sit on the recorder's clock, within one sample of the simulated.
        assert t_rec == pytest.approx(t_sim, abs=0.1 + 1e-6)
        assert np.abs(p_rec[:, :2] - p_sim[:, :2]).max() < 1e-3
        assert np.abs(p_rec[:, 2] - p_sim[:, 2]).max() < 1e-4
    assert len(read_tum(merged / "result" / "poses" / "b.tum")[0]) == 2


def invoke(*args: str, input: str | None = None) -> tuple[int, str]:
    result = CliRunner().invoke(app, list(args), input=input)
    return result.exit_code, result.output


def test_the_operator_prompt_records_events_and_stops_on_quit(tmp_path: Path) -> None:
    code, output = invoke(
        "record", "--robot", "b", "--out", str(tmp_path / "rec"), "--clock-offset", "0",
        "--robots", "a,b", input="start\ndepart\narrive a\narrive\nquit\n",
    )  # fmt: skip
    assert code == 0, output
    assert "error: robot a has not departed" in output
    assert "(quit): 0 LMS telegrams" in output
    log = [json.loads(line) for line in (tmp_path / "rec" / "events.jsonl").read_text().split()]
    assert [(e["event"], e.get("robot")) for e in log] == [("start", "a"), ("start", "b"),
                                                           ("move", "b")]  # fmt: skip


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--clock-server", "127.0.0.1:9", "--clock-offset", "0"], "give --clock-server"),
        (["--clock-offset", "0", "--robot", "ab"], "one lowercase letter"),
        (["--clock-offset", "0", "--odometry", "tcp://127.0.0.1:9"], "tcp://127.0.0.1:9: cannot"),
        (["--clock-server", "127.0.0.1:9"], "clock server 127.0.0.1:9 did not answer"),
        (["--clock-offset", "0", "--lms-port", "/dev/nonexistent"], "cannot open /dev/nonexist"),
        (["--clock-offset", "0", "--events", "missing.jsonl"], "missing.jsonl: no such file"),
    ],
)
def test_record_errors_are_one_line(tmp_path: Path, args: list[str], message: str) -> None:
    base = ["record", "--robot", "a", "--out", str(tmp_path / "rec")]
    if "--robot" in args:
        base = base[:1] + base[3:]
    code, output = invoke(*base, *args)
    assert code == 2
    assert message in output
    assert output.count("\n") == 1
    assert "Traceback" not in output
    assert not (tmp_path / "rec").exists()


def test_clock_query_of_a_silent_server_is_an_error() -> None:
    code, output = invoke("clock", "query", "127.0.0.1:9", "--count", "2", "--timeout", "0.05")
    assert code == 2
    assert "did not answer" in output


def test_clock_serve_answers_queries() -> None:
    server = subprocess.Popen(
        [str(COOPMAP), "clock", "serve", "--listen", "127.0.0.1:0", "--seconds", "20"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert server.stdout is not None
        endpoint = lines_of(server.stdout).get(timeout=20).strip()
        code, output = invoke("clock", "query", endpoint, "--count", "4")
    finally:
        stop(server)
        for stream in (server.stdout, server.stderr):
            if stream is not None:
                stream.close()
    assert code == 0, output
    offset = float(output.split("offset ")[1].split()[0])
    assert abs(offset) < 0.01  # the same machine's unix time


def test_replay_of_a_missing_robot_is_an_error(simulated: Path) -> None:
    code, output = invoke("replay", str(simulated), "--robot", "z")
    assert code == 2
    assert "robot 'z' has no lms.cap to replay" in output


def test_dataset_merge_errors_are_one_line(tmp_path: Path) -> None:
    code, output = invoke("dataset", "merge", str(tmp_path / "none"), "--out", str(tmp_path / "o"),
                          "--robot", "a=0,0,0")  # fmt: skip
    assert code == 2
    assert output.strip() == f"coopmap: error: {tmp_path / 'none'}: no such recording folder"
    code, output = invoke("dataset", "merge", str(tmp_path), "--out", str(tmp_path / "o"))
    assert code == 2
    assert "give either --mission FILE or --robot" in output
