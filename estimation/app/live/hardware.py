"""A robot on real hardware as its agent runs it: ``coopmap robot --port --odometry --drive``.

The LMS 200 is read by the real driver (``sensors.lms200.driver.Lms200``: a serial device, or
any URL pyserial opens) in a thread; its tap stamps every read on the robot's clock
(``time.monotonic``). Odometry lines come from the robot base's stream
(``sensors.recording.odometry``), stamped on arrival on the same clock. Goals go to the base
over the goal protocol (``sensors.recording.drive``). Nothing of the mission's motion is
simulated: the robot executes its own goals, dwells by standing still for a full sweep on the
wall clock, and between commands the agent cuts what it recorded into time slices, writes them
to its disk and publishes them. A sensor that stops talking is started again (the driver's
whole start-up sequence); the gap is what the capture lacks.

Frames. A goal comes in the map frame with the pose the base's estimate gives the robot
(``believed``); the robot drives the same relative motion from where its odometry stood at the
end of its last command (its *anchor*): ``goal_odom = anchor ∘ (believed⁻¹ ∘ goal)``. An absolute
goal (an explicit plan: no belief) is taken relative to the mission's declared start pose, where
the odometry stood when the mission's first command came.

A robot that moved while a goal failed (a blocked path, a timeout) has a new pose: its index
goes up all the same, so the mission knows it stands somewhere new.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from estimation.app.config import Config
from estimation.app.live.wire import WireError
from estimation.app.rig import dwell_seconds
from sensors.errors import DeviceError
from sensors.geometry import se2
from sensors.recording.drive import DriveClient
from sensors.recording.odometry import OdometryReader, OdometrySource
from sensors.recording.recorder import LmsDevice

__all__ = ["HardwareRobot", "parse_goal"]

#: How far a robot must have moved during a failed goal to count as standing somewhere new.
MOVED_M, MOVED_RAD = 0.01, math.radians(0.5)


def parse_goal(args: dict[str, Any]) -> tuple[str, np.ndarray, list[np.ndarray], np.ndarray | None]:
    """A move command's (robot, goal pose, path waypoints, believed pose), map frame."""
    try:
        pose = np.array([float(v) for v in args["pose"]], dtype=float)
        path = [np.array([float(p[0]), float(p[1])]) for p in args.get("path") or []]
        believed = args.get("believed")
        belief = None if believed is None else np.array([float(v) for v in believed])
        robot = str(args["robot"])
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise WireError(f"move command: bad goal ({exc})") from None
    values = [pose, *path] + ([belief] if belief is not None else [])
    if (
        pose.shape != (3,)
        or (belief is not None and belief.shape != (3,))
        or not all(np.all(np.isfinite(v)) for v in values)
    ):
        raise WireError("move command: a goal needs finite x, y, yaw (and a finite belief)")
    return robot, pose, path, belief


class HardwareRobot:
    """The robot's sensors and base behind the agent (see the module's docstring)."""

    #: The agent publishes what this robot recorded between commands, in time slices.
    streaming = True

    def __init__(self, config: Config, robot: str, start_pose: np.ndarray, lms: LmsDevice,
                 odometry: OdometrySource, drive: DriveClient, *,
                 clock: Callable[[], float] = time.monotonic, move_timeout_s: float = 600.0,
                 odometry_wait_s: float = 5.0, restart_wait_s: float = 1.0) -> None:  # fmt: skip
        self.config, self.robot = config, robot
        self.start_pose = np.asarray(start_pose, dtype=float)
        self.lms, self.drive, self.clock = lms, drive, clock
        self.move_timeout_s, self.odometry_wait_s = move_timeout_s, odometry_wait_s
        self.restart_wait_s = restart_wait_s
        self.odometry = OdometryReader(odometry, None, None, clock="arrival", local_clock=clock,
                                       on_pose=self._on_pose)  # fmt: skip
        self._lock = threading.Condition()
        self._records: list[tuple[float, bytes]] = []
        self._odometry: list[tuple[float, float, float, float]] = []
        self._latest: tuple[float, np.ndarray] | None = None
        self._recording = False
        self._index = 0
        self._goal_id = 0
        self._anchor: np.ndarray | None = None
        self._origin: np.ndarray | None = None
        self._halt = threading.Event()
        self._reader: threading.Thread | None = None
        self.lms_error: str | None = None
        self.lms_restarts = 0
        self.scans_read = 0

    # -- sensors -------------------------------------------------------------------------------

    def start_sensors(self) -> None:
        """Odometry and drive links first (a one-line error when either cannot be reached), then
        the LMS 200's start-up sequence and its stream, in a thread."""
        if self._reader is not None:
            return
        self.odometry.start()
        self.drive.connect()
        self.lms.tap = self._tap
        self.lms.start()
        self._reader = threading.Thread(target=self._read_lms, name="lms-driver", daemon=True)
        self._reader.start()

    def _read_lms(self) -> None:
        while not self._halt.is_set():
            try:
                for _ in self.lms.scans():
                    self.scans_read += 1
                    if self._halt.is_set():
                        return
            except DeviceError as exc:
                self.lms_error = str(exc)
            if self._halt.wait(self.restart_wait_s):
                return
            try:
                self.lms.close()
                self.lms.start()
                self.lms_restarts += 1
            except DeviceError as exc:
                self.lms_error = str(exc)

    def _tap(self, stamp_s: float, data: bytes) -> None:
        with self._lock:
            if self._recording:
                self._records.append((stamp_s, data))

    def _on_pose(self, t_s: float, x_m: float, y_m: float, yaw_rad: float) -> None:
        with self._lock:
            if self._recording:
                self._odometry.append((t_s, x_m, y_m, yaw_rad))
            self._latest = (t_s, np.array([x_m, y_m, yaw_rad]))
            self._lock.notify_all()

    def _odometry_after(self, t_s: float) -> np.ndarray:
        """The first odometry pose stamped after ``t_s`` (waits for it)."""
        deadline = time.monotonic() + self.odometry_wait_s
        with self._lock:
            while self._latest is None or self._latest[0] <= t_s:
                left = deadline - time.monotonic()
                if left <= 0 or self._halt.is_set():
                    source, wait = self.odometry.source.name, self.odometry_wait_s
                    raise WireError(f"robot {self.robot}: no odometry from {source} "
                                    f"for {wait:g} s")  # fmt: skip
                self._lock.wait(left)
            return self._latest[1].copy()

    # -- the agent's interface -----------------------------------------------------------------

    @property
    def now_s(self) -> float:
        return self.clock()

    def local(self, t_s: float | np.ndarray) -> Any:
        return t_s  # stamps are on the robot's clock already

    def index(self, robot: str) -> int:
        return self._index

    def apply(self, op: str, args: dict[str, Any]) -> dict[str, Any]:
        """Carry out one command on the robot; the reply's fields."""
        if self._origin is None:  # the mission's first command: its recording begins
            with self._lock:
                self._recording = True
            self._origin = self._anchor = self._odometry_after(-math.inf)
        if op == "move":
            return self._move(args)
        if op == "dwell":
            self._halt.wait(dwell_seconds(self.config))
            self._anchor = self._odometry_after(self.clock() - 1.0)
            return {"ok": True}
        if op == "change":
            raise WireError("a mission's changes step moves a simulated world's objects; a real "
                            "robot cannot")  # fmt: skip
        if op == "end":
            return {"ok": True, "files": {}}
        raise WireError(f"unknown command {op!r}")

    def _move(self, args: dict[str, Any]) -> dict[str, Any]:
        robot, pose, path, believed = parse_goal(args)
        if robot != self.robot:
            return {"ok": True, "index": self._index, "reason": None}  # another robot drives
        anchor = self._anchor if believed is not None else self._origin
        reference = believed if believed is not None else self.start_pose
        assert anchor is not None

        def in_odometry(p: np.ndarray) -> np.ndarray:
            return se2.compose(anchor, se2.between(reference, p))

        target = in_odometry(pose)
        waypoints = [in_odometry(np.array([p[0], p[1], 0.0]))[:2] for p in path]
        self._goal_id += 1
        result = self.drive.go(
            self._goal_id, (float(target[0]), float(target[1]), float(target[2])),
            [(float(w[0]), float(w[1])) for w in waypoints], self.move_timeout_s, self._halt,
        )  # fmt: skip
        before, now = self._anchor, self._odometry_after(self.clock())
        assert before is not None
        step = se2.between(before, now)
        self._anchor = now
        if result.ok or math.hypot(step[0], step[1]) > MOVED_M or abs(step[2]) > MOVED_RAD:
            self._index += 1
        return {"ok": result.ok, "index": self._index, "reason": result.reason}

    def recorded(self) -> tuple[list[tuple[float, bytes]], np.ndarray, np.ndarray]:
        """The LMS records and odometry since the last call (robot clock)."""
        with self._lock:
            records, self._records = self._records, []
            rows, self._odometry = self._odometry, []
        table = np.array(rows, dtype=float).reshape(-1, 4)
        return records, table[:, 0], table[:, 1:]

    def state(self) -> dict[str, Any]:
        """What a restarted agent takes back: the pose index, the goal counter, the anchors."""
        return {
            "index": self._index, "goal_id": self._goal_id,
            "anchor": None if self._anchor is None else self._anchor.tolist(),
            "origin": None if self._origin is None else self._origin.tolist(),
        }  # fmt: skip

    def replay(self, log: list[dict[str, Any]]) -> None:
        """A restarted agent: the state after the last executed command (the robot itself did
        not forget where it drove; its odometry goes on)."""
        if not log:
            return
        state = log[-1]["state"]
        self._index, self._goal_id = int(state["index"]), int(state["goal_id"])
        for name in ("anchor", "origin"):
            value = state.get(name)
            setattr(self, f"_{name}", None if value is None else np.array(value, dtype=float))
        with self._lock:
            self._recording = self._origin is not None

    def close(self) -> None:
        self._halt.set()
        if self._reader is not None:
            self._reader.join(timeout=2.0)  # it leaves the stream after the next scan
        with contextlib.suppress(DeviceError):
            self.lms.close()  # ends the sensor's continuous output first
        self.odometry.close()
        self.drive.close()

    def links(self) -> dict[str, Any]:
        """The state of the robot's links, for its info query and log."""
        counts = self.drive.counts
        return {
            "lms": {"port": self.lms.port, "scans": self.scans_read,
                    "restarts": self.lms_restarts, "last_error": self.lms_error},
            "odometry": {"source": self.odometry.source.name, "poses": self.odometry.counts.poses,
                         "malformed": self.odometry.counts.malformed,
                         "reconnects": self.odometry.counts.reconnects},
            "drive": {"endpoint": self.drive.name, "goals": counts.goals,
                      "arrived": counts.arrived, "failed": counts.failed,
                      "ignored_lines": counts.ignored_lines},
        }  # fmt: skip
