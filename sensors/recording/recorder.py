"""The robot's recorder: LMS capture, odometry, events and the clock, each written as it comes.

:class:`Recorder` owns one recording folder (``sensors.recording.folder``) and runs its pieces:
the LMS 200 read in a thread (the driver's ``tap`` writes every byte it reads, stamped on the
local clock, into the capture), the odometry reader thread, the clock exchanges (a burst at the
start, then one every ``sync_interval_s``), and the event log (operator commands or a mission
file released as the mission clock passes each event). It is a library class: ``coopmap record``
is a thin shell around it, and a robot agent can run it the same way (``start``, then ``poll``
and ``command`` until it says stop, then ``stop``).

The local clock is ``time.monotonic`` (the driver stamps with it too); clock.json relates it to
the reference clock, and also to the robot's unix time.
"""

from __future__ import annotations

import contextlib
import math
import queue
import shutil
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from sensors.errors import RecordingError, SensorError
from sensors.lms200.capture import CaptureWriter
from sensors.lms200.protocol.stream import StreamParser, Telegram
from sensors.recording.clock import ClockMapping, ClockSync
from sensors.recording.events import EventLog, MissionSchedule, OperatorLog, Reply
from sensors.recording.folder import (
    CLOCK_FORMAT,
    FORMAT,
    create_folder,
    unix_pair,
    write_json,
)
from sensors.recording.odometry import OdometryReader, OdometrySource

__all__ = ["LmsDevice", "LmsRecorder", "Recorder", "RecordingSummary", "run_recorder"]

#: How the odometry lines are stamped, and on which clock odometry.tum then is.
ODOMETRY_CLOCKS = {"arrival": "local", "monotonic": "local", "unix": "unix",
                   "reference": "reference"}  # fmt: skip


class LmsDevice(Protocol):
    """What the recorder needs of an LMS 200 driver (``sensors.lms200.driver.Lms200``)."""

    port: str
    baud_rate: int
    tap: Any

    def start(self) -> Any: ...

    def scans(self, limit: int | None = None) -> Iterator[Any]: ...

    def close(self) -> None: ...


class _StoppedError(Exception):
    """Raised from the tap to end the driver's scan loop when the recording stops."""


class LmsRecorder:
    """The LMS 200 streaming in a thread, every byte read captured with its local stamp.

    The driver's tap sees every read, whether or not the driver delivers a scan (it drops scans
    it finds implausible), so the tap also counts the measured-value telegrams and is where the
    thread learns that the recording stops.
    """

    def __init__(self, device: LmsDevice, path: Path, header: dict[str, Any]) -> None:
        self.device = device
        self.writer = CaptureWriter(path, header)
        self.device.tap = self._tap
        self.scans = 0  # delivered by the driver
        self.telegrams = 0  # measured-value telegrams in the capture
        self.error = ""
        self.info: Any = None
        self._parser = StreamParser("from_sensor")
        self._abort = False
        self._flushed = time.monotonic()
        self._thread: threading.Thread | None = None

    def _tap(self, stamp_s: float, chunk: bytes) -> None:
        self.writer.write(stamp_s, chunk)
        self.telegrams += sum(
            isinstance(e, Telegram) and e.code == 0xB0 for e in self._parser.feed(chunk)
        )
        if stamp_s - self._flushed > 1.0:
            self.writer.flush()
            self._flushed = stamp_s
        if self._abort:
            raise _StoppedError

    def start(self) -> Any:
        """The sensor's start-up (a failure is raised here), then streaming in a thread."""
        self.info = self.device.start()
        self._thread = threading.Thread(target=self._run, name="lms-recorder", daemon=True)
        self._thread.start()
        return self.info

    def _run(self) -> None:
        try:
            for _ in self.device.scans():
                self.scans += 1
        except _StoppedError:
            return
        except SensorError as exc:
            self.error = str(exc)

    @property
    def failed(self) -> bool:
        return bool(self.error)

    def close(self) -> None:
        """End the scan loop at its next read, then stop the stream and close the capture."""
        if self._thread is not None:
            self._abort = True
            self._thread.join(timeout=5.0)
            self._abort = False
        with contextlib.suppress(SensorError):
            self.device.close()
        self.writer.close()


@dataclass(frozen=True)
class RecordingSummary:
    path: Path
    robot: str
    reason: str
    error: str
    lms_telegrams: int
    lms_bytes: int
    odometry_poses: int
    odometry_malformed: int
    events: int
    clock: ClockMapping
    clock_samples: int
    clock_lost: int


class Recorder:
    """One robot's recording (see the module docstring)."""

    def __init__(
        self,
        out_dir: Path | str,
        robot: str,
        *,
        lms: LmsDevice | None = None,
        odometry: OdometrySource | None = None,
        odometry_clock: str = "arrival",
        clock: ClockSync | None = None,
        clock_offset_s: float | None = None,
        mission_events: list[dict[str, Any]] | None = None,
        mission_file: str = "",
        robots: list[str] | None = None,
        mission_start_ref_s: float | None = None,
        until_mission_s: float | None = None,
        sync_interval_s: float = 1.0,
        header: dict[str, Any] | None = None,
    ) -> None:
        if (clock is None) == (clock_offset_s is None):
            raise RecordingError("give either a clock server or a clock offset, not both")
        if odometry_clock not in ODOMETRY_CLOCKS:
            raise RecordingError(
                f"odometry clock must be one of {', '.join(ODOMETRY_CLOCKS)}, "
                f"got {odometry_clock!r}"
            )
        if mission_events is not None and mission_start_ref_s is None:
            mission_start_ref_s = 0.0
        self.path = Path(out_dir)
        self.robot = robot
        self.clock = clock
        self.clock_offset_s = clock_offset_s
        self.odometry_clock = odometry_clock
        self.sync_interval_s = sync_interval_s
        self.mission_start_ref_s = mission_start_ref_s
        self._given_start = mission_start_ref_s
        self.schedule = MissionSchedule(mission_events) if mission_events is not None else None
        self.until_mission_s = until_mission_s
        if self.schedule is not None and until_mission_s is None:
            self.until_mission_s = self.schedule.last_s + 1.0
        self.operator = OperatorLog(robot, list(robots or [robot]))
        self._lms_device = lms
        self._odometry_source = odometry
        self.lms: LmsRecorder | None = None
        self.odometry: OdometryReader | None = None
        self.events: EventLog | None = None
        self._meta: dict[str, Any] = {
            "format": FORMAT,
            "version": 1,
            "robot": robot,
            "robots": self.operator.robots,
            "local_clock": "monotonic",
            "mission_start_ref_s": mission_start_ref_s,
            "events": {"source": mission_file or "operator",
                       "clock": "mission" if mission_events is not None else "local"},
            **(header or {}),
        }  # fmt: skip
        self._pairs: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._sync_thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._started = False
        self.error = ""

    # ---------------------------------------------------------------------------------------
    # Life cycle

    def start(self) -> None:
        """Create the folder, map the clock, start the LMS and the odometry; a failure of any of
        them is raised, with what was created closed again."""
        create_folder(self.path)
        self._pairs.append(unix_pair())
        self._meta["state"] = "recording"
        self._meta["started_unix_s"] = self._pairs[0][1]
        write_json(self.path / "recording.json", self._meta)
        self.events = EventLog(self.path / "events.jsonl")
        self._started = True
        try:
            if self.clock is not None:
                self.clock.burst()
            self._write_clock(final=False)
            if self._lms_device is not None:
                device = self._lms_device
                header = {"robot": self.robot, "port": device.port,
                          "baud_rate": device.baud_rate, "clock": "local monotonic"}  # fmt: skip
                self.lms = LmsRecorder(device, self.path / "lms.cap", header)
                info = self.lms.start()
                self._meta["lms"] = {"port": device.port, "baud_rate": device.baud_rate,
                                     "type": getattr(info, "type_text", "")}  # fmt: skip
            if self._odometry_source is not None:
                stamped = "arrival" if self.odometry_clock == "arrival" else "source"
                self.odometry = OdometryReader(
                    self._odometry_source, self.path / "odometry.tum",
                    self.path / "odometry.lines", clock=stamped,
                )  # fmt: skip
                self._meta["odometry"] = {
                    "source": self._odometry_source.name,
                    "stamped": self.odometry_clock,
                    "clock": ODOMETRY_CLOCKS[self.odometry_clock],
                }
                self.odometry.start()
        except BaseException:
            self._abort()
            raise
        write_json(self.path / "recording.json", self._meta)
        if self.clock is not None:
            self._sync_thread = threading.Thread(target=self._sync, name="clock-sync", daemon=True)
            self._sync_thread.start()

    def _sync(self) -> None:
        assert self.clock is not None
        count = 0
        while not self._stop.wait(self.sync_interval_s):
            self.clock.sample()
            count += 1
            if count % 10 == 0:
                self._write_clock(final=False)

    def mapping(self) -> ClockMapping:
        """The local → reference mapping so far."""
        if self.clock is not None:
            return self.clock.mapping()
        assert self.clock_offset_s is not None
        monotonic, unix = self._pairs[0]
        return ClockMapping(offset_s=unix - monotonic + self.clock_offset_s, source="given")

    def reference_now(self) -> float:
        return float(self.mapping().to_reference(time.monotonic()))

    def mission_now(self) -> float | None:
        """The mission clock now, once its zero is known (given, or the operator's ``start``)."""
        if self.mission_start_ref_s is None:
            return None
        return self.reference_now() - self.mission_start_ref_s

    # ---------------------------------------------------------------------------------------
    # Events

    def command(self, line: str) -> Reply:
        """One operator command, stamped now on the local clock."""
        if self.schedule is not None:
            return Reply(False, "events come from the mission file; only 'quit' is accepted")
        reply = self.operator.command(line, time.monotonic())
        self._log(reply.events)
        if reply.ok and line.split()[:1] == ["start"] and self.mission_start_ref_s is None:
            self.mission_start_ref_s = float(self.mapping().to_reference(reply.events[0]["t_s"]))
        return reply

    def _log(self, events: tuple[dict[str, Any], ...] | list[dict[str, Any]]) -> None:
        with self._lock:
            if self.events is not None:
                for event in events:
                    self.events.write(event)

    def poll(self) -> str | None:
        """Release due mission events; the reason to stop, when there is one."""
        if self.lms is not None and self.lms.failed:
            return f"LMS failed: {self.lms.error}"
        now = self.mission_now()
        if now is None:
            return None
        if self.schedule is not None:
            self._log(self.schedule.due(now))
        if self.until_mission_s is not None and now >= self.until_mission_s:
            return f"mission time {self.until_mission_s:g} s reached"
        return None

    # ---------------------------------------------------------------------------------------
    # Stop

    def _write_clock(self, *, final: bool) -> None:
        document: dict[str, Any] = {
            "format": CLOCK_FORMAT,
            "version": 1,
            "final": final,
            "local_clock": "monotonic",
            "unix_pairs": [list(p) for p in self._pairs],
        }
        if self.clock is not None:
            samples = self.clock.snapshot()
            document.update(
                reference=f"server {self.clock.endpoint}",
                samples=[s.as_list() for s in samples],
                lost=self.clock.lost,
            )
        else:
            document.update(reference="given", clock_offset_s=self.clock_offset_s, samples=[])
        if self.clock is None or self.clock.samples:
            document["mapping"] = self.mapping().as_dict()
        write_json(self.path / "clock.json", document)

    def _abort(self) -> None:
        """A start that failed leaves nothing behind: the folder was created by this start."""
        self._stop.set()
        for close in (self.lms.close if self.lms else None,
                      self.odometry.close if self.odometry else None,
                      self.events.close if self.events else None,
                      self.clock.close if self.clock else None):  # fmt: skip
            if close is not None:
                with contextlib.suppress(Exception):
                    close()
        shutil.rmtree(self.path, ignore_errors=True)
        self._started = False

    def stop(self, reason: str, error: str = "") -> RecordingSummary:
        """Stop every piece, publish the files under their names, write how it ended."""
        self._stop.set()
        if self._sync_thread is not None:
            self._sync_thread.join(timeout=2.0)
        errors = [error] if error else []
        if self.lms is not None:
            if self.lms.error:
                errors.append(self.lms.error)
            self.lms.close()
            self._meta.setdefault("lms", {}).update(
                telegrams=self.lms.telegrams,
                scans_delivered=self.lms.scans,
                bytes=self.lms.writer.bytes_written,
            )
        if self.odometry is not None:
            counts = self.odometry.close()
            self._meta.setdefault("odometry", {}).update(counts.__dict__)
        with self._lock:
            if self.events is not None:
                self._meta["events"]["count"] = self.events.events
                self.events.close()
        if self.clock is not None:
            with contextlib.suppress(SensorError):
                self.clock.sample()  # one more at the end: the drift over the whole recording
        self._pairs.append(unix_pair())
        with contextlib.suppress(SensorError):
            self._write_clock(final=True)
        if self.clock is not None:
            self.clock.close()
        self.error = "; ".join(errors)
        self._meta.update(
            state="failed" if self.error else "complete",
            stopped_unix_s=self._pairs[-1][1],
            stop_reason=reason,
            error=self.error,
        )
        if self._started:
            write_json(self.path / "recording.json", self._meta)
        mapping = self.mapping() if (self.clock is None or self.clock.samples) else None
        return RecordingSummary(
            path=self.path,
            robot=self.robot,
            reason=reason,
            error=self.error,
            lms_telegrams=self.lms.telegrams if self.lms else 0,
            lms_bytes=self.lms.writer.bytes_written if self.lms else 0,
            odometry_poses=self.odometry.counts.poses if self.odometry else 0,
            odometry_malformed=self.odometry.counts.malformed if self.odometry else 0,
            events=self._meta["events"].get("count", 0),
            clock=mapping or ClockMapping(offset_s=0.0, source="none"),
            clock_samples=len(self.clock.samples) if self.clock else 0,
            clock_lost=self.clock.lost if self.clock else 0,
        )


def run_recorder(
    recorder: Recorder,
    *,
    lines: queue.Queue[str | None] | None = None,
    seconds: float = 0.0,
    answer: Callable[[Reply], None] | None = None,
    poll_s: float = 0.05,
) -> RecordingSummary:
    """Run a started recorder until it says stop, ``seconds`` pass, an operator types ``quit``
    (or ``lines`` yields None: the prompt closed), or KeyboardInterrupt; then stop it."""
    deadline = time.monotonic() + seconds if seconds > 0 else math.inf
    reason: str | None = None
    try:
        while reason is None:
            while lines is not None and reason is None:
                try:
                    line = lines.get_nowait()
                except queue.Empty:
                    break
                if line is None:
                    reason = "the operator prompt closed"
                    break
                reply = (
                    recorder.command(line)
                    if line.strip() != "quit"
                    else Reply(True, "stopping", quit=True)
                )
                if answer is not None and (reply.message or not reply.ok):
                    answer(reply)
                if reply.quit:
                    reason = "quit"
            reason = reason or recorder.poll()
            if reason is None and time.monotonic() >= deadline:
                reason = f"{seconds:g} s elapsed"
            if reason is None:
                time.sleep(poll_s)
    except KeyboardInterrupt:
        reason = "interrupted"
    return recorder.stop(reason)
