"""The robot agent without a network: its store, its commands, and a restart that changes nothing."""

from __future__ import annotations

import json
import math
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from estimation.app.live.agent import AgentFaults, RobotAgent, RobotStore, SimulatedRobot
from estimation.app.live.wire import WireError, decode_chunk
from estimation.app.mission.simulated import simulated_fleet
from estimation.app.resources import resolve_builtin
from estimation.app.sim.simulate import load_simulated
from sensors.errors import OutputError

MISSION = resolve_builtin("missions", Path("essex_lab"))
SPEC, CONFIG, WORLD, SPACE, SEED = load_simulated(MISSION, None, None)
HEADER = {"baud_rate": 38400, "simulated": True, "started_unix_s": 1.0}
COMMANDS = [
    ("dwell", {"fields": {"phase": "start", "reference": "a", "mapper": "b", "step": -1}}),
    ("move", {"robot": "b", "pose": [3.0, 5.0, math.radians(200)], "path": [], "believed": None}),
    ("dwell", {"fields": {"phase": "mapping", "reference": "a", "mapper": "b", "step": 0}}),
    ("move", {"robot": "a", "pose": [2.0, 3.5, math.radians(60)], "path": [], "believed": None}),
    ("dwell", {"fields": {"phase": "station", "reference": "a", "mapper": "b", "step": 1}}),
]


class FakeSession:
    """What the agent calls on a Zenoh session, recorded."""

    def __init__(self) -> None:
        self.published: list[tuple[str, bytes]] = []
        self.declared = 0
        self.undeclared = 0

    def put(self, key: str, data: bytes) -> None:
        self.published.append((key, data))

    def declare_queryable(self, key: str, handler: Any) -> Any:
        self.declared += 1
        return self

    def liveliness(self) -> Any:
        return self

    def declare_token(self, key: str) -> Any:
        self.declared += 1
        return self

    def undeclare(self) -> None:
        self.undeclared += 1


def simulate() -> SimulatedRobot:
    return SimulatedRobot(simulated_fleet(SPEC, CONFIG, WORLD, SEED, SPACE), "b")


def agent(folder: Path, faults: AgentFaults | None = None) -> tuple[RobotAgent, FakeSession]:
    session = FakeSession()
    return RobotAgent(session, "essex_lab", "b", folder, HEADER, simulate, faults), session


def command(seq: int, run: str = "run1") -> dict[str, Any]:
    op, args = COMMANDS[seq]
    return {"run": run, "seq": seq, "op": op, "args": args}


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[dict[str, Any]]]:
    folder = tmp_path_factory.mktemp("robot") / "b"
    robot, _ = agent(folder)
    replies = [robot._command(command(k)) for k in range(len(COMMANDS))]
    return folder, replies


def test_commands_record_chunks_and_replies(uninterrupted: tuple[Path, list[Any]]) -> None:
    folder, replies = uninterrupted
    assert [r["seq"] for r in replies] == list(range(len(COMMANDS)))
    assert replies[1]["ok"]
    assert replies[1]["index"] == 1  # b moved
    assert replies[3]["index"] == 1  # a moved; b, still at its pose 1, recorded it
    assert replies[2]["t_s"] > replies[1]["t_s"] > replies[0]["t_s"] > 0
    chunks = sorted((folder / "chunks").iterdir())
    assert len(chunks) == replies[-1]["last_chunk"] + 1
    streams = {decode_chunk(p.read_bytes()).stream for p in chunks}
    assert streams == {"lms", "odom", "event", "summary"}
    # on board: each dwell's sweep assembled and the other robot's beacon found in it
    for dwell in (replies[0], replies[2], replies[4]):
        assert dwell["sweep"]["sweep_scans"] > 100
        assert dwell["sweep"]["points"] > 10_000
    assert replies[0]["beacons"] == 1  # b sees a at the start


def test_a_command_sent_again_gets_the_same_reply(tmp_path: Path) -> None:
    robot, session = agent(tmp_path / "b")
    first = robot._command(command(0))
    published = len(session.published)
    assert robot._command(command(0)) == first
    assert len(session.published) == published  # nothing recorded twice
    assert robot._command(command(3)) == {"seq": 3, "need": 1}  # the base sends 1 and 2 first


def test_a_restarted_agent_records_what_it_would_have(
    uninterrupted: tuple[Path, list[Any]], tmp_path: Path
) -> None:
    folder, replies = uninterrupted
    first, _ = agent(tmp_path / "b")
    for k in range(3):
        first._command(command(k))
    # killed mid-command: a chunk written, its command line not
    stale = first.store.chunk_path(first.store.next_seq, "lms")  # type: ignore[union-attr]
    stale.write_bytes(b"half")
    with open(tmp_path / "b" / "commands.jsonl", "ab") as f:
        f.write(b'{"seq": 3, "op": "mo')
    second, _ = agent(tmp_path / "b")
    assert not stale.exists()
    again = [second._command(command(k)) for k in range(len(COMMANDS))]
    assert again == replies
    for path in sorted((folder / "chunks").iterdir()):
        redone = decode_chunk((tmp_path / "b" / "chunks" / path.name).read_bytes())
        original = decode_chunk(path.read_bytes())
        # the same recording; only when the robot wrote it differs
        assert redone.payload == original.payload
        assert (redone.stream, redone.seq) == (original.stream, original.seq)


def test_a_new_run_replaces_the_store(tmp_path: Path) -> None:
    robot, _ = agent(tmp_path / "b")
    robot._command(command(0))
    robot._command(command(0, run="run2"))
    meta = json.loads((tmp_path / "b" / "store.json").read_text())
    assert meta["run"] == "run2"
    assert len(robot.store.log) == 1  # type: ignore[union-attr]


def test_bad_commands_are_refused(tmp_path: Path) -> None:
    robot, _ = agent(tmp_path / "b")
    for bad in [{"seq": 0, "op": "dwell", "args": {}}, {"run": "r", "seq": "0", "op": "x",
                "args": {}}, {"run": "r/../x", "seq": 0, "op": "dwell", "args": {}}]:  # fmt: skip
        with pytest.raises(WireError, match="needs run"):
            robot._command(bad)
    with pytest.raises(WireError, match="unknown command 'fly'"):
        robot._command({"run": "r", "seq": 0, "op": "fly", "args": {}})
    with pytest.raises(WireError, match="bad goal"):
        robot._command({"run": "r", "seq": 0, "op": "move", "args": {"robot": "b"}})


def test_the_store_refuses_what_is_not_its_own(tmp_path: Path) -> None:
    user = tmp_path / "user"
    user.mkdir()
    (user / "thesis.tex").write_text("mine")
    with pytest.raises(OutputError, match="not a coopmap robot store"):
        agent(user)
    assert (user / "thesis.tex").read_text() == "mine"
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "store.json").write_text("{")
    with pytest.raises(OutputError, match="unreadable"):
        agent(tmp_path / "bad")
    other = RobotStore(tmp_path / "other", "essex_lab", "r1", "a", HEADER)
    with pytest.raises(OutputError, match="the store of robot 'a'"):
        agent(other.folder)


def test_faults_parse_and_fail_in_one_line() -> None:
    assert AgentFaults.parse("drop=0.2,duplicate=0.1,seed=3") == AgentFaults(0.2, 0.1, 0.0, 3)
    for bad, message in [("lose=0.1", "unknown fault"), ("drop=x", "not a number"),
                         ("drop=1.5", r"in \[0, 1\)")]:  # fmt: skip
        with pytest.raises(WireError, match=message):
            AgentFaults.parse(bad)


def test_injected_faults_drop_duplicate_and_reorder(tmp_path: Path) -> None:
    robot, session = agent(tmp_path / "b", AgentFaults(0.3, 0.3, 0.3, seed=1))
    for k in range(len(COMMANDS)):
        robot._command(command(k))
    keys = [key for key, _ in session.published]
    stored = len(list((tmp_path / "b" / "chunks").iterdir()))
    assert len(set(keys)) < stored  # some dropped: the base queries them
    assert len(keys) > len(set(keys))  # some twice
    seqs = [int(k.rsplit("/", 1)[1]) for k in keys]
    assert seqs != sorted(seqs)  # some out of order


class FakeQuery:
    """A query as the agent's queryables receive it."""

    def __init__(self, parameters: dict[str, str] | None = None) -> None:
        self.parameters = parameters or {}
        self.key_expr = "coopmap/essex_lab/robot/b/store"
        self.replies: list[bytes] = []
        self.errors: list[bytes] = []
        self.finalized = False

    def __enter__(self) -> FakeQuery:
        return self

    def __exit__(self, *exc: object) -> None:
        self.finalized = True  # the querier's get returns now

    def reply(self, key: str, data: bytes) -> None:
        self.replies.append(data)

    def reply_err(self, data: bytes) -> None:
        self.errors.append(data)


def test_the_store_info_and_clock_queries(tmp_path: Path) -> None:
    robot, _ = agent(tmp_path / "b")
    before = FakeQuery()
    robot._serve_store(before)
    assert before.errors == [b"store: nothing recorded yet"]
    clock = FakeQuery()
    robot._serve_clock(clock)
    assert clock.errors == [b"clock: no mission run yet"]
    robot._command(command(0))
    served = FakeQuery({"from": "1", "to": "2"})
    robot._serve_store(served)
    assert [decode_chunk(d).seq for d in served.replies] == [1, 2]
    bad = FakeQuery({"from": "one"})
    robot._serve_store(bad)
    assert bad.errors == [b"store: ?from=A;to=B with integers"]
    info = FakeQuery()
    robot._serve_info(info)
    assert json.loads(info.replies[0]) == {
        "robot": "b", "header": {**HEADER, "robot": "b"}, "run": "run1", "done": 0,
        "next_seq": robot.store.next_seq,  # type: ignore[union-attr]
    }  # fmt: skip
    robot._serve_clock(clock)
    assert json.loads(clock.replies[0])["t_s"] == pytest.approx(31.3, abs=0.1)
    assert all(q.finalized for q in (before, clock, served, bad, info))


def test_closing_the_agent_undeclares_what_it_declared(tmp_path: Path) -> None:
    robot, session = agent(tmp_path / "b")
    assert session.declared == 5  # cmd, store, info, clock queryables and the liveliness token
    robot.close()
    assert session.undeclared == session.declared
    assert robot.stop.is_set()


def test_malformed_command_payloads_are_answered_with_an_error(tmp_path: Path) -> None:
    robot, _ = agent(tmp_path / "b")

    class Payload:
        def __init__(self, data: bytes) -> None:
            self.data = data

        def to_bytes(self) -> bytes:
            return self.data

    queries = []
    for data in [b"not json", b"[1]", b'{"run": "r", "seq": 0}']:
        query = FakeQuery()
        query.payload = Payload(data)  # type: ignore[attr-defined]
        queries.append(query)
        robot.commands.put(query)
    worker = threading.Thread(target=robot.run)
    worker.start()
    _wait_until(lambda: all(q.errors for q in queries))
    robot.stop.set()
    worker.join(5)
    assert robot.rejected == 3
    assert [q.errors[0].split(b":")[0] for q in queries] == [b"command"] * 3
    assert all(not q.replies for q in queries)
    assert all(q.finalized for q in queries)


def _wait_until(predicate: Any, timeout_s: float = 10.0) -> None:
    import time

    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline
        time.sleep(0.01)


def test_a_simulated_robot_refuses_a_goal_it_cannot_drive_to(tmp_path: Path) -> None:
    robot, _ = agent(tmp_path / "b")
    robot._command(command(0))
    bad = {"run": "run1", "seq": 1, "op": "move",
           "args": {"robot": "b", "pose": [3.0, math.nan, 0.0], "path": []}}  # fmt: skip
    with pytest.raises(WireError, match="finite x, y, yaw"):
        robot._command(bad)
    assert len(robot.store.log) == 1  # type: ignore[union-attr]  # nothing executed


def test_a_refused_move_replies_where_the_way_was_blocked() -> None:
    robot = simulate()
    robot.apply(
        "dwell", {"fields": {"phase": "start", "reference": "a", "mapper": "b", "step": -1}}
    )
    # From b's start (3.5, 5.75) straight through pillar_1 (4.0, 4.5).
    reply = robot.apply("move", {"robot": "b", "pose": [4.5, 3.25, 0.0],
                                 "path": [[3.5, 5.75], [4.5, 3.25]], "believed": None})  # fmt: skip
    assert not reply["ok"]
    assert "would collide" in reply["reason"]
    assert len(reply["blocked"]) == 2
    assert not robot.fleet.builder.space.is_free(np.array(reply["blocked"]))
    assert 0.35 < math.dist(reply["blocked"], (4.0, 4.5)) < 0.6
    reply = robot.apply("move", {"robot": "b", "pose": [3.0, 5.0, 0.0], "path": [],
                                 "believed": None})  # fmt: skip
    assert reply["ok"]
    assert reply["blocked"] is None
