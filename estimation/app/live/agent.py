"""``coopmap robot``: one robot as a process on the network (docs/live.md).

The agent executes the base station's numbered commands in order (drive to a goal, dwell for a
sweep, the world's changes, the end), and after each one writes what its sensors recorded to its
own disk first — immutable numbered chunks (:mod:`estimation.app.live.wire`) and a line in its
command log — then publishes the chunks and replies. It serves any range of its chunks from disk
on query, holds a liveliness token, and answers a command it already executed with the reply it
gave then, so a base that lost a reply, or restarted, just asks again.

The robot's store (``--dir``):

* ``store.json`` — mission, run, robot, the capture header;
* ``chunks/<seq>.<stream>`` — every chunk as published;
* ``commands.jsonl`` — per executed command: the command, the reply, the simulator's state
  after it. A line is written after the command's chunks, so it is the commit point: an agent
  killed mid-command redoes that command when it comes again;
* ``lms.cap`` / ``odometry.tum`` — the robot's capture and odometry, rebuilt from the chunks.

In simulation (``--simulate``) the robot is the simulator's
(:class:`~estimation.app.mission.fleet.SimulatedFleet`, restricted to this robot's sensors): it
keeps a copy of every robot's true motion, replayed from the commands, because its scanner sees
the others' bodies and beacons. A restarted agent replays its command log through that copy and
takes the sensors' state back, so what it records next is what it would have recorded anyway.

On real hardware (``--port --odometry --drive``) the robot is a
:class:`~estimation.app.live.hardware.HardwareRobot`: its recording goes on between commands and
is cut into time slices, and a restarted agent keeps every chunk on its disk, since nothing can
record it again.
"""

from __future__ import annotations

import contextlib
import json
import math
import queue
import random
import shutil
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from estimation.app.config import Config
from estimation.app.live.emulated import EmulatedLms
from estimation.app.live.hardware import parse_goal
from estimation.app.live.wire import (
    Chunk,
    WireError,
    append_journal,
    chunk_key,
    decode_chunk,
    decode_json,
    decode_odometry,
    encode_chunk,
    encode_json,
    encode_lms,
    encode_odometry,
    mission_key,
    read_journal,
)
from estimation.app.mission.fleet import Goal, SimulatedFleet
from sensors.atomic import write_bytes_atomic, write_text_atomic
from sensors.errors import OutputError, SensorError
from sensors.lms200.capture import capture_head
from sensors.sim.mission import ChangesSpec
from sensors.trajio import tum_text

__all__ = [
    "AgentFaults",
    "RobotAgent",
    "RobotStore",
    "SimulatedRobot",
    "capture_bytes",
    "sweep_summary",
]

#: How long the agent waits for the next command before looking at its stop flag (s).
_POLL_S = 0.02


class RobotStore:
    """A robot's own disk copy of what it recorded (see the module's docstring)."""

    def __init__(self, folder: Path, mission: str, run: str, robot: str,
                 header: dict[str, Any], *, keep_uncommitted: bool = False) -> None:  # fmt: skip
        self.folder, self.run = Path(folder), run
        meta = {"format": "coopmap robot store", "mission": mission, "run": run, "robot": robot}
        existing = self._existing(self.folder)
        if existing is not None and existing.get("run") != run:
            # An earlier run's store of coopmap's own: replaced, never merged.
            shutil.rmtree(self.folder)
            existing = None
        if existing is None:
            self.folder.mkdir(parents=True, exist_ok=True)
            (self.folder / "chunks").mkdir(exist_ok=True)
            header = {**header, "robot": robot}
            write_text_atomic(self.folder / "store.json",
                              json.dumps({**meta, "header": header}, indent=1) + "\n")  # fmt: skip
        elif {k: existing.get(k) for k in meta} != meta:
            raise OutputError(f"{self.folder}: the store of robot {existing.get('robot')!r} "
                              f"in mission {existing.get('mission')!r}, not {robot!r} in "
                              f"{mission!r}")  # fmt: skip
        self.header: dict[str, Any] = json.loads((self.folder / "store.json").read_text())["header"]
        self.log = read_journal(self.folder / "commands.jsonl")
        self.next_seq = int(self.log[-1]["next_seq"]) if self.log else 0
        for path in sorted((self.folder / "chunks").iterdir()):
            if int(path.stem) < self.next_seq:
                continue
            if keep_uncommitted:  # a real robot's recording: kept, whatever the command did
                self.next_seq = int(path.stem) + 1
            else:  # a simulated command cut short left these: it is done again
                path.unlink()

    @classmethod
    def existing_run(cls, folder: Path, mission: str, robot: str) -> str | None:
        """The run of the store in ``folder`` when it is this robot's in this mission (None:
        no store yet); OutputError when the folder holds anything else."""
        meta = cls._existing(folder)
        if meta is None:
            return None
        if meta.get("mission") != mission or meta.get("robot") != robot:
            raise OutputError(f"{folder}: the store of robot {meta.get('robot')!r} in mission "
                              f"{meta.get('mission')!r}, not {robot!r} in {mission!r}")  # fmt: skip
        return str(meta.get("run"))

    @staticmethod
    def _existing(folder: Path) -> dict[str, Any] | None:
        if not folder.exists():
            return None
        meta = folder / "store.json"
        if not meta.is_file():
            if folder.is_dir() and not any(folder.iterdir()):
                return None
            raise OutputError(f"{folder}: exists and is not a coopmap robot store; "
                              "choose another --dir")  # fmt: skip
        try:
            value = json.loads(meta.read_text(encoding="utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError):
            raise OutputError(f"{meta}: not a coopmap robot store (unreadable)") from None
        if not isinstance(value, dict) or value.get("format") != "coopmap robot store":
            raise OutputError(f"{folder}: not a coopmap robot store; choose another --dir")
        return value

    def chunk_path(self, seq: int, stream: str) -> Path:
        return self.folder / "chunks" / f"{seq:08d}.{stream}"

    def put(self, chunk: Chunk) -> bytes:
        data = encode_chunk(chunk)
        write_bytes_atomic(self.chunk_path(chunk.seq, chunk.stream), data)
        self.next_seq = max(self.next_seq, chunk.seq + 1)
        return data

    def commit(self, entry: dict[str, Any]) -> None:
        append_journal(self.folder / "commands.jsonl", entry)
        self.log.append(entry)
        self.next_seq = int(entry["next_seq"])

    def chunks(self, first: int, last: int) -> list[tuple[int, str, bytes]]:
        """The stored chunks with seq in [first, last] as (seq, stream, bytes)."""
        out = []
        for seq in range(max(0, first), min(last, self.next_seq - 1) + 1):
            for path in (self.folder / "chunks").glob(f"{seq:08d}.*"):
                out.append((seq, path.suffix[1:], path.read_bytes()))
        return out

    def write_recording(self) -> None:
        """``lms.cap`` and ``odometry.tum`` from the chunks: the robot's recording as a whole."""
        lms, times, poses = [], [], []
        for _, stream, data in self.chunks(0, self.next_seq - 1):
            chunk = decode_chunk(data)
            if stream == "lms":
                lms.append(chunk.payload)
            elif stream == "odom":
                t, p = decode_odometry(chunk.payload)
                times.append(t)
                poses.append(p)
        write_bytes_atomic(self.folder / "lms.cap", capture_bytes(self.header, lms))
        if times:
            text = tum_text(np.concatenate(times), np.vstack(poses), decimals=6)
            write_text_atomic(self.folder / "odometry.tum", text)


def sweep_summary(config: Config, header: dict[str, Any], records: list[tuple[float, bytes]],
                  start_s: float, end_s: float) -> dict[str, Any]:  # fmt: skip
    """On board, after a dwell: the sweep assembled from the dwell's telegrams (``records``,
    stamped on the robot's clock) and the beacons detected in it, as the base will find them
    in the capture."""
    from estimation.app.dataset import DWELL_SETTLE_S, LmsDecoder, sweep_in
    from estimation.app.rig import beacon_parameters, scan_limits
    from sensors.scan3d.beacon import detect_beacons

    decoder = LmsDecoder(config.scanner.measuring_mode, scan_limits(config), header)
    decoder.feed_chunks(records)
    scan, why = sweep_in(decoder.stream(), start_s + DWELL_SETTLE_S, end_s, config)
    if scan is None:
        return {"dwell_s": [start_s, end_s], "scans": decoder.decoded, "why": why}
    detections, rejections = detect_beacons(scan.points_scanner, scan.reflector,
                                            **beacon_parameters(config))  # fmt: skip
    return {
        "dwell_s": [start_s, end_s], "scans": decoder.decoded, "sweep_scans": scan.scans,
        "points": len(scan.points_scanner), "beacons_rejected": len(rejections),
        "beacons": [{"range_m": round(d.range_m, 4),
                     "bearing_deg": round(math.degrees(d.bearing_rad), 3),
                     "returns": d.returns, "quality": round(d.quality, 3)} for d in detections],
    }  # fmt: skip


def capture_bytes(header: dict[str, Any], lms_payloads: list[bytes]) -> bytes:
    """A capture file's bytes: its header and the records of the lms chunks in order."""
    return capture_head(header) + b"".join(lms_payloads)


@dataclass
class SimulatedRobot:
    """One robot of a simulated mission as its agent runs it (see the module's docstring)."""

    fleet: SimulatedFleet
    robot: str
    #: The robot's own clock: ``clock_offset_s + clock_rate · t`` at mission time t. Its
    #: stamps are on it; the base maps them onto its clock (docs/live.md, "Clocks").
    clock_offset_s: float = 0.0
    clock_rate: float = 1.0
    #: ``--emulate``: the configuration of the LMS 200 whose telegrams go through the device
    #: emulator on a pty and the real driver (:mod:`estimation.app.live.emulated`).
    emulate: Config | None = None
    lms: EmulatedLms | None = None
    #: The simulator records only while a command runs: nothing to publish in between.
    streaming = False

    @property
    def config(self) -> Config:
        return self.fleet.config

    def state(self) -> dict[str, Any]:
        return self.fleet.state()

    def start_sensors(self) -> None:
        """After a replay: the emulated sensor, set up as on a robot, from where it stands."""
        if self.emulate is not None and self.lms is None:
            self.lms = EmulatedLms(self.emulate, self.now_s)

    def close(self) -> None:
        if self.lms is not None:
            self.lms.close()
            self.lms = None

    def local(self, t_s: float | np.ndarray) -> Any:
        return self.clock_offset_s + self.clock_rate * t_s

    def apply(self, op: str, args: dict[str, Any]) -> dict[str, Any]:
        """Carry out one command on the simulator's copy of the mission; the reply's fields."""
        fleet = self.fleet
        if op == "move":
            status = fleet.move(_goal(args))
            return {
                "ok": status.ok,
                "index": status.index,
                "reason": status.reason,
                "blocked": None if status.blocked_xy is None else list(status.blocked_xy),
            }
        if op == "dwell":
            fleet.dwell(**args.get("fields", {}))
            return {"ok": True}
        if op == "change":
            return {"ok": True, "moved": fleet.change_world(ChangesSpec(**args["changes"]))}
        if op == "end":
            return {"ok": True, "files": fleet.truth_files([self.robot])}
        raise WireError(f"unknown command {op!r}")

    def recorded(self) -> tuple[list[tuple[float, bytes]], np.ndarray, np.ndarray]:
        """This robot's LMS records and odometry since the last call."""
        got = self.fleet.receive([self.robot])
        times, poses = got.odometry.get(self.robot, (np.zeros(0), np.zeros((0, 3))))
        records = got.lms.get(self.robot, [])
        if self.lms is not None:
            records = self.lms.pass_through(records)
        records = [(float(self.local(t)), data) for t, data in records]
        return records, self.local(times), poses

    @property
    def now_s(self) -> float:
        return self.fleet.builder.t

    def index(self, robot: str) -> int:
        return self.fleet.builder.index[robot]

    def replay(self, log: list[dict[str, Any]]) -> None:
        """The motion of every command in ``log`` again, then the sensors' state after it."""
        for entry in log:
            self.apply(entry["op"], entry["args"])
        if log:
            self.fleet.restore(log[-1]["state"])


def _goal(args: dict[str, Any]) -> Goal:
    """A move command's goal, checked as a real robot checks it (finite, the right shapes)."""
    robot, pose, path, believed = parse_goal(args)
    return Goal(
        robot, (float(pose[0]), float(pose[1]), float(pose[2])),
        tuple((float(p[0]), float(p[1])) for p in path),
        None if believed is None else (float(believed[0]), float(believed[1]), float(believed[2])),
    )  # fmt: skip


@dataclass(frozen=True)
class AgentFaults:
    """Faults the agent injects into its own publication, for tests of the transport: each
    chunk is dropped (the base must query it), sent twice, or held back until after the next
    one, with these probabilities (seeded)."""

    drop: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    seed: int = 0

    @classmethod
    def parse(cls, text: str) -> AgentFaults:
        """``drop=0.2,duplicate=0.1,reorder=0.2,seed=3``."""
        values: dict[str, float] = {}
        for part in filter(None, text.split(",")):
            name, _, value = part.partition("=")
            if name not in ("drop", "duplicate", "reorder", "seed"):
                raise WireError(
                    f"--faults: unknown fault {name!r} (drop, duplicate, reorder, seed)"
                )
            try:
                values[name] = float(value)
            except ValueError:
                raise WireError(f"--faults: {name}={value!r} is not a number") from None
            if name != "seed" and not 0.0 <= values[name] < 1.0:
                raise WireError(f"--faults: {name} must be in [0, 1), got {value}")
        seed = int(values.pop("seed", 0))
        return cls(seed=seed, **values)


class RobotAgent:
    """The agent process's work (see the module's docstring); ``run`` until ``stop``.

    ``make_robot`` gives the robot the commands go to: a :class:`SimulatedRobot`, or a robot on
    real hardware (:class:`~estimation.app.live.hardware.HardwareRobot`), whose recording between
    commands is cut every ``slice_s`` into chunks, written and published as it comes.
    """

    def __init__(self, session: Any, mission: str, robot: str, folder: Path,
                 header: dict[str, Any], make_robot: Callable[[], Any],
                 faults: AgentFaults | None = None,
                 log: Callable[[str], None] | None = None, *,
                 slice_s: float = 1.0) -> None:  # fmt: skip
        self.session, self.mission, self.name = session, mission, robot
        self.folder, self.make_robot, self.slice_s = Path(folder), make_robot, slice_s
        self._emit_lock = threading.RLock()
        self._dwell: list[tuple[float, bytes]] | None = None
        self.faults = faults or AgentFaults()
        self._fault_rng = random.Random(self.faults.seed)
        self._held: list[tuple[str, bytes]] = []
        self.say = log or (lambda text: None)
        self.stop = threading.Event()
        self.commands: queue.Queue[Any] = queue.Queue()
        self.rejected = 0
        self.store: RobotStore | None = None
        self.robot: Any = None
        self.header = {**header, "robot": robot}
        self.hardware = not header.get("simulated", True)
        run = RobotStore.existing_run(self.folder, mission, robot)
        if run is not None:
            self._open(run)
        base = f"{mission_key(mission)}/robot/{robot}"
        self._slicer = threading.Thread(target=self._slices, name="slices", daemon=True)
        self._slicer.start()
        self._declared = [
            session.declare_queryable(f"{base}/cmd", self.commands.put),
            session.declare_queryable(f"{base}/store", self._serve_store),
            session.declare_queryable(f"{base}/info", self._serve_info),
            session.declare_queryable(f"{base}/clock", self._serve_clock),
            session.liveliness().declare_token(f"{mission_key(mission)}/alive/{robot}"),
        ]

    def _open(self, run: str) -> None:
        """The store of ``run`` (an earlier run's is replaced), the simulation replayed."""
        with self._emit_lock:
            self.store = RobotStore(self.folder, self.mission, run, self.name, self.header,
                                    keep_uncommitted=self.hardware)  # fmt: skip
            self.header = self.store.header
            if self.robot is not None:
                self.robot.close()
            self.robot = None
            robot = self.make_robot()
            robot.replay(self.store.log)
            try:
                robot.start_sensors()
            except SensorError as exc:  # a real robot's port or link: said, and tried again
                robot.close()
                raise WireError(f"robot {self.name}: {exc}") from None
            self.robot = robot
        if self.store.log:
            self.say(f"resumed run {run} after command {self.store.log[-1]['seq']} "
                     f"(next chunk {self.store.next_seq})")  # fmt: skip

    # -- queries ---------------------------------------------------------------------------------

    def _serve_store(self, query: Any) -> None:
        with query:
            self._reply_store(query)

    def _reply_store(self, query: Any) -> None:
        """Replies on the query's own key: each chunk's header names it."""
        store = self.store
        if store is None:
            query.reply_err(b"store: nothing recorded yet")
            return
        try:
            params = query.parameters
            first, last = int(params.get("from") or 0), int(params.get("to") or -1)
        except (TypeError, ValueError):
            query.reply_err(b"store: ?from=A;to=B with integers")
            return
        for _, _, data in store.chunks(first, last):
            query.reply(query.key_expr, data)

    def _serve_info(self, query: Any) -> None:
        store = self.store
        with query:
            links = getattr(self.robot, "links", None)
            query.reply(query.key_expr, encode_json({
                "robot": self.name, "header": self.header,
                "run": None if store is None else store.run,
                "done": len(store.log) - 1 if store is not None else -1,
                "next_seq": 0 if store is None else store.next_seq,
                **({"links": links()} if links is not None else {}),
            }))  # fmt: skip

    def _serve_clock(self, query: Any) -> None:
        """The robot's clock now: one side of the base's clock exchange."""
        with query:
            robot = self.robot
            if robot is None:
                query.reply_err(b"clock: no mission run yet")
                return
            query.reply(query.key_expr, encode_json({"t_s": float(robot.local(robot.now_s))}))

    # -- commands --------------------------------------------------------------------------------

    def run(self) -> None:
        while not self.stop.is_set():
            try:
                query = self.commands.get(timeout=_POLL_S)
            except queue.Empty:
                continue
            with query:  # leaving it finalizes the query: the base's get returns at once
                try:
                    payload = query.payload.to_bytes() if query.payload is not None else None
                    reply = self._command(decode_json(payload, "command"))
                except WireError as exc:
                    self.rejected += 1
                    query.reply_err(str(exc).encode())
                    continue
                query.reply(query.key_expr, encode_json(reply))
            if reply.get("op") == "end" and self.store is not None:
                self.store.write_recording()

    def _command(self, command: dict[str, Any]) -> dict[str, Any]:
        seq, op, args = command.get("seq"), command.get("op"), command.get("args")
        run = command.get("run")
        if (
            not isinstance(seq, int)
            or not isinstance(op, str)
            or not isinstance(args, dict)
            or (not isinstance(run, str) or not run.isalnum())
        ):
            raise WireError("command: needs run (str), seq (int), op (str) and args (object)")
        if self.store is None or self.store.run != run or self.robot is None:
            self._open(run)  # a new run of the mission: this robot starts afresh
        store, robot = self.store, self.robot
        assert store is not None
        assert robot is not None
        log = store.log
        if seq < len(log):
            return dict(log[seq]["reply"])  # executed already: the same reply again
        if seq > len(log):
            return {"seq": seq, "need": len(log)}  # the base sends the ones we lack first
        began = robot.now_s
        if op == "dwell":
            self._dwell = []  # the dwell's telegrams, whichever chunks they go into
        try:
            reply = {"seq": seq, "op": op, "start_s": began, **robot.apply(op, args)}
        except (TypeError, ValueError, KeyError, WireError) as exc:
            with self._emit_lock:
                self._dwell = None
            if isinstance(exc, WireError):
                raise
            raise WireError(f"command {seq} ({op}): {exc}") from None
        ended = robot.now_s  # a real robot's clock runs on while the reply is made
        with self._emit_lock:
            dwell, self._dwell = self._dwell, None
            records, times, poses = robot.recorded()
            event = {"seq": seq, "op": op, "t_s": round(ended, 6), "ok": reply["ok"]}
            summary = None
            if op == "dwell":
                window = (float(robot.local(began)), float(robot.local(ended)))
                summary = sweep_summary(robot.config, self.header, [*(dwell or []), *records],
                                        *window)  # fmt: skip
                reply["sweep"] = {k: v for k, v in summary.items() if k != "beacons"}
                reply["beacons"] = len(summary.get("beacons", []))
            outgoing = self._chunks(store, records, times, poses, [
                ("event", encode_json(event) + b"\n"),
                ("summary", encode_json(summary)) if summary is not None else None,
            ])  # fmt: skip
            reply.update(t_s=ended, index=reply.get("index", robot.index(self.name)),
                         last_chunk=store.next_seq - 1)  # fmt: skip
            store.commit({"seq": seq, "op": op, "args": args, "reply": reply,
                          "state": robot.state(), "next_seq": store.next_seq})  # fmt: skip
            for key, data in outgoing:
                self._publish(key, data)
        return reply

    def _chunks(self, store: RobotStore, records: list[tuple[float, bytes]], times: np.ndarray,
                poses: np.ndarray,
                more: list[tuple[str, bytes] | None]) -> list[tuple[str, bytes]]:  # fmt: skip
        """Write ``records``, the odometry and ``more`` as the next chunks on disk; their keys
        and bytes, to publish."""
        parts = [("lms", encode_lms(records)) if records else None,
                 ("odom", encode_odometry(times, poses)) if len(times) else None,
                 *more]  # fmt: skip
        outgoing = []
        for stream, payload in filter(None, parts):
            seq = store.next_seq
            chunk = Chunk(self.mission, store.run, self.name, stream, seq, payload, time.time())
            outgoing.append((chunk_key(self.mission, self.name, stream, seq), store.put(chunk)))
        return outgoing

    def _slices(self) -> None:
        """A real robot's recording between (and during) commands, cut every ``slice_s``."""
        while not self.stop.wait(self.slice_s):
            with self._emit_lock:
                robot, store = self.robot, self.store
                if robot is None or store is None or not robot.streaming:
                    continue
                records, times, poses = robot.recorded()
                if self._dwell is not None:
                    self._dwell.extend(records)
                for key, data in self._chunks(store, records, times, poses, []):
                    self._publish(key, data)

    def _publish(self, key: str, data: bytes) -> None:
        faults, rng = self.faults, self._fault_rng
        if faults.drop and rng.random() < faults.drop:
            return
        if faults.reorder and rng.random() < faults.reorder:
            self._held.append((key, data))
            return
        self.session.put(key, data)
        if faults.duplicate and rng.random() < faults.duplicate:
            self.session.put(key, data)
        while self._held:
            self.session.put(*self._held.pop())

    def close(self) -> None:
        self.stop.set()
        self._slicer.join(timeout=2.0)
        for entity in reversed(self._declared):
            with contextlib.suppress(Exception):
                entity.undeclare()
        if self.robot is not None:
            self.robot.close()
