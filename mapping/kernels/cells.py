"""Cell- and block-wise kernels: adding evidence, looking cells up, merging and resampling grids.

No per-scan de-duplication here (see ``mapping.kernels.integrate`` for scans). Kernels that
create blocks return where to resume when the pool is full.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from mapping.kernels.blocks import EMPTY_KEY, find_block, find_or_add_block, pack_block, split
from mapping.kernels.traversal import ray_cells


@njit(cache=True)
def add_cells(
    cells: np.ndarray,
    values: np.ndarray,
    table_keys: np.ndarray,
    table_vals: np.ndarray,
    shift: int,
    block_coords: np.ndarray,
    count: np.ndarray,
    logodds: np.ndarray,
    known: np.ndarray,
    block_scan: np.ndarray,
    lut: np.ndarray,
    bs: int,
    l_min: float,
    l_max: float,
    start: int,
) -> int:
    """Add log-odds ``values`` (N,) to ``cells`` (N, 3), clamped; returns where to resume.

    No per-scan de-duplication: a cell listed twice gets both additions (eq. 3 applied twice).
    Every cell touched becomes known. Returns N when done.
    """
    for n in range(start, len(cells)):
        bx, lx = split(cells[n, 0], bs)
        by, ly = split(cells[n, 1], bs)
        bz, lz = split(cells[n, 2], bs)
        blk = find_or_add_block(
            table_keys,
            table_vals,
            shift,
            block_coords,
            count,
            logodds,
            known,
            block_scan,
            bx,
            by,
            bz,
        )
        if blk < 0:
            return n
        flat = lut[0, lx] + lut[1, ly] + lut[2, lz]
        logodds[blk, flat] = min(max(logodds[blk, flat] + values[n], l_min), l_max)
        known[blk, flat >> 3] |= np.uint8(1 << (flat & 7))
    return len(cells)


@njit(cache=True, inline="always")
def _lookup(
    ix: int,
    iy: int,
    iz: int,
    last_key: int,
    blk: int,
    table_keys: np.ndarray,
    table_vals: np.ndarray,
    shift: int,
    logodds: np.ndarray,
    known: np.ndarray,
    lut: np.ndarray,
    bs: int,
) -> tuple[float, int, int]:
    """Log-odds of cell (ix, iy, iz), NaN where unknown, with its block's key and pool index
    (−1: none): passed back in with ``last_key`` and ``blk``, the next cell of the same block
    skips the hash table."""
    bx, lx = split(ix, bs)
    by, ly = split(iy, bs)
    bz, lz = split(iz, bs)
    key = pack_block(bx, by, bz)
    if key != last_key:
        blk = find_block(table_keys, table_vals, shift, bx, by, bz)
    value = np.nan
    if blk >= 0:
        flat = lut[0, lx] + lut[1, ly] + lut[2, lz]
        if (known[blk, flat >> 3] >> (flat & 7)) & 1:
            value = np.float64(logodds[blk, flat])
    return value, key, blk


@njit(cache=True)
def lookup_cells(
    cells: np.ndarray,
    table_keys: np.ndarray,
    table_vals: np.ndarray,
    shift: int,
    logodds: np.ndarray,
    known: np.ndarray,
    lut: np.ndarray,
    bs: int,
) -> np.ndarray:
    """Log-odds of (N, 3) cells, NaN where unknown."""
    n_cells = len(cells)
    values = np.full(n_cells, np.nan, dtype=np.float64)
    last_key = EMPTY_KEY
    blk = -1
    for n in range(n_cells):
        values[n], last_key, blk = _lookup(cells[n, 0], cells[n, 1], cells[n, 2], last_key, blk,
                                           table_keys, table_vals, shift, logodds, known, lut,
                                           bs)  # fmt: skip
    return values


@njit(cache=True)
def merge_blocks(
    src_coords: np.ndarray,
    src_logodds: np.ndarray,
    src_known: np.ndarray,
    table_keys: np.ndarray,
    table_vals: np.ndarray,
    shift: int,
    block_coords: np.ndarray,
    count: np.ndarray,
    logodds: np.ndarray,
    known: np.ndarray,
    block_scan: np.ndarray,
    l_min: float,
    l_max: float,
    start: int,
) -> int:
    """Fuse every known cell of the source blocks into the grid by eq. 3 (log-odds addition).

    Both grids share the lattice, block size and layout. Returns where to resume (len = done).
    """
    cells = src_logodds.shape[1]
    for b in range(start, len(src_coords)):
        has_known = False
        for byte in range(src_known.shape[1]):
            if src_known[b, byte] != 0:
                has_known = True
                break
        if not has_known:
            continue
        blk = find_or_add_block(
            table_keys,
            table_vals,
            shift,
            block_coords,
            count,
            logodds,
            known,
            block_scan,
            src_coords[b, 0],
            src_coords[b, 1],
            src_coords[b, 2],
        )
        if blk < 0:
            return b
        for f in range(cells):
            if (src_known[b, f >> 3] >> (f & 7)) & 1:
                logodds[blk, f] = min(max(logodds[blk, f] + src_logodds[b, f], l_min), l_max)
                known[blk, f >> 3] |= np.uint8(1 << (f & 7))
    return len(src_coords)


@njit(cache=True)
def resample_blocks(
    targets: np.ndarray,
    T_src_dst: np.ndarray,
    dst_origin: np.ndarray,
    src_origin: np.ndarray,
    res: float,
    src_keys: np.ndarray,
    src_vals: np.ndarray,
    src_shift: int,
    src_logodds: np.ndarray,
    src_known: np.ndarray,
    table_keys: np.ndarray,
    table_vals: np.ndarray,
    shift: int,
    block_coords: np.ndarray,
    count: np.ndarray,
    logodds: np.ndarray,
    known: np.ndarray,
    block_scan: np.ndarray,
    lut: np.ndarray,
    bs: int,
    start: int,
) -> int:
    """Fill target blocks (B, 3) of a new grid by nearest-cell lookup in a source grid.

    Each target cell takes the source cell that contains its centre mapped by ``T_src_dst``
    (both grids have resolution ``res`` and block size ``bs``). Blocks that receive no known
    cell are not created. Returns where to resume (B = done).
    """
    n_cells = bs * bs * bs
    vals = np.zeros(n_cells, dtype=np.float64)
    got = np.zeros(n_cells, dtype=np.bool_)
    inv_res = 1.0 / res
    for t in range(start, len(targets)):
        any_known = False
        last_key = EMPTY_KEY
        blk_src = -1
        for lx in range(bs):
            cx = dst_origin[0] + ((targets[t, 0] * bs + lx) + 0.5) * res
            for ly in range(bs):
                cy = dst_origin[1] + ((targets[t, 1] * bs + ly) + 0.5) * res
                for lz in range(bs):
                    cz = dst_origin[2] + ((targets[t, 2] * bs + lz) + 0.5) * res
                    px = T_src_dst[0, 0] * cx + T_src_dst[0, 1] * cy + T_src_dst[0, 2] * cz
                    py = T_src_dst[1, 0] * cx + T_src_dst[1, 1] * cy + T_src_dst[1, 2] * cz
                    pz = T_src_dst[2, 0] * cx + T_src_dst[2, 1] * cy + T_src_dst[2, 2] * cz
                    px += T_src_dst[0, 3] - src_origin[0]
                    py += T_src_dst[1, 3] - src_origin[1]
                    pz += T_src_dst[2, 3] - src_origin[2]
                    sbx, slx = split(math.floor(px * inv_res), bs)
                    sby, sly = split(math.floor(py * inv_res), bs)
                    sbz, slz = split(math.floor(pz * inv_res), bs)
                    key = pack_block(sbx, sby, sbz)
                    if key != last_key:
                        blk_src = find_block(src_keys, src_vals, src_shift, sbx, sby, sbz)
                        last_key = key
                    f = lut[0, lx] + lut[1, ly] + lut[2, lz]
                    got[f] = False
                    if blk_src >= 0:
                        sf = lut[0, slx] + lut[1, sly] + lut[2, slz]
                        if (src_known[blk_src, sf >> 3] >> (sf & 7)) & 1:
                            vals[f] = src_logodds[blk_src, sf]
                            got[f] = True
                            any_known = True
        if not any_known:
            continue
        blk = find_or_add_block(
            table_keys,
            table_vals,
            shift,
            block_coords,
            count,
            logodds,
            known,
            block_scan,
            targets[t, 0],
            targets[t, 1],
            targets[t, 2],
        )
        if blk < 0:
            return t
        for f in range(n_cells):
            if got[f]:
                logodds[blk, f] = vals[f]
                known[blk, f >> 3] |= np.uint8(1 << (f & 7))
    return len(targets)


@njit(cache=True)
def segment_blocked(
    start: np.ndarray,
    end: np.ndarray,
    origin: np.ndarray,
    resolution: float,
    ignore_xy: np.ndarray,
    ignore_radius: float,
    unknown_blocks: bool,
    unknown_gap: int,
    threshold: float,
    table_keys: np.ndarray,
    table_vals: np.ndarray,
    shift: int,
    logodds: np.ndarray,
    known: np.ndarray,
    lut: np.ndarray,
    bs: int,
) -> bool:
    """Whether a cell the segment ``start`` → ``end`` (cell units, end cell included) visits
    is occupied (log-odds above ``threshold``) or, with ``unknown_blocks``, unknown in a run of
    more than ``unknown_gap`` unknown cells in a row; cells whose centre lies within
    ``ignore_radius`` (in the plane) of a point of ``ignore_xy`` (N, 2; grid frame, metres) are
    not tested (nor do they end a run). The cells are ``ray_cells``'s."""
    cells = ray_cells(start, end, True)
    last_key = EMPTY_KEY
    blk = -1
    run = 0
    for n in range(len(cells)):
        if ignore_radius > 0:
            cx = origin[0] + (cells[n, 0] + 0.5) * resolution
            cy = origin[1] + (cells[n, 1] + 0.5) * resolution
            near = False
            for p in range(len(ignore_xy)):
                if math.hypot(cx - ignore_xy[p, 0], cy - ignore_xy[p, 1]) <= ignore_radius:
                    near = True
                    break
            if near:
                continue
        value, last_key, blk = _lookup(cells[n, 0], cells[n, 1], cells[n, 2], last_key, blk,
                                       table_keys, table_vals, shift, logodds, known, lut,
                                       bs)  # fmt: skip
        if math.isnan(value):
            run += 1
            if unknown_blocks and run > unknown_gap:
                return True
            continue
        run = 0
        if value > threshold:
            return True
    return False


@njit(cache=True, nogil=True)
def known_in_layers(
    coords: np.ndarray, known: np.ndarray, logodds: np.ndarray, local_of_flat: np.ndarray,
    bs: int, k_first: int, k_last: int,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The known cells of the blocks at ``coords`` (their ``known`` bits and ``logodds``)
    whose layer lies in [``k_first``, ``k_last``]: (N, 3) cell indices and (N,) float64
    log-odds, block by block and in storage order within a block (``np.nonzero``'s order over
    the blocks' known bits). Only the bits of those layers are read (twice: counted, then
    copied into arrays of that many cells)."""
    n_blocks = len(coords)
    cells_per_block = bs * bs * bs
    total = 0  # counted first, so that the arrays are the cells' own (no larger buffer behind)
    for visit in range(2):
        if visit == 1:
            cells = np.empty((total, 3), dtype=np.int64)
            values = np.empty(total, dtype=np.float64)
        count = 0
        for b in range(n_blocks):
            x0, y0, z0 = coords[b, 0] * bs, coords[b, 1] * bs, coords[b, 2] * bs
            if z0 + bs - 1 < k_first or z0 > k_last:
                continue
            for flat in range(cells_per_block):
                z = z0 + local_of_flat[flat, 2]
                if z < k_first or z > k_last or not (known[b, flat >> 3] >> (flat & 7)) & 1:
                    continue
                if visit == 1:
                    cells[count, 0] = x0 + local_of_flat[flat, 0]
                    cells[count, 1] = y0 + local_of_flat[flat, 1]
                    cells[count, 2] = z
                    values[count] = logodds[b, flat]
                count += 1
        total = count
    return cells, values


@njit(cache=True)
def known_by_block(
    known: np.ndarray, logodds: np.ndarray, flat_of_xmajor: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The blocks' known cells in x-major order (``flat_of_xmajor[j]``: the storage offset of
    the j-th cell x-major): (B, ⌈bs³ / 8⌉) their bits packed little-endian per block
    (``np.packbits(..., bitorder="little")``'s layout) and the known cells' log-odds, block by
    block, x-major within a block (as stored, float32)."""
    n_blocks, cells = len(known), len(flat_of_xmajor)
    total = 0
    for b in range(n_blocks):
        for j in range(cells):
            f = flat_of_xmajor[j]
            total += (known[b, f >> 3] >> (f & 7)) & 1
    bits = np.zeros((n_blocks, (cells + 7) // 8), dtype=np.uint8)
    values = np.empty(total, dtype=logodds.dtype)
    count = 0
    for b in range(n_blocks):
        for j in range(cells):
            f = flat_of_xmajor[j]
            if (known[b, f >> 3] >> (f & 7)) & 1:
                bits[b, j >> 3] |= np.uint8(1 << (j & 7))
                values[count] = logodds[b, f]
                count += 1
    return bits, values
