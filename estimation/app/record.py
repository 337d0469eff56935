"""``coopmap record``: the configuration → a robot's recorder (docs/recording.md).

The recorder itself (``sensors.recording.recorder``) takes explicit pieces; this module builds
them from the configuration and the command's options: the LMS 200 driver as ``lms record``
sets it up (``rig.driver_from_config``), the odometry source, the clock exchange or a given
offset, and the mission file or the operator prompt.
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from estimation.app.config import Config
from estimation.app.rig import driver_from_config
from sensors.errors import RecordingError
from sensors.recording.clock import ClockSync, parse_endpoint
from sensors.recording.events import read_events_file
from sensors.recording.odometry import open_source
from sensors.recording.recorder import Recorder

__all__ = ["RecordOptions", "build_recorder", "prompt_lines"]


@dataclass(frozen=True)
class RecordOptions:
    """What ``coopmap record`` was asked (units in the names; times in seconds)."""

    robot: str
    out_dir: Path
    lms_port: str | None = None
    odometry: str | None = None
    odometry_clock: str = "arrival"
    clock_server: str | None = None
    clock_offset_s: float | None = None
    events_file: Path | None = None
    robots: tuple[str, ...] = ()
    mission_start_ref_s: float | None = None
    until_mission_s: float | None = None
    sync_interval_s: float = 1.0
    clock_timeout_s: float = 0.2


def build_recorder(config: Config, options: RecordOptions) -> Recorder:
    """The recorder for ``options``, with the LMS driver set up from ``config``."""
    robot = options.robot
    if not (len(robot) == 1 and "a" <= robot <= "z"):
        raise RecordingError(f"--robot must be one lowercase letter, got {robot!r}")
    bad = [r for r in options.robots if not (len(r) == 1 and "a" <= r <= "z")]
    if bad:
        raise RecordingError(f"--robots: names are one lowercase letter, got {bad}")
    if (options.clock_server is None) == (options.clock_offset_s is None):
        raise RecordingError(
            "give --clock-server HOST:PORT (a clock exchange) or --clock-offset SECONDS "
            "(reference = this robot's unix time + offset)"
        )
    if options.sync_interval_s <= 0:
        raise RecordingError(f"--sync-interval must be > 0, got {options.sync_interval_s}")
    events = read_events_file(options.events_file) if options.events_file is not None else None
    odometry = open_source(options.odometry) if options.odometry else None
    server = parse_endpoint(options.clock_server) if options.clock_server is not None else None
    clock = ClockSync(server, timeout_s=options.clock_timeout_s) if server is not None else None
    return Recorder(
        options.out_dir,
        robot,
        lms=driver_from_config(config, options.lms_port) if options.lms_port else None,
        odometry=odometry,
        odometry_clock=options.odometry_clock,
        clock=clock,
        clock_offset_s=options.clock_offset_s,
        mission_events=events,
        mission_file=str(options.events_file or ""),
        robots=list(options.robots) or [robot],
        mission_start_ref_s=options.mission_start_ref_s,
        until_mission_s=options.until_mission_s,
        sync_interval_s=options.sync_interval_s,
    )


def prompt_lines(stream: TextIO) -> queue.Queue[str | None]:
    """Lines typed on ``stream``, read in a thread; None when it closes."""
    lines: queue.Queue[str | None] = queue.Queue()

    def read() -> None:
        for line in stream:
            lines.put(line.strip())
        lines.put(None)

    threading.Thread(target=read, name="operator-prompt", daemon=True).start()
    return lines
