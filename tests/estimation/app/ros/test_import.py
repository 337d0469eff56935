"""A dataset as a ROS bag and back (``coopmap export DATASET``, ``coopmap import``).

The proof: a small simulated mission, exported to a bag and imported again, gives ``batch`` the
same poses — exactly through coopmap's own topics (the files come back byte for byte), within
a stated tolerance through LaserScan and Odometry alone (a foreign bag, as sqlite3 ROS 2 and as
ROS 1), where the dwells are found from the odometry. The bag is also read with the independent
MCAP reader (mcap-ros2-support), and every bad input is one clear error.
"""

from __future__ import annotations

import dataclasses
import filecmp
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from estimation.app.config import ConfigError
from estimation.app.dataset import decode_robot, load_dataset
from estimation.app.pipeline import run_batch
from estimation.app.rig import scan_limits
from estimation.app.ros.dataset_bag import export_dataset
from estimation.app.ros.dwells import DwellRule, find_dwells, moves_and_dwells
from estimation.app.ros.importer import ImportOptions, import_bag
from estimation.app.sim.simulate import run_simulation
from estimation.errors import EstimationError
from sensors.errors import OutputError
from sensors.lms200.capture import CaptureReader
from sensors.lms200.protocol.scan import SpecialCode
from sensors.trajio import read_tum
from tests.estimation.app.missions import ONE_STEP_MISSION

MISSION = ONE_STEP_MISSION
ROBOTS = ("a", "b")
FOREIGN_TOPICS = ["/a/scan", "/b/scan", "/a/odom", "/b/odom"]
#: The importer finds a dwell's ends on the odometry's samples (10 Hz in the simulator): one
#: sample period is the resolution of the stop and start times.
ODOMETRY_PERIOD_S = 0.1
#: Through LaserScan the scans come back exactly (ranges to the mm, flag bits, measurement times
#: to the ns); what moves is the dwell's start, to the first odometry sample after the arrival,
#: so a sweep is cut from slightly other scans and the mirror estimated from them. Measured:
#: 0.04 mm and 0.0015°; allowed: 1 mm and 0.05°, far below the estimator's own error (~3 mm).
FOREIGN_POSE_TOLERANCE_M = 1e-3
FOREIGN_YAW_TOLERANCE_RAD = math.radians(0.05)


@dataclasses.dataclass(frozen=True)
class Mission:
    dataset: Path
    bag: Path
    config: dict[str, Any]


@pytest.fixture(scope="module")
def mission(tmp_path_factory: pytest.TempPathFactory) -> Mission:
    root = tmp_path_factory.mktemp("bag")
    (root / "small.yaml").write_text(MISSION)
    run_simulation(root / "small.yaml", root / "sim")
    run_batch(root / "sim")
    bag = root / "sim.mcap"
    export_dataset(root / "sim", bag)
    config = yaml.safe_load((root / "sim" / "mission.yaml").read_text())["config"]
    return Mission(root / "sim", bag, config)


def convert(src: Path, dst: Path, topics: list[str]) -> Path:
    """``src`` with only ``topics``, as written by rosbags' converter (a sqlite3 ROS 2 folder,
    or ROS 1 when ``dst`` ends in .bag): bags coopmap did not write."""
    from rosbags.convert.converter import convert as rosbags_convert

    rosbags_convert([src], dst, "sqlite3", 9, None, "file", None, None, [], topics, [], [])
    return dst


Change = Callable[[str, Any], Any]


def rewrite(
    src: Path, dst: Path, topics: list[str], change: Change | None = None,
    rename: dict[str, str] | None = None, shift_ns: int = 0,
) -> Path:  # fmt: skip
    """A ROS 2 MCAP bag folder of ``src``'s ``topics``, each message passed through ``change``
    (None drops it), topics renamed by ``rename`` and log times shifted by ``shift_ns``."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer

    with AnyReader([src]) as reader, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        store = reader.typestore
        out: dict[str, Any] = {}
        wanted = [c for c in reader.connections if c.topic in topics]
        for connection, t, raw in reader.messages(connections=wanted):
            message = reader.deserialize(raw, connection.msgtype)
            if change is not None:
                message = change(connection.topic, message)
            if message is None:
                continue
            topic = (rename or {}).get(connection.topic, connection.topic)
            if topic not in out:
                out[topic] = w.add_connection(topic, connection.msgtype, typestore=store)
            w.write(out[topic], t + shift_ns, store.serialize_cdr(message, connection.msgtype))
    return dst


def read_independently(path: Path) -> dict[str, list[tuple[int, Any]]]:
    """{topic: [(log time ns, decoded message)]} by mcap + mcap-ros2-support."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out: dict[str, list[tuple[int, Any]]] = {}
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            out.setdefault(channel.topic, []).append((message.log_time, decoded))
    return out


def dwells_of(dataset: Path) -> list[tuple[float, float]]:
    events = load_dataset(dataset).events
    return [(e["t_s"], e["end_s"]) for e in events if e["event"] == "dwell"]


def poses_of(dataset: Path) -> dict[str, np.ndarray]:
    return {r: read_tum(dataset / "result" / "poses" / f"{r}.tum")[1] for r in ROBOTS}


def foreign_options(mission: Mission, **changes: Any) -> ImportOptions:
    base = ImportOptions(overrides=mission.config, reference="a", mapper="b",
                         starts={"a": (2.0, 3.5, 20.0), "b": (3.5, 5.75, 220.0)})  # fmt: skip
    return dataclasses.replace(base, **changes)


# -- the dataset as a bag ------------------------------------------------------------------------


def test_the_bag_holds_every_telegram_record_sample_and_event(mission: Mission) -> None:
    messages = read_independently(mission.bag)
    config = load_dataset(mission.dataset).config
    events = [line for line in (mission.dataset / "events.jsonl").read_text().splitlines() if line]
    assert [m.data for _, m in messages["/coopmap/events"]] == events
    assert messages["/coopmap/mission"][0][1].data == (mission.dataset / "mission.yaml").read_text()
    odometry_total = 0
    for robot in ROBOTS:
        folder = mission.dataset / "robots" / robot
        records = list(CaptureReader(folder / "lms.cap").chunks())
        raw = messages[f"/{robot}/lms_raw"]
        assert len(raw) == len(records) == 916
        assert all(bytes(m.data) == chunk and m.stamp_s == stamp
                   for (_, m), (stamp, chunk) in zip(raw, records, strict=True))  # fmt: skip
        assert json.loads(raw[0][1].capture_header) == CaptureReader(folder / "lms.cap").header
        stream = decode_robot(folder / "lms.cap", 1, scan_limits(config))
        scans = messages[f"/{robot}/scan"]
        assert len(scans) == len(stream.scans) == 916
        for (log_ns, m), scan, t_s in zip(scans, stream.scans, stream.times_s, strict=True):
            assert m.header.frame_id == f"{robot}/scanner"
            assert abs(m.header.stamp.sec * 1e9 + m.header.stamp.nanosec - t_s * 1e9) <= 0.5
            assert log_ns == m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
            valid = scan.code == SpecialCode.VALID
            np.testing.assert_allclose(np.asarray(m.ranges)[valid], scan.ranges_m[valid], atol=1e-6)
            assert np.all(np.isposinf(np.asarray(m.ranges)[scan.code == SpecialCode.NO_RETURN]))
            np.testing.assert_array_equal(m.intensities, scan.flags)
        assert scans[0][1].angle_min == pytest.approx(math.radians(-50), abs=1e-6)
        assert scans[0][1].angle_increment == pytest.approx(math.radians(1.0), abs=1e-7)
        stamps, poses = read_tum(folder / "odometry.tum")
        odometry = messages[f"/{robot}/odom"]
        assert len(odometry) == len(stamps) == 733
        last = odometry[-1][1]
        assert (last.header.frame_id, last.child_frame_id) == (
            f"{robot}/odom",
            f"{robot}/base_link",
        )
        assert (last.pose.pose.position.x, last.pose.pose.position.y) == tuple(poses[-1, :2])
        odometry_total += len(stamps)
    assert len(messages["/tf"]) == odometry_total
    static = messages["/tf_static"][0][1].transforms
    assert {t.child_frame_id for t in static} == {
        f"{r}/{m}" for r in ROBOTS for m in ("scanner", "beacon")
    }
    assert len(messages) == 10


# -- back: lossless ------------------------------------------------------------------------------


def test_the_exported_bag_comes_back_byte_for_byte_with_the_same_poses(
    mission: Mission, tmp_path: Path
) -> None:
    out = tmp_path / "back"
    summary = import_bag(mission.bag, out)
    assert summary.lossless
    assert [(r.name, r.scans, r.odometry_samples) for r in summary.robots] == [
        ("a", 916, 733), ("b", 916, 733)]  # fmt: skip
    assert (summary.events, summary.dwells) == (6, dwells_of(mission.dataset))
    files = ["events.jsonl", "mission.yaml"] + [
        f"robots/{r}/{name}" for r in ROBOTS for name in ("lms.cap", "odometry.tum")]  # fmt: skip
    for name in files:
        assert filecmp.cmp(mission.dataset / name, out / name, shallow=False), name
    assert summary.bytes_written == sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    run_batch(out)
    for robot, expected in poses_of(mission.dataset).items():
        np.testing.assert_array_equal(poses_of(out)[robot], expected)  # exact, so within 1 mm


# -- back: a foreign bag (LaserScan and Odometry) ------------------------------------------------


@pytest.fixture(scope="module")
def foreign(mission: Mission, tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("foreign")
    bag = convert(mission.bag, root / "scans_db3", FOREIGN_TOPICS)
    assert sorted(p.suffix for p in bag.iterdir()) == [".db3", ".yaml"]
    import_bag(bag, root / "dataset", foreign_options(mission))
    return root / "dataset"


def test_a_foreign_bag_gives_the_dwells_of_the_mission(mission: Mission, foreign: Path) -> None:
    true, found = dwells_of(mission.dataset), dwells_of(foreign)
    assert len(found) == len(true) == 2
    np.testing.assert_allclose(np.array(found), np.array(true), atol=ODOMETRY_PERIOD_S)
    moves = [e for e in load_dataset(foreign).events if e["event"] == "move"]
    truth = [e for e in load_dataset(mission.dataset).events if e["event"] == "move"]
    assert [(m["robot"], m["to_index"]) for m in moves] == [
        (m["robot"], m["to_index"]) for m in truth
    ]
    assert moves[0]["start_s"] == pytest.approx(truth[0]["start_s"], abs=ODOMETRY_PERIOD_S)
    assert moves[0]["t_s"] == pytest.approx(truth[0]["t_s"], abs=ODOMETRY_PERIOD_S)


def test_a_foreign_bag_gives_the_scans_exactly(mission: Mission, foreign: Path) -> None:
    config = load_dataset(mission.dataset).config
    for robot in ROBOTS:
        original = decode_robot(mission.dataset / "robots" / robot / "lms.cap", 1,
                                scan_limits(config))  # fmt: skip
        imported = decode_robot(foreign / "robots" / robot / "lms.cap", 1, scan_limits(config))
        assert len(imported.scans) == len(original.scans)
        np.testing.assert_allclose(imported.times_s, original.times_s, rtol=0, atol=1e-9)
        for a, b in zip(original.scans, imported.scans, strict=True):
            np.testing.assert_array_equal(a.code, b.code)
            np.testing.assert_array_equal(a.flags, b.flags)
            np.testing.assert_array_equal(np.nan_to_num(a.ranges_m), np.nan_to_num(b.ranges_m))


def test_batch_on_a_foreign_bag_gives_the_poses(mission: Mission, foreign: Path) -> None:
    run_batch(foreign)
    for robot, expected in poses_of(mission.dataset).items():
        got = poses_of(foreign)[robot]
        assert got.shape == expected.shape
        assert np.abs(got[:, :2] - expected[:, :2]).max() < FOREIGN_POSE_TOLERANCE_M
        assert np.abs(got[:, 2] - expected[:, 2]).max() < FOREIGN_YAW_TOLERANCE_RAD


def test_the_rig_mounts_come_from_tf_static(mission: Mission, tmp_path: Path) -> None:
    def raised(topic: str, message: Any) -> Any:  # the scanner mounted 5 cm higher
        for t in message.transforms if topic == "/tf_static" else []:
            if t.child_frame_id.endswith("/scanner"):
                t.transform.translation.z += 0.05
        return message

    bag = rewrite(mission.bag, tmp_path / "tf", [*FOREIGN_TOPICS, "/tf_static"], raised)
    rig = {k: v for k, v in mission.config.items() if k not in ("robot", "beacon")}
    import_bag(bag, tmp_path / "from_tf", foreign_options(mission, overrides=rig))
    config = load_dataset(tmp_path / "from_tf").config
    robot, beacon = mission.config["robot"], mission.config["beacon"]
    assert config.robot.scanner_height_m == pytest.approx(robot["scanner_height_m"] + 0.05)
    assert config.robot.scanner_x_m == pytest.approx(robot["scanner_x_m"])
    assert config.beacon.offset_m == pytest.approx(beacon["offset_m"])
    assert config.beacon.height_m == pytest.approx(beacon["height_m"])
    # A --config that names the mounts wins over the bag's.
    import_bag(bag, tmp_path / "from_config", foreign_options(mission))
    given = load_dataset(tmp_path / "from_config").config
    assert given.robot.scanner_height_m == pytest.approx(robot["scanner_height_m"])


def test_a_ros1_bag_imports_as_the_ros2_one(
    mission: Mission, foreign: Path, tmp_path: Path
) -> None:
    bag = convert(mission.bag, tmp_path / "scans.bag", FOREIGN_TOPICS)
    import_bag(bag, tmp_path / "ros1", foreign_options(mission))
    for name in ("events.jsonl", "robots/a/odometry.tum", "robots/b/odometry.tum"):
        assert filecmp.cmp(foreign / name, tmp_path / "ros1" / name, shallow=False), name
    for robot in ROBOTS:
        records = [list(CaptureReader(d / "robots" / robot / "lms.cap").chunks())
                   for d in (foreign, tmp_path / "ros1")]  # fmt: skip
        assert records[0] == records[1]


def test_without_odometry_topics_the_odometry_comes_from_tf(
    mission: Mission, foreign: Path, tmp_path: Path
) -> None:
    bag = rewrite(mission.bag, tmp_path / "tf_only", ["/a/scan", "/b/scan", "/tf"])
    summary = import_bag(bag, tmp_path / "from_tf", foreign_options(mission))
    assert [r.odometry_topic for r in summary.robots] == ["/tf", "/tf"]
    for robot in ROBOTS:
        expected = read_tum(foreign / "robots" / robot / "odometry.tum")
        got = read_tum(tmp_path / "from_tf" / "robots" / robot / "odometry.tum")
        np.testing.assert_array_equal(got[0], expected[0])
        np.testing.assert_allclose(got[1], expected[1], atol=1e-9)
    assert dwells_of(tmp_path / "from_tf") == dwells_of(foreign)


def restamped(m: Any, shift_ns: int) -> Any:
    ns = m.header.stamp.sec * 10**9 + m.header.stamp.nanosec + shift_ns
    stamp = dataclasses.replace(m.header.stamp, sec=ns // 10**9, nanosec=ns % 10**9)
    return dataclasses.replace(m, header=dataclasses.replace(m.header, stamp=stamp))


def test_a_wall_clock_bag_starts_the_mission_at_its_first_second(
    mission: Mission, foreign: Path, tmp_path: Path
) -> None:
    shift_ns = 1_700_000_000_250_000_000  # November 2023, a quarter second past the second

    bag = rewrite(mission.bag, tmp_path / "wall", FOREIGN_TOPICS, shift_ns=shift_ns,
                  change=lambda _, m: restamped(m, shift_ns))  # fmt: skip
    import_bag(bag, tmp_path / "out", foreign_options(mission))
    imported = yaml.safe_load((tmp_path / "out" / "mission.yaml").read_text())["imported"]
    assert imported["clock_zero_ns"] == 1_700_000_000 * 10**9
    np.testing.assert_allclose(dwells_of(tmp_path / "out"), np.array(dwells_of(foreign)) + 0.25,
                               atol=1e-6)  # fmt: skip


def test_clockwise_beams_are_turned_round(mission: Mission, foreign: Path, tmp_path: Path) -> None:
    def clockwise(topic: str, m: Any) -> Any:
        if not topic.endswith("/scan"):
            return m
        return dataclasses.replace(m, angle_min=m.angle_max, angle_max=m.angle_min,
                                   angle_increment=-m.angle_increment,
                                   ranges=np.ascontiguousarray(m.ranges[::-1]),
                                   intensities=np.ascontiguousarray(m.intensities[::-1]))  # fmt: skip

    bag = rewrite(mission.bag, tmp_path / "cw", FOREIGN_TOPICS, change=clockwise)
    import_bag(bag, tmp_path / "out", foreign_options(mission))
    for robot in ROBOTS:
        records = [list(CaptureReader(d / "robots" / robot / "lms.cap").chunks())
                   for d in (foreign, tmp_path / "out")]  # fmt: skip
        assert records[0] == records[1]


def test_robots_can_be_named_by_their_topics(mission: Mission, tmp_path: Path) -> None:
    names = {"/a/scan": "/robot1/scan", "/a/odom": "/robot1/odom"}
    bag = rewrite(mission.bag, tmp_path / "named", FOREIGN_TOPICS, rename=names)
    with pytest.raises(
        ConfigError, match=r"/robot1/scan's namespace: a robot's name is one lowercase letter"
    ):
        import_bag(bag, tmp_path / "out", foreign_options(mission))
    options = foreign_options(mission, robots={"a": "/robot1", "b": "/b/scan"})
    summary = import_bag(bag, tmp_path / "out", options)
    assert [(r.name, r.scan_topic, r.odometry_topic) for r in summary.robots] == [
        ("a", "/robot1/scan", "/robot1/odom"), ("b", "/b/scan", "/b/odom")]  # fmt: skip


# -- dwells from odometry ------------------------------------------------------------------------


def still_then_moving(stops: list[tuple[float, float]], end_s: float, rate_hz: float = 10.0):
    """Odometry at ``rate_hz`` standing still in ``stops`` and driving 0.3 m/s between them."""
    t = np.arange(0.0, end_s + 1e-9, 1.0 / rate_hz)
    moving = np.ones(len(t) - 1, dtype=bool)
    for a, b in stops:
        moving[(t[:-1] >= a - 1e-9) & (t[1:] <= b + 1e-9)] = False
    x = np.concatenate([[0.0], np.cumsum(np.where(moving, 0.3 / rate_hz, 0.0))])
    return t, np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])


def test_dwells_are_where_every_robot_stands_still_long_enough() -> None:
    rule = DwellRule()
    a = still_then_moving([(0, 30), (40, 70), (80, 85)], 100)
    b = still_then_moving([(0, 25), (35, 75)], 100)
    assert find_dwells({"a": a}, rule, 20.0) == [(0.0, 30.0), (40.0, 70.0)]  # 5 s is no dwell
    assert find_dwells({"a": a, "b": b}, rule, 20.0) == [(0.0, 25.0), (40.0, 70.0)]
    assert find_dwells({"a": a, "b": b}, rule, 30.1) == []
    turning = (a[0], a[1] + np.column_stack([0 * a[0], 0 * a[0], np.radians(1.0) * a[0]]))
    assert find_dwells({"a": turning}, rule, 20.0) == []  # 1°/s is not standing still
    assert find_dwells({"a": turning}, DwellRule(still_turn_rate_deg_s=2.0), 20.0) != []


def test_moves_and_dwells_make_a_valid_event_log() -> None:
    rule = DwellRule()
    odometry = {"a": still_then_moving([(0, 30), (40, 70)], 75),
                "b": still_then_moving([(0, 35), (38, 72)], 75)}  # fmt: skip
    dwells = find_dwells(odometry, rule, 20.0)
    assert dwells == [(0.0, 30.0), (40.0, 70.0)]
    events = moves_and_dwells(odometry, dwells, rule, "a", "b")
    assert [(e["event"], e.get("robot")) for e in events] == [
        ("start", "a"), ("start", "b"), ("dwell", None), ("move", "b"), ("move", "a"),
        ("dwell", None), ("move", "a"), ("move", "b")]  # fmt: skip
    assert (events[3]["start_s"], events[3]["t_s"]) == pytest.approx((35.0, 38.0))
    assert events[5]["poses"] == {"a": 1, "b": 1}
    assert (events[2]["phase"], events[5]["phase"]) == ("start", "mapping")
    assert (events[5]["reference"], events[5]["mapper"]) == ("a", "b")


def test_dwell_thresholds_must_be_positive() -> None:
    with pytest.raises(ConfigError, match="still_speed_m_s must be > 0, got -1"):
        DwellRule(still_speed_m_s=-1.0)
    with pytest.raises(ConfigError, match="min_dwell_s must be > 0"):
        DwellRule(min_dwell_s=math.nan)


# -- bad input: one clear error ------------------------------------------------------------------


def damaged(mission: Mission, folder: Path, how: str) -> Path:
    data = bytearray(mission.bag.read_bytes())
    path = folder / f"{how}.mcap"
    if how == "truncated":
        data = data[: len(data) // 2]
    elif how == "zeroed":
        data[len(data) // 2 : len(data) // 2 + 4000] = bytes(4000)
    elif how == "text":
        data = bytearray(b"not a bag\n")
    elif how == "empty":
        data = bytearray()
    path.write_bytes(bytes(data))
    return path


@pytest.mark.parametrize(
    ("how", "pattern"),
    [
        ("truncated", r"truncated\.mcap: not a readable ROS bag \(File end magic is invalid"),
        # What the zeroed middle hits (a message, an index) depends on the bag's layout.
        ("zeroed", r"zeroed\.mcap: corrupt bag \("),
        ("text", r"text\.mcap: not a readable ROS bag \(File magic is invalid"),
        ("empty", r"empty\.mcap: not a readable ROS bag"),
    ],
)
def test_a_damaged_bag_is_one_error(
    mission: Mission, tmp_path: Path, how: str, pattern: str
) -> None:
    with pytest.raises(EstimationError, match=pattern):
        import_bag(damaged(mission, tmp_path, how), tmp_path / "out")
    assert not (tmp_path / "out").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_what_is_not_a_bag_is_one_error(tmp_path: Path) -> None:
    with pytest.raises(EstimationError, match=r"nothing\.mcap: no such file or folder"):
        import_bag(tmp_path / "nothing.mcap", tmp_path / "out")
    (tmp_path / "folder").mkdir()
    with pytest.raises(EstimationError, match=r"folder: not a ROS bag .*metadata\.yaml"):
        import_bag(tmp_path / "folder", tmp_path / "out")
    for name, reason in (("x.bag", "File magic is invalid"), ("x.db3", "file is not a database"),
                         ("x.txt", "Unrecognized storage format")):  # fmt: skip
        (tmp_path / name).write_text("garbage\n")
        with pytest.raises(EstimationError, match=f"{name}: not a readable ROS bag .*{reason}"):
            import_bag(tmp_path / name, tmp_path / "out")


def test_a_bag_without_laserscans_is_one_error(mission: Mission, tmp_path: Path) -> None:
    bag = rewrite(mission.bag, tmp_path / "odom", ["/a/odom", "/b/odom"])
    with pytest.raises(
        EstimationError,
        match=r"no sensor_msgs/LaserScan topic to import \(topics: /a/odom, /b/odom\)",
    ):
        import_bag(bag, tmp_path / "out")
    with pytest.raises(EstimationError, match="no sensor_msgs/LaserScan topic"):
        import_bag(mission.bag, tmp_path / "out", ImportOptions(topics=("/tf", "/a/odom")))


def test_nan_and_infinite_ranges_are_counted_and_sent_as_no_return(
    mission: Mission, tmp_path: Path
) -> None:
    def spoil(topic: str, m: Any) -> Any:
        if topic != "/a/scan" or m.header.stamp.nanosec % 3:
            return m
        ranges = np.array(m.ranges)
        ranges[20:25] = np.nan
        ranges[30] = -np.inf
        return dataclasses.replace(m, ranges=ranges)

    bag = rewrite(mission.bag, tmp_path / "nan", FOREIGN_TOPICS, change=spoil)
    spoilt = sum(1 for _, m in read_independently(next(bag.glob("*.mcap")))["/a/scan"]
                 if m.header.stamp.nanosec % 3 == 0)  # fmt: skip
    summary = import_bag(bag, tmp_path / "out", foreign_options(mission))
    assert spoilt > 100
    assert summary.beams["NaN or -inf"] == 6 * spoilt
    assert summary.beams["+inf (no return)"] > 0
    assert summary.skipped == {}
    config = load_dataset(tmp_path / "out").config
    stream = decode_robot(tmp_path / "out" / "robots" / "a" / "lms.cap", 1, scan_limits(config))
    no_return = sum(
        int(np.count_nonzero(s.code[20:25] == SpecialCode.NO_RETURN)) for s in stream.scans
    )
    assert no_return >= 5 * spoilt


def test_scans_whose_stamps_go_back_are_counted_and_skipped(
    mission: Mission, tmp_path: Path
) -> None:
    seen: list[Any] = []

    def replay(topic: str, m: Any) -> Any:
        if topic == "/b/scan":
            seen.append(m.header.stamp)
            if len(seen) % 100 == 0:  # every 100th scan carries the stamp of two scans before
                return dataclasses.replace(m, header=dataclasses.replace(m.header, stamp=seen[-3]))
        return m

    bag = rewrite(mission.bag, tmp_path / "back", FOREIGN_TOPICS, change=replay)
    summary = import_bag(bag, tmp_path / "out", foreign_options(mission))
    assert summary.skipped == {"scan stamps not after the previous scan's": 9}
    assert [r.scans for r in summary.robots] == [916, 907]


def test_a_scan_that_is_no_lms_variant_is_one_error(mission: Mission, tmp_path: Path) -> None:
    def shorten(topic: str, m: Any) -> Any:
        return dataclasses.replace(m, ranges=np.array(m.ranges)[:90]) if topic == "/a/scan" else m

    bag = rewrite(mission.bag, tmp_path / "short", FOREIGN_TOPICS, change=shorten)
    with pytest.raises(
        EstimationError, match=r"/a/scan: 90 beams from -50\.00° .*not an LMS 200 variant"
    ):
        import_bag(bag, tmp_path / "out", foreign_options(mission))


def test_empty_or_missing_odometry_is_one_error(mission: Mission, tmp_path: Path) -> None:
    first: set[str] = set()

    def one_sample(topic: str, m: Any) -> Any:
        if topic != "/b/odom" or topic not in first:
            first.add(topic)
            return m
        return None

    bag = rewrite(mission.bag, tmp_path / "one", FOREIGN_TOPICS, change=one_sample)
    with pytest.raises(EstimationError, match=r"robot b: empty odometry \(1 samples on /b/odom\)"):
        import_bag(bag, tmp_path / "out", foreign_options(mission))
    bag = rewrite(mission.bag, tmp_path / "none", ["/a/scan", "/b/scan", "/a/odom"])
    with pytest.raises(
        EstimationError,
        match=r"robot b: no odometry \(no nav_msgs/Odometry topic under /b, no /tf\)",
    ):
        import_bag(bag, tmp_path / "out", foreign_options(mission))


BAD_OPTIONS = {
    "start": ({"starts": {"z": (0.0, 0.0, 0.0)}},
              r"--start z: no robot z in the bag \(robots: a, b\)"),
    "reference": ({"reference": "q"}, "--reference q: no robot q in the bag"),
    "same roles": ({"mapper": "a"}, "--reference and --mapper are both a"),
    "robot name": ({"robots": {"robot": "/a/scan"}},
                   "a robot's name is one lowercase letter a-z, got 'robot'"),
    "robot topic": ({"robots": {"a": "/c"}}, r"--robot a=/c: 0 LaserScan topics there"),
    "topics": ({"topics": ("/a/scan", "/x")}, r"--topics: /x not in the bag"),
    "variant": ({"overrides": {"scanner": {"field_of_view_deg": 180}}},
                r"--config: scanner 180°/1.0°, but the bag's scans are 100°/1.0°"),
    "config key": ({"overrides": {"scanner": {"colour": 1}}}, "scanner.colour"),
    "no dwell": ({"dwell": DwellRule(min_dwell_s=40.0)},
                 r"no dwell found: .* for 40 s or more; see --still-speed"),
}  # fmt: skip


@pytest.mark.parametrize(("changes", "pattern"), BAD_OPTIONS.values(), ids=BAD_OPTIONS.keys())
def test_unknown_robots_and_bad_options_are_one_error(
    mission: Mission, foreign: Path, tmp_path: Path, changes: dict[str, Any], pattern: str
) -> None:
    with pytest.raises((ConfigError, EstimationError), match=pattern):
        import_bag(foreign.parent / "scans_db3", tmp_path / "out",
                   foreign_options(mission, **changes))  # fmt: skip
    assert not (tmp_path / "out").exists()


def test_a_lossless_import_takes_no_foreign_options(mission: Mission, tmp_path: Path) -> None:
    with pytest.raises(
        ConfigError,
        match=r"--config, --reference, --mapper: only for a bag without coopmap's mission",
    ):
        import_bag(mission.bag, tmp_path / "out", foreign_options(mission, starts={}))
    summary = import_bag(mission.bag, tmp_path / "out", foreign_options(mission, starts={},
                         topics=tuple(FOREIGN_TOPICS)))  # fmt: skip
    assert not summary.lossless


# -- output rules --------------------------------------------------------------------------------


def test_only_an_earlier_coopmap_dataset_is_replaced(mission: Mission, tmp_path: Path) -> None:
    out = tmp_path / "imported"
    import_bag(mission.bag, out)
    (out / "extra.txt").write_text("from the first import\n")
    import_bag(mission.bag, out)  # a dataset coopmap wrote: replaced whole
    assert not (out / "extra.txt").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["imported"]  # no hidden folder left
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine\n")
    with pytest.raises(OutputError, match=r"mine: holds files coopmap did not write \(notes.txt\)"):
        import_bag(mission.bag, mine)
    assert (mine / "notes.txt").read_text() == "mine\n"
    with pytest.raises(OutputError, match="exists and is not a folder"):
        import_bag(mission.bag, mine / "notes.txt")


def test_the_bag_itself_and_its_folders_are_refused(mission: Mission, tmp_path: Path) -> None:
    with pytest.raises(OutputError, match=r"holds the bag .*sim\.mcap; choose another --out"):
        import_bag(mission.bag, mission.bag)
    with pytest.raises(OutputError, match=r"holds the bag .*sim\.mcap; choose another --out"):
        import_bag(mission.bag, mission.bag.parent)
    folder = rewrite(mission.bag, tmp_path / "rosbag2", FOREIGN_TOPICS)
    with pytest.raises(OutputError, match=r"lies inside the bag"):
        import_bag(folder, folder / "dataset")
    assert mission.bag.is_file()
