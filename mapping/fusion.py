"""Local and global maps: fusing raw scans with given poses, moving grids between frames, merging.

A *local* map is built in the reference robot's frame (the scans' poses given in that frame); the
*global* map is re-fused from every raw scan with the optimized poses in the map frame
(docs/design.md §6) — the step that runs after every optimization. Grids built elsewhere are brought
into a frame with ``transform_grid`` and fused with ``merge_grids`` (paper eq. 3 per cell).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from mapping.errors import MapError
from mapping.grid import GridParams, OccupancyGrid
from mapping.kernels.cells import resample_blocks

__all__ = ["Scan", "check_rigid", "fuse_scans", "merge_grids", "rays_into_slab", "transform_grid"]


def _no_returns() -> np.ndarray:
    return np.zeros((0, 3), dtype=np.float64)


@dataclass(frozen=True)
class Scan:
    """One 3D scan in its scanner's frame: returns, and directions of beams without a return."""

    points_scanner: np.ndarray  # (N, 3) metres, float64 or float32 (kept as given)
    no_return_scanner: np.ndarray = field(default_factory=_no_returns)  # (M, 3) directions

    def __post_init__(self) -> None:
        for name in ("points_scanner", "no_return_scanner"):
            value = np.asarray(getattr(self, name))
            if value.dtype != np.float32:  # float32 points are moved into float64 scan by scan
                value = np.asarray(value, dtype=np.float64)
            if value.ndim != 2 or value.shape[1] != 3:
                raise MapError(f"Scan.{name} must be (N, 3), got {value.shape}")
            object.__setattr__(self, name, value)


def check_rigid(T: np.ndarray, name: str = "T", tolerance: float = 1e-6) -> np.ndarray:
    """``T`` as a float (4, 4) rigid transform; MapError unless it is one (within tolerance)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise MapError(f"{name} must be a 4×4 matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise MapError(f"{name} has non-finite entries")
    R = T[:3, :3]
    # np.allclose's test (|a − b| ≤ atol + 1e-5 |b|) and the determinant's sign, written out: a
    # fusion checks every scan's pose, and np.allclose took 30 µs a call.
    (a, b, c), (d, e, f), (g, h, i) = R.tolist()
    if (
        not np.all(np.abs(T[3] - _BOTTOM) <= tolerance + 1e-5 * _BOTTOM)
        or not np.all(np.abs(R.T @ R - _EYE) <= tolerance + 1e-5 * _EYE)
        or a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) < 0
    ):
        raise MapError(f"{name} is not a rigid transform (rotation and translation)")
    return T


_BOTTOM = np.array([0.0, 0.0, 0.0, 1.0])
_EYE = np.eye(3)


def fuse_scans(
    scans: Sequence[Scan],
    T_frame_scanner: Sequence[np.ndarray] | np.ndarray,
    params: GridParams,
    grid: OccupancyGrid | None = None,
    *,
    threads: int = 1,
    z_slab: tuple[float, float] | None = None,
) -> OccupancyGrid:
    """Integrate every scan at its pose into ``grid`` (a new one with ``params`` if None).

    ``T_frame_scanner[i]`` (4, 4) maps scan i's points into the grid's frame: the map frame for
    the global map, the reference robot's frame for a local map. ``threads``: as in
    :meth:`OccupancyGrid.integrate_scan` (the same grid, sooner). ``z_slab`` (low, high): only
    the returns whose ray from the scanner reaches between these heights are cast (beams
    without a return all are); a map that is only cut into a band (:func:`mapping.band.band_slab_m`)
    gets the band's cells as with every ray, for the rays' share in the slab (a station map's
    ceiling band: a third of them). Every cell outside the slab is left out or in part.
    """
    poses = np.asarray(T_frame_scanner, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise MapError(f"need one 4×4 pose per scan, got an array of shape {poses.shape}")
    if len(poses) != len(scans):
        raise MapError(f"need one pose per scan: {len(poses)} poses for {len(scans)} scans")
    if grid is None:
        grid = OccupancyGrid(params)
    elif grid.params != params:
        raise MapError("the grid's parameters differ from the ones given")
    for i, (scan, T) in enumerate(zip(scans, poses, strict=True)):
        T = check_rigid(T, f"T_frame_scanner[{i}]")
        R, t = T[:3, :3], T[:3, 3]
        no_return = scan.no_return_scanner @ R.T if len(scan.no_return_scanner) else None
        points = scan.points_scanner @ R.T + t
        if z_slab is not None:
            cast = rays_into_slab(points[:, 2], float(t[2]), *z_slab)
            points = points[cast | ~np.isfinite(points).all(axis=1)]  # the grid refuses those
        grid.integrate_scan(points, t, no_return, threads=threads)
    return grid


def rays_into_slab(heights: np.ndarray, origin_z_m: float, low_m: float,
                   high_m: float) -> np.ndarray:  # fmt: skip
    """(N,) bool: which rays from a scanner at height ``origin_z_m`` to points at ``heights``
    (N,) reach heights in [``low_m``, ``high_m``]; true for a height that is not finite (the
    grid refuses its point, as it would without the slab)."""
    top, bottom = np.maximum(heights, origin_z_m), np.minimum(heights, origin_z_m)
    return np.asarray(((top >= low_m) & (bottom <= high_m)) | ~np.isfinite(heights))


def merge_grids(grids: Sequence[OccupancyGrid]) -> OccupancyGrid:
    """One grid holding the eq. 3 fusion of all ``grids`` (same lattice), cell by cell."""
    if not grids:
        raise MapError("nothing to merge: no grids given")
    merged = grids[0].copy()
    for other in grids[1:]:
        merged.merge(other)
    return merged


def _target_blocks(grid: OccupancyGrid, T_a_b: np.ndarray, params: GridParams) -> np.ndarray:
    """Blocks of a grid in frame a that can receive cells of ``grid`` (frame b) moved by T_a_b."""
    coords, known, _ = grid.known_blocks()
    coords = coords[known.any(axis=1)]
    if len(coords) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    src_edge = grid.params.block_size_cells * grid.resolution_m
    dst_edge = params.block_size_cells * params.resolution_m
    corners = np.array(list(itertools.product((0.0, 1.0), repeat=3)))
    boxes_b = grid.origin_m + (coords[:, None, :] + corners[None]) * src_edge  # (B, 8, 3)
    boxes_a = boxes_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]
    origin_a = np.asarray(params.origin_m)
    low = np.floor((boxes_a.min(axis=1) - origin_a) / dst_edge).astype(np.int64)
    high = np.floor((boxes_a.max(axis=1) - origin_a) / dst_edge).astype(np.int64)
    span = int((high - low).max()) + 1
    offsets = np.array(list(itertools.product(range(span), repeat=3)), dtype=np.int64)
    candidates = low[:, None, :] + offsets[None]  # (B, span³, 3)
    inside = (candidates <= high[:, None, :]).all(axis=2)
    return np.asarray(np.unique(candidates[inside], axis=0))


def transform_grid(
    grid: OccupancyGrid, T_a_b: np.ndarray, params: GridParams | None = None
) -> OccupancyGrid:
    """The grid (frame b) seen from frame a: each cell of the new grid takes the cell of
    ``grid`` that contains its centre mapped back by T_b_a (nearest-cell resampling).

    The new grid has ``params`` (default: those of ``grid``; the lattice is anchored at
    ``origin_m`` in frame a). A transform that maps the lattice onto itself (a translation by
    whole cells, rotations by multiples of 90° about the axes) moves every cell exactly.
    """
    T_a_b = check_rigid(T_a_b, "T_a_b")
    params = grid.params if params is None else params
    if params.resolution_m != grid.resolution_m:
        raise MapError(
            f"transform_grid keeps the resolution: {grid.resolution_m} m, "
            f"not {params.resolution_m} m"
        )
    if params.block_size_cells != grid.params.block_size_cells:
        raise MapError("transform_grid keeps the block size")
    T_b_a = np.linalg.inv(T_a_b)
    targets = _target_blocks(grid, T_a_b, params)
    out = OccupancyGrid(params, capacity_blocks=max(1, len(targets)))
    src, dst = grid._store, out._store
    start = 0
    while True:
        start = resample_blocks(
            targets,
            T_b_a,
            np.asarray(params.origin_m, dtype=np.float64),
            grid.origin_m,
            grid.resolution_m,
            src.table[0],
            src.table[1],
            src.shift,
            src.logodds,
            src.known,
            dst.table[0],
            dst.table[1],
            dst.shift,
            dst.coords,
            dst.count,
            dst.logodds,
            dst.known,
            dst.block_scan,
            dst.lut,
            params.block_size_cells,
            start,
        )
        if start == len(targets):
            return out
        dst.grow()
