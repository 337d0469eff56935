"""numba kernels of the occupancy grid: block table, voxel traversal, scan integration, merging.

Storage (see ``mapping.grid``): the map is a pool of cubic blocks of ``bs³`` cells. A cell holds
its log-odds (float64; 0, the prior, until observed) and a "known" bit (``known``, (capacity,
⌈bs³/8⌉) uint8, bit ``f & 7`` of byte ``f >> 3`` for the cell stored at ``f``; set once the cell
has been observed). Freshly allocated blocks are all zeros. Blocks are found through an
open-addressing hash table keyed by the packed block coordinates; a block is created the first
time a ray reaches it, so memory follows the observed volume. Within a block, cells are laid out
in Morton (Z-) order when ``bs`` is a power of two — the 2 × 2 × 2 neighbours of a cell share a
cache line, which is what a ray walking through the block touches next. The layout is given by
``lut`` (3, bs): cell (x, y, z) of a block is at ``lut[0, x] + lut[1, y] + lut[2, z]``.

Per-scan de-duplication uses one bit per cell (``flags``, (capacity, bs³ / 8) uint8), valid for
the scan whose id is in ``block_scan`` (capacity,): a block's bits are cleared lazily the first
time the scan reaches it. The bits are small enough to stay in cache, so a ray costs little in
cells that other rays of the scan have already updated.

Kernels that may create blocks return early when the pool is full; the caller grows the pool and
calls again from where the kernel stopped. A cell is flagged when updated and a flagged cell is
skipped for the rest of the scan, so resuming (even mid-ray) is exact.

Cell coordinates: cell (i, j, k) spans ``origin + [i, i + 1) · resolution`` per axis, so a point
``p`` lies in cell ``floor((p − origin) / resolution)`` (OctoMap's convention with origin 0).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: Block coordinates are packed into 21 bits each, offset by 2^20.
BLOCK_BITS = 21
BLOCK_OFFSET = 1 << (BLOCK_BITS - 1)
EMPTY_KEY = -1
_HASH_MUL = np.uint64(0x9E3779B97F4A7C15)
#: Kernel phases: occupied end points, free rays to end points, free rays of no-return beams.
PHASE_HITS, PHASE_RAYS, PHASE_FREE, PHASE_DONE = 0, 1, 2, 3


def layout_table(bs: int) -> np.ndarray:
    """(3, bs) int64 offsets of the in-block layout: Morton order if ``bs`` is a power of 2."""
    lut = np.zeros((3, bs), dtype=np.int64)
    coords = np.arange(bs, dtype=np.int64)
    if bs & (bs - 1) == 0:
        for bit in range(bs.bit_length() - 1):
            for axis in range(3):
                lut[axis] |= ((coords >> bit) & 1) << (3 * bit + 2 - axis)
    else:
        lut[0], lut[1], lut[2] = coords * bs * bs, coords * bs, coords
    return lut


@njit(cache=True, inline="always")
def pack_block(bx: int, by: int, bz: int) -> int:
    return (
        ((bx + BLOCK_OFFSET) << (2 * BLOCK_BITS))
        | ((by + BLOCK_OFFSET) << BLOCK_BITS)
        | (bz + BLOCK_OFFSET)
    )


@njit(cache=True, inline="always")
def _slot(key: int, shift: int) -> int:
    return int(np.int64((np.uint64(key) * _HASH_MUL) >> np.uint64(shift)))


@njit(cache=True, inline="always")
def find_block(
    table_keys: np.ndarray, table_vals: np.ndarray, shift: int, bx: int, by: int, bz: int
) -> int:
    """Pool index of block (bx, by, bz), or −1 if it does not exist."""
    key = pack_block(bx, by, bz)
    mask = len(table_keys) - 1
    h = _slot(key, shift)
    while True:
        k = table_keys[h]
        if k == key:
            return table_vals[h]
        if k == EMPTY_KEY:
            return -1
        h = (h + 1) & mask


@njit(cache=True, inline="always")
def _probe(table_keys: np.ndarray, table_vals: np.ndarray, shift: int, key: int) -> int:
    """Pool index of the block with packed ``key``, or −1 if it does not exist."""
    mask = len(table_keys) - 1
    h = _slot(key, shift)
    found = -1
    k = table_keys[h]
    while k != EMPTY_KEY:
        if k == key:
            found = table_vals[h]
            break
        h = (h + 1) & mask
        k = table_keys[h]
    return found


@njit(cache=True, inline="always")
def find_or_add_block(
    table_keys: np.ndarray,
    table_vals: np.ndarray,
    shift: int,
    block_coords: np.ndarray,
    count: np.ndarray,
    logodds: np.ndarray,
    known: np.ndarray,
    block_scan: np.ndarray,
    bx: int,
    by: int,
    bz: int,
) -> int:
    """Pool index of block (bx, by, bz), created if absent; −1 if the pool is full.

    The pool's spare rows are not initialised (growing it copies only the rows in use): a new
    block's rows are cleared here.
    """
    key = pack_block(bx, by, bz)
    mask = len(table_keys) - 1
    h = _slot(key, shift)
    found = -1
    while True:
        k = table_keys[h]
        if k == key:
            found = table_vals[h]
            break
        if k == EMPTY_KEY:
            n = count[0]
            if n < len(block_coords):
                table_keys[h] = key
                table_vals[h] = n
                block_coords[n, 0] = bx
                block_coords[n, 1] = by
                block_coords[n, 2] = bz
                for f in range(logodds.shape[1]):
                    logodds[n, f] = 0.0
                for f in range(known.shape[1]):
                    known[n, f] = 0
                block_scan[n] = 0
                count[0] = n + 1
                found = n
            break
        h = (h + 1) & mask
    return found


@njit(cache=True)
def rebuild_table(block_coords: np.ndarray, count: int, table_bits: int) -> np.ndarray:
    """A fresh hash table (row 0 keys, row 1 pool indices) for the first ``count`` blocks."""
    size = 1 << table_bits
    shift = 64 - table_bits
    table = np.full((2, size), EMPTY_KEY, dtype=np.int64)
    mask = size - 1
    for n in range(count):
        key = pack_block(block_coords[n, 0], block_coords[n, 1], block_coords[n, 2])
        h = _slot(key, shift)
        while table[0, h] != EMPTY_KEY:
            h = (h + 1) & mask
        table[0, h] = key
        table[1, h] = n
    return table


@njit(cache=True, inline="always")
def _split(i: int, bs: int) -> tuple[int, int]:
    """(block, local) coordinate of cell coordinate ``i`` (floor division)."""
    b = i // bs
    return b, i - b * bs


@njit(cache=True, inline="always")
def _locate(i: int, bs: int, lg: int) -> tuple[int, int]:
    """(block, local) coordinate of cell coordinate ``i``: shifts when bs = 2^lg (lg ≥ 0)."""
    if lg >= 0:
        return i >> lg, i & (bs - 1)
    return _split(i, bs)


@njit(cache=True)
def _flush(
    logodds: np.ndarray,
    known: np.ndarray,
    pending: np.ndarray,
    updates: np.ndarray,
    delta: float,
    l_min: float,
    l_max: float,
) -> None:
    """Apply ``delta`` (clamped) to every queued cell, mark it known; empty the queue."""
    count = pending[0, 0]
    for n in range(1, count + 1):
        blk = pending[0, n]
        flat = pending[1, n]
        logodds[blk, flat] = min(max(logodds[blk, flat] + delta, l_min), l_max)
        known[blk, flat >> 3] |= np.uint8(1 << (flat & 7))
    updates[0] += count
    pending[0, 0] = 0


# -- the scan's "seen" cube ------------------------------------------------------------------
# Within one scan each cell is updated once. Cells within ±CUBE_HALF cells of the sensor (per
# axis) are tracked in a bitmap of the cube around it, in Morton order (an 8 × 8 × 8 corner of
# the cube shares a cache line), where a ray steps from cell to cell with a few bit operations
# and no lookup; most of a scan's traversal happens there. Cells outside use the per-block bits.

CUBE_BITS = 9
CUBE_SIDE = 1 << CUBE_BITS
CUBE_HALF = CUBE_SIDE // 2
#: The bitmap's bytes, then one byte per 4 kB chunk of it: set when the scan wrote to the chunk,
#: so that clearing the bitmap after a scan touches only those chunks.
CUBE_BYTES = 1 << (3 * CUBE_BITS - 3)
CUBE_CHUNK_BITS = 12
CUBE_ARRAY_BYTES = CUBE_BYTES + (CUBE_BYTES >> CUBE_CHUNK_BITS)
_MZ = 0x01249249  # Morton bits of z (bit 3i), y (3i + 1) and x (3i + 2) for 9-bit coordinates
_MY = _MZ << 1
_MX = _MZ << 2


@njit(cache=True, inline="always")
def _dilate(v: int) -> int:
    """Spread the bits of a coordinate below 1024 to every third bit."""
    v &= 0x3FF
    v = (v ^ (v << 16)) & 0xFF0000FF
    v = (v ^ (v << 8)) & 0x0300F00F
    v = (v ^ (v << 4)) & 0x030C30C3
    return (v ^ (v << 2)) & 0x09249249


@njit(cache=True, inline="always")
def _compact(v: int) -> int:
    """Inverse of ``_dilate`` on bits 0, 3, 6, …"""
    v &= 0x09249249
    v = (v ^ (v >> 2)) & 0x030C30C3
    v = (v ^ (v >> 4)) & 0x0300F00F
    v = (v ^ (v >> 8)) & 0xFF0000FF
    return (v ^ (v >> 16)) & 0x3FF


@njit(cache=True, inline="always")
def _morton(x: int, y: int, z: int) -> int:
    return (_dilate(x) << 2) | (_dilate(y) << 1) | _dilate(z)


@njit(cache=True)
def _apply_fresh(
    fresh: np.ndarray,
    n_fresh: int,
    corner: np.ndarray,
    cube: np.ndarray,
    table_keys: np.ndarray,
    table_vals: np.ndarray,
    shift: int,
    block_coords: np.ndarray,
    count: np.ndarray,
    logodds: np.ndarray,
    known: np.ndarray,
    block_scan: np.ndarray,
    updates: np.ndarray,
    lut: np.ndarray,
    bs: int,
    lg: int,
    delta: float,
    l_min: float,
    l_max: float,
) -> int:
    """Update the cube cells ``fresh[:n_fresh]`` (Morton indices, marked in the cube).

    Returns ``n_fresh``, or k < n_fresh when the pool ran out at ``fresh[k]``: cells k… are
    then cleared in the cube again, so that tracing their rays again updates them.
    """
    blk = -1
    stop = n_fresh
    if lg >= 0:
        # Power-of-two blocks and a block-aligned cube: a cell's Morton code is its block's
        # Morton code (relative to the cube corner's block) followed by its in-block offset.
        s3 = 3 * lg
        low = (1 << s3) - 1
        cbx = corner[0] >> lg
        cby = corner[1] >> lg
        cbz = corner[2] >> lg
        last_hi = -1
        for k in range(n_fresh):
            m = fresh[k]
            cube[CUBE_BYTES + (m >> (CUBE_CHUNK_BITS + 3))] = 1
            hi = m >> s3
            if hi != last_hi:
                bx = _compact(hi >> 2) + cbx
                by = _compact(hi >> 1) + cby
                bz = _compact(hi) + cbz
                blk = _probe(table_keys, table_vals, shift, pack_block(bx, by, bz))
                if blk < 0:
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
                    stop = k
                    break
                last_hi = hi
            flat = m & low
            logodds[blk, flat] = min(max(logodds[blk, flat] + delta, l_min), l_max)
            known[blk, flat >> 3] |= np.uint8(1 << (flat & 7))
    else:
        last = EMPTY_KEY
        for k in range(n_fresh):
            m = fresh[k]
            cube[CUBE_BYTES + (m >> (CUBE_CHUNK_BITS + 3))] = 1
            bx, lx = _split(_compact(m >> 2) + corner[0], bs)
            by, ly = _split(_compact(m >> 1) + corner[1], bs)
            bz, lz = _split(_compact(m) + corner[2], bs)
            key = pack_block(bx, by, bz)
            if key != last:
                blk = _probe(table_keys, table_vals, shift, key)
                if blk < 0:
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
                    stop = k
                    break
                last = key
            flat = lut[0, lx] + lut[1, ly] + lut[2, lz]
            logodds[blk, flat] = min(max(logodds[blk, flat] + delta, l_min), l_max)
            known[blk, flat >> 3] |= np.uint8(1 << (flat & 7))
    updates[0] += stop
    for k in range(stop, n_fresh):
        m = fresh[k]
        cube[m >> 3] &= np.uint8(~(1 << (m & 7)) & 0xFF)
    return stop


@njit(cache=True)
def _visit_cells(
    cells: np.ndarray,
    start: int,
    corner: np.ndarray,
    cube: np.ndarray,
    table_keys: np.ndarray,
    table_vals: np.ndarray,
    shift: int,
    block_coords: np.ndarray,
    count: np.ndarray,
    logodds: np.ndarray,
    known: np.ndarray,
    flags: np.ndarray,
    block_scan: np.ndarray,
    pending: np.ndarray,
    updates: np.ndarray,
    lut: np.ndarray,
    bs: int,
    lg: int,
    scan_id: int,
    delta: float,
    l_min: float,
    l_max: float,
) -> int:
    """Update each cell of (K, 3) ``cells`` (from ``start``) unless this scan has seen it.

    The general path, for end points and for the rare rays that leave the cube. Returns K, or
    the index of the cell where the pool ran out of blocks (that cell is left unseen).
    """
    last = EMPTY_KEY
    blk = -1
    stop = len(cells)
    q = pending.shape[1] - 1
    for c in range(start, len(cells)):
        ix = cells[c, 0]
        iy = cells[c, 1]
        iz = cells[c, 2]
        cx = ix - corner[0]
        cy = iy - corner[1]
        cz = iz - corner[2]
        in_cube = 0 <= cx < CUBE_SIDE and 0 <= cy < CUBE_SIDE and 0 <= cz < CUBE_SIDE
        m = 0
        if in_cube:
            m = _morton(cx, cy, cz)
            seen = np.int64(cube[m >> 3])
            if seen & (1 << (m & 7)):
                continue
            cube[m >> 3] = np.uint8(seen | (1 << (m & 7)))
            cube[CUBE_BYTES + (m >> (CUBE_CHUNK_BITS + 3))] = 1
        bx, lx = _locate(ix, bs, lg)
        by, ly = _locate(iy, bs, lg)
        bz, lz = _locate(iz, bs, lg)
        key = pack_block(bx, by, bz)
        if key != last:
            blk = _probe(table_keys, table_vals, shift, key)
            if blk < 0:
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
                if in_cube:
                    cube[m >> 3] = np.uint8(np.int64(cube[m >> 3]) & ~(1 << (m & 7)))
                stop = c
                break
            if block_scan[blk] != scan_id:
                block_scan[blk] = scan_id
                flags[blk, :] = 0
            last = key
        flat = lut[0, lx] + lut[1, ly] + lut[2, lz]
        if not in_cube:
            seen = np.int64(flags[blk, flat >> 3])
            if seen & (1 << (flat & 7)):
                continue
            flags[blk, flat >> 3] = np.uint8(seen | (1 << (flat & 7)))
        n = pending[0, 0] + 1
        pending[0, n] = blk
        pending[1, n] = flat
        pending[0, 0] = n
        if n == q:
            _flush(logodds, known, pending, updates, delta, l_min, l_max)
    _flush(logodds, known, pending, updates, delta, l_min, l_max)
    return stop


@njit(cache=True)
def _trace_rays(
    ends: np.ndarray,
    start: int,
    o: np.ndarray,
    corner: np.ndarray,
    grid_origin: np.ndarray,
    inv_res: float,
    cube: np.ndarray,
    table_keys: np.ndarray,
    table_vals: np.ndarray,
    shift: int,
    block_coords: np.ndarray,
    count: np.ndarray,
    logodds: np.ndarray,
    known: np.ndarray,
    flags: np.ndarray,
    block_scan: np.ndarray,
    pending: np.ndarray,
    updates: np.ndarray,
    lut: np.ndarray,
    bs: int,
    lg: int,
    scan_id: int,
    delta: float,
    l_min: float,
    l_max: float,
) -> int:
    """Free evidence on every cell from the sensor's cell ``o`` (cell units) up to, not
    including, each end's cell. Returns the ray to resume from when the pool ran out of blocks,
    or ``len(ends)`` when every ray is done.

    Amanatides–Woo traversal, with the number of steps per axis fixed in advance by the two end
    cells, so the walk ends exactly in the end cell whatever the rounding. Ties (a ray through
    an edge or corner) step z before y before x, as OctoMap's comparisons do. Rays within
    the cube step through its Morton-ordered bitmap and collect the cells not yet seen in
    ``fresh``, which is applied in batches.
    """
    inf = math.inf
    ox, oy, oz = o[0], o[1], o[2]
    ix0 = math.floor(ox)
    iy0 = math.floor(oy)
    iz0 = math.floor(oz)
    m0 = _morton(ix0 - corner[0], iy0 - corner[1], iz0 - corner[2])
    n_cap = 16384
    fresh = np.empty(n_cap, dtype=np.int64)
    n_fresh = 0
    batch_start = start
    e = np.empty(3, dtype=np.float64)
    for n in range(start, len(ends)):
        ex = (ends[n, 0] - grid_origin[0]) * inv_res
        ey = (ends[n, 1] - grid_origin[1]) * inv_res
        ez = (ends[n, 2] - grid_origin[2]) * inv_res
        jx = math.floor(ex)
        jy = math.floor(ey)
        jz = math.floor(ez)
        nx = abs(jx - ix0)
        ny = abs(jy - iy0)
        nz = abs(jz - iz0)
        total = nx + ny + nz
        if total == 0:
            continue
        cx = jx - corner[0]
        cy = jy - corner[1]
        cz = jz - corner[2]
        inside = 0 <= cx < CUBE_SIDE and 0 <= cy < CUBE_SIDE and 0 <= cz < CUBE_SIDE
        if n_fresh > n_cap - 3 * CUBE_SIDE or not inside:
            done = _apply_fresh(
                fresh,
                n_fresh,
                corner,
                cube,
                table_keys,
                table_vals,
                shift,
                block_coords,
                count,
                logodds,
                known,
                block_scan,
                updates,
                lut,
                bs,
                lg,
                delta,
                l_min,
                l_max,
            )
            if done < n_fresh:
                return batch_start
            n_fresh = 0
            batch_start = n
        if not inside:
            e[0] = ex
            e[1] = ey
            e[2] = ez
            cells = ray_cells(o, e, False)
            done = _visit_cells(
                cells,
                0,
                corner,
                cube,
                table_keys,
                table_vals,
                shift,
                block_coords,
                count,
                logodds,
                known,
                flags,
                block_scan,
                pending,
                updates,
                lut,
                bs,
                lg,
                scan_id,
                delta,
                l_min,
                l_max,
            )
            if done < len(cells):
                return n
            batch_start = n + 1
            continue
        sx = 1 if jx > ix0 else -1
        sy = 1 if jy > iy0 else -1
        sz = 1 if jz > iz0 else -1
        # Dilated-integer increments: +1 is the axis's lowest bit, −1 all of its bits.
        incx = 4 if sx > 0 else _MX
        incy = 2 if sy > 0 else _MY
        incz = 1 if sz > 0 else _MZ
        tmx = inf
        tmy = inf
        tmz = inf
        tdx = 0.0
        tdy = 0.0
        tdz = 0.0
        if nx > 0:
            tdx = 1.0 / abs(ex - ox)
            tmx = ((ix0 + 1 if sx > 0 else ix0) - ox) / (ex - ox)
        if ny > 0:
            tdy = 1.0 / abs(ey - oy)
            tmy = ((iy0 + 1 if sy > 0 else iy0) - oy) / (ey - oy)
        if nz > 0:
            tdz = 1.0 / abs(ez - oz)
            tmz = ((iz0 + 1 if sz > 0 else iz0) - oz) / (ez - oz)
        m = m0
        seen = np.int64(cube[m >> 3])
        if not seen & (1 << (m & 7)):
            cube[m >> 3] = np.uint8(seen | (1 << (m & 7)))
            fresh[n_fresh] = m
            n_fresh += 1
        for _ in range(total - 1):
            if tmx < tmy:
                if tmx < tmz:
                    nx -= 1
                    tmx = tmx + tdx if nx > 0 else inf
                    m = (((m | ~_MX) + incx) & _MX) | (m & ~_MX)
                else:
                    nz -= 1
                    tmz = tmz + tdz if nz > 0 else inf
                    m = (((m | ~_MZ) + incz) & _MZ) | (m & ~_MZ)
            elif tmy < tmz:
                ny -= 1
                tmy = tmy + tdy if ny > 0 else inf
                m = (((m | ~_MY) + incy) & _MY) | (m & ~_MY)
            else:
                nz -= 1
                tmz = tmz + tdz if nz > 0 else inf
                m = (((m | ~_MZ) + incz) & _MZ) | (m & ~_MZ)
            byte = m >> 3
            seen = np.int64(cube[byte])
            bit = 1 << (m & 7)
            if not seen & bit:
                cube[byte] = np.uint8(seen | bit)
                fresh[n_fresh] = m
                n_fresh += 1
    done = _apply_fresh(
        fresh,
        n_fresh,
        corner,
        cube,
        table_keys,
        table_vals,
        shift,
        block_coords,
        count,
        logodds,
        known,
        block_scan,
        updates,
        lut,
        bs,
        lg,
        delta,
        l_min,
        l_max,
    )
    if done < n_fresh:
        return batch_start
    return len(ends)


@njit(cache=True)
def first_bad_point(points: np.ndarray, origin: np.ndarray, reach_m: float) -> int:
    """Index of the first (N, 3) point that is not finite or lies ``reach_m`` or more from
    ``origin`` along an axis; −1 if none."""
    for n in range(len(points)):
        for axis in range(3):
            if not abs(points[n, axis] - origin[axis]) < reach_m:
                return n
    return -1


@njit(cache=True)
def reset_cube(cube: np.ndarray) -> None:
    """Clear the chunks of the bitmap that a scan wrote to, and their marks."""
    chunk = 1 << CUBE_CHUNK_BITS
    for c in range(CUBE_BYTES >> CUBE_CHUNK_BITS):
        if cube[CUBE_BYTES + c]:
            cube[c * chunk : (c + 1) * chunk] = 0
            cube[CUBE_BYTES + c] = 0


@njit(cache=True)
def integrate(
    hits: np.ndarray,
    free_ends: np.ndarray,
    sensor: np.ndarray,
    grid_origin: np.ndarray,
    inv_res: float,
    cube: np.ndarray,
    table_keys: np.ndarray,
    table_vals: np.ndarray,
    shift: int,
    block_coords: np.ndarray,
    count: np.ndarray,
    logodds: np.ndarray,
    known: np.ndarray,
    flags: np.ndarray,
    block_scan: np.ndarray,
    updates: np.ndarray,
    lut: np.ndarray,
    bs: int,
    lg: int,
    scan_id: int,
    l_hit: float,
    l_miss: float,
    l_min: float,
    l_max: float,
    phase: int,
    start: int,
) -> tuple[int, int]:
    """Integrate one scan; returns (phase, index) to resume from, phase 3 when done.

    ``hits`` (N, 3): end points of returns; ``free_ends`` (M, 3): where no-return beams stop
    giving free evidence; ``sensor`` (3,): the sensor origin — all in the grid's frame.
    ``cube`` (CUBE_ARRAY_BYTES,) uint8: the scan's bitmap around the sensor, all zeros when the
    scan starts, kept between calls of the same scan and cleared when it is done. End cells are
    updated first, so a cell that is an end point anywhere in the scan is occupied for the whole
    scan; every cell is updated at most once per scan. ``lg`` = log2(bs) when bs is a power of
    two, else −1.
    """
    pending = np.zeros((2, 4097), dtype=np.int64)
    o = np.empty(3, dtype=np.float64)
    corner = np.empty(3, dtype=np.int64)
    for axis in range(3):
        o[axis] = (sensor[axis] - grid_origin[axis]) * inv_res
        # The cube is aligned to blocks when they are powers of two (see _apply_fresh).
        cell = math.floor(o[axis])
        corner[axis] = (cell >> lg << lg if lg >= 0 else cell) - CUBE_HALF
    if phase == PHASE_HITS:
        cells = np.empty((len(hits), 3), dtype=np.int64)
        for n in range(len(hits)):
            for axis in range(3):
                cells[n, axis] = math.floor((hits[n, axis] - grid_origin[axis]) * inv_res)
        stop = _visit_cells(
            cells,
            start,
            corner,
            cube,
            table_keys,
            table_vals,
            shift,
            block_coords,
            count,
            logodds,
            known,
            flags,
            block_scan,
            pending,
            updates,
            lut,
            bs,
            lg,
            scan_id,
            l_hit,
            l_min,
            l_max,
        )
        if stop < len(hits):
            return PHASE_HITS, stop
        phase = PHASE_RAYS
        start = 0
    for current, ends in ((PHASE_RAYS, hits), (PHASE_FREE, free_ends)):
        if phase != current:
            continue
        stop = _trace_rays(
            ends,
            start,
            o,
            corner,
            grid_origin,
            inv_res,
            cube,
            table_keys,
            table_vals,
            shift,
            block_coords,
            count,
            logodds,
            known,
            flags,
            block_scan,
            pending,
            updates,
            lut,
            bs,
            lg,
            scan_id,
            l_miss,
            l_min,
            l_max,
        )
        if stop < len(ends):
            return current, stop
        phase = current + 1
        start = 0
    reset_cube(cube)
    return PHASE_DONE, 0


@njit(cache=True)
def ray_cells(start: np.ndarray, end: np.ndarray, include_end: bool) -> np.ndarray:
    """(K, 3) int64 cells a segment visits, in order (both ends in cell units).

    The same traversal as the integration kernel, without storage: for tests and for callers
    that need the cells themselves.
    """
    ix = math.floor(start[0])
    iy = math.floor(start[1])
    iz = math.floor(start[2])
    jx = math.floor(end[0])
    jy = math.floor(end[1])
    jz = math.floor(end[2])
    nx = abs(jx - ix)
    ny = abs(jy - iy)
    nz = abs(jz - iz)
    total = nx + ny + nz
    out = np.empty((total + 1, 3), dtype=np.int64)
    out[0, 0] = ix
    out[0, 1] = iy
    out[0, 2] = iz
    inf = math.inf
    sx = 1 if jx > ix else -1
    sy = 1 if jy > iy else -1
    sz = 1 if jz > iz else -1
    tmx = inf
    tmy = inf
    tmz = inf
    tdx = 0.0
    tdy = 0.0
    tdz = 0.0
    if nx > 0:
        tdx = 1.0 / abs(end[0] - start[0])
        tmx = ((ix + 1 if sx > 0 else ix) - start[0]) / (end[0] - start[0])
    if ny > 0:
        tdy = 1.0 / abs(end[1] - start[1])
        tmy = ((iy + 1 if sy > 0 else iy) - start[1]) / (end[1] - start[1])
    if nz > 0:
        tdz = 1.0 / abs(end[2] - start[2])
        tmz = ((iz + 1 if sz > 0 else iz) - start[2]) / (end[2] - start[2])
    for s in range(1, total + 1):
        # Ties: z before y before x (OctoMap's comparisons).
        axis = (0 if tmx < tmz else 2) if tmx < tmy else (1 if tmy < tmz else 2)
        if axis == 0:
            ix += sx
            nx -= 1
            tmx = tmx + tdx if nx > 0 else inf
        elif axis == 1:
            iy += sy
            ny -= 1
            tmy = tmy + tdy if ny > 0 else inf
        else:
            iz += sz
            nz -= 1
            tmz = tmz + tdz if nz > 0 else inf
        out[s, 0] = ix
        out[s, 1] = iy
        out[s, 2] = iz
    return out if include_end else out[:total]


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
        bx, lx = _split(cells[n, 0], bs)
        by, ly = _split(cells[n, 1], bs)
        bz, lz = _split(cells[n, 2], bs)
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
        bx, lx = _split(cells[n, 0], bs)
        by, ly = _split(cells[n, 1], bs)
        bz, lz = _split(cells[n, 2], bs)
        key = pack_block(bx, by, bz)
        if key != last_key:
            blk = find_block(table_keys, table_vals, shift, bx, by, bz)
            last_key = key
        if blk >= 0:
            flat = lut[0, lx] + lut[1, ly] + lut[2, lz]
            if (known[blk, flat >> 3] >> (flat & 7)) & 1:
                values[n] = logodds[blk, flat]
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
                    sbx, slx = _split(math.floor(px * inv_res), bs)
                    sby, sly = _split(math.floor(py * inv_res), bs)
                    sbz, slz = _split(math.floor(pz * inv_res), bs)
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
