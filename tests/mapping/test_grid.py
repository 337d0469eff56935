"""The grid's storage: growth that follows the observed volume, queries, construction, errors."""

from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest

from mapping.errors import MapError
from mapping.grid import GridParams, OccupancyGrid
from tests.mapping.conftest import room_scan


def test_a_building_sized_map_does_not_allocate_its_bounding_box() -> None:
    # Rooms at the four corners and the middle of a 200 m × 200 m × 4 m building at 0.1 m.
    # Its bounding box would be 2000 × 2000 × 40 cells: 1.28 GB of float64 log-odds.
    box_bytes = 2000 * 2000 * 40 * 8
    grid = OccupancyGrid(GridParams(resolution_m=0.1))
    tracemalloc.start()
    try:
        for corner in ([0, 0], [196, 0], [0, 197], [196, 197], [98, 98]):
            sensor = np.array([2.0, 1.5, 1.0])
            offset = np.array([*corner, 0.0])
            grid.integrate_scan(room_scan(sensor) + offset, sensor + offset)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    low, high = grid.bounds_cells()
    span = (high - low + 1).tolist()
    assert 2000 <= span[0] <= 2002  # it spans the building …
    assert 2000 <= span[1] <= 2002
    assert span[2] == 26
    assert grid.memory_bytes() < box_bytes / 50  # … but holds five rooms' worth of blocks
    assert peak < box_bytes / 25
    # The blocks in use are the rooms' (4 m × 3 m × 2.5 m: at most 4 × 3 × 2 blocks of 1.6 m).
    assert 5 * 3 * 2 * 2 <= grid.block_count <= 5 * 4 * 3 * 2
    # Memory grows with the blocks, not with the extent: within a factor 2 of what they need.
    block_bytes = 16**3 * (8 + 2 / 8)
    assert grid.memory_bytes() < 2 * max(grid.block_count, 256) * block_bytes + 1e6


def test_growth_keeps_every_cell() -> None:
    sensor = np.array([2.0, 1.5, 1.0])
    reference = OccupancyGrid(capacity_blocks=4096)
    reference.integrate_scan(room_scan(sensor), sensor)
    grown = OccupancyGrid(capacity_blocks=1)
    grown.integrate_scan(room_scan(sensor), sensor)
    a, b = reference.cells(), grown.cells()
    order_a, order_b = np.lexsort(a[0].T), np.lexsort(b[0].T)
    np.testing.assert_array_equal(a[0][order_a], b[0][order_b])
    np.testing.assert_array_equal(a[1][order_a], b[1][order_b])


def test_queries_on_known_and_unknown_cells() -> None:
    params = GridParams()
    grid = OccupancyGrid(params)
    grid.integrate_scan(np.array([[1.05, 0.05, 0.05]]), np.array([0.05, 0.05, 0.05]))
    values = grid.logodds_at(np.array([[10, 0, 0], [3, 0, 0], [0, 5, 0]]))
    assert values[0] == pytest.approx(params.logodds_hit)
    assert values[1] == pytest.approx(params.logodds_miss)
    assert math.isnan(values[2])
    p = grid.probability_at(np.array([[1.01, 0.02, 0.03], [0.3, 0.0, 0.0], [9.0, 9.0, 9.0]]))
    np.testing.assert_allclose(p, [0.7, 0.4, 0.5], atol=1e-12)
    cells, probability = grid.occupied()
    assert cells.tolist() == [[10, 0, 0]]
    np.testing.assert_allclose(probability, [0.7])
    assert len(grid.occupied(threshold=0.75)[0]) == 0
    np.testing.assert_allclose(grid.cell_centers(cells), [[1.05, 0.05, 0.05]])
    assert grid.cell_of(np.array([[-0.01, 0.0, 0.25]])).tolist() == [[-1, 0, 2]]


def scanned_room(block: int) -> OccupancyGrid:
    """A grid of blocks of ``block`` cells holding one scan of the room."""
    sensor = np.array([2.0, 1.5, 1.0])
    grid = OccupancyGrid(GridParams(block_size_cells=block))
    grid.integrate_scan(room_scan(sensor), sensor)
    return grid


@pytest.mark.parametrize("block", [16, 8, 6])
def test_cells_of_some_layers(block: int) -> None:
    grid = scanned_room(block)
    every, values = grid.cells()
    # Every layer: what unpacking the known bits block by block (np.nonzero's order) gives.
    n = grid.block_count
    bits = np.unpackbits(grid._store.known[:n], axis=1, bitorder="little")[:, : block**3]
    rows, flat = np.nonzero(bits)
    cells = grid._store.coords[:n][rows] * block + grid._local_of_flat()[flat]
    assert np.array_equal(every, cells)
    assert np.array_equal(values, grid._store.logodds[:n][rows, flat].astype(np.float64))
    # Arrays of just the known cells (not views of a buffer for every cell of the blocks).
    tracemalloc.start()
    try:
        grid.cells()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 33 * len(every) + 65536
    for first, last in [(20, 22), (0, 0), (15, 16), (-5, 2), (-40, 60), (23, 20), (500, 600)]:
        band, band_values = grid.cells(z_range=(first, last))
        keep = (every[:, 2] >= first) & (every[:, 2] <= last)
        # Only those layers' bits are read, and the cells come in the same order.
        assert np.array_equal(band, every[keep])
        assert np.array_equal(band_values, values[keep])
        assert band.dtype == np.int64
        assert band_values.dtype == np.float64
    assert len(grid.cells(z_range=(20, 22))[0]) > 0
    assert len(grid.cells(z_range=(-40, 60))[0]) == len(every)


@pytest.mark.parametrize("block", [16, 8, 6])
def test_known_blocks_are_the_dense_blocks_packed(block: int) -> None:
    grid = scanned_room(block)
    coords, values = grid.blocks()
    known_coords, bits, known_values = grid.known_blocks()
    flat = values.reshape(len(coords), -1)
    known = ~np.isnan(flat)
    assert np.array_equal(known_coords, coords)
    assert np.array_equal(bits, np.packbits(known, axis=1, bitorder="little"))
    assert known_values.dtype == np.float32
    assert np.array_equal(known_values.astype(np.float64), flat[known])
    assert len(known_values) == grid.known_count() > 1000
    empty = OccupancyGrid(GridParams(block_size_cells=block)).known_blocks()
    assert [a.shape for a in empty] == [(0, 3), (0, (block**3 + 7) // 8), (0,)]


def test_origin_shifts_the_lattice() -> None:
    grid = OccupancyGrid(GridParams(origin_m=(0.05, -0.05, 0.0)))
    assert grid.cell_of(np.array([[0.06, -0.04, 0.01], [0.04, 0.0, 0.0]])).tolist() == [
        [0, 0, 0],
        [-1, 0, 0],
    ]
    np.testing.assert_allclose(grid.cell_centers(np.array([[0, 0, 0]])), [[0.1, 0.0, 0.05]])


def test_a_copy_is_independent() -> None:
    sensor = np.array([2.0, 1.5, 1.0])
    grid = OccupancyGrid()
    grid.integrate_scan(room_scan(sensor, azimuth_steps=36, elevation_steps=12), sensor)
    copy = grid.copy()
    before = grid.cells()
    copy.integrate_scan(np.array([[9.0, 9.0, 2.0]]), sensor)
    after = grid.cells()
    np.testing.assert_array_equal(before[0], after[0])
    assert copy.known_count() > grid.known_count()


def test_blocks_round_trip() -> None:
    sensor = np.array([2.0, 1.5, 1.0])
    grid = OccupancyGrid(GridParams(block_size_cells=6))
    grid.integrate_scan(room_scan(sensor, azimuth_steps=36, elevation_steps=12), sensor)
    coords, values = grid.blocks()
    assert values.shape == (len(coords), 6, 6, 6)
    rebuilt = OccupancyGrid.from_blocks(grid.params, coords, values)
    a, b = grid.cells(), rebuilt.cells()
    assert {tuple(c): v for c, v in zip(*a, strict=True)} == {
        tuple(c): v for c, v in zip(*b, strict=True)
    }


@pytest.mark.parametrize(
    ("coords", "shape", "message"),
    [
        ([[0, 0, 0], [0, 0, 0]], (2, 4, 4, 4), "block coordinates are not unique"),
        ([[0, 0, 0]], (1, 4, 4, 3), r"block values must be \(1, 4, 4, 4\)"),
        ([[0.5, 0, 0]], (1, 4, 4, 4), r"block coordinates must be \(B, 3\) integers"),
        ([[2**21, 0, 0]], (1, 4, 4, 4), "block coordinate 2097152 beyond"),
    ],
)
def test_bad_blocks_are_rejected(coords: list, shape: tuple[int, ...], message: str) -> None:
    with pytest.raises(MapError, match=message):
        OccupancyGrid.from_blocks(GridParams(block_size_cells=4), np.array(coords), np.zeros(shape))


def test_infinite_block_values_are_rejected() -> None:
    values = np.zeros((1, 4, 4, 4))
    values[0, 1, 2, 3] = np.inf
    with pytest.raises(MapError, match="finite or NaN"):
        OccupancyGrid.from_blocks(GridParams(block_size_cells=4), np.zeros((1, 3), int), values)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"resolution_m": 0.0}, "resolution_m must be a positive number, got 0.0"),
        ({"resolution_m": float("nan")}, "resolution_m must be a positive number"),
        ({"resolution_m": 0.0005}, r"resolution_m must be at least 0.005 m, got 0.0005"),
        ({"prob_hit": 1.0}, r"prob_hit must lie in \(0, 1\), got 1.0"),
        ({"prob_hit": 0.4}, r"need prob_miss < 0.5 < prob_hit"),
        ({"prob_miss": 0.6}, r"need prob_miss < 0.5 < prob_hit"),
        ({"clamp_max": 0.45}, "need clamp_min < occupied_threshold < clamp_max"),
        ({"no_return_free_m": -1.0}, "no_return_free_m must be ≥ 0"),
        ({"block_size_cells": 1}, r"block_size_cells must be an integer in \[2, 256\]"),
        ({"block_size_cells": 8.0}, r"block_size_cells must be an integer"),
        ({"origin_m": (0.0, 0.0)}, "origin_m must be three finite numbers"),
    ],
)
def test_bad_parameters_are_rejected(kwargs: dict, message: str) -> None:
    with pytest.raises(MapError, match=message):
        GridParams(**kwargs)


def test_bad_cells_are_rejected() -> None:
    grid = OccupancyGrid()
    with pytest.raises(MapError, match=r"cells must be integers, got float64"):
        grid.logodds_at(np.zeros((1, 3)))
    with pytest.raises(MapError, match=r"cells must be \(N, 3\)"):
        grid.logodds_at(np.zeros((3,), int))
    with pytest.raises(MapError, match="beyond the addressable map"):
        grid.apply_evidence(np.array([[2**40, 0, 0]]), np.array([0.7]))
    with pytest.raises(MapError, match="the grid is empty"):
        grid.bounds_cells()
    with pytest.raises(MapError, match=r"need one value per cell: 1 for 2"):
        OccupancyGrid.from_cells(GridParams(), np.zeros((2, 3), int), np.zeros(1))


@pytest.mark.parametrize("seed", range(6))
def test_the_bounds_of_the_known_cells_are_those_of_the_listed_cells(seed: int) -> None:
    """Scattered cells in blocks of every sign, some blocks known only in part: the bounds read
    from the edge blocks alone are the listed cells' extremes."""
    rng = np.random.default_rng(seed)
    grid = OccupancyGrid(GridParams(resolution_m=0.1, block_size_cells=8))
    cells = rng.integers(-70, 70, size=(int(rng.integers(1, 40)), 3))
    grid.apply_evidence(cells, np.full(len(cells), 0.7))
    listed, _ = grid.cells()
    low, high = grid.bounds_cells()
    np.testing.assert_array_equal(low, listed.min(axis=0))
    np.testing.assert_array_equal(high, listed.max(axis=0))
    np.testing.assert_array_equal(low, cells.min(axis=0))
