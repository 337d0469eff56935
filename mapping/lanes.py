"""A scan's rays walked on several threads (``OccupancyGrid.integrate_scan(threads=...)``).

The rays that stay in the scan's cube only mark cells in it (``mapping.kernels.traversal``), so
shares of them can be walked at once, each thread in a cube of its own (marks of two threads in
one byte would lose bits); the cubes are merged into the caller's, whose marks are then applied
as when one thread walked them all. The rays that leave the cube are left to that one thread, in
their order: a grid fused this way is the same bit for bit.
"""

from __future__ import annotations

import itertools
import os
import threading
from concurrent.futures import ThreadPoolExecutor, wait

import numpy as np

from mapping.kernels.cube import merge_cube
from mapping.kernels.integrate import scan_frame
from mapping.kernels.traversal import mark_rays
from mapping.storage import lane_cubes

__all__ = ["RAYS_PER_LANE", "mark_side_by_side"]

#: A thread that marks a share of a scan's rays gets at least this many: below, starting it
#: costs more than it saves.
RAYS_PER_LANE = 4096
_HELPERS: ThreadPoolExecutor | None = None
_HELPERS_LOCK = threading.Lock()


def _helpers() -> ThreadPoolExecutor:
    """The threads that mark shares of scans' rays beside the caller's."""
    global _HELPERS
    with _HELPERS_LOCK:
        if _HELPERS is None:
            workers = max(1, (os.cpu_count() or 2) - 1)
            _HELPERS = ThreadPoolExecutor(workers, thread_name_prefix="coopmap-rays")
        return _HELPERS


def mark_side_by_side(
    hits: np.ndarray, free_ends: np.ndarray, sensor: np.ndarray, grid_origin: np.ndarray,
    inv_res: float, lg: int, cube: np.ndarray, lanes: int,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Mark the cells of the rays to ``hits`` and ``free_ends`` that stay in the scan's cube,
    ``lanes`` shares at once (the first in ``cube``, on this thread), and merge the marks into
    ``cube``; the rays left to walk (their ends, in their order)."""
    o, corner = scan_frame(sensor, grid_origin, inv_res, lg)
    shares = [
        (hits[a:b], free_ends[c:d])
        for (a, b), (c, d) in zip(_split(len(hits), lanes), _split(len(free_ends), lanes),
                                  strict=True)
    ]  # fmt: skip
    cubes = [cube, *lane_cubes(lanes - 1)]

    def mark(k: int) -> tuple[np.ndarray, np.ndarray]:
        rays, free = shares[k]
        left_rays = np.empty(len(rays), dtype=np.int64)
        left_free = np.empty(len(free), dtype=np.int64)
        n_rays = mark_rays(rays, o, corner, grid_origin, inv_res, cubes[k], left_rays)
        n_free = mark_rays(free, o, corner, grid_origin, inv_res, cubes[k], left_free)
        return rays[left_rays[:n_rays]], free[left_free[:n_free]]

    others = [_helpers().submit(mark, k) for k in range(1, lanes)]
    try:
        first = mark(0)
    finally:
        wait(others)  # on an error too: no helper goes on marking after the call has ended
    left = [first, *(f.result() for f in others)]
    for other in cubes[1:]:
        merge_cube(cube, other)
    return (np.concatenate([rays for rays, _ in left]),
            np.concatenate([free for _, free in left]))  # fmt: skip


def _split(count: int, parts: int) -> list[tuple[int, int]]:
    """``parts`` contiguous ranges of ``count`` items, as even as can be."""
    edges = [count * k // parts for k in range(parts + 1)]
    return list(itertools.pairwise(edges))
