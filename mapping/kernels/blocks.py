"""Block storage of the occupancy grid: block keys, in-block layout, the block hash table.

Storage (see ``mapping.grid``): the map is a pool of cubic blocks of ``bs³`` cells. A cell holds its
log-odds (float32, see ``mapping.storage``; 0, the prior, until observed) and a "known" bit
(``known``, (capacity, ⌈bs³/8⌉) uint8, bit ``f & 7`` of byte ``f >> 3`` for the cell stored at
``f``; set once the cell has been observed). Freshly allocated blocks are all zeros. Blocks are
found through an open-addressing hash table keyed by the packed block coordinates; a block is
created the first time a ray reaches it, so memory follows the observed volume. Within a block,
cells are laid out in Morton (Z-) order when ``bs`` is a power of two — the 2 × 2 × 2 neighbours of
a cell share a cache line, which is what a ray walking through the block touches next. The layout is
given by ``lut`` (3, bs): cell (x, y, z) of a block is at ``lut[0, x] + lut[1, y] + lut[2, z]``.

Kernels that may create blocks (``find_or_add_block``) return early when the pool is full; the
caller grows the pool and calls again from where the kernel stopped.

Cell coordinates: cell (i, j, k) spans ``origin + [i, i + 1) · resolution`` per axis, so a point
``p`` lies in cell ``floor((p − origin) / resolution)`` (OctoMap's convention with origin 0).
Block coordinates are packed into ``BLOCK_BITS`` bits each, which bounds the addressable volume
(``first_bad_point``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Block coordinates are packed into 21 bits each, offset by 2^20.
BLOCK_BITS = 21
BLOCK_OFFSET = 1 << (BLOCK_BITS - 1)
EMPTY_KEY = -1
_HASH_MUL = np.uint64(0x9E3779B97F4A7C15)


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
def probe(table_keys: np.ndarray, table_vals: np.ndarray, shift: int, key: int) -> int:
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
def split(i: int, bs: int) -> tuple[int, int]:
    """(block, local) coordinate of cell coordinate ``i`` (floor division)."""
    b = i // bs
    return b, i - b * bs


@njit(cache=True, inline="always")
def locate(i: int, bs: int, lg: int) -> tuple[int, int]:
    """(block, local) coordinate of cell coordinate ``i``: shifts when bs = 2^lg (lg ≥ 0)."""
    if lg >= 0:
        return i >> lg, i & (bs - 1)
    return split(i, bs)


@njit(cache=True)
def first_bad_point(points: np.ndarray, origin: np.ndarray, reach_m: float) -> int:
    """Index of the first (N, 3) point that is not finite or lies ``reach_m`` or more from
    ``origin`` along an axis; −1 if none."""
    for n in range(len(points)):
        for axis in range(3):
            if not abs(points[n, axis] - origin[axis]) < reach_m:
                return n
    return -1
