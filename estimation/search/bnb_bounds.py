"""Upper bounds of the scores over blocks of translations, for the branch and bound (``bnb``).

For one rotation the search's score (``lattice``) is Σ_k v_L(k)·v_G(m + o_k): local cell k, at
the integer offset o_k from the translation m, falls in global cell m + o_k, and cells off the map
count 0.

**Bound.** Over a block of B × B translations m = B·T + d (0 ≤ d < B), a cell of the group
q = ⌊o_k/B⌋ (o_k = B·q + e, 0 ≤ e < B) reaches only the global cells B·(T + q) + [0, 2B − 2]²:

    max_d score(B·T + d) ≤ Σ_q W⁺(q)·Max(T + q) + W⁻(q)·Min(T + q),

with W⁺(q) ≥ 0 and W⁻(q) ≤ 0 the sums of the group's positive and negative local values, and
Max(u) / Min(u) the largest / smallest global value over the (2B − 1)² cells from B·u (0 off the
map, and 0 where unknown). For every block at once that is a correlation on a grid B times
coarser than the map.

**Quarter turns.** When the search's quarter-turn shortcut applies (``correlate``), rotation
j + k·T/4 is rotation j scored against the global values turned by k quarter turns: one coarse
splat and its spectrum serve four rotations, whose blocks are aligned in the turned frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft
from numba import njit

from estimation.errors import EstimationError
from estimation.search.lattice import (
    EDGE,
    QUARTER,
    TIE,
    Metric,
    check_pair,
    frac,
    local_cells,
    match_values,
    quarter_lattice,
    rotation_matrices,
)
from mapping.band import Band

__all__ = [
    "BLOCK",
    "Bounds",
    "Problem",
    "Turned",
    "block_bounds",
    "build_problem",
    "cell_offsets",
    "fine_bounds",
    "fine_pooled",
    "fine_splat",
]

#: Translations along each side of a level-2 block (``fine_bounds`` splits it in quarters).
BLOCK = 4
#: The pooling window: a block's BLOCK translations plus a group's BLOCK offsets, less one.
_WINDOW = 2 * BLOCK - 1
#: Margin added to the FFT-computed bounds, relative to Σ|v_L|·max|v_G|.
_BOUND_MARGIN = 1e-4
#: The bound of a block that is not one (the turned window is narrower than the array).
_NO_BLOCK = np.float32(np.finfo(np.float32).min)


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
    within round-off of a cell boundary (``ties[i]``; a few more than ``correlate._splat``'s)."""
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
            fx = np.floor(ax + EDGE)
            fy = np.floor(ay + EDGE)
            dx = ax - fx
            dy = ay - fy
            tie += (dx < 2 * TIE) | (dx > 1 - 2 * TIE) | (dy < 2 * TIE) | (dy > 1 - 2 * TIE)
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
def cell_offsets(
    ux: np.ndarray,
    uy: np.ndarray,
    rotation: np.ndarray,
    s: np.ndarray,
    ox: np.ndarray,
    oy: np.ndarray,
) -> None:
    """The offsets ⌊R·u_k + s⌋, rounded as ``correlate._splat`` rounds them."""
    c00, c01, c10, c11 = rotation[0, 0], rotation[0, 1], rotation[1, 0], rotation[1, 1]
    for k in range(len(ux)):
        ox[k] = math.floor(c00 * ux[k] + c01 * uy[k] + s[0] + EDGE)
        oy[k] = math.floor(c10 * ux[k] + c11 * uy[k] + s[1] + EDGE)


@njit(cache=True, nogil=True)
def fine_splat(
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
def fine_bounds(
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


# -- the bounds --------------------------------------------------------------------------------


@dataclass
class Turned:
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


def _turn(values: np.ndarray, k: int, D: np.ndarray, m_lo: np.ndarray, m_hi: np.ndarray) -> Turned:
    R = np.linalg.matrix_power(QUARTER, k)
    back = np.linalg.matrix_power(QUARTER, (4 - k) % 4)
    rows, cols = values.shape
    corners = np.array([[0, 0], [cols - 1, 0], [0, rows - 1], [cols - 1, rows - 1]]) @ back.T
    turned = np.rot90(values, k)  # turned[y − lower_y, x − lower_x] = values at R^k·(x, y)
    window = np.array([[m_lo[0], m_lo[1]], [m_hi[0], m_lo[1]], [m_lo[0], m_hi[1]], m_hi]) + D
    window = window @ back.T
    w_lo, w_hi = window.min(axis=0), window.max(axis=0)
    T_lo = w_lo // BLOCK
    return Turned(
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
class Bounds:
    """Every (rotation, block) bound of a search, and what scoring a block needs."""

    bounds: np.ndarray  # (P, By, Bx) float32: problem p's bound of block T_lo + (x, y)
    rows: np.ndarray  # (P, By, ≥ Bx): the C-contiguous array ``bounds`` is a view of
    splat: np.ndarray  # (P,) the coarse splat (rotation of the offsets) of problem p
    turn: np.ndarray  # (P,) the turned values it is scored against
    rotation: np.ndarray  # (P,) the search's rotation index it stands for
    splat_rotations: np.ndarray  # (S, 2, 2)
    turns: list[Turned]
    span: int  # coarse groups along an axis, any rotation
    margin: float  # added to a bound before it is compared with a score
    fine_margin: float  # the same for the level-1 bounds (direct float64 sums)


@dataclass(frozen=True)
class Problem:
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


def build_problem(
    local: Band,
    global_: Band,
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    metric: Metric,
) -> Problem:
    if metric.score == "excess":
        raise EstimationError(
            "branch and bound bounds one correlation; the excess score is searched exhaustively"
        )
    r = check_pair(local, global_)
    cells = local_cells(local, metric)
    values = match_values(global_, metric)
    if not values.any():
        raise EstimationError("map grid has no known cell with occupied or free evidence")
    origin = np.asarray(global_.lower_xy, dtype=float)
    s = frac(-np.asarray(local.lower_xy, dtype=float) / r)
    m_lo = np.array(
        [round((x_m[0] - origin[0]) / r - s[0]), round((y_m[0] - origin[1]) / r - s[1])]
    )
    local_frac = frac(np.asarray(local.lower_xy, dtype=float) / r)
    symmetric = local_frac[0] == local_frac[1] and local_frac[0] in (0.0, 0.5)
    order = np.concatenate([np.flatnonzero(cells.w > 0.0), np.flatnonzero(cells.w < 0.0)])
    return Problem(
        ux=cells.u[order, 0],
        uy=cells.u[order, 1],
        w=cells.w[order],
        positives=int(np.count_nonzero(cells.w > 0.0)),  # occupied evidence first
        values=values,
        s=s,
        m_lo=m_lo,
        m_hi=m_lo + np.array([len(x_m), len(y_m)]) - 1,
        yaw_rad=yaw_rad,
        quarter=bool(symmetric and quarter_lattice(yaw_rad)),
    )


def block_bounds(problem: Problem, workers: int) -> Bounds:
    """Level 2: every (rotation, block) bound, by FFT correlations on the coarse grid."""
    count = len(problem.yaw_rad)
    rotations = rotation_matrices(problem.yaw_rad)
    quarter = problem.quarter
    step = count // 4
    z = problem.s - 0.5  # a quarter-turn-symmetric point of the lattice in quarter mode
    turns = []
    for k in range(4 if quarter else 1):
        Rk = np.linalg.matrix_power(QUARTER, k)
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
    return Bounds(
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
    turns: list[Turned],
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
    problem: Problem,
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


def fine_pooled(turn: Turned) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
