"""The scores of every pose of the lattice: FFT correlations, and the per-pose loop.

**Exactness.** For one rotation the rotated cell centres fall at fixed offsets o_k = ⌊R c_k/r + s⌋
from the translation, so the scores of every translation are one cross-correlation of a splatted
image (Σ v_L of the cells at each offset) with the global values, computed with real FFTs — the
result equals the per-pose loop (``score_poses_loop``, the paper's method) up to float32
round-off. When the local grid's frame sits on a cell corner or a cell centre and T is a multiple
of 4, a quarter turn of the rotated cells is an exact lattice permutation, so the spectrum of one
splatted image serves four rotations, against four rotated copies of the global spectrum.

The metric and the lattice: ``lattice``; the PDF and the peak of the scores: ``peak``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
import scipy.fft as sfft
from numba import njit

from estimation.errors import EstimationError
from estimation.search.lattice import (
    EDGE,
    MASK_METRIC,
    QUARTER,
    TIE,
    Cells,
    Metric,
    check_pair,
    frac,
    known_mask,
    local_cells,
    match_values,
    overlap_weight,
    quarter_lattice,
    rotation_matrices,
)
from mapping.band import Band

__all__ = [
    "NORMAL_FLOOR",
    "Slices",
    "correlate_all",
    "correlate_lattice",
    "run_chunked",
    "score_poses_loop",
]

#: exp(−x) of float32 is subnormal beyond this x.
NORMAL_FLOOR = 87.0


# -- the per-pose loop (the paper's method; the reference for the fast search) -----------------


def score_poses_loop(
    local: Band,
    global_: Band,
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    metric: Metric,
    *,
    progress: Callable[[int], None] | None = None,
) -> np.ndarray:
    """Scores (T, Y, X) of every pose by the per-pose loop: transform the known local cells, look
    up the global cell holding each, sum the products — the paper's search, in plain numpy
    (rotations hoisted out of the translation loop, buffers reused, the global values padded
    with zeros so that no lookup needs a bounds test). The reference for the fast search.

    ``progress`` is called with the index of each rotation once it is done. The ``excess``
    score is the agreement's loop less c times the loop over the known masks.
    """
    if metric.score == "excess":
        plain = replace(metric, score="agreement")
        scores = score_poses_loop(local, global_, x_m, y_m, yaw_rad, plain, progress=progress)
        counts = score_poses_loop(
            known_mask(local), known_mask(global_), x_m, y_m, yaw_rad, MASK_METRIC
        )
        return scores - overlap_weight(local, global_, metric, None) * counts
    r = check_pair(local, global_)
    cells = local_cells(local, metric)
    centres = cells.u * r
    values = match_values(global_, metric)
    rows, cols = values.shape
    origin = np.asarray(global_.lower_xy, dtype=float)
    reach = float(np.abs(centres).max()) * math.sqrt(2.0) / r
    beyond = max(
        0.0,
        (origin[0] - float(np.min(x_m))) / r,
        (float(np.max(x_m)) - origin[0]) / r - cols,
        (origin[1] - float(np.min(y_m))) / r,
        (float(np.max(y_m)) - origin[1]) / r - rows,
    )
    pad = math.ceil(reach + beyond) + 2
    padded = np.pad(values, pad).ravel()
    stride = cols + 2 * pad
    scores = np.zeros((len(yaw_rad), len(y_m), len(x_m)))
    where = np.empty_like(centres)
    index = np.empty(centres.shape, dtype=np.int64)
    flat = np.empty(len(centres), dtype=np.int64)
    looked_up = np.empty(len(centres))
    shift = np.empty(2)
    for t, yaw in enumerate(yaw_rad):
        c, s = math.cos(yaw), math.sin(yaw)
        rotated = centres @ np.array([[c, s], [-s, c]])  # (K, 2): R·c_k per row
        for iy, y in enumerate(y_m):
            for ix, x in enumerate(x_m):
                shift[0], shift[1] = x - origin[0], y - origin[1]
                np.add(rotated, shift, out=where)
                where /= r
                where += EDGE
                np.floor(where, out=where)
                np.copyto(index, where, casting="unsafe")
                np.multiply(index[:, 1] + pad, stride, out=flat)
                flat += index[:, 0]
                flat += pad
                np.take(padded, flat, out=looked_up)
                # Not np.dot: a BLAS call per pose costs more in thread hand-offs than it sums.
                looked_up *= cells.w
                scores[t, iy, ix] = looked_up.sum()
        if progress is not None:
            progress(t)
    return scores


# -- the fast search ---------------------------------------------------------------------------


def _box_of(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return points.min(axis=0), points.max(axis=0)


def _rotate_box(k: int, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The box R^k·[lo, hi] (integer vectors, R the quarter turn)."""
    corners = np.array([[lo[0], lo[1]], [lo[0], hi[1]], [hi[0], lo[1]], [hi[0], hi[1]]])
    turned = corners @ np.linalg.matrix_power(QUARTER, k).T
    return _box_of(turned)


_DIHEDRAL: list[Callable[[np.ndarray], np.ndarray]] = [
    lambda a: a,
    lambda a: np.rot90(a, 1),
    lambda a: np.rot90(a, 2),
    lambda a: np.rot90(a, 3),
    lambda a: a.T,
    lambda a: np.rot90(a, 1).T,
    lambda a: np.rot90(a, 2).T,
    lambda a: np.rot90(a, 3).T,
]


@njit(cache=True, nogil=True)
def _splat(
    u: np.ndarray,
    w: np.ndarray,
    rotation: np.ndarray,
    s: np.ndarray,
    low: np.ndarray,
    out: np.ndarray,
) -> bool:
    """Add each cell's value at its offset ⌊R·u + s⌋ − low into ``out`` (zeroed by the caller);
    True when some rotated centre lies within round-off of a cell boundary (a tie)."""
    c00, c01, c10, c11 = rotation[0, 0], rotation[0, 1], rotation[1, 0], rotation[1, 1]
    tie = False
    for k in range(len(w)):
        ax = c00 * u[k, 0] + c01 * u[k, 1] + s[0]
        ay = c10 * u[k, 0] + c11 * u[k, 1] + s[1]
        if abs(ax - np.rint(ax)) < TIE or abs(ay - np.rint(ay)) < TIE:
            tie = True
        ox = math.floor(ax + EDGE) - low[0]
        oy = math.floor(ay + EDGE) - low[1]
        out[oy, ox] += w[k]
    return tie


@dataclass
class _Turn:
    """Quarter turn k: the global values turned by k·90°, their spectrum, the window layout."""

    k: int
    parity: int  # k % 2: which FFT shape
    spectrum: np.ndarray | None  # rfft2 of the padded, turned global values; None: all zero
    b_min: np.ndarray  # (2,) lowest splat offset over the rotations this turn serves
    size: np.ndarray  # (2,) x, y: window size in turned coordinates
    view: Callable[[np.ndarray], np.ndarray]  # turned window → (Y, X) window layout


@dataclass
class _Plan:
    """The integer geometry of one search (in cells; vectors are (x, y))."""

    rotations: np.ndarray  # (T, 2, 2)
    base: np.ndarray  # indices of the rotations that are splatted
    quarter: bool  # each base rotation t also serves t + T/4, t + T/2, t + 3T/4
    cells: Cells
    s: np.ndarray
    b: np.ndarray  # (T, 2) int64: lowest splat offset of each rotation
    extent: int  # splat box edge
    shapes: tuple[tuple[int, int], tuple[int, int]]  # (rows, cols) FFT shape per parity
    turns: list[_Turn]


def _fft_cost(shape: tuple[int, int]) -> float:
    n = shape[0] * shape[1]
    return n * math.log2(max(n, 2))


def _fft_shapes(need: list[np.ndarray], extent: int) -> tuple[tuple[int, int], tuple[int, int]]:
    """(rows, cols) FFT shapes for even and odd quarter turns: each its own, or one shape for
    both (one forward transform per base rotation instead of two) when that is cheaper."""
    shapes = []
    for parity in (0, 1):
        n = np.maximum(need[parity], extent)
        shapes.append(
            (sfft.next_fast_len(int(n[1]), real=True), sfft.next_fast_len(int(n[0]), real=True))
        )
    if shapes[0] == shapes[1] or not need[1].any():
        return shapes[0], shapes[1]
    side = (max(shapes[0][0], shapes[1][0]), max(shapes[0][1], shapes[1][1]))
    separate = 3 * (_fft_cost(shapes[0]) + _fft_cost(shapes[1]))
    shared = 5 * _fft_cost(side)
    return (side, side) if shared < separate else (shapes[0], shapes[1])


def _plan(
    cells: Cells,
    global_values: np.ndarray,
    s: np.ndarray,
    m_lo: np.ndarray,
    m_hi: np.ndarray,
    yaw_rad: np.ndarray,
    quarter: bool,
) -> _Plan:
    count = len(yaw_rad)
    base = np.arange(count // 4 if quarter else count)
    rotations = rotation_matrices(yaw_rad)
    # Splat boxes: every centre lies within ``reach`` of the rotated pivot.
    pivot = np.round(cells.u.mean(axis=0))
    reach = float(np.sqrt(((cells.u - pivot) ** 2).sum(axis=1)).max())
    b = np.floor(rotations @ pivot + s - reach - 1e-6).astype(np.int64)
    extent = math.floor(2 * reach + 2e-6) + 2

    rows_g, cols_g = np.nonzero(global_values)
    if len(rows_g) == 0:
        raise EstimationError("map grid has no known cell with occupied or free evidence")
    g_lo = np.array([cols_g.min(), rows_g.min()])
    g_hi = np.array([cols_g.max(), rows_g.max()])

    z = s - 0.5  # a quarter-turn-symmetric point of the lattice in quarter mode
    mx, my = np.meshgrid(np.arange(m_lo[0], m_hi[0] + 1), np.arange(m_lo[1], m_hi[1] + 1))
    need = [np.zeros(2, dtype=np.int64), np.zeros(2, dtype=np.int64)]
    turns: list[_Turn] = []
    regions = []
    for k in range(4 if quarter else 1):
        Rk = np.linalg.matrix_power(QUARTER, k)
        back = (4 - k) % 4
        D = np.round(z - Rk @ z).astype(np.int64)  # offsets turned by k: R^k·o + D
        w_lo, w_hi = _rotate_box(back, D + m_lo, D + m_hi)  # window m' = R^-k·(D + m)
        sup_lo, sup_hi = _rotate_box(back, g_lo, g_hi)  # support of G_k[u] = G[R^k·u]
        # Turn 0 also computes rotations directly (all of them, or those with ties).
        served = b if k == 0 else b[base]
        b_min, b_max = served.min(axis=0), served.max(axis=0)
        lo = np.maximum(b_min + w_lo, sup_lo)
        hi = np.minimum(b_max + extent - 1 + w_hi, sup_hi)
        size = w_hi - w_lo + 1
        turned = np.linalg.matrix_power(QUARTER, back) @ (
            np.stack([mx.ravel(), my.ravel()]) + D[:, None]
        )
        flat = ((turned[1] - w_lo[1]) * size[0] + (turned[0] - w_lo[0])).reshape(mx.shape)
        ids = np.arange(size[1] * size[0]).reshape(size[1], size[0])
        view = next(f for f in _DIHEDRAL if f(ids).shape == flat.shape and (f(ids) == flat).all())
        turns.append(_Turn(k=k, parity=k % 2, spectrum=None, b_min=b_min, size=size, view=view))
        if np.any(hi < lo):
            continue  # the window never reaches the map under this turn: scores stay 0
        n_lo = b_min + w_lo - lo  # ≤ 0: where the window starts, relative to the region
        length = hi - lo + 1
        # No wrap-around: the region fits after the shift, the farthest product lands in the
        # zero padding, and every rotation's window lies inside the output.
        span = b_max - b_min
        need[k % 2] = np.maximum.reduce(
            [need[k % 2], length - n_lo, extent + size - 1 + span + n_lo, span + size]
        )
        regions.append((turns[-1], Rk, lo, length, n_lo))
    shapes = _fft_shapes(need, extent)
    for turn, Rk, lo, length, n_lo in regions:
        ux, uy = np.meshgrid(lo[0] + np.arange(length[0]), lo[1] + np.arange(length[1]))
        gx = Rk[0, 0] * ux + Rk[0, 1] * uy
        gy = Rk[1, 0] * ux + Rk[1, 1] * uy
        inside = (gx >= 0) & (gx < global_values.shape[1]) & (gy >= 0)
        inside &= gy < global_values.shape[0]
        padded = np.zeros(shapes[turn.parity], dtype=np.float32)
        target = padded[-n_lo[1] : -n_lo[1] + length[1], -n_lo[0] : -n_lo[0] + length[0]]
        target[inside] = global_values[gy[inside], gx[inside]]
        turn.spectrum = sfft.rfft2(padded)
    return _Plan(
        rotations=rotations,
        base=base,
        quarter=quarter,
        cells=cells,
        s=s,
        b=b,
        extent=extent,
        shapes=shapes,
        turns=turns,
    )


@dataclass(frozen=True)
class Slices:
    """Per rotation t, filled while its scores are hot in cache: the maximum score, and (when
    β is given) Σ exp(β·(score − maximum)) over the slice."""

    beta: float | None
    maxima: np.ndarray  # (T,)
    sums: np.ndarray  # (T,)
    argmax: np.ndarray | None = None  # (T,) flat index of each maximum, when kept

    def record(self, t: int, scores: np.ndarray, scratch: np.ndarray) -> None:
        if self.argmax is not None:
            self.argmax[t] = int(np.argmax(scores))
            self.maxima[t] = scores.flat[self.argmax[t]]
            return
        top = scores.max()
        self.maxima[t] = top
        if self.beta is not None:
            np.subtract(scores, top, out=scratch)
            scratch *= np.float32(self.beta)
            np.maximum(scratch, np.float32(-NORMAL_FLOOR), out=scratch)
            np.exp(scratch, out=scratch)
            self.sums[t] = scratch.sum(dtype=np.float64)


def _correlate(
    plan: _Plan, chunk: np.ndarray, out: np.ndarray | None, slices: Slices, window: tuple[int, int]
) -> None:
    """Fill ``out[t]`` (unless None: best pose only) and ``slices`` for every rotation served
    by the base rotations ``plan.base[chunk]``."""
    cells, extent = plan.cells, plan.extent
    step = len(plan.rotations) // 4
    splat = np.zeros((extent, extent), dtype=np.float32)
    products = [np.empty((rows, cols // 2 + 1), dtype=np.complex64) for rows, cols in plan.shapes]
    scratch = np.empty(window, dtype=np.float32)

    def spectrum(t: int, parity: int) -> tuple[np.ndarray, bool]:
        splat.fill(0.0)
        tie = _splat(cells.u, cells.w, plan.rotations[t], plan.s, plan.b[t], splat)
        rows, cols = plan.shapes[parity]
        # Zero rows transform to zero: transform the splat's rows, then pad the columns' length.
        half = sfft.fft(sfft.rfft(splat, n=cols, axis=1), n=rows, axis=0)
        return np.conj(half), tie

    def emit(t: int, turn: _Turn, local_spectrum: np.ndarray, b: np.ndarray) -> None:
        if turn.spectrum is None:
            scratch.fill(0.0)
            if out is not None:
                out[t] = 0.0
            slices.record(t, scratch, scratch)
            return
        x0, y0 = b - turn.b_min
        product = products[turn.parity]
        np.multiply(local_spectrum, turn.spectrum, out=product)
        # Inverse along y (in place), then along x only for the rows of the window.
        half = sfft.ifft(product, axis=0, overwrite_x=True)[y0 : y0 + turn.size[1]]
        corr = sfft.irfft(half, n=plan.shapes[turn.parity][1], axis=1, overwrite_x=True)
        scores = turn.view(corr[:, x0 : x0 + turn.size[0]])
        if out is not None:
            out[t] = scores
            scores = out[t]
        slices.record(t, scores, scratch)

    for j in plan.base[chunk]:
        j = int(j)
        first, tie = spectrum(j, 0)
        if not plan.quarter:
            emit(j, plan.turns[0], first, plan.b[j])
            continue
        if tie:
            # A centre on a cell boundary: the quarter-turn permutation would round it the
            # other way, so these four rotations are splatted one by one.
            emit(j, plan.turns[0], first, plan.b[j])
            for k in (1, 2, 3):
                t = j + k * step
                emit(t, plan.turns[0], spectrum(t, 0)[0], plan.b[t])
            continue
        odd = first if plan.shapes[1] == plan.shapes[0] else spectrum(j, 1)[0]
        for turn in plan.turns:
            emit(j + turn.k * step, turn, first if turn.parity == 0 else odd, plan.b[j])


def correlate_lattice(
    local: Band,
    global_: Band,
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    metric: Metric,
    workers: int,
    beta: float | None = None,
    keep_scores: bool = True,
    global_mean: float | None = None,
) -> tuple[np.ndarray | None, Slices]:
    """float32 scores (T, Y, X) and each rotation's maximum (and, given β, its sum of
    exp(β·(score − maximum))). Without ``keep_scores``, no scores: each rotation's maximum and
    where it lies (``slices.argmax``). ``global_mean``: the centre of the global values for the
    ``centred`` and ``excess`` scores when ``global_`` is a crop of the map (default: its own
    mean). ``excess``: the agreement's correlation less c times that of the known masks."""
    if metric.score == "excess":
        return _excess_lattice(
            local, global_, (x_m, y_m, yaw_rad), metric, workers, beta, keep_scores, global_mean
        )
    r = check_pair(local, global_)
    cells = local_cells(local, metric)
    values = match_values(global_, metric, global_mean)
    origin = np.asarray(global_.lower_xy, dtype=float)
    s = frac(-np.asarray(local.lower_xy, dtype=float) / r)
    m_lo = np.array(
        [round((x_m[0] - origin[0]) / r - s[0]), round((y_m[0] - origin[1]) / r - s[1])]
    )
    m_hi = m_lo + np.array([len(x_m), len(y_m)]) - 1
    local_frac = frac(np.asarray(local.lower_xy, dtype=float) / r)
    symmetric = local_frac[0] == local_frac[1] and local_frac[0] in (0.0, 0.5)
    plan = _plan(cells, values, s, m_lo, m_hi, yaw_rad, symmetric and quarter_lattice(yaw_rad))
    shape = (len(yaw_rad), len(y_m), len(x_m))
    out = np.empty(shape, dtype=np.float32) if keep_scores else None
    argmax = None if keep_scores else np.zeros(shape[0], dtype=np.int64)
    slices = Slices(beta, np.empty(shape[0]), np.zeros(shape[0]), argmax)
    window = (shape[1], shape[2])

    def work(chunk: np.ndarray) -> None:
        _correlate(plan, chunk, out, slices, window)

    run_chunked(work, np.arange(len(plan.base)), workers)
    return out, slices


def _excess_lattice(
    local: Band,
    global_: Band,
    lattice: tuple[np.ndarray, np.ndarray, np.ndarray],
    metric: Metric,
    workers: int,
    beta: float | None,
    keep_scores: bool,
    global_mean: float | None,
) -> tuple[np.ndarray | None, Slices]:
    """``correlate_lattice`` for the ``excess`` score: agreement − c·overlap count, the two
    correlations combined rotation by rotation, then each rotation's maximum (and sum)."""
    plain = replace(metric, score="agreement")
    scores = correlate_lattice(local, global_, *lattice, plain, workers)[0]
    counts = correlate_lattice(
        known_mask(local), known_mask(global_), *lattice, MASK_METRIC, workers
    )[0]
    assert scores is not None
    assert counts is not None
    scores -= np.float32(overlap_weight(local, global_, metric, global_mean)) * counts
    del counts
    count = len(scores)
    slices = Slices(
        beta, np.empty(count), np.zeros(count), None if keep_scores else np.zeros(count, np.int64)
    )
    scratch = np.empty(scores.shape[1:], dtype=np.float32)
    for t in range(count):
        slices.record(t, scores[t], scratch)
    return (scores if keep_scores else None), slices


def correlate_all(
    local: Band,
    global_: Band,
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    metric: Metric,
    workers: int = 1,
) -> np.ndarray:
    """float32 scores (T, Y, X) of every pose of the lattice ``pose_lattice`` gives, by FFT.

    Equal to ``score_poses_loop`` up to float32 round-off.
    """
    scores = correlate_lattice(local, global_, x_m, y_m, yaw_rad, metric, workers)[0]
    assert scores is not None
    return scores


def run_chunked(work: Callable[[np.ndarray], None], items: np.ndarray, workers: int) -> None:
    """Call ``work`` on ``items`` split in up to ``workers`` chunks, a thread each (in this thread
    when there is one chunk)."""
    chunks = [c for c in np.array_split(items, max(1, workers)) if len(c)]
    if len(chunks) <= 1:
        for chunk in chunks:
            work(chunk)
        return
    with ThreadPoolExecutor(max_workers=len(chunks)) as pool:
        for future in [pool.submit(work, c) for c in chunks]:
            future.result()
