"""Local and global maps: fusing scans at poses, moving grids between frames, merging."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from mapping.band import band_layers, band_slab_m
from mapping.errors import MapError
from mapping.fusion import (
    Scan,
    check_rigid,
    fuse_scans,
    merge_grids,
    rays_into_slab,
    transform_grid,
)
from mapping.grid import GridParams, OccupancyGrid
from sensors.geometry.frames import pose2_matrix
from tests.mapping.conftest import room_scan

#: The room's corner, off the lattice's planes (surfaces on cell faces make rounding decide).
CORNER = np.array([0.013, 0.047, -0.031])


def scans_in_room(count: int = 3, seed: int = 0) -> tuple[list[Scan], list[np.ndarray]]:
    """Scans of the box room from ``count`` poses, each in its own scanner frame."""
    rng = np.random.default_rng(seed)
    scans, poses = [], []
    for _ in range(count):
        x, y, yaw = rng.uniform(0.8, 3.2), rng.uniform(0.8, 2.2), rng.uniform(-np.pi, np.pi)
        T = pose2_matrix(x, y, yaw, z_m=0.45)
        points_map = room_scan(T[:3, 3] - CORNER, azimuth_steps=90, elevation_steps=30) + CORNER
        scans.append(Scan(points_map @ T[:3, :3] + -T[:3, 3] @ T[:3, :3]))
        poses.append(T)
    return scans, poses


def as_dict(grid: OccupancyGrid) -> dict[tuple[int, ...], float]:
    cells, values = grid.cells()
    return {tuple(c): float(v) for c, v in zip(cells, values, strict=True)}


def test_fusing_scans_at_poses_is_integrating_them_in_the_frame() -> None:
    scans, poses = scans_in_room()
    params = GridParams()
    fused = fuse_scans(scans, poses, params)
    direct = OccupancyGrid(params)
    for scan, T in zip(scans, poses, strict=True):
        direct.integrate_scan(scan.points_scanner @ T[:3, :3].T + T[:3, 3], T[:3, 3])
    assert as_dict(fused) == pytest.approx(as_dict(direct), abs=1e-12)
    assert fused.scan_count == 3


def test_a_local_map_moved_into_the_map_frame_equals_fusing_there() -> None:
    # A local map in the reference robot's frame, then moved by a lattice-preserving pose
    # (90° and whole cells), against the same scans fused directly in the map frame.
    scans, T_map_scanner = scans_in_room(seed=1)
    T_map_ref = pose2_matrix(3.0, -2.0, math.pi / 2)
    T_ref_map = np.linalg.inv(T_map_ref)
    params = GridParams()
    local = fuse_scans(scans, [T_ref_map @ T for T in T_map_scanner], params)
    moved = as_dict(transform_grid(local, T_map_ref))
    direct = as_dict(fuse_scans(scans, T_map_scanner, params))
    same = sum(1 for c, v in direct.items() if c in moved and abs(moved[c] - v) < 1e-9)
    assert same / len(direct) > 0.999  # a ray through a cell edge may round either way
    assert abs(len(moved) - len(direct)) / len(direct) < 0.001


@pytest.mark.parametrize("yaw_deg", [90, 180, -90])
def test_moving_by_lattice_poses_and_back_is_exact(yaw_deg: float) -> None:
    scans, poses = scans_in_room(seed=2)
    grid = fuse_scans(scans, poses, GridParams(block_size_cells=8))
    T = pose2_matrix(1.2, -3.5, math.radians(yaw_deg), z_m=0.7)
    there = transform_grid(grid, T)
    back = transform_grid(there, np.linalg.inv(T))
    assert as_dict(back) == as_dict(grid)
    assert there.known_count() == grid.known_count()


def test_moving_by_any_pose_keeps_the_occupied_surfaces() -> None:
    scans, poses = scans_in_room(seed=3)
    grid = fuse_scans(scans, poses, GridParams())
    T = pose2_matrix(0.37, 0.21, 0.3)
    moved = transform_grid(grid, T)
    cells, _ = grid.occupied()
    moved_cells, _ = moved.occupied()
    assert abs(len(moved_cells) - len(cells)) / len(cells) < 0.05
    expected = grid.cell_centers(cells) @ T[:3, :3].T + T[:3, 3]
    distance, _ = cKDTree(moved.cell_centers(moved_cells)).query(expected)
    # Nearest-cell resampling: centres move by at most half a cell diagonal, mostly less.
    assert np.percentile(distance, 95) <= 0.1 * math.sqrt(3) / 2 + 1e-9
    assert abs(moved.known_count() - grid.known_count()) / grid.known_count() < 0.05


def test_merging_grids_fuses_every_cell() -> None:
    scans, poses = scans_in_room(count=2, seed=4)
    params = GridParams()
    a = fuse_scans(scans[:1], poses[:1], params)
    b = fuse_scans(scans[1:], poses[1:], params)
    merged = merge_grids([a, b])
    da, db, dm = as_dict(a), as_dict(b), as_dict(merged)
    assert dm.keys() == da.keys() | db.keys()
    for cell, value in dm.items():
        expected = np.clip(da.get(cell, 0.0) + db.get(cell, 0.0), params.logodds_min, 10.0)
        assert value == pytest.approx(min(expected, params.logodds_max), abs=1e-12)
    assert as_dict(a) == da  # the inputs are untouched


def test_merging_needs_one_lattice() -> None:
    a, b = OccupancyGrid(), OccupancyGrid(GridParams(origin_m=(0.05, 0.0, 0.0)))
    with pytest.raises(MapError, match="cannot merge grids on different lattices"):
        a.merge(b)
    with pytest.raises(MapError, match="nothing to merge"):
        merge_grids([])


@pytest.mark.parametrize(
    ("T", "message"),
    [
        (np.eye(3), r"must be a 4×4 matrix, got shape \(3, 3\)"),
        (np.diag([2.0, 1.0, 1.0, 1.0]), "is not a rigid transform"),
        (np.diag([-1.0, 1.0, 1.0, 1.0]), "is not a rigid transform"),
        (np.full((4, 4), np.nan), "has non-finite entries"),
        (np.diag([1.0, 1.0, 1.0, 1.0 + 2e-5]), "is not a rigid transform"),  # beyond allclose
        (np.eye(4) + np.eye(4, k=-3) * 2e-6, "is not a rigid transform"),
        (np.eye(4)[[1, 0, 2, 3]], "is not a rigid transform"),  # a reflection
    ],
)
def test_poses_must_be_rigid(T: np.ndarray, message: str) -> None:
    with pytest.raises(MapError, match=message):
        check_rigid(T)
    scans, _ = scans_in_room(count=1)
    if T.shape == (4, 4):
        with pytest.raises(MapError, match=rf"T_frame_scanner\[0\] {message}"):
            fuse_scans(scans, [T], GridParams())
    else:
        with pytest.raises(MapError, match=r"need one 4×4 pose per scan, got .* \(1, 3, 3\)"):
            fuse_scans(scans, [T], GridParams())


def test_a_pose_within_np_allclose_of_rigid_is_rigid() -> None:
    T = pose2_matrix(1.0, 2.0, 0.3, z_m=0.45)
    off = T + np.eye(4, k=-3) * 0.9e-6  # the bottom row within the absolute tolerance
    scaled = np.diag([1.0, 1.0, 1.0, 1.0 + 1.05e-5])  # within np.allclose's relative one
    for pose in (T, off, scaled):
        assert np.allclose(pose[3], [0, 0, 0, 1], atol=1e-6)
        np.testing.assert_array_equal(check_rigid(pose), pose)


def test_scan_and_pose_lists_must_match() -> None:
    scans, poses = scans_in_room(count=2)
    with pytest.raises(MapError, match="need one pose per scan: 1 poses for 2 scans"):
        fuse_scans(scans, poses[:1], GridParams())
    with pytest.raises(MapError, match=r"Scan.points_scanner must be \(N, 3\)"):
        Scan(np.zeros((3, 2)))
    with pytest.raises(MapError, match="the grid's parameters differ"):
        fuse_scans(scans, poses, GridParams(), OccupancyGrid(GridParams(resolution_m=0.2)))
    with pytest.raises(MapError, match="transform_grid keeps the resolution"):
        transform_grid(OccupancyGrid(), np.eye(4), GridParams(resolution_m=0.2))


def test_grids_fused_on_threads_at_once_equal_grids_fused_one_by_one() -> None:
    """The fusion kernel releases the GIL and each thread has its own de-duplication bitmap:
    grids fused side by side are cell for cell the ones fused in turn."""
    from concurrent.futures import ThreadPoolExecutor

    params = GridParams(resolution_m=0.05)
    jobs = [scans_in_room(count=4, seed=seed) for seed in range(6)]
    alone = [as_dict(fuse_scans(scans, poses, params)) for scans, poses in jobs]
    with ThreadPoolExecutor(max_workers=3) as pool:
        together = list(pool.map(lambda job: as_dict(fuse_scans(*job, params)), jobs))
    assert all(len(cells) > 10_000 for cells in alone)
    assert together == alone


def test_each_thread_has_its_own_scan_cube() -> None:
    from concurrent.futures import ThreadPoolExecutor

    from mapping.storage import discard_scan_cube, scan_cube

    here = scan_cube()
    assert scan_cube() is here
    with ThreadPoolExecutor(max_workers=1) as pool:
        there = pool.submit(scan_cube).result()
    assert there is not here
    assert not there.any()
    discard_scan_cube()
    assert scan_cube() is not here


@pytest.mark.parametrize("band", [(1.5, 2.0), (0.1, 0.4), (2.2, 2.6)])
def test_a_slab_fuses_the_bands_cells_as_every_ray_does(band: tuple[float, float]) -> None:
    scans, poses = scans_in_room(count=4, seed=3)
    params = GridParams()
    slab = band_slab_m(0.0, params.resolution_m, *band)
    every = fuse_scans(scans, poses, params)
    some = fuse_scans(scans, poses, params, z_slab=slab)
    layers = band_layers(0.0, params.resolution_m, *band)
    inside = {c: v for c, v in as_dict(every).items() if layers[0] <= c[2] <= layers[1]}
    assert inside
    assert {c: v for c, v in as_dict(some).items() if layers[0] <= c[2] <= layers[1]} == inside
    cast = sum(
        int(rays_into_slab(s.points_scanner @ T[2, :3] + T[2, 3], T[2, 3], *slab).sum())
        for s, T in zip(scans, poses, strict=True)
    )
    total = sum(len(s.points_scanner) for s in scans)
    if band[0] > 0.45:  # above the scanner: the floor's rays are left out
        assert cast < 0.8 * total
        assert len(as_dict(some)) < len(as_dict(every))


def test_rays_into_a_slab_are_those_that_reach_its_heights() -> None:
    heights = np.array([
        3.0,  # up through the slab
        0.0,  # down to the floor: below it
        1.0,  # ends at its bottom
        0.99,  # ends just below
        np.nan,  # not a point: kept, for the grid to refuse
    ])  # fmt: skip
    assert rays_into_slab(heights, 0.5, 1.0, 2.0).tolist() == [True, False, True, False, True]
    # From above it: down through it.
    assert rays_into_slab(heights[:4], 2.5, 1.0, 2.0).tolist() == [False, True, True, True]
    # A point that is not finite is cast even where its height lies below the slab: refused.
    for bad in ([1.0, 0.0, np.nan], [np.nan, 0.0, 0.0]):
        points = np.array([[1.0, 0.0, 3.0], bad])
        with pytest.raises(MapError, match="finite"):
            fuse_scans([Scan(points)], [np.eye(4)], GridParams(), z_slab=(1.0, 2.0))


def test_a_bands_slab_spares_a_cell_on_either_side() -> None:
    low, high = band_slab_m(0.0, 0.1, 2.3, 2.9)
    assert (low, high) == pytest.approx((2.2, 3.0))
    first, last = band_layers(0.0, 0.1, 2.3, 2.9)
    assert low == pytest.approx((first - 1) * 0.1)
    assert high == pytest.approx((last + 2) * 0.1)
    with pytest.raises(MapError, match="no cell centre"):
        band_slab_m(0.0, 0.1, 2.31, 2.32)
