"""PLY point clouds: round trips, what other tools read, and corrupt files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mapping.formats.ply import PlyError, read_ply, write_ply


def sample(n: int = 50) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    points = rng.normal(size=(n, 3))
    colors = rng.integers(0, 256, size=(n, 3), dtype=np.uint8)
    probability = rng.uniform(0.5, 1.0, n)
    return points, colors, probability


def test_round_trip_with_colours_and_fields(tmp_path: Path) -> None:
    points, colors, probability = sample()
    path = tmp_path / "cloud.ply"
    write_ply(
        path,
        points,
        colors=colors,
        fields={"probability": probability, "label": np.arange(50, dtype=np.int32)},
    )
    cloud = read_ply(path)
    np.testing.assert_allclose(
        np.column_stack([cloud["x"], cloud["y"], cloud["z"]]), points, atol=1e-6
    )
    np.testing.assert_array_equal(
        np.column_stack([cloud["red"], cloud["green"], cloud["blue"]]), colors
    )
    np.testing.assert_array_equal(cloud["probability"], probability)  # doubles stay exact
    np.testing.assert_array_equal(cloud["label"], np.arange(50))


def test_open3d_reads_what_we_write(tmp_path: Path) -> None:
    import open3d as o3d

    points, colors, probability = sample()
    path = tmp_path / "cloud.ply"
    write_ply(path, points, colors=colors, fields={"probability": probability.astype(np.float32)})
    legacy = o3d.io.read_point_cloud(str(path))
    np.testing.assert_allclose(np.asarray(legacy.points), points, atol=1e-6)
    np.testing.assert_allclose(np.asarray(legacy.colors) * 255, colors, atol=0.5)
    tensor = o3d.t.io.read_point_cloud(str(path))
    np.testing.assert_allclose(tensor.point["probability"].numpy().ravel(), probability, atol=1e-6)


def test_empty_cloud(tmp_path: Path) -> None:
    path = tmp_path / "empty.ply"
    write_ply(path, np.zeros((0, 3)))
    assert len(read_ply(path)["x"]) == 0


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"points": np.zeros((4, 2))}, r"points must be \(N, 3\)"),
        ({"points": np.zeros((4, 3)), "colors": np.zeros((3, 3))}, r"colors must be \(4, 3\)"),
        ({"points": np.zeros((4, 3)), "fields": {"p": np.zeros(5)}}, r"field 'p' must be \(4,\)"),
    ],
)
def test_bad_arrays_are_rejected(tmp_path: Path, kwargs: dict, message: str) -> None:
    with pytest.raises(PlyError, match=message):
        write_ply(tmp_path / "x.ply", **kwargs)
    assert not (tmp_path / "x.ply").exists()


def test_corrupt_files_are_clear_errors(tmp_path: Path) -> None:
    points, _, _ = sample()
    good = tmp_path / "good.ply"
    write_ply(good, points)
    truncated = tmp_path / "truncated.ply"
    truncated.write_bytes(good.read_bytes()[:-7])
    with pytest.raises(PlyError, match=r"truncated: 50 vertices need 600 bytes, found 593"):
        read_ply(truncated)
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"\x00\x01garbage")
    with pytest.raises(PlyError, match="not a PLY file"):
        read_ply(junk)
    ascii_ply = tmp_path / "ascii.ply"
    ascii_ply.write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    with pytest.raises(PlyError, match="only binary_little_endian"):
        read_ply(ascii_ply)
    with pytest.raises(PlyError, match="cannot read"):
        read_ply(tmp_path / "absent.ply")


def test_failed_write_keeps_the_old_file(tmp_path: Path) -> None:
    path = tmp_path / "cloud.ply"
    path.write_bytes(b"previous")
    with pytest.raises(PlyError):
        write_ply(path, np.zeros((3, 3)), colors=np.zeros((2, 3)))
    assert path.read_bytes() == b"previous"


def test_occupied_voxels_export_with_their_probability(tmp_path: Path) -> None:
    from mapping.formats.ply import write_grid_ply
    from mapping.grid import GridParams, OccupancyGrid

    params = GridParams()
    grid = OccupancyGrid(params)
    sensor = np.array([0.05, 0.05, 0.05])
    grid.integrate_scan(np.array([[1.05, 0.05, 0.05], [0.05, 2.05, 0.05]]), sensor)
    grid.integrate_scan(np.array([[1.05, 0.05, 0.05]]), sensor)
    path = tmp_path / "map.ply"
    assert write_grid_ply(path, grid) == 2
    cloud = read_ply(path)
    order = np.argsort(cloud["x"])
    np.testing.assert_allclose(cloud["x"][order], [0.05, 1.05], atol=1e-6)
    np.testing.assert_allclose(cloud["y"][order], [2.05, 0.05], atol=1e-6)
    p_twice = 1 / (1 + (0.3 / 0.7) ** 2)
    np.testing.assert_allclose(cloud["probability"][order], [0.7, p_twice], atol=1e-6)
    assert write_grid_ply(tmp_path / "sure.ply", grid, threshold=0.8) == 1


def test_ply_errors_are_map_errors() -> None:
    from mapping.errors import MapError

    assert issubclass(PlyError, MapError)
