"""Coarse-to-fine global localization, for maps whose whole PDF does not fit (docs/design.md §7).

**Coarse level.** Both bands are averaged over F × F cells (their metric values, mapped back to
occupancies so that the same correlation scores them) and every pose of the coarse lattice — the
same rotations, translations every F cells — is scored by ``correlate``. A coarse score stands
for about F² fine local cells, so the coarse PDF is ∝ exp(β·F²·score_c). Averaging blurs thin
walls: the coarse peak is lower than the fine one and the coarse PDF broader, which errs on the
side of evaluating more.

**Selection.** The coarse cells holding all but ``mass_tolerance`` (ε) of the coarse PDF — the
most probable first, cut by a histogram of their log-probabilities — grown by ``grow`` coarse
cells in x and y and one rotation either way, then split into connected regions.

**Fine level.** Each region's poses at full resolution, by the same FFT correlation on the
region's bounding box (the map cropped to what the local cells reach from it), masked to the
region. Where the fine PDF still holds more than ε on a region's border (its mass runs on into
unevaluated poses), the selection grows by one more coarse cell, up to ``MAX_GROWTH`` times.

**The unevaluated mass.** ``TiledResult.unevaluated_mass`` is the coarse PDF's mass outside the
selection plus the fine PDF's mass on the selection's border: an estimate, not a proof (the
coarse score is not a bound of the fine one; the sound bounds of ``bnb_bounds`` leave most of a
wall-dense map). The tests check it against the exhaustive PDF on random buildings: the
exhaustive PDF's mass outside the evaluated poses stays below it. The evaluated probabilities
are normalised over the evaluated poses; the exhaustive PDF's are those times 1 − (its mass
outside), so each differs from the exhaustive one by at most that share.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np
from numba import njit
from scipy import ndimage

from estimation.errors import EstimationError
from estimation.search.correlate import correlate_lattice
from estimation.search.exhaustive import SearchParams
from estimation.search.lattice import (
    Metric,
    check_pair,
    lattice_steps,
    local_cells,
    match_values,
    pose_lattice,
    value_mean,
    yaw_lattice,
)
from estimation.search.peak import peak_covariance, refine_peak, refine_pose
from mapping.band import Band

__all__ = [
    "COARSE_POSES",
    "MAX_GROWTH",
    "MAX_LATTICE_POSES",
    "Patch",
    "TiledResult",
    "coarsen",
    "search_coarse_to_fine",
]

#: The coarse level's factor F is the smallest that keeps its lattice within this many poses.
COARSE_POSES = 2**25
#: The largest lattice searched coarse to fine (8 × the 100 m × 100 m map at 0.1 m and 1°).
MAX_LATTICE_POSES = 2**31
#: The most poses evaluated at full resolution (float32 scores: 64 MiB).
MAX_FINE_POSES = 2**24
#: Times a selection whose border holds fine probability may grow.
MAX_GROWTH = 3
#: Width of the histogram bins of coarse log-probabilities, and their count.
_BIN = 0.25
_BINS = 400


@dataclass(frozen=True)
class Patch:
    """A box of the lattice evaluated at full resolution: rotations ``t`` (indices into the
    result's ``yaw_rad``; consecutive modulo T), rows y0 … y0 + Y − 1, columns x0 … x0 + X − 1;
    ``prob`` (T', Y, X) float32, 0 on the poses outside the region (``mask`` False)."""

    t: np.ndarray
    y0: int
    x0: int
    scores: np.ndarray  # float32, −inf outside the mask
    prob: np.ndarray
    mask: np.ndarray


@dataclass(frozen=True, eq=False)
class TiledResult:
    """The coarse-to-fine search's answer, in ``SearchResult``'s terms (pose of the local grid's
    frame in the global grid's frame, refined; covariance; peak ratio) over the same lattice
    ``yaw_rad`` × ``y_m`` × ``x_m``, whose probabilities are known on ``patches`` only.

    ``unevaluated_mass``: the estimated probability of every pose outside the patches (see the
    module). ``peak_ratio`` is that of the evaluated poses, capped at what an unevaluated pose
    of that mass allows: never above the exhaustive search's when the estimate holds.
    """

    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray
    patches: tuple[Patch, ...]
    beta: float
    best_index: tuple[int, int, int]
    best_score: float
    pose: np.ndarray
    covariance: np.ndarray
    peak_ratio: float
    unevaluated_mass: float
    coarse_factor: int
    seconds: float

    @property
    def poses(self) -> int:
        """The poses of the lattice (most not evaluated at full resolution)."""
        return len(self.x_m) * len(self.y_m) * len(self.yaw_rad)

    @property
    def poses_evaluated(self) -> int:
        return int(sum(int(p.mask.sum()) for p in self.patches))

    @property
    def lattice_pose(self) -> np.ndarray:
        t, y, x = self.best_index
        return np.array([self.x_m[x], self.y_m[y], self.yaw_rad[t]])

    def is_dominant(self, dominance_ratio: float) -> bool:
        return self.peak_ratio >= dominance_ratio

    def position_marginal(self) -> np.ndarray:
        """(Y, X) float64: the probability of each position, summed over rotations."""
        out = np.zeros((len(self.y_m), len(self.x_m)))
        for p in self.patches:
            _, rows, cols = p.prob.shape
            out[p.y0 : p.y0 + rows, p.x0 : p.x0 + cols] += p.prob.sum(axis=0, dtype=np.float64)
        return out

    def dense_prob(self) -> np.ndarray:
        """(T, Y, X) float32 probabilities, 0 where not evaluated: for lattices that fit."""
        if self.poses > 2**28:
            raise EstimationError(f"{self.poses:,} poses are too many for a dense PDF")
        out = np.zeros((len(self.yaw_rad), len(self.y_m), len(self.x_m)), dtype=np.float32)
        for p in self.patches:
            _, rows, cols = p.prob.shape
            out[p.t, p.y0 : p.y0 + rows, p.x0 : p.x0 + cols] += p.prob
        return out


# -- the coarse level --------------------------------------------------------------------------


def coarsen(band: Band, factor: int, metric: Metric) -> Band:
    """The band averaged over ``factor`` × ``factor`` cells: a coarse cell's metric value is the
    mean of its cells' (0 for unknown ones), given back as the occupancy the metric maps onto it;
    it is known when one of its cells is. Same lower corner, ``factor`` times the resolution.
    The ``agreement`` values are averaged (the occupancy maps onto them); a ``centred`` search
    centres the coarse band on its own mean."""
    values = match_values(band, replace(metric, score="agreement"))
    rows, cols = values.shape
    n_y, n_x = -(-rows // factor), -(-cols // factor)
    padded = np.zeros((n_y * factor, n_x * factor))
    padded[:rows, :cols] = values
    known = np.zeros(padded.shape, dtype=bool)
    known[:rows, :cols] = np.asarray(band.known, dtype=bool)
    mean = padded.reshape(n_y, factor, n_x, factor).mean(axis=(1, 3))
    known_c = np.asarray(known.reshape(n_y, factor, n_x, factor).any(axis=(1, 3)))
    level, weight = metric.occupied_level, metric.free_weight
    free = level * (1.0 + mean / weight) if weight > 0 else np.full_like(mean, level)
    occupancy = np.clip(np.where(mean >= 0.0, level * (1.0 + mean), free), 0.0, 1.0)
    return Band(
        occupancy=np.where(known_c, occupancy, 0.0),
        known=known_c,
        lower_xy=np.asarray(band.lower_xy, dtype=float),
        resolution_m=float(band.resolution_m) * factor,
    )


@njit(cache=True, nogil=True)
def _histogram(
    scores: np.ndarray, top: float, beta: float, counts: np.ndarray, mass: np.ndarray
) -> None:
    """Per bin of d = β·(top − score) (width ``_BIN``; the last bin holds every d beyond): the
    count of poses and their Σ exp(−d). Beyond the last bin's start each pose is counted with
    the mass exp(−_BIN·(bins − 1)), more than its own: the tail is never underestimated."""
    flat = scores.ravel()
    last = len(counts) - 1
    far = 0
    for i in range(len(flat)):
        d = beta * (top - flat[i])
        b = int(d / _BIN)
        if b >= last:
            far += 1
        else:
            counts[b] += 1
            mass[b] += math.exp(-d)
    counts[last] += far
    mass[last] += far * math.exp(-_BIN * last)


def _cut(counts: np.ndarray, mass: np.ndarray, epsilon: float, budget: int) -> tuple[int, float]:
    """The fewest bins (the most probable first) whose poses hold all but ``epsilon`` of the mass
    and number at most ``budget`` (fewer bins if not: a larger tail); and the tail's share."""
    total = float(mass.sum())
    held = np.cumsum(mass)
    taken = np.cumsum(counts)
    k = int(np.searchsorted(held, (1.0 - epsilon) * total)) + 1
    k = min(k, len(counts))
    while k > 1 and taken[k - 1] > budget:
        k -= 1
    return k, max(0.0, 1.0 - float(held[k - 1]) / total)


# -- the fine level ----------------------------------------------------------------------------


def _crop(global_: Band, rows: tuple[int, int], cols: tuple[int, int]) -> Band:
    r0, r1 = max(0, rows[0]), min(global_.shape[0], rows[1])
    c0, c1 = max(0, cols[0]), min(global_.shape[1], cols[1])
    r = float(global_.resolution_m)
    return Band(
        occupancy=np.asarray(global_.occupancy)[r0:r1, c0:c1],
        known=np.asarray(global_.known)[r0:r1, c0:c1],
        lower_xy=np.asarray(global_.lower_xy, dtype=float) + r * np.array([c0, r0]),
        resolution_m=r,
    )


@dataclass(frozen=True)
class _Lattice:
    """The fine lattice and what the fine evaluations need of it."""

    local: Band
    global_: Band
    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray
    metric: Metric
    reach_cells: int  # the local cells lie within this many cells of the local frame's origin
    workers: int
    global_mean: float  # the whole map's centre of the centred score (crops keep it)

    def scores(self, t: np.ndarray, ys: slice, xs: slice) -> np.ndarray:
        """float32 scores (len(t), Y, X) of rotations ``t`` over rows ``ys``, columns ``xs``."""
        x_m, y_m = self.x_m[xs], self.y_m[ys]
        r = float(self.global_.resolution_m)
        origin = np.asarray(self.global_.lower_xy, dtype=float)
        col = (np.array([x_m[0], x_m[-1]]) - origin[0]) / r
        row = (np.array([y_m[0], y_m[-1]]) - origin[1]) / r
        pad = self.reach_cells + 2
        crop = _crop(
            self.global_,
            (math.floor(row[0]) - pad, math.ceil(row[1]) + pad + 1),
            (math.floor(col[0]) - pad, math.ceil(col[1]) + pad + 1),
        )
        shape = (len(t), len(y_m), len(x_m))
        if crop.occupancy.size == 0 or not match_values(crop, self.metric, self.global_mean).any():
            return np.zeros(shape, dtype=np.float32)  # no map where the local cells land
        scores, _ = correlate_lattice(
            self.local, crop, x_m, y_m, self.yaw_rad[t], self.metric, self.workers,
            global_mean=self.global_mean,
        )  # fmt: skip
        assert scores is not None
        return scores


def _regions(selected: np.ndarray, grow: int) -> list[tuple[np.ndarray, slice, slice, np.ndarray]]:
    """The selected coarse cells (T, Yc, Xc) grown by ``grow`` cells in x, y and one rotation
    either way, in connected regions: (rotations, rows, columns, mask over them)."""
    count, n_y, n_x = selected.shape
    # Work on the box of the selected positions (any rotation), grown.
    rows_any, cols_any = np.nonzero(selected.any(axis=0))
    y0, y1 = max(0, rows_any.min() - grow), min(n_y, rows_any.max() + grow + 1)
    x0, x1 = max(0, cols_any.min() - grow), min(n_x, cols_any.max() + grow + 1)
    box = selected[:, y0:y1, x0:x1]
    grown = box | np.roll(box, 1, axis=0) | np.roll(box, -1, axis=0)
    size = 2 * grow + 1
    grown = ndimage.maximum_filter(grown, size=(1, size, size), mode="constant")
    # Start the rotations at one that holds nothing, so that no region wraps around.
    empty = np.flatnonzero(~grown.any(axis=(1, 2)))
    shift = int(empty[0]) if len(empty) else 0
    rolled = np.roll(grown, -shift, axis=0)
    labels, _ = ndimage.label(rolled, structure=np.ones((3, 3, 3), dtype=bool))
    regions = []
    for k, found in enumerate(ndimage.find_objects(labels), start=1):
        if found is None:
            continue
        t = (np.arange(found[0].start, found[0].stop) + shift) % count
        rows = slice(y0 + found[1].start, y0 + found[1].stop)
        cols = slice(x0 + found[2].start, x0 + found[2].stop)
        regions.append((t, rows, cols, labels[found] == k))
    return regions


def _fine_boxes(
    lattice: _Lattice,
    coarse_x: np.ndarray,
    coarse_y: np.ndarray,
    regions: list[tuple[np.ndarray, slice, slice, np.ndarray]],
) -> list[Patch]:
    """Each region's fine poses: those whose nearest coarse translation is in the region."""
    patches = []
    step = float(coarse_x[1] - coarse_x[0]) if len(coarse_x) > 1 else float(lattice.x_m[-1])
    for t, rows, cols, mask in regions:
        # Fine columns whose nearest coarse column lies in cols (and rows likewise).
        picks = []
        for fine, coarse, span in ((lattice.x_m, coarse_x, cols), (lattice.y_m, coarse_y, rows)):
            nearest = np.clip(np.rint((fine - coarse[0]) / step), 0, len(coarse) - 1)
            inside = np.flatnonzero((nearest >= span.start) & (nearest < span.stop))
            picks.append((inside, nearest[inside].astype(np.int64) - span.start))
        (xi, xc), (yi, yc) = picks
        if len(xi) == 0 or len(yi) == 0:
            continue
        fine_mask = mask[:, yc][:, :, xc]
        scores = lattice.scores(t, slice(yi[0], yi[-1] + 1), slice(xi[0], xi[-1] + 1))
        scores[~fine_mask] = -np.inf
        patches.append(Patch(t=t, y0=int(yi[0]), x0=int(xi[0]), scores=scores,
                             prob=np.empty(0, dtype=np.float32), mask=fine_mask))  # fmt: skip
    return patches


def _border(
    mask: np.ndarray, whole_circle: bool, y0: int, x0: int, rows: int, cols: int
) -> np.ndarray:
    """The poses of ``mask`` (a patch from row y0, column x0 of a rows × cols lattice) with a
    neighbour — in x, y or rotation — that is a pose of the lattice outside the mask."""
    _, n_y, n_x = mask.shape
    p = np.pad(mask, 1, constant_values=False)
    if whole_circle:  # the patch holds every rotation: the first and last are neighbours
        p[0], p[-1] = p[-2], p[1]
    # Beyond the lattice's edges there are no poses.
    if y0 == 0:
        p[:, 0] = True
    if y0 + n_y == rows:
        p[:, -1] = True
    if x0 == 0:
        p[:, :, 0] = True
    if x0 + n_x == cols:
        p[:, :, -1] = True
    inner = mask.copy()
    for near in (p[2:, 1:-1, 1:-1], p[:-2, 1:-1, 1:-1], p[1:-1, 2:, 1:-1], p[1:-1, :-2, 1:-1],
                 p[1:-1, 1:-1, 2:], p[1:-1, 1:-1, :-2]):  # fmt: skip
        inner &= near
    return mask & ~inner


def _neighbourhood_scores(
    lattice: _Lattice, index: tuple[int, int, int], radius_m: float, radius_rad: float
) -> tuple[np.ndarray, tuple[int, int, int], np.ndarray, np.ndarray, np.ndarray]:
    """The scores of the box holding the peak's neighbourhood (``peak``'s definition) and the
    sub-lattice they lie on (yaws unwrapped around the peak's): what ``refine_peak`` and
    ``peak_covariance`` read of the whole lattice."""
    t, y, x = index
    sx, sy, syaw = lattice_steps(lattice.x_m, lattice.y_m, lattice.yaw_rad)
    count = len(lattice.yaw_rad)
    reach_t = min(int(radius_rad / syaw + 1e-9) if syaw > 0 else 0, (count - 1) // 2)
    reach_t = max(reach_t, 1) if count >= 3 else 0  # refine_peak reads t ± 1
    offsets = np.arange(-reach_t, reach_t + 1)
    ts = (t + offsets) % count
    axes = []
    for i, n, step in ((y, len(lattice.y_m), sy), (x, len(lattice.x_m), sx)):
        reach = max(int(radius_m / step + 1e-9) if step > 0 else 0, 1)
        axes.append(slice(max(0, i - reach), min(n, i + reach + 1)))
    scores = lattice.scores(ts, axes[0], axes[1])
    yaw = lattice.yaw_rad[t] + offsets * syaw
    centre = (reach_t, y - axes[0].start, x - axes[1].start)
    return scores, centre, lattice.x_m[axes[1]], lattice.y_m[axes[0]], yaw


def search_coarse_to_fine(
    local: Band,
    global_: Band,
    params: SearchParams,
    window_m: tuple[float, float, float, float] | None = None,
    *,
    coarse_factor: int | None = None,
    mass_tolerance: float = 1e-6,
    grow: int = 1,
) -> TiledResult:
    """The lattice of ``exhaustive.search`` — every (x, y) of the window (default: the whole
    map) at the grids' resolution, every rotation at ``params.angular_resolution_rad`` — searched
    coarse to fine (see the module): its best pose refined, covariance and peak ratio as
    ``search`` computes them, and the probabilities of the poses the coarse level leaves.

    ``coarse_factor`` F (default: the smallest keeping the coarse lattice within
    ``COARSE_POSES``); ``mass_tolerance``: the coarse mass left out, and the fine mass allowed
    on a region's border. EstimationError as ``search``, and beyond ``MAX_LATTICE_POSES``.
    """
    started = time.perf_counter()
    if not 0.0 < mass_tolerance < 1.0:
        raise EstimationError(f"mass_tolerance must lie in (0, 1), got {mass_tolerance!r}")
    if grow < 0:
        raise EstimationError(f"grow must be >= 0, got {grow}")
    check_pair(local, global_)
    metric = params.metric
    cells = local_cells(local, metric)  # EstimationError on an empty or NaN scan grid
    x_m, y_m, _ = pose_lattice(local, global_, window_m)
    yaw_rad = yaw_lattice(params.angular_resolution_rad)
    poses = len(x_m) * len(y_m) * len(yaw_rad)
    if poses > MAX_LATTICE_POSES:
        raise EstimationError(
            f"the search would cover {poses:,} poses ({len(x_m)} × {len(y_m)} positions × "
            f"{len(yaw_rad)} headings); at most {MAX_LATTICE_POSES:,} are searched coarse to "
            "fine: search a window around a prior, or a coarser grid or angular resolution"
        )
    if coarse_factor is not None and coarse_factor < 1:
        raise EstimationError(f"coarse_factor must be >= 1, got {coarse_factor}")
    factor = coarse_factor or max(1, math.ceil(math.sqrt(poses / COARSE_POSES)))
    if not match_values(global_, metric).any():
        raise EstimationError("map grid has no known cell with occupied or free evidence")
    workers = params.thread_count()
    reach = math.ceil(float(np.sqrt((cells.u**2).sum(axis=1)).max()))
    lattice = _Lattice(
        local, global_, x_m, y_m, yaw_rad, metric, reach, workers, value_mean(global_, metric)
    )

    # The coarse level: every pose, F times coarser in x and y.
    local_c, global_c = coarsen(local, factor, metric), coarsen(global_, factor, metric)
    x0, x1, y0, y1 = (float(v) for v in global_.extent())
    window = window_m if window_m is not None else (x0, x1, y0, y1)
    coarse_x, coarse_y, _ = pose_lattice(local_c, global_c, window)
    coarse, _ = correlate_lattice(local_c, global_c, coarse_x, coarse_y, yaw_rad, metric, workers)
    assert coarse is not None
    beta_c = params.beta * factor * factor
    top = float(coarse.max())
    counts, mass = np.zeros(_BINS, dtype=np.int64), np.zeros(_BINS)
    _histogram(coarse, top, beta_c, counts, mass)
    budget = MAX_FINE_POSES // (factor * factor * 3 * (2 * grow + 1) ** 2)
    bins, coarse_tail = _cut(counts, mass, mass_tolerance, budget)
    selected = coarse >= np.float32(top - bins * _BIN / beta_c)
    del coarse

    # The fine level, grown while its border holds probability.
    for growth in range(MAX_GROWTH + 1):
        patches = _fine_boxes(lattice, coarse_x, coarse_y, _regions(selected, grow + growth))
        best = max(float(p.scores.max()) for p in patches)
        totals, borders = 0.0, 0.0
        for p in patches:
            w = np.exp(params.beta * (p.scores.astype(np.float64) - best))
            edge = _border(p.mask, len(p.t) == len(yaw_rad), p.y0, p.x0, len(y_m), len(x_m))
            totals += float(w.sum())
            borders += float(w[edge].sum())
        border_share = borders / totals
        if border_share <= mass_tolerance or growth == MAX_GROWTH:
            break
    unevaluated = min(1.0, coarse_tail + border_share)

    # The best pose: the highest score, the lowest (t, y, x) among equal ones.
    candidates = []
    for p in patches:
        flat = int(np.argmax(p.scores))
        i, j, k = np.unravel_index(flat, p.scores.shape)
        index = (int(p.t[i]), p.y0 + int(j), p.x0 + int(k))
        candidates.append((-float(p.scores[i, j, k]), index))
    negative, best_index = min(candidates)
    best_score = -negative
    log_z = math.log(totals) + params.beta * (best - best_score)
    final = []
    for p in patches:
        prob = np.exp(params.beta * (p.scores.astype(np.float64) - best_score) - log_z)
        final.append(Patch(t=p.t, y0=p.y0, x0=p.x0, scores=p.scores,
                           prob=prob.astype(np.float32), mask=p.mask))  # fmt: skip

    # Refinement, covariance and dominance, as ``exhaustive.result_from_scores``.
    radii = (params.peak_radius_m, params.peak_radius_rad)
    box, centre, bx, by, byaw = _neighbourhood_scores(lattice, best_index, *radii)
    steps = np.array(lattice_steps(x_m, y_m, yaw_rad))
    t, y, x = best_index
    at = np.array([x_m[x], y_m[y], yaw_rad[t]])
    pose = at + refine_peak(box, centre, yaw_wraps=False) * steps
    pose = refine_pose(
        local, global_, pose, metric, np.column_stack([at - 2 * steps, at + 2 * steps])
    )
    pose[2] = float((pose[2] + math.pi) % (2.0 * math.pi) - math.pi)
    covariance = peak_covariance(box, centre, bx, by, byaw, params.beta, *radii)
    elsewhere = _best_outside(final, best_index, x_m, y_m, yaw_rad, *radii)
    with np.errstate(over="ignore", divide="ignore"):
        ratio = float(np.exp(params.beta * (best_score - elsewhere)))
        # An unevaluated pose holds at most the unevaluated mass.
        cap = math.exp(-log_z) * (1.0 - unevaluated) / unevaluated if unevaluated > 0 else math.inf
    return TiledResult(
        x_m=x_m,
        y_m=y_m,
        yaw_rad=yaw_rad,
        patches=tuple(final),
        beta=params.beta,
        best_index=best_index,
        best_score=best_score,
        pose=pose,
        covariance=covariance,
        peak_ratio=min(ratio, cap),
        unevaluated_mass=unevaluated,
        coarse_factor=factor,
        seconds=time.perf_counter() - started,
    )


def _best_outside(
    patches: list[Patch],
    index: tuple[int, int, int],
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    radius_m: float,
    radius_rad: float,
) -> float:
    """The best evaluated score outside the peak's neighbourhood (−inf if none)."""
    t, y, x = index
    best = -math.inf
    for p in patches:
        _, n_y, n_x = p.scores.shape
        dyaw = (yaw_rad[p.t] - yaw_rad[t] + math.pi) % (2.0 * math.pi) - math.pi
        dx = x_m[p.x0 : p.x0 + n_x] - x_m[x]
        dy = y_m[p.y0 : p.y0 + n_y] - y_m[y]
        near_xy = np.hypot(dx[None, :], dy[:, None]) <= radius_m + 1e-12
        near = (np.abs(dyaw) <= radius_rad + 1e-12)[:, None, None] & near_xy[None]
        outside = np.where(near, -np.inf, p.scores)
        best = max(best, float(outside.max()))
    return best
