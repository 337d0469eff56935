"""Nearest neighbours within a reach on a dense voxel grid (the registration's correspondences
and normals, docs/design.md §7).

The registration asks, many times over, for the few points of a cloud nearest to each of
thousands of query points, never farther than a fixed reach (30 cm). A k-d tree answers any
such question; a grid answers this one faster: the points are sorted by the cell of a dense
3D grid over their bounding box, and each query visits the cells around its own in shells of
growing Chebyshev distance, stopping as soon as no farther shell can hold a point nearer than
the k-th found. A converged registration's query finds its match in the first shell (27 cells).

The answer is a k-d tree's (``scipy.spatial.cKDTree.query(..., k, distance_upper_bound)``):
indices of the k nearest within the reach, nearest first, ``len(points)`` where fewer lie
there; equidistant points may come in another order.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from estimation.errors import EstimationError

__all__ = ["PointGrid"]

#: The grid's cells are at least this big (m), and at most this many per point (and never more
#: than ``_MAX_CELLS``): a cloud spread over a large box gets larger cells, so that the grid's
#: memory stays that of the points (the search stays exact, only slower).
_MIN_CELL_M = 0.1
_CELLS_PER_POINT = 4
_MAX_CELLS = 1 << 23


class PointGrid:
    """``points`` (N, 3), finite, sorted into the cells of a dense grid over their box."""

    def __init__(self, points: np.ndarray, cell_m: float = _MIN_CELL_M) -> None:
        if np.size(points) >= 3 << 31:  # its indices are 4 bytes each
            raise EstimationError(f"neighbour grid: {np.size(points) // 3:,} points, "
                                  "at most 2,147,483,647")  # fmt: skip
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        if not np.isfinite(points).all():
            raise EstimationError("neighbour grid: points must be finite")
        if not cell_m > 0.0:
            raise EstimationError(f"neighbour grid: cell size must be positive, got {cell_m}")
        self.size = len(points)
        lower = points.min(axis=0) if len(points) else np.zeros(3)
        span = (points.max(axis=0) - lower) if len(points) else np.zeros(3)
        # Cells of cell_m unless that makes too many; then as many as allowed.
        most = min(max(_CELLS_PER_POINT * len(points), 4096), _MAX_CELLS)
        cell = max(cell_m, float(np.prod(span + cell_m) / most) ** (1.0 / 3.0))
        dims = np.floor(span / cell).astype(np.int64) + 1
        while int(np.prod(dims)) > most:  # rounding up in floor(span / cell) + 1
            cell *= 1.05
            dims = np.floor(span / cell).astype(np.int64) + 1
        self.cell_m = cell
        self.lower = lower
        self.dims = dims
        ijk = np.minimum(np.floor((points - lower) / cell).astype(np.int64), dims - 1)
        keys = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
        order = np.argsort(keys, kind="stable")
        self.sorted = np.ascontiguousarray(points[order])
        # 4-byte indices: 20 of the 64 bytes a point took here with 8-byte ones.
        self.order = order.astype(np.int32)
        counts = np.bincount(keys, minlength=int(np.prod(dims)))
        self.starts = np.zeros(len(counts) + 1, dtype=np.int32)
        np.cumsum(counts, out=self.starts[1:])

    def __len__(self) -> int:
        return self.size

    def query(self, queries: np.ndarray, k: int, reach_m: float) -> np.ndarray:
        """(Q, k) indices of the ``k`` points nearest to each query within ``reach_m``, nearest
        first; ``len(self)`` where fewer lie within reach."""
        queries = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
        if k < 1:
            raise EstimationError(f"neighbour grid: k must be at least 1, got {k}")
        return self._answer(queries, k, reach_m, False)

    def any_within(self, queries: np.ndarray, reach_m: float) -> np.ndarray:
        """(Q,) bool: whether some point lies within ``reach_m`` of each query. The search stops
        at the first such point instead of going on for the nearest (the registration's
        overlap check: about half its time went into finding nearest points it did not use)."""
        queries = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
        return self._answer(queries, 1, reach_m, True)[:, 0] < self.size

    def _answer(self, queries: np.ndarray, k: int, reach_m: float, any_one: bool) -> np.ndarray:
        out = np.full((len(queries), k), self.size, dtype=np.int64)
        if self.size and len(queries) and reach_m >= 0.0:
            _query(self.sorted, self.order, self.starts, self.lower, self.dims, self.cell_m,
                   queries, float(reach_m), any_one, out)  # fmt: skip
        return out


@njit(cache=True, nogil=True)
def _query(
    points: np.ndarray, order: np.ndarray, starts: np.ndarray, lower: np.ndarray,
    dims: np.ndarray, cell: float, queries: np.ndarray, reach: float, any_one: bool,
    out: np.ndarray,
) -> None:  # fmt: skip
    """The k nearest within reach of each query into ``out``; with ``any_one`` (k = 1), any
    one within reach: the first found."""
    k = out.shape[1]
    nx, ny, nz = dims[0], dims[1], dims[2]
    reach2 = reach * reach
    shells = math.ceil(reach / cell)
    best = np.empty(k)
    found = np.empty(k, dtype=np.int64)
    for q in range(len(queries)):
        qx, qy, qz = queries[q, 0], queries[q, 1], queries[q, 2]
        fx, fy, fz = (qx - lower[0]) / cell, (qy - lower[1]) / cell, (qz - lower[2]) / cell
        ix, iy, iz = math.floor(fx), math.floor(fy), math.floor(fz)
        # The query's distance to its own cell's nearest face: a point s shells out lies at
        # least (s - 1) cells plus this far away.
        margin = cell * min(fx - ix, ix + 1 - fx, fy - iy, iy + 1 - fy, fz - iz, iz + 1 - fz)
        count = 0
        for s in range(shells + 1):
            if any_one and count == k:
                break
            if s > 0:
                bound = (s - 1) * cell + margin
                if bound * bound > reach2 or (count == k and best[k - 1] <= bound * bound):
                    break
            z0, z1 = max(iz - s, 0), min(iz + s, nz - 1)
            if z0 > z1:
                continue  # the shell lies above or below the grid
            for x in range(max(ix - s, 0), min(ix + s, nx - 1) + 1):
                ex = x == ix - s or x == ix + s
                for y in range(max(iy - s, 0), min(iy + s, ny - 1) + 1):
                    column = (x * ny + y) * nz
                    # A column on the shell's box's side lies in the shell from z0 to z1, one
                    # range of the sorted points; inside the box only its two z faces do.
                    for face in range(2):
                        if ex or y == iy - s or y == iy + s:
                            if face == 1:
                                break
                            first, end = starts[column + z0], starts[column + z1 + 1]
                        else:
                            z = iz - s if face == 0 else iz + s
                            if z < z0 or z > z1:
                                continue
                            first, end = starts[column + z], starts[column + z + 1]
                        for p in range(first, end):
                            dx = points[p, 0] - qx
                            dy = points[p, 1] - qy
                            dz = points[p, 2] - qz
                            d2 = dx * dx + dy * dy + dz * dz
                            if d2 > reach2 or (count == k and d2 >= best[k - 1]):
                                continue
                            j = count if count < k else k - 1
                            while j > 0 and best[j - 1] > d2:
                                best[j] = best[j - 1]
                                found[j] = found[j - 1]
                                j -= 1
                            best[j] = d2
                            found[j] = order[p]
                            if count < k:
                                count += 1
                            if any_one:
                                break
                        if any_one and count == k:
                            break
                    if any_one and count == k:
                        break
                if any_one and count == k:
                    break
        for j in range(count):
            out[q, j] = found[j]
