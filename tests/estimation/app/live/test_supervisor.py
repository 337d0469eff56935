"""``coopmap live`` with real processes on loopback, and the faults it must survive.

One uninterrupted run of essex_lab is the reference. The faulty runs must end with the same
estimate within 1 mm: a robot agent killed with SIGKILL and restarted while another robot
drops, duplicates and reorders its chunks and foreign messages arrive; then the base killed and
restarted while a robot is frozen past the liveliness lease. Each run is bounded in time and
every process it started is gone afterwards.
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from estimation.app.live.session import open_session
from estimation.app.live.supervisor import (
    CLOCK_DRIFTS_PPM,
    LiveOptions,
    Supervisor,
    free_port,
    robot_dirs,
)
from estimation.app.live.wire import decode_json
from estimation.app.resources import resolve_builtin
from sensors.trajio import read_tum
from tests.estimation.app.ros.test_live_view import typestore

pytestmark = pytest.mark.slow

MISSION = resolve_builtin("missions", Path("essex_lab"))
RUN_TIMEOUT_S = 150.0


def _poses(result: Path) -> dict[str, np.ndarray]:
    out = {}
    for path in sorted((result / "poses").glob("*.tum")):
        out[path.stem] = read_tum(path)[1]
    return out


def _commands_logged(out: Path) -> int:
    path = out.with_name(f".{out.name}.base") / "commands.jsonl"
    return path.read_bytes().count(b"\n") if path.exists() else 0


def _sigint_default() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _wait(predicate: Any, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out waiting"
        time.sleep(0.05)


class Live:
    """A supervised live mission in a thread; the test injects faults meanwhile."""

    def __init__(self, out: Path, mission: Path = MISSION, robots: tuple[str, ...] = ("a", "b"),
                 **options: Any) -> None:  # fmt: skip
        self.supervisor = Supervisor(LiveOptions(mission, out, list(robots), free_port(),
                                                 **options))  # fmt: skip
        self.code: int | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        self.code = self.supervisor.run(timeout_s=RUN_TIMEOUT_S)

    def __enter__(self) -> Live:
        self.thread.start()
        return self

    def to_the_end(self) -> Live:
        """The whole mission with no fault injected (the same checks on the way out)."""
        with self:
            self.thread.join(RUN_TIMEOUT_S + 30)
        return self

    def __exit__(self, *exc: object) -> None:
        self.thread.join(RUN_TIMEOUT_S + 30)
        assert not self.thread.is_alive()
        for pid in self.supervisor.pids().values():
            with pytest.raises(ProcessLookupError):
                os.kill(pid, 0)  # every process it started is gone
        # ... and theirs (a killed base's localization worker): none writes to the logs
        _wait(lambda: not _writers(self.supervisor.logs), timeout_s=10.0)


def _writers(folder: Path) -> list[int]:
    """The processes holding a file in ``folder`` open."""
    pids = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            links = [os.readlink(fd) for fd in (proc / "fd").iterdir()]
        except OSError:
            continue
        if any(link.startswith(str(folder)) for link in links):
            pids.append(int(proc.name))
    return pids


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("live") / "clean"
    live = Live(out).to_the_end()
    assert live.code == 0, live.supervisor.base_log()[-2000:]
    return out


def test_a_live_mission_completes_and_batch_reproduces_it(reference: Path, tmp_path: Path) -> None:
    from estimation.app.pipeline import run_batch

    report = json.loads((reference / "result" / "report.json").read_text())
    loop = report["mission_loop"]
    assert loop["stop_reason"] == "station budget (4) spent"
    assert loop["dwells"] >= 8
    for robot in ("a", "b"):  # every dwell's sweep assembled on board, a beacon seen in each
        on_board = loop["on_board"][robot]
        assert on_board["sweeps"] == on_board["dwells"] == loop["dwells"]
        assert on_board["beacons"] >= loop["dwells"] - 2
    for k, robot in enumerate(("a", "b")):
        disk = robot_dirs(reference) / robot / "lms.cap"
        assert (reference / "live" / robot / "lms.cap").read_bytes() == disk.read_bytes()
        # the robot's clock, off by 1000 s and drifting, was found from the exchanges
        clock = loop["clocks"][robot]
        assert clock["offset_s"] == pytest.approx(1000.0 * (k + 1) + 0.25, abs=1e-6)
        assert clock["drift_ppm"] == pytest.approx(CLOCK_DRIFTS_PPM[k], abs=1e-6)
        network = loop["network"]["robots"][robot]
        assert network["chunks"] > 0
        assert network["bytes"] > 100_000
    batch = run_batch(reference, tmp_path / "batch", figures=False)
    live = _poses(reference / "result")
    for robot, poses in _poses(tmp_path / "batch").items():
        assert np.abs(poses[:, :2] - live[robot][:, :2]).max() < 1e-3
    assert batch.report["robots"]["a"]["poses"] == len(live["a"])
    # the truth travelled too: evaluate finds every file it needs
    assert (reference / "ground_truth" / "a.tum").exists()
    assert (reference / "world.yaml").exists()


def test_a_killed_robot_and_a_lossy_link_change_nothing(reference: Path, tmp_path: Path) -> None:
    out = tmp_path / "faulty"
    with Live(out, faults={"b": "drop=0.3,duplicate=0.3,reorder=0.3,seed=4"}) as live:
        session = open_session(connect=[live.supervisor.endpoint])
        try:
            _wait(lambda: _commands_logged(out) >= 5)
            # foreign and malformed messages on the mission's keys; a robot not in the mission
            session.put("coopmap/essex_lab/robot/a/lms/999", b"not a chunk")
            session.put("coopmap/essex_lab/robot/a/odom/notanumber", b"x")
            session.put("coopmap/essex_lab/robot/q/lms/0", b"x")
            token = session.liveliness().declare_token("coopmap/essex_lab/alive/z")
            os.kill(live.supervisor.pids()["robot-a"], signal.SIGKILL)
            _wait(lambda: live.supervisor.restarted["a"] == 1)
            # a viewer that joins late gets the current estimate and map at once
            _wait(lambda: _commands_logged(out) >= 12)
            got = {str(r.ok.key_expr).rsplit("/", 1)[-1]: r.ok.payload.to_bytes()
                   for r in session.get("coopmap/essex_lab/base/**", timeout=5.0) if r.ok}  # fmt: skip
            token.undeclare()
        finally:
            session.close()
    assert live.code == 0, live.supervisor.base_log()[-2000:]
    assert {"estimate", "map", "state"} <= set(got)
    estimate = decode_json(got["estimate"], "estimate")
    assert set(estimate["poses"]) == {"a", "b"}
    report = json.loads((out / "result" / "report.json").read_text())
    network = report["mission_loop"]["network"]
    assert network["malformed_dropped"] >= 2  # not chunks, whoever's key they came on
    assert network["foreign_dropped"] >= 1  # not a chunk key
    assert network["refused_robots"] == ["z"]
    assert network["robots"]["b"]["queried_from_disk"] > 0
    assert network["robots"]["b"]["duplicates_dropped"] > 0
    for robot in ("a", "b"):
        disk = robot_dirs(out) / robot / "lms.cap"
        assert (out / "live" / robot / "lms.cap").read_bytes() == disk.read_bytes()
    clean, faulty = _poses(reference / "result"), _poses(out / "result")
    for robot in ("a", "b"):
        assert faulty[robot].shape == clean[robot].shape
        assert np.abs(faulty[robot][:, :2] - clean[robot][:, :2]).max() < 1e-3
    clean_events = (reference / "events.jsonl").read_text()
    assert (out / "events.jsonl").read_text() == clean_events


def test_a_killed_base_resumes_and_a_frozen_robot_returns(reference: Path, tmp_path: Path) -> None:
    """With ``--emulate`` robots: every telegram goes through the LMS 200 emulator on a pty and
    the real driver (power-on, baud switch, configuration, continuous output)."""
    from sensors.lms200.capture import CaptureReader

    out = tmp_path / "restarted"
    with Live(out, emulate=True) as live:
        _wait(lambda: _commands_logged(out) >= 4)
        robot_b = live.supervisor.pids()["robot-b"]
        os.kill(robot_b, signal.SIGSTOP)  # past the lease: the base sees it go offline
        time.sleep(4.0)
        os.kill(robot_b, signal.SIGCONT)
        _wait(lambda: _commands_logged(out) >= 9)
        os.kill(live.supervisor.pids()["base"], signal.SIGKILL)
        _wait(lambda: live.supervisor.base_restarts == 1)
    assert live.code == 0, live.supervisor.base_log()[-2000:]
    log = live.supervisor.base_log()
    assert "robot b offline" in log
    assert "resuming run" in log
    report = json.loads((out / "result" / "report.json").read_text())
    assert report["mission_loop"]["resumed_commands"] >= 9
    clean, resumed = _poses(reference / "result"), _poses(out / "result")
    for robot in ("a", "b"):
        assert np.abs(resumed[robot][:, :2] - clean[robot][:, :2]).max() < 1e-3
    assert not out.with_name(f".{out.name}.base").exists()  # the checkpoint's work is done
    for robot in ("a", "b"):
        emulated = CaptureReader(out / "live" / robot / "lms.cap")
        direct = CaptureReader(reference / "live" / robot / "lms.cap")
        assert emulated.header["emulated"] is True
        chunks = list(emulated.chunks())
        assert b"".join(c for _, c in chunks) == b"".join(c for _, c in direct.chunks())
        assert len(chunks) > len(list(direct.chunks()))  # cut into reads as the line gave them


def test_a_three_robot_mission_in_a_generated_building(tmp_path: Path) -> None:
    import yaml

    from estimation.app.config import Config
    from estimation.app.evaluation.missions import furnish_params, generated_mission
    from estimation.app.pipeline import run_batch
    from sensors.sim.generate import write_generated_world

    # Building 1: every robot's observations pass the gates there (in building 2 none of the
    # first station's did, and the third robot was never tied to the others).
    write_generated_world(tmp_path / "building.yaml", 1, 3, furnish_params(Config()))
    mission = generated_mission(tmp_path / "building.yaml", 1, 3, stations=3)
    (tmp_path / "three.yaml").write_text(yaml.safe_dump(mission, sort_keys=False))
    out = tmp_path / "live"
    live = Live(out, tmp_path / "three.yaml", ("a", "b", "c")).to_the_end()
    assert live.code == 0, live.supervisor.base_log()[-2000:]
    report = json.loads((out / "result" / "report.json").read_text())
    assert report["mission_loop"]["stop_reason"] == "station budget (3) spent"
    assert set(report["mission_loop"]["clocks"]) == {"a", "b", "c"}
    run_batch(out, tmp_path / "batch", figures=False)
    live_poses, batch_poses = _poses(out / "result"), _poses(tmp_path / "batch")
    assert set(batch_poses) == {"a", "b", "c"}
    for robot, poses in batch_poses.items():
        assert np.abs(poses[:, :2] - live_poses[robot][:, :2]).max() < 1e-3


def test_ctrl_c_keeps_the_data_and_the_same_command_resumes(
    reference: Path, tmp_path: Path
) -> None:
    import subprocess
    import sys

    out = tmp_path / "interrupted"
    command = [sys.executable, "-m", "estimation.app.cli.main", "live", "essex_lab", "--out",
               str(out), "--port", str(free_port())]  # fmt: skip
    # Ctrl-C at a terminal: SIGINT at its default even when the suite runs in the background
    first = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             preexec_fn=_sigint_default)  # fmt: skip
    try:
        _wait(lambda: _commands_logged(out) >= 3)
        first.send_signal(signal.SIGINT)
        _, stderr = first.communicate(timeout=60)
    finally:
        _stop(first)
    assert first.returncode == 130
    assert "the same command resumes the mission" in stderr
    assert "Traceback" not in stderr
    assert not out.exists()
    assert _commands_logged(out) >= 3  # the checkpoint stayed
    assert (robot_dirs(out) / "a" / "commands.jsonl").exists()
    # resumed, and watched in Foxglove: the base serves its live view while it flies, and its
    # final state for a few seconds after (the resumed mission may end before the client asks)
    view_port = free_port()
    second = subprocess.Popen([*command, "--view", "--view-port", str(view_port),
                               "--view-seconds", "5"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              preexec_fn=_sigint_default)  # fmt: skip
    try:
        data = _latched_map(view_port)
        stdout, stderr = second.communicate(timeout=RUN_TIMEOUT_S)
    finally:
        _stop(second)
    grid = typestore().deserialize_cdr(data, "nav_msgs/msg/OccupancyGrid")
    assert grid.info.width > 10
    assert second.returncode == 0, stderr[-2000:]
    assert "coopmap base: station budget (4) spent" in stdout
    base_log = (out.with_name(f".{out.name}.logs") / "base.log").read_text()
    assert f"live view: serving the final state at ws://127.0.0.1:{view_port} for 5 s" in base_log
    clean, resumed = _poses(reference / "result"), _poses(out / "result")
    for robot in ("a", "b"):
        assert np.abs(resumed[robot][:, :2] - clean[robot][:, :2]).max() < 1e-3


def _stop(process: Any) -> None:
    """Stop a ``coopmap live`` still running (a failed check): Ctrl-C, so that it stops its
    base and robots too (killed, it would leave them running), and kill it only if it hangs."""
    import subprocess

    if process.poll() is not None:
        return
    process.send_signal(signal.SIGINT)
    try:
        process.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        process.kill()
        process.communicate()


def _latched_map(port: int) -> bytes:
    """The live view's ``/map`` as a client that subscribes to it gets it. A client that
    connects as the view makes its channels may be refused the subscription by the SDK's
    server (it advertised a channel it had not yet recorded for that client); as a Foxglove
    user would, it connects again."""
    from tests.estimation.app.ros.test_live_view import SubscriptionRefusedError

    for attempt in range(3):
        client = _foxglove(port)
        try:
            client.subscribe({"/map"})
            return client.message("/map")[1]
        except SubscriptionRefusedError:
            if attempt == 2:
                raise
        finally:
            client.close()
    raise AssertionError("unreachable")


def _foxglove(port: int) -> Any:
    """A Foxglove WebSocket client of the base's live view, once it listens. The base flies
    its mission meanwhile, two robot processes beside it, so the first map may take a while
    on a loaded machine: the client waits up to a minute for it, not the view tests' 10 s."""
    from tests.estimation.app.ros.test_live_view import FoxgloveClient

    deadline = time.monotonic() + 60.0
    while True:
        try:
            return FoxgloveClient(port, timeout_s=60.0)
        except OSError:
            assert time.monotonic() < deadline, "the live view never listened"
            time.sleep(0.2)


def test_children_stop_on_sigint_even_when_the_supervisor_ignores_it() -> None:
    """Started in the background (nohup, ``&`` in a script) the supervisor ignores SIGINT; the
    base and robots it starts must not inherit that, since it stops them with SIGINT."""
    import subprocess
    import sys

    from estimation.app.live.supervisor import _sigint_stops

    probe = [sys.executable, "-c",
             "import signal; print(signal.getsignal(signal.SIGINT) == signal.SIG_IGN)"]  # fmt: skip
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        inherited = subprocess.run(probe, capture_output=True, text=True, timeout=30).stdout
        restored = subprocess.run(probe, capture_output=True, text=True, timeout=30,
                                  preexec_fn=_sigint_stops).stdout  # fmt: skip
    finally:
        signal.signal(signal.SIGINT, before)
    assert inherited.strip() == "True"
    assert restored.strip() == "False"
