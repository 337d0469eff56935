"""TUM and g2o readers and writers: round trips, GTSAM agreement, and every corrupt-file error."""

from __future__ import annotations

import gzip
import math
from pathlib import Path

import gtsam
import numpy as np
import pytest

from sensors import trajio
from sensors.errors import TrajectoryError
from sensors.trajio import (
    G2oGraph,
    as_logged,
    pose_at,
    read_carmen_odometry,
    read_g2o,
    read_relations,
    read_tum,
    tum_rows,
    write_g2o,
    write_tum,
)
from tests.paths import DATA

INTEL_G2O = DATA / "pose_graphs_g2o" / "intel.g2o"


def test_tum_round_trip_keeps_poses(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    stamps = np.cumsum(rng.uniform(0.05, 0.2, 50))
    poses = np.column_stack([rng.normal(size=(50, 2)) * 10, rng.uniform(-math.pi, math.pi, 50)])
    path = write_tum(tmp_path / "poses" / "a.tum", stamps, poses)
    back_stamps, back_poses = read_tum(path)
    np.testing.assert_allclose(back_stamps, stamps, atol=1e-9)
    np.testing.assert_allclose(back_poses[:, :2], poses[:, :2], atol=1e-9)
    np.testing.assert_allclose(
        np.angle(np.exp(1j * (back_poses[:, 2] - poses[:, 2]))), 0, atol=1e-8
    )
    assert path.read_text().splitlines()[1].split()[3:6] == ["0", "0", "0"]


def test_tum_quaternion_is_a_rotation_about_z(tmp_path: Path) -> None:
    path = write_tum(tmp_path / "t.tum", np.array([1.0]), np.array([[1.0, 2.0, math.pi / 2]]))
    fields = [float(v) for v in path.read_text().splitlines()[1].split()]
    assert fields[6] == pytest.approx(math.sqrt(0.5))
    assert fields[7] == pytest.approx(math.sqrt(0.5))


@pytest.mark.parametrize(
    ("text", "pattern"),
    [
        ("1 2 3\n", r"t\.tum:1: TUM line needs 8 fields .*got 3"),
        ("1 0 0 0 0 0 x 1\n", r"t\.tum:1: TUM line: not a number"),
        ("1 0 0 0 0 0 0 nan\n", r"t\.tum:1: TUM line: non-finite value"),
        ("1 0 0 0 0 0 0 2\n", r"t\.tum:1: quaternion norm is 2, not 1"),
        ("1 0 0 0 0.7071068 0 0 0.7071068\n", r"t\.tum:1: pose is tilted"),
        ("2 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", r"t\.tum:2: timestamp 1\.0 goes back"),
        ("# only a comment\n", r"t\.tum: no poses in the TUM file"),
        # the first bad line is named past comments and blank lines
        ("# c\n1 0 0 0 0 0 0 1\n\n2 0 0 0 0 0 0 nan\n3 0 0 0 0 0 0 2\n", r"t\.tum:4: .*non-finite"),
        ("1 0 0 0 0 0 0 1\n# c\n2 0 0 0 0 0 0x10 1\n", r"t\.tum:3: TUM line: not a number"),
        (
            "1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1\n\n1.5 0 0 0 0 0 0 1\n",
            r"t\.tum:4: timestamp 1\.5 goes back",
        ),
        ("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1.01\n", r"t\.tum:2: quaternion norm is 1\.01"),
        # What numpy's parser of a whole file reads otherwise is read as the line reader does.
        ("1 0 0 0 0 0 0 1 # stamp\n", r"t\.tum:1: TUM line needs 8 fields .*got 10"),
        ("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1_0\n", r"t\.tum:2: quaternion norm is 10, not 1"),
        ("1 0 0 0 0 0 0 1\n" + "2 " * 40_000 + "\n", r"t\.tum:2: a line longer than 65,536"),
    ],
)
def test_corrupt_tum_files_are_named_with_line_and_reason(
    tmp_path: Path, text: str, pattern: str
) -> None:
    path = tmp_path / "t.tum"
    path.write_text(text)
    with pytest.raises(TrajectoryError, match=pattern):
        read_tum(path)


def test_binary_garbage_is_not_a_trajectory(tmp_path: Path) -> None:
    path = tmp_path / "t.tum"
    path.write_bytes(b"\xff\xfe\x00\x81garbage")
    with pytest.raises(TrajectoryError, match="not a readable text file"):
        read_tum(path)


def small_graph() -> G2oGraph:
    info = np.array([[100.0, 1.0, 0.5], [1.0, 200.0, 0.2], [0.5, 0.2, 1000.0]])
    return G2oGraph(
        vertex_ids=np.array([0, 1, 2]),
        poses=np.array([[0.0, 0.0, 0.0], [1.0, 0.1, 0.2], [2.0, 0.3, -0.1]]),
        edges=np.array([[0, 1], [1, 2], [0, 2]]),
        measurements=np.array([[1.0, 0.1, 0.2], [1.0, 0.0, -0.3], [2.0, 0.3, -0.1]]),
        information=np.stack([info] * 3),
        fixed=(0,),
    )


def test_g2o_round_trip_and_gtsam_reads_what_we_write(tmp_path: Path) -> None:
    graph = small_graph()
    path = write_g2o(tmp_path / "graph.g2o", graph)
    back = read_g2o(path)
    np.testing.assert_array_equal(back.vertex_ids, graph.vertex_ids)
    np.testing.assert_allclose(back.poses, graph.poses)
    np.testing.assert_array_equal(back.edges, graph.edges)
    np.testing.assert_allclose(back.measurements, graph.measurements)
    np.testing.assert_allclose(back.information, graph.information)
    assert back.fixed == (0,)
    factors, values = gtsam.readG2o(str(path), False)
    assert values.size() == 3
    assert factors.size() == 3
    assert values.atPose2(1).x() == pytest.approx(1.0)
    measured = factors.at(2).measured()
    assert (measured.x(), measured.y(), measured.theta()) == pytest.approx((2.0, 0.3, -0.1))


@pytest.mark.skipif(not INTEL_G2O.exists(), reason="../shared/data is not available")
def test_reads_the_intel_graph_like_gtsam() -> None:
    graph = read_g2o(INTEL_G2O)
    assert graph.num_poses == 1728
    assert len(graph.edges) == 2512
    factors, values = gtsam.readG2o(str(INTEL_G2O), False)
    assert values.size() == graph.num_poses
    assert factors.size() == len(graph.edges)
    poses = gtsam.utilities.extractPose2(values)
    np.testing.assert_allclose(poses[:, :2], graph.poses[:, :2], atol=1e-6)
    for i in (0, 1000, 2511):
        m = factors.at(i).measured()
        np.testing.assert_allclose(
            [m.x(), m.y()], graph.measurements[i, :2], atol=1e-6, err_msg=f"edge {i}"
        )


@pytest.mark.parametrize(
    ("text", "pattern"),
    [
        ("VERTEX_SE2 0 0 0\n", r"g\.g2o:1: VERTEX_SE2 needs 'id x y theta', got 3 values"),
        ("VERTEX_SE2 a 0 0 0\n", r"g\.g2o:1: vertex id 'a' is not an integer"),
        ("VERTEX_SE2 -1 0 0 0\n", r"g\.g2o:1: vertex id -1 is negative"),
        ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 0 1 0 0\n", r"g\.g2o:2: vertex 0 defined twice"),
        (
            "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0\n",
            r"g\.g2o:2: EDGE_SE2 needs .*got 10 values",
        ),
        (
            "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 -1 0 1\n",
            r"g\.g2o:3: EDGE_SE2 0-1: information matrix is not positive definite",
        ),
        (
            "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 7 1 0 0 1 0 0 1 0 1\n",
            r"edges refer to undefined vertices \[7\]",
        ),
        (
            "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n",
            r"g\.g2o:1: unsupported g2o record 'VERTEX_SE3:QUAT'",
        ),
        ("VERTEX_SE2 0 0 0 inf\n", r"g\.g2o:1: VERTEX_SE2: non-finite value"),
        ("\n# nothing\n", r"g\.g2o: no VERTEX_SE2 or EDGE_SE2 lines"),
    ],
)
def test_corrupt_g2o_files_are_named_with_line_and_reason(
    tmp_path: Path, text: str, pattern: str
) -> None:
    path = tmp_path / "g.g2o"
    path.write_text(text)
    with pytest.raises(TrajectoryError, match=pattern):
        read_g2o(path)


def test_edges_only_g2o_counts_its_poses(tmp_path: Path) -> None:
    path = tmp_path / "e.g2o"
    path.write_text("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\n")
    assert read_g2o(path).num_poses == 3


def test_carmen_odometry_skips_unstamped_lines(tmp_path: Path) -> None:
    path = tmp_path / "log.gz"
    with gzip.open(path, "wt") as handle:
        handle.write("# a comment\nPARAM robot_frontlaser_offset 0.0 nohost 0\n")
        handle.write("ODOM 1 2 0.5 0 0 0 10.5 host 10.5\n")
        handle.write("FLASER 3 1 1 1 1 2 0.5 1 2 0.5 10.6 host 10.6\n")
        handle.write("ODOM 1 2 0.5 0 0 0 0 host 0\n")
        handle.write("ODOM 1.5 2 0.6 0 0 0 10.7 host 10.7\n")
    stamps, poses = read_carmen_odometry(path)
    np.testing.assert_allclose(stamps, [10.5, 10.7])
    np.testing.assert_allclose(poses, [[1, 2, 0.5], [1.5, 2, 0.6]])
    bad = tmp_path / "bad.log"
    bad.write_text("ODOM 1 2\n")
    with pytest.raises(TrajectoryError, match=r"bad\.log:1: ODOM line needs"):
        read_carmen_odometry(bad)
    empty = tmp_path / "empty.log"
    empty.write_text("PARAM a b\n")
    with pytest.raises(TrajectoryError, match="no timestamped ODOM lines"):
        read_carmen_odometry(empty)


def test_relations_reader_checks_its_lines(tmp_path: Path) -> None:
    path = tmp_path / "r.relations"
    path.write_text("1.0 2.0 0.5 0.1 0 0 0 0.2\n")
    stamps, relations = read_relations(path)
    np.testing.assert_allclose(stamps, [[1.0, 2.0]])
    np.testing.assert_allclose(relations, [[0.5, 0.1, 0.2]])
    path.write_text("1.0 2.0 0.5\n")
    with pytest.raises(TrajectoryError, match=r"r\.relations:1: relation needs 8 fields"):
        read_relations(path)
    path.write_text("")
    with pytest.raises(TrajectoryError, match="no relations"):
        read_relations(path)


def test_tum_keeps_the_digits_asked_for(tmp_path: Path) -> None:
    path = write_tum(
        tmp_path / "odo.tum", np.array([1.5]), np.array([[1.0, 2.0, 0.0]]), z_m=0.0, decimals=6
    )
    assert (
        path.read_text().splitlines()[1]
        == "1.500000 1.000000 2.000000 0.000000 0 0 0.000000000 1.000000000"
    )
    stamps, poses = read_tum(path)
    np.testing.assert_allclose(stamps, [1.5])
    np.testing.assert_allclose(poses, [[1.0, 2.0, 0.0]])
    with pytest.raises(TrajectoryError, match=r"need stamps \(N,\) and poses \(N, 3\)"):
        write_tum(tmp_path / "bad.tum", np.array([1.0, 2.0]), np.zeros((1, 3)))


def random_planar_poses(rng: np.random.Generator, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Stamps and poses whose yaws include the wrap: at and next to ±π, and zero."""
    stamps = np.cumsum(rng.uniform(0.01, 0.3, count)) + rng.uniform(0.0, 1000.0)
    yaw = rng.uniform(-math.pi, math.pi, count)
    near_pi = [math.pi, -math.pi, math.pi - 1e-7, -math.pi + 1e-7, math.pi - 3e-10, 0.0, -0.0]
    yaw[: len(near_pi)] = near_pi
    poses = np.column_stack([rng.normal(size=(count, 2)) * 20.0, yaw])
    return stamps, poses


def test_tum_rows_are_the_lines_write_tum_writes(tmp_path: Path) -> None:
    stamps, poses = random_planar_poses(np.random.default_rng(7), 40)
    for decimals, z_m in [(9, 0.0), (6, 0.0), (4, 0.45)]:
        path = write_tum(tmp_path / f"t{decimals}.tum", stamps, poses, z_m=z_m, decimals=decimals)
        lines = path.read_text(encoding="utf-8").splitlines()
        assert lines[0].startswith("#")
        assert lines[1:] == tum_rows(stamps, poses, z_m=z_m, decimals=decimals)
    row = tum_rows(np.array([2.0]), np.array([[1.0, -2.0, math.pi / 2]]), decimals=3)
    assert row == ["2.000 1.000 -2.000 0.000 0 0 0.707106781 0.707106781"]


def test_as_logged_is_bitwise_what_read_tum_reads_back(tmp_path: Path) -> None:
    rng = np.random.default_rng(11)
    for trial in range(3):
        stamps, poses = random_planar_poses(rng, 200)
        logged_stamps, logged_poses = as_logged(stamps, poses, decimals=6)
        path = write_tum(tmp_path / f"odo{trial}.tum", stamps, poses, decimals=6)
        read_stamps, read_poses = read_tum(path)
        assert logged_stamps.dtype == read_stamps.dtype == np.float64
        assert logged_poses.shape == read_poses.shape == (200, 3)
        np.testing.assert_array_equal(logged_stamps, read_stamps)
        np.testing.assert_array_equal(logged_poses, read_poses)
        # The numbers are the logged ones, not the inputs: rounded to a micrometre.
        assert np.abs(logged_poses[:, :2] - poses[:, :2]).max() <= 0.5e-6 + 1e-12
        assert np.abs(logged_poses[:, :2] - poses[:, :2]).max() > 0.0
        yaw_error = np.angle(np.exp(1j * (logged_poses[:, 2] - poses[:, 2])))
        assert np.abs(yaw_error).max() < 1e-8
        assert (np.abs(logged_poses[:, 2]) <= math.pi).all()
    empty_stamps, empty_poses = as_logged(np.zeros(0), np.zeros((0, 3)), decimals=6)
    assert empty_stamps.shape == (0,)
    assert empty_poses.shape == (0, 3)


def test_a_tum_file_read_at_once_is_what_the_line_reader_reads(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    stamps, poses = random_planar_poses(np.random.default_rng(3), 300)
    rows = tum_rows(stamps, poses, decimals=9)
    # Comments, blank and indented lines, tabs and Windows line ends, as hand-edited files have.
    text = "# t x y z qx qy qz qw\n\n" + "\r\n".join(rows[:150]) + "\n  # note\n\t\n"
    text += "\n".join(("  " + row.replace(" ", "\t", 2)) for row in rows[150:]) + "\n"
    path = tmp_path / "odo.tum"
    path.write_bytes(text.encode())
    with gzip.open(tmp_path / "odo.tum.gz", "wt") as handle:
        handle.write(text)
    at_once = read_tum(path)
    monkeypatch.setattr(trajio, "_AT_ONCE_BYTES", 0)
    for line_by_line in (read_tum(path), read_tum(tmp_path / "odo.tum.gz")):
        np.testing.assert_array_equal(at_once[0], line_by_line[0])
        np.testing.assert_array_equal(at_once[1], line_by_line[1])
    assert len(at_once[0]) == 300
    np.testing.assert_allclose(at_once[1][:, :2], poses[:, :2], atol=1e-9)


def test_pose_at_interpolates_across_the_yaw_wrap_and_holds_beyond_the_ends() -> None:
    stamps = np.array([0.0, 1.0, 2.0, 3.0])
    poses = np.array([[0.0, 0.0, 3.0], [1.0, 2.0, -3.0], [2.0, 4.0, -2.5], [3.0, 6.0, -2.0]])
    mid = pose_at(stamps, poses, 0.5)
    assert mid.shape == (3,)
    # From 3.0 rad to −3.0 rad the short way: through π, not through 0.
    np.testing.assert_allclose(mid, [0.5, 1.0, 3.0 + 0.5 * (2 * math.pi - 6.0)], atol=1e-12)
    np.testing.assert_allclose(pose_at(stamps, poses, -5.0), poses[0], atol=0)
    assert pose_at(stamps, poses, 9.0)[2] == pytest.approx(-2.0 + 2 * math.pi)  # unwrapped
    # Many instants at once, and the unwrapped yaw given: the same numbers, bit for bit.
    times = np.array([-1.0, 0.25, 1.5, 2.75, 4.0])
    at_once = pose_at(stamps, poses, times)
    one_by_one = np.array([pose_at(stamps, poses, t) for t in times])
    assert at_once.shape == (5, 3)
    assert np.array_equal(at_once, one_by_one)
    given = pose_at(stamps, poses, times, np.unwrap(poses[:, 2]))
    assert np.array_equal(given, at_once)
    assert np.array_equal(pose_at(stamps, poses, 1.5, np.unwrap(poses[:, 2])), one_by_one[2])
