"""``coopmap live``: the base and one agent per robot as processes on this machine, supervised.

Each process is the same command a user would run on its own machine (``coopmap base``,
``coopmap robot``), on loopback. A robot agent that dies is started again (it resumes from its
disk and the base re-sends what it missed); when the base ends, the robots are stopped. Ctrl-C
stops everything with SIGINT: the base's checkpoint and the robots' disks stay, and the same
``coopmap live`` resumes the mission.
"""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from estimation.app.live.station import default_state
from sensors.atomic import check_replaceable
from sensors.errors import OutputError

__all__ = ["LiveOptions", "Supervisor", "free_port", "robot_dirs"]

Say = Callable[[str], None]


#: The drift of the simulated robots' clocks against the base's, by robot (ppm).
CLOCK_DRIFTS_PPM = (40.0, -25.0, 12.0, -60.0)


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def robot_dirs(out: Path) -> Path:
    """Where ``coopmap live`` keeps the simulated robots' own disks."""
    return out.with_name(f".{out.name}.robots")


@dataclass
class LiveOptions:
    mission: Path
    out: Path
    robots: list[str]
    port: int = 0
    config: Path | None = None
    seed: int | None = None
    faults: dict[str, str] = field(default_factory=dict)  # robot → --faults text
    restarts: int = 5  # per robot
    #: The robots' LMS 200 telegrams go through the device emulator on a pty and the driver.
    emulate: bool = False
    #: The base serves a Foxglove live view on this loopback port (None: no view).
    view_port: int | None = None
    #: How long the base keeps serving the final state to the live view after the mission (s).
    view_seconds: float = 0.0


def _sigint_stops() -> None:
    """In a child before exec: SIGINT at its default, since the supervisor stops its children
    with it. A supervisor started in the background (nohup, ``&`` in a script) ignores SIGINT,
    and its children would inherit that."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _command(*args: str) -> list[str]:
    return [sys.executable, "-m", "estimation.app.cli.main", *args]


class Supervisor:
    """Start, watch and stop the processes of one live mission."""

    def __init__(self, options: LiveOptions, say: Say | None = None) -> None:
        check_replaceable(options.out, "dataset")
        self.options = options
        self.say = say or (lambda text: None)
        self.port = options.port or free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.base: subprocess.Popen[bytes] | None = None
        self.agents: dict[str, subprocess.Popen[bytes]] = {}
        self.restarted: dict[str, int] = dict.fromkeys(options.robots, 0)
        self.base_restarts = 0
        self.logs = options.out.with_name(f".{options.out.name}.logs")
        disks = robot_dirs(options.out)
        for path in (disks, self.logs):
            if path.exists() and not (path / ".coopmap-live").exists():
                raise OutputError(f"{path}: exists and was not made by coopmap live")
            path.mkdir(parents=True, exist_ok=True)
            (path / ".coopmap-live").touch()

    def _common(self) -> list[str]:
        extra = []
        if self.options.config is not None:
            extra += ["--config", str(self.options.config)]
        return extra

    def _start_base(self) -> None:
        o = self.options
        args = ["base", str(o.mission), "--out", str(o.out), "--listen", self.endpoint,
                "--state", str(default_state(o.out)), *self._common()]  # fmt: skip
        if o.view_port is not None:
            args += ["--view", "--view-port", str(o.view_port)]
            if o.view_seconds > 0:
                args += ["--view-seconds", f"{o.view_seconds:g}"]
        self.base = self._spawn("base", args)

    def _start_robot(self, robot: str) -> None:
        o = self.options
        disk = robot_dirs(o.out) / robot
        source = "--emulate" if o.emulate else "--simulate"
        args = ["robot", str(o.mission), "--name", robot, source, "--connect",
                self.endpoint, "--dir", str(disk), *self._common()]  # fmt: skip
        if o.seed is not None:
            args += ["--seed", str(o.seed)]
        # Every simulated robot's clock is off and drifts, unlike the base's: the stamps cross
        # the clock mapping as a real robot's do.
        k = o.robots.index(robot)
        drift = CLOCK_DRIFTS_PPM[k % len(CLOCK_DRIFTS_PPM)]
        offset = 1000.0 * (k + 1) + 0.25
        args += ["--clock-offset", f"{offset:g}", "--clock-drift-ppm", f"{drift:g}"]
        if robot in o.faults:
            args += ["--faults", o.faults[robot]]
        self.agents[robot] = self._spawn(f"robot-{robot}", args)

    def _spawn(self, name: str, args: list[str]) -> subprocess.Popen[bytes]:
        log = open(self.logs / f"{name}.log", "ab")  # noqa: SIM115 - the child holds it
        try:
            return subprocess.Popen(_command(*args), stdout=log, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, preexec_fn=_sigint_stops)  # fmt: skip
        finally:
            log.close()

    def run(self, poll_s: float = 0.2, timeout_s: float | None = None) -> int:
        """Until the base exits: its exit code. Robots that die are started again."""
        for robot in self.options.robots:
            self._start_robot(robot)
        self._start_base()
        assert self.base is not None
        began = time.monotonic()
        try:
            while True:
                code = self.base.poll()
                if code is not None and code < 0 and self.base_restarts < self.options.restarts:
                    # killed by a signal (not an error of its own): it resumes from its checkpoint
                    self.base_restarts += 1
                    self.say(f"the base was killed ({-code}): starting it again")
                    self._start_base()
                    continue
                if code is not None:
                    break
                if timeout_s is not None and time.monotonic() - began > timeout_s:
                    self.say(f"the mission took longer than {timeout_s:g} s: stopping it")
                    code = 124
                    break
                for robot, process in list(self.agents.items()):
                    if process.poll() is None:
                        continue
                    if self.restarted[robot] >= self.options.restarts:
                        self.say(f"robot {robot} died {self.restarted[robot] + 1} times: "
                                 "stopping the mission")  # fmt: skip
                        return self._stop(3)
                    self.restarted[robot] += 1
                    self.say(f"robot {robot} exited ({process.returncode}): starting it again")
                    self._start_robot(robot)
                time.sleep(poll_s)
        except KeyboardInterrupt:
            self.say("interrupted: stopping the base and the robots (their data stays)")
            return self._stop(130)
        return self._stop(code)

    def _stop(self, code: int) -> int:
        for process in [self.base, *self.agents.values()]:
            if process is not None and process.poll() is None:
                process.send_signal(signal.SIGINT)
        deadline = time.monotonic() + 10.0
        for process in [self.base, *self.agents.values()]:
            if process is None:
                continue
            try:
                process.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        return code

    def base_log(self) -> str:
        path = self.logs / "base.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def pids(self) -> dict[str, int]:
        out = {f"robot-{r}": p.pid for r, p in self.agents.items()}
        if self.base is not None:
            out["base"] = self.base.pid
        return out
