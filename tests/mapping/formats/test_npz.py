"""map.npz: exact round trips, and clear errors that never clobber a map on disk."""

from __future__ import annotations

import contextlib
import io
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from mapping.errors import MapError
from mapping.formats import npz
from mapping.formats.npz import load_map, save_map
from mapping.grid import GridParams, OccupancyGrid
from tests.mapping.conftest import room_scan


def scanned(params: GridParams | None = None) -> OccupancyGrid:
    grid = OccupancyGrid(params)
    for sensor in ([2.0, 1.5, 1.0], [1.0, 2.2, 0.5]):
        grid.integrate_scan(room_scan(np.array(sensor)), np.array(sensor))
    return grid


def assert_same(a: OccupancyGrid, b: OccupancyGrid) -> None:
    assert a.params == b.params
    (ca, va), (cb, vb) = a.cells(), b.cells()
    oa, ob = np.lexsort(ca.T), np.lexsort(cb.T)
    np.testing.assert_array_equal(ca[oa], cb[ob])
    np.testing.assert_array_equal(va[oa], vb[ob])  # bit for bit


@pytest.mark.parametrize(
    "params",
    [GridParams(), GridParams(resolution_m=0.05, block_size_cells=5, origin_m=(0.1, -2.0, 0.3),
                              prob_hit=0.8, clamp_max=0.99, no_return_free_m=2.0)],
)  # fmt: skip
def test_round_trip_is_lossless(tmp_path: Path, params: GridParams) -> None:
    grid = scanned(params)
    path = save_map(tmp_path / "map.npz", grid)
    assert_same(grid, load_map(path))
    assert path.stat().st_size < grid.known_count() * 8  # compressed


def test_an_empty_map_round_trips(tmp_path: Path) -> None:
    loaded = load_map(save_map(tmp_path / "empty.npz", OccupancyGrid()))
    assert loaded.known_count() == 0


def test_loaded_maps_keep_integrating(tmp_path: Path) -> None:
    grid = scanned()
    loaded = load_map(save_map(tmp_path / "map.npz", grid))
    sensor = np.array([3.0, 1.0, 1.2])
    grid.integrate_scan(room_scan(sensor), sensor)
    loaded.integrate_scan(room_scan(sensor), sensor)
    assert_same(grid, loaded)


def rewrite(path: Path, out: Path, **changes: object) -> Path:
    with np.load(path) as archive:
        arrays = {key: archive[key] for key in archive.files}
    for key, value in changes.items():
        if value is None:
            del arrays[key]
        else:
            arrays[key] = np.asarray(value)
    np.savez_compressed(out, **arrays)
    return out


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"version": 3}, "map format version 3 is not supported .*reads versions 1 and 2"),
        ({"format": "something.else"}, "not a coopmap map"),
        ({"version": None}, r"not a coopmap map \(no format/version entry\)"),
        ({"known": None}, "map is missing known"),
        ({"resolution_m": -0.1}, "resolution_m must be a positive number"),
        ({"block_size_cells": 8}, r"known declares [\d,]+ bytes, more than the [\d,]+ its map"),
        ({"logodds": np.zeros(3)}, "logodds must hold one float32 per known cell"),
        ({"block_coords": np.zeros((2, 2), int)}, r"block_coords must be \(B, 3\) integers"),
        ({"origin_m": [0.0, 0.0]}, "origin_m must be 3 floats"),
        ({"version": 1.5}, "'version' must be a scalar"),
    ],
)
def test_malformed_contents_are_clear_errors(tmp_path: Path, changes: dict, message: str) -> None:
    good = save_map(tmp_path / "map.npz", scanned())
    with pytest.raises(MapError, match=message):
        load_map(rewrite(good, tmp_path / "bad.npz", **changes))


def test_values_outside_the_clamps_are_rejected(tmp_path: Path) -> None:
    good = save_map(tmp_path / "map.npz", scanned())
    with np.load(good) as archive:
        values = archive["logodds"].copy()
    values[0] = 50.0
    with pytest.raises(MapError, match="outside the clamping bounds"):
        load_map(rewrite(good, tmp_path / "bad.npz", logodds=values))
    values[0] = np.nan
    with pytest.raises(MapError, match="non-finite"):
        load_map(rewrite(good, tmp_path / "bad2.npz", logodds=values))


def test_corrupt_and_truncated_files_are_clear_errors(tmp_path: Path) -> None:
    good = save_map(tmp_path / "map.npz", scanned())
    data = good.read_bytes()
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(MapError, match=r"truncated.npz: not a readable coopmap map"):
        load_map(truncated)
    corrupt = tmp_path / "corrupt.npz"
    flipped = bytearray(data)
    middle = len(flipped) // 2
    flipped[middle : middle + 64] = bytes(64)
    corrupt.write_bytes(bytes(flipped))
    with pytest.raises(MapError, match=r"corrupt.npz: not a readable coopmap map"):
        load_map(corrupt)
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip at all")
    with pytest.raises(MapError, match="not a readable coopmap map"):
        load_map(junk)
    with pytest.raises(MapError, match=r"absent\.npz: no such map file"):
        load_map(tmp_path / "absent.npz")
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("format.npy", b"\x93NUMPY garbage")
        archive.writestr("version.npy", b"\x93NUMPY garbage")
    (tmp_path / "garbage.npz").write_bytes(buffer.getvalue())
    with pytest.raises(MapError, match="not a readable coopmap map"):
        load_map(tmp_path / "garbage.npz")


def test_a_failed_write_keeps_the_old_map(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = save_map(tmp_path / "map.npz", scanned())
    before = path.read_bytes()

    def crash(*args: object, **kwargs: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(npz.np, "savez_compressed", crash)
    with pytest.raises(OSError, match="disk full"):
        save_map(path, OccupancyGrid())
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.npz"]  # no temporary left


def crafted(path: Path, block_size: int, coords: np.ndarray, known: np.ndarray,
            values: np.ndarray) -> Path:  # fmt: skip
    arrays = {
        "format": np.array("coopmap.map"), "version": np.array(1),
        "resolution_m": np.array(0.1), "prob_hit": np.array(0.7), "prob_miss": np.array(0.4),
        "clamp_min": np.array(0.12), "clamp_max": np.array(0.97),
        "occupied_threshold": np.array(0.5), "no_return_free_m": np.array(0.0),
        "block_size_cells": np.array(block_size), "origin_m": np.zeros(3),
        "block_coords": coords, "known": known, "logodds": values,
    }  # fmt: skip
    np.savez_compressed(path, **arrays)
    return path


def peak_bytes(action: Callable[[], object]) -> int:
    import tracemalloc

    tracemalloc.start()
    with contextlib.suppress(MapError):
        action()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak


def test_many_nearly_empty_blocks_are_refused_before_allocating(tmp_path: Path) -> None:
    """60,000 blocks with one known cell each: 1.9 GB of dense blocks from a 1 MB file."""
    n = 60_000
    coords = np.stack([np.arange(n), np.zeros(n, int), np.zeros(n, int)], axis=1)
    known = np.zeros((n, 512), np.uint8)
    known[:, 0] = 1
    path = crafted(tmp_path / "bomb.npz", 16, coords, known, np.zeros(n))
    assert path.stat().st_size < 2e6
    with pytest.raises(MapError, match="60,000 blocks of 4,096 cells hold only 60,000 known"):
        load_map(path)
    assert peak_bytes(lambda: load_map(path)) < 100e6


def test_huge_empty_blocks_and_zip_bombs_are_refused_from_the_directory(tmp_path: Path) -> None:
    coords = np.stack([np.arange(200), np.zeros(200, int), np.zeros(200, int)], axis=1)
    known = np.zeros((200, 256**3 // 8), np.uint8)  # 200 empty 256-cube blocks: 3.4 GB dense
    path = crafted(tmp_path / "empty.npz", 256, coords, known, np.zeros(0))
    with pytest.raises(MapError, match="block_coords declares 4,928 bytes"):
        load_map(path)
    # A constant logodds array compresses 1000:1; its declared size gives it away.
    coords = np.zeros((1, 3), int)
    known = np.full((1, 512), 255, np.uint8)
    path = crafted(tmp_path / "zip.npz", 16, coords, known, np.zeros(20_000_000))
    assert path.stat().st_size < 1e6
    with pytest.raises(MapError, match="logodds declares 160,000,128 bytes"):
        load_map(path)
    assert peak_bytes(lambda: load_map(path)) < 50e6


def test_a_sparse_small_map_still_loads(tmp_path: Path) -> None:
    """Below SMALL_MAP_CELLS any density is accepted (a few rays in a fresh map)."""
    coords = np.stack([np.arange(100), np.zeros(100, int), np.zeros(100, int)], axis=1)
    known = np.zeros((100, 512), np.uint8)
    known[:, 0] = 1
    grid = load_map(crafted(tmp_path / "sparse.npz", 16, coords, known, np.full(100, 0.5)))
    assert grid.known_count() == 100


def test_version_2_stores_the_float32_values_as_held(tmp_path: Path) -> None:
    grid = scanned()
    path = save_map(tmp_path / "map.npz", grid)
    with np.load(path) as archive:
        assert int(archive["version"]) == 2
        assert archive["logodds"].dtype == np.float32
        stored = archive["logodds"]
    _, values = grid.blocks()
    expected = values[~np.isnan(values)].astype(np.float32)  # the file's order: block, then j
    np.testing.assert_array_equal(stored, expected)


def test_version_1_files_are_read_with_values_rounded_to_float32(tmp_path: Path) -> None:
    grid = scanned()
    path = save_map(tmp_path / "map.npz", grid)
    with np.load(path) as archive:
        v2_values = archive["logodds"].astype(np.float64)
    # As the float64 grid wrote them: values between float32 steps, inside the clamps.
    v1_values = np.clip(v2_values + 1e-9, grid.params.logodds_min, grid.params.logodds_max)
    assert not np.array_equal(v1_values.astype(np.float32).astype(np.float64), v1_values)
    old = rewrite(path, tmp_path / "v1.npz", version=1, logodds=v1_values)
    loaded = load_map(old)
    (cells, values), (ref_cells, _) = loaded.cells(), grid.cells()
    order, ref_order = np.lexsort(cells.T), np.lexsort(ref_cells.T)
    np.testing.assert_array_equal(cells[order], ref_cells[ref_order])
    np.testing.assert_array_equal(
        np.sort(values), np.sort(v1_values.astype(np.float32).astype(np.float64))
    )
    # A version 1 file with float32 values (or version 2 with float64: twice the bytes its
    # known cells allow) is malformed.
    with pytest.raises(MapError, match="logodds must hold one float64 per known cell"):
        load_map(rewrite(path, tmp_path / "bad1.npz", version=1))
    with pytest.raises(MapError, match=r"logodds declares [\d,]+ bytes, more than"):
        load_map(rewrite(path, tmp_path / "bad2.npz", logodds=v2_values))
