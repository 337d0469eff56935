"""The 3D Bayesian occupancy grid (docs/design.md §6, paper eq. 3), stored as log-odds in blocks.

Each cell holds the log-odds of its probability of occupancy, 0 (P = 0.5) until observed, and
is updated by adding the log-odds of the evidence (identical to the paper's eq. 3, see
``mapping.logodds``), clamped to [l(clamp_min), l(clamp_max)] as OctoMap does so that the map
stays updatable. The extent of the map is not known in advance: cells live in cubic blocks of
``block_size_cells³`` that are created the first time a ray reaches them, found through a hash
table of block coordinates. Memory follows the observed volume, not its bounding box.

Cell (i, j, k) is the half-open cube ``origin + [i, i + 1) · resolution`` per axis; with the
origin at 0 (the default) the lattice is OctoMap's.
"""

from __future__ import annotations

import functools

import numpy as np

from mapping.errors import MapError
from mapping.kernels.blocks import (
    BLOCK_OFFSET,
    first_bad_point,
    layout_table,
    rebuild_table,
)
from mapping.kernels.cells import (
    add_cells,
    known_by_block,
    known_in_layers,
    lookup_cells,
    merge_blocks,
    segment_blocked,
)
from mapping.kernels.integrate import PHASE_DONE, PHASE_HITS, integrate
from mapping.lanes import RAYS_PER_LANE, mark_side_by_side
from mapping.logodds import logodds, probability
from mapping.params import MIN_RESOLUTION_M, GridParams, open_probability
from mapping.storage import BlockStorage, discard_scan_cube, scan_cube, stored_bounds

__all__ = ["MIN_RESOLUTION_M", "GridParams", "OccupancyGrid"]

#: Cell coordinates beyond this many cells from the origin cannot be addressed (block keys).
_INITIAL_BLOCKS = 256
#: Beyond any layer a grid can hold (``cells()`` of every layer).
_ALL_LAYERS = 1 << 62


class OccupancyGrid:
    """A 3D occupancy grid that grows on demand (docs/design.md §6).

    ``integrate_scan`` fuses one scan by exact voxel traversal; ``merge`` fuses another grid by
    eq. 3; ``cells`` lists what is known. Coordinates are in the frame the grid was built in
    (the map frame for a global map, the reference robot's frame for a local one).
    """

    def __init__(self, params: GridParams | None = None, *, capacity_blocks: int = _INITIAL_BLOCKS):
        self.params = params if params is not None else GridParams()
        self._store = BlockStorage(self.params.block_size_cells, max(1, int(capacity_blocks)))
        self._scan_id = 0
        # The clamping bounds as the kernels apply them: float32 values within the bounds.
        self._l_min, self._l_max = stored_bounds(self.params.logodds_min, self.params.logodds_max)
        # Cells farther than this from the origin cannot be packed into block keys.
        self._max_cells = (BLOCK_OFFSET - 2) * self.params.block_size_cells

    # -- properties -------------------------------------------------------------------------

    @property
    def resolution_m(self) -> float:
        return self.params.resolution_m

    @property
    def origin_m(self) -> np.ndarray:
        return np.asarray(self.params.origin_m, dtype=np.float64)

    @property
    def block_count(self) -> int:
        """Blocks allocated so far."""
        return self._store.used

    @property
    def cell_updates(self) -> int:
        """Cell updates made by the scans integrated so far (each cell at most once a scan)."""
        return int(self._store.updates[0])

    @property
    def scan_count(self) -> int:
        """Scans integrated into this grid object."""
        return self._scan_id

    def known_count(self) -> int:
        """Cells observed at least once."""
        return int(np.count_nonzero(self._known_mask(self.block_count)))

    def memory_bytes(self) -> int:
        """Bytes held by the grid's arrays: the block pool with its spare capacity (float32
        log-odds, known and per-scan bits, block coordinates), the hash table."""
        return self._store.nbytes()

    def __repr__(self) -> str:
        return (
            f"OccupancyGrid(resolution_m={self.resolution_m}, blocks={self.block_count}, "
            f"known={self.known_count()}, scans={self.scan_count})"
        )

    # -- coordinates ------------------------------------------------------------------------

    def cell_of(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) int64 cell of each (N, 3) point."""
        points = self._points(points, "points")
        return np.floor((points - self.origin_m) * (1.0 / self.resolution_m)).astype(np.int64)

    def cell_centers(self, cells: np.ndarray) -> np.ndarray:
        """(N, 3) centres of (N, 3) cells, in the grid's frame."""
        cells = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
        return np.asarray(self.origin_m + (cells + 0.5) * self.resolution_m)

    # -- updates ----------------------------------------------------------------------------

    def integrate_scan(
        self,
        points: np.ndarray,
        sensor_origin: np.ndarray,
        no_return_directions: np.ndarray | None = None,
        *,
        threads: int = 1,
    ) -> None:
        """Fuse one scan: free evidence along every ray, occupied evidence at its end point.

        ``points`` (N, 3) are the returns and ``sensor_origin`` (3,) the sensor position, both
        in the grid's frame; ``no_return_directions`` (M, 3) are the directions of beams that
        returned nothing, which give free evidence up to ``no_return_free_m``. Within the scan
        every cell is updated at most once and an end point's cell is occupied even if another
        ray passes through it, as OctoMap's ``insertPointCloud`` does. A ray's own end cell
        gets no free evidence from it; nor does the cell where a no-return beam's cut-off falls.

        ``threads`` > 1: up to that many threads (at least ``RAYS_PER_LANE`` rays each) walk
        the rays that stay in the scan's cube side by side, each marking its cells in a cube of
        its own; the cubes are merged and the scan goes on as with one. The grid is the same
        bit for bit (a cell is marked or not whichever thread marks it; the rays that leave the
        cube are walked afterwards in their order).
        """
        hits = self._points(points, "points")
        sensor = self._points(np.asarray(sensor_origin, dtype=np.float64).reshape(1, 3), "sensor")
        free_ends = np.zeros((0, 3), dtype=np.float64)
        cutoff = self.params.no_return_free_m
        if no_return_directions is not None:
            directions = np.asarray(no_return_directions, dtype=np.float64)
            if directions.ndim != 2 or directions.shape[1] != 3:
                raise MapError(f"no_return_directions must be (M, 3), got {directions.shape}")
            norms = np.linalg.norm(directions, axis=1)
            bad = ~np.isfinite(norms) | (norms == 0)
            if bad.any():
                first = int(np.flatnonzero(bad)[0])
                raise MapError(
                    f"no_return_directions[{first}] is not a direction: "
                    f"{directions[first].tolist()}"
                )
            if cutoff > 0:
                ends = sensor + directions * (cutoff / norms)[:, None]
                free_ends = self._points(ends, "no-return cut-off points")
        if threads < 1:
            raise MapError(f"threads must be at least 1, got {threads}")
        self._scan_id += 1
        bs = self.params.block_size_cells
        lg = bs.bit_length() - 1 if bs & (bs - 1) == 0 else -1
        cube = scan_cube()
        lanes = min(threads, (len(hits) + len(free_ends)) // RAYS_PER_LANE)
        rays, phase, start = hits, PHASE_HITS, 0
        try:
            if lanes > 1:
                phase, start = self._integrate(hits, hits, free_ends, sensor, cube, lg, phase,
                                               start, until=PHASE_HITS)  # fmt: skip
                rays, free_ends = mark_side_by_side(hits, free_ends, sensor[0], self.origin_m,
                                                     1.0 / self.params.resolution_m, lg, cube,
                                                     lanes)  # fmt: skip
            self._integrate(hits, rays, free_ends, sensor, cube, lg, phase, start, PHASE_DONE)
        except BaseException:
            discard_scan_cube()  # it holds half a scan's bits: the next scan starts afresh
            raise

    def _integrate(
        self, hits: np.ndarray, rays: np.ndarray, free_ends: np.ndarray, sensor: np.ndarray,
        cube: np.ndarray, lg: int, phase: int, start: int, until: int,
    ) -> tuple[int, int]:  # fmt: skip
        """Run the scan's phases from ``phase`` (at ``start``) through ``until``, growing the
        block pool whenever it runs out; the phase and index to go on from."""
        params, store = self.params, self._store
        while True:
            phase, start = integrate(
                hits,
                rays,
                free_ends,
                sensor[0],
                self.origin_m,
                1.0 / params.resolution_m,
                cube,
                store.table[0],
                store.table[1],
                store.shift,
                store.coords,
                store.count,
                store.logodds,
                store.known,
                store.flags,
                store.block_scan,
                store.updates,
                store.lut,
                params.block_size_cells,
                lg,
                self._scan_id,
                params.logodds_hit,
                params.logodds_miss,
                self._l_min,
                self._l_max,
                phase,
                start,
                until,
            )
            if phase > until or phase == PHASE_DONE:
                return phase, start
            store.grow()

    def apply_evidence(self, cells: np.ndarray, evidence: np.ndarray) -> None:
        """Update (N, 3) cells with measurement probabilities ``evidence`` (N,) by eq. 3.

        Unlike a scan, a cell listed k times is updated k times, in order. Results are clamped.
        """
        cells = self._cells(cells)
        evidence = np.asarray(evidence, dtype=np.float64).reshape(-1)
        if len(evidence) != len(cells):
            raise MapError(f"need one evidence value per cell: {len(evidence)} for {len(cells)}")
        inside = (evidence > 0) & (evidence < 1)
        if not inside.all():
            bad = int(np.flatnonzero(~inside)[0])
            raise MapError(
                f"evidence must lie in (0, 1), got {float(evidence[bad])} at index {bad}"
            )
        self._add(cells, logodds(evidence))

    def merge(self, other: OccupancyGrid) -> None:
        """Fuse ``other`` into this grid by eq. 3 (log-odds addition, clamped), cell by cell.

        Both grids must share the lattice (resolution, origin, block size); bring a grid from
        another frame over with ``mapping.fusion.transform_grid`` first.
        """
        if not self.params.same_lattice(other.params):
            raise MapError(
                "cannot merge grids on different lattices: "
                f"{self._lattice_text()} and {other._lattice_text()}"
            )
        n, src = other.block_count, other._store
        store = self._store
        start = 0
        while True:
            start = merge_blocks(
                src.coords[:n],
                src.logodds[:n],
                src.known[:n],
                store.table[0],
                store.table[1],
                store.shift,
                store.coords,
                store.count,
                store.logodds,
                store.known,
                store.block_scan,
                self._l_min,
                self._l_max,
                start,
            )
            if start == n:
                return
            store.grow()

    def copy(self) -> OccupancyGrid:
        """An independent grid with the same cells."""
        out = OccupancyGrid(self.params, capacity_blocks=max(1, self.block_count))
        n = self.block_count
        store = out._store
        store.coords[:n] = self._store.coords[:n]
        store.logodds[:n] = self._store.logodds[:n]
        store.known[:n] = self._store.known[:n]
        store.count[0] = n
        store.table = rebuild_table(store.coords, n, store.table_bits)
        return out

    # -- queries ----------------------------------------------------------------------------

    def cells(self, z_range: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Every known cell: (N, 3) int64 indices and (N,) float64 log-odds (as stored).

        ``z_range`` (k_first, k_last) keeps the cells of those layers only (and reads only the
        blocks that hold them).
        """
        n, bs = self.block_count, self.params.block_size_cells
        coords, logodds, known_bits = (
            self._store.coords[:n],
            self._store.logodds[:n],
            self._store.known[:n],
        )
        # Every layer: the same cells in the same order as unpacking the bits with numpy, 32
        # bytes a cell where unpacking and gathering took 67 (53 MB for office_loop's map).
        k_first, k_last = (-_ALL_LAYERS, _ALL_LAYERS) if z_range is None else z_range
        return known_in_layers(coords, known_bits, logodds, self._local_of_flat(), bs,
                               int(k_first), int(k_last))  # fmt: skip

    def logodds_at(self, cells: np.ndarray) -> np.ndarray:
        """(N,) log-odds of (N, 3) cells, NaN where unknown."""
        cells = self._cells(cells)
        store = self._store
        return np.asarray(
            lookup_cells(
                cells,
                store.table[0],
                store.table[1],
                store.shift,
                store.logodds,
                store.known,
                store.lut,
                self.params.block_size_cells,
            )
        )

    def segment_blocked(
        self,
        start: np.ndarray,
        end: np.ndarray,
        *,
        unknown_blocks: bool,
        ignore_xy: np.ndarray,
        ignore_radius_m: float,
        unknown_gap_cells: int = 0,
    ) -> bool:
        """Whether a cell that the segment ``start`` → ``end`` (cell units, as
        ``mapping.kernels.traversal.ray_cells`` takes them; the end cell included) visits is
        occupied or, with ``unknown_blocks``, unknown in a run of more than
        ``unknown_gap_cells`` unknown cells in a row; cells whose centre lies within
        ``ignore_radius_m`` of a point of ``ignore_xy`` (N, 2; metres) in the plane are not
        tested."""
        if unknown_gap_cells < 0:
            raise MapError(f"unknown_gap_cells must be >= 0, got {unknown_gap_cells}")
        ends = np.floor(np.stack([np.asarray(start, float), np.asarray(end, float)]))
        if ends.shape != (2, 3) or not np.isfinite(ends).all():
            raise MapError(f"a segment needs two finite 3D end points, got {start} and {end}")
        if np.abs(ends).max() >= self._max_cells:
            raise MapError(f"cell index {int(np.abs(ends).max())} beyond the addressable map")
        store = self._store
        return bool(
            segment_blocked(
                np.asarray(start, np.float64), np.asarray(end, np.float64),
                self.origin_m, self.resolution_m,
                np.ascontiguousarray(ignore_xy, dtype=np.float64).reshape(-1, 2),
                float(ignore_radius_m), bool(unknown_blocks), int(unknown_gap_cells),
                self.params.logodds_threshold,
                store.table[0], store.table[1], store.shift, store.logodds, store.known,
                store.lut, self.params.block_size_cells,
            )
        )  # fmt: skip

    def probability_at(self, points: np.ndarray) -> np.ndarray:
        """(N,) probability of occupancy at (N, 3) points; 0.5 where unknown."""
        values = self.logodds_at(self.cell_of(points))
        return probability(np.nan_to_num(values, nan=0.0))

    def occupied(self, threshold: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Cells with P > ``threshold`` (default: the grid's): (N, 3) indices, (N,) P."""
        cells, values = self.cells()
        if threshold is None:
            level = self.params.logodds_threshold
        else:
            open_probability("threshold", threshold)
            level = float(logodds(threshold))
        keep = values > level
        return cells[keep], probability(values[keep])

    def bounds_cells(self) -> tuple[np.ndarray, np.ndarray]:
        """Smallest and largest known cell index per axis; MapError when nothing is known.
        Only the blocks at the edges of the known blocks are decoded."""
        rows = np.flatnonzero(self._store.known[: self.block_count].any(axis=1))
        if len(rows) == 0:
            raise MapError("the grid is empty: no cell has been observed")
        coords = self._store.coords[rows]
        low, high = coords.min(axis=0), coords.max(axis=0)
        edge = rows[((coords == low) | (coords == high)).any(axis=1)]
        store, bs = self._store, self.params.block_size_cells
        cells, _ = known_in_layers(store.coords[edge], store.known[edge], store.logodds[edge],
                                   self._local_of_flat(), bs, -_ALL_LAYERS,
                                   _ALL_LAYERS)  # fmt: skip
        return cells.min(axis=0), cells.max(axis=0)

    # -- blocks (for file formats and resampling) ---------------------------------------------

    def blocks(self) -> tuple[np.ndarray, np.ndarray]:
        """(B, 3) block coordinates and (B, bs, bs, bs) log-odds (NaN = unknown), x-major."""
        n, bs = self.block_count, self.params.block_size_cells
        order = self._flat_of_local().reshape(-1)
        values = np.where(self._known_mask(n), self._store.logodds[:n], np.float64(np.nan))
        return self._store.coords[:n].copy(), values[:, order].reshape(n, bs, bs, bs)

    def known_blocks(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What :meth:`blocks` says, without the dense values: (B, 3) block coordinates,
        (B, ⌈bs³ / 8⌉) which cells are known, x-major, packed little-endian per block, and the
        known cells' log-odds in that order (as stored, float32). 5 bytes a known cell where
        :meth:`blocks` takes 16 a cell of every block (the map file's arrays)."""
        n = self.block_count
        order = self._flat_of_local().reshape(-1)
        bits, values = known_by_block(self._store.known[:n], self._store.logodds[:n], order)
        return self._store.coords[:n].copy(), bits, values

    @classmethod
    def from_blocks(
        cls, params: GridParams, coords: np.ndarray, values: np.ndarray
    ) -> OccupancyGrid:
        """A grid from (B, 3) unique block coordinates and (B, bs, bs, bs) log-odds.

        NaN marks unknown cells; values are clamped to the grid's bounds.
        """
        bs = params.block_size_cells
        coords = np.asarray(coords)
        values = np.asarray(values, dtype=np.float64)
        if coords.ndim != 2 or coords.shape[1] != 3 or coords.dtype.kind not in "iu":
            raise MapError(f"block coordinates must be (B, 3) integers, got {coords.shape}")
        if values.shape != (len(coords), bs, bs, bs):
            raise MapError(
                f"block values must be ({len(coords)}, {bs}, {bs}, {bs}), got {values.shape}"
            )
        limit = BLOCK_OFFSET - 2
        if len(coords) and np.abs(coords).max() >= limit:
            raise MapError(f"block coordinate {int(np.abs(coords).max())} beyond ±{limit}")
        if len(np.unique(coords, axis=0)) != len(coords):
            raise MapError("block coordinates are not unique")
        finite = values[~np.isnan(values)]
        if not np.all(np.isfinite(finite)):
            raise MapError("block log-odds must be finite or NaN (unknown)")
        grid = cls(params, capacity_blocks=max(1, len(coords)))
        store = grid._store
        n = len(coords)
        store.coords[:n] = coords
        order = grid._flat_of_local().reshape(-1)
        flat_values = values.reshape(n, bs**3)
        known = ~np.isnan(flat_values)
        store.logodds[:n, order] = np.where(
            known, np.clip(flat_values, grid._l_min, grid._l_max), 0.0
        )
        bits = np.zeros((n, bs**3), dtype=bool)
        bits[:, order] = known
        store.known[:n] = np.packbits(bits, axis=1, bitorder="little")
        store.count[0] = n
        store.table = rebuild_table(store.coords, n, store.table_bits)
        return grid

    @classmethod
    def from_cells(cls, params: GridParams, cells: np.ndarray, values: np.ndarray) -> OccupancyGrid:
        """A grid whose (N, 3) unique ``cells`` hold log-odds ``values`` (N,), clamped."""
        grid = cls(params)
        cells = grid._cells(cells)
        values = np.asarray(values, dtype=np.float64).reshape(-1)
        if len(values) != len(cells):
            raise MapError(f"need one value per cell: {len(values)} for {len(cells)}")
        if not np.all(np.isfinite(values)):
            raise MapError("cell log-odds must be finite")
        if len(cells):
            blocks = np.unique(cells // params.block_size_cells, axis=0)
            grid._store.grow(len(blocks))
        grid._add(cells, values)
        return grid

    # -- helpers ----------------------------------------------------------------------------

    def _known_mask(self, n: int) -> np.ndarray:
        """(n, bs³) bool: which cells of the first n blocks are known, in storage order."""
        cells = self.params.block_size_cells**3
        bits = np.unpackbits(self._store.known[:n], axis=1, bitorder="little")
        return np.asarray(bits[:, :cells].view(bool))

    def _flat_of_local(self) -> np.ndarray:
        """(bs, bs, bs) storage offset of each in-block cell (x, y, z) (read-only)."""
        return _flat_of_local(self.params.block_size_cells)

    def _local_of_flat(self) -> np.ndarray:
        """(bs³, 3) in-block cell (x, y, z) of each storage offset (read-only)."""
        return _local_of_flat(self.params.block_size_cells)

    def _add(self, cells: np.ndarray, values: np.ndarray) -> None:
        params, store = self.params, self._store
        start = 0
        while True:
            start = add_cells(
                cells,
                values,
                store.table[0],
                store.table[1],
                store.shift,
                store.coords,
                store.count,
                store.logodds,
                store.known,
                store.block_scan,
                store.lut,
                params.block_size_cells,
                self._l_min,
                self._l_max,
                start,
            )
            if start == len(cells):
                return
            store.grow()

    def _lattice_text(self) -> str:
        p = self.params
        return (
            f"(resolution {p.resolution_m} m, origin {list(p.origin_m)}, "
            f"block {p.block_size_cells})"
        )

    def _points(self, points: np.ndarray, name: str) -> np.ndarray:
        points = np.ascontiguousarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise MapError(f"{name} must be (N, 3), got {points.shape}")
        reach_m = self._max_cells * self.resolution_m
        bad = first_bad_point(points, self.origin_m, reach_m)
        if bad >= 0:
            if not np.all(np.isfinite(points[bad])):
                raise MapError(f"{name}[{bad}] is not finite: {points[bad].tolist()}")
            raise MapError(
                f"{name}[{bad}] {points[bad].tolist()} lies beyond the {reach_m:.4g} m from the "
                "grid origin that the grid can address"
            )
        return points

    def _cells(self, cells: np.ndarray) -> np.ndarray:
        cells = np.asarray(cells)
        if cells.ndim != 2 or cells.shape[1] != 3:
            raise MapError(f"cells must be (N, 3), got {cells.shape}")
        if cells.dtype.kind not in "iu":
            raise MapError(f"cells must be integers, got {cells.dtype}")
        cells = np.ascontiguousarray(cells, dtype=np.int64)
        if len(cells) and np.abs(cells).max() >= self._max_cells:
            raise MapError(f"cell index {int(np.abs(cells).max())} beyond the addressable map")
        return cells


@functools.lru_cache(maxsize=4)
def _flat_of_local(bs: int) -> np.ndarray:
    """(bs, bs, bs) storage offset of each in-block cell (x, y, z) of a block of side ``bs``
    (its layout, ``layout_table``, as the block storage lays it out), made once per side:
    read-only."""
    lut = layout_table(bs)
    flat = lut[0][:, None, None] + lut[1][None, :, None] + lut[2][None, None, :]
    flat.flags.writeable = False
    return flat


@functools.lru_cache(maxsize=4)
def _local_of_flat(bs: int) -> np.ndarray:
    """(bs³, 3) in-block cell (x, y, z) of each storage offset of a block of side ``bs``, made
    once per side: read-only."""
    local = np.stack(np.meshgrid(*(np.arange(bs),) * 3, indexing="ij"), axis=-1)
    out = np.empty((bs**3, 3), dtype=np.int64)
    out[_flat_of_local(bs).reshape(-1)] = local.reshape(-1, 3)
    out.flags.writeable = False
    return out
