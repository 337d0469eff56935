"""Scan integration: one scan's end points and rays into the grid, resumable.

End cells are updated first (occupied), then the free rays to them and the free rays of
no-return beams are traced, and last the cells those marked in the scan's cube are updated
(free) (``PHASE_*``); the traversal is ``mapping.kernels.traversal``. When the block pool is
full the kernel returns the phase and index to resume from; the caller grows the pool and
calls again.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from mapping.kernels.cube import (
    CUBE_HALF,
    CUBE_SIDE,
    apply_fresh,
    apply_marked,
    morton,
    reset_cube,
    unmark,
)
from mapping.kernels.traversal import trace_rays, visit_cells

#: Kernel phases: occupied end points, free rays to end points, free rays of no-return beams,
#: the free cells the rays marked in the cube (``start``: the Morton index to resume from).
PHASE_HITS, PHASE_RAYS, PHASE_FREE, PHASE_APPLY, PHASE_DONE = 0, 1, 2, 3, 4


@njit(cache=True, nogil=True)
def scan_frame(
    sensor: np.ndarray, grid_origin: np.ndarray, inv_res: float, lg: int
) -> tuple[np.ndarray, np.ndarray]:
    """The sensor in cell units (3,) and the corner cell of the scan's cube (3,)."""
    o = np.empty(3, dtype=np.float64)
    corner = np.empty(3, dtype=np.int64)
    for axis in range(3):
        o[axis] = (sensor[axis] - grid_origin[axis]) * inv_res
        # The cube is aligned to blocks when they are powers of two (see ``cube.apply_fresh``).
        cell = math.floor(o[axis])
        corner[axis] = (cell >> lg << lg if lg >= 0 else cell) - CUBE_HALF
    return o, corner


@njit(cache=True)
def _sort_hits(
    hits: np.ndarray,
    grid_origin: np.ndarray,
    inv_res: float,
    corner: np.ndarray,
    cube: np.ndarray,
    fresh: np.ndarray,
    outside: np.ndarray,
) -> tuple[int, int]:
    """The end cells of (N, 3) ``hits``: those in the cube and not yet marked there are marked
    and listed in ``fresh`` (Morton codes), the others in ``outside`` (cells); the two counts."""
    n_fresh = 0
    n_out = 0
    for n in range(len(hits)):
        ix = math.floor((hits[n, 0] - grid_origin[0]) * inv_res)
        iy = math.floor((hits[n, 1] - grid_origin[1]) * inv_res)
        iz = math.floor((hits[n, 2] - grid_origin[2]) * inv_res)
        cx = ix - corner[0]
        cy = iy - corner[1]
        cz = iz - corner[2]
        if 0 <= cx < CUBE_SIDE and 0 <= cy < CUBE_SIDE and 0 <= cz < CUBE_SIDE:
            m = morton(cx, cy, cz)
            seen = np.int64(cube[m >> 3])
            if not seen & (1 << (m & 7)):
                cube[m >> 3] = np.uint8(seen | (1 << (m & 7)))
                fresh[n_fresh] = m
                n_fresh += 1
        else:
            outside[n_out, 0] = ix
            outside[n_out, 1] = iy
            outside[n_out, 2] = iz
            n_out += 1
    return n_fresh, n_out


@njit(cache=True, nogil=True)
def integrate(
    hits: np.ndarray,
    rays: np.ndarray,
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
    until: int,
) -> tuple[int, int]:
    """Integrate one scan; returns (phase, index) to resume from, ``PHASE_DONE`` when done,
    or the phase after ``until`` (with index 0) once that one is done.

    ``hits`` (N, 3): end points of returns; ``rays`` (K, 3): the ends of the free rays traced
    (``hits``, or those of them not marked yet by :func:`mark_rays`); ``free_ends`` (M, 3):
    where no-return beams stop giving free evidence (all, or those not marked yet);
    ``sensor`` (3,): the sensor origin — all in the grid's frame.
    ``cube`` (CUBE_ARRAY_BYTES,) uint8: the scan's bitmap around the sensor, all zeros when the
    scan starts, kept between calls of the same scan and cleared when it is done. End cells are
    updated first, so a cell that is an end point anywhere in the scan is occupied for the whole
    scan; every cell is updated at most once per scan. ``lg`` = log2(bs) when bs is a power of
    two, else −1.
    """
    pending = np.zeros((2, 4097), dtype=np.int64)
    o, corner = scan_frame(sensor, grid_origin, inv_res, lg)
    if phase == PHASE_HITS:
        # End cells in the cube are marked there and applied as a batch; the others go through
        # the per-block bits. A pool that runs out restarts the phase: what was applied is
        # marked (skipped), the rest is not.
        fresh = np.empty(len(hits), dtype=np.int64)
        outside = np.empty((len(hits), 3), dtype=np.int64)
        n_fresh, n_out = _sort_hits(hits, grid_origin, inv_res, corner, cube, fresh, outside)
        done = apply_fresh(
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
            l_hit,
            l_min,
            l_max,
        )
        if done < n_fresh:
            return PHASE_HITS, 0
        stop = visit_cells(
            outside[:n_out],
            0,
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
        if stop < n_out:
            return PHASE_HITS, 0
        phase = PHASE_RAYS
        start = 0
        if until == PHASE_HITS:
            return phase, start
    for current, ends in ((PHASE_RAYS, rays), (PHASE_FREE, free_ends)):
        if phase != current:
            continue
        stop = trace_rays(
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
    # The end cells took their (occupied) update first; the rays marked them too.
    unmark(hits, grid_origin, inv_res, corner, cube)
    stop = apply_marked(
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
        block_scan,
        updates,
        lut,
        bs,
        lg,
        l_miss,
        l_min,
        l_max,
    )
    if stop >= 0:
        return PHASE_APPLY, stop
    reset_cube(cube)
    return PHASE_DONE, 0
