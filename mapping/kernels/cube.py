"""The scan's "seen" cube: a Morton-ordered bitmap that de-duplicates updates near the sensor.

Within one scan each cell is updated once. Cells within ±CUBE_HALF cells of the sensor (per
axis) are tracked in a bitmap of the cube around it, in Morton order (an 8 × 8 × 8 corner of
the cube shares a cache line), where a ray steps from cell to cell with a few bit operations
and no lookup; most of a scan's traversal happens there (``mapping.kernels.traversal``). Cells
outside use the per-block bits. ``apply_fresh`` writes listed cube cells (the end points) into
the blocks; ``apply_marked`` writes every cell the rays marked, reading the bitmap in order: a
block's cells are contiguous there (the cube is aligned to blocks), so each block is looked up
once and its cells are written in memory order — in the rays' order the lookups jumped between
blocks, half the time of a fine scan. ``reset_cube`` clears the bitmap when the scan is done.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mapping.kernels.blocks import (
    EMPTY_KEY,
    find_or_add_block,
    locate,
    pack_block,
    probe,
    split,
)

CUBE_BITS = 9
CUBE_SIDE = 1 << CUBE_BITS
CUBE_HALF = CUBE_SIDE // 2
#: The bitmap's bytes, then one byte per 4 kB chunk of it: set when the scan wrote to the chunk,
#: so that clearing the bitmap after a scan touches only those chunks.
CUBE_BYTES = 1 << (3 * CUBE_BITS - 3)
CUBE_CHUNK_BITS = 12
CUBE_ARRAY_BYTES = CUBE_BYTES + (CUBE_BYTES >> CUBE_CHUNK_BITS)
MZ = 0x01249249  # Morton bits of z (bit 3i), y (3i + 1) and x (3i + 2) for 9-bit coordinates
MY = MZ << 1
MX = MZ << 2


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
def morton(x: int, y: int, z: int) -> int:
    return (_dilate(x) << 2) | (_dilate(y) << 1) | _dilate(z)


@njit(cache=True, inline="always")
def _block_key(m: int, corner: np.ndarray, bs: int, lg: int) -> int:
    """A number that names the block of cube cell ``m`` (Morton): with power-of-two blocks and a
    block-aligned cube, the block's own Morton code (the cell's code without its in-block
    bits); otherwise its packed coordinates."""
    if lg >= 0:
        return m >> (3 * lg)
    return pack_block(
        (_compact(m >> 2) + corner[0]) // bs,
        (_compact(m >> 1) + corner[1]) // bs,
        (_compact(m) + corner[2]) // bs,
    )


@njit(cache=True, inline="always")
def _block_of(
    m: int,
    corner: np.ndarray,
    table_keys: np.ndarray,
    table_vals: np.ndarray,
    shift: int,
    block_coords: np.ndarray,
    count: np.ndarray,
    logodds: np.ndarray,
    known: np.ndarray,
    block_scan: np.ndarray,
    bs: int,
    lg: int,
) -> int:
    """The pool index of cube cell ``m``'s block, created if new; −1 when the pool is full."""
    bx, _ = locate(_compact(m >> 2) + corner[0], bs, lg)
    by, _ = locate(_compact(m >> 1) + corner[1], bs, lg)
    bz, _ = locate(_compact(m) + corner[2], bs, lg)
    blk = probe(table_keys, table_vals, shift, pack_block(bx, by, bz))
    if blk < 0:
        blk = find_or_add_block(table_keys, table_vals, shift, block_coords, count, logodds,
                                known, block_scan, bx, by, bz)  # fmt: skip
    return blk


@njit(cache=True, inline="always")
def _offset(m: int, corner: np.ndarray, lut: np.ndarray, bs: int, lg: int) -> int:
    """Where cube cell ``m`` lies in its block: its in-block Morton bits when the blocks are
    powers of two (their layout is Morton order), the layout table's offset otherwise."""
    if lg >= 0:
        return m & ((1 << (3 * lg)) - 1)
    _, lx = split(_compact(m >> 2) + corner[0], bs)
    _, ly = split(_compact(m >> 1) + corner[1], bs)
    _, lz = split(_compact(m) + corner[2], bs)
    return lut[0, lx] + lut[1, ly] + lut[2, lz]


@njit(cache=True, inline="always")
def _update(
    logodds: np.ndarray, known: np.ndarray, blk: int, flat: int, delta: float, l_min: float,
    l_max: float,
) -> None:  # fmt: skip
    logodds[blk, flat] = min(max(logodds[blk, flat] + delta, l_min), l_max)
    known[blk, flat >> 3] |= np.uint8(1 << (flat & 7))


@njit(cache=True)
def apply_fresh(
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
    last = EMPTY_KEY
    stop = n_fresh
    for k in range(n_fresh):
        m = fresh[k]
        cube[CUBE_BYTES + (m >> (CUBE_CHUNK_BITS + 3))] = 1
        key = _block_key(m, corner, bs, lg)
        if key != last:
            blk = _block_of(m, corner, table_keys, table_vals, shift, block_coords, count,
                            logodds, known, block_scan, bs, lg)  # fmt: skip
            if blk < 0:
                stop = k
                break
            last = key
        _update(logodds, known, blk, _offset(m, corner, lut, bs, lg), delta, l_min, l_max)
    updates[0] += stop
    for k in range(stop, n_fresh):
        m = fresh[k]
        cube[m >> 3] &= np.uint8(~(1 << (m & 7)) & 0xFF)
    return stop


#: Index of a 64-bit word's lowest set bit from the top 6 bits of (that bit × ``_DE_BRUIJN``).
_DE_BRUIJN = np.uint64(0x03F79D71B4CB0A89)
_LOWEST_BIT = np.zeros(64, dtype=np.int64)
for _bit in range(64):
    _LOWEST_BIT[((1 << _bit) * int(_DE_BRUIJN) >> 58) & 63] = _bit


@njit(cache=True)
def apply_marked(
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
    block_scan: np.ndarray,
    updates: np.ndarray,
    lut: np.ndarray,
    bs: int,
    lg: int,
    delta: float,
    l_min: float,
    l_max: float,
) -> int:
    """Update every cell marked in the cube from Morton index ``start`` on, in Morton order;
    returns −1, or the index of the cell where the pool ran out of blocks (call again from
    there once it has grown). The caller unmarks the cells it updated otherwise first."""
    words = cube[:CUBE_BYTES].view(np.uint64)
    chunk_words = 1 << (CUBE_CHUNK_BITS - 3)
    blk = -1
    last = EMPTY_KEY
    done = 0
    for c in range(start >> (CUBE_CHUNK_BITS + 3), CUBE_BYTES >> CUBE_CHUNK_BITS):
        if not cube[CUBE_BYTES + c]:
            continue
        for w in range(max(c * chunk_words, start >> 6), (c + 1) * chunk_words):
            word = words[w]
            if w == start >> 6:
                word &= ~np.uint64(0) << np.uint64(start & 63)  # the cells before start: done
            while word:
                bit = word & (~word + np.uint64(1))
                m = (w << 6) | _LOWEST_BIT[np.int64((bit * _DE_BRUIJN) >> np.uint64(58))]
                word ^= bit
                key = _block_key(m, corner, bs, lg)
                if key != last:
                    blk = _block_of(m, corner, table_keys, table_vals, shift, block_coords,
                                    count, logodds, known, block_scan, bs, lg)  # fmt: skip
                    if blk < 0:
                        updates[0] += done
                        return m
                    last = key
                _update(logodds, known, blk, _offset(m, corner, lut, bs, lg), delta, l_min,
                        l_max)  # fmt: skip
                done += 1
    updates[0] += done
    return -1


@njit(cache=True)
def unmark(
    points: np.ndarray, grid_origin: np.ndarray, inv_res: float, corner: np.ndarray,
    cube: np.ndarray,
) -> None:  # fmt: skip
    """Clear the cube's marks of the cells of (K, 3) ``points`` (those in the cube)."""
    for k in range(len(points)):
        cx = int(np.floor((points[k, 0] - grid_origin[0]) * inv_res)) - corner[0]
        cy = int(np.floor((points[k, 1] - grid_origin[1]) * inv_res)) - corner[1]
        cz = int(np.floor((points[k, 2] - grid_origin[2]) * inv_res)) - corner[2]
        if 0 <= cx < CUBE_SIDE and 0 <= cy < CUBE_SIDE and 0 <= cz < CUBE_SIDE:
            m = morton(cx, cy, cz)
            cube[m >> 3] &= np.uint8(~(1 << (m & 7)) & 0xFF)


@njit(cache=True, nogil=True)
def merge_cube(cube: np.ndarray, other: np.ndarray) -> None:
    """Mark in ``cube`` every cell marked in ``other`` (another thread's share of the scan's
    rays), and clear ``other``."""
    words = cube[:CUBE_BYTES].view(np.uint64)
    others = other[:CUBE_BYTES].view(np.uint64)
    chunk_words = 1 << (CUBE_CHUNK_BITS - 3)
    for c in range(CUBE_BYTES >> CUBE_CHUNK_BITS):
        if other[CUBE_BYTES + c]:
            for w in range(c * chunk_words, (c + 1) * chunk_words):
                words[w] |= others[w]
                others[w] = 0
            cube[CUBE_BYTES + c] = 1
            other[CUBE_BYTES + c] = 0


@njit(cache=True)
def reset_cube(cube: np.ndarray) -> None:
    """Clear the chunks of the bitmap that a scan wrote to, and their marks."""
    chunk = 1 << CUBE_CHUNK_BITS
    for c in range(CUBE_BYTES >> CUBE_CHUNK_BITS):
        if cube[CUBE_BYTES + c]:
            cube[c * chunk : (c + 1) * chunk] = 0
            cube[CUBE_BYTES + c] = 0
