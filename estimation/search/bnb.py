"""The best lattice pose alone, exactly: branch and bound over (rotation, translation block).

The score of each pose, its bounds over blocks of translations and how quarter turns align
the blocks: ``bnb_bounds``.

**Levels.** Level 2, B = 4 (7 × 7 windows): the bounds of every (rotation, block) pair by one small
FFT per rotation. Level 1, B = 2 (3 × 3 windows): the four 2 × 2 quarters of a block that level 2
leaves, by direct sums over the groups. Level 0: the exact scores of a quarter that level 1 leaves,
direct float64 sums over the local cells. On the benchmark (``coopmap bench search``) level 2 leaves
149 of 917,889 blocks, level 1 17 of their 596 quarters; a coarser first level prunes nothing worth
having (B = 8 keeps 30 % of the blocks and every rotation: a 15 × 15 window nearly always holds a
wall for each occupied cell and a free cell for each free one).

**Search.** Best first: the block with the highest bound gives a first best score; then every
block whose bound reaches the best score so far, in decreasing order of bound, until the next
bound falls below it. The answer is the exhaustive lattice argmax: the bounds are true upper
bounds (the level-2 FFT's float32 round-off, ~10⁻⁶ of the score scale, is covered by a margin
of 10⁻⁴ of it), and ties go to the lowest (rotation, y, x) index, as ``numpy.argmax`` over the
full search's scores does. Where the bounds prune too little (a small lattice, a window away
from any good match), the work is capped near half the FFT search's, which then answers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft
from numba import njit

from estimation.search.bnb_bounds import (
    BLOCK,
    Problem,
    Turned,
    block_bounds,
    build_problem,
    cell_offsets,
    fine_bounds,
    fine_pooled,
    fine_splat,
)
from estimation.search.correlate import correlate_lattice
from estimation.search.lattice import Metric, rotation_matrices
from mapping.band import Band

__all__ = [
    "LatticeBest",
    "lattice_best",
    "lattice_scores",
    "pose_bounds",
]

#: Splats whose offsets and level-1 groups the search keeps at once.
_SLOTS = 64
#: Costs in nanoseconds, measured on the benchmark (one core): ``search``'s FFT per rotation
#: and N² log₂ N² of its transforms (0.36 ms at 288²), a new splat's offsets and level-1 groups
#: per local cell, the four level-1 bounds of a block per group term, a 2 × 2 quarter's exact
#: scores per local cell. The branch and bound gives up for the FFT when its work would exceed
#: _FFT_SHARE of the FFT's.
_NS_PER_FFT_TERM = 0.27
_NS_PER_CELL_SPLAT = 2.5
_NS_PER_FINE_TERM = 0.85
_NS_PER_CELL_QUARTER = 1.8
_FFT_SHARE = 0.5


@dataclass(frozen=True)
class LatticeBest:
    """The lattice argmax, its exact score, and how much of the lattice the bounds left."""

    index: tuple[int, int, int]  # (t, y, x) into yaw_rad × y_m × x_m
    score: float  # float64 direct sum
    near: np.ndarray  # exact scores around it, as ``refine_peak`` reads them (see ``_near``)
    blocks: int  # (rotation, 4 × 4 block) pairs bounded by FFT
    blocks_expanded: int  # of those, whose bound reached the best score: quarters bounded
    quarters_scored: int  # 2 × 2 quarters whose bound reached it: scored exactly
    rotations_expanded: int  # rotations with at least one block expanded
    splats: int  # coarse splats transformed (one per rotation, or per four with quarter turns)
    pruned: bool  # False: the bounds left too much, and the FFT over every pose answered


# -- kernels -----------------------------------------------------------------------------------


@njit(cache=True, nogil=True)
def _score_pair(
    padded: np.ndarray,
    ox: np.ndarray,
    oy: np.ndarray,
    w: np.ndarray,
    corner_x: int,
    corner_y: int,
) -> tuple[float, float, float, float]:
    """The exact scores Σ_k w_k·v(m + o_k) of the 2 × 2 translations m = corner + (x, y), in
    float64, row by row; ``padded``: the values with BLOCK zero cells around them, ``corner``
    in its indices."""
    rows, cols = padded.shape
    a00 = a01 = a10 = a11 = 0.0
    for k in range(len(w)):
        y = corner_y + oy[k]
        x = corner_x + ox[k]
        if y < 0 or x < 0 or y + 2 > rows or x + 2 > cols:
            continue  # all the cells it reaches lie in the zero margin or beyond it
        wk = w[k]
        a00 += wk * padded[y, x]
        a01 += wk * padded[y, x + 1]
        a10 += wk * padded[y + 1, x]
        a11 += wk * padded[y + 1, x + 1]
    return a00, a01, a10, a11


@njit(cache=True, nogil=True)
def _scan(
    order: np.ndarray,
    bounds: np.ndarray,
    margin: float,
    fine_margin: float,
    splat: np.ndarray,
    turn: np.ndarray,
    rotation: np.ndarray,
    splat_rotations: np.ndarray,
    ux: np.ndarray,
    uy: np.ndarray,
    w: np.ndarray,
    positives: int,
    s: np.ndarray,
    padded: np.ndarray,
    geometry: np.ndarray,
    fine_max: np.ndarray,
    fine_min: np.ndarray,
    m_lo: np.ndarray,
    size_x: int,
    size_y: int,
    best: np.ndarray,
    best_flat: np.ndarray,
    slot_of: np.ndarray,
    owner: np.ndarray,
    ox: np.ndarray,
    oy: np.ndarray,
    fine_positive: np.ndarray,
    fine_negative: np.ndarray,
    fine_corner: np.ndarray,
    scored: np.ndarray,
    counts: np.ndarray,
    costs: np.ndarray,
    spent: np.ndarray,
) -> bool:
    """Expand the blocks ``order`` (flat indices into the (P, By, Bx) bounds, best first) until
    a bound falls below the best score so far: bound each block's four 2 × 2 quarters (level 1),
    score those whose bound reaches the best exactly; update ``best`` / ``best_flat`` (the flat
    (t, y, x) index, lowest among equal scores). ``counts`` += blocks expanded, quarters
    scored; ``spent`` += the work, in the units of ``costs`` (a new splat, a block, a quarter,
    the budget). False if the work would exceed the budget.

    A splat's offsets and level-1 groups are kept in one of the slots ``ox`` … ``fine_corner``
    (``slot_of[j]``: splat j's, -1: none; ``owner``: each slot's splat, taken in turn)."""
    blocks_y, blocks_x = bounds.shape[1], bounds.shape[2]
    quarters = np.empty(4)
    for i in order:
        p = i // (blocks_x * blocks_y)
        ly = (i // blocks_x) % blocks_y
        lx = i % blocks_x
        if bounds[p, ly, lx] + margin < best[0]:
            break
        if spent[0] > costs[3]:
            return False
        j, k = splat[p], turn[p]
        if slot_of[j] < 0:
            spent[0] += costs[0]
            c = counts[2] % len(owner)
            counts[2] += 1
            if owner[c] >= 0:
                slot_of[owner[c]] = -1
            owner[c] = j
            slot_of[j] = c
            cell_offsets(ux, uy, splat_rotations[j], s, ox[c], oy[c])
            fine_splat(
                ox[c], oy[c], w, positives, fine_positive[c], fine_negative[c], fine_corner[c]
            )
        c = slot_of[j]
        g = geometry[k]  # lower x y, T_lo x y, window lo x y, hi x y, R (4), D x y, fine origin x y
        counts[0] += 1
        spent[0] += costs[1]
        scored[p] = True
        fine_bounds(
            fine_positive[c], fine_negative[c], fine_corner[c], fine_max[k], fine_min[k],
            g[14:16], 2 * (g[2] + lx), 2 * (g[3] + ly), quarters,
        )  # fmt: skip
        t = rotation[p]
        for q in np.argsort(-quarters):
            if quarters[q] + fine_margin < best[0]:
                break
            counts[1] += 1
            spent[0] += costs[2]
            cx = (g[2] + lx) * BLOCK + 2 * (q % 2)
            cy = (g[3] + ly) * BLOCK + 2 * (q // 2)
            pair = _score_pair(padded[k], ox[c], oy[c], w, cx - g[0] + BLOCK, cy - g[1] + BLOCK)
            for a in range(2):
                for b in range(2):
                    mx, my = cx + b, cy + a
                    if mx < g[4] or my < g[5] or mx > g[6] or my > g[7]:
                        continue
                    ix = g[8] * mx + g[9] * my - g[12] - m_lo[0]
                    iy = g[10] * mx + g[11] * my - g[13] - m_lo[1]
                    flat = (t * size_y + iy) * size_x + ix
                    v = pair[2 * a + b]
                    if v > best[0] or (v == best[0] and flat < best_flat[0]):
                        best[0] = v
                        best_flat[0] = flat
    return True


@njit(cache=True, nogil=True)
def _direct_scores(
    values: np.ndarray,
    ox: np.ndarray,
    oy: np.ndarray,
    w: np.ndarray,
    mx: np.ndarray,
    my: np.ndarray,
    out: np.ndarray,
) -> None:
    """out[i, j] = Σ_k w_k·v(m + o_k) for m = (mx[j], my[i]), v 0 off ``values``."""
    rows, cols = values.shape
    for i in range(len(my)):
        for j in range(len(mx)):
            total = 0.0
            for k in range(len(w)):
                y = my[i] + oy[k]
                x = mx[j] + ox[k]
                if 0 <= y < rows and 0 <= x < cols:
                    total += w[k] * values[y, x]
            out[i, j] = total


@njit(cache=True, nogil=True, fastmath=True)
def _maxima(rows: np.ndarray, blocks_x: int) -> np.ndarray:
    """Each problem's largest bound, over the first ``blocks_x`` of each row. (Column maxima
    first: numba vectorises those, not a running maximum.)"""
    out = np.empty(rows.shape[0])
    columns = np.empty(blocks_x, dtype=rows.dtype)
    for p in range(rows.shape[0]):
        columns[:] = rows[p, 0, :blocks_x]
        for y in range(1, rows.shape[1]):
            row = rows[p, y]
            for x in range(blocks_x):
                columns[x] = max(columns[x], row[x])
        out[p] = columns.max()
    return out


@njit(cache=True, nogil=True)
def _count_reaching(bounds: np.ndarray, maxima: np.ndarray, level: float) -> int:
    """How many bounds are ≥ ``level`` (``maxima``: each problem's largest bound)."""
    count = 0
    for p in np.flatnonzero(maxima >= level):
        for y in range(bounds.shape[1]):
            for x in range(bounds.shape[2]):
                count += bounds[p, y, x] >= level
    return count


@njit(cache=True, nogil=True)
def _reaching(bounds: np.ndarray, maxima: np.ndarray, level: float) -> np.ndarray:
    """The flat indices of the bounds ≥ ``level``, highest bound first (``maxima``: each
    problem's largest bound)."""
    found = []
    values = []
    for p in np.flatnonzero(maxima >= level):
        for y in range(bounds.shape[1]):
            for x in range(bounds.shape[2]):
                if bounds[p, y, x] >= level:
                    found.append((p * bounds.shape[1] + y) * bounds.shape[2] + x)
                    values.append(-bounds[p, y, x])
    order = np.argsort(np.array(values), kind="mergesort")
    return np.array(found, dtype=np.int64)[order]


# -- the search --------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Leaves:
    """What scoring a block needs, per turn: the values with BLOCK zero cells around them, the
    level-1 pooled values, and the geometry (see ``_scan``)."""

    padded: np.ndarray  # (turns, rows, cols)
    fine_max: np.ndarray  # (turns, rows, cols)
    fine_min: np.ndarray
    geometry: np.ndarray  # (turns, 16) int64


def _leaves(turns: list[Turned]) -> _Leaves:
    shapes = np.array([t.values.shape for t in turns])
    padded = np.zeros((len(turns), *(shapes.max(axis=0) + 2 * BLOCK)))
    fine = [fine_pooled(t) for t in turns]
    fine_shape = np.max([f[0].shape for f in fine], axis=0)
    fine_max = np.zeros((len(turns), *fine_shape))
    fine_min = np.zeros((len(turns), *fine_shape))
    geometry = np.zeros((len(turns), 16), dtype=np.int64)
    for k, t in enumerate(turns):
        rows, cols = t.values.shape
        padded[k, BLOCK : BLOCK + rows, BLOCK : BLOCK + cols] = t.values
        (rows, cols), origin = fine[k][0].shape, fine[k][2]
        fine_max[k, :rows, :cols], fine_min[k, :rows, :cols] = fine[k][0], fine[k][1]
        geometry[k] = [*t.lower, *t.T_lo, *t.m_lo, *t.m_hi, *t.R.ravel(), *t.D, *origin]
    return _Leaves(padded=padded, fine_max=fine_max, fine_min=fine_min, geometry=geometry)


def lattice_best(
    local: Band,
    global_: Band,
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    metric: Metric,
    workers: int = 1,
    fft_share: float = _FFT_SHARE,
) -> LatticeBest:
    """The best pose of the lattice x_m × y_m × yaw_rad (``lattice.pose_lattice`` and
    ``lattice.yaw_lattice``): its (t, y, x) index and exact score — the argmax of
    ``correlate.correlate_all``'s scores, up to ties within their float32 round-off — and the exact
    scores around it. Where the branch and bound's work would exceed ``fft_share`` of the FFT
    search's (estimated), the FFT search answers. EstimationError as ``exhaustive.search``."""
    problem = build_problem(local, global_, x_m, y_m, yaw_rad, metric)
    b = block_bounds(problem, workers)
    leaves = _leaves(b.turns)
    S, K = len(b.splat_rotations), len(problem.w)
    slots = min(S, _SLOTS)
    slot_of = np.full(S, -1, dtype=np.int64)
    owner = np.full(slots, -1, dtype=np.int64)
    ox = np.empty((slots, K), dtype=np.int32)
    oy = np.empty((slots, K), dtype=np.int32)
    fine_size = b.span * BLOCK // 2 + 1
    fine_positive = np.empty((slots, fine_size, fine_size))
    fine_negative = np.empty((slots, fine_size, fine_size))
    fine_corner = np.empty((slots, 2), dtype=np.int64)
    scored = np.zeros(len(b.splat), dtype=np.bool_)
    counts = np.zeros(3, dtype=np.int64)
    best = np.array([-np.inf])
    best_flat = np.array([-1], dtype=np.int64)
    spent = np.zeros(1)
    costs = np.array(
        [
            _NS_PER_CELL_SPLAT * K,
            _NS_PER_FINE_TERM * fine_size**2,
            _NS_PER_CELL_QUARTER * K,
            fft_share * _fft_ns(problem, b.span),
        ]
    )

    def scan(order: np.ndarray) -> bool:
        return _scan(
            order, b.bounds, b.margin, b.fine_margin, b.splat, b.turn, b.rotation,
            b.splat_rotations, problem.ux, problem.uy, problem.w, problem.positives, problem.s,
            leaves.padded, leaves.geometry, leaves.fine_max, leaves.fine_min, problem.m_lo,
            len(x_m), len(y_m), best, best_flat, slot_of, owner, ox, oy, fine_positive,
            fine_negative, fine_corner, scored, counts, costs, spent,
        )  # fmt: skip

    # Best first: the block with the highest bound gives a first best score; then every block
    # whose bound reaches it, highest first, while the best score rises.
    maxima = _maxima(b.rows, b.bounds.shape[2])
    top = int(np.argmax(maxima))
    top = (top * b.bounds.shape[1] * b.bounds.shape[2]) + int(np.argmax(b.bounds[top]))
    within = scan(np.array([top]))
    if within:
        # Check the cap before collecting and sorting: when more blocks reach the best score
        # so far than the budget could ever expand, the bounds prune too little to win (on the
        # benchmark: 196 blocks for a budget of 19,000; a 4 m view on a 40 m map: 3.3 million
        # for 127,000) and sorting them alone took longer than the FFT.
        level = best[0] - b.margin
        room = (costs[3] - spent[0]) / costs[1]
        within = _count_reaching(b.bounds, maxima, level) <= room
    if within:
        order = _reaching(b.bounds, maxima, level)
        within = scan(order[order != top])
    if within:
        t, rest = divmod(int(best_flat[0]), len(x_m) * len(y_m))
        y, x = divmod(rest, len(x_m))
    else:
        # The bounds prune too little here (a small lattice, or no distinctive match): the
        # FFT over every pose costs less than scoring the blocks they leave.
        _, slices = correlate_lattice(
            local, global_, x_m, y_m, yaw_rad, metric, workers, keep_scores=False
        )
        assert slices.argmax is not None
        t = int(np.argmax(slices.maxima))
        y, x = divmod(int(slices.argmax[t]), len(x_m))
    near = _near(problem, (t, y, x), len(x_m), len(y_m))
    return LatticeBest(
        index=(t, y, x),
        score=float(near[len(near) // 2, min(y, 1), min(x, 1)]),
        near=near,
        blocks=int(np.prod([turn.blocks for turn in b.turns], axis=1)[b.turn].sum()),
        blocks_expanded=int(counts[0]),
        quarters_scored=int(counts[1]),
        rotations_expanded=int(scored.sum()),
        splats=S,
        pruned=within,
    )


def _fft_ns(problem: Problem, span: int) -> float:
    """The cost of ``search``'s FFT over every pose, estimated from its transforms' sizes."""
    extent = span * BLOCK
    size = [sfft.next_fast_len(int(n) + extent, real=True) for n in problem.m_hi - problem.m_lo + 1]
    points = size[0] * size[1]
    return _NS_PER_FFT_TERM * len(problem.yaw_rad) * points * math.log2(points)


def _near(problem: Problem, index: tuple[int, int, int], size_x: int, size_y: int) -> np.ndarray:
    """The exact scores ``refine_peak`` reads around the best pose: rotations t − 1, t, t + 1
    (t alone if there are fewer than three), rows and columns y ± 1, x ± 1 within the lattice."""
    t, y, x = index
    count = len(problem.yaw_rad)
    around = np.arange(t - 1, t + 2) % count if count >= 3 else np.array([t])
    ys = np.arange(max(0, y - 1), min(size_y, y + 2))
    xs = np.arange(max(0, x - 1), min(size_x, x + 2))
    return _lattice_scores(problem, around, ys, xs)


def pose_bounds(
    local: Band,
    global_: Band,
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    metric: Metric,
    level: int = 2,
) -> np.ndarray:
    """(T, Y, X) float64: for each pose of the lattice, the bound of the 4 × 4 block (level 2,
    by FFT) or of the 2 × 2 quarter (level 1, direct) it lies in, with the margin the search
    adds: an upper bound of the pose's score. For tests and diagnostics: slow."""
    problem = build_problem(local, global_, x_m, y_m, yaw_rad, metric)
    b = block_bounds(problem, workers=1)
    leaves = _leaves(b.turns)
    out = np.full((len(yaw_rad), len(y_m), len(x_m)), np.nan)
    ox, oy = np.empty(len(problem.w), dtype=np.int32), np.empty(len(problem.w), dtype=np.int32)
    size = b.span * BLOCK // 2 + 1
    positive, negative = np.empty((size, size)), np.empty((size, size))
    corner = np.empty(2, dtype=np.int64)
    quarters = np.empty(4)
    for p in range(len(b.splat)):
        k = int(b.turn[p])
        turn = b.turns[k]
        mx, my = np.meshgrid(
            np.arange(turn.m_lo[0], turn.m_hi[0] + 1), np.arange(turn.m_lo[1], turn.m_hi[1] + 1)
        )
        by, bx = my // BLOCK - turn.T_lo[1], mx // BLOCK - turn.T_lo[0]
        if level == 2:
            bound = b.bounds[p][by, bx] + b.margin
        else:
            cell_offsets(problem.ux, problem.uy, b.splat_rotations[b.splat[p]], problem.s, ox, oy)
            fine_splat(ox, oy, problem.w, problem.positives, positive, negative, corner)
            fine = np.empty((*turn.blocks[::-1], 4))
            for ly, lx in np.ndindex(*turn.blocks[::-1]):
                fine_bounds(
                    positive, negative, corner, leaves.fine_max[k], leaves.fine_min[k],
                    leaves.geometry[k, 14:16], 2 * (turn.T_lo[0] + lx), 2 * (turn.T_lo[1] + ly),
                    quarters,
                )  # fmt: skip
                fine[ly, lx] = quarters
            q = 2 * (my % BLOCK // 2) + mx % BLOCK // 2
            bound = fine[by, bx, q] + b.fine_margin
        m = np.tensordot(turn.R, np.stack([mx, my]), axes=1) - turn.D[:, None, None]
        out[b.rotation[p], m[1] - problem.m_lo[1], m[0] - problem.m_lo[0]] = bound
    return out


def lattice_scores(
    local: Band,
    global_: Band,
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    metric: Metric,
    t: np.ndarray,
    y: np.ndarray,
    x: np.ndarray,
) -> np.ndarray:
    """(len(t), len(y), len(x)) float64 exact scores of the lattice poses t × y × x (indices
    into yaw_rad, y_m, x_m): direct sums over the local cells, for a few poses."""
    problem = build_problem(local, global_, x_m, y_m, yaw_rad, metric)
    return _lattice_scores(problem, np.asarray(t), np.asarray(y), np.asarray(x))


def _lattice_scores(problem: Problem, t: np.ndarray, y: np.ndarray, x: np.ndarray) -> np.ndarray:
    rotations = rotation_matrices(problem.yaw_rad[t])
    out = np.empty((len(t), len(y), len(x)))
    ox = np.empty(len(problem.w), dtype=np.int32)
    oy = np.empty(len(problem.w), dtype=np.int32)
    mx = problem.m_lo[0] + x.astype(np.int64)
    my = problem.m_lo[1] + y.astype(np.int64)
    for i, rotation in enumerate(rotations):
        cell_offsets(problem.ux, problem.uy, rotation, problem.s, ox, oy)
        _direct_scores(problem.values, ox, oy, problem.w, mx, my, out[i])
    return out
