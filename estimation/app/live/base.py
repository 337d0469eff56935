"""``coopmap base``: the base station — the mission loop with the robots on the network.

:class:`NetworkFleet` is the loop's :class:`~estimation.app.mission.fleet.Fleet` over Zenoh. Every
goal, dwell and change is a numbered command sent to every robot agent (each keeps a copy of the
mission's motion; the one addressed moves); a command is repeated until each robot replied,
waiting while a robot is offline (its liveliness token gone). A reply names the robot's last
chunk; the base holds every chunk up to it before it goes on — from the robots' publications,
or queried from their disks when one is missing — so what the loop receives does not depend on
what the network lost, duplicated or reordered. Chunks are kept by (robot, seq): a second copy
is dropped; anything on the mission's keys that does not decode, or comes from a robot or run
that is not the mission's, is counted and dropped.

The checkpoint (``--state``, :class:`BaseState`) is the command log with the replies and every
chunk received. The loop is deterministic in what it receives, so a restarted base resumes by
running the loop again over the checkpoint — each command it decides must be the logged one —
and goes on live where the log ends; robots answer the commands they executed already with the
replies they gave. After every dwell the base publishes the mission state, the estimate and the
ceiling map, and answers queries for them, so a viewer that joins late gets them at once.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from estimation.app.config import Config
from estimation.app.live.agent import capture_bytes
from estimation.app.live.wire import (
    STREAMS,
    WireError,
    append_journal,
    decode_chunk,
    decode_json,
    decode_lms,
    decode_odometry,
    encode_json,
    mission_key,
    parse_chunk_key,
    read_journal,
)
from estimation.app.mission.fleet import Fleet, Goal, Received, Status
from estimation.app.mission.simulated import mission_starts
from sensors.atomic import MARKER, write_bytes_atomic, write_text_atomic
from sensors.errors import OutputError
from sensors.recording.clock import ClockMapping, ClockSample, fit_mapping
from sensors.sim.mission import ChangesSpec, MissionSpec

__all__ = ["BaseState", "NetworkCounts", "NetworkFleet"]

Say = Callable[[str], None]
#: How long one command may take a robot (ray casting a dwell's sweep) before it is sent again.
COMMAND_TIMEOUT_S = 120.0
#: Clock exchanges per command with a real robot (the one with the shortest round trip is kept).
_EXCHANGES = 4


class BaseState:
    """The base's checkpoint folder: ``state.json`` (mission, run), ``commands.jsonl`` (each
    command with every robot's reply, appended once all replied and every chunk they named
    was held) and ``chunks/<r>/<seq>.<stream>``."""

    KIND = "base-state"

    def __init__(self, folder: Path, mission: str) -> None:
        self.folder = Path(folder)
        marker = self.folder / MARKER
        if self.folder.exists() and any(self.folder.iterdir()):
            try:
                kind = json.loads(marker.read_text(encoding="utf-8")).get("kind")
            except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError):
                kind = None
            if kind != self.KIND:
                raise OutputError(f"{self.folder}: exists and is not a coopmap base checkpoint; "
                                  "choose another --state")  # fmt: skip
            meta = json.loads((self.folder / "state.json").read_text(encoding="utf-8"))
            if meta.get("mission") != mission:
                raise OutputError(f"{self.folder}: the checkpoint of mission "
                                  f"{meta.get('mission')!r}, not {mission!r}")  # fmt: skip
            self.run: str = meta["run"]
            self.started_unix_s = float(meta.get("started_unix_s", time.time()))
            self.resumed = True
        else:
            self.folder.mkdir(parents=True, exist_ok=True)
            marker.write_text(json.dumps({"kind": self.KIND, "pid": os.getpid()}) + "\n")
            self.run = secrets.token_hex(4)
            self.started_unix_s = time.time()
            write_text_atomic(self.folder / "state.json", json.dumps({
                "mission": mission, "run": self.run, "started_unix_s": self.started_unix_s,
            }) + "\n")  # fmt: skip
            self.resumed = False
        self.log = read_journal(self.folder / "commands.jsonl")

    def commit(self, entry: dict[str, Any]) -> None:
        append_journal(self.folder / "commands.jsonl", entry)

    def chunk_path(self, robot: str, seq: int, stream: str) -> Path:
        return self.folder / "chunks" / robot / f"{seq:08d}.{stream}"

    def stored_chunks(self) -> list[tuple[str, int, str, bytes]]:
        out = []
        root = self.folder / "chunks"
        if root.is_dir():
            for robot_dir in sorted(root.iterdir()):
                for path in sorted(robot_dir.iterdir()):
                    if path.suffix[1:] in STREAMS and path.stem.isdigit():
                        out.append((robot_dir.name, int(path.stem), path.suffix[1:],
                                    path.read_bytes()))  # fmt: skip
        return out


@dataclass
class NetworkCounts:
    """What crossed the network, per robot: chunks and bytes received, duplicates dropped,
    chunks queried from the robot's disk; and the messages dropped as malformed or foreign."""

    chunks: dict[str, int] = field(default_factory=dict)
    bytes: dict[str, int] = field(default_factory=dict)
    duplicates: dict[str, int] = field(default_factory=dict)
    queried: dict[str, int] = field(default_factory=dict)
    resent: dict[str, int] = field(default_factory=dict)
    latency_s: dict[str, list[float]] = field(default_factory=dict)
    scan_to_map_s: dict[str, list[float]] = field(default_factory=dict)
    malformed: int = 0
    foreign: int = 0
    refused_robots: list[str] = field(default_factory=list)
    offline: list[dict[str, Any]] = field(default_factory=list)

    def as_dict(self, seconds: float) -> dict[str, Any]:
        robots = {}
        for r in sorted(self.chunks):
            lat = np.array(self.latency_s.get(r) or [0.0])
            fused = np.array(self.scan_to_map_s.get(r) or [0.0])
            robots[r] = {
                "chunks": self.chunks[r], "bytes": self.bytes[r],
                "bytes_per_s": self.bytes[r] / seconds if seconds > 0 else 0.0,
                "duplicates_dropped": self.duplicates.get(r, 0),
                "queried_from_disk": self.queried.get(r, 0),
                "commands_resent": self.resent.get(r, 0),
                "command_latency_s": {"p50": float(np.percentile(lat, 50)),
                                      "p99": float(np.percentile(lat, 99))},
                "scan_to_map_s": {"p50": float(np.percentile(fused, 50)),
                                  "p99": float(np.percentile(fused, 99)),
                                  "chunks": len(self.scan_to_map_s.get(r, []))},
            }  # fmt: skip
        return {"robots": robots, "malformed_dropped": self.malformed,
                "foreign_dropped": self.foreign, "refused_robots": self.refused_robots,
                "offline": self.offline}  # fmt: skip


class NetworkFleet(Fleet):
    """The mission's robot agents behind the loop's fleet interface (see the docstring)."""

    def __init__(self, session: Any, mission: MissionSpec, name: str, config: Config,
                 state: BaseState, *, say: Say | None = None,
                 command_timeout_s: float = COMMAND_TIMEOUT_S,
                 join_timeout_s: float = 60.0) -> None:  # fmt: skip
        self.session, self.spec, self.name, self.config = session, mission, name, config
        self.state, self.run = state, state.run
        self.say = say or (lambda text: None)
        self.command_timeout_s = command_timeout_s
        self.robots = mission.robot_names()
        self.starts = mission_starts(mission)
        self.key = mission_key(name)
        self.counts = NetworkCounts()
        self.began = time.monotonic()
        for r in self.robots:
            for table in (self.counts.chunks, self.counts.bytes):
                table[r] = 0
        self._lock = threading.Condition()
        self.chunks: dict[str, dict[int, tuple[str, bytes]]] = {r: {} for r in self.robots}
        #: The lms chunks received by this process (not from the checkpoint) and when the
        #: robot recorded them; those delivered to the loop wait for :meth:`fused`.
        self._recorded: dict[tuple[str, int], float] = {}
        self._delivered_lms: list[tuple[str, float]] = []
        self.online: set[str] = set()
        self.headers: dict[str, dict[str, Any]] = {}
        self.t = 0.0
        self.index = dict.fromkeys(self.robots, 0)
        self.events: list[dict[str, Any]] = [
            {"t_s": 0.0, "event": "start", "robot": r, "index": 0} for r in self.robots
        ]
        self._events_sent = 0
        self._delivered = dict.fromkeys(self.robots, -1)
        self._expected = dict.fromkeys(self.robots, -1)
        self.robot_events: dict[str, list[dict[str, Any]]] = {r: [] for r in self.robots}
        self.clock_samples: dict[str, list[ClockSample]] = {r: [] for r in self.robots}
        #: The robots' on-board summaries of their dwells (sweep, beacons seen).
        self.summaries: dict[str, list[dict[str, Any]]] = {r: [] for r in self.robots}
        self.refused: list[str] = []
        self.seq = 0
        self.replayed = 0
        for robot, seq, stream, data in state.stored_chunks():
            if robot in self.chunks:
                self.chunks[robot][seq] = (stream, _payload(data))
        self._declared = [
            session.declare_subscriber(f"{self.key}/robot/**", self._on_sample),
            session.liveliness().declare_subscriber(
                f"{self.key}/alive/*", self._on_alive, history=True
            ),
        ]
        self._wait_for_robots(join_timeout_s)
        kinds = {bool(h.get("simulated", True)) for h in self.headers.values()}
        if len(kinds) > 1:
            real = sorted(r for r, h in self.headers.items() if not h.get("simulated", True))
            raise WireError(f"mission {name}: robots {', '.join(real)} are real and the "
                            "others simulated; a mission runs on one clock: all real or all "
                            "simulated")  # fmt: skip
        #: Real robots: the mission runs on the base's wall clock (seconds since the mission
        #: began), and every robot stamp is mapped onto it by the clock exchanges. Simulated
        #: robots: on the simulator's mission time, which the robots' replies carry.
        self.wall = kinds == {False}
        if self.wall and mission.changes is not None:
            raise WireError(f"mission {name}: its changes step moves a simulated world's "
                            "objects; real robots cannot (remove changes:)")  # fmt: skip

    def base_now(self) -> float:
        """The base's clock on a real mission: seconds since the mission began (unix time, so
        that a restarted base goes on with the same clock)."""
        return time.time() - self.state.started_unix_s

    # -- what arrives --------------------------------------------------------------------------

    def _on_sample(self, sample: Any) -> None:
        key = str(sample.key_expr)
        parsed = parse_chunk_key(key, self.name)
        if parsed is None:
            # cmd/store/info replies do not come here; anything else is not ours
            if not key.endswith(("/cmd", "/store", "/info")):
                with self._lock:
                    self.counts.foreign += 1
            return
        self._take(parsed[0], sample.payload.to_bytes(), parsed)

    def _take(self, robot: str, data: bytes, key: tuple[str, str, int] | None = None) -> None:
        """A chunk of ``robot``: published on ``key``, or (None) queried from its disk, where
        its header says which it is."""
        try:
            chunk = decode_chunk(data)
        except WireError:
            with self._lock:
                self.counts.malformed += 1
            return
        seq, stream = chunk.seq, chunk.stream
        with self._lock:
            if (
                robot not in self.chunks
                or chunk.robot != robot
                or (key is not None and (stream, seq) != key[1:])
                or (chunk.mission != self.name or chunk.run != self.run)
            ):
                self.counts.foreign += 1
                return
            if seq in self.chunks[robot]:
                self.counts.duplicates[robot] = self.counts.duplicates.get(robot, 0) + 1
                return
            write_bytes_atomic(self.state.chunk_path(robot, seq, stream), data)
            self.chunks[robot][seq] = (stream, chunk.payload)
            if stream == "lms":
                self._recorded[(robot, seq)] = chunk.recorded_unix_s
            self.counts.chunks[robot] += 1
            self.counts.bytes[robot] += len(data)
            if key is None:
                self.counts.queried[robot] = self.counts.queried.get(robot, 0) + 1
            self._lock.notify_all()

    def _on_alive(self, sample: Any) -> None:
        import zenoh

        robot = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._lock:
            if robot not in self.robots:
                if robot not in self.counts.refused_robots:
                    self.counts.refused_robots.append(robot)
                    self.say(f"refused robot {robot!r}: not in mission {self.name}")
                return
            if sample.kind == zenoh.SampleKind.PUT:
                if robot not in self.online:
                    self.say(f"robot {robot} online")
                self.online.add(robot)
            else:
                self.online.discard(robot)
                self.counts.offline.append({"robot": robot, "mission_s": self.t,
                                            "unix_s": time.time()})  # fmt: skip
                self.say(f"robot {robot} offline: waiting for it")
            self._lock.notify_all()

    def _wait_for_robots(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        for robot in self.robots:
            while robot not in self.headers:
                if time.monotonic() > deadline:
                    missing = [r for r in self.robots if r not in self.headers]
                    raise WireError(f"robots {', '.join(missing)} did not join mission "
                                    f"{self.name} within {timeout_s:g} s")  # fmt: skip
                info = self._query_json(f"{self.key}/robot/{robot}/info", None, 2.0)
                if info is not None and isinstance(info.get("header"), dict):
                    self.headers[robot] = info["header"]
                else:
                    time.sleep(0.2)

    def _query_json(self, key: str, payload: bytes | None,
                    timeout_s: float) -> dict[str, Any] | None:  # fmt: skip
        try:
            replies = self.session.get(key, payload=payload, timeout=timeout_s)
            for reply in replies:
                if reply.ok is not None:
                    return decode_json(reply.ok.payload.to_bytes(), key)
                with contextlib.suppress(Exception):
                    self.say(f"{key}: {reply.err.payload.to_bytes().decode(errors='replace')}")
        except WireError:
            with self._lock:
                self.counts.malformed += 1
        return None

    # -- commands ------------------------------------------------------------------------------

    def _command(self, op: str, args: dict[str, Any]) -> dict[str, dict[str, Any]]:
        """Send command ``self.seq`` to every robot; their replies, once every chunk they
        name is held."""
        seq = self.seq
        self.seq += 1
        if seq < len(self.state.log):  # resuming: the checkpoint holds this command
            entry = self.state.log[seq]
            if entry["op"] != op or entry["args"] != json.loads(encode_json(args)):
                raise WireError(f"checkpoint {self.state.folder}: command {seq} was "
                                f"{entry['op']} {entry['args']}, the mission now decides {op} "
                                f"{args}")  # fmt: skip
            self.replayed += 1
            replies: dict[str, dict[str, Any]] = entry["replies"]
        else:
            payload = encode_json({"run": self.run, "seq": seq, "op": op, "args": args})
            replies = {}
            threads = [threading.Thread(target=self._send, args=(r, seq, payload, replies))
                       for r in self.robots]  # fmt: skip
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join()
            if self.wall:
                for robot, reply in replies.items():
                    self._onto_base_clock(robot, reply)
            self.state.commit({"seq": seq, "op": op, "args": args, "replies": replies})
        for robot, reply in replies.items():
            self._expected[robot] = max(self._expected[robot], int(reply["last_chunk"]))
            if "clock_sample" in reply:
                self.clock_samples[robot].append(ClockSample(*reply["clock_sample"]))
        return replies

    def _send(self, robot: str, seq: int, payload: bytes,
              replies: dict[str, dict[str, Any]]) -> None:  # fmt: skip
        """Until ``robot`` replied to command ``seq`` and every chunk it names is held."""
        key = f"{self.key}/robot/{robot}/cmd"
        began = time.monotonic()
        while True:
            self._wait_online(robot)
            reply = self._query_json(key, payload, self.command_timeout_s)
            if reply is None:
                self.counts.resent[robot] = self.counts.resent.get(robot, 0) + 1
                time.sleep(0.2)
                continue
            if "need" in reply:  # the robot lacks earlier commands (its disk was lost)
                self._catch_up(robot, int(reply["need"]), seq)
                continue
            if reply.get("seq") != seq or "last_chunk" not in reply:
                with self._lock:
                    self.counts.malformed += 1
                continue
            self._complete(robot, int(reply["last_chunk"]))
            self.counts.latency_s.setdefault(robot, []).append(time.monotonic() - began)
            # A real clock: the exchange with the shortest round trip of a few.
            exchanges = [self._exchange(robot, float(reply["t_s"]))
                         for _ in range(_EXCHANGES if self.wall else 1)]  # fmt: skip
            sample = min(filter(None, exchanges), key=lambda s: s.round_trip_s, default=None)
            if sample is not None:
                reply["clock_sample"] = sample.as_list()
            replies[robot] = reply
            return

    def _onto_base_clock(self, robot: str, reply: dict[str, Any]) -> None:
        """A real robot's reply times (its clock) → the base's, with the exchanges so far and
        the reply's own; the robot's values stay beside them."""
        samples = list(self.clock_samples[robot])
        if "clock_sample" in reply:
            samples.append(ClockSample(*reply["clock_sample"]))
        if not samples:
            raise WireError(f"robot {robot} did not answer a clock exchange: its stamps cannot "
                            "be put on the base's clock")  # fmt: skip
        mapping = fit_mapping(samples)
        for name in ("t_s", "start_s"):
            if name in reply:
                reply[f"robot_{name}"] = reply[name]
                reply[name] = float(mapping.to_local(float(reply[name])))

    def _exchange(self, robot: str, now_s: float) -> ClockSample | None:
        """One clock exchange with ``robot`` after a command: the robot's clock read between
        two readings of the base's. In simulation the base's clock is the mission's, which
        stands still between commands (``now_s``): the exchange has no round trip. On a real
        mission both readings are of the base's wall clock, and the round trip is real."""
        t1 = self.base_now() if self.wall else now_s
        reply = self._query_json(f"{self.key}/robot/{robot}/clock", None, 5.0)
        t4 = self.base_now() if self.wall else now_s
        value = None if reply is None else reply.get("t_s")
        if not isinstance(value, int | float) or isinstance(value, bool):
            return None
        return ClockSample(t1, float(value), float(value), t4)

    def clock(self, robot: str) -> ClockMapping:
        """The robot's clock → the base's, fitted on the exchanges so far (identity before
        the first). As fitted, ``reference`` is the robot's clock: ``to_local`` maps a robot
        stamp onto the base's clock."""
        samples = self.clock_samples[robot]
        if not samples:
            return ClockMapping(0.0)
        return fit_mapping(samples)

    def _catch_up(self, robot: str, first: int, seq: int) -> None:
        for entry in self.state.log[first:seq]:
            payload = encode_json({"run": self.run, "seq": entry["seq"], "op": entry["op"],
                                   "args": entry["args"]})  # fmt: skip
            self._query_json(f"{self.key}/robot/{robot}/cmd", payload, self.command_timeout_s)

    def _wait_online(self, robot: str) -> None:
        with self._lock:
            while robot not in self.online:
                self._lock.wait(0.5)

    def _complete(self, robot: str, last: int) -> None:
        """Hold every chunk of ``robot`` up to ``last``: wait briefly for the publications,
        then query the robot's disk for what is missing."""
        deadline = time.monotonic() + 0.5
        held = self._expected[robot]  # every chunk up to here is held already
        while True:
            with self._lock:
                missing = [s for s in range(held + 1, last + 1) if s not in self.chunks[robot]]
                if not missing:
                    return
                left = deadline - time.monotonic()
                if left > 0:
                    self._lock.wait(left)
                    continue
            self._wait_online(robot)
            selector = f"{self.key}/robot/{robot}/store?from={missing[0]};to={missing[-1]}"
            for reply in self.session.get(selector, timeout=30.0):
                if reply.ok is not None:
                    self._take(robot, reply.ok.payload.to_bytes())
            deadline = time.monotonic() + 0.5

    # -- the Fleet interface -------------------------------------------------------------------

    def capture_header(self, robot: str) -> dict[str, Any]:
        return dict(self.headers[robot])

    def move(self, goal: Goal) -> Status:
        args = {"robot": goal.robot, "pose": list(goal.pose),
                "path": [list(p) for p in goal.path],
                "believed": None if goal.believed is None else list(goal.believed)}  # fmt: skip
        replies = self._command("move", args)
        reply = replies[goal.robot]
        before = self.index[goal.robot]
        index = int(reply["index"])
        if index != before:  # a real robot whose goal failed may have moved all the same
            self.events.append({
                "t_s": round(float(reply["t_s"]), 6), "event": "move", "robot": goal.robot,
                "from_index": before, "to_index": index,
                "start_s": round(float(reply["start_s"]), 6),
            })  # fmt: skip
            self.index[goal.robot] = index
            self.t = float(reply["t_s"])
        if not reply["ok"]:
            self.refused.append(str(reply.get("reason")))
            return Status(goal.robot, False, index, reply.get("reason"),
                          _blocked(reply.get("blocked")))  # fmt: skip
        return Status(goal.robot, True, index)

    def dwell(self, **fields: Any) -> None:
        replies = self._command("dwell", {"fields": fields})
        end = max(float(r["t_s"]) for r in replies.values())
        if self.wall:  # every robot stands still from when the last one began its dwell
            self.t = max(self.t, max(float(r["start_s"]) for r in replies.values()))
        self.events.append({"t_s": round(self.t, 6), "event": "dwell", "end_s": round(end, 6),
                            "poses": dict(self.index), **fields})  # fmt: skip
        self.t = end

    def log(self, event: str, **fields: Any) -> None:
        self.events.append({"t_s": round(self.t, 6), "event": event, **fields})

    def change_world(self, changes: ChangesSpec) -> list[str]:
        replies = self._command("change", {"changes": changes.model_dump(mode="json")})
        first = replies[self.robots[0]]
        self.events.append({"t_s": round(self.t, 6), "event": "changes",
                            "objects": first.get("objects", [])})  # fmt: skip
        return list(first.get("moved", []))

    def receive(self) -> Received:
        got = Received(now_s=self.t)
        got.events = [dict(e) for e in self.events[self._events_sent :]]
        self._events_sent = len(self.events)
        for robot in self.robots:
            lms: list[tuple[float, bytes]] = []
            times, poses = [np.zeros(0)], [np.zeros((0, 3))]
            clock = self.clock(robot)
            with self._lock:
                seqs = range(self._delivered[robot] + 1, self._expected[robot] + 1)
                pieces = [self.chunks[robot][s] for s in seqs]
                self._delivered_lms += [(robot, self._recorded.pop((robot, s))) for s in seqs
                                        if (robot, s) in self._recorded]  # fmt: skip
            for stream, payload in pieces:
                if stream == "lms":
                    lms += [(float(clock.to_local(t)), data) for t, data in decode_lms(payload)]
                elif stream == "odom":
                    t, p = decode_odometry(payload)
                    times.append((t - clock.offset_s) / clock.rate)  # clock.to_local
                    poses.append(p)
                elif stream == "summary":
                    self.summaries[robot].append(json.loads(payload))
                else:
                    self.robot_events[robot] += [json.loads(line) for line in
                                                 payload.splitlines() if line]  # fmt: skip
            self._delivered[robot] = self._expected[robot]
            got.lms[robot] = lms
            got.odometry[robot] = (np.concatenate(times), np.vstack(poses))
        return got

    def fused(self) -> None:
        """The loop's map now holds what :meth:`receive` delivered: each lms chunk's scan →
        map latency ends here."""
        now = time.time()
        for robot, recorded in self._delivered_lms:
            self.counts.scan_to_map_s.setdefault(robot, []).append(now - recorded)
        self._delivered_lms = []

    def finish(self, out_dir: Path) -> dict[str, Any]:
        replies = self._command("end", {})
        for robot, reply in replies.items():
            for name, text in (reply.get("files") or {}).items():
                if name.startswith("ground_truth/") and name != f"ground_truth/{robot}.tum":
                    continue
                write_text_atomic(out_dir / name, text)
        live = out_dir / "live"
        for robot, events in self.robot_events.items():
            write_text_atomic(live / robot / "events.jsonl",
                              "".join(json.dumps(e) + "\n" for e in events))  # fmt: skip
            write_text_atomic(live / robot / "sweeps.jsonl", "".join(
                json.dumps(e) + "\n" for e in self.summaries[robot]))  # fmt: skip
            # The capture as the robot recorded it, on its own clock (its disk copy, byte for
            # byte); the dataset's is on the base's clock.
            lms = [p for s, (stream, p) in sorted(self.chunks[robot].items()) if stream == "lms"]
            write_bytes_atomic(live / robot / "lms.cap", capture_bytes(self.headers[robot], lms))
            mapping = self.clock(robot)
            clock = {"robot_to_base": "base_s = (robot_s - offset_s) / rate", **mapping.as_dict(),
                     "samples": [s.as_list() for s in self.clock_samples[robot]]}  # fmt: skip
            write_text_atomic(live / robot / "clock.json", json.dumps(clock, indent=1) + "\n")
        seconds = time.monotonic() - self.began
        clocks = {r: self.clock(r).as_dict() for r in self.robots}
        on_board = {r: {"sweeps": sum("points" in e for e in self.summaries[r]),
                        "dwells": len(self.summaries[r]),
                        "beacons": sum(len(e.get("beacons", [])) for e in self.summaries[r])}
                    for r in self.robots}  # fmt: skip
        return {"refused_goals": list(self.refused), "network": self.counts.as_dict(seconds),
                "clocks": clocks, "on_board": on_board,
                "resumed_commands": self.replayed}  # fmt: skip

    def close(self) -> None:
        for entity in reversed(self._declared):
            with contextlib.suppress(Exception):
                entity.undeclare()


def _payload(data: bytes) -> bytes:
    return decode_chunk(data).payload


def _blocked(value: Any) -> tuple[float, float] | None:
    """A reply's ``blocked`` point: two finite numbers, else None (a robot that does not say,
    or says something else)."""
    if not isinstance(value, list | tuple) or len(value) != 2:
        return None
    try:
        x, y = float(value[0]), float(value[1])
    except (TypeError, ValueError):
        return None
    return (x, y) if np.isfinite(x) and np.isfinite(y) else None
