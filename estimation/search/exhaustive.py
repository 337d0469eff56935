"""Exhaustive (x, y, θ) search of a local 2D band grid against a global one (DESIGN §7, paper §2.2).

**Metric.** Each known cell of a band with occupancy p (the share of the band's layers that
are occupied in its column) gets the value

    v(p) = min(1, (p − τ)/τ)    for p ≥ τ   (occupied evidence, +1 from 2τ up)
    v(p) = w · (p − τ)/τ        for p < τ   (free evidence, down to −w at p = 0)

with τ = ``occupied_level`` (default 0.1: a column with any occupied layer out of the ceiling
band's six is occupied evidence) and w = ``free_weight``; unknown cells get 0. The score of a
pose T (of the local grid's frame in the global grid's frame) is the correlation

    score(T) = Σ_k v_L(k) · v_G(cell of the global grid containing T·c_k)

over the known local cells k with centres c_k: occupied on occupied and free on free agree
(positive), occupied on free disagree (negative), and an unknown cell on either side — or a
local cell that falls off the global grid — counts nothing. For binary cells (v = ±1), this is
the log-likelihood of the local grid given the map and the pose, up to a constant, when each cell
agrees with the map with probability q: log q or log(1 − q) per cell is
½·log(q(1 − q)) + ½·logit(q)·v_L·v_G. The pose PDF is therefore

    P(T) ∝ exp(β · score(T)),

where β (``beta``) stands for ½·logit(q) divided by the number of cells that one independent
error spans (neighbouring cells are not independent); it is calibrated on simulated searches by
maximising the probability the PDF gives to the true pose (see ``calibrate_beta``).

**Lattice.** Translations step by the grids' resolution r; their lattice is offset so that at
θ = 0 local cell centres land on global cell centres; rotations step by 2π/T over the whole
circle. The global cell "containing" a point is ⌊(q − origin)/r⌋ per axis.

**Exactness.** For one rotation the rotated cell centres fall at fixed offsets o_k = ⌊R c_k/r + s⌋
from the translation, so the scores of every translation are one cross-correlation of a splatted
image (Σ v_L of the cells at each offset) with the global values, computed with real FFTs — the
result equals the per-pose loop (``score_poses_loop``, the paper's method) up to float32
round-off. When the local grid's frame sits on a cell corner or a cell centre and T is a multiple
of 4, a quarter turn of the rotated cells is an exact lattice permutation, so the spectrum of one
splatted image serves four rotations, against four rotated copies of the global spectrum.

**Best pose alone.** ``best_pose`` finds the same lattice argmax without scoring every pose: by
branch and bound over (rotation, translation block), with true upper bounds of each block's
scores (``search_bnb``), then refines it as ``search`` does.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.fft as sfft
from numba import njit

from estimation.errors import EstimationError
from estimation.posepdf import PosePdf
from mapping.band import Band

__all__ = [
    "Metric",
    "SearchParams",
    "SearchResult",
    "WindowStep",
    "WindowedResult",
    "best_pose",
    "best_pose_outside",
    "correlate_all",
    "match_values",
    "normalise",
    "overlap_fraction",
    "peak_covariance",
    "pose_lattice",
    "refine_peak",
    "refine_pose",
    "result_from_scores",
    "score_poses_loop",
    "search",
    "windowed_search",
    "yaw_lattice",
]

#: Fractions of a cell this close to an integer count as on it (float round-off in origins).
_SNAP = 1e-6
#: A point within this many cells below a cell boundary belongs to the cell above it, so that
#: centres exactly on a boundary (e.g. on the diagonal at 45°) fall the same way whatever the
#: float round-off.
_EDGE = 1e-9
#: exp(−x) of float32 is subnormal beyond this x.
_NORMAL_FLOOR = 87.0
#: Zero cells around the global values for the spline refinement.
_PAD = 3
#: Rotated centres this close to a boundary are ties: the quarter-turn shortcut is not used.
_TIE = 1e-7

#: The quarter-turn rotation on integer (x, y) vectors: R·(x, y) = (−y, x).
_QUARTER = np.array([[0, -1], [1, 0]], dtype=np.int64)


@dataclass(frozen=True)
class Metric:
    """How band occupancy becomes the cell values the score correlates (see the module)."""

    free_weight: float = 0.5
    occupied_level: float = 0.1

    def __post_init__(self) -> None:
        if not (math.isfinite(self.free_weight) and self.free_weight >= 0):
            raise EstimationError(f"search free_weight must be >= 0, got {self.free_weight!r}")
        if not 0 < self.occupied_level < 1:
            raise EstimationError(
                f"search occupied_level must lie in (0, 1), got {self.occupied_level!r}"
            )


@dataclass(frozen=True)
class SearchParams:
    """Parameters of a search. Names follow the ``search`` section of the configuration; angles
    in radians here (degrees in the configuration)."""

    angular_resolution_rad: float = math.radians(1.0)
    free_weight: float = 0.5
    occupied_level: float = 0.1
    beta: float = 0.04
    peak_radius_m: float = 0.5
    peak_radius_rad: float = math.radians(10.0)
    dominance_ratio: float = 2.0
    workers: int = 0  # threads for the FFT loop; 0: one per CPU, at most 4

    def __post_init__(self) -> None:
        for name in ("angular_resolution_rad", "beta", "peak_radius_m", "peak_radius_rad"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise EstimationError(f"search {name} must be a positive number, got {value!r}")
        Metric(self.free_weight, self.occupied_level)  # validates them
        if not self.dominance_ratio >= 1:
            raise EstimationError(
                f"search dominance_ratio must be >= 1, got {self.dominance_ratio!r}"
            )
        if self.workers < 0:
            raise EstimationError(f"search workers must be >= 0, got {self.workers}")

    @property
    def metric(self) -> Metric:
        return Metric(self.free_weight, self.occupied_level)

    def thread_count(self) -> int:
        return self.workers or min(4, os.cpu_count() or 1)


# -- inputs ------------------------------------------------------------------------------------


def match_values(band: Band, metric: Metric) -> np.ndarray:
    """(H, W) float64 cell values of the metric: occupied evidence up to +1, free evidence down
    to −``free_weight``, 0 on unknown cells. EstimationError on occupancy outside [0, 1] or NaN
    on a known cell."""
    occupancy = np.asarray(band.occupancy, dtype=np.float64)
    known = np.asarray(band.known, dtype=bool)
    if known.any():
        p = occupancy[known]
        if not np.isfinite(p).all() or p.min() < 0.0 or p.max() > 1.0:
            raise EstimationError("band occupancy must lie within [0, 1] on known cells")
    level = metric.occupied_level
    excess = (np.where(known, occupancy, level) - level) / level
    v = np.where(excess < 0.0, metric.free_weight * excess, np.minimum(excess, 1.0))
    return np.asarray(v)


def overlap_fraction(local: Band, global_: Band, pose: np.ndarray) -> float:
    """The share of the local grid's known cells that land on a known cell of the global grid
    when the local frame sits at ``pose`` (x_m, y_m, yaw_rad) in the global frame (a cell centre
    belongs to the global cell containing it, as in the score). A score summed over a small
    overlap rests on little of the local map: few cells of structure in common. EstimationError
    on a local grid with no known cell, a non-finite pose or mismatched resolutions."""
    r = _check_pair(local, global_)
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (3,) or not np.isfinite(pose).all():
        raise EstimationError(f"overlap pose must be 3 finite numbers, got {pose!r}")
    known = np.asarray(local.known, dtype=bool)
    if not known.any():
        raise EstimationError("the scan grid has no known cell")
    gx, gy = local.cell_centers()
    px, py = gx[known], gy[known]
    c, s = math.cos(pose[2]), math.sin(pose[2])
    col = np.floor((pose[0] + c * px - s * py - global_.lower_xy[0]) / r + _EDGE).astype(np.int64)
    row = np.floor((pose[1] + s * px + c * py - global_.lower_xy[1]) / r + _EDGE).astype(np.int64)
    rows, cols = global_.shape
    inside = (col >= 0) & (row >= 0) & (col < cols) & (row < rows)
    hits = np.asarray(global_.known, dtype=bool)[row[inside], col[inside]]
    return float(hits.sum()) / float(known.sum())


def yaw_lattice(angular_resolution_rad: float) -> np.ndarray:
    """(T,) yaws 0, Δ, …, 2π − Δ; EstimationError unless Δ divides the circle."""
    count = round(2.0 * math.pi / angular_resolution_rad)
    if count < 1 or abs(count * angular_resolution_rad - 2.0 * math.pi) > 1e-6:
        raise EstimationError(
            f"angular resolution {math.degrees(angular_resolution_rad):g}° must divide 360°"
        )
    return np.arange(count) * (2.0 * math.pi / count)


def _quarter_lattice(yaw_rad: np.ndarray) -> bool:
    """Whether ``yaw_rad`` is a whole-circle lattice (``yaw_lattice``) whose quarter turns are
    lattice rotations: the quarter-turn shortcut needs both."""
    count = len(yaw_rad)
    return count % 4 == 0 and bool(
        np.allclose(yaw_rad, np.arange(count) * (2.0 * math.pi / count), rtol=0.0, atol=1e-9)
    )


def _check_pair(local: Band, global_: Band) -> float:
    r = float(global_.resolution_m)
    if abs(float(local.resolution_m) - r) > 1e-9 * r:
        raise EstimationError(
            f"scan grid resolution {local.resolution_m:g} m differs from the map's {r:g} m"
        )
    if not np.isfinite(local.lower_xy).all() or not np.isfinite(global_.lower_xy).all():
        raise EstimationError("grid origins must be finite")
    return r


def _frac(value: np.ndarray) -> np.ndarray:
    """Fractional parts in [0, 1), snapped to 0 within round-off."""
    f = np.asarray(value, dtype=float) % 1.0
    return np.where((f < _SNAP) | (f > 1.0 - _SNAP), 0.0, f)


@dataclass(frozen=True)
class _Cells:
    """The informative local cells: centres in cells (local frame / r), and their values."""

    u: np.ndarray  # (K, 2) float64, x and y
    w: np.ndarray  # (K,) float64, non-zero


def _local_cells(local: Band, metric: Metric) -> _Cells:
    values = match_values(local, metric)
    rows, cols = np.nonzero(values)
    if len(rows) == 0:
        raise EstimationError("scan grid has no known cell with occupied or free evidence")
    r = float(local.resolution_m)
    origin = np.asarray(local.lower_xy, dtype=float) / r
    u = np.column_stack([origin[0] + cols + 0.5, origin[1] + rows + 0.5])
    return _Cells(u=u, w=values[rows, cols])


def pose_lattice(
    local: Band, global_: Band, window_m: tuple[float, float, float, float] | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The translation lattice of a search: (x_m (X,), y_m (Y,), s (2,)).

    Translations are ``origin_G + r·(s + m)`` for integer m, with the sub-cell offset s chosen
    so that at θ = 0 local cell centres land on global cell centres. ``window_m`` (x_min, x_max,
    y_min, y_max), half-open, default the global grid's extent, is clipped to that extent.
    """
    r = _check_pair(local, global_)
    s = _frac(-np.asarray(local.lower_xy, dtype=float) / r)
    x0, x1, y0, y1 = global_.extent()
    if window_m is not None:
        wx0, wx1, wy0, wy1 = (float(v) for v in window_m)
        if not (wx0 < wx1 and wy0 < wy1) or not all(map(math.isfinite, window_m)):
            raise EstimationError(f"search window must be a non-empty rectangle, got {window_m}")
        if wx1 <= x0 or wx0 >= x1 or wy1 <= y0 or wy0 >= y1:
            raise EstimationError(
                f"search window x {wx0:g}…{wx1:g} m, y {wy0:g}…{wy1:g} m lies outside the map "
                f"(x {x0:g}…{x1:g} m, y {y0:g}…{y1:g} m)"
            )
        x0, x1, y0, y1 = max(x0, wx0), min(x1, wx1), max(y0, wy0), min(y1, wy1)
    axes = []
    for k, (lo, hi) in enumerate(((x0, x1), (y0, y1))):
        base = float(global_.lower_xy[k])
        first = math.ceil((lo - base) / r - s[k] - _SNAP)
        last = math.ceil((hi - base) / r - s[k] - _SNAP) - 1
        if last < first:
            raise EstimationError(
                f"search window {window_m} holds no pose at the map's {r:g} m lattice"
            )
        axes.append(base + r * (s[k] + np.arange(first, last + 1)))
    return axes[0], axes[1], s


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

    ``progress`` is called with the index of each rotation once it is done.
    """
    r = _check_pair(local, global_)
    cells = _local_cells(local, metric)
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
                where += _EDGE
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
    turned = corners @ np.linalg.matrix_power(_QUARTER, k).T
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
        if abs(ax - np.rint(ax)) < _TIE or abs(ay - np.rint(ay)) < _TIE:
            tie = True
        ox = math.floor(ax + _EDGE) - low[0]
        oy = math.floor(ay + _EDGE) - low[1]
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
    cells: _Cells
    s: np.ndarray
    b: np.ndarray  # (T, 2) int64: lowest splat offset of each rotation
    extent: int  # splat box edge
    shapes: tuple[tuple[int, int], tuple[int, int]]  # (rows, cols) FFT shape per parity
    turns: list[_Turn]


def _rotations(yaw_rad: np.ndarray) -> np.ndarray:
    """(T, 2, 2) rotation matrices, exact at multiples of 90°."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    for arr in (c, s):
        arr[np.abs(arr) < 1e-15] = 0.0
        arr[np.abs(np.abs(arr) - 1.0) < 1e-15] = np.sign(arr[np.abs(np.abs(arr) - 1.0) < 1e-15])
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


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
    cells: _Cells,
    global_values: np.ndarray,
    s: np.ndarray,
    m_lo: np.ndarray,
    m_hi: np.ndarray,
    yaw_rad: np.ndarray,
    quarter: bool,
) -> _Plan:
    count = len(yaw_rad)
    base = np.arange(count // 4 if quarter else count)
    rotations = _rotations(yaw_rad)
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
        Rk = np.linalg.matrix_power(_QUARTER, k)
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
        turned = np.linalg.matrix_power(_QUARTER, back) @ (
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
class _Slices:
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
            np.maximum(scratch, np.float32(-_NORMAL_FLOOR), out=scratch)
            np.exp(scratch, out=scratch)
            self.sums[t] = scratch.sum(dtype=np.float64)


def _correlate(
    plan: _Plan, chunk: np.ndarray, out: np.ndarray | None, slices: _Slices, window: tuple[int, int]
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


def _correlate_lattice(
    local: Band,
    global_: Band,
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    metric: Metric,
    workers: int,
    beta: float | None = None,
    keep_scores: bool = True,
) -> tuple[np.ndarray | None, _Slices]:
    """float32 scores (T, Y, X) and each rotation's maximum (and, given β, its sum of
    exp(β·(score − maximum))). Without ``keep_scores``, no scores: each rotation's maximum and
    where it lies (``slices.argmax``)."""
    r = _check_pair(local, global_)
    cells = _local_cells(local, metric)
    values = match_values(global_, metric)
    origin = np.asarray(global_.lower_xy, dtype=float)
    s = _frac(-np.asarray(local.lower_xy, dtype=float) / r)
    m_lo = np.array(
        [round((x_m[0] - origin[0]) / r - s[0]), round((y_m[0] - origin[1]) / r - s[1])]
    )
    m_hi = m_lo + np.array([len(x_m), len(y_m)]) - 1
    local_frac = _frac(np.asarray(local.lower_xy, dtype=float) / r)
    symmetric = local_frac[0] == local_frac[1] and local_frac[0] in (0.0, 0.5)
    plan = _plan(cells, values, s, m_lo, m_hi, yaw_rad, symmetric and _quarter_lattice(yaw_rad))
    shape = (len(yaw_rad), len(y_m), len(x_m))
    out = np.empty(shape, dtype=np.float32) if keep_scores else None
    argmax = None if keep_scores else np.zeros(shape[0], dtype=np.int64)
    slices = _Slices(beta, np.empty(shape[0]), np.zeros(shape[0]), argmax)
    window = (shape[1], shape[2])

    def work(chunk: np.ndarray) -> None:
        _correlate(plan, chunk, out, slices, window)

    _run(work, np.arange(len(plan.base)), workers)
    return out, slices


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
    scores = _correlate_lattice(local, global_, x_m, y_m, yaw_rad, metric, workers)[0]
    assert scores is not None
    return scores


def _run(work: Callable[[np.ndarray], None], items: np.ndarray, workers: int) -> None:
    chunks = [c for c in np.array_split(items, max(1, workers)) if len(c)]
    if len(chunks) <= 1:
        for chunk in chunks:
            work(chunk)
        return
    with ThreadPoolExecutor(max_workers=len(chunks)) as pool:
        for future in [pool.submit(work, c) for c in chunks]:
            future.result()


def _pdf(
    scores: np.ndarray, slices: _Slices, workers: int = 1, in_place: bool = False
) -> np.ndarray:
    """float32 probabilities exp(β·(score − max) − log Z), Z = Σ exp(β·(score − max)), from
    the scores and their per-rotation maxima and sums: one pass writing the result (over the
    scores themselves when ``in_place``). Rotations whose best cell lies more than float32's
    normal range (e^−87) below the peak hold exactly 0; in the others, cells are floored at
    e^−87 — float32's exp is ten times slower where it returns subnormal numbers."""
    assert slices.beta is not None
    beta = slices.beta
    top = float(slices.maxima.max())
    relative = beta * (slices.maxima - top)
    live = np.flatnonzero(relative > -_NORMAL_FLOOR)
    log_total = math.log(float((np.exp(relative[live]) * slices.sums[live]).sum()))
    if in_place:
        prob = scores
        prob[np.flatnonzero(relative <= -_NORMAL_FLOOR)] = 0.0
    else:
        prob = np.zeros(scores.shape, dtype=np.float32)
    b = np.float32(beta)
    # The maxima are float32 scores, so ``peak`` is exact and s − peak loses nothing near the
    # peak; log Z is subtracted after scaling, where its rounding is relative to log Z alone.
    peak, log_z = np.float32(top), np.float32(log_total)
    sums = np.zeros(len(scores))

    def exponentiate(ts: np.ndarray) -> None:
        for t in ts:
            target = prob[t]
            np.subtract(scores[t], peak, out=target)
            target *= b
            target -= log_z
            np.maximum(target, np.float32(-_NORMAL_FLOOR), out=target)
            np.exp(target, out=target)
            sums[t] = target.sum(dtype=np.float64)

    _run(exponentiate, live, workers)
    total = float(sums.sum())
    if abs(total - 1.0) > 1e-7:  # float32 rounding of the exponents: put the sum back on 1
        factor = np.float32(1.0 / total)

        def rescale(ts: np.ndarray) -> None:
            for t in ts:
                prob[t] *= factor

        _run(rescale, live, workers)
    return prob


# -- the peak: refinement, dominance, covariance -----------------------------------------------


def _reach(radius: float, step: float) -> int:
    return int(radius / step + 1e-9) if step > 0 else 0


def _steps(x_m: np.ndarray, y_m: np.ndarray, yaw_rad: np.ndarray) -> tuple[float, float, float]:
    def step(a: np.ndarray) -> float:
        return float(a[1] - a[0]) if len(a) > 1 else 0.0

    return step(x_m), step(y_m), step(yaw_rad)


def _wraps(yaw_rad: np.ndarray) -> bool:
    step = _steps(yaw_rad, yaw_rad, yaw_rad)[2]
    return step > 0 and abs(step * len(yaw_rad) - 2.0 * math.pi) < 1e-6


def _neighbourhood(
    index: tuple[int, int, int],
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    radius_m: float,
    radius_rad: float,
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], np.ndarray, np.ndarray]:
    """The peak's neighbourhood as ``PosePdf`` defines it: the cells within ``radius_m`` (x, y)
    and ``radius_rad`` (yaw, wrapped) of the cell ``index``. Returns the index box (t, y, x
    arrays), the (t, y, x) mask of the cells inside it, and their offsets (n, 3)."""
    bt, by, bx = index
    sx, sy, syaw = _steps(x_m, y_m, yaw_rad)
    axes = []
    for n, i, step, radius, wraps in (
        (len(yaw_rad), bt, syaw, radius_rad, _wraps(yaw_rad)),
        (len(y_m), by, sy, radius_m, False),
        (len(x_m), bx, sx, radius_m, False),
    ):
        reach = _reach(radius, step)
        if wraps:
            reach = min(reach, (n - 1) // 2)
            axes.append(np.arange(i - reach, i + reach + 1) % n)
        else:
            axes.append(np.arange(max(0, i - reach), min(n, i + reach + 1)))
    it, iy, ix = axes
    yaw, y, x = np.meshgrid(yaw_rad[it], y_m[iy], x_m[ix], indexing="ij")
    dyaw = (yaw - yaw_rad[bt] + math.pi) % (2.0 * math.pi) - math.pi
    dx, dy = x - x_m[bx], y - y_m[by]
    inside = (np.hypot(dx, dy) <= radius_m + 1e-12) & (np.abs(dyaw) <= radius_rad + 1e-12)
    offsets = np.stack([dx[inside], dy[inside], dyaw[inside]], axis=-1)
    return (it, iy, ix), inside, offsets


def best_pose_outside(
    scores: np.ndarray,
    index: tuple[int, int, int],
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    radius_m: float,
    radius_rad: float,
    *,
    maxima: np.ndarray | None = None,
) -> float:
    """The best score outside the peak's neighbourhood (−inf if every cell is inside it).

    ``maxima``: the maximum of each rotation's slice, if already known.
    """
    (it, iy, ix), inside, _ = _neighbourhood(index, x_m, y_m, yaw_rad, radius_m, radius_rad)
    if maxima is None:
        maxima = scores.reshape(len(scores), -1).max(axis=1)
    per_slice = np.array(maxima, dtype=np.float64)
    for row, t in enumerate(it):
        sub = scores[t].astype(np.float64)  # one slice: cheap
        box = sub[np.ix_(iy, ix)]
        box[inside[row]] = -np.inf
        sub[np.ix_(iy, ix)] = box
        per_slice[t] = sub.max()
    return float(per_slice.max())


def peak_covariance(
    scores: np.ndarray,
    index: tuple[int, int, int],
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    beta: float,
    radius_m: float,
    radius_rad: float,
) -> np.ndarray:
    """3×3 covariance (m, m, rad) of the PDF ∝ exp(β·score) over the peak's neighbourhood, as
    ``PosePdf.covariance`` computes it: second moments about the neighbourhood's mean, plus the
    variance of a uniform cell (step²/12) along each axis."""
    (it, iy, ix), inside, offsets = _neighbourhood(index, x_m, y_m, yaw_rad, radius_m, radius_rad)
    box = scores[np.ix_(it, iy, ix)].astype(np.float64)[inside]
    w = np.exp(beta * (box - box.max()))
    w /= w.sum()
    centred = offsets - (w[:, None] * offsets).sum(axis=0)
    cov = (w[:, None, None] * centred[:, :, None] * centred[:, None, :]).sum(axis=0)
    cov += np.diag(np.square(_steps(x_m, y_m, yaw_rad))) / 12.0
    return np.asarray(0.5 * (cov + cov.T))


def refine_peak(scores: np.ndarray, index: tuple[int, int, int], yaw_wraps: bool) -> np.ndarray:
    """Sub-cell offset (x, y, yaw, in lattice steps) of the score's maximum near ``index``.

    A quadratic (cross terms included) is fitted by least squares to the 3×3×3 neighbourhood and
    its vertex taken when it is a maximum; else each axis gets its own parabola through three
    samples. Axes without a neighbour on both sides stay at 0; offsets are clipped to ±1 step.
    """
    shape = scores.shape  # (T, Y, X)
    t0, y0, x0 = index
    usable = []  # (pose axis, array axis)
    for k, axis in ((0, 2), (1, 1), (2, 0)):
        i, n = index[axis], shape[axis]
        if (axis == 0 and yaw_wraps and n >= 3) or 0 < i < n - 1:
            usable.append((k, axis))
    step = np.zeros(3)
    if not usable:
        return step
    grid = np.array(np.meshgrid(*[[-1, 0, 1]] * len(usable), indexing="ij")).reshape(
        len(usable), -1
    )
    values = []
    for column in grid.T:
        cell = [t0, y0, x0]
        for (_, axis), d in zip(usable, column, strict=True):
            cell[axis] = (cell[axis] + int(d)) % shape[axis]
        values.append(float(scores[cell[0], cell[1], cell[2]]))
    f = np.array(values)
    m = len(usable)
    pairs = [(i, j) for i in range(m) for j in range(i, m)]
    design = np.column_stack(
        [np.ones(grid.shape[1]), *grid, *[grid[i] * grid[j] for i, j in pairs]]
    )
    coef = np.linalg.lstsq(design, f, rcond=None)[0]
    g = coef[1 : 1 + m]
    H = np.zeros((m, m))
    for (i, j), c in zip(pairs, coef[1 + m :], strict=True):
        H[i, j] += c if i != j else 2 * c
        if i != j:
            H[j, i] += c
    if np.linalg.eigvalsh(H).max() < 0:
        delta = -np.linalg.solve(H, g)
    else:
        delta = np.zeros(m)
        centre = grid.shape[1] // 2
        for r in range(m):
            others = np.all(np.delete(grid, r, axis=0) == 0, axis=0)
            fm = f[others & (grid[r] == -1)][0]
            fp = f[others & (grid[r] == 1)][0]
            curvature = fm - 2 * f[centre] + fp
            if curvature < 0:
                delta[r] = (fm - fp) / (2 * curvature)
    for (k, _), d in zip(usable, delta, strict=True):
        step[k] = float(np.clip(d, -1.0, 1.0))
    return step


@njit(cache=True, nogil=True, inline="always")
def _bspline(t: float) -> tuple[float, float, float, float, float, float, float, float]:
    """The cubic B-spline's four weights at fraction t of a cell, and their derivatives."""
    u = 1.0 - t
    t2 = t * t
    t3 = t2 * t
    return (
        u * u * u / 6.0,
        (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0,
        (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0,
        t3 / 6.0,
        -u * u / 2.0,
        (3.0 * t2 - 4.0 * t) / 2.0,
        (-3.0 * t2 + 2.0 * t + 1.0) / 2.0,
        t2 / 2.0,
    )


@njit(cache=True, nogil=True, fastmath=True)
def _spline_score(
    centres: np.ndarray,
    w: np.ndarray,
    coefficients: np.ndarray,
    origin: np.ndarray,
    resolution_m: float,
    pose: np.ndarray,
    gradient: np.ndarray,
) -> float:
    """Σ w_k · v_G(T·c_k) with v_G interpolated by a cubic B-spline through the global cell
    centres (``coefficients``: the prefiltered values, padded by ``_PAD`` cells): the score as a
    smooth function of the pose; its gradient (x, y, yaw) is written into ``gradient``.

    Two passes: where each centre falls (vectorised), then the 4 × 4 coefficients around it."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    rows, cols = coefficients.shape
    scale = 1.0 / resolution_m
    shift_x = (pose[0] - origin[0]) * scale - 0.5 + _PAD
    shift_y = (pose[1] - origin[1]) * scale - 0.5 + _PAD
    count = len(w)
    frac_x = np.empty(count)
    frac_y = np.empty(count)
    first = np.empty(count, dtype=np.int64)  # flat index of the 4 × 4 coefficients; -1: none
    for k in range(count):
        fx = (c * centres[k, 0] - s * centres[k, 1]) * scale + shift_x
        fy = (s * centres[k, 0] + c * centres[k, 1]) * scale + shift_y
        j0 = np.floor(fx)
        i0 = np.floor(fy)
        frac_x[k] = fx - j0
        frac_y[k] = fy - i0
        inside = (i0 >= 1) & (j0 >= 1) & (i0 + 2 < rows) & (j0 + 2 < cols)  # else the values are 0
        first[k] = np.int64(i0 - 1) * cols + np.int64(j0 - 1) if inside else -1
    flat = coefficients.ravel()
    total = 0.0
    gx = 0.0
    gy = 0.0
    gt = 0.0
    for k in range(count):
        i = first[k]
        if i < 0:
            continue
        bx0, bx1, bx2, bx3, dx0, dx1, dx2, dx3 = _bspline(frac_x[k])
        by0, by1, by2, by3, dy0, dy1, dy2, dy3 = _bspline(frac_y[k])
        value = 0.0
        dfx = 0.0
        dfy = 0.0
        for weight, slope in ((by0, dy0), (by1, dy1), (by2, dy2), (by3, dy3)):
            c0, c1, c2, c3 = flat[i], flat[i + 1], flat[i + 2], flat[i + 3]
            row_value = bx0 * c0 + bx1 * c1 + bx2 * c2 + bx3 * c3
            value += weight * row_value
            dfx += weight * (dx0 * c0 + dx1 * c1 + dx2 * c2 + dx3 * c3)
            dfy += slope * row_value
            i += cols
        rx = c * centres[k, 0] - s * centres[k, 1]
        ry = s * centres[k, 0] + c * centres[k, 1]
        total += w[k] * value
        gx += w[k] * dfx
        gy += w[k] * dfy
        gt += w[k] * (dfx * -ry + dfy * rx)
    gradient[0] = gx * scale
    gradient[1] = gy * scale
    gradient[2] = gt * scale
    return total


def refine_pose(
    local: Band,
    global_: Band,
    start: np.ndarray,
    metric: Metric,
    bounds: np.ndarray,
) -> np.ndarray:
    """Maximise the score with the global values interpolated by a cubic B-spline, from
    ``start`` (x, y, yaw) within ``bounds`` (3, 2): a continuous refinement of the lattice's best
    pose, which the lattice samples only every cell and every angular step. (A bilinear
    interpolant has kinks exactly where the lattice puts the local cell centres.)"""
    from scipy.ndimage import spline_filter

    r = _check_pair(local, global_)
    cells = _local_cells(local, metric)
    centres = cells.u * r
    values = np.pad(match_values(global_, metric), _PAD)
    coefficients = spline_filter(values, order=3, mode="mirror")
    origin = np.asarray(global_.lower_xy, dtype=float)
    # Scale the variables so that the bounds are ±1 along each.
    scale = np.maximum(bounds[:, 1] - bounds[:, 0], 1e-12) / 2.0
    centre = bounds.mean(axis=1)
    gradient = np.zeros(3)

    def cost(z: np.ndarray) -> tuple[float, np.ndarray]:
        pose = centre + z * scale
        value = _spline_score(centres, cells.w, coefficients, origin, r, pose, gradient)
        return -value, -gradient * scale

    start = np.clip(np.asarray(start, dtype=float), bounds[:, 0], bounds[:, 1])
    best = _minimise_in_box(cost, (start - centre) / scale)
    return np.asarray(centre + best * scale, dtype=float)


def _minimise_in_box(
    cost: Callable[[np.ndarray], tuple[float, np.ndarray]],
    z: np.ndarray,
    iterations: int = 40,
) -> np.ndarray:
    """Minimise a smooth cost (value, gradient) within the box [−1, 1]ⁿ: quasi-Newton (BFGS)
    steps, projected onto the box, with backtracking. A few variables: a dozen evaluations,
    where scipy's L-BFGS-B spends most of its time in its own bookkeeping."""
    f, g = cost(z)
    inverse = np.eye(len(z)) * (0.1 / max(float(np.abs(g).max()), 1e-12))
    for _ in range(iterations):
        direction = -inverse @ g
        step = 1.0
        while True:
            trial = np.clip(z + step * direction, -1.0, 1.0)
            moved = trial - z
            f_trial, g_trial = cost(trial)
            if f_trial <= f + 1e-4 * float(g @ moved) or step < 1e-4:
                break
            step *= 0.5
        if f_trial > f or np.abs(moved).max() < 1e-7:
            break
        change = g_trial - g
        curvature = float(moved @ change)
        if curvature > 1e-12:
            rho = 1.0 / curvature
            identity = np.eye(len(z))
            inverse = (identity - rho * np.outer(moved, change)) @ inverse @ (
                identity - rho * np.outer(change, moved)
            ) + rho * np.outer(moved, moved)
        z, f, g = trial, f_trial, g_trial
        if abs(float(g @ moved)) < 1e-10 * max(1.0, abs(f)):
            break
    return z


# -- the search --------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SearchResult:
    """The exhaustive search's answer: pose of the local grid's frame in the global grid's frame.

    ``prob`` (float32, (T, Y, X) over ``yaw_rad`` × ``y_m`` × ``x_m``) ∝ exp(β·score) sums to
    1; ``scores`` are the float32 scores when the search was asked to keep them (else None: the
    PDF is computed over them). ``pose`` is the refined best pose (x_m, y_m, yaw_rad);
    ``covariance`` (m, m, rad) and ``peak_ratio`` are those of ``pdf`` (``PosePdf``'s
    definitions), computed on the scores.
    """

    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray
    scores: np.ndarray | None
    prob: np.ndarray
    beta: float
    best_index: tuple[int, int, int]
    best_score: float
    pose: np.ndarray
    covariance: np.ndarray
    peak_ratio: float
    seconds: float

    @cached_property
    def pdf(self) -> PosePdf:
        """The whole normalised PDF as a ``PosePdf`` (a float64 copy, built on first use)."""
        return PosePdf(self.x_m, self.y_m, self.yaw_rad, self.prob)

    @property
    def poses(self) -> int:
        """The number of poses scored."""
        return int(self.prob.size)

    @property
    def lattice_pose(self) -> np.ndarray:
        t, y, x = self.best_index
        return np.array([self.x_m[x], self.y_m[y], self.yaw_rad[t]])

    def is_dominant(self, dominance_ratio: float) -> bool:
        return self.peak_ratio >= dominance_ratio


def normalise(scores: np.ndarray, beta: float) -> np.ndarray:
    """float32 probabilities ∝ exp(β·(score − max)), summing to 1."""
    scores = np.asarray(scores, dtype=np.float32)
    slices = _Slices(beta, np.empty(len(scores)), np.zeros(len(scores)))
    scratch = np.empty(scores.shape[1:], dtype=np.float32)
    for t in range(len(scores)):
        slices.record(t, scores[t], scratch)
    return _pdf(scores, slices)


def result_from_scores(
    scores: np.ndarray,
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    params: SearchParams,
    started: float,
    grids: tuple[Band, Band] | None = None,
    slices: _Slices | None = None,
    keep_scores: bool = True,
) -> SearchResult:
    """Best pose, refinement, PDF, covariance and dominance of a score lattice (T, Y, X).

    The best lattice pose is refined by a quadratic fitted to the scores around it, then, when
    the (local, global) ``grids`` are given, by maximising the spline-interpolated score
    within two lattice steps of it (``refine_pose``): near-flat peaks can put the best lattice
    cell a step away from the one nearest the optimum. Without ``keep_scores`` the PDF is
    computed over the scores (float32, contiguous), which are then gone.
    """
    scores = np.ascontiguousarray(scores, dtype=np.float32)
    if slices is None or slices.beta != params.beta:
        slices = _Slices(params.beta, np.empty(len(scores)), np.zeros(len(scores)))
        scratch = np.empty(scores.shape[1:], dtype=np.float32)
        for i in range(len(scores)):
            slices.record(i, scores[i], scratch)
    maxima = slices.maxima
    t = int(np.argmax(maxima))
    y, x = (int(i) for i in np.unravel_index(int(np.argmax(scores[t])), scores.shape[1:]))
    best = float(scores[t, y, x])
    delta = refine_peak(scores, (t, y, x), _wraps(yaw_rad))
    steps = np.array(_steps(x_m, y_m, yaw_rad))
    lattice = np.array([x_m[x], y_m[y], yaw_rad[t]])
    pose = lattice + delta * steps
    if grids is not None:
        bounds = np.column_stack([lattice - 2 * steps, lattice + 2 * steps])
        pose = refine_pose(grids[0], grids[1], pose, params.metric, bounds)
    pose[2] = float((pose[2] + math.pi) % (2.0 * math.pi) - math.pi)
    radii = (params.peak_radius_m, params.peak_radius_rad)
    elsewhere = best_pose_outside(scores, (t, y, x), x_m, y_m, yaw_rad, *radii, maxima=maxima)
    with np.errstate(over="ignore"):
        ratio = float(np.exp(params.beta * (best - elsewhere)))
    covariance = peak_covariance(scores, (t, y, x), x_m, y_m, yaw_rad, params.beta, *radii)
    prob = _pdf(scores, slices, params.thread_count(), in_place=not keep_scores)
    return SearchResult(
        x_m=x_m,
        y_m=y_m,
        yaw_rad=yaw_rad,
        scores=scores if keep_scores else None,
        prob=prob,
        beta=params.beta,
        best_index=(t, y, x),
        best_score=best,
        pose=pose,
        covariance=covariance,
        peak_ratio=ratio,
        seconds=time.perf_counter() - started,
    )


def search(
    local: Band,
    global_: Band,
    params: SearchParams,
    window_m: tuple[float, float, float, float] | None = None,
    *,
    keep_scores: bool = False,
) -> SearchResult:
    """Score every pose (x, y, θ) of the window (default: the whole global grid) at the grids'
    resolution and ``params.angular_resolution_rad``; the whole normalised PDF and its peak.
    The scores are kept in the result only when asked (the PDF is otherwise computed over
    them, in place).

    The pose is that of ``local``'s frame (the frame its ``lower_xy`` is given in) in
    ``global_``'s frame. EstimationError on an empty scan or map, mismatched resolutions or a
    window outside the map.
    """
    started = time.perf_counter()
    x_m, y_m, _ = pose_lattice(local, global_, window_m)
    yaw_rad = yaw_lattice(params.angular_resolution_rad)
    scores, slices = _correlate_lattice(
        local, global_, x_m, y_m, yaw_rad, params.metric, params.thread_count(), params.beta
    )
    assert scores is not None
    return result_from_scores(
        scores, x_m, y_m, yaw_rad, params, started, (local, global_), slices, keep_scores
    )


def best_pose(
    local: Band,
    global_: Band,
    params: SearchParams,
    window_m: tuple[float, float, float, float] | None = None,
) -> tuple[np.ndarray, float, float]:
    """The refined best pose alone (x_m, y_m, yaw_rad), its lattice score and the seconds it
    took: the lattice argmax of the exhaustive search (``search_bnb.lattice_best``: branch and
    bound, exact, without scoring every pose), then ``search``'s refinement — a quadratic over
    the 3×3×3 scores around it, then ``refine_pose``. EstimationError as ``search``."""
    from estimation.search.bnb import lattice_best  # it builds on this module's helpers

    started = time.perf_counter()
    x_m, y_m, _ = pose_lattice(local, global_, window_m)
    yaw_rad = yaw_lattice(params.angular_resolution_rad)
    best = lattice_best(local, global_, x_m, y_m, yaw_rad, params.metric, params.thread_count())
    t, y, x = best.index
    # ``near`` is the neighbourhood refine_peak reads in the full search, cut at the lattice's
    # edges: the best pose sits at its centre unless on an edge.
    index = (len(best.near) // 2, min(y, 1), min(x, 1))
    steps = np.array(_steps(x_m, y_m, yaw_rad))
    lattice = np.array([x_m[x], y_m[y], yaw_rad[t]])
    pose = lattice + refine_peak(best.near, index, yaw_wraps=False) * steps
    bounds = np.column_stack([lattice - 2 * steps, lattice + 2 * steps])
    pose = refine_pose(local, global_, pose, params.metric, bounds)
    pose[2] = float((pose[2] + math.pi) % (2.0 * math.pi) - math.pi)
    return pose, best.score, time.perf_counter() - started


# -- windowed search around an estimate --------------------------------------------------------


@dataclass(frozen=True)
class WindowStep:
    """One window of a windowed search: its side, what it found, and why it did (not) stop."""

    side_m: float
    window_m: tuple[float, float, float, float]
    pose: np.ndarray
    peak_ratio: float
    on_edge: bool  # the best cell lies on a border of the window that is not the map's border
    covers_map: bool
    seconds: float


@dataclass(frozen=True)
class WindowedResult:
    """The last window's search, and every window tried (smallest first)."""

    result: SearchResult
    steps: tuple[WindowStep, ...]
    dominance_ratio: float

    @property
    def dominant(self) -> bool:
        """Whether the search stopped on a dominant peak inside its window."""
        last = self.steps[-1]
        return not last.on_edge and last.peak_ratio >= self.dominance_ratio


def windowed_search(
    local: Band,
    global_: Band,
    params: SearchParams,
    prior_xy: tuple[float, float] | np.ndarray,
    window_m: float,
    max_window_m: float,
) -> WindowedResult:
    """Search a square window of side ``window_m`` centred on the prior position, then windows
    twice as wide, until the peak is dominant (``peak_ratio ≥ params.dominance_ratio``, with the
    best cell off the window's inner borders), the window covers the whole map, or its side
    reaches ``max_window_m``. The batch form of the paper's spiral search out from an estimate:
    every rotation is searched in each window, and the answer is the last window's whole PDF.
    """
    px, py = (float(v) for v in prior_xy)
    if not (math.isfinite(px) and math.isfinite(py)):
        raise EstimationError(f"prior position must be finite, got ({px}, {py})")
    if not (0 < window_m <= max_window_m) or not math.isfinite(max_window_m):
        raise EstimationError(
            f"need 0 < window_m <= max_window_m, got {window_m} and {max_window_m}"
        )
    mx0, mx1, my0, my1 = global_.extent()
    steps: list[WindowStep] = []
    side = float(window_m)
    while True:
        window = (px - side / 2, px + side / 2, py - side / 2, py + side / 2)
        result = search(local, global_, params, window)
        covers = window[0] <= mx0 and window[1] >= mx1 and window[2] <= my0 and window[3] >= my1
        _, by, bx = result.best_index
        r = float(global_.resolution_m)
        inner = (
            (bx == 0 and result.x_m[0] - r >= mx0)
            or (bx == len(result.x_m) - 1 and result.x_m[-1] + r < mx1)
            or (by == 0 and result.y_m[0] - r >= my0)
            or (by == len(result.y_m) - 1 and result.y_m[-1] + r < my1)
        )
        steps.append(
            WindowStep(
                side_m=side,
                window_m=window,
                pose=result.pose,
                peak_ratio=result.peak_ratio,
                on_edge=bool(inner),
                covers_map=bool(covers),
                seconds=result.seconds,
            )
        )
        dominant = result.peak_ratio >= params.dominance_ratio and not inner
        if dominant or covers or side >= max_window_m:
            return WindowedResult(result, tuple(steps), params.dominance_ratio)
        side = min(2.0 * side, float(max_window_m))
