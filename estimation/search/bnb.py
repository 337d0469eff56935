"""The best lattice pose alone, exactly: branch and bound over (rotation, translation block).

For one rotation the search's score (``estimation.search.exhaustive``) is Σ_k v_L(k)·v_G(m + o_k):
local cell k, at the integer offset o_k from the translation m, falls in global cell m + o_k, and
cells off the map count 0.

**Bound.** Over a block of B × B translations m = B·T + d (0 ≤ d < B), a cell of the group
q = ⌊o_k/B⌋ (o_k = B·q + e, 0 ≤ e < B) reaches only the global cells B·(T + q) + [0, 2B − 2]²:

    max_d score(B·T + d) ≤ Σ_q W⁺(q)·Max(T + q) + W⁻(q)·Min(T + q),

with W⁺(q) ≥ 0 and W⁻(q) ≤ 0 the sums of the group's positive and negative local values, and
Max(u) / Min(u) the largest / smallest global value over the (2B − 1)² cells from B·u (0 off the
map, and 0 where unknown). For every block at once that is a correlation on a grid B times
coarser than the map.

**Levels.** Level 2, B = 4 (7 × 7 windows): the bounds of every (rotation, block) pair by one
small FFT per rotation. Level 1, B = 2 (3 × 3 windows): the four 2 × 2 quarters of a block that
level 2 leaves, by direct sums over the groups. Level 0: the exact scores of a quarter that
level 1 leaves, direct float64 sums over the local cells. On the benchmark (``bench_search``)
level 2 leaves 149 of 917,889 blocks, level 1 17 of their 596 quarters; a coarser first level
prunes nothing worth having (B = 8 keeps 30 % of the blocks and every rotation: a 15 × 15
window nearly always holds a wall for each occupied cell and a free cell for each free one).

**Quarter turns.** When the search's quarter-turn shortcut applies (``search`` module), rotation
j + k·T/4 is rotation j scored against the global values turned by k quarter turns: one coarse
splat and its spectrum serve four rotations, whose blocks are aligned in the turned frame.

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

from estimation.errors import EstimationError
from estimation.search.exhaustive import (
    _EDGE,
    _QUARTER,
    _TIE,
    Metric,
    _check_pair,
    _correlate_lattice,
    _frac,
    _local_cells,
    _quarter_lattice,
    _rotations,
    match_values,
)
from mapping.band import Band

__all__ = ["LatticeBest", "lattice_best", "lattice_scores", "pose_bounds"]

#: Translations along each side of a level-2 block (``_fine_bounds`` splits it in quarters).
BLOCK = 4
#: The pooling window: a block's BLOCK translations plus a group's BLOCK offsets, less one.
_WINDOW = 2 * BLOCK - 1
#: Margin added to the FFT-computed bounds, relative to Σ|v_L|·max|v_G|.
_BOUND_MARGIN = 1e-4
#: Splats whose offsets and level-1 groups the search keeps at once.
_SLOTS = 64
#: The bound of a block that is not one (the turned window is narrower than the array).
_NO_BLOCK = np.float32(np.finfo(np.float32).min)
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
def _coarse_splats(
    ux: np.ndarray,
    uy: np.ndarray,
    w: np.ndarray,
    positives: int,
    rotations: np.ndarray,
    s: np.ndarray,
    base: np.ndarray,
    positive: np.ndarray,
    negative: np.ndarray,
    ties: np.ndarray,
) -> None:
    """Per rotation i: the sums of the positive and of the negative local values (the first
    ``positives`` cells, then the others) by group q = ⌊o_k/BLOCK⌋, at q − base[i] of
    ``positive[i]`` / ``negative[i]`` (zeroed by the caller), and whether a rotated centre lies
    within round-off of a cell boundary (``ties[i]``; a few more than ``search._splat``'s)."""
    index = np.empty(len(w), dtype=np.int64)
    cols = positive.shape[2]
    for i in range(len(rotations)):
        c00, c01 = rotations[i, 0, 0], rotations[i, 0, 1]
        c10, c11 = rotations[i, 1, 0], rotations[i, 1, 1]
        bx, by = base[i, 0], base[i, 1]
        tie = 0
        for k in range(len(w)):  # branch-free: vectorised
            ax = c00 * ux[k] + c01 * uy[k] + s[0]
            ay = c10 * ux[k] + c11 * uy[k] + s[1]
            fx = np.floor(ax + _EDGE)
            fy = np.floor(ay + _EDGE)
            dx = ax - fx
            dy = ay - fy
            tie += (dx < 2 * _TIE) | (dx > 1 - 2 * _TIE) | (dy < 2 * _TIE) | (dy > 1 - 2 * _TIE)
            index[k] = (np.int64(fy) // BLOCK - by) * cols + np.int64(fx) // BLOCK - bx
        ties[i] = tie > 0
        plus = positive[i].ravel()
        minus = negative[i].ravel()
        for k in range(positives):
            plus[index[k]] += w[k]
        for k in range(positives, len(w)):
            minus[index[k]] += w[k]


@njit(cache=True, nogil=True)
def _pool(
    values: np.ndarray,
    lower: np.ndarray,
    u_lo: np.ndarray,
    step: int,
    width: int,
    out_max: np.ndarray,
    out_min: np.ndarray,
) -> None:
    """out_max[i, j] / out_min[i, j]: the largest / smallest value over the width² cells from
    step·(u_lo + (j, i)), counting 0 off ``values`` (whose first cell is ``lower``, x and y).
    Separable: along x into every row, then along y."""
    rows, cols = values.shape
    n_y, n_x = out_max.shape
    y0 = u_lo[1] * step - lower[1]
    x0 = u_lo[0] * step - lower[0]
    span_y = (n_y - 1) * step + width  # rows of values the windows cover, from y0
    along_max = np.zeros((span_y, n_x))
    along_min = np.zeros((span_y, n_x))
    for i in range(span_y):
        y = y0 + i
        if y < 0 or y >= rows:
            continue  # a row off the map: its windows hold 0 only
        for j in range(n_x):
            hi = -np.inf
            lo = np.inf
            for x in range(x0 + j * step, x0 + j * step + width):
                v = values[y, x] if 0 <= x < cols else 0.0
                hi = max(hi, v)
                lo = min(lo, v)
            along_max[i, j] = hi
            along_min[i, j] = lo
    for i in range(n_y):
        for j in range(n_x):
            hi = -np.inf
            lo = np.inf
            for y in range(i * step, i * step + width):
                hi = max(hi, along_max[y, j])
                lo = min(lo, along_min[y, j])
            out_max[i, j] = hi
            out_min[i, j] = lo


@njit(cache=True, nogil=True)
def _products(
    positive: np.ndarray,
    negative: np.ndarray,
    pooled_max: np.ndarray,
    pooled_min: np.ndarray,
    shift: np.ndarray,
    splat: np.ndarray,
    turn: np.ndarray,
    out: np.ndarray,
) -> None:
    """out[p]: the spectrum of problem p's bounds, conj(Ŵ⁺)·M̂ax + conj(Ŵ⁻)·M̂in for its splat
    and its turn, with the splat's row placement (``shift``: a phase per row of the spectrum)."""
    for p in range(len(splat)):
        j, k = splat[p], turn[p]
        for a in range(out.shape[1]):
            phase = shift[j, a]
            for b in range(out.shape[2]):
                out[p, a, b] = phase * (
                    np.conj(positive[j, a, b]) * pooled_max[k, a, b]
                    + np.conj(negative[j, a, b]) * pooled_min[k, a, b]
                )


@njit(cache=True, nogil=True)
def _offsets(
    ux: np.ndarray,
    uy: np.ndarray,
    rotation: np.ndarray,
    s: np.ndarray,
    ox: np.ndarray,
    oy: np.ndarray,
) -> None:
    """The offsets ⌊R·u_k + s⌋, rounded as ``search._splat`` rounds them."""
    c00, c01, c10, c11 = rotation[0, 0], rotation[0, 1], rotation[1, 0], rotation[1, 1]
    for k in range(len(ux)):
        ox[k] = math.floor(c00 * ux[k] + c01 * uy[k] + s[0] + _EDGE)
        oy[k] = math.floor(c10 * ux[k] + c11 * uy[k] + s[1] + _EDGE)


@njit(cache=True, nogil=True)
def _fine_splat(
    ox: np.ndarray,
    oy: np.ndarray,
    w: np.ndarray,
    positives: int,
    positive: np.ndarray,
    negative: np.ndarray,
    corner: np.ndarray,
) -> None:
    """The level-1 splat: sums of the positive and of the negative values by group ⌊o_k/2⌋,
    at the group less ``corner`` (set here: the lowest group)."""
    corner[0] = np.min(ox) // 2
    corner[1] = np.min(oy) // 2
    positive[:] = 0.0
    negative[:] = 0.0
    for k in range(positives):
        positive[oy[k] // 2 - corner[1], ox[k] // 2 - corner[0]] += w[k]
    for k in range(positives, len(w)):
        negative[oy[k] // 2 - corner[1], ox[k] // 2 - corner[0]] += w[k]


@njit(cache=True, nogil=True, fastmath=True)
def _fine_bounds(
    positive: np.ndarray,
    negative: np.ndarray,
    corner: np.ndarray,
    pooled_max: np.ndarray,
    pooled_min: np.ndarray,
    origin: np.ndarray,
    T_x: int,
    T_y: int,
    out: np.ndarray,
) -> None:
    """out[2·dy + dx]: the bound of the 2 × 2 translations from 2·(T + (dx, dy)),
    Σ_q W⁺(q)·Max(T + (dx, dy) + q) + W⁻(q)·Min(…), over the level-1 groups q and the 3 × 3
    pooled values (first at ``origin``, with a border of zeros; 0 beyond them too)."""
    rows, cols = pooled_max.shape
    left = T_x + corner[0] - origin[0]  # pooled column of the splat's column 0
    c0 = max(0, -left)
    n = max(0, min(positive.shape[1], cols - 1 - left) - c0)
    a00 = a01 = a10 = a11 = 0.0
    for r in range(positive.shape[0]):
        y = T_y + corner[1] + r - origin[1]
        if y < 0 or y + 1 >= rows:
            continue  # both rows lie in the zero border or beyond it
        # Slices from the first column used: indices from 0 let numba vectorise the sums.
        upper0 = pooled_max[y, left + c0 : left + c0 + n + 1]
        upper1 = pooled_max[y + 1, left + c0 : left + c0 + n + 1]
        lower0 = pooled_min[y, left + c0 : left + c0 + n + 1]
        lower1 = pooled_min[y + 1, left + c0 : left + c0 + n + 1]
        plus = positive[r, c0 : c0 + n]
        minus = negative[r, c0 : c0 + n]
        for i in range(n):
            a00 += plus[i] * upper0[i] + minus[i] * lower0[i]
            a01 += plus[i] * upper0[i + 1] + minus[i] * lower0[i + 1]
            a10 += plus[i] * upper1[i] + minus[i] * lower1[i]
            a11 += plus[i] * upper1[i + 1] + minus[i] * lower1[i + 1]
    out[0], out[1], out[2], out[3] = a00, a01, a10, a11


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
            _offsets(ux, uy, splat_rotations[j], s, ox[c], oy[c])
            _fine_splat(
                ox[c], oy[c], w, positives, fine_positive[c], fine_negative[c], fine_corner[c]
            )
        c = slot_of[j]
        g = geometry[k]  # lower x y, T_lo x y, window lo x y, hi x y, R (4), D x y, fine origin x y
        counts[0] += 1
        spent[0] += costs[1]
        scored[p] = True
        _fine_bounds(
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


# -- the bounds --------------------------------------------------------------------------------


@dataclass
class _Turned:
    """The global values turned by k quarter turns, v_k(x) = v(R^k·x), and the search's window
    in that frame: translations m' = R^-k·(m + D) for the search's m."""

    R: np.ndarray  # (2, 2) int64: R^k
    D: np.ndarray  # (2,) int64
    values: np.ndarray  # (rows, cols) float64, a view of the global values
    lower: np.ndarray  # (2,) x, y: turned cell index of values[0, 0]
    m_lo: np.ndarray  # (2,) the window, in turned translations
    m_hi: np.ndarray
    T_lo: np.ndarray  # (2,) the window's first block
    blocks: np.ndarray  # (2,) its blocks along x, y


def _turn(values: np.ndarray, k: int, D: np.ndarray, m_lo: np.ndarray, m_hi: np.ndarray) -> _Turned:
    R = np.linalg.matrix_power(_QUARTER, k)
    back = np.linalg.matrix_power(_QUARTER, (4 - k) % 4)
    rows, cols = values.shape
    corners = np.array([[0, 0], [cols - 1, 0], [0, rows - 1], [cols - 1, rows - 1]]) @ back.T
    turned = np.rot90(values, k)  # turned[y − lower_y, x − lower_x] = values at R^k·(x, y)
    window = np.array([[m_lo[0], m_lo[1]], [m_hi[0], m_lo[1]], [m_lo[0], m_hi[1]], m_hi]) + D
    window = window @ back.T
    w_lo, w_hi = window.min(axis=0), window.max(axis=0)
    T_lo = w_lo // BLOCK
    return _Turned(
        R=R,
        D=D,
        values=turned,
        lower=corners.min(axis=0),
        m_lo=w_lo,
        m_hi=w_hi,
        T_lo=T_lo,
        blocks=w_hi // BLOCK - T_lo + 1,
    )


@dataclass
class _Bounds:
    """Every (rotation, block) bound of a search, and what scoring a block needs."""

    bounds: np.ndarray  # (P, By, Bx) float32: problem p's bound of block T_lo + (x, y)
    rows: np.ndarray  # (P, By, ≥ Bx): the C-contiguous array ``bounds`` is a view of
    splat: np.ndarray  # (P,) the coarse splat (rotation of the offsets) of problem p
    turn: np.ndarray  # (P,) the turned values it is scored against
    rotation: np.ndarray  # (P,) the search's rotation index it stands for
    splat_rotations: np.ndarray  # (S, 2, 2)
    turns: list[_Turned]
    span: int  # coarse groups along an axis, any rotation
    margin: float  # added to a bound before it is compared with a score
    fine_margin: float  # the same for the level-1 bounds (direct float64 sums)


@dataclass(frozen=True)
class _Problem:
    """A search's inputs, in cells: local cells (x, y, value), global values, lattice."""

    ux: np.ndarray  # (K,) the positive values first
    uy: np.ndarray
    w: np.ndarray
    positives: int
    values: np.ndarray
    s: np.ndarray
    m_lo: np.ndarray  # (2,) x, y: translation index of the lattice's first pose
    m_hi: np.ndarray
    yaw_rad: np.ndarray
    quarter: bool


def _problem(
    local: Band,
    global_: Band,
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    metric: Metric,
) -> _Problem:
    r = _check_pair(local, global_)
    cells = _local_cells(local, metric)
    values = match_values(global_, metric)
    if not values.any():
        raise EstimationError("map grid has no known cell with occupied or free evidence")
    origin = np.asarray(global_.lower_xy, dtype=float)
    s = _frac(-np.asarray(local.lower_xy, dtype=float) / r)
    m_lo = np.array(
        [round((x_m[0] - origin[0]) / r - s[0]), round((y_m[0] - origin[1]) / r - s[1])]
    )
    local_frac = _frac(np.asarray(local.lower_xy, dtype=float) / r)
    symmetric = local_frac[0] == local_frac[1] and local_frac[0] in (0.0, 0.5)
    order = np.concatenate([np.flatnonzero(cells.w > 0.0), np.flatnonzero(cells.w < 0.0)])
    return _Problem(
        ux=cells.u[order, 0],
        uy=cells.u[order, 1],
        w=cells.w[order],
        positives=int(np.count_nonzero(cells.w > 0.0)),  # occupied evidence first
        values=values,
        s=s,
        m_lo=m_lo,
        m_hi=m_lo + np.array([len(x_m), len(y_m)]) - 1,
        yaw_rad=yaw_rad,
        quarter=bool(symmetric and _quarter_lattice(yaw_rad)),
    )


def _bounds(problem: _Problem, workers: int) -> _Bounds:
    """Level 2: every (rotation, block) bound, by FFT correlations on the coarse grid."""
    count = len(problem.yaw_rad)
    rotations = _rotations(problem.yaw_rad)
    quarter = problem.quarter
    step = count // 4
    z = problem.s - 0.5  # a quarter-turn-symmetric point of the lattice in quarter mode
    turns = []
    for k in range(4 if quarter else 1):
        Rk = np.linalg.matrix_power(_QUARTER, k)
        D = np.round(z - Rk @ z).astype(np.int64)
        turns.append(_turn(problem.values, k, D, problem.m_lo, problem.m_hi))

    # The splats: the base rotations (every rotation without the quarter shortcut), plus the
    # four rotations of a base one whose centres tie on a cell boundary, which the quarter-turn
    # permutation would round the other way.
    u = np.column_stack([problem.ux, problem.uy])
    pivot = np.round(u.mean(axis=0))
    reach = float(np.sqrt(((u - pivot) ** 2).sum(axis=1)).max()) + 2.0
    span = int(2 * reach) // BLOCK + 2  # groups along an axis, any rotation
    base = np.arange(step if quarter else count)
    positive, negative, corner, ties = _splats(problem, rotations[base], pivot, reach, span)
    extra = np.zeros(0, dtype=np.int64)
    if quarter and ties.any():
        extra = (base[ties][:, None] + step * np.arange(1, 4)).ravel()
        more = _splats(problem, rotations[extra], pivot, reach, span)
        positive, negative = (
            np.concatenate([positive, more[0]]),
            np.concatenate([negative, more[1]]),
        )
        corner = np.concatenate([corner, more[2]])
    splat: list[int] = []
    turn: list[int] = []
    rotation: list[int] = []
    for j in range(len(base)):
        for k in range(4) if quarter and not ties[j] else range(1):
            splat.append(j)
            turn.append(k)
            rotation.append(j + k * step)
    splat += range(len(base), len(base) + len(extra))
    turn += [0] * len(extra)
    rotation += (int(t) for t in extra)
    splat_a, turn_a = np.array(splat, dtype=np.int64), np.array(turn, dtype=np.int64)

    # The pooled values each turn's blocks reach with some splat: the FFT's shape is theirs
    # plus a splat's, less one, so that no output wraps around onto another.
    Q_lo, Q_hi = corner.min(axis=0), corner.max(axis=0) + span - 1
    crops = []
    for t in turns:
        u_lo = -((_WINDOW - 1 - t.lower) // BLOCK)  # the first u whose window reaches the map
        u_hi = (t.lower + np.array(t.values.shape[::-1]) - 1) // BLOCK
        lo = np.maximum(u_lo, t.T_lo + Q_lo)
        crops.append((lo, np.minimum(u_hi, t.T_lo + t.blocks - 1 + Q_hi)))
    length = np.max([np.maximum(hi - lo + 1, 0) for lo, hi in crops], axis=0)
    shape = tuple(sfft.next_fast_len(int(n), real=True) for n in (length + span - 1)[::-1])

    pooled = _pooled_spectra(turns, crops, shape, workers)
    spectra, shift = _splat_spectra(positive, negative, corner, shape, workers)
    product = np.empty((len(splat_a), shape[0], shape[1] // 2 + 1), dtype=np.complex64)
    _products(spectra[0], spectra[1], pooled[0], pooled[1], shift, splat_a, turn_a, product)
    blocks = np.max([t.blocks for t in turns], axis=0)
    half = sfft.ifft(product, axis=1, workers=workers, overwrite_x=True)[:, : blocks[1]]
    full = sfft.irfft(half, n=shape[1], axis=2, workers=workers, overwrite_x=True)
    bounds = full[:, :, : blocks[0]]

    # Outputs that no group reaches from the pooled values hold wrap-around: the bound is 0.
    T_lo = np.array([t.T_lo for t in turns])[turn_a]
    first = np.array([c[0] for c in crops])[turn_a] - T_lo - corner[splat_a] - span + 1
    last = np.array([c[1] for c in crops])[turn_a] - T_lo - corner[splat_a]
    for p in np.flatnonzero(np.any(first > 0, axis=1) | np.any(last < blocks - 1, axis=1)):
        (x0, y0), (x1, y1) = np.maximum(first[p], 0), np.maximum(last[p] + 1, 0)
        reaches = np.zeros(bounds.shape[1:], dtype=bool)
        reaches[y0:y1, x0:x1] = True
        bounds[p][~reaches] = 0.0
    inside = np.array([t.blocks for t in turns])[turn_a]
    for p in np.flatnonzero(np.any(inside < blocks, axis=1)):
        bounds[p, inside[p, 1] :] = _NO_BLOCK
        bounds[p, :, inside[p, 0] :] = _NO_BLOCK
    scale = float(np.abs(problem.w).sum() * np.abs(problem.values).max())
    return _Bounds(
        bounds=bounds,
        rows=full,
        splat=splat_a,
        turn=turn_a,
        rotation=np.array(rotation, dtype=np.int64),
        splat_rotations=np.concatenate([rotations[base], rotations[extra]]),
        turns=turns,
        span=span,
        margin=_BOUND_MARGIN * scale,
        fine_margin=1e-9 * scale,
    )


def _pooled_spectra(
    turns: list[_Turned],
    crops: list[tuple[np.ndarray, np.ndarray]],
    shape: tuple[int, int],
    workers: int,
) -> np.ndarray:
    """(2, turns, rows, cols // 2 + 1): the spectra of each turn's pooled maxima and minima,
    placed at (u − T_lo) mod shape: output ℓ of a correlation is then the bound of block
    T_lo + ℓ, given that each splat sits at (q mod shape)."""
    rows, cols = shape
    pooled = np.zeros((2, len(turns), rows, cols), dtype=np.float32)
    for k, (turn, (lo, hi)) in enumerate(zip(turns, crops, strict=True)):
        if np.any(hi < lo):
            continue  # the local cells never reach the map from the window
        size = hi - lo + 1
        out_max, out_min = np.empty((size[1], size[0])), np.empty((size[1], size[0]))
        _pool(turn.values, turn.lower, lo, BLOCK, _WINDOW, out_max, out_min)
        at = np.ix_(
            (lo[1] - turn.T_lo[1] + np.arange(size[1])) % rows,
            (lo[0] - turn.T_lo[0] + np.arange(size[0])) % cols,
        )
        pooled[0, k][at] = out_max
        pooled[1, k][at] = out_min
    return np.asarray(sfft.rfft2(pooled, workers=workers))


def _splat_spectra(
    positive: np.ndarray,
    negative: np.ndarray,
    corner: np.ndarray,
    shape: tuple[int, int],
    workers: int,
) -> tuple[list[np.ndarray], np.ndarray]:
    """The splats' spectra, each splat placed at (q mod shape): along x (its rows only, the
    others are 0) with the placement along x as a phase ramp, then along y; and the phase per
    row that places them along y (``_products`` applies it)."""
    rows, cols = shape
    place = corner % np.array([cols, rows])
    ramp = np.exp(-2j * np.pi / cols * np.outer(place[:, 0], np.arange(cols // 2 + 1)))
    ramp = ramp[:, None, :].astype(np.complex64)
    shift = np.exp(2j * np.pi / rows * np.outer(place[:, 1], np.arange(rows)))
    spectra = []
    for values in (positive, negative):
        half = sfft.rfft(values, n=cols, axis=2, workers=workers)
        half *= ramp
        spectra.append(sfft.fft(half, n=rows, axis=1, workers=workers, overwrite_x=True))
    return spectra, shift.astype(np.complex64)


def _splats(
    problem: _Problem,
    rotations: np.ndarray,
    pivot: np.ndarray,
    reach: float,
    span: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(positive, negative, corner, ties): each rotation's groups from ``corner`` (x, y)."""
    n = len(rotations)
    corner = np.floor((rotations @ pivot + problem.s - reach) / BLOCK).astype(np.int64)
    positive = np.zeros((n, span, span), dtype=np.float32)
    negative = np.zeros((n, span, span), dtype=np.float32)
    ties = np.empty(n, dtype=np.bool_)
    _coarse_splats(
        problem.ux, problem.uy, problem.w, problem.positives, rotations, problem.s, corner,
        positive, negative, ties,
    )  # fmt: skip
    return positive, negative, corner, ties


# -- the search --------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Leaves:
    """What scoring a block needs, per turn: the values with BLOCK zero cells around them, the
    level-1 pooled values, and the geometry (see ``_scan``)."""

    padded: np.ndarray  # (turns, rows, cols)
    fine_max: np.ndarray  # (turns, rows, cols)
    fine_min: np.ndarray
    geometry: np.ndarray  # (turns, 16) int64


def _leaves(turns: list[_Turned]) -> _Leaves:
    shapes = np.array([t.values.shape for t in turns])
    padded = np.zeros((len(turns), *(shapes.max(axis=0) + 2 * BLOCK)))
    fine = [_fine_pooled(t) for t in turns]
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
    """The best pose of the lattice x_m × y_m × yaw_rad (``search.pose_lattice`` and
    ``search.yaw_lattice``): its (t, y, x) index and exact score — the argmax of
    ``search.correlate_all``'s scores, up to ties within their float32 round-off — and the exact
    scores around it. Where the branch and bound's work would exceed ``fft_share`` of the FFT
    search's (estimated), the FFT search answers. EstimationError as ``search.search``."""
    problem = _problem(local, global_, x_m, y_m, yaw_rad, metric)
    b = _bounds(problem, workers)
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
        order = _reaching(b.bounds, maxima, best[0] - b.margin)
        within = scan(order[order != top])
    if within:
        t, rest = divmod(int(best_flat[0]), len(x_m) * len(y_m))
        y, x = divmod(rest, len(x_m))
    else:
        # The bounds prune too little here (a small lattice, or no distinctive match): the
        # FFT over every pose costs less than scoring the blocks they leave.
        _, slices = _correlate_lattice(
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


def _fft_ns(problem: _Problem, span: int) -> float:
    """The cost of ``search``'s FFT over every pose, estimated from its transforms' sizes."""
    extent = span * BLOCK
    size = [sfft.next_fast_len(int(n) + extent, real=True) for n in problem.m_hi - problem.m_lo + 1]
    points = size[0] * size[1]
    return _NS_PER_FFT_TERM * len(problem.yaw_rad) * points * math.log2(points)


def _fine_pooled(turn: _Turned) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Level 1, for the quarters of a block: the largest and smallest values over the 3 × 3
    cells from 2·u, for every u whose cells reach the map and a border of one u around them
    (where they are 0); and the first u (x, y)."""
    lower = turn.lower
    upper = lower + np.array(turn.values.shape[::-1]) - 1
    first = -((2 - lower) // 2) - 1
    size = upper // 2 + 1 - first + 1
    out_max, out_min = np.empty((size[1], size[0])), np.empty((size[1], size[0]))
    _pool(turn.values, lower, first, 2, 3, out_max, out_min)
    return out_max, out_min, first


def _near(problem: _Problem, index: tuple[int, int, int], size_x: int, size_y: int) -> np.ndarray:
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
    problem = _problem(local, global_, x_m, y_m, yaw_rad, metric)
    b = _bounds(problem, workers=1)
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
            _offsets(problem.ux, problem.uy, b.splat_rotations[b.splat[p]], problem.s, ox, oy)
            _fine_splat(ox, oy, problem.w, problem.positives, positive, negative, corner)
            fine = np.empty((*turn.blocks[::-1], 4))
            for ly, lx in np.ndindex(*turn.blocks[::-1]):
                _fine_bounds(
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
    problem = _problem(local, global_, x_m, y_m, yaw_rad, metric)
    return _lattice_scores(problem, np.asarray(t), np.asarray(y), np.asarray(x))


def _lattice_scores(problem: _Problem, t: np.ndarray, y: np.ndarray, x: np.ndarray) -> np.ndarray:
    rotations = _rotations(problem.yaw_rad[t])
    out = np.empty((len(t), len(y), len(x)))
    ox = np.empty(len(problem.w), dtype=np.int32)
    oy = np.empty(len(problem.w), dtype=np.int32)
    mx = problem.m_lo[0] + x.astype(np.int64)
    my = problem.m_lo[1] + y.astype(np.int64)
    for i, rotation in enumerate(rotations):
        _offsets(problem.ux, problem.uy, rotation, problem.s, ox, oy)
        _direct_scores(problem.values, ox, oy, problem.w, mx, my, out[i])
    return out
