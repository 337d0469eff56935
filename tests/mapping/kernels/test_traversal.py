"""Exact voxel traversal and scan integration against brute force and set-based references."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapping.errors import MapError
from mapping.grid import GridParams, OccupancyGrid
from mapping.kernels.traversal import ray_cells
from tests.mapping.conftest import reference_fusion, room_scan

coordinate = st.floats(-15.0, 15.0, allow_nan=False, allow_subnormal=False)
point = st.tuples(coordinate, coordinate, coordinate).map(np.array)


def segment_box_gap(start: np.ndarray, end: np.ndarray, cell: np.ndarray) -> float:
    """How far (parameter t) the segment misses the unit cube of ``cell``: ≤ 0 if it meets it."""
    d = end - start
    t0, t1 = 0.0, 1.0
    for axis in range(3):
        lo, hi = cell[axis] - start[axis], cell[axis] + 1 - start[axis]
        if d[axis] == 0:
            if not lo <= 0 <= hi:
                return np.inf
            continue
        with np.errstate(over="ignore"):
            a, b = sorted((lo / d[axis], hi / d[axis]))
        t0, t1 = max(t0, a), min(t1, b)
    return t0 - t1


@settings(max_examples=200, deadline=None)
@given(point, point)
def test_traversal_visits_exactly_the_cells_of_a_supersampled_ray(
    start: np.ndarray, end: np.ndarray
) -> None:
    cells = ray_cells(start, end, True)
    # From the start's cell to the end's, one face-neighbour step at a time.
    assert tuple(cells[0]) == tuple(np.floor(start).astype(int))
    assert tuple(cells[-1]) == tuple(np.floor(end).astype(int))
    steps = np.abs(np.diff(cells, axis=0)).sum(axis=1)
    assert np.all(steps == 1)
    assert len(cells) == 1 + int(np.abs(np.floor(end) - np.floor(start)).sum())
    # None skipped: every cell a dense sampling of the segment passes through is visited.
    # (Samples within 1e-9 of a cell face are left out: rounding decides their side.)
    samples = int(np.linalg.norm(end - start) * 1000) + 2
    t = np.linspace(0.0, 1.0, samples)[:, None]
    along = np.vstack([start + t * (end - start), start, end])
    clear = (np.abs(along - np.rint(along)) > 1e-9).all(axis=1)
    sampled = {tuple(c) for c in np.floor(along[clear]).astype(int)}
    visited = {tuple(c) for c in cells}
    assert sampled <= visited
    # None extra: every visited cell meets the segment (a corner or edge touch at worst).
    assert max(segment_box_gap(start, end, c) for c in cells) <= 1e-9


@pytest.mark.parametrize(
    ("start", "end", "expected"),
    [
        ((0.5, 0.5, 0.5), (3.5, 0.5, 0.5), [(0, 0, 0), (1, 0, 0), (2, 0, 0), (3, 0, 0)]),
        ((0.5, 0.5, 0.5), (-1.5, 0.5, 0.5), [(0, 0, 0), (-1, 0, 0), (-2, 0, 0)]),
        # Through a cell edge: y steps before x (OctoMap's tie order: z, then y, then x).
        ((0.5, 0.5, 0.5), (1.5, 1.5, 0.5), [(0, 0, 0), (0, 1, 0), (1, 1, 0)]),
        ((0.5, 0.5, 0.5), (1.5, 0.5, 1.5), [(0, 0, 0), (0, 0, 1), (1, 0, 1)]),
        # Through a corner: z, then y, then x.
        ((0.5, 0.5, 0.5), (1.5, 1.5, 1.5), [(0, 0, 0), (0, 0, 1), (0, 1, 1), (1, 1, 1)]),
        ((0.2, 0.2, 0.2), (0.7, 0.9, 0.1), [(0, 0, 0)]),
    ],
)
def test_traversal_of_axis_aligned_and_tied_rays(
    start: tuple[float, ...], end: tuple[float, ...], expected: list[tuple[int, ...]]
) -> None:
    cells = ray_cells(np.array(start), np.array(end), True)
    assert [tuple(c) for c in cells] == expected
    assert len(ray_cells(np.array(start), np.array(end), False)) == len(expected) - 1


def fused_sets(grid: OccupancyGrid) -> tuple[set[tuple[int, ...]], set[tuple[int, ...]]]:
    cells, values = grid.cells()
    return {tuple(c) for c in cells[values > 0]}, {tuple(c) for c in cells[values < 0]}


@pytest.mark.parametrize(
    ("block", "resolution", "spread", "seed"),
    [(16, 0.1, 1.0, 0), (8, 0.05, 5.0, 1), (4, 0.3, 30.0, 2), (5, 0.1, 3.0, 3),
     (3, 0.05, 20.0, 4), (32, 0.1, 4.0, 5), (2, 0.1, 2.0, 6)],
)  # fmt: skip
def test_scan_integration_matches_insert_point_cloud_semantics(
    block: int, resolution: float, spread: float, seed: int
) -> None:
    # Random scans, some rays longer than the 512-cell cube the kernel tracks around the
    # sensor, blocks that are not powers of two, and a pool that must grow many times.
    rng = np.random.default_rng(seed)
    sensor = rng.uniform(-3, 3, 3)
    points = sensor + rng.normal(0, spread, (int(rng.integers(50, 300)), 3))
    params = GridParams(resolution_m=resolution, block_size_cells=block)
    grid = OccupancyGrid(params, capacity_blocks=1)
    grid.integrate_scan(points, sensor)
    occupied, free = reference_fusion(points, sensor, resolution)
    assert fused_sets(grid) == (occupied, free)
    _, values = grid.cells()
    np.testing.assert_array_equal(
        np.unique(values),
        np.unique(np.float32([params.logodds_miss, params.logodds_hit])),  # stored as float32
    )
    assert grid.cell_updates == len(occupied) + len(free) == grid.known_count()


def test_every_cell_is_updated_once_per_scan_and_again_next_scan() -> None:
    params = GridParams()
    grid = OccupancyGrid(params)
    sensor = np.array([0.05, 0.05, 0.05])
    points = np.repeat([[2.05, 0.05, 0.05]], 500, axis=0)  # 500 identical rays
    grid.integrate_scan(points, sensor)
    values = grid.logodds_at(np.array([[k, 0, 0] for k in range(21)]))
    np.testing.assert_allclose(values[:20], params.logodds_miss, atol=1e-15)
    np.testing.assert_allclose(values[20], params.logodds_hit, atol=1e-15)
    assert grid.cell_updates == 21
    grid.integrate_scan(points, sensor)
    values = grid.logodds_at(np.array([[k, 0, 0] for k in range(21)]))
    np.testing.assert_allclose(values[:20], 2 * params.logodds_miss, atol=1e-15)
    assert grid.scan_count == 2


def test_an_end_point_stays_occupied_when_another_ray_crosses_it() -> None:
    params = GridParams()
    sensor = np.array([0.05, 0.05, 0.05])
    near, far = [1.05, 0.05, 0.05], [3.05, 0.05, 0.05]
    for order in ([near, far], [far, near]):
        grid = OccupancyGrid(params)
        grid.integrate_scan(np.array(order), sensor)
        values = grid.logodds_at(np.array([[10, 0, 0], [30, 0, 0], [20, 0, 0]]))
        np.testing.assert_allclose(
            values, [params.logodds_hit, params.logodds_hit, params.logodds_miss], atol=1e-15
        )


def test_no_return_beams_are_free_up_to_the_cut_off() -> None:
    params = GridParams(no_return_free_m=4.0)
    grid = OccupancyGrid(params)
    sensor = np.array([0.05, 0.05, 0.05])
    grid.integrate_scan(np.zeros((0, 3)), sensor, np.array([[2.0, 0.0, 0.0]]))
    cells, values = grid.cells()
    # Free from the sensor's cell to the one before the cut-off's (4.05 m: cell 40).
    assert sorted(c[0] for c in cells) == list(range(40))
    assert np.all(cells[:, 1:] == 0)
    np.testing.assert_allclose(values, params.logodds_miss)
    silent = OccupancyGrid(GridParams(no_return_free_m=0.0))
    silent.integrate_scan(np.zeros((0, 3)), sensor, np.array([[1.0, 0.0, 0.0]]))
    assert silent.known_count() == 0


def test_no_return_beams_match_the_reference() -> None:
    rng = np.random.default_rng(9)
    sensor = np.array([0.31, -0.42, 0.45])
    directions = rng.normal(size=(200, 3))
    points = room_scan(np.array([2.0, 1.5, 1.2]), azimuth_steps=20, elevation_steps=10) - [
        2.0 - 0.31,
        1.5 + 0.42,
        1.2 - 0.45,
    ]
    params = GridParams(no_return_free_m=2.5)
    grid = OccupancyGrid(params)
    grid.integrate_scan(points, sensor, directions)
    ends = sensor + 2.5 * directions / np.linalg.norm(directions, axis=1, keepdims=True)
    assert fused_sets(grid) == reference_fusion(points, sensor, params.resolution_m, ends)


@pytest.mark.parametrize(
    ("points", "sensor", "directions", "message"),
    [
        ([[1, 2, 3], [np.nan, 0, 0]], [0, 0, 0], None, r"points\[1\] is not finite"),
        ([[1, 2, np.inf]], [0, 0, 0], None, r"points\[0\] is not finite"),
        ([[1, 2, 3]], [0, np.nan, 0], None, r"sensor\[0\] is not finite"),
        ([[1, 2]], [0, 0, 0], None, r"points must be \(N, 3\), got \(1, 2\)"),
        ([[1, 2, 3]], [0, 0, 0], [[0, 0, 0]], r"no_return_directions\[0\] is not a direction"),
        ([[1, 2, 3]], [0, 0, 0], [[1, 0]], r"no_return_directions must be \(M, 3\)"),
        ([[1e9, 0, 0]], [0, 0, 0], None, r"beyond the .* m from the grid origin"),
    ],
)
def test_bad_scans_are_rejected_and_leave_the_grid_as_it_was(
    points: list, sensor: list, directions: list | None, message: str
) -> None:
    grid = OccupancyGrid()
    grid.integrate_scan(np.array([[0.5, 0.5, 0.5]]), np.zeros(3))
    before = grid.cells()
    with pytest.raises(MapError, match=message):
        grid.integrate_scan(
            np.array(points, dtype=float),
            np.array(sensor, dtype=float),
            None if directions is None else np.array(directions, dtype=float),
        )
    after = grid.cells()
    np.testing.assert_array_equal(before[0], after[0])
    np.testing.assert_array_equal(before[1], after[1])


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    resolution=st.sampled_from([0.01, 0.02, 0.05, 0.1]),
    block=st.sampled_from([2, 3, 8, 16]),
    spread=st.floats(0.05, 6.0),
    free_m=st.sampled_from([0.0, 1.5, 7.0]),
)
def test_random_scans_match_the_reference_in_and_beyond_the_cube(
    seed: int, resolution: float, block: int, spread: float, free_m: float
) -> None:
    # At 0.01 m the cube spans ±2.56 m: many rays end beyond it and are walked in two parts.
    rng = np.random.default_rng(seed)
    sensor = rng.uniform(-2, 2, 3)
    points = sensor + rng.normal(0, spread, (int(rng.integers(1, 60)), 3))
    directions = rng.normal(size=(int(rng.integers(0, 20)), 3))
    params = GridParams(resolution_m=resolution, block_size_cells=block, no_return_free_m=free_m)
    grid = OccupancyGrid(params, capacity_blocks=1)  # grows mid-ray, many times
    grid.integrate_scan(points, sensor, directions)
    ends = sensor + free_m * directions / np.linalg.norm(directions, axis=1, keepdims=True)
    occupied, free = reference_fusion(points, sensor, resolution, ends if free_m > 0 else ())
    assert fused_sets(grid) == (occupied, free)
    assert grid.cell_updates == len(occupied) + len(free)


def _scan_with_far_rays(seed: int, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A sensor, ``count`` returns around it (some beyond a fine grid's cube) and no-return
    directions."""
    rng = np.random.default_rng(seed)
    sensor = rng.uniform(-1, 1, 3)
    points = sensor + rng.normal(0, 2.0, (count, 3))
    points[::97] *= 4.0  # far beyond the cube at 0.01 m (±2.56 m)
    return sensor, points, rng.normal(size=(count // 4, 3))


def _pool(grid: OccupancyGrid) -> tuple[np.ndarray, ...]:
    store = grid._store
    used = int(store.count[0])
    return store.coords[:used], store.logodds[:used], store.known[:used]


@pytest.mark.parametrize(("resolution", "block", "threads"),
                         [(0.01, 8, 2), (0.05, 3, 3), (0.2, 16, 2)])  # fmt: skip
def test_rays_walked_side_by_side_give_the_same_grid_bit_for_bit(
    resolution: float, block: int, threads: int
) -> None:
    from mapping.storage import lane_cubes, scan_cube

    params = GridParams(resolution_m=resolution, block_size_cells=block, no_return_free_m=3.0)
    alone = OccupancyGrid(params, capacity_blocks=1)  # grows in every phase, many times
    together = OccupancyGrid(params, capacity_blocks=1)
    for seed in range(3):
        sensor, points, directions = _scan_with_far_rays(seed, 13_000)
        alone.integrate_scan(points, sensor, directions)
        together.integrate_scan(points, sensor, directions, threads=threads)
    for ours, theirs in zip(_pool(together), _pool(alone), strict=True):
        np.testing.assert_array_equal(ours, theirs)
    assert together.cell_updates == alone.cell_updates > 100_000
    # Every bitmap is clear again for the next scan.
    assert not scan_cube().any()
    assert not any(cube.any() for cube in lane_cubes(threads - 1))


@pytest.mark.parametrize("failing", ["helper", "caller"])
def test_a_thread_that_fails_leaves_no_marks_for_the_next_scan(
    monkeypatch: pytest.MonkeyPatch, failing: str
) -> None:
    """A share that fails after marking, on a helper or on the caller's thread (the helper
    then still marking, slowly): the error reaches the caller once every helper is done, and
    the next scan is fused as if alone."""
    import threading
    import time

    import mapping.lanes as lanes_module

    sensor, points, directions = _scan_with_far_rays(5, 12_000)
    params = GridParams(resolution_m=0.05, no_return_free_m=3.0)
    next_scan = _scan_with_far_rays(6, 12_000)  # elsewhere: stale marks would show in it
    reference = OccupancyGrid(params)
    reference.integrate_scan(next_scan[1], next_scan[0], next_scan[2])
    real = lanes_module.mark_rays

    def fails(*args: object) -> int:
        on_helper = threading.current_thread() is not threading.main_thread()
        if on_helper and failing == "caller":
            time.sleep(0.2)  # still marking when the caller fails
        result = real(*args)  # its marks are made, then it fails
        if on_helper:
            helper_done.append(True)
        if on_helper == (failing == "helper"):
            raise RuntimeError(f"{failing} failed")
        return result

    helper_done: list[bool] = []
    grid = OccupancyGrid(params)
    monkeypatch.setattr(lanes_module, "mark_rays", fails)
    with pytest.raises(RuntimeError, match=f"{failing} failed"):
        grid.integrate_scan(points, sensor, directions, threads=2)
    assert helper_done  # the helper finished its share before the error came out
    monkeypatch.setattr(lanes_module, "mark_rays", real)
    again = OccupancyGrid(params)
    again.integrate_scan(next_scan[1], next_scan[0], next_scan[2], threads=2)
    for ours, theirs in zip(_pool(again), _pool(reference), strict=True):
        np.testing.assert_array_equal(ours, theirs)


def test_a_small_scan_is_walked_on_one_thread_and_threads_below_one_are_refused(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import mapping.grid as grid_module

    def never(*args: object) -> None:
        raise AssertionError("a scan of fewer than 2 × 4,096 rays was shared out")

    monkeypatch.setattr(grid_module, "mark_side_by_side", never)
    sensor, points, directions = _scan_with_far_rays(1, 6_000)
    grid = OccupancyGrid(GridParams(resolution_m=0.1))
    grid.integrate_scan(points, sensor, directions, threads=4)
    assert grid.cell_updates > 1_000
    with pytest.raises(MapError, match="threads must be at least 1, got 0"):
        grid.integrate_scan(points, sensor, threads=0)
