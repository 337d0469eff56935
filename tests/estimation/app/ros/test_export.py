"""``coopmap export``: every topic of the bag read back with an independent MCAP/ROS 2 decoder
(mcap-ros2-support) and compared with map.npz, the TUM poses and the dataset's odometry."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from estimation.app.cli.main import app
from estimation.app.config import load_config
from estimation.app.pipeline import run_batch
from estimation.app.ros.export import export_result
from mapping.band import extract_band
from mapping.formats.npz import load_map
from mapping.formats.octomap_bt import tree_stream
from mapping.grid import OccupancyGrid
from sensors.geometry import se2
from sensors.trajio import read_tum
from tests.estimation.app.missions import copy_of

Messages = dict[str, list[tuple[int, str, Any]]]


@pytest.fixture(scope="module")
def exported(
    tmp_path_factory: pytest.TempPathFactory, essex_simulated: Path
) -> tuple[Path, Path, Messages]:
    dataset = copy_of(essex_simulated, tmp_path_factory, "ros")
    run_batch(dataset, figures=False)
    bag = dataset.parent / "essex.mcap"
    export_result(dataset / "result", bag)
    return dataset, bag, read_bag(bag)


def read_bag(path: Path) -> Messages:
    """{topic: [(log time ns, schema name, decoded message)]} in log-time order."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out: Messages = {}
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            assert schema is not None
            assert schema.encoding == "ros2msg"
            assert channel.message_encoding == "cdr"
            out.setdefault(channel.topic, []).append((message.log_time, schema.name, decoded))
    return out


def ns(stamp: Any) -> int:
    return int(stamp.sec) * 10**9 + int(stamp.nanosec)


def yaw(q: Any) -> float:
    assert abs(q.x) < 1e-12
    assert abs(q.y) < 1e-12
    assert math.hypot(q.z, q.w) == pytest.approx(1.0, abs=1e-12)
    return 2 * math.atan2(q.z, q.w)


def planar(pose: Any) -> np.ndarray:
    return np.array([pose.position.x, pose.position.y, yaw(pose.orientation)])


def transforms(messages: Messages) -> Iterator[tuple[int, Any]]:
    for log_ns, _, message in messages["/tf"]:
        for t in message.transforms:
            yield log_ns, t


def test_topics_types_and_counts(exported: tuple[Path, Path, Messages]) -> None:
    dataset, _, messages = exported
    poses = {r: len(read_tum(dataset / "result" / "poses" / f"{r}.tum")[0]) for r in "ab"}
    odometry = {r: len(read_tum(dataset / "robots" / r / "odometry.tum")[0]) for r in "ab"}
    types = {topic: {name for _, name, _ in rows} for topic, rows in messages.items()}
    assert types == {
        "/map": {"nav_msgs/msg/OccupancyGrid"},
        "/map/points": {"sensor_msgs/msg/PointCloud2"},
        "/map/voxels": {"foxglove_msgs/msg/VoxelGrid"},
        "/octomap_binary": {"octomap_msgs/msg/Octomap"},
        "/a/path": {"nav_msgs/msg/Path"},
        "/b/path": {"nav_msgs/msg/Path"},
        "/a/pose": {"geometry_msgs/msg/PoseWithCovarianceStamped"},
        "/b/pose": {"geometry_msgs/msg/PoseWithCovarianceStamped"},
        "/tf": {"tf2_msgs/msg/TFMessage"},
        "/tf_static": {"tf2_msgs/msg/TFMessage"},
        "/markers": {"visualization_msgs/msg/MarkerArray"},
    }
    counts = {topic: len(rows) for topic, rows in messages.items()}
    assert counts["/tf"] == sum(poses.values()) + sum(odometry.values())
    for r in "ab":
        assert counts[f"/{r}/path"] == counts[f"/{r}/pose"] == poses[r]
    for topic in ("/map", "/map/points", "/map/voxels", "/octomap_binary", "/markers",
                  "/tf_static"):  # fmt: skip
        assert counts[topic] == 1
    # Every header is stamped with its log time (mission time in ROS time).
    for topic, rows in messages.items():
        if topic not in ("/tf", "/tf_static", "/markers", "/map/voxels"):
            assert all(ns(m.header.stamp) == t for t, _, m in rows), topic
    assert ns(messages["/map/voxels"][0][2].timestamp) == messages["/map/voxels"][0][0]
    end = messages["/map"][0][0]
    assert end == round(max(read_tum(dataset / "robots" / r / "odometry.tum")[0][-1]
                            for r in "ab") * 1e9)  # fmt: skip


def test_map_is_the_ceiling_band_with_unknown_cells_at_minus_one(
    exported: tuple[Path, Path, Messages],
) -> None:
    dataset, _, messages = exported
    check_ceiling_band(messages["/map"][0][2], dataset / "result")


def check_ceiling_band(grid: Any, result: Path) -> None:
    """``grid`` (a decoded ``nav_msgs/OccupancyGrid``) is the result's ceiling band."""
    config = load_config(result / "config.yaml")
    band = extract_band(load_map(result / "map.npz"), config.bands.ceiling.min_m,
                        config.bands.ceiling.max_m,
                        free_min_observed=config.bands.free_min_observed)  # fmt: skip
    assert grid.header.frame_id == "map"
    assert (grid.info.height, grid.info.width) == band.shape
    assert grid.info.resolution == pytest.approx(band.resolution_m, rel=1e-6)
    np.testing.assert_allclose(planar(grid.info.origin), [*band.lower_xy, 0.0], atol=1e-9)
    cells = np.array(grid.data, dtype=np.int8).reshape(band.shape)
    np.testing.assert_array_equal(cells == -1, ~band.known)
    np.testing.assert_allclose(cells[band.known], 100 * band.occupancy[band.known], atol=0.5)
    assert (cells == 100).sum() > 20
    assert (cells == 0).sum() > 5000


def test_points_are_the_occupied_voxels_with_their_probability(
    exported: tuple[Path, Path, Messages],
) -> None:
    dataset, _, messages = exported
    grid = load_map(dataset / "result" / "map.npz")
    cloud = messages["/map/points"][0][2]
    assert cloud.header.frame_id == "map"
    assert [(f.name, f.offset, f.datatype, f.count) for f in cloud.fields] == [
        ("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("probability", 12, 7, 1)]  # fmt: skip
    assert (cloud.height, cloud.point_step, cloud.is_bigendian) == (1, 16, False)
    table = np.frombuffer(bytes(cloud.data), dtype="<f4").reshape(-1, 4)
    cells, probability = grid.occupied()
    assert cloud.width == len(table) == len(cells) > 10_000
    np.testing.assert_allclose(table[:, :3], grid.cell_centers(cells), atol=1e-5)
    np.testing.assert_allclose(table[:, 3], probability, atol=1e-6)
    assert table[:, 3].min() > grid.params.occupied_threshold


def test_voxels_are_the_box_of_occupied_cells_of_the_map(
    exported: tuple[Path, Path, Messages],
) -> None:
    dataset, _, messages = exported
    check_voxel_grid(messages["/map/voxels"][0][2], load_map(dataset / "result" / "map.npz"))


def check_voxel_grid(voxels: Any, grid: OccupancyGrid) -> None:
    """``voxels`` (a decoded ``foxglove_msgs/VoxelGrid``) is the box around the occupied cells
    of ``grid``: every occupied voxel opaque at its cell with its probability, the other known
    cells transparent with theirs, unknown cells NaN."""
    cells, probability = grid.occupied()
    known, logodds = grid.cells()
    res = grid.resolution_m
    lower = cells.min(axis=0)
    nx, ny, nz = (cells.max(axis=0) - lower + 1).tolist()
    assert voxels.frame_id == "map"
    assert (voxels.cell_size.x, voxels.cell_size.y, voxels.cell_size.z) == (res, res, res)
    assert planar(voxels.pose).tolist() == [*(grid.origin_m + lower * res)[:2], 0.0]
    assert voxels.pose.position.z == pytest.approx(grid.origin_m[2] + lower[2] * res, abs=1e-12)
    assert (voxels.column_count, voxels.row_count) == (nx, ny)
    assert (voxels.cell_stride, voxels.row_stride, voxels.slice_stride) == (8, 8 * nx, 8 * nx * ny)
    assert [(f.name, f.offset, f.type) for f in voxels.fields] == [
        ("probability", 0, 7), ("red", 4, 1), ("green", 5, 1), ("blue", 6, 1), ("alpha", 7, 1)]  # fmt: skip
    assert len(voxels.data) == 8 * nx * ny * nz
    dtype = np.dtype([("probability", "<f4"), ("rgba", "u1", 4)])
    block = np.frombuffer(bytes(voxels.data), dtype=dtype).reshape(nz, ny, nx)
    i, j, k = (cells - lower).T
    assert (block["rgba"][k, j, i, 3] == 255).all()
    assert (block["rgba"][..., 3] == 255).sum() == len(cells) > 10_000
    np.testing.assert_allclose(block["probability"][k, j, i], probability, rtol=1e-6)
    inside = np.all((known >= lower) & (known < lower + np.array([nx, ny, nz])), axis=1)
    assert np.isfinite(block["probability"]).sum() == inside.sum() > len(cells)
    i, j, k = (known[inside] - lower).T
    expected = 1 / (1 + np.exp(-logodds[inside]))
    np.testing.assert_allclose(block["probability"][k, j, i], expected, rtol=1e-6)
    # Coloured by height: the lowest occupied voxels blue, the highest red.
    assert block["rgba"][0][block["rgba"][0][..., 3] == 255][:, 2].min() > 150
    assert block["rgba"][-1][block["rgba"][-1][..., 3] == 255][:, 0].min() > 150


def test_octomap_carries_the_tree_of_map_bt(exported: tuple[Path, Path, Messages]) -> None:
    import pyoctomap

    dataset, _, messages = exported
    octomap = messages["/octomap_binary"][0][2]
    assert (octomap.header.frame_id, octomap.id, octomap.binary) == ("map", "OcTree", True)
    data = np.array(octomap.data, dtype=np.int8).tobytes()
    bt = (dataset / "result" / "map.bt").read_bytes()
    tree_id, resolution_m, stream = tree_stream(bt)
    assert (tree_id, octomap.resolution) == ("OcTree", resolution_m)
    assert data == stream
    # OctoMap reads the message's tree (with a .bt header) to the occupied voxels of the map.
    header = bt[: len(bt) - len(stream)]
    (dataset.parent / "from_message.bt").write_bytes(header + data)
    tree = pyoctomap.OcTree(0.5)
    assert tree.readBinary(str(dataset.parent / "from_message.bt"))
    leaves = [(tree.isNodeOccupied(leaf.current_node), round(leaf.getSize() / 0.1) ** 3)
              for leaf in tree.begin_leafs()]  # fmt: skip
    occupied_cells = sum(size for occupied, size in leaves if occupied)
    assert occupied_cells == len(load_map(dataset / "result" / "map.npz").occupied()[0])


def test_paths_and_poses_are_the_tum_poses_with_their_marginals(
    exported: tuple[Path, Path, Messages],
) -> None:
    dataset, _, messages = exported
    covariances = json.loads((dataset / "result" / "covariances.json").read_text())["robots"]
    for robot in "ab":
        stamps, poses = read_tum(dataset / "result" / "poses" / f"{robot}.tum")
        final = messages[f"/{robot}/path"][-1][2]
        assert final.header.frame_id == "map"
        assert [ns(p.header.stamp) for p in final.poses] == [round(t * 1e9) for t in stamps]
        got = np.array([planar(p.pose) for p in final.poses])
        np.testing.assert_allclose(got, poses, atol=1e-9)
        assert [len(m.poses) for _, _, m in messages[f"/{robot}/path"]] == list(
            range(1, len(stamps) + 1)
        )
        for (log_ns, _, message), pose, tangent, t in zip(
            messages[f"/{robot}/pose"], poses, covariances[robot]["covariances"], stamps,
            strict=True,
        ):  # fmt: skip
            assert log_ns == round(t * 1e9)
            assert message.header.frame_id == "map"
            np.testing.assert_allclose(planar(message.pose.pose), pose, atol=1e-9)
            cov = np.array(message.pose.covariance).reshape(6, 6)
            c, s = math.cos(pose[2]), math.sin(pose[2])
            R = np.array([[c, -s], [s, c]])
            tangent = np.array(tangent)
            np.testing.assert_allclose(cov[:2, :2], R @ tangent[:2, :2] @ R.T, rtol=1e-9,
                                       atol=1e-18)  # fmt: skip
            assert cov[5, 5] == pytest.approx(tangent[2, 2], rel=1e-12)
            assert cov[2, 2] == cov[3, 3] == cov[4, 4] == 0.0
            np.testing.assert_allclose(cov, cov.T, atol=1e-18)
    gauge = np.array(messages["/a/pose"][0][2].pose.covariance).reshape(6, 6)
    assert math.sqrt(gauge[0, 0]) == pytest.approx(0.001, rel=0.05)  # the gauge prior's sigma


def test_tf_chains_map_odom_base_link_to_the_tum_poses(
    exported: tuple[Path, Path, Messages],
) -> None:
    dataset, _, messages = exported
    pairs = {(t.header.frame_id, t.child_frame_id) for _, t in transforms(messages)}
    assert pairs == {("map", "a/odom"), ("a/odom", "a/base_link"),
                     ("map", "b/odom"), ("b/odom", "b/base_link")}  # fmt: skip
    for robot in "ab":
        map_odom, odom_base = {}, {}
        for log_ns, t in transforms(messages):
            assert ns(t.header.stamp) == log_ns
            q, v = t.transform.rotation, t.transform.translation
            value = np.array([v.x, v.y, yaw(q)])
            assert v.z == 0.0
            if t.child_frame_id == f"{robot}/odom":
                map_odom[log_ns] = value
            elif t.child_frame_id == f"{robot}/base_link":
                odom_base[log_ns] = value
        stamps, odometry = read_tum(dataset / "robots" / robot / "odometry.tum")
        assert sorted(odom_base) == [round(t * 1e9) for t in stamps]
        got = np.array([odom_base[k] for k in sorted(odom_base)])
        np.testing.assert_allclose(got[:, :2], odometry[:, :2], atol=1e-9)
        np.testing.assert_allclose(np.cos(got[:, 2] - odometry[:, 2]), 1.0, atol=1e-12)
        pose_stamps, poses = read_tum(dataset / "result" / "poses" / f"{robot}.tum")
        assert sorted(map_odom) == [round(t * 1e9) for t in pose_stamps]
        for t, pose in zip(pose_stamps, poses, strict=True):
            key = round(t * 1e9)
            chained = se2.compose(map_odom[key], odom_base[key])
            np.testing.assert_allclose(chained[:2], pose[:2], atol=1e-9)
            assert math.remainder(chained[2] - pose[2], 2 * math.pi) == pytest.approx(0, abs=1e-9)
    static = messages["/tf_static"][0][2].transforms
    config = load_config(dataset / "result" / "config.yaml")
    mounts = {(t.header.frame_id, t.child_frame_id): (t.transform.translation.x,
              t.transform.translation.y, t.transform.translation.z) for t in static}  # fmt: skip
    r, b = config.robot, config.beacon
    for robot in "ab":
        base = f"{robot}/base_link"
        assert mounts[(base, f"{robot}/scanner")] == pytest.approx(
            (r.scanner_x_m, 0.0, r.scanner_height_m)
        )
        assert mounts[(base, f"{robot}/beacon")] == pytest.approx(
            (r.scanner_x_m + b.offset_m, 0.0, b.height_m)
        )
    assert len(static) == 4


def test_markers_show_the_mutual_observations_and_the_searches(
    exported: tuple[Path, Path, Messages],
) -> None:
    dataset, _, messages = exported
    report = json.loads((dataset / "result" / "report.json").read_text())
    poses = {}
    for robot in "ab":
        _, tum = read_tum(dataset / "result" / "poses" / f"{robot}.tum")
        poses.update({f"{robot}{i}": p for i, p in enumerate(tum)})
    markers = messages["/markers"][0][2].markers
    mutual = [m for m in markers if m.ns == "mutual"]
    rows = report["mutual_observations"]
    assert len(mutual) == len(rows) >= 4
    height = load_config(dataset / "result" / "config.yaml").beacon.height_m
    for marker, row in zip(mutual, rows, strict=True):
        assert marker.type == 0
        assert marker.header.frame_id == "map"
        ends = np.array([[p.x, p.y, p.z] for p in marker.points])
        expected = [[*poses[label][:2], height] for label in row["pair"]]
        np.testing.assert_allclose(ends, expected, atol=1e-9)
        # Green for a kept factor; orange (outlier) and red (gated out) are redder than green.
        assert (marker.color.g > marker.color.r) == bool(row["accepted"] and row.get("inlier"))
    found = report["global_localization"]
    records = [*found["searches"], *found["relocalization"]]
    searches = [m for m in markers if m.ns == "search"]
    assert len(searches) == len(records) >= 1
    for marker, record in zip(searches, records, strict=True):
        anchor = record["against"]
        expected = record["pose"] if anchor == "map" else se2.compose(poses[anchor], record["pose"])
        np.testing.assert_allclose(planar(marker.pose)[:2], expected[:2], atol=1e-9)
        assert math.remainder(planar(marker.pose)[2] - expected[2], 2 * math.pi) == (
            pytest.approx(0, abs=1e-9)
        )
    assert [m.id for m in mutual] == list(range(len(mutual)))


def test_export_command_rewrites_its_own_bag_and_refuses_other_files(
    exported: tuple[Path, Path, Messages], tmp_path: Path
) -> None:
    dataset, bag, _ = exported
    runner = CliRunner()
    result = runner.invoke(app, ["export", str(dataset / "result"), "--mcap", str(bag)])
    assert result.exit_code == 0, result.output
    assert "coopmap export: 11 topics" in result.output
    assert "/octomap_binary" in result.output
    foreign = tmp_path / "mine.mcap"
    foreign.write_bytes(b"\x89MCAP0\r\n my notes")
    result = runner.invoke(app, ["export", str(dataset / "result"), "--mcap", str(foreign)])
    assert result.exit_code == 2
    assert result.output.strip().endswith("exists and is not a bag coopmap wrote; refusing to "
                                          "replace it (choose another file)")  # fmt: skip
    assert len(result.output.strip().splitlines()) == 1
    assert foreign.read_bytes() == b"\x89MCAP0\r\n my notes"
    result = runner.invoke(app, ["export", str(tmp_path), "--mcap", str(tmp_path / "x.mcap")])
    assert result.exit_code == 2
    assert "no result here" in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.mcap"]


def test_batch_writes_the_bag_too(exported: tuple[Path, Path, Messages], tmp_path: Path) -> None:
    dataset, _, first = exported
    bag = tmp_path / "batch.mcap"
    result = CliRunner().invoke(
        app, ["batch", str(dataset), "--out", str(tmp_path / "result"), "--mcap", str(bag)]
    )
    assert result.exit_code == 0, result.output
    again = read_bag(bag)
    assert {t: len(r) for t, r in again.items()} == {t: len(r) for t, r in first.items()}
    a, b = again["/map/points"][0][2], first["/map/points"][0][2]
    assert bytes(a.data) == bytes(b.data)  # the same map, bit for bit
