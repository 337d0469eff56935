"""Importing a foreign bag (docs/ros.md, "Importing a bag"): ``sensor_msgs/LaserScan`` of an
LMS 2xx and odometry → a dataset folder (:mod:`estimation.app.ros.importer` runs it).

Robots are named by their scan topics' namespaces (``/a/scan`` is robot a) or by ``--robot
NAME=TOPIC``. A robot's odometry is the ``nav_msgs/Odometry`` topic beside its scan topic, else
``/tf`` ``<ns>/odom`` → ``<ns>/base_link`` (or ``base_footprint``). Each scan is encoded again
as the measured-value telegram the sensor sent (:func:`~estimation.app.ros.laser.telegram_of_scan`)
into ``robots/<robot>/lms.cap``, stamped at its header stamp, without real-time indices (so
the stamps are the measurement times); the dwells are where all robots stood still
(:func:`~estimation.app.ros.dwells.find_dwells`), and the events are the moves between them.

Stamps stay as they are when the bag starts before one day of ROS time (a mission clock:
coopmap's bags, simulated time); a wall-clock bag's first whole second becomes mission time 0.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection

from estimation import __version__
from estimation.app.config import Config, ConfigError, config_from_mapping
from estimation.app.ros.bag import bag_messages, header_stamp_ns
from estimation.app.ros.dwells import DwellRule, find_dwells, moves_and_dwells
from estimation.app.ros.laser import beam_layout, clockwise, telegram_of_scan
from estimation.errors import EstimationError
from sensors.atomic import write_text_atomic
from sensors.lms200.capture import CaptureWriter
from sensors.trajio import write_tum
from sensors.yamlio import merge_mappings

__all__ = [
    "ImportOptions",
    "ImportTally",
    "RobotImport",
    "Written",
    "connections_of",
    "import_foreign",
]

_LASER_SCAN = "sensor_msgs/msg/LaserScan"
_ODOMETRY = "nav_msgs/msg/Odometry"
_TF = "tf2_msgs/msg/TFMessage"
#: Stamps below this are a mission clock already (coopmap's bags, simulated time); above it a
#: wall clock (ROS time since 1970), whose first whole second becomes mission time 0.
_WALL_CLOCK_NS = 86_400 * 10**9


@dataclass(frozen=True)
class ImportOptions:
    """How to read a foreign bag. ``robots`` maps a robot's name to its scan topic or its
    namespace; ``starts`` gives start poses (x_m, y_m, yaw_deg); ``overrides`` is the
    configuration (``--config``) written into mission.yaml."""

    topics: tuple[str, ...] = ()
    overrides: dict[str, Any] | None = None
    robots: dict[str, str] = field(default_factory=dict)
    starts: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    reference: str | None = None
    mapper: str | None = None
    dwell: DwellRule = DwellRule()  # noqa: RUF009 - frozen, shared safely
    intensity_threshold: float = 0.5

    @property
    def foreign_only(self) -> list[str]:
        """The options a lossless import does not use (it has the bag's mission)."""
        given = {
            "--config": self.overrides,
            "--robot": self.robots,
            "--start": self.starts,
            "--reference": self.reference,
            "--mapper": self.mapper,
        }
        return [name for name, value in given.items() if value]


@dataclass(frozen=True)
class RobotImport:
    """One robot of an import: its topics and what was written of them."""

    name: str
    scan_topic: str
    odometry_topic: str
    scans: int
    capture_bytes: int
    odometry_samples: int


@dataclass(frozen=True)
class Written:
    """What one way of importing wrote into the dataset folder."""

    robots: list[RobotImport]
    events: int
    dwells: list[tuple[float, float]]
    min_dwell_s: float | None = None


def connections_of(topics: dict[str, Any], names: list[str]) -> list[Connection]:
    """The connections of the topics ``names`` (``topics``: AnyReader's topic infos)."""
    return [c for n in names for c in topics[n].connections]


def _yaw(q: Any) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def _namespace(topic: str) -> str:
    return topic.rstrip("/").rpartition("/")[0]


@dataclass
class _Robot:
    """One robot's streams as the bag is read: its capture, its odometry so far."""

    name: str
    scan_topic: str
    odometry_topic: str  # "/tf" when the odometry comes from odom → base_link transforms
    frames: tuple[str, tuple[str, ...]]  # the tf parent and children of its odometry
    writer: CaptureWriter
    flip: bool | None = None  # the beams come clockwise (None: no scan seen yet)
    scan_frame: str | None = None  # the frame of its LaserScans
    last_scan_ns: int = -1
    last_odometry_ns: int = -1
    scans: int = 0
    stamps_s: list[float] = field(default_factory=list)
    poses: list[tuple[float, float, float]] = field(default_factory=list)


@dataclass
class ImportTally:
    """What was skipped (messages, by reason) and how many beams had no usable range."""

    skipped: dict[str, int] = field(default_factory=dict)
    beams: dict[str, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def skip(self, reason: str, n: int = 1) -> None:
        self.skipped[reason] = self.skipped.get(reason, 0) + n

    def beam(self, reason: str, n: int) -> None:
        if n:
            self.beams[reason] = self.beams.get(reason, 0) + n


def _robot_name(name: str, where: str) -> str:
    if not (len(name) == 1 and "a" <= name <= "z"):
        raise ConfigError(f"{where}: a robot's name is one lowercase letter a-z, got {name!r}")
    return name


def _scan_topics(topics: dict[str, Any], options: ImportOptions) -> dict[str, str]:
    """{robot: LaserScan topic}: by ``--robot NAME=TOPIC`` (a scan topic or a namespace), else
    by each scan topic's namespace, which must be one letter."""
    scans = sorted(t for t, info in topics.items() if info.msgtype == _LASER_SCAN)
    if not scans:
        listed = ", ".join(sorted(topics)) or "none"
        raise EstimationError(f"no sensor_msgs/LaserScan topic to import (topics: {listed})")
    if not options.robots:
        found: dict[str, str] = {}
        for topic in scans:
            namespace = _namespace(topic).strip("/")
            if not namespace:
                raise ConfigError(
                    f"{topic}: no robot namespace; name the robot with --robot a={topic}"
                )
            name = _robot_name(namespace.split("/")[-1], f"{topic}'s namespace")
            if name in found:
                raise ConfigError(
                    f"{found[name]} and {topic}: two scan topics of robot {name}; "
                    "choose one with --topics or --robot"
                )
            found[name] = topic
        return dict(sorted(found.items()))
    out = {}
    for name, value in options.robots.items():
        _robot_name(name, f"--robot {name}={value}")
        if value in scans:
            out[name] = value
            continue
        namespace = "/" + value.strip("/")
        under = [t for t in scans if _namespace(t) == namespace.rstrip("/")]
        if len(under) != 1:
            raise ConfigError(
                f"--robot {name}={value}: {len(under)} LaserScan topics there "
                f"(LaserScan topics: {', '.join(scans)})"
            )
        out[name] = under[0]
    return out


def _odometry_source(topics: dict[str, Any], robot: str, scan_topic: str) -> tuple[str, str]:
    """(topic, tf prefix): the Odometry topic beside the scan topic, else ``/tf``."""
    namespace = _namespace(scan_topic)
    odometry = [
        t for t, i in topics.items() if i.msgtype == _ODOMETRY and _namespace(t) == namespace
    ]
    if len(odometry) > 1:
        raise ConfigError(
            f"robot {robot}: several nav_msgs/Odometry topics under "
            f"{namespace or '/'} ({', '.join(sorted(odometry))}): choose one with "
            "--topics"
        )
    prefix = namespace.strip("/") + "/" if namespace.strip("/") else ""
    if odometry:
        return odometry[0], prefix
    if any(i.msgtype == _TF for t, i in topics.items() if t == "/tf"):
        return "/tf", prefix
    raise EstimationError(
        f"robot {robot}: no odometry (no nav_msgs/Odometry topic under {namespace or '/'}, no /tf)"
    )


def _foreign_robots(
    topics: dict[str, Any], options: ImportOptions, work: Path, bag: Path
) -> list[_Robot]:
    """Every robot's topics (all resolved before any capture is opened) and its capture."""
    found = []
    for name, scan_topic in _scan_topics(topics, options).items():
        odometry_topic, prefix = _odometry_source(topics, name, scan_topic)
        found.append((name, scan_topic, odometry_topic, prefix))
    _check_roles(options, [name for name, *_ in found])
    robots = []
    for name, scan_topic, odometry_topic, prefix in found:
        frames = (f"{prefix}odom", (f"{prefix}base_link", f"{prefix}base_footprint"))
        header = {"robot": name, "imported_from": str(bag), "topic": scan_topic}
        writer = CaptureWriter(work / "robots" / name / "lms.cap", header)
        robots.append(_Robot(name, scan_topic, odometry_topic, frames, writer))
    return robots


def _read_foreign(
    reader: AnyReader,
    bag: Path,
    topics: dict[str, Any],
    robots: list[_Robot],
    config: Config,
    threshold: float,
    tally: ImportTally,
    statics: dict[tuple[str, str], tuple[float, float, float]],
) -> tuple[int, tuple[int, float]]:
    """Encode every robot's scans into its capture and gather its odometry and the static
    transforms (into ``statics``: (parent, child) → translation); returns the clock zero (ns)
    and the scans' variant (field of view °, resolution °)."""
    start_ns = int(reader.start_time)
    zero_ns = 0 if start_ns < _WALL_CLOCK_NS else start_ns // 10**9 * 10**9
    by_scan = {r.scan_topic: r for r in robots}
    by_odometry = {r.odometry_topic: r for r in robots if r.odometry_topic != "/tf"}
    by_frames = {
        (r.frames[0], child): r
        for r in robots
        if r.odometry_topic == "/tf"
        for child in r.frames[1]
    }
    static = (
        ["/tf_static"]
        if any(i.msgtype == _TF for t, i in topics.items() if t == "/tf_static")
        else []
    )
    names = sorted({*by_scan, *by_odometry, *(["/tf"] if by_frames else []), *static})
    by_id = {c.id: t for t in names for c in topics[t].connections}
    variant: tuple[int, float] | None = None
    for connection, log_ns, message in bag_messages(reader, connections_of(topics, names), bag):
        topic = by_id[connection.id]
        if topic == "/tf_static":
            for transform in message.transforms:
                t = transform.transform.translation
                key = (transform.header.frame_id.lstrip("/"), transform.child_frame_id.lstrip("/"))
                statics[key] = (float(t.x), float(t.y), float(t.z))
        elif topic in by_scan:
            robot = by_scan[topic]
            if robot.scan_frame is None:
                robot.scan_frame = message.header.frame_id.lstrip("/")
            if robot.flip is None:
                fov, res, robot.flip = beam_layout(message, topic)
                if variant is not None and variant != (fov, res):
                    raise EstimationError(
                        f"{topic}: {fov}°/{res}° scans, but the other robots' are "
                        f"{variant[0]}°/{variant[1]}°: one mission has one scanner variant"
                    )
                variant = (fov, res)
            elif variant is None or clockwise(message, *variant) != robot.flip:
                tally.skip("scans of another beam layout")
                continue
            ns = header_stamp_ns(message, log_ns)
            if ns <= robot.last_scan_ns:
                tally.skip("scan stamps not after the previous scan's")
                continue
            telegram, beams = telegram_of_scan(message, robot.flip, config.scanner, threshold)
            if telegram is None:
                tally.skip("scans whose intensities are not one per range")
                continue
            for reason, n in beams.items():
                tally.beam(reason, n)
            robot.last_scan_ns = ns
            robot.writer.write((ns - zero_ns) / 1e9, telegram)
            robot.scans += 1
            if not len(message.intensities) and robot.scans == 1:
                tally.notes.append(
                    f"{topic}: no intensities: no reflector bits, so no beacon can be detected"
                )
        elif topic in by_odometry:
            pose = message.pose.pose
            _add_odometry(
                by_odometry[topic],
                header_stamp_ns(message, log_ns) - zero_ns,
                pose.position,
                pose.orientation,
                tally,
            )
        else:
            for transform in message.transforms:
                key = (transform.header.frame_id.lstrip("/"), transform.child_frame_id.lstrip("/"))
                if key in by_frames:
                    t = transform.transform
                    _add_odometry(
                        by_frames[key],
                        header_stamp_ns(transform, log_ns) - zero_ns,
                        t.translation,
                        t.rotation,
                        tally,
                    )
    if variant is None:
        listed = ", ".join(r.scan_topic for r in robots)
        raise EstimationError(f"{bag}: no LaserScan message on {listed}")
    return zero_ns, variant


def _add_odometry(robot: _Robot, ns: int, position: Any, rotation: Any, tally: ImportTally) -> None:
    values = (float(position.x), float(position.y), _yaw(rotation))
    if not all(math.isfinite(v) for v in values):
        tally.skip("odometry poses that are not finite")
        return
    if ns <= robot.last_odometry_ns:
        tally.skip("odometry stamps not after the previous sample's")
        return
    robot.last_odometry_ns = ns
    robot.stamps_s.append(ns / 1e9)
    robot.poses.append(values)


def rig_from_tf(
    robots: list[_Robot], statics: dict[tuple[str, str], tuple[float, float, float]],
    tally: ImportTally,
) -> dict[str, Any]:  # fmt: skip
    """The scanner and beacon mounts the bag's ``/tf_static`` gives (``base_link`` →
    the LaserScans' frame, and → ``<robot>/beacon``) as configuration: the first robot that has
    them; a robot whose mounts differ by more than a millimetre is noted (one mission, one rig)."""
    mounts = []
    for robot in robots:
        bases = robot.frames[1]
        prefix = bases[0][: -len("base_link")]

        def mount(child: str | None, bases: tuple[str, ...] = bases) -> Any:
            if child is None:
                return None
            return next((statics[(b, child)] for b in bases if (b, child) in statics), None)

        scanner = mount(robot.scan_frame)
        if scanner is not None and all(math.isfinite(v) for v in scanner):
            beacon = mount(f"{prefix}beacon")
            if beacon is not None and not all(math.isfinite(v) for v in beacon):
                beacon = None
            mounts.append((robot.name, scanner, beacon))
    if not mounts:
        return {}
    name, scanner, beacon = mounts[0]
    for other, s, b in mounts[1:]:
        if max(abs(u - v) for u, v in zip(s, scanner, strict=True)) > 1e-3 or (b is None) != (
            beacon is None
        ) or (b is not None and beacon is not None
              and max(abs(u - v) for u, v in zip(b, beacon, strict=True)) > 1e-3):  # fmt: skip
            tally.notes.append(f"/tf_static: robot {other}'s mounts differ from robot {name}'s; "
                               f"the mission uses robot {name}'s")  # fmt: skip
    document: dict[str, Any] = {
        "robot": {"scanner_x_m": round(scanner[0], 6), "scanner_height_m": round(scanner[2], 6)}
    }
    if beacon is not None:
        document["beacon"] = {"offset_m": round(beacon[0] - scanner[0], 6),
                              "height_m": round(beacon[2], 6)}  # fmt: skip
    return document


def _foreign_config(overrides: dict[str, Any] | None, variant: tuple[int, float],
                    rig: dict[str, Any] | None = None) -> dict[str, Any]:  # fmt: skip
    """The mission's configuration: the mounts of ``/tf_static`` (``rig``) under ``overrides``
    (the user's --config wins), with the scans' variant, which it must not contradict."""
    document = merge_mappings(dict(rig or {}), dict(overrides or {}))
    scanner = document.get("scanner") or {}
    given = (
        scanner.get("field_of_view_deg", variant[0]),
        scanner.get("angular_resolution_deg", variant[1]),
    )
    if tuple(given) != variant:
        raise ConfigError(
            f"--config: scanner {given[0]}°/{given[1]}°, but the bag's scans are "
            f"{variant[0]}°/{variant[1]}°"
        )
    variant_doc = {
        "scanner": {"field_of_view_deg": variant[0], "angular_resolution_deg": variant[1]}
    }
    return merge_mappings(document, variant_doc)


def _check_roles(options: ImportOptions, robots: list[str]) -> None:
    for flag, name in (
        ("--reference", options.reference),
        ("--mapper", options.mapper),
        *(("--start", n) for n in options.starts),
    ):
        if name is not None and name not in robots:
            raise ConfigError(
                f"{flag} {name}: no robot {name} in the bag (robots: {', '.join(robots)})"
            )
    if options.reference is not None and options.reference == options.mapper:
        raise ConfigError(f"--reference and --mapper are both {options.reference}")


def import_foreign(
    reader: AnyReader,
    bag: Path,
    topics: dict[str, Any],
    options: ImportOptions,
    work: Path,
    tally: ImportTally,
) -> Written:
    """Write the dataset of a foreign bag (module docstring)."""
    config = config_from_mapping(options.overrides or {}, source="--config")
    robots = _foreign_robots(topics, options, work, bag)
    statics: dict[tuple[str, str], tuple[float, float, float]] = {}
    try:
        zero_ns, variant = _read_foreign(
            reader, bag, topics, robots, config, options.intensity_threshold, tally, statics
        )
    except BaseException:
        for robot in robots:
            robot.writer.discard()
        raise
    for robot in robots:
        robot.writer.close()
    document = _foreign_config(options.overrides, variant, rig_from_tf(robots, statics, tally))
    config = config_from_mapping(document, source="--config")
    odometry = {}
    for robot in robots:
        if robot.scans == 0:
            raise EstimationError(
                f"{robot.scan_topic}: no scan could be imported "
                f"({_listed(tally.skipped) or 'none left'})"
            )
        if len(robot.stamps_s) < 2:
            raise EstimationError(
                f"robot {robot.name}: empty odometry ({len(robot.stamps_s)} "
                f"samples on {robot.odometry_topic})"
            )
        odometry[robot.name] = (np.asarray(robot.stamps_s), np.asarray(robot.poses))
        write_tum(work / "robots" / robot.name / "odometry.tum", *odometry[robot.name])
    rule = options.dwell
    min_dwell_s = rule.min_dwell_s if rule.min_dwell_s is not None else config.mirror.period_s / 2
    dwells = find_dwells(odometry, rule, min_dwell_s)
    if not dwells:
        raise EstimationError(
            f"{bag}: no dwell found: the robots never stood still together (below "
            f"{rule.still_speed_m_s} m/s and {rule.still_turn_rate_deg_s}°/s) for "
            f"{min_dwell_s:g} s or more; see --still-speed, --still-turn-rate, --min-dwell"
        )
    events = moves_and_dwells(odometry, dwells, rule, options.reference, options.mapper)
    lines = [json.dumps(e, separators=(",", ":")) for e in events]
    write_text_atomic(work / "events.jsonl", "\n".join(lines) + "\n")
    starts = {r.name: list(options.starts.get(r.name, (0.0, 0.0, 0.0))) for r in robots}
    mission = {
        "robots": [{"name": r.name, "start": starts[r.name]} for r in robots],
        "config": document,
        "imported": {
            "bag": str(bag),
            "clock_zero_ns": zero_ns,
            "topics": {
                r.name: {"scan": r.scan_topic, "odometry": r.odometry_topic} for r in robots
            },
            "dwells": {
                "still_speed_m_s": rule.still_speed_m_s,
                "still_turn_rate_deg_s": rule.still_turn_rate_deg_s,
                "min_dwell_s": min_dwell_s,
            },
            "intensity_threshold": options.intensity_threshold,
        },
    }
    header = f"# imported from {bag.name} (LaserScan re-encoded); coopmap {__version__}\n"
    write_text_atomic(work / "mission.yaml", header + yaml.safe_dump(mission, sort_keys=False))
    out = [
        RobotImport(
            r.name, r.scan_topic, r.odometry_topic, r.scans, r.writer.bytes_written, len(r.stamps_s)
        )
        for r in robots
    ]
    return Written(out, len(events), dwells, min_dwell_s)


def _listed(counts: dict[str, int]) -> str:
    return ", ".join(f"{n:,} {why}" for why, n in counts.items())
