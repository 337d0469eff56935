"""Block storage: float32 log-odds, their clamping bounds, and the grid's memory accounting."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mapping.grid import GridParams, OccupancyGrid
from mapping.storage import LOGODDS_DTYPE, BlockStorage, stored_bounds
from tests.mapping.conftest import room_scan


@settings(max_examples=300, deadline=None)
@given(st.floats(-20.0, -1e-3), st.floats(1e-3, 20.0))
def test_stored_bounds_are_the_nearest_float32_inside(l_min: float, l_max: float) -> None:
    low, high = stored_bounds(l_min, l_max)
    assert l_min <= low
    assert high <= l_max
    for value, outward in ((low, -np.inf), (high, np.inf)):
        assert float(np.float32(value)) == value  # representable: storing it is exact
        beyond = float(np.nextafter(np.float32(value), np.float32(outward)))
        assert not l_min <= beyond <= l_max  # the next float32 outwards leaves the bounds


def test_clamped_cells_stay_inside_the_float64_bounds() -> None:
    params = GridParams()
    grid = OccupancyGrid(params)
    cell = np.array([[0, 0, 0], [1, 0, 0]])
    grid.apply_evidence(np.repeat(cell[:1], 40, axis=0), np.full(40, 0.9))
    grid.apply_evidence(np.repeat(cell[1:], 40, axis=0), np.full(40, 0.1))
    high, low = grid.logodds_at(cell)
    assert params.logodds_max - 5e-7 < high <= params.logodds_max
    assert params.logodds_min <= low < params.logodds_min + 5e-7


def test_the_pool_holds_float32_log_odds() -> None:
    store = BlockStorage(16, 4)
    assert store.logodds.dtype == LOGODDS_DTYPE == np.float32
    assert store.logodds.shape == (4, 4096)
    store.grow()
    assert store.logodds.dtype == np.float32
    assert store.capacity == 8


def test_memory_is_every_array_of_the_pool_and_its_table() -> None:
    grid = OccupancyGrid(GridParams(), capacity_blocks=8)
    sensor = np.array([2.0, 1.5, 1.0])
    grid.integrate_scan(room_scan(sensor), sensor)
    store = grid._store
    per_block = 4096 * 4 + 2 * 512 + 3 * 8 + 8  # log-odds, known and scan bits, coords, scan id
    assert grid.memory_bytes() == store.capacity * per_block + store.table.nbytes
    # Half of a float64 grid's log-odds: 4.25 B a cell of the pool, known or not.
    assert grid.memory_bytes() < store.capacity * 4096 * 4.4 + store.table.nbytes
    assert grid.memory_bytes() / grid.known_count() < 30  # OctoMap: ~31 B per leaf at 0.1 m
