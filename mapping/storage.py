"""The arrays an occupancy grid lives in: its block pool, the pool's hash table, the per-scan
bits, and the de-duplication bitmap that every grid shares. The kernels of ``mapping.kernels``
work on these arrays; ``mapping.grid.OccupancyGrid`` owns one :class:`BlockStorage`."""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field

import numpy as np

from mapping.kernels.blocks import EMPTY_KEY, layout_table, rebuild_table
from mapping.kernels.cube import CUBE_ARRAY_BYTES

__all__ = [
    "LOGODDS_DTYPE",
    "BlockStorage",
    "discard_scan_cube",
    "hash_table_bits",
    "scan_cube",
    "stored_bounds",
]

#: The type a cell's log-odds is stored in: float32, as OctoMap stores them. Updates are summed
#: in float64 and rounded once, on the store; 24 bits of mantissa resolve 2e-7 at the clamps.
LOGODDS_DTYPE = np.float32


def stored_bounds(l_min: float, l_max: float) -> tuple[float, float]:
    """The clamping bounds as stored values: the float32 values nearest to [l_min, l_max] that
    lie inside it, so that a clamped, stored log-odds never leaves the float64 bounds."""
    low, high = np.float32(l_min), np.float32(l_max)
    if float(low) < l_min:
        low = np.nextafter(low, np.float32(np.inf))
    if float(high) > l_max:
        high = np.nextafter(high, np.float32(-np.inf))
    return float(low), float(high)


@dataclass
class BlockStorage:
    """The block pool, its hash table and the per-scan bits (see ``mapping.kernels.blocks``)."""

    block_size: int
    capacity: int
    coords: np.ndarray = field(init=False)  # (capacity, 3) int64 block coordinates
    logodds: np.ndarray = field(init=False)  # (capacity, bs³) float32, 0 until observed
    known: np.ndarray = field(init=False)  # (capacity, ⌈bs³/8⌉) uint8 bits: observed
    flags: np.ndarray = field(init=False)  # (capacity, ⌈bs³/8⌉) uint8 bits: updated this scan
    block_scan: np.ndarray = field(init=False)  # (capacity,) int64 scan the flags belong to
    count: np.ndarray = field(init=False)  # (1,) int64 blocks in use
    updates: np.ndarray = field(init=False)  # (1,) int64 cell updates by scans so far
    table: np.ndarray = field(init=False)  # (2, 2^bits) int64: keys, pool indices
    table_bits: int = field(init=False)
    lut: np.ndarray = field(init=False)  # (3, bs) in-block layout

    def __post_init__(self) -> None:
        cells = self.block_size**3
        # Rows of blocks not yet created are left uninitialised: the kernels clear a block's
        # rows when they create it, so growing the pool copies only the rows in use.
        self.coords = np.zeros((self.capacity, 3), dtype=np.int64)
        self.logodds = np.empty((self.capacity, cells), dtype=LOGODDS_DTYPE)
        self.known = np.empty((self.capacity, -(-cells // 8)), dtype=np.uint8)
        self.flags = np.empty_like(self.known)
        self.block_scan = np.zeros(self.capacity, dtype=np.int64)
        self.count = np.zeros(1, dtype=np.int64)
        self.updates = np.zeros(1, dtype=np.int64)
        self.table_bits = hash_table_bits(self.capacity)
        self.table = np.full((2, 1 << self.table_bits), EMPTY_KEY, dtype=np.int64)
        self.lut = layout_table(self.block_size)

    @property
    def shift(self) -> int:
        return 64 - self.table_bits

    @property
    def used(self) -> int:
        return int(self.count[0])

    def grow(self, capacity: int | None = None) -> None:
        """Double the pool (or grow it to ``capacity``), keeping every block."""
        n = self.used
        new = max(capacity or 0, 2 * self.capacity, 1)

        def grown(old: np.ndarray) -> np.ndarray:
            out = np.empty((new, *old.shape[1:]), dtype=old.dtype)
            out[:n] = old[:n]
            return out

        self.coords, self.logodds = grown(self.coords), grown(self.logodds)
        self.known, self.flags = grown(self.known), grown(self.flags)
        self.block_scan = grown(self.block_scan)
        self.capacity = new
        self.table_bits = hash_table_bits(new)
        self.table = rebuild_table(self.coords, n, self.table_bits)

    def nbytes(self) -> int:
        arrays = (self.coords, self.logodds, self.known, self.flags, self.block_scan, self.table)
        return sum(int(a.nbytes) for a in arrays)


#: The bitmap that de-duplicates a scan's updates near the sensor (see ``mapping.kernels.cube``):
#: 16 MB of address space, of which a scan touches the pages around its rays. All zeros
#: between scans, so every grid of a thread shares that thread's (the kernel releases the GIL:
#: grids on other threads integrate at the same time).
_SCAN_CUBE = threading.local()


def scan_cube() -> np.ndarray:
    """This thread's de-duplication bitmap, allocated on first use."""
    cube = getattr(_SCAN_CUBE, "cube", None)
    if cube is None:
        cube = _SCAN_CUBE.cube = np.zeros(CUBE_ARRAY_BYTES, dtype=np.uint8)
    return cube


def discard_scan_cube() -> None:
    """Drop this thread's bitmaps (after a scan failed half-way they hold that scan's bits)."""
    _SCAN_CUBE.cube = None
    _SCAN_CUBE.lanes = []


def lane_cubes(count: int) -> list[np.ndarray]:
    """``count`` more bitmaps of this thread, for the threads that mark a share of its scan's
    rays (each in its own: marks of two threads in one byte would lose bits); all zeros
    between scans, like :func:`scan_cube`'s."""
    lanes: list[np.ndarray] = getattr(_SCAN_CUBE, "lanes", [])
    while len(lanes) < count:
        lanes.append(np.zeros(CUBE_ARRAY_BYTES, dtype=np.uint8))
    _SCAN_CUBE.lanes = lanes
    return lanes[:count]


def hash_table_bits(capacity: int) -> int:
    """Hash table size for a pool: at most half full."""
    return max(4, math.ceil(math.log2(2 * capacity)))
