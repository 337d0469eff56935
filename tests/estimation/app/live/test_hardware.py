"""A robot on real hardware behind the agent: the LMS 200 through the real driver on a pty, the
robot base's odometry and goals over TCP (the simulated base), and the base station on the wall
clock over Zenoh on loopback."""

from __future__ import annotations

import math
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from estimation.app.live.agent import RobotAgent, RobotStore
from estimation.app.live.base import BaseState, NetworkFleet
from estimation.app.live.hardware import HardwareRobot, parse_goal
from estimation.app.live.session import open_session
from estimation.app.live.wire import Chunk, WireError, decode_chunk, decode_lms
from estimation.app.mission.fleet import Goal
from estimation.app.resources import resolve_builtin
from estimation.app.rig import driver_from_config, dwell_seconds
from estimation.app.sim.simulate import mission_config
from sensors.geometry import se2
from sensors.lms200.emulator import Lms200Emulator
from sensors.lms200.protocol.stream import StreamParser, Telegram
from sensors.recording.drive import DriveClient, SimulatedBase
from sensors.recording.odometry import TcpSource
from sensors.sim.mission import load_mission
from tests.estimation.app.live.test_agent import FakeSession

MISSION = resolve_builtin("missions", Path("essex_lab"))
SPEC = load_mission(MISSION)
#: A fast mirror, so that a dwell lasts 2.5 s of wall time rather than 31 s.
CONFIG = mission_config(SPEC, {"mirror": {"period_s": 2.0, "gear_ratio": 4.0}}, "test")
START = {"a": np.array([6.0, 4.5, math.radians(90)]), "b": np.array([3.0, 4.5, 0.0])}
HEADER = {"baud_rate": 38400, "simulated": False, "started_unix_s": 1.0}


def _walls(t_s: float, count: int) -> tuple[np.ndarray, np.ndarray]:
    """A sensor in a round room, 4 m away everywhere (no ray casting: the tests time things)."""
    return np.full(count, 4.0), np.zeros(count, dtype=bool)


class Rig:
    """One real robot's hardware: the LMS 200 emulator on a pty and a simulated base."""

    def __init__(self, odometry_start: tuple[float, float, float], **base: Any) -> None:
        self.emulator = Lms200Emulator(_walls, password=CONFIG.serial.password)
        self.port = self.emulator.start()
        self.base = SimulatedBase(
            odometry_start, **{"speed_m_s": 4.0, "turn_rate_rad_s": 8.0, **base}
        )
        self.base.start()

    def robot(self, name: str = "a", **options: Any) -> HardwareRobot:
        return HardwareRobot(
            CONFIG, name, START[name], driver_from_config(CONFIG, self.port),
            TcpSource("127.0.0.1", self.base.odometry_port),
            DriveClient(f"tcp://127.0.0.1:{self.base.drive_port}"), **options,
        )  # fmt: skip

    def close(self) -> None:
        self.base.close()
        self.emulator.close()


@pytest.fixture
def rig() -> Iterator[Rig]:
    r = Rig((10.0, -2.0, 0.5))
    yield r
    r.close()


def telegrams(records: list[tuple[float, bytes]]) -> int:
    parser = StreamParser("from_sensor")
    return sum(
        isinstance(e, Telegram) and e.code == 0xB0 for _, data in records for e in parser.feed(data)
    )


def test_goals_reach_the_base_in_its_odometry_frame(rig: Rig) -> None:
    robot = rig.robot()
    robot.start_sensors()
    try:
        believed = np.array([6.2, 4.4, math.radians(95)])  # where the estimate puts it
        goal = np.array([7.0, 5.0, math.radians(10)])
        reply = robot.apply("move", {"robot": "a", "pose": goal.tolist(), "path": [[6.5, 5.2]],
                                     "believed": believed.tolist()})  # fmt: skip
        anchor = np.array([10.0, -2.0, 0.5])  # the odometry when the mission began
        expected = se2.compose(anchor, se2.between(believed, goal))
        via = se2.compose(anchor, se2.between(believed, np.array([6.5, 5.2, 0.0])))
        assert reply == {"ok": True, "index": 1, "reason": None}
        [(goal_id, sent, waypoints)] = rig.base.goals
        assert goal_id == 1
        assert sent == pytest.approx(tuple(expected), abs=2e-6)
        assert waypoints[0] == pytest.approx(tuple(via[:2]), abs=2e-6)
        # an absolute goal (explicit plan): relative to the declared start pose
        reply = robot.apply("move", {"robot": "a", "pose": [6.0, 5.5, math.radians(90)]})
        assert reply["index"] == 2
        assert rig.base.goals[-1][1] == pytest.approx(
            tuple(se2.compose(anchor, se2.between(START["a"], np.array([6.0, 5.5, math.pi / 2])))),
            abs=2e-6,
        )  # fmt: skip
        # another robot's goal: this one stands still and records
        assert robot.apply("move", {"robot": "b", "pose": [1.0, 1.0, 0.0]})["index"] == 2
        assert len(rig.base.goals) == 2
        assert robot.state()["index"] == 2
        assert robot.state()["goal_id"] == 2
    finally:
        robot.close()


def test_a_dwell_records_sensor_and_odometry_on_the_robot_clock(rig: Rig) -> None:
    robot = rig.robot()
    robot.start_sensors()
    try:
        robot.recorded()  # nothing before the mission's first command
        began = time.monotonic()
        assert robot.apply("dwell", {"fields": {}}) == {"ok": True}
        ended = time.monotonic()
        records, times, poses = robot.recorded()
    finally:
        robot.close()
    assert ended - began == pytest.approx(dwell_seconds(CONFIG), abs=0.5)
    stamps = np.array([t for t, _ in records])
    assert began - 0.1 <= stamps.min()
    assert stamps.max() <= ended + 0.1
    assert telegrams(records) >= 10  # scans decode from the bytes as the driver read them
    assert len(times) >= 10
    assert np.all(np.diff(times) > 0)
    assert poses[-1] == pytest.approx([10.0, -2.0, 0.5])
    assert robot.links()["lms"]["scans"] >= 10


def test_a_failed_goal_counts_a_new_pose_only_when_the_robot_moved() -> None:
    refused = Rig((0.0, 0.0, 0.0), fail=lambda goal_id, pose: "blocked")
    slow = Rig((0.0, 0.0, 0.0), speed_m_s=0.5)
    robots = [refused.robot(), slow.robot(move_timeout_s=1.0)]
    try:
        for robot in robots:
            robot.start_sensors()
        goal = {"robot": "a", "pose": [6.0, 9.0, math.radians(90)], "believed": START["a"].tolist()}
        assert robots[0].apply("move", goal) == {"ok": False, "index": 0, "reason": "blocked"}
        reply = robots[1].apply("move", goal)  # gives up after 1 s, 0.5 m on
        assert not reply["ok"]
        assert reply["index"] == 1
        assert "no answer in 1 s" in reply["reason"]
    finally:
        for robot in robots:
            robot.close()
        refused.close()
        slow.close()


def test_commands_a_real_robot_cannot_take_are_one_line_errors(rig: Rig) -> None:
    robot = rig.robot()
    robot.start_sensors()
    try:
        with pytest.raises(WireError, match="changes step moves a simulated world"):
            robot.apply("change", {"changes": {}})
        with pytest.raises(WireError, match="unknown command 'fly'"):
            robot.apply("fly", {})
        with pytest.raises(WireError, match="finite x, y, yaw"):
            robot.apply("move", {"robot": "a", "pose": [1.0, math.nan, 0.0]})
        with pytest.raises(WireError, match="bad goal"):
            robot.apply("move", {"robot": "a"})
        assert robot.apply("end", {}) == {"ok": True, "files": {}}
        assert rig.base.goals == []
    finally:
        robot.close()


def test_parse_goal_checks_shapes() -> None:
    robot, pose, path, belief = parse_goal({"robot": "a", "pose": [1, 2, 3], "path": [[4, 5]]})
    assert (robot, pose.tolist(), path[0].tolist(), belief) == ("a", [1, 2, 3], [4, 5], None)
    with pytest.raises(WireError, match="finite x, y, yaw"):
        parse_goal({"robot": "a", "pose": [1, 2]})
    with pytest.raises(WireError, match="finite x, y, yaw"):
        parse_goal({"robot": "a", "pose": [1, 2, 3], "believed": [1, 2]})


def test_no_odometry_is_a_one_line_error(rig: Rig) -> None:
    silent = socket.create_server(("127.0.0.1", 0))  # accepts, never sends a line
    robot = HardwareRobot(CONFIG, "a", START["a"], driver_from_config(CONFIG, rig.port),
                          TcpSource("127.0.0.1", silent.getsockname()[1]),
                          DriveClient(f"tcp://127.0.0.1:{rig.base.drive_port}"),
                          odometry_wait_s=0.5)  # fmt: skip
    robot.start_sensors()
    try:
        with pytest.raises(WireError, match=r"robot a: no odometry from tcp://127.0.0.1:\d+ for"):
            robot.apply("dwell", {"fields": {}})
    finally:
        robot.close()
        silent.close()


def test_a_restarted_agent_takes_its_state_back(rig: Rig) -> None:
    robot = rig.robot()
    robot.start_sensors()
    try:
        robot.apply("move", {"robot": "a", "pose": [6.5, 4.5, 0.0],
                             "believed": START["a"].tolist()})  # fmt: skip
        state = robot.state()
    finally:
        robot.close()
    again = rig.robot()
    again.replay([{"state": state}])
    assert again.state() == state
    assert again.index("a") == 1


def test_a_real_robots_store_keeps_what_it_recorded_after_its_last_command(tmp_path: Path) -> None:
    def chunk(seq: int) -> Chunk:
        return Chunk("essex_lab", "r1", "a", "lms", seq, b"", 1.0)

    store = RobotStore(tmp_path / "a", "essex_lab", "r1", "a", HEADER, keep_uncommitted=True)
    for seq in range(3):
        store.put(chunk(seq))
    store.commit({"seq": 0, "next_seq": 2, "state": {}})
    kept = RobotStore(tmp_path / "a", "essex_lab", "r1", "a", HEADER, keep_uncommitted=True)
    assert kept.next_seq == 3  # chunk 2 is the robot's recording: kept
    assert [s for s, _, _ in kept.chunks(0, 9)] == [0, 1, 2]
    simulated = RobotStore(tmp_path / "a", "essex_lab", "r1", "a", HEADER)
    assert simulated.next_seq == 2  # a simulated command cut short is done again
    assert [s for s, _, _ in simulated.chunks(0, 9)] == [0, 1]


def test_the_agent_publishes_time_slices_while_a_command_runs(rig: Rig, tmp_path: Path) -> None:
    session = FakeSession()
    agent = RobotAgent(session, "essex_lab", "a", tmp_path / "a", HEADER, rig.robot,
                       slice_s=0.25)  # fmt: skip
    try:
        reply = agent._command({"run": "r1", "seq": 0, "op": "dwell", "args": {"fields": {}}})
    finally:
        agent.close()
    chunks = [decode_chunk(data) for _, data in session.published]
    lms = [c for c in chunks if c.stream == "lms"]
    assert len(lms) >= 5  # cut every 0.25 s during a 2.5 s dwell, not once at its end
    assert [c.seq for c in chunks] == list(range(len(chunks)))  # slices go on after it
    assert chunks[reply["last_chunk"]].stream == "summary"
    records = [r for c in lms for r in decode_lms(c.payload)]
    assert telegrams(records) >= 10
    assert reply["sweep"]["scans"] >= 10  # the summary saw the slices' telegrams too
    on_disk = sorted((tmp_path / "a" / "chunks").iterdir())
    assert [p.read_bytes() for p in on_disk] == [data for _, data in session.published]


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def test_the_base_runs_real_robots_on_its_wall_clock(tmp_path: Path) -> None:
    """Two real robots over Zenoh: a dwell and a goal; their stamps on the base's clock."""
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    base_session = open_session(listen=[endpoint])
    rigs = {r: Rig((float(k), 0.0, 0.0)) for k, r in enumerate("ab")}
    sessions, agents = [], []
    for r, rig in rigs.items():
        session = open_session(connect=[endpoint])
        sessions.append(session)
        agents.append(RobotAgent(session, "essex_lab", r, tmp_path / r, HEADER,
                                 lambda r=r, rig=rig: rig.robot(r), slice_s=0.5))  # fmt: skip
    threads = []
    for agent in agents:
        import threading

        threads.append(threading.Thread(target=agent.run, daemon=True))
        threads[-1].start()
    state = BaseState(tmp_path / "state", "essex_lab")
    with pytest.raises(WireError, match="changes step moves a simulated world's objects"):
        NetworkFleet(base_session, SPEC, "essex_lab", CONFIG, state, join_timeout_s=20.0)
    spec = SPEC.model_copy(update={"changes": None})
    fleet = NetworkFleet(base_session, spec, "essex_lab", CONFIG, state, join_timeout_s=20.0)
    try:
        assert fleet.wall
        began = fleet.base_now()
        fleet.dwell(phase="start", reference="a", mapper="b", step=-1)
        status = fleet.move(Goal("b", (4.0, 4.5, 0.0), (), (3.0, 4.5, 0.0)))
        ended = fleet.base_now()
        got = fleet.receive()
    finally:
        fleet.close()
        for agent in agents:
            agent.close()
        for session in [*sessions, base_session]:
            session.close()
        for rig in rigs.values():
            rig.close()
    assert status.ok
    assert status.index == 1
    assert rigs["b"].base.goals[0][1] == pytest.approx((2.0, 0.0, 0.0), abs=2e-6)
    dwell, move = (e for e in got.events if e["event"] in ("dwell", "move"))
    assert began - 0.05 <= dwell["t_s"] < dwell["end_s"] <= move["start_s"] < move["t_s"] <= ended
    assert dwell["end_s"] - dwell["t_s"] == pytest.approx(dwell_seconds(CONFIG), abs=0.6)
    for r in "ab":
        stamps = np.array([t for t, _ in got.lms[r]])
        assert telegrams(got.lms[r]) >= 10
        assert began - 0.2 <= stamps.min()  # the base's clock
        assert stamps.max() <= ended + 0.2
        mapping = fleet.clock(r)
        assert mapping.samples_used >= 1
        assert mapping.max_round_trip_s < 0.5
        times, _ = got.odometry[r]
        assert began - 0.2 <= times.min()
        assert times.max() <= ended + 0.2
    # the robot's clock (monotonic) against the base's (unix time since the mission began)
    offset = fleet.clock("a").offset_s
    assert offset == pytest.approx(time.monotonic() - fleet.base_now(), abs=0.05)
    assert fleet.counts.chunks["a"] >= 5


def test_a_mission_of_real_and_simulated_robots_is_refused(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    base_session = open_session(listen=[endpoint])
    sessions = [open_session(connect=[endpoint]) for _ in range(2)]
    rig = Rig((0.0, 0.0, 0.0))
    agents = [
        RobotAgent(sessions[0], "essex_lab", "a", tmp_path / "a", HEADER, rig.robot),
        RobotAgent(
            sessions[1], "essex_lab", "b", tmp_path / "b", {**HEADER, "simulated": True}, rig.robot
        ),
    ]
    try:
        with pytest.raises(WireError, match="robots a are real and the others simulated"):
            NetworkFleet(base_session, SPEC, "essex_lab", CONFIG,
                         BaseState(tmp_path / "state", "essex_lab"), join_timeout_s=20.0)  # fmt: skip
    finally:
        for agent in agents:
            agent.close()
        for session in [*sessions, base_session]:
            session.close()
        rig.close()
