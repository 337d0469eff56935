"""MCAP bags under coopmap's output rules: its own bags are replaced, nothing else is."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from estimation.app.ros.bag import BagMessage, check_mcap_replaceable, coopmap_wrote, write_mcap
from estimation.app.ros.messages import RosMessages
from sensors.errors import OutputError


def sample(ros: RosMessages, frame: str = "map") -> list[BagMessage]:
    pose = ros.pose_stamped(2_500_000_000, frame, (1.0, 2.0, 0.5))
    path = ros.path(2_500_000_000, frame, [pose])
    early = ros.tf([ros.transform(1_000_000_000, "map", "a/odom", (0.0, 0.0, 0.0))])
    return [BagMessage("/a/path", "nav_msgs/msg/Path", 2_500_000_000, path),
            BagMessage("/tf", "tf2_msgs/msg/TFMessage", 1_000_000_000, early)]  # fmt: skip


def read(path: Path) -> list[tuple[str, int, object]]:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [(c.topic, m.log_time, d) for _, c, m, d in reader.iter_decoded_messages()]


def test_a_written_bag_is_one_file_in_log_time_order_and_known_as_coopmaps(
    tmp_path: Path,
) -> None:
    ros = RosMessages()
    bag = write_mcap(tmp_path / "run.mcap", sample(ros), ros)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"]  # no folder left
    rows = read(bag)
    assert [(topic, t) for topic, t, _ in rows] == [("/tf", 1_000_000_000),
                                                    ("/a/path", 2_500_000_000)]  # fmt: skip
    assert rows[1][2].poses[0].pose.position.y == 2.0
    assert coopmap_wrote(bag)
    # Written again: the old bag is ours, so it is replaced.
    write_mcap(bag, sample(ros, "odom"), ros)
    assert read(bag)[1][2].header.frame_id == "odom"


def test_other_files_folders_and_links_are_refused(tmp_path: Path) -> None:
    ros = RosMessages()
    mine = tmp_path / "mine.mcap"
    mine.write_bytes(b"\x89MCAP0\r\nnot a bag of coopmap's")
    with pytest.raises(OutputError, match=r"mine\.mcap: exists and is not a bag coopmap wrote"):
        write_mcap(mine, sample(ros), ros)
    assert mine.read_bytes() == b"\x89MCAP0\r\nnot a bag of coopmap's"
    folder = tmp_path / "folder.mcap"
    folder.mkdir()
    with pytest.raises(OutputError, match="exists and is not a file"):
        check_mcap_replaceable(folder)
    link = tmp_path / "link.mcap"
    link.symlink_to(write_mcap(tmp_path / "real.mcap", sample(ros), ros))
    with pytest.raises(OutputError, match="is a symbolic link"):
        check_mcap_replaceable(link)
    with pytest.raises(OutputError, match=r"must end in \.mcap"):
        check_mcap_replaceable(tmp_path / "bag.db3")
    assert not coopmap_wrote(tmp_path / "absent.mcap")


def test_a_bag_another_tool_wrote_is_not_coopmaps(tmp_path: Path) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer

    ros = RosMessages()
    with Writer(tmp_path / "other", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        message = sample(ros)[0]
        connection = writer.add_connection(message.topic, message.msgtype, typestore=ros.store)
        writer.write(connection, message.stamp_ns, ros.serialize(message.message))
    other = tmp_path / "other" / "other.mcap"
    assert read(other)[0][0] == "/a/path"  # a valid bag …
    assert not coopmap_wrote(other)  # … without coopmap's mark
    truncated = tmp_path / "cut.mcap"
    truncated.write_bytes(write_mcap(tmp_path / "whole.mcap", sample(ros), ros).read_bytes()[:-9])
    assert not coopmap_wrote(truncated)


def test_a_killed_exports_leftover_folder_is_removed(tmp_path: Path) -> None:
    leftover = tmp_path / ".run.mcap.abc123"
    leftover.mkdir()
    (leftover / ".coopmap").write_text(json.dumps({"kind": "mcap", "pid": 2**22 + 1}))
    foreign = tmp_path / ".run.mcap.user"
    foreign.mkdir()
    ros = RosMessages()
    write_mcap(tmp_path / "run.mcap", sample(ros), ros)
    assert sorted(p.name for p in tmp_path.iterdir()) == [".run.mcap.user", "run.mcap"]
    assert os.stat(tmp_path / "run.mcap").st_mode & 0o044  # readable by others, as outputs are
