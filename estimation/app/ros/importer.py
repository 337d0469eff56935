"""``coopmap import BAG --out DATASET``: a ROS bag as a dataset (docs/ros.md, "Importing a bag").

Two ways in, chosen by the topics the bag holds (and ``--topics`` selects):

* **lossless** — a bag of ``coopmap export DATASET`` (``/coopmap/mission``, ``/coopmap/events``
  and each mission robot's ``/<robot>/lms_raw`` and ``/<robot>/odom``): the dataset as it was,
  the capture byte for byte, the odometry's numbers, the event lines and the mission verbatim;
* **foreign** — any ROS 1 or ROS 2 bag with ``sensor_msgs/LaserScan`` of an LMS 2xx and the
  robots' odometry (``nav_msgs/Odometry``, else ``/tf`` ``odom`` → ``base_link``): each scan is
  encoded again as the measured-value telegram the sensor sent (ranges in the configured unit,
  intensities above a threshold as reflector bits), the dwells are found where all robots
  stood still (:func:`~estimation.app.ros.dwells.find_dwells`), and the events are the moves
  between them (:mod:`estimation.app.ros.foreign`).

Bags are read with ``rosbags.highlevel.AnyReader`` (MCAP or sqlite3 ROS 2 bags, ROS 1 bags).
The dataset is built in a hidden folder beside ``--out`` and renamed into place when it is
complete and ``load_dataset`` reads it; only an earlier coopmap dataset is ever replaced.
"""

from __future__ import annotations

import contextlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader

from estimation.app.config import ConfigError
from estimation.app.dataset import load_dataset, read_robots
from estimation.app.ros.bag import bag_messages, header_stamp_ns, open_bag
from estimation.app.ros.dataset_bag import EVENTS_TOPIC, MISSION_TOPIC
from estimation.app.ros.dwells import DwellRule
from estimation.app.ros.foreign import (
    ImportOptions,
    ImportTally,
    RobotImport,
    Written,
    connections_of,
    import_foreign,
)
from estimation.errors import EstimationError
from sensors.atomic import check_replaceable, replace_directory, write_text_atomic
from sensors.errors import OutputError, SensorError
from sensors.lms200.capture import CaptureWriter
from sensors.yamlio import parse_yaml

__all__ = ["ImportOptions", "ImportSummary", "RobotImport", "import_bag"]

_ODOMETRY = "nav_msgs/msg/Odometry"
_LMS_RAW = "coopmap_msgs/msg/LmsRaw"
_STRING = "std_msgs/msg/String"


@dataclass(frozen=True)
class ImportSummary:
    """What an import wrote: per robot its topics and counts, the events and dwells (found or
    read), the thresholds of a foreign import, what was skipped (messages by reason; beams
    without a range by reason), notes, and the size of the dataset folder."""

    bag: Path
    out_dir: Path
    lossless: bool
    robots: list[RobotImport]
    events: int
    dwells: list[tuple[float, float]]
    dwell_rule: DwellRule | None
    min_dwell_s: float | None
    skipped: dict[str, int]
    beams: dict[str, int]
    notes: list[str]
    bytes_written: int


# -- output ----------------------------------------------------------------------------------


def _check_output(bag: Path, out_dir: Path) -> None:
    bag_r, out_r = bag.resolve(), out_dir.resolve()
    if out_r == bag_r or out_r in bag_r.parents:
        raise OutputError(f"{out_dir}: holds the bag {bag}; choose another --out")
    if bag_r in out_r.parents:
        raise OutputError(f"{out_dir}: lies inside the bag {bag}; choose another --out")
    check_replaceable(out_dir, "dataset")


def _folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def _tum_text(table: np.ndarray) -> str:
    """TUM lines holding exactly ``table``'s numbers (N, 8): in ``write_tum``'s layout with 6
    or 9 decimals when that keeps every number, else in the shortest exact form."""

    def fixed(v: np.ndarray, d: int) -> str:
        t, x, y, z, qx, qy, qz, qw = v
        zs = "0" if z == 0.0 and d == 9 else f"{z:.{d}f}"
        qxs, qys = ("0" if q == 0.0 else f"{q:.9f}" for q in (qx, qy))
        return f"{t:.{d}f} {x:.{d}f} {y:.{d}f} {zs} {qxs} {qys} {qz:.9f} {qw:.9f}"

    for d in (6, 9):
        rows = [fixed(v, d) for v in table]
        if all(
            [float(f) for f in row.split()] == v.tolist()
            for row, v in zip(rows, table, strict=True)
        ):
            break
    else:
        rows = [" ".join(repr(float(f)) for f in v) for v in table]
    return "# timestamp tx ty tz qx qy qz qw\n" + "".join(r + "\n" for r in rows)


def _validate(work: Path, out_dir: Path) -> None:
    try:
        load_dataset(work)
    except (ConfigError, SensorError) as exc:
        text = str(exc).replace(str(work), str(out_dir))
        raise EstimationError(f"the imported dataset is not valid: {text}") from None


# -- the lossless way: a bag coopmap wrote ---------------------------------------------------


def _mission(
    reader: AnyReader, topics: dict[str, Any], bag: Path, tally: ImportTally
) -> str | None:
    """The text of the bag's mission when the bag holds everything a lossless import needs:
    ``/coopmap/mission``, ``/coopmap/events``, and each robot's ``lms_raw`` and ``odom``."""
    if not all(t in topics and topics[t].msgtype == _STRING for t in (MISSION_TOPIC, EVENTS_TOPIC)):
        return None
    text = ""
    for _, _, message in bag_messages(reader, connections_of(topics, [MISSION_TOPIC]), bag):
        text = str(message.data)
    missing = [
        t
        for t, kind in _lossless_topics(_mission_robots(text, bag)).items()
        if t not in topics or topics[t].msgtype != kind
    ]
    if missing:
        tally.notes.append(
            f"the bag has coopmap's mission but not {', '.join(missing)}: "
            "imported from its LaserScans"
        )
        return None
    return text


def _mission_robots(text: str, bag: Path) -> list[str]:
    where = f"{bag}: {MISSION_TOPIC}"
    document = parse_yaml(text, where, EstimationError)
    if not isinstance(document, dict) or "robots" not in document:
        raise EstimationError(f"{where}: not a mission (no robots)")
    try:
        return read_robots(document["robots"], where)[0]
    except ConfigError as exc:
        raise EstimationError(str(exc)) from None


def _lossless_topics(robots: list[str]) -> dict[str, str]:
    return {
        f"/{r}/{kind}": msgtype
        for r in robots
        for kind, msgtype in (("lms_raw", _LMS_RAW), ("odom", _ODOMETRY))
    }


def _lossless(
    reader: AnyReader,
    bag: Path,
    topics: dict[str, Any],
    mission: str,
    work: Path,
    tally: ImportTally,
) -> Written:
    """Write the dataset of a coopmap bag: capture records, odometry numbers, event lines and
    mission text as the bag holds them."""
    robots = _mission_robots(mission, bag)
    names = [EVENTS_TOPIC, *_lossless_topics(robots)]
    others = sorted(t for t in topics if t.endswith("/lms_raw") and t not in names)
    if others:
        tally.notes.append(f"{', '.join(others)}: not a robot of the mission; left out")
    by_id = {c.id: t for t in names for c in topics[t].connections}
    writers: dict[str, CaptureWriter] = {}
    tables: dict[str, list[list[float]]] = {r: [] for r in robots}
    last_ns = dict.fromkeys(robots, -1)
    lines: list[str] = []
    try:
        for connection, _, message in bag_messages(reader, connections_of(topics, names), bag):
            topic = by_id[connection.id]
            robot = topic.split("/")[1]
            if topic == EVENTS_TOPIC:
                lines.append(str(message.data))
            elif topic.endswith("/lms_raw"):
                if robot not in writers:
                    writers[robot] = _capture_writer(work, robot, message, tally)
                writers[robot].write(float(message.stamp_s), bytes(message.data))
            else:
                ns = header_stamp_ns(message, 0)
                if ns < last_ns[robot]:
                    tally.skip("odometry stamps going back")
                    continue
                last_ns[robot] = ns
                p, q = message.pose.pose.position, message.pose.pose.orientation
                tables[robot].append([ns / 1e9, p.x, p.y, p.z, q.x, q.y, q.z, q.w])
    except BaseException:
        for writer in writers.values():
            writer.discard()
        raise
    out = []
    for robot in robots:
        if robot not in writers:
            raise EstimationError(f"{bag}: /{robot}/lms_raw holds no message")
        writers[robot].close()
        if not tables[robot]:
            raise EstimationError(f"{bag}: /{robot}/odom holds no message (empty odometry)")
        write_text_atomic(
            work / "robots" / robot / "odometry.tum",
            _tum_text(np.asarray(tables[robot], dtype=float)),
        )
        out.append(
            RobotImport(
                robot,
                f"/{robot}/lms_raw",
                f"/{robot}/odom",
                writers[robot].records,
                writers[robot].bytes_written,
                len(tables[robot]),
            )
        )
    write_text_atomic(work / "events.jsonl", "".join(line + "\n" for line in lines))
    write_text_atomic(work / "mission.yaml", mission)
    events = [json.loads(line) for line in lines if line.strip()]
    dwells = [(float(e["t_s"]), float(e["end_s"])) for e in events if e.get("event") == "dwell"]
    return Written(out, len(events), dwells)


def _capture_writer(work: Path, robot: str, message: Any, tally: ImportTally) -> CaptureWriter:
    """The robot's capture, with the header its first record carries."""
    header = None
    with contextlib.suppress(json.JSONDecodeError):
        header = json.loads(str(message.capture_header)) if message.capture_header else None
    if not isinstance(header, dict):
        tally.notes.append(f"/{robot}/lms_raw: the first record has no capture header")
        header = {"robot": robot}
    return CaptureWriter(work / "robots" / robot / "lms.cap", header)


# -- the command -----------------------------------------------------------------------------


def _selected(reader: AnyReader, options: ImportOptions) -> dict[str, Any]:
    topics = dict(reader.topics)
    if not options.topics:
        return topics
    absent = [t for t in options.topics if t not in topics]
    if absent:
        raise ConfigError(
            f"--topics: {', '.join(absent)} not in the bag (topics: {', '.join(sorted(topics))})"
        )
    return {t: i for t, i in topics.items() if t in options.topics}


def import_bag(
    bag: Path | str, out_dir: Path | str, options: ImportOptions | None = None
) -> ImportSummary:
    """Write the dataset of a ROS bag at ``out_dir`` (module docstring)."""
    bag, out_dir = Path(bag), Path(out_dir)
    options = options or ImportOptions()
    if not bag.exists():
        raise EstimationError(f"{bag}: no such file or folder")
    _check_output(bag, out_dir)
    reader = open_bag(bag)
    tally = ImportTally()
    try:
        topics = _selected(reader, options)
        mission = _mission(reader, topics, bag, tally)
        if mission is not None and options.foreign_only:
            raise ConfigError(
                f"{', '.join(options.foreign_only)}: only for a bag without "
                f"coopmap's mission ({MISSION_TOPIC}); to import this one's "
                "LaserScans, leave /coopmap/* out of --topics"
            )
        with replace_directory(out_dir, "dataset") as work:
            written = (
                import_foreign(reader, bag, topics, options, work, tally)
                if mission is None
                else _lossless(reader, bag, topics, mission, work, tally)
            )
            _validate(work, out_dir)
    finally:
        reader.close()
    return ImportSummary(
        bag=bag,
        out_dir=out_dir,
        lossless=mission is not None,
        robots=written.robots,
        events=written.events,
        dwells=written.dwells,
        dwell_rule=None if mission is not None else options.dwell,
        min_dwell_s=written.min_dwell_s,
        skipped=tally.skipped,
        beams=tally.beams,
        notes=tally.notes,
        bytes_written=_folder_bytes(out_dir),
    )
