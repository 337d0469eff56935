"""``coopmap export DATASET --mcap OUT.mcap``: a recorded dataset as a ROS 2 bag (docs/ros.md).

Topics (frames ``<robot>/odom``, ``<robot>/base_link``, ``<robot>/scanner``,
``<robot>/beacon``; stamps are mission time):

* ``/<robot>/scan`` ``sensor_msgs/LaserScan`` — every measured-value telegram of the capture
  that the pipeline decodes, at its measurement time: ranges in metres (+inf no return, NaN
  the other special codes), intensities = the flag bits (reflector: > 0);
* ``/<robot>/lms_raw`` ``coopmap_msgs/LmsRaw`` — every capture record, its bytes and its
  receive stamp (exact), so that ``coopmap import`` rebuilds the capture byte for byte;
* ``/<robot>/odom`` ``nav_msgs/Odometry`` — every line of ``odometry.tum``, the numbers as the
  file holds them;
* ``/tf`` — ``<robot>/odom`` → ``<robot>/base_link`` at every odometry sample;
  ``/tf_static`` — scanner and beacon mounts;
* ``/coopmap/events`` ``std_msgs/String`` — each line of ``events.jsonl``, verbatim;
  ``/coopmap/mission`` ``std_msgs/String`` (latched) — the text of ``mission.yaml``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from estimation.app.config import Config, ConfigError
from estimation.app.dataset import EVENTS_LIMIT_BYTES, decode_robot, load_dataset
from estimation.app.rig import scan_limits
from estimation.app.ros.bag import BagMessage, check_mcap_replaceable, write_mcap
from estimation.app.ros.export import ExportSummary, static_tf
from estimation.app.ros.laser import range_limits, scan_angles, scan_fields, scan_timing
from estimation.app.ros.messages import RosMessages, stamp_ns
from sensors.errors import SensorError
from sensors.lms200.capture import CaptureReader
from sensors.trajio import read_tum
from sensors.yamlio import read_text_file

__all__ = [
    "EVENTS_TOPIC",
    "MISSION_TOPIC",
    "export_dataset",
    "is_dataset",
    "read_tum_table",
]

EVENTS_TOPIC = "/coopmap/events"
MISSION_TOPIC = "/coopmap/mission"
_STRING = "std_msgs/msg/String"
#: mission.yaml of any mission stays far below this.
_MISSION_LIMIT_BYTES = 64 * 2**20


def is_dataset(folder: Path | str) -> bool:
    """Whether ``folder`` looks like a dataset (mission.yaml, events.jsonl, robots/)."""
    folder = Path(folder)
    return (
        (folder / "mission.yaml").is_file()
        and (folder / "events.jsonl").is_file()
        and (folder / "robots").is_dir()
    )


def read_tum_table(path: Path) -> np.ndarray:
    """The numbers of a TUM file as it holds them, (N, 8): ``t x y z qx qy qz qw`` per row,
    including what ``read_tum`` (which checks the file: call it first) leaves out or normalises
    (z, the quaternion)."""
    rows = []
    for line in read_text_file(path, SensorError, 2**31).splitlines():
        fields = line.split()
        if fields and not fields[0].startswith("#"):
            rows.append([float(f) for f in fields])
    return np.asarray(rows, dtype=float).reshape(-1, 8)


def _text_lines(path: Path, limit: int) -> list[str]:
    return [line for line in read_text_file(path, ConfigError, limit).splitlines() if line.strip()]


def _capture_messages(
    ros: RosMessages, robot: str, capture: Path, notes: list[str]
) -> list[BagMessage]:
    reader = CaptureReader(capture)
    if not reader.is_capture:
        raise SensorError(
            f"{capture}: a plain binary dump (no capture header): a mission "
            "needs receive stamps (docs/dataset.md)"
        )
    header = json.dumps(reader.header, sort_keys=True)
    out: list[BagMessage] = []
    for stamp, chunk in reader.chunks():
        assert stamp is not None  # a capture's records are stamped
        message = ros.lms_raw(stamp, chunk, header if not out else "")
        out.append(
            BagMessage(f"/{robot}/lms_raw", "coopmap_msgs/msg/LmsRaw", stamp_ns(stamp), message)
        )
    lost = reader.truncated_bytes + reader.corrupt_bytes
    if lost:
        notes.append(
            f"{capture}: {lost:,} bytes of damaged or truncated records are not in the bag"
        )
    return out


def _scan_messages(ros: RosMessages, robot: str, capture: Path, config: Config) -> list[BagMessage]:
    """A LaserScan per scan the pipeline decodes (the plausibility rules of the configured
    scanner applied), stamped at its measurement time."""
    stream = decode_robot(capture, config.scanner.measuring_mode, scan_limits(config))
    angles, limits = scan_angles(config), range_limits(config)
    interval_s = float(np.median(np.diff(stream.times_s))) if len(stream.times_s) > 1 else 0.0
    times = scan_timing(config, interval_s)
    out = []
    for scan, t_s in zip(stream.scans, stream.times_s, strict=True):
        ranges, intensities = scan_fields(scan)
        ns = stamp_ns(float(t_s))
        message = ros.laser_scan(
            ns,
            f"{robot}/scanner",
            angles_rad=angles,
            times_s=times,
            limits_m=limits,
            ranges_m=ranges,
            intensities=intensities,
        )
        out.append(BagMessage(f"/{robot}/scan", "sensor_msgs/msg/LaserScan", ns, message))
    return out


def _odometry_messages(
    ros: RosMessages, robot: str, path: Path, notes: list[str]
) -> list[BagMessage]:
    """Odometry (the file's numbers) and ``odom`` → ``base_link`` on /tf (planar)."""
    stamps, poses = read_tum(path)
    table = read_tum_table(path)
    if not np.array_equal(np.rint(table[:, 0] * 1e9) / 1e9, table[:, 0]):
        notes.append(f"{path}: stamps finer than 1 ns are rounded to ns")
    odom, base = f"{robot}/odom", f"{robot}/base_link"
    out = []
    for row, t_s, pose in zip(table, stamps, poses, strict=True):
        ns = stamp_ns(float(t_s))
        message = ros.odometry(ns, odom, base, row[1:4], row[4:8])
        out.append(BagMessage(f"/{robot}/odom", "nav_msgs/msg/Odometry", ns, message))
        tf = ros.tf([ros.transform(ns, odom, base, pose)])
        out.append(BagMessage("/tf", "tf2_msgs/msg/TFMessage", ns, tf))
    return out


def export_dataset(dataset_dir: Path | str, mcap_path: Path | str) -> ExportSummary:
    """Write a dataset's captures (raw and as LaserScans), odometry, frames, events and mission
    as an MCAP bag (module docstring); ``coopmap import`` turns it back into the dataset."""
    check_mcap_replaceable(mcap_path)
    dataset = load_dataset(dataset_dir)
    folder = dataset.path
    ros = RosMessages()
    notes: list[str] = []
    mission = read_text_file(folder / "mission.yaml", ConfigError, _MISSION_LIMIT_BYTES)
    messages = [
        static_tf(ros, dataset.config, dataset.robots),
        BagMessage(MISSION_TOPIC, _STRING, 0, ros.string(mission), True),
    ]
    # Log times never go back, so that the events keep their file order in the bag.
    latest = 0
    for line in _text_lines(folder / "events.jsonl", EVENTS_LIMIT_BYTES):
        latest = max(latest, stamp_ns(float(json.loads(line)["t_s"])))
        messages.append(BagMessage(EVENTS_TOPIC, _STRING, latest, ros.string(line)))
    for robot in dataset.robots:
        robot_dir = folder / "robots" / robot
        messages += _capture_messages(ros, robot, robot_dir / "lms.cap", notes)
        messages += _scan_messages(ros, robot, robot_dir / "lms.cap", dataset.config)
        messages += _odometry_messages(ros, robot, robot_dir / "odometry.tum", notes)
    path = write_mcap(mcap_path, messages, ros)
    topics: dict[str, int] = {}
    for m in messages:
        topics[m.topic] = topics.get(m.topic, 0) + 1
    return ExportSummary(path, topics, notes)
