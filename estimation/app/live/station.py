"""The two processes' main functions: :func:`run_base` (``coopmap base``) and
:func:`run_robot` (``coopmap robot``), each a typed function the CLI and the tests call."""

from __future__ import annotations

import json
import shutil
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from estimation.app.config import ConfigError
from estimation.app.live.agent import AgentFaults, RobotAgent, SimulatedRobot
from estimation.app.live.base import BaseState, NetworkFleet
from estimation.app.live.session import DEFAULT_ENDPOINT, open_session
from estimation.app.live.wire import WireError, encode_json, mission_key
from estimation.app.mission.loop import LoopResult, MissionLoop
from sensors.atomic import check_replaceable, replace_directory, write_text_atomic

__all__ = [
    "BaseOptions",
    "HardwareOptions",
    "default_state",
    "run_base",
    "run_hardware_robot",
    "run_robot",
]

Say = Callable[[str], None]


@dataclass(frozen=True)
class BaseOptions:
    mission: Path
    out: Path
    state: Path | None = None
    listen: str = DEFAULT_ENDPOINT
    overrides: dict[str, Any] | None = None
    join_timeout_s: float = 60.0
    command_timeout_s: float = 120.0


def default_state(out: Path) -> Path:
    """Where the base keeps its checkpoint unless told: beside the dataset it writes."""
    return out.with_name(f".{out.name}.base")


class Publications:
    """What the base publishes after every dwell, kept for viewers that ask later."""

    def __init__(self, session: Any, mission: str) -> None:
        self.session, self.key = session, f"{mission_key(mission)}/base"
        self.latest: dict[str, bytes] = {}
        self._lock = threading.Lock()
        self._ros: Any = None
        self.queryable = session.declare_queryable(f"{self.key}/**", self._serve)

    def _serve(self, query: Any) -> None:
        with self._lock:
            items = list(self.latest.items())
        for name, data in items:
            key = f"{self.key}/{name}"
            if query.key_expr.intersects(key):
                query.reply(key, data)

    def put(self, name: str, data: bytes) -> None:
        with self._lock:
            self.latest[name] = data
        self.session.put(f"{self.key}/{name}", data)

    def publish_loop(self, loop: MissionLoop, fleet: NetworkFleet) -> None:
        from estimation.app.rig import cut_ceiling_band
        from estimation.app.ros.messages import RosMessages, stamp_ns
        from estimation.posegraph.keys import split_key
        from mapping.errors import MapError

        fleet.fused()
        poses: dict[str, dict[str, list[float]]] = {}
        for key, pose in sorted(loop.estimate.items()):
            robot, index = split_key(key)
            poses.setdefault(robot, {})[str(index)] = [round(float(v), 6) for v in pose]
        self.put("estimate", encode_json({"mission_s": loop.now_s, "poses": poses}))
        self.put("state", encode_json({
            "mission_s": loop.now_s, "dwells": loop.dwells, "stations": len(loop.steps),
            "online": sorted(fleet.online), "robots": fleet.robots,
            "index": dict(loop.index),
        }))  # fmt: skip
        try:
            ceiling = cut_ceiling_band(loop.map.grid, loop.config)
        except MapError:
            return  # nothing observed in the band yet
        if self._ros is None:
            self._ros = RosMessages()
        grid = self._ros.occupancy_grid(stamp_ns(loop.now_s), "map", ceiling)
        self.put("map", self._ros.serialize(grid))  # nav_msgs/OccupancyGrid, CDR as on ROS 2

    def close(self) -> None:
        self.queryable.undeclare()


def run_base(options: BaseOptions, say: Say | None = None,
             observe: Callable[[MissionLoop], None] | None = None) -> LoopResult:  # fmt: skip
    """Run the mission with its robots on the network; resume from the checkpoint if there is
    one. The dataset as the base rebuilt it, with the result in ``result/``, replaces
    ``options.out``; the checkpoint is removed once that is done."""
    from estimation.app.sim.simulate import mission_config
    from sensors.sim.mission import load_mission

    say = say or (lambda text: None)
    check_replaceable(options.out, "dataset")
    spec = load_mission(options.mission)
    if len(spec.robots) < 2:
        raise ConfigError(f"{options.mission}: a live mission needs two robots or more")
    if spec.plan == "auto":  # the base has no world to plan on: it explores its map
        spec = spec.model_copy(update={"auto": spec.auto.model_copy(update={"planner": "map"})})
    config = mission_config(spec, options.overrides, str(options.mission))
    name = options.mission.stem
    state = BaseState(options.state or default_state(options.out), name)
    if state.resumed:
        say(f"resuming run {state.run} from {state.folder} ({len(state.log)} commands)")
    session = open_session(listen=[options.listen])
    try:
        publications = Publications(session, name)
        fleet = NetworkFleet(session, spec, name, config, state, say=say,
                             command_timeout_s=options.command_timeout_s,
                             join_timeout_s=options.join_timeout_s)  # fmt: skip
        with replace_directory(options.out, "dataset") as work:

            def publish(lp: MissionLoop) -> None:
                publications.publish_loop(lp, fleet)
                if observe is not None:
                    observe(lp)  # a Foxglove live view (coopmap base --view)

            loop = MissionLoop(fleet, spec, config, work, progress=say, observe=publish)
            try:
                reason = loop.run()
            except BaseException:
                loop.discard()
                raise
            result = loop.finish(work / "result", reason, options.out)
            shutil.copy(state.folder / "commands.jsonl", work / "live" / "commands.jsonl")
            network = json.dumps(result.loop.get("network", {}), indent=1) + "\n"
            write_text_atomic(work / "live" / "network.json", network)
        publications.put("state", encode_json({"mission_s": loop.now_s, "done": True,
                                               "stop_reason": reason}))  # fmt: skip
        fleet.close()
        publications.close()
    finally:
        session.close()
    shutil.rmtree(state.folder, ignore_errors=True)
    return result


def run_robot(
    mission_path: Path,
    robot: str,
    folder: Path,
    *,
    connect: str = DEFAULT_ENDPOINT,
    overrides: dict[str, Any] | None = None,
    seed: int | None = None,
    faults: AgentFaults | None = None,
    clock_offset_s: float = 0.0,
    clock_drift_ppm: float = 0.0,
    emulate: bool = False,
    say: Say | None = None,
    stop: threading.Event | None = None,
) -> None:
    """One simulated robot of the mission as an agent process, until ``stop`` (or SIGTERM /
    SIGINT when run as a process)."""
    from estimation.app.mission.simulated import simulated_fleet
    from estimation.app.sim.simulate import load_simulated

    say = say or (lambda text: None)
    spec, config, world, space, seed = load_simulated(mission_path, overrides, seed)
    if robot not in spec.robot_names():
        raise WireError(f"robot {robot!r} is not in mission {mission_path.stem} "
                        f"(robots {', '.join(spec.robot_names())})")  # fmt: skip

    def simulate() -> SimulatedRobot:
        fleet = simulated_fleet(spec, config, world, seed, space)
        return SimulatedRobot(fleet, robot, clock_offset_s, 1.0 + clock_drift_ppm * 1e-6,
                              config if emulate else None)  # fmt: skip

    header = {"baud_rate": config.serial.baud_rate, "simulated": True,
              "emulated": emulate, "started_unix_s": time.time()}  # fmt: skip
    session = open_session(connect=[connect])
    agent = RobotAgent(session, mission_path.stem, robot, folder, header, simulate, faults, say)
    _serve(agent, session, f"robot {robot} of mission {mission_path.stem} up, connecting to "
           f"{connect}", say, stop)  # fmt: skip


@dataclass(frozen=True)
class HardwareOptions:
    """A robot agent on real hardware: its LMS 200's serial port (or pyserial URL), the
    robot base's odometry stream and goal endpoint (docs/live.md, "A real robot")."""

    port: str
    odometry: str
    drive: str
    move_timeout_s: float = 600.0
    slice_s: float = 1.0


def run_hardware_robot(
    mission_path: Path,
    robot: str,
    folder: Path,
    hardware: HardwareOptions,
    *,
    connect: str = DEFAULT_ENDPOINT,
    overrides: dict[str, Any] | None = None,
    say: Say | None = None,
    stop: threading.Event | None = None,
) -> None:
    """One robot of the mission on real hardware as an agent process, until ``stop`` (or
    SIGTERM / SIGINT when run as a process). The links are opened before the agent joins:
    a port, stream or endpoint that cannot be reached is a one-line error."""
    from estimation.app.live.hardware import HardwareRobot
    from estimation.app.mission.simulated import mission_starts
    from estimation.app.rig import driver_from_config
    from estimation.app.sim.simulate import mission_config
    from sensors.recording.drive import DriveClient
    from sensors.recording.odometry import open_source
    from sensors.sim.mission import load_mission

    say = say or (lambda text: None)
    spec = load_mission(mission_path)
    config = mission_config(spec, overrides, str(mission_path))
    if robot not in spec.robot_names():
        raise WireError(f"robot {robot!r} is not in mission {mission_path.stem} "
                        f"(robots {', '.join(spec.robot_names())})")  # fmt: skip
    start = mission_starts(spec)[robot]
    # Every link once now: one line says which cannot be reached, before the agent joins.
    probe = driver_from_config(config, hardware.port)
    probe.open()
    probe.close()
    for link in (open_source(hardware.odometry), DriveClient(hardware.drive)):
        link.connect()
        link.close()

    def make_robot() -> HardwareRobot:
        lms = driver_from_config(config, hardware.port)
        return HardwareRobot(config, robot, start, lms, open_source(hardware.odometry),
                             DriveClient(hardware.drive),
                             move_timeout_s=hardware.move_timeout_s)  # fmt: skip

    header = {"baud_rate": config.serial.baud_rate, "simulated": False, "port": hardware.port,
              "started_unix_s": time.time()}  # fmt: skip
    session = open_session(connect=[connect])
    agent = RobotAgent(session, mission_path.stem, robot, folder, header, make_robot, None, say,
                       slice_s=hardware.slice_s)  # fmt: skip
    _serve(agent, session, f"robot {robot} of mission {mission_path.stem} up on "
           f"{hardware.port}, connecting to {connect}", say, stop)  # fmt: skip


def _serve(agent: RobotAgent, session: Any, hello: str, say: Say,
           stop: threading.Event | None) -> None:  # fmt: skip
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
    worker = threading.Thread(target=agent.run, name=f"robot-{agent.name}", daemon=True)
    worker.start()
    say(hello)
    try:
        while not stop.wait(0.1):
            if not worker.is_alive():
                break
    finally:
        agent.close()
        worker.join(timeout=5.0)
        session.close()
