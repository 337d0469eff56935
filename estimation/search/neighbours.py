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

__all__ = ["NearestSince", "PointGrid"]

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
        self.points = points  # as given (a view of the caller's array when it is float64)
        lower, upper = np.zeros(3), np.zeros(3)
        if len(points):
            _bounds(points, lower, upper)  # points.min(axis=0) and max, 10× faster
        span = upper - lower
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
        # 4-byte indices: 20 of the 64 bytes a point took here with 8-byte ones.
        self.sorted = np.empty_like(points)
        self.order = np.empty(len(points), dtype=np.int32)
        self.starts = np.zeros(int(np.prod(dims)) + 1, dtype=np.int32)
        _sort_into_cells(points, lower, cell, dims, self.sorted, self.order, self.starts)

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
def _bounds(points: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> None:
    """The smallest and largest coordinate of ``points`` (at least one) on each axis."""
    for a in range(3):
        lower[a] = upper[a] = points[0, a]
    for p in range(1, len(points)):
        for a in range(3):
            v = points[p, a]
            if v < lower[a]:
                lower[a] = v
            elif v > upper[a]:
                upper[a] = v


@njit(cache=True, nogil=True)
def _sort_into_cells(
    points: np.ndarray, lower: np.ndarray, cell: float, dims: np.ndarray, sorted_: np.ndarray,
    order: np.ndarray, starts: np.ndarray,
) -> None:  # fmt: skip
    """A counting sort of ``points`` by their cells (x-major, then y, then z; points of one
    cell in their given order): the points in that order into ``sorted_``, their indices into
    ``order``, and where each cell's run begins into ``starts`` (one more than the cells)."""
    n = len(points)
    keys = np.empty(n, dtype=np.int64)
    for p in range(n):
        ix = min(math.floor((points[p, 0] - lower[0]) / cell), dims[0] - 1)
        iy = min(math.floor((points[p, 1] - lower[1]) / cell), dims[1] - 1)
        iz = min(math.floor((points[p, 2] - lower[2]) / cell), dims[2] - 1)
        key = (ix * dims[1] + iy) * dims[2] + iz
        keys[p] = key
        starts[key + 1] += 1
    for c in range(1, len(starts)):
        starts[c] += starts[c - 1]
    fill = starts[:-1].copy()
    for p in range(n):
        slot = fill[keys[p]]
        fill[keys[p]] = slot + 1
        for a in range(3):
            sorted_[slot, a] = points[p, a]
        order[slot] = p


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


class NearestSince:
    """:meth:`PointGrid.query` with ``k = 1`` for queries that move a little at a time (the
    registration's source points, iteration after iteration): a query is looked up again only
    when it has moved so far since its last lookup that another point may have become its
    nearest — half the gap between its nearest and second nearest then, within ``reach_m`` +
    ``margin_m`` — and otherwise answered from that lookup. The answers are the query's, index
    for index: a query kept lies strictly nearer to its point than to any other (ties are
    always looked up again), and whether that point is within reach is checked afresh."""

    def __init__(self, grid: PointGrid, count: int, reach_m: float, margin_m: float) -> None:
        if not (reach_m >= 0.0 and margin_m > 0.0):
            raise EstimationError(f"nearest: reach {reach_m} and margin {margin_m} must be "
                                  "non-negative and positive")  # fmt: skip
        self.grid = grid
        self.reach_m = reach_m
        self.margin_m = margin_m
        self.nearest = np.full(count, grid.size, dtype=np.int64)
        self.at = np.zeros((count, 3))  # where each was last looked up
        self.gap = np.full(count, -1.0)  # how far it may move from there (< 0: look it up)
        self.looked_up = 0  # queries looked up (for the tests)

    def query(self, rows: np.ndarray, queries: np.ndarray) -> np.ndarray:
        """(R,) the nearest point within reach of query ``rows[r]`` now at ``queries[r]``;
        ``len(grid)`` where none lies within reach."""
        queries = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
        rows = np.asarray(rows, dtype=np.int64)
        out = np.empty(len(rows), dtype=np.int64)
        stale = np.empty(len(rows), dtype=np.int64)
        points, reach = self.grid.points, float(self.reach_m)
        count = _recall(rows, queries, self.at, self.gap, self.nearest, points, reach, out, stale)
        if count:
            stale = stale[:count]
            far = reach + self.margin_m
            answer = self.grid.query(queries[stale], 2, far)
            _learn(rows, stale, queries, answer, points, reach, far, self.at, self.gap,
                   self.nearest, out)  # fmt: skip
            self.looked_up += count
        return out


#: Below this, a query's distances to two points count as equal (m; float round-off is ~1e-16).
_TIE_M = 1e-9


@njit(cache=True, nogil=True)
def _recall(
    rows: np.ndarray, queries: np.ndarray, at: np.ndarray, gap: np.ndarray,
    nearest: np.ndarray, points: np.ndarray, reach: float, out: np.ndarray, stale: np.ndarray,
) -> int:  # fmt: skip
    """Answers the queries that stayed within their gap into ``out``; the others' positions in
    ``rows`` into ``stale``, returning how many."""
    n = len(points)
    reach2 = reach * reach
    count = 0
    for r in range(len(rows)):
        i = rows[r]
        qx, qy, qz = queries[r, 0], queries[r, 1], queries[r, 2]
        mx, my, mz = qx - at[i, 0], qy - at[i, 1], qz - at[i, 2]
        g = gap[i]
        if g <= 0.0 or mx * mx + my * my + mz * mz >= g * g:
            stale[count] = r
            count += 1
            continue
        t = nearest[i]
        out[r] = n
        if t < n:  # the same sums as the grid's search, so the same verdict on the reach
            dx, dy, dz = points[t, 0] - qx, points[t, 1] - qy, points[t, 2] - qz
            if dx * dx + dy * dy + dz * dz <= reach2:
                out[r] = t
    return count


@njit(cache=True, nogil=True)
def _learn(
    rows: np.ndarray, stale: np.ndarray, queries: np.ndarray, answer: np.ndarray,
    points: np.ndarray, reach: float, far: float, at: np.ndarray, gap: np.ndarray,
    nearest: np.ndarray, out: np.ndarray,
) -> None:  # fmt: skip
    """From the two nearest within ``far`` of each stale query (``answer``): its answer, and
    its nearest, position and gap remembered."""
    n = len(points)
    reach2 = reach * reach
    for s in range(len(stale)):
        r = stale[s]
        i = rows[r]
        qx, qy, qz = queries[r, 0], queries[r, 1], queries[r, 2]
        at[i, 0], at[i, 1], at[i, 2] = qx, qy, qz
        first, second = answer[s, 0], answer[s, 1]
        nearest[i] = first
        out[r] = n
        if first >= n:  # nothing within far: nothing within reach until it moves by the margin
            gap[i] = far - reach - _TIE_M
            continue
        dx, dy, dz = points[first, 0] - qx, points[first, 1] - qy, points[first, 2] - qz
        d2 = dx * dx + dy * dy + dz * dz
        if d2 <= reach2:
            out[r] = first
        other = far
        if second < n:
            ex, ey, ez = points[second, 0] - qx, points[second, 1] - qy, points[second, 2] - qz
            other = math.sqrt(ex * ex + ey * ey + ez * ez)
        gap[i] = 0.5 * (other - math.sqrt(d2)) - _TIE_M
